"""The arm node in one process: the sim back end's kinematics and the serial back end
against the emulated sketch (noise, a vanishing port), and the on-purpose stop."""
import math
import threading
import time

import pytest
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

from activeloc_ros.control import HOME_DEG, JOINT_NAMES, SAFETY_DEG, within_limits
from activeloc_ros.control.emulator import ArduinoEmulator
from activeloc_ros.errors import ConfigError
from conftest import params_args, spin_until


def command(joints_deg, names=JOINT_NAMES) -> JointState:
    return JointState(name=list(names), position=[math.radians(q) for q in joints_deg])


class Probe:
    def __init__(self, context):
        self.node = Node('probe', context=context)
        reliable = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE)
        self.commands = self.node.create_publisher(JointState, 'joint_commands', reliable)
        self.states: list[tuple[float, tuple[float, ...]]] = []
        self.node.create_subscription(JointState, 'joint_states', self.on_state,
                                      QoSProfile(depth=100))

    def on_state(self, msg):
        stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        assert list(msg.name) == list(JOINT_NAMES)
        self.states.append((stamp, tuple(math.degrees(p) for p in msg.position)))

    @property
    def joints(self):
        return self.states[-1][1] if self.states else None


@pytest.fixture
def arm_graph(context):
    from activeloc_ros.arm_node import ArmNode
    made = []

    def make(*overrides):
        arm = ArmNode(context=context, cli_args=params_args('arm', *overrides))
        probe = Probe(context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(arm)
        executor.add_node(probe.node)
        made.append((executor, arm, probe))
        assert spin_until(executor, lambda: probe.commands.get_subscription_count() > 0, 5.0)
        return executor, arm, probe

    yield make
    for executor, arm, probe in made:
        executor.shutdown()
        arm.destroy_node()
        probe.node.destroy_node()


def test_sim_arm_follows_in_whole_degrees_at_the_servos_speed(arm_graph):
    executor, arm, probe = arm_graph('backend:=sim', 'step_delay_ms:=20')
    assert spin_until(executor, lambda: probe.joints is not None, 5.0)
    assert probe.joints == pytest.approx(HOME_DEG)
    target = (150.0, 100.0, 45.0, 45.0, 90.0, 73.0)
    probe.commands.publish(command(target))
    assert spin_until(executor, lambda: probe.joints == pytest.approx(target), 5.0)
    for (t0, q0), (t1, q1) in zip(probe.states, probe.states[1:]):
        assert within_limits(q1, tol=1e-6)
        assert all(abs(q - round(q)) < 1e-6 for q in q1)  # whole degrees
        steps = math.floor((t1 - t0) / 0.020) + 2  # step ticks in the interval, +1 phase
        assert all(abs(a - b) <= steps + 1e-6 for a, b in zip(q0, q1))
    assert len(probe.states) > 30  # 60 degrees at 50 deg/s: seen on its way


def test_sim_arm_clamps_and_rejects_bad_commands(arm_graph):
    executor, arm, probe = arm_graph('backend:=sim')
    probe.commands.publish(command([math.nan] * 6))
    assert spin_until(executor, lambda: arm.rejected == 1, 5.0)
    probe.commands.publish(command([91.0, 90.0], names=['base', 'neck']))
    assert spin_until(executor, lambda: arm.rejected == 2, 5.0)
    probe.commands.publish(command([250.0, 0.0], names=['base', 'shoulder']))  # partial
    assert spin_until(executor, lambda: arm.clamped == 1, 5.0)
    assert arm.sim.target == (180, 15) + tuple(HOME_DEG[2:])
    probe.commands.publish(JointState(position=[math.radians(q) for q in HOME_DEG]))
    assert spin_until(executor, lambda: arm.sim.target == HOME_DEG, 5.0)  # unnamed: in order


def test_serial_arm_publishes_the_echo_and_survives_noise_and_unplugging(arm_graph, tmp_path):
    with ArduinoEmulator(path=str(tmp_path / 'ttyBRACCIO')) as emulator:
        executor, arm, probe = arm_graph('backend:=serial', f'port:={emulator.path}',
                                         'silence_timeout:=0.5', 'reconnect_period:=0.2')
        assert spin_until(executor, lambda: probe.joints == pytest.approx(SAFETY_DEG), 10.0)
        probe.commands.publish(command(HOME_DEG))
        assert spin_until(executor, lambda: HOME_DEG in emulator.host_writes(), 5.0)

        emulator.inject(b'garbage<s,1,2><s,500,1,1,1,1,1>\xff')
        assert spin_until(executor, lambda: arm.link.stats.bad_frames >= 2, 5.0)
        count = len(probe.states)
        assert spin_until(executor, lambda: len(probe.states) > count + 5, 5.0)
        assert all(within_limits(q) for _, q in probe.states)

        emulator.vanish()
        assert spin_until(executor, lambda: arm.link.state == 'closed', 5.0)
        assert spin_until(executor, lambda: not arm.link.fresh(time.monotonic()), 5.0)
        count = len(probe.states)
        spin_until(executor, lambda: len(probe.states) > count + 2, 0.5)
        assert len(probe.states) <= count + 1  # no stale state published while unplugged
        emulator.reappear()
        assert spin_until(executor, lambda: arm.link.state == 'connected', 5.0)
        assert spin_until(executor, lambda: len(probe.states) > count + 5, 5.0)
        assert arm.link.stats.losses == 1


@pytest.mark.parametrize('mode', ['hold', 'home'])
def test_sim_arm_stops_on_purpose(arm_graph, mode):
    executor, arm, probe = arm_graph('backend:=sim', f'stop_mode:={mode}',
                                     'sim_start_deg:=[60,90,45,45,90,73]',
                                     'home_speed_deg_s:=40.0')
    probe.commands.publish(command((170.0,) + HOME_DEG[1:]))
    assert spin_until(executor, lambda: probe.joints and probe.joints[0] > 70, 5.0)
    assert arm.stop_on_purpose(executor)
    base = probe.joints[0]
    if mode == 'hold':
        assert 70 < base < 170 and arm.sim.target == arm.sim.joints
    else:
        assert arm.sim.joints == HOME_DEG
    probe.commands.publish(command((10.0,) + HOME_DEG[1:]))
    spin_until(executor, lambda: arm.sim.target[0] == 10, 0.3)
    assert arm.sim.target[0] != 10  # commands are ignored once stopped


@pytest.mark.parametrize('override', ['backend:=arm', 'home_deg:=[90,90,45]',
                                      'step_delay_ms:=40', 'baud:=1234'])
def test_bad_parameters_are_refused(context, override):
    from activeloc_ros.arm_node import ArmNode
    with pytest.raises(ConfigError):
        ArmNode(context=context, cli_args=params_args('arm', override))


def test_stop_on_purpose_while_another_thread_spins(arm_graph):
    """As in bringup --in-process: the executor keeps running in its thread, the call waits."""
    executor, arm, probe = arm_graph('backend:=sim', 'stop_mode:=home',
                                     'sim_start_deg:=[75,90,45,45,90,73]',
                                     'home_speed_deg_s:=60.0')
    assert spin_until(executor, lambda: probe.joints is not None, 5.0)
    halt = threading.Event()

    def spin():
        while not halt.is_set():
            executor.spin_once(timeout_sec=0.02)

    thread = threading.Thread(target=spin)
    thread.start()
    try:
        assert arm.stop_on_purpose()
        assert arm.sim.joints == HOME_DEG
    finally:
        halt.set()
        thread.join()
