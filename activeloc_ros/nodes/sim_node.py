"""
Simulation node: the projected-screen world (`world.ScreenWorld`) in the graph.

    ros2 run activeloc_ros sim_node --ros-args -p scene:=otb_crossing

A recorded scene plays on the virtual screen, seen by a camera that a simulated Braccio
(`control.SimArm`, whole degrees at its servos' speed) aims. The node is the camera and the
arm of a virtual run, so a frame and the pose it was rendered with never disagree. It moves
the arm to `joint_commands` and publishes `joint_states`, `camera/image_raw`,
`camera/camera_info` and `camera/pose` (sensor_msgs/JointState named pan, tilt: radians,
stamped like the image).

In real time the scene plays at its own rate (times `rate`). With `lockstep` (and
`use_sim_time` on every node) the node owns a simulated `/clock` and steps the graph frame
by frame as `closed_loop` does (`activeloc_ros.nodes.lockstep`).
"""
import math
import threading
import time

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import CameraInfo, Image, JointState

from activeloc_ros.control.braccio import clamp_text, clamp_to_limits, refusal_text
from activeloc_ros.data import FrameTruth
from activeloc_ros.errors import ConfigError
from activeloc_ros.nodes.frames import (
    end_playback, images_heard, lockstep_graph_up, lockstep_wiring, may_start, publish_frame)
from activeloc_ros.nodes.lockstep import moot_in_lockstep, time_ns
from activeloc_ros.nodes.masters import PublisherWatch
from activeloc_ros.nodes.messages import (
    arm_joints_deg, joint_state, stamp_ns, time_from_ns)
from activeloc_ros.nodes.params import declare, node_help
from activeloc_ros.nodes.process import frame_due, frames_stopped, run
from activeloc_ros.screen import VirtualScreen
from activeloc_ros.settings import mapping_from, screen_from
from activeloc_ros.sim_params import PARAMS
from activeloc_ros.sources import DEFAULT_SCENE_FPS, open_scene, Pacer, Playback
from activeloc_ros.world import frame_time, ScreenWorld


class SimNode(Node):

    def __init__(self, **kwargs):
        super().__init__('sim', **kwargs)
        self.params = declare(self, PARAMS, cli_args=kwargs.get('cli_args'),
                              use_global_arguments=kwargs.get('use_global_arguments', True),
                              check_all=moot_in_lockstep, on_change=self.on_parameters)
        p = self.params
        self.sim_time = self.get_parameter('use_sim_time').value
        if p['lockstep'] and not self.sim_time:
            raise ConfigError("parameter 'lockstep' runs the graph on simulated time: set "
                              'use_sim_time:=true on every node')
        if self.sim_time and not p['lockstep']:
            raise ConfigError('on simulated time this node owns the clock: set lockstep:=true')
        screen = VirtualScreen(screen_from(p), mapping=mapping_from(p))
        self.scene = open_scene(p['scene'], image_topic=p['image_topic'],
                                folder_fps=p['folder_fps'])
        self.fps = self.scene.fps or DEFAULT_SCENE_FPS
        self.world = ScreenWorld((), fps=self.fps, screen=screen,
                                 home_deg=screen.mapping.home_deg,
                                 step_delay_ms=p['step_delay_ms'])
        self.index = 0                    # the next scene frame
        self.lockstep = None
        reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.image_pub = self.create_publisher(Image, 'camera/image_raw', reliable)
        self.info_pub = self.create_publisher(CameraInfo, 'camera/camera_info', 10)
        self.pose_pub = self.create_publisher(JointState, 'camera/pose', reliable)
        self.state_pub = self.create_publisher(JointState, 'joint_states', reliable)
        self.masters = PublisherWatch(self, 'joint_commands')   # the arm obeys one master
        self.command_sub = self.create_subscription(
            JointState, 'joint_commands', self.on_command,
            QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        if p['lockstep']:
            # our own arm state back: it is on its way to the controller too
            self.lockstep = lockstep_wiring(self, JointState, 'joint_states')
        else:
            self.create_timer(1.0 / p['state_rate'], self.publish_state, clock=steady)
        self.pacer = Pacer(p['rate'])
        self.playback = Playback(self.scene, p['scene'], warn=self.get_logger().warning)
        self.pending = None               # real time: the next scene frame, when it is due
        self.published = 0
        self.rejected = 0
        self.refused = 0
        self.clamped = 0
        self.finished = False
        self.failure: str | None = None   # why the stream ended in error (run() exits 1)
        self.started_at = time.monotonic()
        # a multi-threaded executor may run a tick while another thread destroys the node
        self._lock = threading.Lock()
        self._closed = False
        self.waiting = p['wait_for_subscriber'] > 0
        # a steady timer: in lockstep the simulated clock stands still until this node moves it
        self.timer = self.create_timer(0.005, self.tick, clock=steady)
        mode = (f'lockstep, {self.fps:g} frames per simulated second' if p['lockstep']
                else 'real time')
        self.get_logger().info(f'scene {p["scene"]} ({mode}); {screen.describe()}')

    def on_parameters(self, values: dict, changed: set) -> None:
        """A run-time change (read-only parameters are refused before): applied at once."""
        changed = changed & values.keys()     # (use_sim_time is rclpy's)
        self.params.update({name: values[name] for name in changed})
        if 'rate' in changed:
            self.pacer.set_rate(values['rate'])
        self.get_logger().info('set at run time: ' + ', '.join(
            f'{name} {values[name]!r}' for name in sorted(changed)))

    def _now(self) -> float:
        """The world's time: simulated (the frame's), else seconds since the node started."""
        if self.lockstep is not None:
            return self.world.t
        return time.monotonic() - self.started_at

    # -- inputs ----------------------------------------------------------------------------

    def on_command(self, msg: JointState) -> None:
        joints = arm_joints_deg(msg)
        with self._lock:
            if joints is None or not all(math.isfinite(q) for q in joints):
                self.rejected += 1
                self.get_logger().warning(
                    'ignored a joint command without six finite joint angles by name '
                    f'({self.rejected} so far)', throttle_duration_sec=5.0)
            elif not self._closed and self._acceptable(joints):
                self.world.act(joints, self._now())
            if self.lockstep is not None:
                self.lockstep.on_command(stamp_ns(msg.header.stamp))

    def _acceptable(self, joints: tuple[float, ...]) -> bool:
        """
        Refuse (and say so) a command that moves a joint which does not aim the camera;
        say so when one is clamped into the joint limits, which the arm then does.
        """
        mapping = self.world.screen.mapping
        moved = mapping.fixed_moves(joints, self.world.arm.target)
        if moved:
            self.refused += 1
            self.get_logger().warning(
                refusal_text(moved, mapping.aiming_joints, self.refused),
                throttle_duration_sec=5.0)
            return False
        safe = clamp_to_limits(joints)
        if safe != tuple(joints):
            self.clamped += 1
            self.get_logger().warning(clamp_text(joints, safe, self.clamped),
                                      throttle_duration_sec=5.0)
        return True

    # -- outputs ---------------------------------------------------------------------------

    def publish_state(self) -> None:
        with self._lock:
            if self._closed:
                return
            joints = self.world.advance(self._now())
        self.state_pub.publish(joint_state(joints, self.get_clock().now().to_msg()))

    def tick(self) -> None:
        with self._lock:
            if not (self._closed or self.finished
                    or (self.waiting and not self._subscriber_ready())):
                if self.lockstep is not None:
                    self._lockstep_tick()
                else:
                    self._realtime_tick()

    def _max_frames_reached(self) -> bool:
        if self.params['max_frames'] and self.published >= self.params['max_frames']:
            self.finish('max_frames reached')
            return True
        return False

    def _realtime_tick(self) -> None:
        if self._max_frames_reached():
            return
        if self.pending is None:
            self.pending = self._next_scene()
            if self.pending is None:
                end_playback(self, 'scene')
                return
        index, rgb = self.pending
        if not frame_due(self.timer, self.pacer.due(frame_time(index, self.fps),
                                                    time.monotonic())):
            return
        self.pending = None
        self.world.show(index, rgb, FrameTruth(index, None, ()), self._now())
        self.world.advance(self.world.t)
        self.publish(self.get_clock().now().to_msg())

    def _lockstep_tick(self) -> None:
        step, now = self.lockstep, time.monotonic()
        action = step.poll(now)
        if action == 'render':
            self.publish(time_from_ns(step.t_ns))
            step.rendered(now)
            return
        if action != 'next':
            return
        self.playback.report(step.missed, 'lockstep')
        if self._max_frames_reached():
            return
        scene = self._next_scene()
        if scene is None:
            end_playback(self, 'scene')
            return
        index, rgb = scene
        t_ns = time_ns(index, self.fps)
        stamp = time_from_ns(t_ns)
        self.world.show(index, rgb, FrameTruth(index, None, ()))
        self.clock_pub.publish(ClockMsg(clock=stamp))
        self.state_pub.publish(joint_state(self.world.advance(self.world.t), stamp))
        step.begin(t_ns, now)

    def _next_scene(self):
        frame = self.playback.read(loop=self.params['loop'])
        if frame is None:
            return None
        self.index += 1                   # a loop goes on counting: time goes on
        return self.index - 1, frame.rgb

    def publish(self, stamp) -> None:
        """Render the shown frame from the arm's pose now and publish it, stamped ``stamp``."""
        view = self.world.observe()
        header = publish_frame(self, view.rgb, stamp, self.world.screen.K)
        self.pose_pub.publish(JointState(header=header, name=['pan', 'tilt'],
                                         position=[view.pan, view.tilt]))

    def _subscriber_ready(self) -> bool:
        if self.lockstep is not None:
            return may_start(self, lockstep_graph_up(self, self.state_pub),
                             'perception and controller are up',
                             'lockstep starts')
        return may_start(self, images_heard(self), 'a subscriber is listening',
                         'the scene starts')

    def finish(self, why: str) -> None:
        self.finished = True
        self.timer.cancel()
        self.get_logger().info(self.playback.summary(why, self.published))
        if self.lockstep is not None:
            self.lockstep.report_missed(self.get_logger())

    def destroy_node(self):
        with self._lock:
            self._closed = True
            self.scene.close()
        return super().destroy_node()


def main(args=None) -> int:
    return run(SimNode, args, on_stop=frames_stopped,
               help_text=lambda: node_help('sim_node', __doc__, PARAMS))


if __name__ == '__main__':
    raise SystemExit(main())
