"""Perception node: the online surprise model on every newest camera frame.

Subscribes `camera/image_raw` (depth 1: the newest frame wins) and publishes
`surprise_map` (std_msgs/Float32MultiArray, 14 rows x 14 cols), `surprise_map/overlay`
(the frame with the map blended on it) and `action_location` (geometry_msgs/PointStamped:
pixel x, y of the action in the camera image, z = the map's peak; the frame's header).

    ros2 run activeloc_ros perception_node --ros-args --params-file params/perception.yaml
"""
import dataclasses
import math

from geometry_msgs.msg import PointStamped
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image
from std_msgs.msg import Float32MultiArray, MultiArrayDimension

from activeloc_ros.checks import in_range
from activeloc_ros.errors import FrameError
from activeloc_ros.images import image_to_rgb, overlay, rgb_to_image_fields
from activeloc_ros.perception.model import PerceptionConfig, SurpriseModel
from activeloc_ros.ros_params import declare, Param, run

NODE_PARAMS = [
    Param('publish_overlay', True, 'publish surprise_map/overlay (costs a few ms per frame)'),
    Param('overlay_alpha', 0.45, 'weight of the heat map in the overlay', in_range(0.0, 1.0)),
    Param('checkpoint', '', 'model checkpoint to start from (empty: fresh model)',
          read_only=True),
]


def model_params() -> list[Param]:
    """One ROS parameter per PerceptionConfig field, validated by the config's own check."""
    params = []
    for field in dataclasses.fields(PerceptionConfig):
        def check(value, name=field.name):
            return PerceptionConfig.check(name, value)

        params.append(Param(field.name, field.default, field.metadata.get('help', field.name),
                            check, read_only=True))
    return params


def map_message(surprise_map) -> Float32MultiArray:
    rows, cols = surprise_map.shape
    msg = Float32MultiArray()
    msg.layout.dim = [MultiArrayDimension(label='rows', size=rows, stride=rows * cols),
                      MultiArrayDimension(label='cols', size=cols, stride=cols)]
    msg.data = surprise_map.astype('float32').ravel().tolist()
    return msg


class PerceptionNode(Node):
    def __init__(self, **kwargs):
        super().__init__('perception', **kwargs)
        fields = model_params()
        values = declare(self, fields + NODE_PARAMS)
        self.params = {p.name: values[p.name] for p in NODE_PARAMS}
        config = {f.name: values[f.name] for f in fields}
        if self.params['checkpoint']:
            self.model = SurpriseModel.load(self.params['checkpoint'])
        else:
            self.model = SurpriseModel(PerceptionConfig.from_dict(config))
        image_qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE)
        self.map_pub = self.create_publisher(Float32MultiArray, 'surprise_map', 10)
        self.overlay_pub = self.create_publisher(Image, 'surprise_map/overlay', image_qos)
        self.location_pub = self.create_publisher(PointStamped, 'action_location', 10)
        self.sub = self.create_subscription(Image, 'camera/image_raw', self.on_image, image_qos)
        self.logged_problems = set()
        self.nan_events = 0
        self.frames = 0
        self.get_logger().info(f'model ready: encoder {self.model.cfg.encoder}')

    def on_image(self, msg: Image) -> None:
        try:
            rgb = image_to_rgb(msg.encoding, msg.height, msg.width, msg.step, msg.data)
        except FrameError as exc:
            self._warn_once(f'skipping frames: {exc}')
            return
        result = self.model.step(rgb)
        self.frames += 1
        if result.nan_events != self.nan_events:
            self.nan_events = result.nan_events
            self.get_logger().warning(f'non-finite values in the model: update skipped and '
                                      f'state reset ({self.nan_events} so far)')
        self.map_pub.publish(map_message(result.surprise_map))
        location = PointStamped(header=msg.header)
        location.point.x, location.point.y = (float(v) for v in result.location_px)
        location.point.z = float(result.peak) if math.isfinite(result.peak) else 0.0
        self.location_pub.publish(location)
        if self.params['publish_overlay'] and self.overlay_pub.get_subscription_count() > 0:
            blended = overlay(rgb, result.surprise_map, alpha=self.params['overlay_alpha'])
            image = Image(header=msg.header, **rgb_to_image_fields(blended))
            self.overlay_pub.publish(image)
        if self.frames == 1:
            self.get_logger().info('first surprise map published')

    def _warn_once(self, problem: str) -> None:
        if problem not in self.logged_problems:
            self.logged_problems.add(problem)
            self.get_logger().warning(problem)


def main(args=None) -> int:
    return run(PerceptionNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
