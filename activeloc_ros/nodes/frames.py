"""
What the three nodes that publish camera frames (camera, sim, tracking) do alike: publish
a picture with its camera info, hold the first one back until its readers are up, and, for
the two worlds, wire lockstep's clock and answers.

Each node has ``params`` (``encoding``, ``frame_id``, ``min_subscribers``,
``wait_for_subscriber``; a world also ``lockstep_timeout`` and
``lockstep_command_timeout``), ``image_pub``, ``info_pub``, ``published``, ``started_at``
and ``waiting``; a world also ``_lock`` and ``command_sub``; a node that plays a stream
(camera, sim) also ``playback``, ``timer``, ``finished``, ``failure`` and ``finish(why)``.
"""
import time

from geometry_msgs.msg import PointStamped
from rclpy.qos import (
    qos_check_compatible, QoSCompatibility, QoSProfile, ReliabilityPolicy)
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import Image

from activeloc_ros.images import rgb_to_image_fields
from activeloc_ros.nodes.lockstep import Lockstep
from activeloc_ros.nodes.messages import camera_info, stamp_ns

RELIABLE = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)


def publish_frame(node, rgb, stamp, k):
    """
    Publish ``rgb`` on camera/image_raw and its pinhole ``k`` on camera/camera_info, both
    stamped ``stamp``, and count it; returns the header they share.
    """
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


def end_playback(node, what: str) -> None:
    """
    End the frames: the node's ``playback`` has no more.

    A stream that ran out calls the node's ``finish`` with ``end of <what>``; one that
    failed stops with the error, which ``failure`` keeps (``run`` then exits 1).
    """
    node.failure = node.playback.ended(node.published)
    if node.failure is None:
        node.finish(f'end of {what}')
        return
    node.finished = True
    node.timer.cancel()
    node.get_logger().error(f'{what} failed after {node.published} frames: {node.failure}')


def images_heard(node) -> bool:
    """Whether as many readers as ``min_subscribers`` take the pictures."""
    return node.image_pub.get_subscription_count() >= node.params['min_subscribers']


def lockstep_wiring(node, state_type, state_topic: str) -> Lockstep:
    """
    Wire a world's side of lockstep, and return its ``Lockstep``.

    The node publishes ``/clock`` and hears perception's locations, the controller's
    ``action_location/ignored`` and the echo of the world's own state on ``state_topic``,
    each fed to the ``Lockstep`` under ``node._lock``.
    """
    step = Lockstep(timeout=node.params['lockstep_timeout'],
                    command_timeout=node.params['lockstep_command_timeout'])

    def feed(call):
        def callback(msg) -> None:
            with node._lock:
                call(stamp_ns(msg.header.stamp))
        return callback

    node.clock_pub = node.create_publisher(ClockMsg, '/clock', RELIABLE)
    node.location_sub = node.create_subscription(
        PointStamped, 'action_location',
        feed(lambda t_ns: step.on_location(t_ns, time.monotonic())), RELIABLE)
    node.ignored_sub = node.create_subscription(
        PointStamped, 'action_location/ignored', feed(step.on_ignored), RELIABLE)
    node.create_subscription(state_type, state_topic, feed(step.on_state), RELIABLE)
    return step


def readers_matched(node, publisher) -> bool:
    """
    Say whether a message ``publisher`` sends now reaches every reader of its topic.

    Every reader the graph shows counts, but those whose QoS can never match it.
    """
    readers = node.get_subscriptions_info_by_topic(publisher.topic_name)
    can_match = sum(
        qos_check_compatible(publisher.qos_profile, reader.qos_profile)[0]
        != QoSCompatibility.ERROR for reader in readers)
    return publisher.get_subscription_count() >= can_match


def lockstep_graph_up(node, state_pub, *others) -> bool:
    """
    Say whether a world in lockstep may send its first frame.

    The pictures have their readers; perception and the controller, which lockstep waits
    for at every frame, publish what the node listens to; and the world's state
    (``state_pub``), its camera info and ``others`` reach the controller: the state has a
    reader besides the node's own echo, and every reader the graph shows is matched.
    Otherwise the controller could miss the first frame's state or camera info and answer
    that frame late, or not at all.
    """
    return (images_heard(node) and node.command_sub.get_publisher_count() > 0
            and node.ignored_sub.get_publisher_count() > 0
            and node.location_sub.get_publisher_count() > 0
            and state_pub.get_subscription_count() >= 2
            and all(readers_matched(node, p) for p in (state_pub, node.info_pub, *others)))


def may_start(node, ready: bool, heard: str, starts: str) -> bool:
    """
    Whether the frames may start: once ``ready`` (logged as ``heard``), or when
    ``wait_for_subscriber`` seconds have gone by without (a warning); ``starts`` names
    what begins. Ends the node's wait when it says yes.
    """
    if ready:
        node.get_logger().info(f'{heard}: {starts}')
    elif time.monotonic() - node.started_at > node.params['wait_for_subscriber']:
        node.get_logger().warning(
            f'no subscriber after {node.params["wait_for_subscriber"]:g} s: {starts}')
    else:
        return False
    node.waiting = False
    return True
