"""
Tracking world node: the simulated active-tracking world (`tracking.world.TrackingWorld`,
paper Sec. 4.1) in the graph.

    ros2 run activeloc_ros tracking_node --ros-args -p scene:=room -p seed:=3

A person walks ahead of a mobile base that carries a camera, in one of the seeded pybullet
scenes (room, urban, snow, parking). The node owns the world: it moves the base at
``cmd_vel`` (geometry_msgs/Twist: linear.x m/s forward, angular.z rad/s, left positive),
and publishes ``camera/image_raw``, ``camera/camera_info``, ``odom`` (nav_msgs/Odometry of
the base in the world frame), ``scan`` (sensor_msgs/LaserScan of the base's planar range
sensor, frame ``base_link``, 360 deg counterclockwise from behind) and ``target/position``
(geometry_msgs/PointStamped: where the target really is, for recording), all stamped with
the step's time. The episode ends as the benchmark's does (`tracking.reward`: 500 steps, or
the target lost for 10 in a row); the log then gives its AD-VAT scores.

In real time the world steps at its control rate (10 Hz, times ``rate``). With ``lockstep``
(and ``use_sim_time`` on every node) it owns ``/clock`` and steps the graph one control step
at a time as ``closed_loop`` does (`activeloc_ros.nodes.lockstep`; the base's state is
``odom``, and a ``cmd_vel`` that comes once the step's frame is out answers it).
"""
import math
import threading
import time

from geometry_msgs.msg import PointStamped, Twist
from nav_msgs.msg import Odometry
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import CameraInfo, Image, LaserScan
from std_msgs.msg import Header

from activeloc_ros.control.base import Twist as BaseTwist
from activeloc_ros.errors import ConfigError
from activeloc_ros.nodes.frames import (
    images_heard, lockstep_graph_up, lockstep_wiring, may_start, publish_frame)
from activeloc_ros.nodes.lockstep import ANSWER, moot_in_lockstep
from activeloc_ros.nodes.masters import PublisherWatch
from activeloc_ros.nodes.messages import scan_message, time_from_ns
from activeloc_ros.nodes.params import declare, node_help
from activeloc_ros.nodes.process import frame_due, frames_stopped, run
from activeloc_ros.tracking.params import PARAMS
from activeloc_ros.tracking.world import TrackingConfig, TrackingWorld


class TrackingNode(Node):

    def __init__(self, **kwargs):
        super().__init__('tracking', **kwargs)
        self.params = declare(self, PARAMS, cli_args=kwargs.get('cli_args'),
                              use_global_arguments=kwargs.get('use_global_arguments', True),
                              check_all=moot_in_lockstep, on_change=self.on_parameters)
        p = self.params
        self.sim_time = self.get_parameter('use_sim_time').value
        if p['lockstep'] != self.sim_time:
            raise ConfigError('lockstep runs the graph on simulated time this node owns: set '
                              'lockstep:=true and use_sim_time:=true together')
        config = TrackingConfig(target=p['target'], max_steps=p['max_steps'],
                                lost_steps=p['lost_steps'])
        self.world = TrackingWorld(p['scene'], p['seed'], config)
        self.steps = self.world.times()
        reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.image_pub = self.create_publisher(Image, 'camera/image_raw', reliable)
        self.info_pub = self.create_publisher(CameraInfo, 'camera/camera_info', 10)
        self.odom_pub = self.create_publisher(Odometry, 'odom', reliable)
        self.scan_pub = self.create_publisher(LaserScan, 'scan', 10)
        self.target_pub = self.create_publisher(PointStamped, 'target/position', reliable)
        self.command_sub = self.create_subscription(Twist, 'cmd_vel', self.on_command, reliable)
        self.masters = PublisherWatch(self, 'cmd_vel')    # the base obeys one controller
        self.lockstep = None
        if p['lockstep']:
            self.lockstep = lockstep_wiring(self, Odometry, 'odom')
        self.published = 0
        self.rejected = 0
        self.finished = False
        self.due = 0.0                    # real time: when the next step is due (monotonic)
        self.started_at = time.monotonic()
        self._lock = threading.Lock()
        self._closed = False
        self.waiting = p['wait_for_subscriber'] > 0
        self.timer = self.create_timer(0.005, self.tick,
                                       clock=Clock(clock_type=ClockType.STEADY_TIME))
        mode = 'lockstep' if p['lockstep'] else 'real time'
        self.get_logger().info(f'tracking world {p["scene"]} seed {p["seed"]}, target '
                               f'{p["target"]} ({mode}, {1 / config.step:g} steps/s)')

    def on_parameters(self, values: dict, changed: set) -> None:
        changed = changed & values.keys()
        with self._lock:
            wall = self._wall()
            self.params.update({name: values[name] for name in changed})
            if 'rate' in changed and not self.waiting:   # the world's clock goes on from here
                self.started_at = time.monotonic() - wall / self.params['rate']
        self.get_logger().info('set at run time: ' + ', '.join(
            f'{name} {values[name]!r}' for name in sorted(changed)))

    # -- inputs ----------------------------------------------------------------------------

    def on_command(self, msg: Twist) -> None:
        twist = BaseTwist(msg.linear.x, msg.angular.z)
        with self._lock:
            if not (math.isfinite(twist.forward) and math.isfinite(twist.turn)):
                self.rejected += 1
                self.get_logger().warning(f'ignored a cmd_vel that is not finite '
                                          f'({self.rejected} so far)', throttle_duration_sec=5.0)
                return
            if self._closed:
                return
            self.world.act(twist, self.world.t if self.lockstep else self._command_time())
            if self.lockstep is not None and self.lockstep.phase == ANSWER:
                # a Twist has no stamp: a command once the frame is out answers it (DDS may
                # bring it before this node hears the location it answers)
                self.lockstep.on_command(self.lockstep.t_ns)

    # -- stepping --------------------------------------------------------------------------

    def _wall(self) -> float:
        """Real time: the world's seconds since its first step, at the set rate."""
        return (time.monotonic() - self.started_at) * self.params['rate']

    def _command_time(self) -> float:
        """
        Real time: when a command arriving now reaches the base, on the world's clock.
        Never later than the middle of the world's next step: a world that fell behind the
        wall clock (slow rendering) would otherwise keep every command for later, later and
        later as it fell further behind.
        """
        return min(self._wall(), self.world.t + 0.5 * self.world.config.step)

    def tick(self) -> None:
        with self._lock:
            if self._closed or self.finished or (self.waiting and not self._ready()):
                return
            if self.lockstep is not None:
                self._lockstep_tick()
            elif frame_due(self.timer, self.due):
                self.due = time.monotonic() + self.world.config.step / self.params['rate']
                if self._step():
                    self.world.advance(self.world.t)
                    self._publish_base(self.get_clock().now().to_msg())
                    self.publish(self.get_clock().now().to_msg())
                    self.world.score_step()

    def _step(self) -> bool:
        """The next control step (the world's time moves on); False at the episode's end."""
        if next(self.steps, None) is None:
            self._finish()
            return False
        return True

    def _lockstep_tick(self) -> None:
        step, now = self.lockstep, time.monotonic()
        action = step.poll(now)
        if action == 'render':
            self.publish(time_from_ns(step.t_ns))
            step.rendered(now)
            return
        if action != 'next':
            return
        if self.published:
            self.world.score_step()
        if not self._step():
            return
        t_ns = round(self.world.t * 1e9)
        stamp = time_from_ns(t_ns)
        self.clock_pub.publish(ClockMsg(clock=stamp))
        self.world.advance(self.world.t)
        self._publish_base(stamp)
        step.begin(t_ns, now)

    def _publish_base(self, stamp) -> None:
        """
        The base's range scan and its odometry now: the scan first, as a location waiting
        for the odometry of its step is answered as soon as that comes.
        """
        scan = self.world.scan()
        if scan is not None:
            self.scan_pub.publish(scan_message(scan, max_range=self.world.config.scan_range,
                                               header=Header(stamp=stamp,
                                                             frame_id='base_link')))
        base = self.world.base
        odom = Odometry()
        odom.header.stamp = stamp
        odom.header.frame_id = self.params['world_frame']
        odom.child_frame_id = 'base_link'
        odom.pose.pose.position.x, odom.pose.pose.position.y = base.x, base.y
        odom.pose.pose.orientation.z = math.sin(base.heading / 2)
        odom.pose.pose.orientation.w = math.cos(base.heading / 2)
        self.odom_pub.publish(odom)

    def publish(self, stamp) -> None:
        """Render the camera's view now and publish it with the target's true position."""
        view = self.world.observe()
        publish_frame(self, view.rgb, stamp, self.world.intrinsics.matrix)
        target = PointStamped()
        target.header.stamp = stamp
        target.header.frame_id = self.params['world_frame']
        target.point.x, target.point.y = self.world.target.x, self.world.target.y
        self.target_pub.publish(target)

    def _ready(self) -> bool:
        ready = (images_heard(self) if self.lockstep is None
                 else lockstep_graph_up(self, self.odom_pub, self.scan_pub))
        if not may_start(self, ready, 'the graph is up', 'the episode starts'):
            return False
        self.started_at = time.monotonic()
        return True

    def _finish(self) -> None:
        self.finished = True
        self.timer.cancel()
        s = self.world.episode_score()
        self.get_logger().info(
            f'episode over after {s.length} steps: recall {s.recall:.2f}, precision '
            f'{s.precision:.2f} (relaxed {s.precision_relaxed:.2f}), reward {s.reward:.1f}')
        if self.lockstep is not None:
            self.lockstep.report_missed(self.get_logger())

    def destroy_node(self):
        with self._lock:
            self._closed = True
            self.world.close()
        return super().destroy_node()


def main(args=None) -> int:
    return run(TrackingNode, args, on_stop=frames_stopped,
               help_text=lambda: node_help('tracking_node', __doc__, PARAMS))


if __name__ == '__main__':
    raise SystemExit(main())
