"""The controller node in one process: topics, stamps, bad input, watchdog, closed loop."""
import math

from builtin_interfaces.msg import Time
from geometry_msgs.msg import PointStamped
import pytest
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import CameraInfo, JointState

from activeloc_ros.control import HOME_DEG, JOINT_NAMES, within_limits
from activeloc_ros.errors import ConfigError
from conftest import params_args, spin_until

FX, CX, CY = 600.0, 319.5, 239.5


def camera_info() -> CameraInfo:
    msg = CameraInfo(width=640, height=480, distortion_model='plumb_bob')
    msg.k = [FX, 0.0, CX, 0.0, FX, CY, 0.0, 0.0, 1.0]
    msg.d = [0.0] * 5
    return msg


def degrees(msg: JointState) -> tuple[float, ...]:
    return tuple(math.degrees(p) for p in msg.position)


class Probe:
    """Plays camera, perception and arm around the controller."""

    def __init__(self, context):
        self.node = Node('probe', context=context)
        best_effort = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
        self.info = self.node.create_publisher(CameraInfo, 'camera/camera_info', best_effort)
        self.location = self.node.create_publisher(PointStamped, 'action_location', 10)
        self.states = self.node.create_publisher(JointState, 'joint_states', 10)
        self.commands: list[JointState] = []
        self.node.create_subscription(JointState, 'joint_commands', self.commands.append,
                                      QoSProfile(depth=100))

    def send_location(self, u, v, stamp_s, peak=1.0, frame=''):
        msg = PointStamped()
        msg.header.frame_id = frame
        msg.header.stamp = Time(sec=int(stamp_s), nanosec=int(stamp_s % 1 * 1e9))
        msg.point.x, msg.point.y, msg.point.z = float(u), float(v), float(peak)
        self.location.publish(msg)

    def now(self) -> float:
        return self.node.get_clock().now().nanoseconds * 1e-9


@pytest.fixture
def graph(context):
    from activeloc_ros.nodes.controller_node import ControllerNode
    made = []

    def make(*overrides):
        controller = ControllerNode(context=context,
                                    cli_args=params_args(*overrides))
        probe = Probe(context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(controller)
        executor.add_node(probe.node)
        made.append((executor, controller, probe))
        assert spin_until(executor, lambda: probe.info.get_subscription_count() > 0
                          and probe.node.count_publishers('joint_commands') > 0, 5.0)
        probe.info.publish(camera_info())
        assert spin_until(executor, lambda: controller.core.intrinsics is not None, 5.0)
        return executor, controller, probe

    yield make
    for executor, controller, probe in made:
        executor.shutdown()
        controller.destroy_node()
        probe.node.destroy_node()


def test_a_location_becomes_a_command_with_its_stamp(graph):
    executor, controller, probe = graph()
    stamp = probe.now() - 0.05
    probe.send_location(CX - FX * math.tan(math.radians(10.0)), CY, stamp)  # 10 deg left
    assert spin_until(executor, lambda: probe.commands, 5.0)
    cmd = probe.commands[0]
    assert list(cmd.name) == list(JOINT_NAMES)
    assert cmd.header.stamp.sec + cmd.header.stamp.nanosec * 1e-9 == pytest.approx(stamp)
    joints = degrees(cmd)
    assert within_limits(joints, tol=1e-6)
    assert HOME_DEG[0] < joints[0] <= HOME_DEG[0] + 10.0 + 1e-6  # turning left, base up
    assert joints[1:] == pytest.approx(HOME_DEG[1:])


def test_on_simulated_time_a_location_waits_for_the_arms_state_at_its_stamp(graph):
    """
    DDS may deliver a frame's location before the arm's state at the frame's time; the
    controller then answers only once it knows where the camera was (as closed_loop).
    """
    executor, controller, probe = graph('use_sim_time:=true')
    home = JointState(name=list(JOINT_NAMES), position=[math.radians(q) for q in HOME_DEG])
    home.header.stamp = Time(sec=0, nanosec=200_000_000)
    probe.states.publish(home)
    assert spin_until(executor, lambda: len(controller.core.history) == 1, 5.0)
    probe.send_location(CX - FX * math.tan(math.radians(10.0)), CY, 0.3)
    assert not spin_until(executor, lambda: probe.commands, 0.5), 'answered without the pose'
    home.header.stamp = Time(sec=0, nanosec=300_000_000)
    probe.states.publish(home)
    assert spin_until(executor, lambda: probe.commands, 5.0)
    assert probe.commands[0].header.stamp.nanosec == 300_000_000


def test_nan_and_absurd_locations_are_ignored(graph):
    executor, controller, probe = graph()
    t = probe.now()
    for i, (u, v) in enumerate([(math.nan, 10.0), (1e12, 10.0), (-5000.0, 10.0)]):
        probe.send_location(u, v, t + i * 0.01)
        assert spin_until(executor, lambda: sum(controller.core.ignored.values()) > i, 5.0)
    probe.send_location(100.0, 100.0, t + 1.0)
    assert spin_until(executor, lambda: probe.commands, 5.0)
    assert len(probe.commands) == 1 and probe.commands[0].header.stamp.sec == int(t + 1.0)


def test_a_location_in_a_frame_not_the_cameras_is_ignored(graph):
    executor, controller, probe = graph()
    info = camera_info()
    info.header.frame_id = 'camera_color_optical_frame'
    probe.info.publish(info)
    assert spin_until(executor, lambda: controller._camera_frame == info.header.frame_id, 5.0)
    t = probe.now()
    probe.send_location(CX - FX * math.tan(math.radians(10.0)), CY, t, frame='some_other_frame')
    assert spin_until(executor, lambda: controller.core.ignored.get('foreign frame') == 1, 5.0)
    assert not probe.commands
    probe.send_location(CX - FX * math.tan(math.radians(10.0)), CY, t + 0.1,
                        frame=info.header.frame_id)
    assert spin_until(executor, lambda: probe.commands, 5.0)


def test_watchdog_holds_once_when_locations_stop(graph):
    executor, controller, probe = graph('watchdog_timeout:=0.3')
    probe.send_location(100.0, 100.0, probe.now())
    assert spin_until(executor, lambda: len(probe.commands) == 1, 5.0)
    assert spin_until(executor, lambda: controller.core.state == 'holding', 5.0)
    spin_until(executor, lambda: len(probe.commands) > 2, 1.0)  # give drift a chance
    assert len(probe.commands) == 2
    assert degrees(probe.commands[1]) == pytest.approx(degrees(probe.commands[0]))


@pytest.mark.parametrize('override, message', [
    ('kp:=-1.0', 'kp'), ('kp:=1', 'kp'), ('step_delay_ms:=5', 'step_delay_ms'),
    ('pd_variant:=pid', 'pd_variant'), ('home_deg:=[90,5,45,45,90,73]', 'home_deg')])
def test_bad_parameters_are_refused_by_name(context, override, message):
    from activeloc_ros.nodes.controller_node import ControllerNode
    with pytest.raises(ConfigError, match=message):
        ControllerNode(context=context, cli_args=params_args(override))


def test_pd_variant_overrides_the_gains(context):
    from activeloc_ros.nodes.controller_node import ControllerNode
    node = ControllerNode(context=context, cli_args=params_args('pd_variant:=low_p'))
    try:
        assert (node.config.pd.kp, node.config.pd.kd) == (0.5, 0.1)
    finally:
        node.destroy_node()


def test_closed_loop_with_the_sim_arm_centres_a_still_action(context):
    """
    Controller + simulated arm + a virtual camera looking at an action 15 deg left and
    8 deg up: the arm turns until the action is centred (within the dead band).

    Each view is stamped with the time of the joint state it was rendered from; stamped
    later, the controller pairs it with a newer pose and the loop can settle into a
    two-step oscillation.
    """
    from activeloc_ros.nodes.arm_node import ArmNode
    from activeloc_ros.nodes.controller_node import ControllerNode
    controller = ControllerNode(context=context, cli_args=params_args())
    arm = ArmNode(context=context, cli_args=params_args('backend:=sim'))
    probe = Probe(context)
    pose = {}

    def on_state(msg):
        pose['joints'] = degrees(msg)
        pose['stamp'] = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9

    probe.node.create_subscription(JointState, 'joint_states', on_state, 10)
    action_pan, action_tilt = math.radians(15.0), math.radians(8.0)

    def frame():  # what the camera sees now (tilt small: pan/tilt errors add up)
        if 'joints' not in pose:
            return
        pan, tilt = controller.config.mapping.pan_tilt(pose['joints'])
        u = CX - FX * math.tan(action_pan - pan)
        v = CY - FX * math.tan(action_tilt - tilt) / math.cos(action_pan - pan)
        # the view was rendered from the pose of that joint state: that is its capture time
        probe.send_location(u, v, pose['stamp'])

    probe.node.create_timer(0.1, frame)
    probe.node.create_timer(1.0, lambda: probe.info.publish(camera_info()))
    executor = SingleThreadedExecutor(context=context)
    for node in (controller, arm, probe.node):
        executor.add_node(node)
    try:
        def centred():
            if len(probe.commands) < 5 or 'joints' not in pose:
                return False
            pan, tilt = controller.config.mapping.pan_tilt(pose['joints'])
            return (abs(math.degrees(pan - action_pan)) < 2.5
                    and abs(math.degrees(tilt - action_tilt)) < 2.5)

        assert spin_until(executor, centred, 15.0), (pose, [degrees(c) for c in probe.commands])
        assert all(within_limits(degrees(c), tol=1e-6) for c in probe.commands)
    finally:
        executor.shutdown()
        for node in (controller, arm, probe.node):
            node.destroy_node()


def test_a_clock_that_runs_back_restarts_the_controller_and_the_arm(context):
    """
    A bag replayed in a loop with its /clock sends simulated time back to its start. The
    controller and the simulated arm go on from there; before, the arm stood still, and
    every location was out of order, until the clock was back where it had been.
    """
    from activeloc_ros.nodes.arm_node import ArmNode
    from activeloc_ros.nodes.controller_node import ControllerNode
    sim_time = 'use_sim_time:=true'
    controller = ControllerNode(context=context, cli_args=params_args(sim_time))
    arm = ArmNode(context=context, cli_args=params_args('backend:=sim', sim_time))
    probe = Probe(context)
    clock = probe.node.create_publisher(ClockMsg, '/clock', 10)
    now = {'t': 100.0}
    states = []

    def tick():        # the bag's clock: 50 ms a tick
        now['t'] += 0.05
        clock.publish(ClockMsg(clock=Time(sec=int(now['t']),
                                          nanosec=int(now['t'] % 1 * 1e9))))

    def look():        # the action is always 10 deg left of the camera's last pose
        if states:
            stamp = states[-1].header.stamp
            probe.send_location(CX - FX * math.tan(math.radians(10.0)), CY,
                                stamp.sec + stamp.nanosec * 1e-9)

    probe.node.create_subscription(JointState, 'joint_states', states.append, 10)
    probe.node.create_timer(0.02, tick)
    probe.node.create_timer(0.1, look)
    probe.node.create_timer(0.5, lambda: probe.info.publish(camera_info()))
    executor = SingleThreadedExecutor(context=context)
    for node in (controller, arm, probe.node):
        executor.add_node(node)

    def pan_after(t: float) -> float | None:     # the newest pan stamped in [t, t + 50 s)
        after = [degrees(m)[0] for m in states
                 if 0 <= m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 - t < 50]
        return after[-1] if after else None

    try:
        assert spin_until(executor, lambda: (pan_after(100.0) or 0.0) > HOME_DEG[0] + 5, 20.0)
        before = pan_after(100.0)
        now['t'] = 1.0
        assert spin_until(executor, lambda: (pan_after(1.0) or 0.0) > before + 5
                          and (pan_after(1.0) or 0.0) < 180, 20.0), (before, pan_after(1.0))
        assert controller.core.ignored.get('out of order', 0) <= 2   # in flight at the jump
        assert all(within_limits(degrees(c), tol=1e-6) for c in probe.commands)
    finally:
        executor.shutdown()
        for node in (controller, arm, probe.node):
            node.destroy_node()


def test_stop_on_purpose_holds_then_ignores_locations(graph):
    executor, controller, probe = graph()
    probe.send_location(100.0, 100.0, probe.now())
    assert spin_until(executor, lambda: len(probe.commands) == 1, 5.0)
    controller.stop_on_purpose()
    assert spin_until(executor, lambda: len(probe.commands) == 2, 5.0)
    assert degrees(probe.commands[1]) == pytest.approx(degrees(probe.commands[0]))
    probe.send_location(300.0, 100.0, probe.now())
    spin_until(executor, lambda: len(probe.commands) > 2, 0.5)
    assert len(probe.commands) == 2 and controller.core.ignored == {}


# -- parameters set at run time (issue 13, item 8): applied at once, or refused -------------

def set_remote(executor, probe, **values):
    """ros2 param set, over the node's real parameter service: the results."""
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient
    client = AsyncParameterClient(probe.node, 'controller')
    assert spin_until(executor, lambda: client.services_are_ready(), 5.0)
    future = client.set_parameters([Parameter(k, value=v) for k, v in values.items()])
    executor.spin_until_future_complete(future, timeout_sec=5.0)
    return future.result().results


def aim(executor, probe, u, stamp):
    """One location `u` px; the base angle of the command it makes."""
    count = len(probe.commands)
    probe.send_location(u, CY, stamp)
    assert spin_until(executor, lambda: len(probe.commands) > count, 5.0)
    return degrees(probe.commands[-1])[0]


def test_gains_and_limits_set_at_run_time_apply_to_the_next_command(graph):
    executor, controller, probe = graph('settle_time:=0.0')
    left = CX - 100.0  # the action 100 px left of the centre: turn left, base up
    first = aim(executor, probe, left, probe.now())
    assert first > HOME_DEG[0]

    [result] = set_remote(executor, probe, pan_limit_deg=0.0)
    assert result.successful, result.reason
    bases = [first]
    while bases[-1] > HOME_DEG[0] + 1e-6 and len(bases) < 2000:  # the guard ramps at 50 deg/s
        bases.append(aim(executor, probe, left, probe.now()))
    assert bases[-1] == pytest.approx(HOME_DEG[0])  # back home, never further left
    assert all(b <= a + 1e-9 for a, b in zip(bases, bases[1:]))

    assert all(r.successful for r in set_remote(executor, probe, pan_limit_deg=180.0, kp=0.0))
    assert aim(executor, probe, left, probe.now()) == pytest.approx(HOME_DEG[0])  # kp 0: still
    assert set_remote(executor, probe, kp=1.0)[0].successful
    assert aim(executor, probe, left, probe.now()) > HOME_DEG[0]


@pytest.mark.parametrize('values, reason', [
    ({'step_delay_ms': 10}, 'read-only'),        # must match the arm's servos
    ({'home_deg': [90, 90, 45, 45, 90, 73]}, 'read-only'),
    ({'pan_limit_deg': 500.0}, 'out of range'),
    ({'kp': math.nan}, 'out of range'),
    ({'kp': 'fast'}, 'Wrong parameter type'),
    ({'watchdog_timeout': 0.0}, "'watchdog_timeout' must be a finite number > 0"),
    ({'min_peak': math.nan}, 'min_peak must not be NaN'),
])
def test_a_run_time_change_that_would_not_apply_is_refused_with_the_reason(graph, values,
                                                                           reason):
    executor, controller, probe = graph()
    before = {k: controller.get_parameter(k).value for k in values}
    [result] = set_remote(executor, probe, **values)
    assert not result.successful and reason in result.reason
    assert {k: controller.get_parameter(k).value for k in values} == before


def test_a_base_setting_is_refused_by_the_arms_controller(graph):
    executor, controller, probe = graph()
    [result] = set_remote(executor, probe, distance=3.0)
    assert not result.successful and 'distance would have no effect' in result.reason
    assert controller.get_parameter('distance').value == 2.5


def test_an_arm_setting_is_refused_by_a_bases_controller_and_named_at_start(context, capfd):
    from types import SimpleNamespace
    from activeloc_ros.nodes.controller_node import ControllerNode
    controller = ControllerNode(context=context,
                                cli_args=params_args('actuator:=base', 'settle_time:=0.5'))
    probe = SimpleNamespace(node=Node('probe', context=context))
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(controller)
    executor.add_node(probe.node)
    try:
        warned = capfd.readouterr().err
        assert 'settle_time 0.5 has no effect: this controller drives a mobile base' in warned
        assert 'confirm_deg' not in warned           # left at its default: nothing to say
        [result] = set_remote(executor, probe, confirm_deg=8.0)
        assert not result.successful and 'confirm_deg would have no effect' in result.reason
        assert controller.get_parameter('confirm_deg').value == 0.0
        [result] = set_remote(executor, probe, distance=3.0)   # its own: applied
        assert result.successful and controller.core.config.distance == 3.0
    finally:
        executor.shutdown()
        controller.destroy_node()
        probe.node.destroy_node()


def test_gains_under_a_pd_variant_are_refused_not_ignored(graph):
    executor, controller, probe = graph('pd_variant:=paper')
    [result] = set_remote(executor, probe, kp=0.2)
    assert not result.successful and "pd_variant 'paper' sets the gains" in result.reason
    results = set_remote(executor, probe, pd_variant='', kp=0.2)
    assert all(r.successful for r in results)
    assert (controller.config.pd.kp, controller.core.pd.config.kp) == (0.2, 0.2)
