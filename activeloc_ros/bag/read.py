"""
Read MCAP bags: a rosbag2 folder (metadata.yaml + .mcap) or a bare .mcap file, with the
`mcap` library directly (no ROS install needed): their facts, their image topic, their
messages deserialised with the Jazzy typestore.
"""
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

from mcap.exceptions import McapError
from mcap.reader import make_reader

from activeloc_ros.errors import SourceError

IMAGE_TYPES = ('sensor_msgs/msg/Image', 'sensor_msgs/msg/CompressedImage')
CAMERA_INFO_TYPE = 'sensor_msgs/msg/CameraInfo'


def typestore():
    from rosbags.typesys import get_typestore, Stores
    return get_typestore(Stores.ROS2_JAZZY)


@dataclass
class TopicFacts:
    name: str
    msgtype: str
    count: int


@dataclass
class BagFacts:
    path: Path
    files: list[Path]
    size_bytes: int
    start_ns: int
    end_ns: int
    topics: list[TopicFacts] = field(default_factory=list)

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) / 1e9

    @property
    def message_count(self) -> int:
        return sum(t.count for t in self.topics)

    def image_topics(self) -> list[TopicFacts]:
        return [t for t in self.topics if t.msgtype in IMAGE_TYPES and t.count > 0]


def mcap_files(path: Path) -> list[Path]:
    """The .mcap files of a bag given as a rosbag2 folder or a single file."""
    path = Path(path)
    if not path.exists():
        raise SourceError(f'bag not found: {path}')
    if path.is_dir():
        files = sorted(path.glob('*.mcap'))
        if not files:
            raise SourceError(f'bag folder {path} holds no .mcap file')
        return files
    if path.suffix != '.mcap':
        raise SourceError(f'not an MCAP bag (expected a .mcap file or a rosbag2 folder): {path}')
    return [path]


READER_ERRORS = (McapError, OSError, ValueError, EOFError, KeyError, IndexError)


def reindex_hint(path: Path) -> str:
    """What to run on a bag whose writer was cut off."""
    return f'if its recording was cut off, `python -m activeloc_ros.bag reindex {path}` ' \
           'makes it readable again'


def bag_facts(path: Path) -> BagFacts:
    """Read a bag's summary: topics, types, counts, time span. Raises SourceError if unusable."""
    files = mcap_files(path)
    counts: dict[tuple[str, str], int] = {}
    start, end = None, None
    for file in files:
        if file.stat().st_size == 0:
            raise SourceError(f'bag file is empty: {file}')
        try:
            with open(file, 'rb') as stream:
                summary = make_reader(stream).get_summary()
                if summary is None or summary.statistics is None:
                    raise SourceError(f'bag file has no summary (truncated or corrupt?): {file}; '
                                      f'{reindex_hint(path)}')
                stats = summary.statistics
                for channel_id, channel in summary.channels.items():
                    schema = summary.schemas.get(channel.schema_id)
                    key = (channel.topic, schema.name if schema else '')
                    counts[key] = counts.get(key, 0) + stats.channel_message_counts.get(
                        channel_id, 0)
                if stats.message_count:
                    start = stats.message_start_time if start is None else min(
                        start, stats.message_start_time)
                    end = stats.message_end_time if end is None else max(
                        end, stats.message_end_time)
        except READER_ERRORS as exc:
            raise SourceError(f'cannot read bag file {file}: {type(exc).__name__}: {exc}; '
                              f'{reindex_hint(path)}') from exc
    topics = [TopicFacts(name, msgtype, count)
              for (name, msgtype), count in sorted(counts.items())]
    return BagFacts(Path(path), files, sum(f.stat().st_size for f in files),
                    start or 0, end or 0, topics)


def choose_image_topic(facts: BagFacts, topic: str = '') -> TopicFacts:
    """The image topic to replay: the one asked for, or the only/first one in the bag."""
    images = facts.image_topics()
    if topic:
        for candidate in images:
            if candidate.name == topic:
                return candidate
        raise SourceError(f'bag {facts.path} has no image messages on {topic!r} '
                          f'(image topics: {[t.name for t in images] or "none"})')
    if not images:
        raise SourceError(f'bag {facts.path} has no image topic '
                          f'({", ".join(IMAGE_TYPES)}); topics: '
                          f'{[t.name for t in facts.topics] or "none"}')
    return images[0]


def read_messages(path: Path, topics: list[str], *, skipped: Counter | None = None
                  ) -> Iterator[tuple[str, str, int, object]]:
    """
    Yield (topic, msgtype, log_time_ns, message) in log-time order, deserialised.

    A message whose bytes do not deserialise is counted in ``skipped`` (by reason) and the
    rest is read on; without ``skipped`` it ends the reading with a SourceError naming the
    message.
    """
    from rosbags.serde import SerdeError
    store = typestore()
    for file in mcap_files(path):
        try:
            with open(file, 'rb') as stream:
                reader = make_reader(stream)
                for schema, channel, message in reader.iter_messages(topics=topics,
                                                                     log_time_order=True):
                    try:
                        msg = store.deserialize_cdr(message.data, schema.name)
                    except SerdeError as exc:
                        reason = f'corrupt {schema.name} message on {channel.topic}'
                        if skipped is None:
                            raise SourceError(f'{file}: {reason} at log time '
                                              f'{message.log_time / 1e9:.3f} s: {exc}') from exc
                        skipped[reason] += 1
                        continue
                    yield channel.topic, schema.name, message.log_time, msg
        except READER_ERRORS as exc:
            raise SourceError(f'cannot read bag file {file}: {type(exc).__name__}: {exc}; '
                              f'{reindex_hint(file)}') from exc


def format_facts(facts: BagFacts) -> str:
    """The facts `ros2 bag info` prints, in its layout."""
    from datetime import datetime, timezone

    def when(ns):
        stamp = datetime.fromtimestamp(ns / 1e9, tz=timezone.utc)
        return f'{stamp:%b %d %Y %H:%M:%S.%f}'[:-3] + f' ({ns / 1e9:.9f})'

    lines = [
        f'Files:             {", ".join(f.name for f in facts.files)}',
        f'Bag size:          {facts.size_bytes / 2**20:.1f} MiB',
        'Storage id:        mcap',
        f'Duration:          {facts.duration_s:.3f}s',
        f'Start:             {when(facts.start_ns)}',
        f'End:               {when(facts.end_ns)}',
        f'Messages:          {facts.message_count}',
    ]
    for i, topic in enumerate(facts.topics):
        head = 'Topic information: ' if i == 0 else '                   '
        lines.append(f'{head}Topic: {topic.name} | Type: {topic.msgtype} | '
                     f'Count: {topic.count} | Serialization Format: cdr')
    return '\n'.join(lines)
