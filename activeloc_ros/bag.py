"""MCAP bags: read image streams, write rosbag2 MCAP bags, print their facts, make the sample.

Reading uses the `mcap` library directly, so both a rosbag2 folder (metadata.yaml + .mcap)
and a bare .mcap file work; writing uses `rosbags`, which writes the rosbag2 metadata that
`ros2 bag info` and `rosbags` read back. No ROS install is needed for any of it.
A bag whose writer died (killed, disk full) has no index and no metadata.yaml; `reindex`
keeps its complete chunks and writes both, as `ros2 bag reindex` does, and moves the bytes
of the chunk the writer left unfinished to `<file>.incomplete` beside the bag.

    python -m activeloc_ros.bag info PATH
    python -m activeloc_ros.bag reindex PATH
    python -m activeloc_ros.bag make-sample [--video FILE] [--out DIR]
"""
import argparse
from collections import Counter
from dataclasses import dataclass, field
from io import BytesIO
import os
from pathlib import Path
import shutil
import struct
import subprocess
import sys
import tempfile
from typing import Callable, Iterator

from mcap.data_stream import ReadDataStream, RecordBuilder
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import (
    Channel, Chunk, ChunkIndex, DataEnd, Footer, MessageIndex, Metadata, MetadataIndex, Schema,
    Statistics, SummaryOffset)
from mcap.stream_reader import get_chunk_data_stream
import numpy as np

from activeloc_ros.errors import ActivelocError, SourceError
from activeloc_ros.paths import file_sha256, write_atomic

IMAGE_TYPES = ('sensor_msgs/msg/Image', 'sensor_msgs/msg/CompressedImage')
CAMERA_INFO_TYPE = 'sensor_msgs/msg/CameraInfo'


def _typestore():
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
    """Yield (topic, msgtype, log_time_ns, message) in log-time order, deserialised.

    A message whose bytes do not deserialise is counted in ``skipped`` (by reason) and the
    rest is read on; without ``skipped`` it ends the reading with a SourceError naming the
    message."""
    from rosbags.serde import SerdeError
    store = _typestore()
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


class RecordingError(ActivelocError):
    """A bag could not be written (disk full, read-only, path under a file...)."""


class BagWriter:
    """Write CDR messages to a rosbag2 MCAP bag (a folder with metadata.yaml).

    A write error (a full disk...) ends the recording, not the program: the bag is cut back
    to its last complete chunk and indexed, so it reads up to the error, and RecordingError
    says what happened. Every later write is refused with the same error.

    :param wrap_stream: wraps the open .mcap file object (tests: a disk that fills up).
    """

    def __init__(self, path: Path, *, wrap_stream: Callable | None = None):
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.rosbag2.errors import WriterError
        self.path = Path(path)
        if self.path.exists():
            raise SourceError(f'will not overwrite existing bag {self.path}')
        self._store = _typestore()
        self._writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        try:
            self._writer.open()
        except (OSError, WriterError) as exc:
            raise RecordingError(f'cannot create bag {self.path}: {exc}') from exc
        if wrap_stream is not None:
            self._writer.storage.bio = wrap_stream(self._writer.storage.bio)
        self._connections: dict[str, object] = {}
        self.error: RecordingError | None = None
        self.closed = False
        # after a write error: the messages the bag still holds, a topic (None: unknown)
        self.held: dict[str, int] | None = None

    def add_topic(self, topic: str, msgtype: str) -> None:
        if topic not in self._connections:
            self._connections[topic] = self._writer.add_connection(
                topic, msgtype, typestore=self._store)

    def write_cdr(self, topic: str, stamp_ns: int, data: bytes) -> None:
        if self.error is not None:
            raise self.error
        try:
            self._writer.write(self._connections[topic], stamp_ns, data)
        except OSError as exc:
            self._fail(exc)
            raise self.error from exc

    def write(self, topic: str, msgtype: str, stamp_ns: int, message) -> None:
        """Write a rosbags-typestore message object."""
        self.add_topic(topic, msgtype)
        self.write_cdr(topic, stamp_ns, self._store.serialize_cdr(message, msgtype))

    @property
    def store(self):
        return self._store

    def close(self) -> None:
        """Finish the bag (index, metadata.yaml). Raises RecordingError if it could not be
        finished as written; the bag then holds what reached the disk before the error."""
        if self.closed:
            if self.error is not None:
                raise self.error
            return
        try:
            self._writer.close()
            self.closed = True
        except OSError as exc:
            self._fail(exc)
            raise self.error from exc

    def _fail(self, exc: OSError) -> None:
        """Stop writing; keep what is on disk up to the last complete chunk, indexed."""
        self.closed = True
        try:
            self._writer.abort()        # closes the file; flushing what is buffered may fail
        except OSError:
            pass
        problem = f'writing bag {self.path} failed: {exc.strerror or exc}'
        try:
            report = reindex(self.path)
        except (OSError, SourceError) as again:
            self.error = RecordingError(
                f'{problem}; it could not be closed either ({again}): run '
                f'`python -m activeloc_ros.bag reindex {self.path}` once there is room')
        else:
            self.held = report.topics
            self.error = RecordingError(f'{problem}; the bag was closed at the last complete '
                                        f'chunk and holds {report.messages} messages')


# --- Recovering a bag whose writer died -------------------------------------------------
MAGIC = b'\x89MCAP0\r\n'
_RECORD_HEAD = struct.Struct('<BQ')      # opcode, length
_MESSAGE_HEAD = struct.Struct('<HIQQ')   # channel id, sequence, log time, publish time


@dataclass
class _ChunkScan:
    index: ChunkIndex
    messages: dict[int, list[tuple[int, int]]]     # channel id -> [(log time, offset)]


@dataclass
class McapScan:
    """What a sequential read of an .mcap file found before its end or its first damage."""
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    chunks: list[_ChunkScan] = field(default_factory=list)
    metadata: list[MetadataIndex] = field(default_factory=list)
    counts: dict[int, int] = field(default_factory=dict)
    start_ns: int | None = None
    end_ns: int | None = None
    keep_bytes: int = len(MAGIC)    # the sound prefix: complete records only
    reindex_last: bool = False      # the newest chunk's message indexes are written again


def _take_definition(opcode: int, body: bytes, scan: 'McapScan') -> bool:
    """Keep a Schema or Channel record (inside or outside chunks); False for others."""
    if opcode == Opcode.SCHEMA:
        schema = Schema.read(ReadDataStream(BytesIO(body)))
        scan.schemas[schema.id] = schema
    elif opcode == Opcode.CHANNEL:
        channel = Channel.read(ReadDataStream(BytesIO(body)))
        scan.channels[channel.id] = channel
    else:
        return False
    return True


def _scan_chunk(record: Chunk, start: int, length: int, scan: McapScan) -> _ChunkScan:
    stream, size = get_chunk_data_stream(record)
    data = stream.read(size)
    messages: dict[int, list[tuple[int, int]]] = {}
    pos = 0
    while pos + _RECORD_HEAD.size <= size:
        opcode, body_len = _RECORD_HEAD.unpack_from(data, pos)
        body = data[pos + _RECORD_HEAD.size:pos + _RECORD_HEAD.size + body_len]
        if len(body) != body_len:
            raise McapError('record runs past the end of its chunk')
        if _take_definition(opcode, body, scan):
            pass
        elif opcode == Opcode.MESSAGE:
            channel_id, _, log_time, _ = _MESSAGE_HEAD.unpack_from(body)
            messages.setdefault(channel_id, []).append((log_time, pos))
        pos += _RECORD_HEAD.size + body_len
    index = ChunkIndex(chunk_length=length, chunk_start_offset=start,
                       compression=record.compression, compressed_size=len(record.data),
                       message_end_time=record.message_end_time, message_index_length=0,
                       message_index_offsets={}, message_start_time=record.message_start_time,
                       uncompressed_size=record.uncompressed_size)
    return _ChunkScan(index, messages)


def scan_mcap(file: Path) -> McapScan:
    """Read `file` record by record up to its data section's end, or to the first record
    that is incomplete or damaged; collect what an index of the sound part needs."""
    scan = McapScan()
    size = file.stat().st_size
    open_run = False    # the newest chunk's message indexes may still be cut short
    with open(file, 'rb') as stream:
        if stream.read(len(MAGIC)) != MAGIC:
            raise SourceError(f'not an MCAP file (bad magic): {file}')
        pos = len(MAGIC)
        while pos + _RECORD_HEAD.size <= size:
            stream.seek(pos)
            opcode, length = _RECORD_HEAD.unpack(stream.read(_RECORD_HEAD.size))
            end = pos + _RECORD_HEAD.size + length
            if end > size or opcode in (Opcode.DATA_END, Opcode.FOOTER):
                break
            body = stream.read(length)
            try:
                if opcode == Opcode.CHUNK:
                    chunk = _scan_chunk(Chunk.read(ReadDataStream(BytesIO(body))), pos,
                                        end - pos, scan)
                    scan.chunks.append(chunk)
                elif opcode == Opcode.MESSAGE_INDEX and scan.chunks:
                    channel_id = struct.unpack_from('<H', body)[0]
                    index = scan.chunks[-1].index
                    index.message_index_offsets[channel_id] = pos
                    index.message_index_length += end - pos
                elif _take_definition(opcode, body, scan):
                    pass
                elif opcode == Opcode.METADATA:
                    name = Metadata.read(ReadDataStream(BytesIO(body))).name
                    scan.metadata.append(MetadataIndex(offset=pos, length=end - pos, name=name))
                elif opcode not in (Opcode.HEADER, Opcode.ATTACHMENT):
                    break       # a summary record: the data section ended
            except (McapError, struct.error, ValueError, KeyError, EOFError):
                break           # a damaged record ends the sound part, as truncation does
            open_run = opcode in (Opcode.CHUNK, Opcode.MESSAGE_INDEX)
            pos = scan.keep_bytes = end
    if open_run:
        # keep the newest chunk, write its message indexes again after it
        last = scan.chunks[-1].index
        scan.keep_bytes = last.chunk_start_offset + last.chunk_length
        last.message_index_offsets, last.message_index_length = {}, 0
        scan.reindex_last = True
    times = [t for chunk in scan.chunks for entries in chunk.messages.values()
             for t, _ in entries]
    if times:
        scan.start_ns, scan.end_ns = min(times), max(times)
    for chunk in scan.chunks:
        for channel_id, entries in chunk.messages.items():
            scan.counts[channel_id] = scan.counts.get(channel_id, 0) + len(entries)
    return scan


def _bag_info_yaml(files: list[tuple[Path, McapScan]], version: int = 9) -> dict:
    """rosbag2's bagfile information for the scanned files (what metadata.yaml holds)."""
    import yaml
    store = _typestore()
    topics: dict[tuple[str, str], dict] = {}
    for _, scan in files:
        for channel_id, channel in scan.channels.items():
            schema = scan.schemas.get(channel.schema_id)
            msgtype = schema.name if schema else ''
            entry = topics.setdefault((channel.topic, msgtype), {'count': 0,
                                                                  'channel': channel})
            entry['count'] += scan.counts.get(channel_id, 0)
    described = []
    for (topic, msgtype), entry in topics.items():
        qos = entry['channel'].metadata.get('offered_qos_profiles', '')
        try:
            digest = store.hash_rihs01(msgtype)
        except (KeyError, ValueError):
            digest = ''
        described.append({'topic_metadata': {
            'name': topic, 'type': msgtype,
            'serialization_format': entry['channel'].message_encoding,
            'offered_qos_profiles': (yaml.safe_load(qos) or []) if version >= 9 else qos,
            'type_description_hash': digest}, 'message_count': entry['count']})
    starts = [scan.start_ns for _, scan in files if scan.start_ns is not None]
    ends = [scan.end_ns for _, scan in files if scan.end_ns is not None]
    start, end = (min(starts), max(ends)) if starts else (0, 0)
    return {
        'version': version, 'storage_identifier': 'mcap',
        'relative_file_paths': [file.name for file, _ in files],
        'duration': {'nanoseconds': end - start},
        'starting_time': {'nanoseconds_since_epoch': start},
        'message_count': sum(sum(scan.counts.values()) for _, scan in files),
        'topics_with_message_count': described,
        'compression_format': '', 'compression_mode': '',
        'files': [{'path': file.name,
                   'starting_time': {'nanoseconds_since_epoch': scan.start_ns or 0},
                   'duration': {'nanoseconds': (scan.end_ns or 0) - (scan.start_ns or 0)},
                   'message_count': sum(scan.counts.values())} for file, scan in files],
        'custom_data': None, 'ros_distro': 'rosbags',
    }


def _append_index(file: Path, scan: McapScan, info_yaml: str) -> None:
    """Cut `file` to its sound part, then append the newest chunk's message indexes,
    rosbag2's metadata record, the summary and the footer."""
    base = scan.keep_bytes
    out = RecordBuilder()
    if scan.reindex_last:
        last = scan.chunks[-1]
        for channel_id, entries in sorted(last.messages.items()):
            last.index.message_index_offsets[channel_id] = base + out.count
            MessageIndex(channel_id=channel_id, records=entries).write(out)
        last.index.message_index_length = out.count
    metadata = list(scan.metadata)
    if not any(m.name == 'rosbag2' for m in metadata):
        start = base + out.count
        Metadata(name='rosbag2', metadata={'serialized_metadata': info_yaml}).write(out)
        metadata.append(MetadataIndex(offset=start, length=base + out.count - start,
                                      name='rosbag2'))
    DataEnd(data_section_crc=0).write(out)
    summary_start = base + out.count
    groups = []

    def group(opcode, records):
        start = out.count
        for record in records:
            record.write(out)
        if out.count > start:
            groups.append(SummaryOffset(group_opcode=opcode, group_start=base + start,
                                        group_length=out.count - start))

    group(Opcode.SCHEMA, [scan.schemas[k] for k in sorted(scan.schemas)])
    group(Opcode.CHANNEL, [scan.channels[k] for k in sorted(scan.channels)])
    group(Opcode.CHUNK_INDEX, [chunk.index for chunk in scan.chunks])
    group(Opcode.METADATA_INDEX, metadata)
    group(Opcode.STATISTICS, [Statistics(
        attachment_count=0, channel_count=len(scan.channels),
        channel_message_counts=dict(sorted(scan.counts.items())), chunk_count=len(scan.chunks),
        message_count=sum(scan.counts.values()), message_end_time=scan.end_ns or 0,
        message_start_time=scan.start_ns or 0, metadata_count=len(metadata),
        schema_count=len(scan.schemas))])
    offsets_start = base + out.count
    for offset in groups:
        offset.write(out)
    Footer(summary_start=summary_start, summary_offset_start=offsets_start,
           summary_crc=0).write(out)
    with open(file, 'r+b') as stream:
        stream.truncate(base)
        stream.seek(base)
        stream.write(out.end() + MAGIC)
        stream.flush()
        os.fsync(stream.fileno())


def _keep_tail(file: Path, start: int) -> Path:
    """Copy the bytes of `file` from `start` on, which `reindex` cuts off, to a file beside
    it (not read as part of the bag), so that nothing the writer left is lost."""
    tail = file.with_name(file.name + '.incomplete')
    with open(file, 'rb') as stream:           # at most the chunk being written
        stream.seek(start)
        write_atomic(tail, stream.read())
    with open(tail, 'rb') as stream:           # on disk before the bag is cut back
        os.fsync(stream.fileno())
    return tail


def _indexed(file: Path) -> bool:
    """Whether `file` ends in a summary and footer that a reader can use."""
    try:
        with open(file, 'rb') as stream:
            summary = make_reader(stream).get_summary()
        return summary is not None and summary.statistics is not None
    except READER_ERRORS:
        return False


@dataclass
class ReindexReport:
    messages: int
    lines: list[str]
    unrecovered: list[str]   # files cut short before their first complete chunk
    topics: dict[str, int] = field(default_factory=dict)   # messages the bag holds a topic


def reindex(path: Path) -> ReindexReport:
    """Make a bag readable again after its writer died: each .mcap file without an index is
    cut back to its last complete chunk and indexed; metadata.yaml is written anew. The
    bytes cut off go to `<file>.incomplete` beside it.

    Like `ros2 bag reindex`, it works in place. Raises SourceError if `path` holds no
    MCAP file, OSError if a file cannot be rewritten.
    """
    import yaml
    path = Path(path)
    files, lines, unrecovered = [], [], []
    for file in mcap_files(path):
        scan = scan_mcap(file)
        count = sum(scan.counts.values())
        if _indexed(file):
            lines.append(f'{file.name}: complete, {count} messages')
        else:
            dropped = file.stat().st_size - scan.keep_bytes
            lines.append(f'{file.name}: no index; kept {len(scan.chunks)} complete chunks, '
                         f'{count} messages')
            if dropped:
                if not scan.chunks:
                    unrecovered.append(file.name)
                what = f'{file.name}: the {dropped} bytes after them, an incomplete record,'
                try:
                    lines.append(f'{what} moved to {_keep_tail(file, scan.keep_bytes).name}')
                except OSError as exc:      # a full disk: the readable bag comes first
                    lines.append(f'{what} dropped: they could not be kept ({exc})')
            info = _bag_info_yaml([(file, scan)])
            _append_index(file, scan, yaml.safe_dump(info, sort_keys=False).strip())
        files.append((file, scan))
    if path.is_dir():
        info = {'rosbag2_bagfile_information': _bag_info_yaml(files)}
        tmp = path / 'metadata.yaml.tmp'
        tmp.write_text(yaml.safe_dump(info, sort_keys=False))
        tmp.replace(path / 'metadata.yaml')
        lines.append('metadata.yaml written')
    topics: dict[str, int] = {}
    for _, scan in files:
        for channel, count in scan.counts.items():
            topic = scan.channels[channel].topic
            topics[topic] = topics.get(topic, 0) + count
    return ReindexReport(sum(sum(scan.counts.values()) for _, scan in files), lines,
                         unrecovered, topics)


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


# The sample bag: OpenCV's vtest.avi (pedestrians, 768x576, 10 fps), shipped by Debian's
# opencv-doc package under Apache-2.0 AND BSD-3-Clause.
SAMPLE_DEB = 'opencv-doc'
SAMPLE_MEMBER = './usr/share/doc/opencv-doc/examples/data/vtest.avi'
SAMPLE_SHA256 = '45cddc9490be69345cbdab64ca583be65987e864ca408038e648db99e10516cf'
SAMPLE_TOPIC = '/camera/image_raw/compressed'
SAMPLE_FRAME_ID = 'camera_color_optical_frame'
SAMPLE_START_NS = 1_700_000_000 * 10**9


def fetch_sample_video(workdir: Path) -> Path:
    """Download Debian's opencv-doc and extract vtest.avi (needs apt-get and dpkg-deb)."""
    subprocess.run(['apt-get', 'download', SAMPLE_DEB], cwd=workdir, check=True)
    deb = next(workdir.glob(f'{SAMPLE_DEB}_*.deb'))
    tar = subprocess.run(['dpkg-deb', '--fsys-tarfile', str(deb)], check=True,
                         capture_output=True).stdout
    subprocess.run(['tar', '-x', '-C', str(workdir), SAMPLE_MEMBER], input=tar, check=True)
    video = workdir / SAMPLE_MEMBER
    if file_sha256(video) != SAMPLE_SHA256:
        raise SourceError(f'{video.name} from {deb.name} does not have the expected sha256')
    return video


def replaceable(out: Path) -> bool:
    """May `make_sample` replace ``out``? Only when it is absent or a rosbag2 folder: its
    metadata.yaml and MCAP files, nothing else."""
    if not out.exists():
        return True
    return out.is_dir() and (out / 'metadata.yaml').is_file() and all(
        f.name == 'metadata.yaml' or f.suffix in ('.mcap', '.incomplete') for f in out.iterdir())


def make_sample(video: Path, out: Path, *, frames: int, width: int, quality: int) -> BagFacts:
    """Write `frames` frames of `video`, resized to `width`, as JPEG CompressedImage messages.
    ``out`` is replaced only if it is a bag (`replaceable`); anything else is refused."""
    import cv2
    if frames < 1 or not 16 <= width <= 8192 or not 0 <= quality <= 100:
        raise SourceError(f'need frames >= 1, width in 16..8192 and quality in 0..100, got '
                          f'{frames}, {width} and {quality}')
    if not replaceable(out):
        raise SourceError(f'{out} exists and is not a bag: not replacing it')
    capture = cv2.VideoCapture(str(video))
    if not capture.isOpened():
        raise SourceError(f'cannot open video {video}')
    fps = capture.get(cv2.CAP_PROP_FPS) or 10.0
    tmp = out.with_name(out.name + '.partial')
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        written = _write_sample(capture, BagWriter(tmp), frames=frames, width=width,
                                quality=quality, fps=fps)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)    # no half-made bag left beside ``out``
        raise
    if written == 0:
        shutil.rmtree(tmp, ignore_errors=True)
        raise SourceError(f'no frame could be read from {video}')
    shutil.rmtree(out, ignore_errors=True)
    # rosbags names the storage file after the folder; keep that true after the rename.
    for file in tmp.iterdir():
        if file.name.startswith(tmp.name):
            file.rename(tmp / file.name.replace(tmp.name, out.name, 1))
    metadata = tmp / 'metadata.yaml'
    metadata.write_text(metadata.read_text().replace(tmp.name, out.name))
    tmp.rename(out)
    return bag_facts(out)


def _write_sample(capture, writer: BagWriter, *, frames: int, width: int, quality: int,
                  fps: float) -> int:
    """`make_sample`'s frames into ``writer``, which it closes; how many were written."""
    import cv2
    store = writer.store
    Header = store.types['std_msgs/msg/Header']
    Time = store.types['builtin_interfaces/msg/Time']
    Compressed = store.types['sensor_msgs/msg/CompressedImage']
    written = 0
    while written < frames:
        ok, bgr = capture.read()
        if not ok:
            break
        height = round(bgr.shape[0] * width / bgr.shape[1])
        bgr = cv2.resize(bgr, (width, height), interpolation=cv2.INTER_AREA)
        ok, jpeg = cv2.imencode('.jpg', bgr, [cv2.IMWRITE_JPEG_QUALITY, quality])
        stamp = SAMPLE_START_NS + round(written * 1e9 / fps)
        header = Header(stamp=Time(sec=stamp // 10**9, nanosec=stamp % 10**9),
                        frame_id=SAMPLE_FRAME_ID)
        msg = Compressed(header=header, format='jpeg', data=np.frombuffer(jpeg, np.uint8))
        writer.write(SAMPLE_TOPIC, 'sensor_msgs/msg/CompressedImage', stamp, msg)
        written += 1
    writer.close()
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m activeloc_ros.bag', description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest='command', required=True)
    info = sub.add_parser('info', help='print the facts of a bag (like `ros2 bag info`)')
    info.add_argument('path', type=Path)
    fix = sub.add_parser(
        'reindex', help='make a bag whose recording was cut off (killed, disk full) readable: '
        'keep every complete chunk, write the index and metadata.yaml (in place, like '
        '`ros2 bag reindex`); the unfinished chunk\'s bytes go to <file>.incomplete')
    fix.add_argument('path', type=Path, help='rosbag2 folder or .mcap file')
    sample = sub.add_parser('make-sample', help='(re)make the bundled sample bag')
    sample.add_argument('--video', type=Path,
                        help='source video (default: vtest.avi from Debian opencv-doc)')
    sample.add_argument('--out', type=Path, default=Path('bags/vtest'))
    sample.add_argument('--frames', type=int, default=300)
    sample.add_argument('--width', type=int, default=640)
    sample.add_argument('--quality', type=int, default=75)
    args = parser.parse_args(argv)
    try:
        if args.command == 'info':
            print(format_facts(bag_facts(args.path)))
            return 0
        if args.command == 'reindex':
            report = reindex(args.path)
            print('\n'.join(report.lines))
            print(format_facts(bag_facts(args.path)))
            if report.unrecovered:     # a readable bag, but of nothing that was recorded
                print(f'error: nothing could be recovered from {", ".join(report.unrecovered)}:'
                      ' the recording stopped before its first chunk was complete (its bytes '
                      'are kept in the .incomplete file beside it)', file=sys.stderr)
                return 1
            return 0
        with tempfile.TemporaryDirectory() as workdir:
            video = args.video
            if video is None:
                video = fetch_sample_video(Path(workdir))
            facts = make_sample(video, args.out, frames=args.frames, width=args.width,
                                quality=args.quality)
        print(format_facts(facts))
        return 0
    except (SourceError, RecordingError) as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 1
    except OSError as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 1


if __name__ == '__main__':
    sys.exit(main())
