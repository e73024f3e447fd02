"""
Camera node: publishes `camera/image_raw` and `camera/camera_info` from a chosen source.

    ros2 run activeloc_ros camera_node --ros-args -p source:=bag:bags/vtest -p loop:=true

A plain camera driver: a recorded bag, video or folder, a device or a RealSense. The
projected-screen experiment's virtual camera, which an arm aims, is the sim node's
(`activeloc_ros.nodes.sim_node`).
"""
import threading
import time

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image

from activeloc_ros.camera_params import PARAMS
from activeloc_ros.nodes.frames import end_playback, images_heard, may_start, publish_frame
from activeloc_ros.nodes.messages import time_from_s
from activeloc_ros.nodes.params import declare, node_help
from activeloc_ros.nodes.process import frame_due, frames_stopped, run
from activeloc_ros.sources import open_source, Pacer, pinhole_matrix, Playback


class CameraNode(Node):

    def __init__(self, **kwargs):
        super().__init__('camera', **kwargs)
        self.params = declare(self, PARAMS, cli_args=kwargs.get('cli_args'),
                              use_global_arguments=kwargs.get('use_global_arguments', True),
                              on_change=self.on_parameters)
        p = self.params
        self.source = open_source(
            p['source'], clock=self._now_s, image_topic=p['image_topic'],
            folder_fps=p['folder_fps'], realsense_fps=p['realsense_fps'],
            realsense_size=(p['realsense_width'], p['realsense_height']))
        # The writer keeps the last frames until every reader has them, so a recorder gets
        # each one; perception's own depth-1 queue still hands it only the newest.
        reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.image_pub = self.create_publisher(Image, 'camera/image_raw', reliable)
        self.info_pub = self.create_publisher(CameraInfo, 'camera/camera_info', 10)
        self.pacer = Pacer(p['rate'])
        self.playback = Playback(self.source, p['source'], warn=self.get_logger().warning)
        self.pending = None
        self.published = 0
        self.finished = False
        self.failure: str | None = None   # why the stream ended in error (run() exits 1)
        self.started_at = time.monotonic()
        # a multi-threaded executor may still run a tick while another thread destroys the
        # node: the lock keeps the source from being closed under a read
        self._source_lock = threading.Lock()
        self._closed = False
        self.waiting = not self.source.live and p['wait_for_subscriber'] > 0
        self.timer = self.create_timer(0.005, self.tick,
                                       clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(f'streaming {p["source"]}')

    def on_parameters(self, values: dict, changed: set) -> None:
        """A run-time change (read-only parameters are refused before): applied at once."""
        changed = changed & values.keys()     # (use_sim_time is rclpy's)
        self.params.update({name: values[name] for name in changed})
        if 'rate' in changed:
            self.pacer.set_rate(values['rate'])
        self.get_logger().info('set at run time: ' + ', '.join(
            f'{name} {values[name]!r}' for name in sorted(changed)))

    def _now_s(self) -> float:
        return self.get_clock().now().nanoseconds / 1e9

    # -- frames ----------------------------------------------------------------------------

    def tick(self) -> None:
        with self._source_lock:
            if not self._closed:
                self._tick()

    def _tick(self) -> None:
        if self.finished or (self.waiting and not self._subscriber_ready()):
            return
        if self.pending is None:
            self.pending = self.playback.read(loop=self.params['loop'])
            if self.pending is None:
                end_playback(self, 'stream')
                return
        if not (self.source.live or frame_due(
                self.timer, self.pacer.due(self.pending.stamp, time.monotonic()))):
            return
        self.publish(self.pending)
        self.pending = None
        if self.params['max_frames'] and self.published >= self.params['max_frames']:
            self.finish('max_frames reached')

    def _subscriber_ready(self) -> bool:
        return may_start(self, images_heard(self), 'a subscriber is listening', 'replay starts')

    def publish(self, frame) -> None:
        stamp = (self.get_clock().now().to_msg() if self.params['restamp']
                 else time_from_s(frame.stamp))
        k = self.source.camera_matrix()
        if k is None:
            height, width = frame.rgb.shape[:2]
            k = pinhole_matrix(width, height, self.params['hfov_deg'])
        publish_frame(self, frame.rgb, stamp, k)

    def finish(self, why: str) -> None:
        self.finished = True
        self.timer.cancel()
        self.get_logger().info(self.playback.summary(why, self.published))

    def destroy_node(self):
        with self._source_lock:
            self._closed = True
            self.source.close()
        return super().destroy_node()


def main(args=None) -> int:
    # on_stop: a Ctrl-C or kill only ends the spin loop, so no frame is published into a
    # context that rclpy's own signal handler has already shut down
    return run(CameraNode, args, on_stop=frames_stopped,
               help_text=lambda: node_help('camera_node', __doc__, PARAMS))


if __name__ == '__main__':
    raise SystemExit(main())
