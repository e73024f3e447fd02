"""bringup's own node: watches the graph's topics for its status line and summary."""
import math
import sys
import threading
import time

import numpy as np

from activeloc_ros.nodes.messages import stamp_s


class Monitor:
    """
    Watches the graph's topics from its own node: rates, latency, location, arm pose.

    In lockstep the graph's stamps are simulated time, in which a command takes no time:
    the monitor shows how far the simulated clock got instead of a latency.
    """

    def __init__(self, context, *, lockstep: bool = False, arm_node: bool = True,
                 base: bool = False, cli_args=None):
        from geometry_msgs.msg import PointStamped, Twist
        from rclpy.node import Node
        from sensor_msgs.msg import CameraInfo, JointState
        from std_msgs.msg import Float32MultiArray
        self.node = Node('bringup_monitor', context=context, cli_args=cli_args)
        self.lock = threading.Lock()
        self.frames, self.maps, self.commands = [], [], []
        self.latencies: list[float] = []
        self.location = None
        self.image_size = None
        self.lockstep = lockstep
        self.arm_node = arm_node       # the arm is a node of its own, not the sim's
        self.sim_time = 0.0            # lockstep: the newest frame's simulated time, s
        self.joints: dict[str, float] = {}
        self.joints_at = -math.inf     # when the last joint_states came
        sub = self.node.create_subscription
        sub(CameraInfo, 'camera/camera_info', self.on_info, 10)
        # what perception and the controller publish: heard before the source starts
        self.downstream = [
            sub(Float32MultiArray, 'surprise_map', lambda m: self._stamp(self.maps), 10),
            sub(PointStamped, 'action_location', self.on_location, 10)]
        if base:        # a mobile base's commands (the tracking world)
            self.downstream.append(
                sub(Twist, 'cmd_vel', lambda m: self._stamp(self.commands), 10))
        else:
            self.downstream.append(sub(JointState, 'joint_commands', self.on_command, 10))
            sub(JointState, 'joint_states', self.on_state, 10)
        from activeloc_ros.nodes.masters import PublisherWatch
        # a second controller beside the graph, said on this console (the nodes say it too)
        self.masters = PublisherWatch(
            self.node, 'cmd_vel' if base else 'joint_commands', diagnostics=False,
            say=lambda text: print(f'bringup: warning: {text}', file=sys.stderr, flush=True))

    def hears_downstream(self, recorder=None) -> bool:
        """
        Are the monitor's (and the recorder's) subscriptions to what perception and the
        controller publish matched with their publishers? Discovery is pairwise, so a node
        the source already talks to may not yet reach bringup's own nodes.
        """
        subs = list(self.downstream)
        if recorder is not None:
            subs += [recorder.subs.get(s.topic_name) for s in self.downstream]
        return all(s is not None and s.get_publisher_count() > 0 for s in subs)

    def _stamp(self, series):
        with self.lock:
            series.append(time.monotonic())

    def on_info(self, msg):
        self.image_size = (msg.width, msg.height)
        stamp = stamp_s(msg.header.stamp)
        self.sim_time = max(self.sim_time, stamp)
        self._stamp(self.frames)

    def on_location(self, msg):
        self.location = (msg.point.x, msg.point.y)

    def on_command(self, msg):
        sent = stamp_s(msg.header.stamp)
        if sent > 0 and not self.lockstep:
            now = self.node.get_clock().now().nanoseconds * 1e-9
            with self.lock:
                self.latencies.append(now - sent)
        self._stamp(self.commands)

    def on_state(self, msg):
        self.joints = dict(zip(msg.name, np.degrees(msg.position)))
        self.joints_at = time.monotonic()

    @staticmethod
    def rate(series, window=3.0) -> float:
        now = time.monotonic()
        recent = [t for t in series if now - t <= window]
        return len(recent) / window if recent else 0.0

    def latency_ms(self, recent: int = 0) -> tuple[float, float]:
        with self.lock:
            values = self.latencies[-recent:] if recent else list(self.latencies)
        if not values:
            return float('nan'), float('nan')
        p50, p95 = np.percentile(values, [50, 95])
        return p50 * 1e3, p95 * 1e3

    def status(self, elapsed: float) -> str:
        p50, p95 = self.latency_ms(recent=50)
        where = (f'({self.location[0]:.0f}, {self.location[1]:.0f})' if self.location
                 else '(none yet)')
        joints = ' '.join(f'{name} {deg:.0f}°' for name, deg in self.joints.items()
                          if name in ('base', 'shoulder', 'elbow', 'wrist_ver'))
        timing = (f'simulated {self.sim_time:6.1f} s' if self.lockstep
                  else f'frame->command p50 {p50:4.0f} ms p95 {p95:4.0f} ms')
        return (f'[{elapsed:6.1f}s] camera {self.rate(self.frames):4.1f} fps | '
                f'maps {self.rate(self.maps):4.1f} fps | {timing} | action {where} | '
                f'{joints or "arm: no state yet"}')


def percentile_text(monitor: Monitor) -> str:
    if not monitor.latencies and monitor.commands:
        return ("not measured: a base's cmd_vel carries no stamp (the controller's log "
                'has its own figures)')
    p50, p95 = monitor.latency_ms()
    return f'p50 {p50:.0f} ms, p95 {p95:.0f} ms over {len(monitor.latencies)} commands'
