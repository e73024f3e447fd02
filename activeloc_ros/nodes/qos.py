"""
Which reliability a subscription needs to hear the publishers of a topic.

A RELIABLE subscription never hears a BEST_EFFORT publisher (a camera driver with
SensorDataQoS), while a BEST_EFFORT subscription hears both but, over Fast DDS, loses most
large samples (a 640x480 image) even on one machine. So the subscriber follows what the
publishers offer, as ``ros2 bag record`` does: reliable unless one of them offers best
effort only. Used by the recorder and the perception node.
"""
from typing import Iterable

from rclpy.qos import ReliabilityPolicy


def matching_reliability(offered: Iterable[ReliabilityPolicy]) -> ReliabilityPolicy:
    """The reliability that hears every publisher offering `offered` (reliable if none)."""
    if ReliabilityPolicy.BEST_EFFORT in set(offered):
        return ReliabilityPolicy.BEST_EFFORT
    return ReliabilityPolicy.RELIABLE


def offered_reliability(node, topic: str) -> ReliabilityPolicy:
    """`matching_reliability` for the publishers `node` sees on `topic` now."""
    return matching_reliability(info.qos_profile.reliability
                                for info in node.get_publishers_info_by_topic(topic))
