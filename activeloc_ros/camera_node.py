"""Camera node: publishes `camera/image_raw` and `camera/camera_info` from a chosen source.

    ros2 run activeloc_ros camera_node --ros-args -p source:=bag:bags/vtest -p loop:=true
"""
import time

from builtin_interfaces.msg import Time
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image

from activeloc_ros.checks import non_negative, one_of, positive
from activeloc_ros.errors import SourceError
from activeloc_ros.images import rgb_to_image_fields
from activeloc_ros.ros_params import declare, Param, run
from activeloc_ros.sources import default_bag, open_source, Pacer, pinhole_matrix

PARAMS = [
    Param('source', f'bag:{default_bag()}',
          'bag:PATH | video:PATH | folder:PATH | device:N | realsense', read_only=True),
    Param('image_topic', '', 'image topic to replay from a bag (empty: the first one)',
          read_only=True),
    Param('rate', 1.0, 'replay speed of recorded sources (1.0 = recorded timing)', positive),
    Param('loop', False, 'restart recorded sources at their end instead of finishing'),
    Param('encoding', 'rgb8', 'encoding of published images', one_of('rgb8', 'bgr8')),
    Param('frame_id', 'camera_color_optical_frame', 'frame_id of published headers'),
    Param('hfov_deg', 69.4, 'horizontal field of view used for CameraInfo when the source '
          'has no intrinsics of its own (default: RealSense D435 colour)', positive),
    Param('restamp', True, 'stamp frames with the time they are published (a live camera) '
          'instead of their recorded time'),
    Param('folder_fps', 10.0, 'frame rate of folder:PATH sources', positive),
    Param('realsense_width', 640, 'RealSense colour width', positive),
    Param('realsense_height', 480, 'RealSense colour height', positive),
    Param('realsense_fps', 30, 'RealSense colour frame rate', positive),
    Param('max_frames', 0, 'stop after this many frames (0: no limit)', non_negative),
    Param('wait_for_subscriber', 120.0, 'recorded sources: seconds to wait for a subscriber '
          'before the first frame, so a model still loading misses nothing (0: do not wait)',
          non_negative),
]


class CameraNode(Node):
    def __init__(self, **kwargs):
        super().__init__('camera', **kwargs)
        self.params = declare(self, PARAMS)
        p = self.params
        self.source = open_source(
            p['source'], clock=self._now_s, image_topic=p['image_topic'],
            folder_fps=p['folder_fps'], realsense_fps=p['realsense_fps'],
            realsense_size=(p['realsense_width'], p['realsense_height']))
        qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE)
        self.image_pub = self.create_publisher(Image, 'camera/image_raw', qos)
        self.info_pub = self.create_publisher(CameraInfo, 'camera/camera_info', 10)
        self.pacer = Pacer(p['rate'])
        self.pending = None
        self.published = 0
        self.logged_problems = set()
        self.finished = False
        self.started_at = time.monotonic()
        self.waiting = not self.source.live and p['wait_for_subscriber'] > 0
        self.timer = self.create_timer(0.005, self.tick)
        self.get_logger().info(f'streaming {p["source"]}')

    def _now_s(self) -> float:
        return self.get_clock().now().nanoseconds / 1e9

    def tick(self) -> None:
        if self.finished or (self.waiting and not self._subscriber_ready()):
            return
        if self.pending is None:
            self.pending = self._next_frame()
            if self.pending is None:
                self._finish('end of stream')
                return
        if not self.source.live:
            if time.monotonic() < self.pacer.due(self.pending.stamp, time.monotonic()):
                return
        self.publish(self.pending)
        self.pending = None
        if self.params['max_frames'] and self.published >= self.params['max_frames']:
            self._finish('max_frames reached')

    def _subscriber_ready(self) -> bool:
        if self.image_pub.get_subscription_count() > 0:
            self.get_logger().info('a subscriber is listening: replay starts')
        elif time.monotonic() - self.started_at > self.params['wait_for_subscriber']:
            self.get_logger().warning('no subscriber after '
                                      f'{self.params["wait_for_subscriber"]:g} s: replay starts')
        else:
            return False
        self.waiting = False
        return True

    def _next_frame(self):
        try:
            frame = self.source.read()
            if frame is None and self.params['loop']:
                self.source.rewind()
                frame = self.source.read()
        except SourceError as exc:
            self.get_logger().error(str(exc))
            return None
        for problem in set(self.source.skipped) - self.logged_problems:
            self.get_logger().warning(f'skipping frames: {problem}')
            self.logged_problems.add(problem)
        return frame

    def publish(self, frame) -> None:
        height, width = frame.rgb.shape[:2]
        if self.params['restamp']:
            stamp = self.get_clock().now().to_msg()
        else:
            stamp = Time(sec=int(frame.stamp), nanosec=int(round(frame.stamp % 1 * 1e9)) % 10**9)
        image = Image(**rgb_to_image_fields(frame.rgb, self.params['encoding']))
        image.header.stamp = stamp
        image.header.frame_id = self.params['frame_id']
        self.image_pub.publish(image)
        self.info_pub.publish(self.camera_info(width, height, image.header))
        self.published += 1
        if self.published == 1:
            self.get_logger().info(f'first frame published ({width}x{height})')

    def camera_info(self, width: int, height: int, header) -> CameraInfo:
        k = self.source.camera_matrix()
        if k is None:
            k = pinhole_matrix(width, height, self.params['hfov_deg'])
        info = CameraInfo(header=header, width=width, height=height,
                          distortion_model='plumb_bob')
        info.k = [float(v) for v in k.ravel()]
        info.d = [0.0] * 5
        info.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        info.p = [float(k[0, 0]), 0.0, float(k[0, 2]), 0.0,
                  0.0, float(k[1, 1]), float(k[1, 2]), 0.0, 0.0, 0.0, 1.0, 0.0]
        return info

    def _finish(self, why: str) -> None:
        self.finished = True
        self.timer.cancel()
        self.get_logger().info(f'{why}: {self.published} frames published')

    def destroy_node(self):
        self.source.close()
        return super().destroy_node()


def main(args=None) -> int:
    return run(CameraNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
