"""What the three nodes that publish camera frames (camera, sim, tracking) do alike: publish
a picture with its camera info, and hold the first one back until its readers are up.

Each node has ``params`` (``encoding``, ``frame_id``, ``min_subscribers``,
``wait_for_subscriber``), ``image_pub``, ``info_pub``, ``published``, ``started_at`` and
``waiting``; in lockstep also ``command_sub``, ``location_sub`` and ``ignored_sub``.
"""
import time

from sensor_msgs.msg import Image

from activeloc_ros.images import rgb_to_image_fields
from activeloc_ros.nodes.messages import camera_info


def publish_frame(node, rgb, stamp, k):
    """Publish ``rgb`` on camera/image_raw and its pinhole ``k`` on camera/camera_info, both
    stamped ``stamp``, and count it; returns the header they share."""
    height, width = rgb.shape[:2]
    image = Image(**rgb_to_image_fields(rgb, node.params['encoding']))
    image.header.stamp = stamp
    image.header.frame_id = node.params['frame_id']
    node.image_pub.publish(image)
    node.info_pub.publish(camera_info(k, width, height, image.header))
    node.published += 1
    if node.published == 1:
        node.get_logger().info(f'first frame published ({width}x{height})')
    return image.header


def images_heard(node) -> bool:
    """Whether as many readers as ``min_subscribers`` take the pictures."""
    return node.image_pub.get_subscription_count() >= node.params['min_subscribers']


def lockstep_graph_up(node) -> bool:
    """Whether the pictures have their readers, and perception and the controller, which
    lockstep waits for at every frame, publish what the node listens to."""
    return (images_heard(node) and node.command_sub.get_publisher_count() > 0
            and node.ignored_sub.get_publisher_count() > 0
            and node.location_sub.get_publisher_count() > 0)


def may_start(node, ready: bool, heard: str, starts: str) -> bool:
    """Whether the frames may start: once ``ready`` (logged as ``heard``), or when
    ``wait_for_subscriber`` seconds have gone by without (a warning); ``starts`` names
    what begins. Ends the node's wait when it says yes."""
    if ready:
        node.get_logger().info(f'{heard}: {starts}')
    elif time.monotonic() - node.started_at > node.params['wait_for_subscriber']:
        node.get_logger().warning(
            f'no subscriber after {node.params["wait_for_subscriber"]:g} s: {starts}')
    else:
        return False
    node.waiting = False
    return True
