"""
Reactive camera control (paper Sec. 3.3): action location -> PD -> Braccio joint commands,
or, with ``actuator: base``, velocity commands for a mobile base (the tracking world).

Subscribes ``action_location`` (PointStamped: pixel x, y and the surprise peak in z; header
of the source frame), ``camera/camera_info`` and ``joint_states``; publishes
``joint_commands`` (JointState, radians, header.stamp copied from the action location so the
graph can measure frame-to-command latency) and, for each location it does not act on,
``action_location/ignored`` (the location as received; the log says why), so that every
location gets an answer a lockstep simulation can wait for. The maths is
``activeloc_ros.control``.

On simulated time (lockstep) a location waits for the arm's state at its stamp, which may
reach this node after it: the controller then knows the camera's pose at capture, as
``closed_loop``'s controller does. A simulated clock that runs back (a bag replayed in a
loop with its ``/clock``; `nodes.clock`) restarts the core from its last command, with a
warning.

With ``actuator: base`` (`control.base`) it subscribes ``odom`` (nav_msgs/Odometry) in place
of ``joint_states``, ``action_region`` (the box of what is at the location, for the
forward rule) and ``scan`` (sensor_msgs/LaserScan, in the base's frame: to go round
obstacles), and publishes ``cmd_vel`` (geometry_msgs/Twist) in place of
``joint_commands``. A setting only the other actuator reads (the arm's settle time, aim
limits, confirmation; the base's forward rule) is refused at run time, and named with a
warning when set at start, rather than silently ignored.
"""
import math
import threading

from geometry_msgs.msg import PointStamped, PolygonStamped, Twist
from nav_msgs.msg import Odometry
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, JointState, LaserScan

from activeloc_ros.control import Intrinsics, PDController, ReactiveController
from activeloc_ros.control.base import BaseController
from activeloc_ros.control.params import (
    base_config_from, check_change, config_from, PARAMS, unread, unread_reason)
from activeloc_ros.errors import ConfigError
from activeloc_ros.nodes.clock import Rewinds
from activeloc_ros.nodes.masters import PublisherWatch
from activeloc_ros.nodes.messages import (
    arm_joints_deg, joint_state, region_box, scan_from, stamp_ns, stamp_s)
from activeloc_ros.nodes.params import declare, node_help
from activeloc_ros.nodes.process import run


class ControllerNode(Node):

    def __init__(self, **kwargs):
        super().__init__('controller', **kwargs)
        values = declare(self, PARAMS, cli_args=kwargs.get('cli_args'),
                         use_global_arguments=kwargs.get('use_global_arguments', True),
                         check_all=check_change, on_change=self.on_parameters)
        self.base = values['actuator'] == 'base'
        defaults = {p.name: p.default for p in PARAMS}
        for name in unread(values['actuator']):
            if values[name] != defaults[name]:
                self.get_logger().warning(f'{name} {values[name]!r} has no effect: '
                                          + unread_reason(values['actuator']))
        # on a simulated clock (lockstep) t0 is 0, as in closed_loop
        if self.base:
            self.config = base_config_from(values)
            self.core = BaseController(self.config, t0=self._now())
        else:
            self.config = config_from(values)
            self.core = ReactiveController(self.config, t0=self._now())
        self.sim_time = self.get_parameter('use_sim_time').value
        self._state = self.core.state
        self._ignored_logged = 0
        self._info_key = None
        self._camera_frame: str | None = None    # CameraInfo's frame_id, the optical frame
        self._lock = threading.Lock()  # stop_on_purpose may come from another thread
        self.stopped = False
        self._early: PointStamped | None = None   # simulated time: ahead of the arm's state
        self._regions: dict[int, tuple] = {}       # base: stamp (ns) -> box of the location
        self.rewinds = Rewinds(self, self._lock, self._restart,
                               'the controller starts over from its last command')
        self._locked = self.rewinds.locked   # the lock, for a callback that touches the core

        # Best effort hears any publisher (a camera driver's sensor QoS); in simulated time
        # (lockstep, our own reliable publishers) every location and arm state counts.
        inputs = ReliabilityPolicy.RELIABLE if self.sim_time else ReliabilityPolicy.BEST_EFFORT
        sensor = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
        commands = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE)
        self.ignored_pub = self.create_publisher(PointStamped, 'action_location/ignored', 10)
        # one master: a second controller on the same actuator is said, not fought
        self.masters = PublisherWatch(self, 'cmd_vel' if self.base else 'joint_commands')
        self.create_subscription(PointStamped, 'action_location', self.on_location,
                                 QoSProfile(depth=1, reliability=inputs))
        self.create_subscription(CameraInfo, 'camera/camera_info', self.on_camera_info, sensor)
        if self.base:
            self.publisher = self.create_publisher(Twist, 'cmd_vel', commands)
            self.create_subscription(Odometry, 'odom', self.on_odom,
                                     QoSProfile(depth=10, reliability=inputs))
            self.create_subscription(PolygonStamped, 'action_region', self.on_region,
                                     QoSProfile(depth=10, reliability=inputs))
            self.create_subscription(LaserScan, 'scan', self.on_scan,
                                     QoSProfile(depth=1, reliability=inputs))
        else:
            self.publisher = self.create_publisher(JointState, 'joint_commands', commands)
            self.create_subscription(JointState, 'joint_states', self.on_joint_states,
                                     QoSProfile(depth=10, reliability=inputs))
        self.create_timer(0.05, self.on_watchdog)
        if values['latency_report_period'] > 0:
            self.create_timer(values['latency_report_period'], self.report_latency)
        self._malformed_states = 0
        self._log_config('waiting for camera_info')

    def _log_config(self, then: str) -> None:
        pd, c = self.config.pd, self.config
        variant = self.get_parameter('pd_variant').value
        limits = (f'base: forward {c.forward}, distance {c.distance:g} m, top speed '
                  f'{c.max_speed:g} m/s and {c.max_turn_deg_s:g} deg/s, {c.actions} actions, '
                  + ('going round obstacles on scan' if c.avoid else 'not avoiding obstacles')
                  if self.base else
                  f'aim limits pan {c.pan_limit_deg:g} tilt {c.tilt_limit_deg:g} deg')
        self.get_logger().info(
            f'PD kp={pd.kp} kd={pd.kd} ({pd.derivative}'
            + (f', pd_variant {variant!r} sets the gains' if variant else '')
            + f'), dead band {math.degrees(pd.dead_band):g} deg, watchdog '
            f'{c.watchdog_timeout} s, {limits}; {then}')

    def on_parameters(self, values: dict, changed: set) -> None:
        """A run-time change, validated by check_change: the next command uses it."""
        config = base_config_from(values) if self.base else config_from(values)
        with self._lock:
            if config.pd != self.config.pd:
                self.core.pd = PDController(config.pd)  # no derivative across the change
            self.core.config = config
            self.config = config
        self._log_config('set at run time: ' + ', '.join(
            f'{name} {values[name]!r}' for name in sorted(changed)))

    def _now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _restart(self, now: float) -> None:
        """After the clock ran back (`Rewinds`): the core starts over at ``now``."""
        self.core.restart(now)
        self._early = None
        self._regions.clear()

    # -- inputs ----------------------------------------------------------------------------

    def on_camera_info(self, msg: CameraInfo) -> None:
        if msg.header.frame_id != self._camera_frame:
            self._camera_frame = msg.header.frame_id
            self.get_logger().info(f'camera optical frame {self._camera_frame!r}: locations '
                                   'in any other frame are ignored')
        key = (tuple(msg.k), msg.width, msg.height, tuple(msg.d), msg.distortion_model,
               msg.binning_x, msg.binning_y, msg.roi.x_offset, msg.roi.y_offset,
               msg.roi.width, msg.roi.height)
        if key == self._info_key:
            return
        self._info_key = key
        try:
            intrinsics = Intrinsics.from_camera_info(
                msg.k, msg.width, msg.height, d=msg.d, distortion_model=msg.distortion_model,
                binning_x=msg.binning_x, binning_y=msg.binning_y,
                roi=(msg.roi.x_offset, msg.roi.y_offset, msg.roi.width, msg.roi.height))
        except ConfigError as exc:
            self.get_logger().error(f'ignoring camera_info: {exc}')
            return
        self.core.set_intrinsics(intrinsics)
        self.get_logger().info(
            f'camera intrinsics fx={intrinsics.fx:.1f} fy={intrinsics.fy:.1f} '
            f'image {intrinsics.image_size[0]:g}x{intrinsics.image_size[1]:g}')
        self._log_state()

    def on_joint_states(self, msg: JointState) -> None:
        with self._locked():
            self._on_joint_states(msg)

    def _on_joint_states(self, msg: JointState) -> None:
        joints = arm_joints_deg(msg)   # the core ignores poses that are not finite
        if joints is None:
            self._malformed_states += 1
            self.get_logger().warning(
                f'ignored joint states without the six joints by name ('
                f'{self._malformed_states} so far)', throttle_duration_sec=5.0)
            return
        t = stamp_s(msg.header.stamp) or self._now()
        self.core.observe(joints, t)
        self._answer_early()

    def on_odom(self, msg: Odometry) -> None:
        """The base's pose (x, y, heading) at the message's stamp."""
        q = msg.pose.pose.orientation
        heading = math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
        with self._locked():
            self.core.observe((msg.pose.pose.position.x, msg.pose.pose.position.y, heading),
                              stamp_s(msg.header.stamp) or self._now())
            self._answer_early()

    def on_scan(self, msg: LaserScan) -> None:
        """The base's range scan (`control.base.Scan`)."""
        try:
            scan = scan_from(msg, stamp_s(msg.header.stamp) or self._now())
            with self._locked():
                self.core.observe_scan(scan)
        except ConfigError as exc:
            self.get_logger().warning(f'ignored a scan: {exc}', throttle_duration_sec=5.0)

    def on_region(self, msg: PolygonStamped) -> None:
        """The box (two corners, px) of what is at the location of the same stamp."""
        box = region_box(msg)
        if box is not None:
            with self._locked():
                self._regions[stamp_ns(msg.header.stamp)] = box
                while len(self._regions) > 20:
                    del self._regions[min(self._regions)]
                self._answer_early()

    def _answer_early(self) -> None:
        if self._early is not None and self._pose_known(self._early) and not self.stopped:
            early, self._early = self._early, None
            self._answer(early)

    def on_location(self, msg: PointStamped) -> None:
        with self._locked():
            if self.stopped:
                return
            if self.sim_time and not self._pose_known(msg):
                if self._early is not None:   # its state never came: answer it as it is
                    self._answer(self._early)
                self._early = msg
            else:
                self._answer(msg)
        self._log_state()
        self._log_ignored()

    def _pose_known(self, msg: PointStamped) -> bool:
        """
        Simulated time: is what the answer to ``msg`` needs here? The actuator's state at
        its stamp, and for a base the location's region (published before it, but DDS keeps
        no order between topics).
        """
        if self.base:
            newest = self.core.newest_state_time
            if stamp_ns(msg.header.stamp) not in self._regions:
                return False
        else:
            newest = self.core.history.newest[0] if self.core.history.newest else None
        return newest is not None and newest >= stamp_s(msg.header.stamp)

    def _answer(self, msg: PointStamped) -> None:
        """A command, or the location on action_location/ignored."""
        now = self._now()
        t_capture = stamp_s(msg.header.stamp) or now
        if self.sim_time:
            # the frame's clock tick may reach this node after its location; in
            # simulated time a command is never made before its frame (closed_loop)
            now = max(now, t_capture)
        box = self._regions.pop(stamp_ns(msg.header.stamp), None)
        frame = msg.header.frame_id
        if self._camera_frame is not None and frame != self._camera_frame:
            # pixels of another image: acting on them would aim at nothing
            self.get_logger().warning(
                f"ignored action locations in frame {frame!r}, not the camera's "
                f'{self._camera_frame!r}', throttle_duration_sec=5.0)
            command = self.core.ignore('foreign frame', now)
        else:
            command = self.core.on_location(msg.point.x, msg.point.y, t_capture, now,
                                            peak=msg.point.z, box=box)
        if command is not None:        # its own, the watchdog's hold or a move's rest
            self._publish(command, msg.header.stamp)
        if command is None or command.reason != 'track':
            self.ignored_pub.publish(msg)

    def on_watchdog(self) -> None:
        with self._locked():
            command = None if self.stopped else self.core.tick(self._now())
            if command is not None:
                self._publish(command, self.get_clock().now().to_msg())
        self._log_state()

    # -- outputs ---------------------------------------------------------------------------

    def _publish(self, command, stamp) -> None:
        if self.base:
            twist = Twist()
            twist.linear.x, twist.angular.z = command.twist.forward, command.twist.turn
            self.publisher.publish(twist)
        else:
            self.publisher.publish(joint_state(command.joints_deg, stamp))

    def stop_on_purpose(self) -> None:
        """
        Stop the arm where it is, on purpose, make sure the command went out, and send
        no more (safe to call while another thread spins the node).
        """
        with self._locked():
            self.stopped = True
            command = self.core.hold(self._now())
            self._publish(command, self.get_clock().now().to_msg())
        self.publisher.wait_for_all_acked(Duration(seconds=0.5))
        self.get_logger().info('stopped: base told to stop' if self.base else
                               'stopped: arm told to hold '
                               + ', '.join(f'{q:.0f}' for q in command.joints_deg))
        self.report_latency()

    def report_latency(self) -> None:
        s = self.core.latency.summary()
        if s['n']:
            self.get_logger().info(
                f'frame-to-command latency over {s["n"]} commands: '
                f'p50 {s["p50"] * 1e3:.0f} ms, p95 {s["p95"] * 1e3:.0f} ms')

    def _log_state(self) -> None:
        state = self.core.state
        if state == self._state:
            return
        messages = {
            'idle': 'camera info received; waiting for action locations',
            'tracking': 'tracking the action',
            'holding': f'no action location for {self.config.watchdog_timeout} s: holding still',
        }
        self.get_logger().info(messages.get(state, state))
        self._state = state

    def _log_ignored(self) -> None:
        total = sum(self.core.ignored.values())
        if total != self._ignored_logged:
            self._ignored_logged = total
            detail = ', '.join(f'{k}: {v}' for k, v in sorted(self.core.ignored.items()))
            self.get_logger().warning(f'ignored action locations ({detail})',
                                      throttle_duration_sec=5.0)


def main(args=None) -> int:
    return run(ControllerNode, args, on_stop=lambda node: node.stop_on_purpose(),
               help_text=lambda: node_help('controller_node', __doc__, PARAMS))


if __name__ == '__main__':
    raise SystemExit(main())
