"""MCAP bags: read image streams, write rosbag2 MCAP bags, print their facts, make the sample.

Reading uses the `mcap` library directly, so both a rosbag2 folder (metadata.yaml + .mcap)
and a bare .mcap file work; writing uses `rosbags`, which writes the rosbag2 metadata that
`ros2 bag info` and `rosbags` read back. No ROS install is needed for any of it.

    python -m activeloc_ros.bag info PATH
    python -m activeloc_ros.bag make-sample [--video FILE] [--out DIR]
"""
import argparse
from dataclasses import dataclass, field
from pathlib import Path
import shutil
import subprocess
import sys
import tempfile
from typing import Iterator

from mcap.exceptions import McapError
from mcap.reader import make_reader
import numpy as np

from activeloc_ros.errors import SourceError
from activeloc_ros.paths import file_sha256

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
                    raise SourceError(f'bag file has no summary (truncated or corrupt?): {file}')
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
            raise SourceError(
                f'cannot read bag file {file}: {type(exc).__name__}: {exc}') from exc
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


def read_messages(path: Path, topics: list[str]) -> Iterator[tuple[str, str, int, object]]:
    """Yield (topic, msgtype, log_time_ns, message) in log-time order, deserialised."""
    store = _typestore()
    for file in mcap_files(path):
        try:
            with open(file, 'rb') as stream:
                reader = make_reader(stream)
                for schema, channel, message in reader.iter_messages(topics=topics,
                                                                     log_time_order=True):
                    msg = store.deserialize_cdr(message.data, schema.name)
                    yield channel.topic, schema.name, message.log_time, msg
        except READER_ERRORS as exc:
            raise SourceError(
                f'cannot read bag file {file}: {type(exc).__name__}: {exc}') from exc


class BagWriter:
    """Write CDR messages to a rosbag2 MCAP bag (a folder with metadata.yaml)."""

    def __init__(self, path: Path):
        from rosbags.rosbag2 import StoragePlugin, Writer
        self.path = Path(path)
        if self.path.exists():
            raise SourceError(f'will not overwrite existing bag {self.path}')
        self._store = _typestore()
        self._writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        self._writer.open()
        self._connections: dict[str, object] = {}

    def add_topic(self, topic: str, msgtype: str) -> None:
        if topic not in self._connections:
            self._connections[topic] = self._writer.add_connection(
                topic, msgtype, typestore=self._store)

    def write_cdr(self, topic: str, stamp_ns: int, data: bytes) -> None:
        self._writer.write(self._connections[topic], stamp_ns, data)

    def write(self, topic: str, msgtype: str, stamp_ns: int, message) -> None:
        """Write a rosbags-typestore message object."""
        self.add_topic(topic, msgtype)
        self.write_cdr(topic, stamp_ns, self._store.serialize_cdr(message, msgtype))

    @property
    def store(self):
        return self._store

    def close(self) -> None:
        self._writer.close()


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


def make_sample(video: Path, out: Path, *, frames: int, width: int, quality: int) -> BagFacts:
    """Write `frames` frames of `video`, resized to `width`, as JPEG CompressedImage messages."""
    import cv2
    capture = cv2.VideoCapture(str(video))
    if not capture.isOpened():
        raise SourceError(f'cannot open video {video}')
    fps = capture.get(cv2.CAP_PROP_FPS) or 10.0
    tmp = out.with_name(out.name + '.partial')
    shutil.rmtree(tmp, ignore_errors=True)
    writer = BagWriter(tmp)
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m activeloc_ros.bag', description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest='command', required=True)
    info = sub.add_parser('info', help='print the facts of a bag (like `ros2 bag info`)')
    info.add_argument('path', type=Path)
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
        with tempfile.TemporaryDirectory() as workdir:
            video = args.video
            if video is None:
                video = fetch_sample_video(Path(workdir))
            facts = make_sample(video, args.out, frames=args.frames, width=args.width,
                                quality=args.quality)
        print(format_facts(facts))
        return 0
    except SourceError as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 1


if __name__ == '__main__':
    sys.exit(main())
