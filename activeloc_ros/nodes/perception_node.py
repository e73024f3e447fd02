"""
Perception node: the online surprise model on every newest camera frame.

Subscribes `camera/image_raw` (sensor_msgs/Image; with `image_transport: compressed`,
`camera/image_raw/compressed`, sensor_msgs/CompressedImage) with depth 1, so the newest
frame wins, and with the reliability its publishers offer (`image_reliability: auto`,
`activeloc_ros.nodes.qos`): a best-effort camera (SensorDataQoS) is heard, and a reliable one
loses no large frame on the way. Publishes
`surprise_map` (std_msgs/Float32MultiArray, 14 rows x 14 cols), `surprise_map/image` (the
same map as a 32FC1 sensor_msgs/Image with the frame's header), `surprise_map/overlay`
(the frame with the map blended on it), `action_location` (geometry_msgs/PointStamped:
pixel x, y of the action in the camera image, z = the map's peak; the frame's header),
before it `action_region` (geometry_msgs/PolygonStamped: the top-left and bottom-right
corners, px, of the map's blob round its peak, `metrics.blob_box`; a mobile base reads how
far the action is from it) and its health on `/diagnostics` (maps/s, latency, dropped and
skipped frames, the share of maps learnt from). A camera faster than the model makes some
frames late: their map is ready only after the next frame's capture (camera_info stamps
give the camera's period), and the model skips their optimiser step (`skip_late_updates`).

    ros2 run activeloc_ros perception_node --ros-args -p encoder:=vgg19
"""
import math
import os
import threading
import time
from typing import Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PointStamped, PolygonStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Float32MultiArray, Header, MultiArrayDimension

from activeloc_ros import metrics
from activeloc_ros.errors import FrameError
from activeloc_ros.images import (decode_compressed, float_image_fields, image_to_rgb, overlay,
                                  rgb_to_image_fields)
from activeloc_ros.nodes.health import PipelineStats
from activeloc_ros.nodes.messages import region_message, stamp_s
from activeloc_ros.nodes.params import declare, node_help
from activeloc_ros.nodes.process import run
from activeloc_ros.nodes.qos import offered_reliability
from activeloc_ros.perception.config import PerceptionConfig
from activeloc_ros.perception.model import PerceptionResult, SurpriseModel
from activeloc_ros.perception.params import MODEL_PARAMS, NODE_PARAMS, PARAMS
from activeloc_ros.perception.pipeline import Pipeline

RELIABILITY = {'best_effort': ReliabilityPolicy.BEST_EFFORT,
               'reliable': ReliabilityPolicy.RELIABLE}
QOS_CHECK_PERIOD_S = 1.0     # image_reliability auto: how often the publishers are looked at
MAX_CAPTURE_AGE_S = 1.0      # a frame stamped longer ago: its stamp is no capture time


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
        values = declare(self, PARAMS, cli_args=kwargs.get('cli_args'),
                         use_global_arguments=kwargs.get('use_global_arguments', True),
                         on_change=self.on_parameters)
        self.params = {p.name: values[p.name] for p in NODE_PARAMS}
        config = {p.name: values[p.name] for p in MODEL_PARAMS}
        pipelined = self.params['pipeline'] and not config['update_encoder']
        if pipelined and not config['num_threads']:     # one core for each half
            config['num_threads'] = max(1, (os.cpu_count() or 2) // 2)
        if self.params['checkpoint']:
            from activeloc_ros.perception import checkpoint
            self.model = checkpoint.load(self.params['checkpoint'])
        else:
            self.model = SurpriseModel(PerceptionConfig.from_dict(config))
        self.stats_lock = threading.Lock()     # the learning thread publishes the maps
        self.updates_before = self.model.updates    # a checkpoint's count goes on
        self.pipeline = (Pipeline(self.model, self.publish)
                         if pipelined and not self.model.train_encoder else None)
        overlay_qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE)
        self.map_pub = self.create_publisher(Float32MultiArray, 'surprise_map', 10)
        self.map_image_pub = self.create_publisher(Image, 'surprise_map/image', 10)
        self.overlay_pub = self.create_publisher(Image, 'surprise_map/overlay', overlay_qos)
        self.location_pub = self.create_publisher(PointStamped, 'action_location', 10)
        self.region_pub = self.create_publisher(PolygonStamped, 'action_region', 10)
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        choice = self.params['image_reliability']
        self.sub = self._subscribe(RELIABILITY.get(choice, ReliabilityPolicy.RELIABLE))
        if choice == 'auto':     # a steady timer: in lockstep simulated time stands still
            self.create_timer(QOS_CHECK_PERIOD_S, self._follow_publishers,
                              clock=Clock(clock_type=ClockType.STEADY_TIME))
        # one camera_info per published frame: counts the frames the depth-1 queue dropped
        self.info_sub = self.create_subscription(
            CameraInfo, 'camera/camera_info',
            lambda msg: self.stats.frame_announced(stamp_s(msg.header.stamp)),
            QoSProfile(depth=50, reliability=ReliabilityPolicy.BEST_EFFORT))
        self.stats = PipelineStats(time.monotonic())
        self.diagnostics_timer = self.create_timer(self.params['diagnostics_period'],
                                                   self.publish_diagnostics)
        self.logged_problems = set()
        self.frame_wh = None              # the size of the frames coming in
        self.nan_events = 0
        how = ('pipelined' if self.pipeline else
               'one step per frame' + (' (the encoder learns)' if self.params['pipeline']
                                       else ''))
        self.get_logger().info(f'model ready: encoder {self.model.cfg.encoder} '
                               f'({self.model.precision}), {how}; listening on '
                               f'{self.sub.topic_name} ({self.params["image_reliability"]})')

    def destroy_node(self) -> None:
        if self.pipeline is not None:
            self.pipeline.close(timeout=10.0)
        super().destroy_node()

    def _subscribe(self, reliability: ReliabilityPolicy):
        qos = QoSProfile(depth=1, reliability=reliability)
        if self.params['image_transport'] == 'compressed':
            return self.create_subscription(CompressedImage, 'camera/image_raw/compressed',
                                            self.on_compressed, qos)
        return self.create_subscription(Image, 'camera/image_raw', self.on_image, qos)

    def _follow_publishers(self) -> None:
        """image_reliability auto: subscribe again when the publishers need another QoS."""
        wanted = offered_reliability(self, self.sub.topic_name)
        if wanted == self.sub.qos_profile.reliability:
            return
        self.destroy_subscription(self.sub)
        self.sub = self._subscribe(wanted)
        self.get_logger().info(f'image publishers on {self.sub.topic_name} need '
                               f'{wanted.name.lower()}: subscribed again with it')

    def on_parameters(self, values: dict, changed: set) -> None:
        """A run-time change (read-only parameters are refused before): the next frame uses it."""
        changed = changed & values.keys()     # (use_sim_time is rclpy's)
        self.params.update({name: values[name] for name in changed & self.params.keys()})
        self.get_logger().info('set at run time: ' + ', '.join(
            f'{name} {values[name]!r}' for name in sorted(changed)))

    def on_image(self, msg: Image) -> None:
        self.stats.frame_received()
        if self._pipeline_busy():
            return
        try:
            rgb = image_to_rgb(msg.encoding, msg.height, msg.width, msg.step, msg.data,
                               max_pixels=self.params['max_image_pixels'])
        except FrameError as exc:
            self._skip(exc)
            return
        self.process(msg.header, rgb)

    def on_compressed(self, msg: CompressedImage) -> None:
        self.stats.frame_received()
        if self._pipeline_busy():
            return
        try:
            rgb = decode_compressed(msg.format, msg.data,
                                    max_pixels=self.params['max_image_pixels'])
        except FrameError as exc:
            self._skip(exc)
            return
        self.process(msg.header, rgb)

    def _pipeline_busy(self) -> bool:
        """
        With the pipeline, whether a frame already waits for the learner. A frame taken
        now would wait a whole learning step after it was encoded, so it is left, as depth 1
        leaves the frames that arrive while one is in hand, and a newer one is taken once the
        learner has the waiting frame.
        """
        return self.pipeline is not None and self.pipeline.busy()

    def process(self, header, rgb) -> None:
        started = time.monotonic()
        frame_wh = (rgb.shape[1], rgb.shape[0])
        if frame_wh != self.frame_wh:      # once per frame size: the encoder input's shape
            self.frame_wh = frame_wh
            note = self.model.features.aspect_note(frame_wh)
            if note:
                self.get_logger().warning(note)
        captured = stamp_s(header.stamp)
        if self.pipeline is None:  # the map goes out before the optimiser step
            tag = (header, rgb, started)
            self.model.step(rgb, t=captured, on_map=lambda r: self.publish(r, tag),
                            late=self._late(captured))
        else:                      # published from the learning thread
            self.pipeline.submit(rgb, tag=(header, rgb, started), t=captured)

    def _late(self, captured: float) -> Callable[[], bool] | None:
        """
        For the model's `skip_late_updates`: whether the node's clock has passed the
        capture of the camera's next frame (this frame's stamp plus the camera's period).
        None, never late, while the period is unknown or the stamp is no capture time (a
        bag replayed with its recorded stamps). In lockstep the clock stands still while
        the model runs: never late.
        """
        period = self.stats.camera_period
        now = self.get_clock().now().nanoseconds * 1e-9
        if period is None or not 0.0 <= now - captured < MAX_CAPTURE_AGE_S:
            return None
        next_capture = captured + period
        return lambda: self.get_clock().now().nanoseconds * 1e-9 >= next_capture

    def publish(self, result: PerceptionResult, tag: tuple) -> None:
        header, rgb, started = tag
        compute_s = time.monotonic() - started
        if result.nan_events != self.nan_events:
            self.nan_events = result.nan_events
            self.get_logger().warning(f'non-finite values in the model: update skipped and '
                                      f'state reset ({self.nan_events} so far)')
        self.map_pub.publish(map_message(result.surprise_map))
        self.map_image_pub.publish(Image(header=header,
                                         **float_image_fields(result.surprise_map)))
        height, width = rgb.shape[:2]
        box = metrics.blob_box(result.surprise_map, (width, height))
        if box is not None:
            self.region_pub.publish(region_message(box, header))
        location = PointStamped(header=header)
        location.point.x, location.point.y = (float(v) for v in result.location_px)
        location.point.z = float(result.peak) if math.isfinite(result.peak) else 0.0
        self.location_pub.publish(location)
        if self.params['publish_overlay'] and self.overlay_pub.get_subscription_count() > 0:
            blended = overlay(rgb, result.surprise_map, alpha=self.params['overlay_alpha'])
            image = Image(header=header, **rgb_to_image_fields(blended))
            self.overlay_pub.publish(image)
        # (rclpy's Time refuses the negative seconds a stamp can carry: not from_msg)
        latency_s = self.get_clock().now().nanoseconds * 1e-9 - stamp_s(header.stamp)
        with self.stats_lock:
            self.stats.map_published(latency_s=latency_s, compute_s=compute_s)
        if self.stats.maps == 1:
            self.get_logger().info('first surprise map published')

    def count_updates(self) -> None:
        """The optimiser steps the model took since the node started, into the stats."""
        self.stats.frames_learnt(self.model.updates - self.updates_before)

    def publish_diagnostics(self) -> None:
        with self.stats_lock:
            self.count_updates()
            report = self.stats.report(time.monotonic())
        status = DiagnosticStatus(
            level=bytes([report.level]), name=f'{self.get_name()}: surprise maps',
            message=report.message, hardware_id=self.sub.topic_name,
            values=[KeyValue(key=k, value=v) for k, v in report.values.items()])
        header = Header(stamp=self.get_clock().now().to_msg())
        self.diagnostics_pub.publish(DiagnosticArray(header=header, status=[status]))

    def _skip(self, problem: FrameError) -> None:
        """Skip a frame; each kind of problem is logged once and counted in /diagnostics."""
        text = f'skipping frames: {problem}'
        self.stats.frame_skipped(str(problem))
        if text not in self.logged_problems:
            self.logged_problems.add(text)
            self.get_logger().warning(text)


def stop(node: PerceptionNode) -> None:
    if node.pipeline is not None:                 # the frame being learnt is published
        node.pipeline.close(timeout=10.0)
    node.count_updates()
    node.get_logger().info(f'stopped: {node.stats.summary()}')


def main(args=None) -> int:
    # on_stop: a Ctrl-C or kill only ends the spin loop, so the frame in hand is finished
    # and published before the context ends (rclpy's own handler shut it down under it)
    return run(PerceptionNode, args, on_stop=stop,
               help_text=lambda: node_help('perception_node', __doc__, PARAMS))


if __name__ == '__main__':
    raise SystemExit(main())
