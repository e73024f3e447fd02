"""
The perception node as a ROS 2 user's camera meets it: QoS, compressed frames, a stamped
map image, hostile sizes and its health on /diagnostics.
"""
import time

import cv2
import numpy as np
import pytest
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data, QoSProfile, ReliabilityPolicy

from conftest import params_args, spin_until

FRAME = np.random.default_rng(0).integers(0, 255, (60, 80, 3), dtype=np.uint8)


@pytest.fixture
def rig(context):
    """A perception node (real weights, packaged params) and a probe node in one executor."""
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import Image
    from activeloc_ros.nodes.perception_node import PerceptionNode
    made = []

    def make(*overrides):
        node = PerceptionNode(context=context,
                              cli_args=params_args('diagnostics_period:=0.2', *overrides))
        probe = Node('probe', context=context)
        heard = {'maps': [], 'diagnostics': []}
        probe.create_subscription(Image, 'surprise_map/image', heard['maps'].append, 10)
        probe.create_subscription(DiagnosticArray, '/diagnostics',
                                  heard['diagnostics'].append, 10)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        executor.add_node(probe)
        made.append((executor, node, probe))
        return executor, node, probe, heard

    yield make
    for executor, node, probe in made:
        executor.shutdown()
        node.destroy_node()
        probe.destroy_node()


def feed(executor, publisher, msg, condition, timeout=60.0) -> bool:
    """Publish `msg` (re-stamped) until `condition()`; discovery and depth 1 may drop some."""
    deadline = time.monotonic() + timeout
    while not condition() and time.monotonic() < deadline:
        publisher.publish(msg)
        spin_until(executor, condition, 0.5)
    return condition()


def image(header_frame='cam', stamp_s=7):
    from sensor_msgs.msg import Image
    from activeloc_ros.images import rgb_to_image_fields
    msg = Image(**rgb_to_image_fields(FRAME))
    msg.header.frame_id = header_frame
    msg.header.stamp.sec = stamp_s
    return msg


@pytest.mark.parametrize('qos', ['best_effort', 'reliable'])
def test_a_camera_of_either_reliability_is_heard(rig, qos):
    """SensorDataQoS drivers publish best effort, which a reliable subscription never hears."""
    from sensor_msgs.msg import Image
    executor, node, probe, heard = rig()
    profile = (qos_profile_sensor_data if qos == 'best_effort'
               else QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
    publisher = probe.create_publisher(Image, 'camera/image_raw', profile)
    assert feed(executor, publisher, image(), lambda: len(heard['maps']) >= 2)
    assert node.sub.qos_profile.reliability == profile.reliability


@pytest.mark.parametrize('pipeline', [False, True])
def test_the_map_image_carries_the_frames_header(rig, pipeline):
    """Also when the maps are published from the pipeline's learning thread."""
    from sensor_msgs.msg import Image
    executor, node, probe, heard = rig(f'pipeline:={str(pipeline).lower()}')
    assert (node.pipeline is not None) is pipeline
    publisher = probe.create_publisher(Image, 'camera/image_raw', 10)
    assert feed(executor, publisher, image('optical', 7), lambda: len(heard['maps']) >= 2)
    msg = heard['maps'][-1]
    assert (msg.encoding, msg.height, msg.width) == ('32FC1', 14, 14)
    assert msg.header.frame_id == 'optical' and msg.header.stamp.sec == 7
    values = np.frombuffer(bytes(msg.data), np.float32)
    assert values.shape == (196,) and abs(values.sum() - 1.0) < 1e-3
    if pipeline:
        node.destroy_node()                       # the learning thread ends with the node
        assert not node.pipeline._thread.is_alive()


@pytest.mark.parametrize('pipeline', [False, True])
def test_a_frame_stamped_before_1970_is_mapped_not_fatal(rig, pipeline):
    """
    A stamp's seconds are an int32: -1 can come over a topic. rclpy's Time refuses it,
    and computing the latency with it killed the node (with the pipeline: its learner).
    """
    from sensor_msgs.msg import Image
    executor, node, probe, heard = rig(f'pipeline:={str(pipeline).lower()}')
    publisher = probe.create_publisher(Image, 'camera/image_raw', 10)
    assert feed(executor, publisher, image('cam', -1), lambda: len(heard['maps']) >= 2)


@pytest.mark.parametrize('pipeline', [False, True])
def test_the_model_is_told_each_frames_capture_time(rig, pipeline):
    """
    From the header's stamp: the motion weighting's scale follows the time between
    frames (`motion_period`).
    """
    from sensor_msgs.msg import Image
    executor, node, probe, heard = rig(f'pipeline:={str(pipeline).lower()}')
    publisher = probe.create_publisher(Image, 'camera/image_raw', 10)
    msg = image('cam', 7)
    msg.header.stamp.nanosec = 250_000_000
    assert feed(executor, publisher, msg, lambda: len(heard['maps']) >= 1)
    assert node.model.t_prev == pytest.approx(7.25)


def test_compressed_frames_are_decoded(rig):
    from sensor_msgs.msg import CompressedImage
    executor, node, probe, heard = rig('image_transport:=compressed')
    publisher = probe.create_publisher(CompressedImage, 'camera/image_raw/compressed', 10)
    ok, jpeg = cv2.imencode('.jpg', cv2.cvtColor(FRAME, cv2.COLOR_RGB2BGR))
    assert ok
    msg = CompressedImage(format='jpeg', data=jpeg.tobytes())
    assert feed(executor, publisher, msg, lambda: len(heard['maps']) >= 2)


def test_an_oversized_frame_is_skipped_and_reported(rig):
    from sensor_msgs.msg import Image
    from activeloc_ros.nodes.health import WARN
    executor, node, probe, heard = rig(f'max_image_pixels:={60 * 80 - 1}')
    publisher = probe.create_publisher(Image, 'camera/image_raw', 10)
    assert feed(executor, publisher, image(), lambda: node.stats.skipped)
    assert not heard['maps']
    assert 'max_image_pixels' in next(iter(node.stats.skipped))

    def warned():
        return any(s.level == bytes([WARN]) and 'skipping' in s.message
                   for d in heard['diagnostics'] for s in d.status)
    assert spin_until(executor, warned, 5.0)


@pytest.mark.parametrize('stamped', ['now', 'recorded'])
def test_frames_mapped_after_the_next_capture_are_not_all_learnt_from(rig, stamped):
    """
    A 1 kHz camera (its camera_info stamps): each map is ready after the next capture,
    so with skip_late_updates 1 at most every second frame gets an optimiser step. Stamps
    from a recording are no capture times: every frame is learnt from.
    """
    from sensor_msgs.msg import CameraInfo, Image
    executor, node, probe, heard = rig('skip_late_updates:=1')
    info_pub = probe.create_publisher(CameraInfo, 'camera/camera_info', 10)
    image_pub = probe.create_publisher(Image, 'camera/image_raw', 10)
    start = probe.get_clock().now().nanoseconds
    for k in range(3):
        info = CameraInfo()
        info.header.stamp.sec, info.header.stamp.nanosec = divmod(start + k * 10**6, 10**9)
        info_pub.publish(info)
    assert spin_until(executor, lambda: node.stats.camera_period is not None, 30.0)
    assert node.stats.camera_period == pytest.approx(1e-3, rel=1e-3)
    for n in range(1, 9):
        msg = image()
        if stamped == 'now':
            msg.header.stamp = probe.get_clock().now().to_msg()
        assert feed(executor, image_pub, msg, lambda: node.stats.maps >= n)
    node.count_updates()
    maps, learnt = node.stats.maps, node.stats.learnt
    if stamped == 'now':       # the first frame has nothing to learn from
        assert (maps - 1) // 2 <= learnt < maps - 1
    else:
        assert learnt == maps - 1
