"""
The camera node's parameters, ROS-free: the node declares them, bringup checks them
before any node starts.
"""
from activeloc_ros.checks import field_of_view, in_range, non_negative, one_of, Param, positive
from activeloc_ros.sources import default_bag

# Parameters without read_only take effect at once: the next frame uses them.
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
          'has no intrinsics of its own (default: RealSense D435 colour)', field_of_view),
    Param('restamp', True, 'stamp frames with the time they are published (a live camera) '
          'instead of their recorded time'),
    Param('folder_fps', 10.0, 'frame rate of folder:PATH sources', positive, read_only=True),
    Param('realsense_width', 640, 'RealSense colour width', positive, read_only=True),
    Param('realsense_height', 480, 'RealSense colour height', positive, read_only=True),
    Param('realsense_fps', 30, 'RealSense colour frame rate', positive, read_only=True),
    Param('max_frames', 0, 'stop after this many frames (0: no limit)', non_negative),
    Param('wait_for_subscriber', 120.0, 'recorded sources: seconds to wait for a subscriber '
          'before the first frame, so a model still loading misses nothing (0: do not wait)',
          non_negative),
    Param('min_subscribers', 1, 'recorded sources: image subscribers to wait for (up to '
          'wait_for_subscriber) before the first frame; bringup --record makes it 2, so the '
          'recording holds the first frame too', in_range(1, 1000)),
]
