"""Recorder node: writes every topic of the running graph to a rosbag2 MCAP bag.

It discovers topics as they appear and subscribes to each with raw (CDR) callbacks, so
messages go to the bag as they travelled, with no conversion. Used by `bringup --record`.
"""
import importlib
from pathlib import Path

from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

from activeloc_ros.bag import BagWriter

IGNORED = ('/rosout', '/parameter_events')


def message_class(msgtype: str):
    package, kind, name = msgtype.split('/')
    return getattr(importlib.import_module(f'{package}.{kind}'), name)


class RecorderNode(Node):
    def __init__(self, path: Path, **kwargs):
        super().__init__('recorder', **kwargs)
        self.writer = BagWriter(path)
        self.path = Path(path)
        self.counts: dict[str, int] = {}
        self.subs = {}
        self.timer = self.create_timer(0.25, self.discover)
        self.get_logger().info(f'recording to {path}')

    def discover(self) -> None:
        for topic, types in self.get_topic_names_and_types():
            if topic in self.subs or topic in IGNORED or not types:
                continue
            try:
                cls = message_class(types[0])
            except (ImportError, AttributeError, ValueError):
                self.get_logger().warning(f'cannot record {topic}: unknown type {types[0]}')
                self.subs[topic] = None
                continue
            self.writer.add_topic(topic, types[0])
            self.counts[topic] = 0
            qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
            self.subs[topic] = self.create_subscription(
                cls, topic, lambda data, topic=topic: self.on_message(topic, data), qos, raw=True)

    def on_message(self, topic: str, data: bytes) -> None:
        self.writer.write_cdr(topic, self.get_clock().now().nanoseconds, data)
        self.counts[topic] += 1

    def close(self) -> None:
        self.writer.close()
