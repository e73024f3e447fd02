"""
Recorder node: writes every topic of the running graph to a rosbag2 MCAP bag.

It discovers topics as they appear and subscribes to each with raw (CDR) callbacks, so
messages go to the bag as they travelled, with no conversion. Used by `bringup --record`.
In a namespace (`--ros-args -r __ns:=/robot1`) it records that namespace's topics only,
so robots that share a network keep their bags apart.

Every message counts: each subscription keeps a deep queue (the perception's depth 1 is for
perception, which wants the newest frame) and is reliable unless a publisher offers only
best effort, which a reliable subscription would not hear. A write error (a full disk)
ends the recording, not the graph: the bag is closed at its last complete chunk, `error`
says what happened and bringup stops the run with that reason.
"""
from pathlib import Path
import threading

from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosbags.typesys import TypesysError

from activeloc_ros.bag.write import BagWriter, RecordingError
from activeloc_ros.nodes.messages import message_class
from activeloc_ros.nodes.qos import offered_reliability

IGNORED = ('/rosout', '/parameter_events')
QUEUE_DEPTH = 100       # messages a subscription holds while the writer is busy


def in_namespace(topic: str, namespace: str) -> bool:
    return namespace == '/' or topic.startswith(namespace.rstrip('/') + '/')


class RecorderNode(Node):
    """
    :param expected: topics (name -> type) subscribed at once, reliably, before their
        publishers exist, so that not even their first message is missed; other topics are
        found as they appear.
    """

    def __init__(self, path: Path, *, expected: dict[str, str] | None = None,
                 wrap_stream=None, **kwargs):
        super().__init__('recorder', **kwargs)
        self.path = Path(path)
        self.writer = BagWriter(self.path, wrap_stream=wrap_stream)
        self.lock = threading.Lock()     # callbacks and close() come from different threads
        self.counts: dict[str, int] = {}
        self.unrecorded: dict[str, str] = {}   # topic -> why it is not in the bag
        self.subs = {}
        self.error: RecordingError | None = None
        for name, msgtype in (expected or {}).items():
            self.subscribe(self.resolve_topic_name(name), msgtype, ReliabilityPolicy.RELIABLE)
        self.timer = self.create_timer(0.25, self.discover)
        self.get_logger().info(f'recording to {path}')

    def discover(self) -> None:
        for topic, types in self.get_topic_names_and_types():
            if (topic in self.subs or topic in IGNORED or not types
                    or not in_namespace(topic, self.get_namespace())):
                continue
            self.subscribe(topic, types[0], offered_reliability(self, topic))

    def subscribe(self, topic: str, msgtype: str, reliability: ReliabilityPolicy) -> None:
        try:
            cls = message_class(msgtype)
        except (ImportError, AttributeError, ValueError):
            self._cannot_record(topic, f'unknown type {msgtype}')
            return
        with self.lock:
            if self.error is not None or self.writer.closed:
                return
            try:
                self.writer.add_topic(topic, msgtype)
            except TypesysError as exc:     # a type rosbags has no definition of
                self._cannot_record(topic, f"{msgtype} is not among the bag's types ({exc})")
                return
            self.counts[topic] = 0
        self.subs[topic] = self.create_subscription(
            cls, topic, lambda data, topic=topic: self.on_message(topic, data),
            QoSProfile(depth=QUEUE_DEPTH, reliability=reliability), raw=True)

    def _cannot_record(self, topic: str, why: str) -> None:
        """Leave ``topic`` out, once, and say so (bringup's summary names it too)."""
        self.get_logger().warning(f'cannot record {topic}: {why}')
        self.subs[topic] = None
        self.unrecorded[topic] = why

    def on_message(self, topic: str, data: bytes) -> None:
        with self.lock:
            if self.error is not None or self.writer.closed:
                return
            try:
                self.writer.write_cdr(topic, self.get_clock().now().nanoseconds, data)
            except RecordingError as exc:
                self._failed(exc)
                return
            self.counts[topic] += 1

    def close(self) -> None:
        """Finish the bag; a failure is kept in `error`, not raised."""
        with self.lock:
            if self.error is not None:
                return
            try:
                self.writer.close()
            except RecordingError as exc:
                self._failed(exc)

    def _failed(self, exc: RecordingError) -> None:
        """
        The recording ended on an error: count what the bag holds, not what was sent to
        it (a full disk loses the chunk being written).
        """
        self.error = exc
        self.get_logger().error(str(exc))
        held = self.writer.held
        self.counts = {t: (held or {}).get(t, 0) for t in self.counts} if held is not None \
            else {}
