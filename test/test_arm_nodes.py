"""
The arm node in one process: the sim back end's kinematics and the serial back end
against the emulated sketch (noise, a vanishing port), and the on-purpose stop.
"""
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
    from activeloc_ros.nodes.arm_node import ArmNode
    made = []

    def make(*overrides):
        arm = ArmNode(context=context, cli_args=params_args(*overrides))
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
    target = (150.0, 90.0, 45.0, 100.0, 90.0, 73.0)   # the aiming joints: base, wrist_ver
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
    probe.commands.publish(command([250.0, -30.0], names=['base', 'wrist_ver']))  # partial
    assert spin_until(executor, lambda: arm.clamped == 1, 5.0)
    assert arm.sim.target == (180, 90, 45, 0, 90, 73)
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
    from activeloc_ros.nodes.arm_node import ArmNode
    with pytest.raises(ConfigError):
        ArmNode(context=context, cli_args=params_args(override))


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


# -- any message the topic can carry (issue 13, item 5) -------------------------------------

BAD_COMMANDS = [
    (['base'], [1.0e308], 'not a finite angle'),           # finite rad, inf degrees
    (['base'], [-1.0e308], 'not a finite angle'),
    (['base'], [math.nan], 'not a finite angle'),
    (['base'], [math.inf], 'not a finite angle'),
    ([], [1.0e308] * 6, 'not a finite angle'),
    (['base', 'elbow'], [1.0], '2 names for 1 positions'),
    (['base'], [], '1 names for 0 positions'),
    ([], [1.0] * 7, '7 positions without names'),
    ([], [], '0 positions without names'),
    (['neck'], [1.0], "unknown joints ['neck']"),
    (['base', 'base'], [0.5, 2.5], 'joints named twice'),
    (['Base'], [1.0], 'unknown joints'),
]


@pytest.mark.parametrize('names, positions, why', BAD_COMMANDS)
def test_parse_command_says_why_a_command_is_malformed(names, positions, why):
    from activeloc_ros.nodes.arm_node import parse_command
    target, reason = parse_command(JointState(name=names, position=positions), HOME_DEG)
    assert target is None and why in reason


def test_every_bad_command_is_ignored_and_the_arm_lives_on(arm_graph):
    executor, arm, probe = arm_graph('backend:=sim')
    for count, (names, positions, _) in enumerate(BAD_COMMANDS, start=1):
        probe.commands.publish(JointState(name=names, position=positions))
        # a callback that raised would come out of spin_once here and fail the test
        assert spin_until(executor, lambda: arm.rejected == count, 5.0), (names, positions)
    assert arm.sim.target == HOME_DEG
    probe.commands.publish(command((100.0,) + HOME_DEG[1:]))
    assert spin_until(executor, lambda: arm.sim.target[0] == 100, 5.0)  # still listening


def test_random_commands_never_leave_the_joint_limits(arm_graph):
    """
    Seeded fuzz over what a JointState can carry: the node never raises, and its target
    is always inside the limits.
    """
    import random
    executor, arm, probe = arm_graph('backend:=sim')
    rng = random.Random(13)
    values = [0.0, -0.0, 1e-320, 1.0, -1.0, 3.2, 1e308, -1e308, 1.8e308 * 10, math.nan,
              5e-324, 2.0 ** 60]
    for _ in range(2000):
        n = rng.randint(0, 8)
        names = rng.sample(list(JOINT_NAMES) * 2 + ['x', ''], k=min(n, 14)) if rng.random() < .8 \
            else []
        positions = [rng.choice(values) if rng.random() < .5 else rng.uniform(-10, 10)
                     for _ in range(rng.choice([n, len(names), 6]))]
        arm.on_command(JointState(name=names, position=positions))
        assert within_limits(arm.sim.target)
    assert arm.rejected > 100 and arm.clamped > 10 and arm.refused > 100
    assert arm.sim.target[5] == HOME_DEG[5]          # the gripper never moved


@pytest.mark.parametrize('backend', ['sim', 'node'])
def test_a_command_that_moves_a_joint_which_does_not_aim_is_refused(arm_graph, context,
                                                                    backend):
    """
    The foreign pose of the hostile test: every joint outside its limits, the gripper
    open. The arm (or the virtual camera's arm) refuses all of it and says why.
    """
    foreign = (250.0, 0.0, -30.0, 200.0, 190.0, 0.0)
    if backend == 'sim':
        executor, arm, probe = arm_graph('backend:=sim')
        target = lambda: arm.sim.target    # noqa: E731
    else:
        from activeloc_ros.nodes.sim_node import SimNode
        arm = SimNode(context=context, cli_args=params_args('scene:=bag:bags/vtest'))
        probe = Probe(context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(arm)
        executor.add_node(probe.node)
        assert spin_until(executor, lambda: probe.commands.get_subscription_count() > 0, 5.0)
        target = lambda: arm.world.arm.target    # noqa: E731
    try:
        for count in range(1, 6):
            probe.commands.publish(command(foreign))
            assert spin_until(executor, lambda: arm.refused == count, 5.0)
        assert target() == HOME_DEG
        probe.commands.publish(command((100.0, 90.0, 45.0, 50.0, 90.0, 73.0)))
        assert spin_until(executor, lambda: target() == (100, 90, 45, 50, 90, 73), 5.0)
        probe.commands.publish(command((250.0, 90.0, 45.0, 50.0, 90.0, 73.0)))
        assert spin_until(executor, lambda: arm.clamped == 1, 5.0)   # said, and clamped
        assert target()[0] == 180
    finally:
        if backend != 'sim':
            executor.shutdown()
            arm.destroy_node()
            probe.node.destroy_node()


# -- run-time parameters (item 8) -----------------------------------------------------------

def set_remote(executor, probe, node_name, **values):
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient
    client = AsyncParameterClient(probe.node, node_name)
    assert spin_until(executor, lambda: client.services_are_ready(), 5.0)
    future = client.set_parameters([Parameter(k, value=v) for k, v in values.items()])
    executor.spin_until_future_complete(future, timeout_sec=5.0)
    return future.result().results


def test_arm_parameters_set_at_run_time_apply_or_are_refused(arm_graph):
    executor, arm, probe = arm_graph('backend:=sim', 'sim_start_deg:=[70,90,45,45,90,73]',
                                     'home_speed_deg_s:=60.0')
    results = set_remote(executor, probe, 'arm', state_rate=5.0, stop_mode='home')
    assert all(r.successful for r in results)
    assert arm.state_timer.timer_period_ns == 200_000_000
    for name, value in (('step_delay_ms', 10), ('backend', 'serial'), ('port', '/dev/x'),
                        ('sim_start_deg', list(HOME_DEG))):
        [result] = set_remote(executor, probe, 'arm', **{name: value})
        assert not result.successful and 'read-only' in result.reason, name
    [result] = set_remote(executor, probe, 'arm', state_rate=0.5)
    assert not result.successful and 'out of range' in result.reason
    assert arm.stop_on_purpose(executor)
    assert arm.sim.joints == HOME_DEG  # the stop mode set at run time was used


# -- a serial link that is missing or lost ends the node with an error (item 9) -------------

def test_a_missing_serial_port_ends_the_node_with_an_error(arm_graph, tmp_path):
    missing = str(tmp_path / 'ttyNothing')
    executor, arm, probe = arm_graph('backend:=serial', f'port:={missing}',
                                     'reconnect_period:=0.1', 'give_up_timeout:=0.5')
    assert spin_until(executor, lambda: arm.finished, 5.0)
    assert 'never connected for 0.5 s' in arm.failure and missing in arm.failure
    assert 'No such file or directory' in arm.failure
    assert probe.joints is None  # no made-up state was ever published


def test_a_serial_link_lost_for_good_ends_the_node_with_an_error(arm_graph, tmp_path):
    with ArduinoEmulator(path=str(tmp_path / 'ttyBRACCIO')) as emulator:
        executor, arm, probe = arm_graph('backend:=serial', f'port:={emulator.path}',
                                         'reconnect_period:=0.1', 'give_up_timeout:=0.5')
        assert spin_until(executor, lambda: arm.link.state == 'connected', 10.0)
        emulator.vanish()
        assert spin_until(executor, lambda: arm.finished, 5.0)
    assert 'lost for 0.5 s' in arm.failure


def test_the_arm_process_exits_1_with_the_reason_when_the_port_is_missing(tmp_path):
    import subprocess
    import sys
    from conftest import REPO
    missing = str(tmp_path / 'ttyNothing')
    process = subprocess.run(
        [sys.executable, '-m', 'activeloc_ros.nodes.arm_node',
         *params_args('backend:=serial', f'port:={missing}', 'give_up_timeout:=0.3',
                      'reconnect_period:=0.1')],
        cwd=REPO, capture_output=True, text=True, timeout=60)
    assert process.returncode == 1, process.stdout + process.stderr
    assert f'error: serial link to the arm on {missing} never connected' in process.stderr


# -- /diagnostics (item 16) -----------------------------------------------------------------

def test_the_serial_link_reports_its_health_on_diagnostics(arm_graph, tmp_path):
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    with ArduinoEmulator(path=str(tmp_path / 'ttyBRACCIO')) as emulator:
        executor, arm, probe = arm_graph('backend:=serial', f'port:={emulator.path}',
                                         'silence_timeout:=0.3', 'give_up_timeout:=0.0')
        reports = []
        probe.node.create_subscription(   # the link's status (not the publishers' watch)
            DiagnosticArray, '/diagnostics', lambda m: reports.extend(
                s for s in m.status if s.name == 'arm: serial link'), 10)

        def latest(level):
            return spin_until(executor, lambda: reports and reports[-1].level == level, 10.0)

        assert latest(DiagnosticStatus.OK)
        probe.commands.publish(command(HOME_DEG))
        assert spin_until(executor, lambda: HOME_DEG in emulator.host_writes(), 5.0)
        assert spin_until(executor, lambda: {
            v.key: v.value for v in reports[-1].values}['commands sent'] == '1', 5.0)
        status = reports[-1]
        assert (status.name, status.message, status.hardware_id) == (
            'arm: serial link', 'connected', emulator.path)
        emulator.vanish()
        assert latest(DiagnosticStatus.ERROR)
        assert 'disconnected' in reports[-1].message and 'lost' in reports[-1].message
