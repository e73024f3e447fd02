"""
Recover a bag whose writer died (killed, disk full): it has no index and no
metadata.yaml. `reindex` keeps its complete chunks and writes both, as `ros2 bag reindex`
does, and moves the bytes of the chunk the writer left unfinished to `<file>.incomplete`.
"""
from dataclasses import dataclass, field
from io import BytesIO
import os
from pathlib import Path
import struct

from mcap.data_stream import ReadDataStream, RecordBuilder
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import (
    Channel, Chunk, ChunkIndex, DataEnd, Footer, MessageIndex, Metadata, MetadataIndex, Schema,
    Statistics, SummaryOffset)
from mcap.stream_reader import get_chunk_data_stream

from activeloc_ros.bag.read import mcap_files, READER_ERRORS, typestore
from activeloc_ros.errors import SourceError
from activeloc_ros.paths import write_atomic


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
    """
    Read `file` record by record up to its data section's end, or to the first record
    that is incomplete or damaged; collect what an index of the sound part needs.
    """
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
    store = typestore()
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
    """
    Cut `file` to its sound part, then append the newest chunk's message indexes,
    rosbag2's metadata record, the summary and the footer.
    """
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
    """
    Copy the bytes of `file` from `start` on, which `reindex` cuts off, to a file beside
    it (not read as part of the bag), so that nothing the writer left is lost.
    """
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
    """
    Make a bag readable again after its writer died: each .mcap file without an index is
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
