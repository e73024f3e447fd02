"""
Camera sources, ROS-free: bags, videos, image folders, OpenCV devices and RealSense.

A source yields Frames (RGB uint8, a time stamp in seconds and an index). Recorded sources
(`live = False`) are replayed at their recorded timing by a Pacer; live ones deliver frames
as the device does. `open_source(spec)` parses the spec strings the camera node accepts:

    bag:PATH        an MCAP bag (rosbag2 folder or .mcap file) with an Image or
                    CompressedImage topic
    video:PATH      any video OpenCV decodes
    folder:PATH     the images of a folder, sorted by name
    device:N        OpenCV capture device N
    realsense       the colour stream of an Intel RealSense (pyrealsense2)

`open_scene(scene)` opens what the simulated world's virtual screen shows (the sim node):
bag:PATH, video:PATH, folder:PATH, an annotated sequence folder (with meta.json) or the
name of a sequence in the data root (`data.resolve_data_root`).
"""
from collections import Counter
from dataclasses import dataclass
import math
from pathlib import Path
from typing import Callable, Iterator

import cv2
import numpy as np

from activeloc_ros import data, metrics
from activeloc_ros.bag.read import (
    bag_facts, CAMERA_INFO_TYPE, choose_image_topic, IMAGE_TYPES, read_messages)
from activeloc_ros.errors import DataError, FrameError, SourceError
from activeloc_ros.images import decode_compressed, image_to_rgb
from activeloc_ros.paths import share_path
from activeloc_ros.world import frame_time

IMAGE_SUFFIXES = ('.jpg', '.jpeg', '.png', '.bmp', '.ppm', '.pgm', '.tif', '.tiff', '.webp')
DEFAULT_SCENE_FPS = 10.0     # a scene that knows no rate of its own (a bag of one frame)
SCENE_KINDS = ('bag', 'video', 'folder')
SCENE_HELP = ('bag:PATH, video:PATH, folder:PATH, SEQUENCE_DIR (with meta.json) or NAME (a '
              'sequence in the data root)')


@dataclass
class Frame:
    rgb: np.ndarray   # (H, W, 3) uint8
    stamp: float      # seconds on the source's clock (recorded or capture time)
    index: int


def pinhole_matrix(width: int, height: int, hfov_deg: float) -> np.ndarray:
    """K of an ideal pinhole camera with square pixels and the given horizontal field of view."""
    fx = metrics.focal_from_fov(width, hfov_deg)
    return np.array([[fx, 0.0, width / 2.0], [0.0, fx, height / 2.0], [0.0, 0.0, 1.0]])


class Source:
    """Base of all sources. `read()` returns the next Frame or None at the end of the stream."""

    live = False
    fps: float | None = None

    def __init__(self):
        # problems with frames that were skipped, by message (the node logs each kind once)
        self.skipped = Counter()

    def read(self) -> Frame | None:
        raise NotImplementedError

    def rewind(self) -> None:
        raise SourceError(f'{type(self).__name__} cannot loop')

    def camera_matrix(self) -> np.ndarray | None:
        """Intrinsics the source itself knows (recorded CameraInfo, device SDK), else None."""
        return None

    def close(self) -> None:
        pass


class BagSource(Source):

    def __init__(self, path: Path, *, topic: str = ''):
        super().__init__()
        self.facts = bag_facts(path)
        self.topic = choose_image_topic(self.facts, topic)
        self.path = Path(path)
        self._k = self._recorded_camera_matrix()
        # the mean recorded rate (the virtual screen shows the frames at it)
        duration = self.facts.duration_s
        if self.topic.count > 1 and duration > 0:
            self.fps = round((self.topic.count - 1) / duration, 3)
        self.rewind()

    def _recorded_camera_matrix(self) -> np.ndarray | None:
        infos = [t.name for t in self.facts.topics
                 if t.msgtype == CAMERA_INFO_TYPE and t.count > 0]
        for _, _, _, msg in read_messages(self.path, infos[:1]):
            k = np.asarray(msg.k, dtype=float).reshape(3, 3)
            if k[0, 0] > 0 and k[1, 1] > 0:
                return k
        return None

    def rewind(self) -> None:
        self.close()
        self._messages: Iterator = read_messages(self.path, [self.topic.name],
                                                 skipped=self.skipped)
        self._index = 0

    def close(self) -> None:
        if getattr(self, '_messages', None) is not None:
            self._messages.close()

    def read(self) -> Frame | None:
        for _, msgtype, log_ns, msg in self._messages:
            if msgtype not in IMAGE_TYPES:     # a topic may carry more than one type
                self.skipped[f'not an image: {msgtype}'] += 1
                continue
            try:
                if msgtype == 'sensor_msgs/msg/CompressedImage':
                    rgb = decode_compressed(msg.format, msg.data.tobytes())
                else:
                    rgb = image_to_rgb(msg.encoding, msg.height, msg.width, msg.step,
                                       msg.data.tobytes())
            except FrameError as exc:
                self.skipped[str(exc)] += 1
                continue
            self._index += 1
            return Frame(rgb, log_ns / 1e9, self._index - 1)
        return None

    def camera_matrix(self) -> np.ndarray | None:
        return self._k


class VideoSource(Source):

    def __init__(self, path: Path):
        super().__init__()
        self.path = Path(path)
        if not self.path.is_file():
            raise SourceError(f'video not found: {self.path}')
        self.rewind()
        self.fps = self._capture.get(cv2.CAP_PROP_FPS) or 30.0

    def rewind(self) -> None:
        self._capture = cv2.VideoCapture(str(self.path))
        if not self._capture.isOpened():
            raise SourceError(f'OpenCV cannot open video {self.path}')
        self._index = 0

    def read(self) -> Frame | None:
        ok, bgr = self._capture.read()
        if not ok:
            if self._index == 0:
                raise SourceError(f'video {self.path} has no readable frame')
            declared = int(self._capture.get(cv2.CAP_PROP_FRAME_COUNT))
            if self._index < declared - max(2, declared // 50):
                # a file cut short (a copy or a recording that died) reads like its end
                raise SourceError(f'video {self.path} stopped after {self._index} of the '
                                  f'{declared} frames its header declares: it is cut short '
                                  'or damaged')
            return None
        self._index += 1
        return Frame(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB),
                     frame_time(self._index - 1, self.fps), self._index - 1)

    def close(self) -> None:
        self._capture.release()


class FolderSource(Source):

    def __init__(self, path: Path, *, fps: float = 10.0):
        super().__init__()
        self.path = Path(path)
        if not self.path.is_dir():
            raise SourceError(f'image folder not found: {self.path}')
        self.files = sorted(p for p in self.path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not self.files:
            raise SourceError(f'image folder {self.path} holds no image '
                              f'({", ".join(IMAGE_SUFFIXES)})')
        self.fps = fps
        self.rewind()

    def rewind(self) -> None:
        self._index = 0

    def read(self) -> Frame | None:
        while self._index < len(self.files):
            file = self.files[self._index]
            self._index += 1
            bgr = cv2.imread(str(file), cv2.IMREAD_COLOR)
            if bgr is not None:
                return Frame(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB),
                             frame_time(self._index - 1, self.fps), self._index - 1)
            # unreadable or gone since the start: counted, so the run says so
            self.skipped['unreadable image file'] += 1
        return None


class DeviceSource(Source):
    live = True

    def __init__(self, device: int, *, clock):
        super().__init__()
        self._capture = cv2.VideoCapture(device)
        if not self._capture.isOpened():
            raise SourceError(f'OpenCV cannot open capture device {device}')
        self.fps = self._capture.get(cv2.CAP_PROP_FPS) or None
        self._clock = clock
        self._index = 0

    def read(self) -> Frame | None:
        ok, bgr = self._capture.read()
        if not ok:
            raise SourceError('capture device stopped delivering frames')
        self._index += 1
        return Frame(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), self._clock(), self._index - 1)

    def close(self) -> None:
        self._capture.release()


class RealSenseSource(Source):
    """The colour stream of an Intel RealSense, with the SDK's factory intrinsics."""

    live = True

    def __init__(self, *, width: int, height: int, fps: int, clock):
        super().__init__()
        try:
            import pyrealsense2 as rs
        except ImportError as exc:
            raise SourceError('the RealSense source needs the Intel RealSense SDK: '
                              "pip install 'activeloc_ros[realsense]' (pyrealsense2)") from exc
        if len(rs.context().query_devices()) == 0:
            raise SourceError('no RealSense device is connected')
        self._rs = rs
        self._pipeline = rs.pipeline()
        config = rs.config()
        config.enable_stream(rs.stream.color, width, height, rs.format.rgb8, fps)
        try:
            profile = self._pipeline.start(config)
        except RuntimeError as exc:
            raise SourceError(f'RealSense refused {width}x{height}@{fps} rgb8: {exc}') from exc
        intr = profile.get_stream(rs.stream.color).as_video_stream_profile().get_intrinsics()
        self._k = np.array([[intr.fx, 0, intr.ppx], [0, intr.fy, intr.ppy], [0, 0, 1.0]])
        self.fps = float(fps)
        self._clock = clock
        self._index = 0

    def read(self) -> Frame | None:
        try:
            frames = self._pipeline.wait_for_frames(timeout_ms=2000)
        except RuntimeError as exc:
            raise SourceError(f'RealSense stopped delivering frames: {exc}') from exc
        color = frames.get_color_frame()
        self._index += 1
        return Frame(np.asanyarray(color.get_data()).copy(), self._clock(), self._index - 1)

    def camera_matrix(self) -> np.ndarray | None:
        return self._k

    def close(self) -> None:
        self._pipeline.stop()


class SequenceSource(Source):
    """The frames of an annotated sequence (`data.load_sequence`) at its own frame rate."""

    def __init__(self, path: Path):
        super().__init__()
        try:
            self.sequence = data.load_sequence(path)
        except DataError as exc:
            raise SourceError(f'bad sequence: {exc}') from exc
        self.fps = self.sequence.fps
        self._samples = None
        self.rewind()

    def rewind(self) -> None:
        self.close()
        self._samples = self.sequence.frames()

    def read(self) -> Frame | None:
        try:
            sample = next(self._samples, None)
        except DataError as exc:
            raise SourceError(f'bad sequence: {exc}') from exc
        if sample is None:
            return None
        return Frame(sample.image, frame_time(sample.index, self.fps), sample.index)

    def close(self) -> None:
        if self._samples is not None:
            self._samples.close()


def open_scene(scene: str, *, image_topic: str = '', folder_fps: float = 10.0) -> Source:
    """
    The recorded source a virtual screen shows: a source spec, a sequence folder or the
    name of a sequence in the data root.
    """
    kind, _, arg = scene.partition(':')
    if not scene:
        raise SourceError(f'the virtual screen needs a scene: {SCENE_HELP}')
    if kind in SCENE_KINDS:
        return open_source(scene, clock=None, image_topic=image_topic, folder_fps=folder_fps)
    if kind in ('virtual', 'device', 'realsense'):
        raise SourceError(f'a virtual screen shows a recorded scene, not {scene!r}: '
                          f'{SCENE_HELP}')
    path = Path(scene)
    if (path / data.META_FILE).is_file():
        return SequenceSource(path)
    if path.is_dir():
        raise SourceError(f'{path} is not an annotated sequence (no {data.META_FILE}); a '
                          f'folder of images is folder:{path}')
    if path.exists():
        raise SourceError(f'{path} is a file, not a scene: {SCENE_HELP}')
    if len(path.parts) != 1:
        raise SourceError(f'scene not found: {path}')
    root = data.default_data_root()
    if root is None or not root.is_dir():
        raise SourceError(f'cannot look up the sequence {scene!r}: no folder of annotated '
                          f"sequences (set {data.ENV_VAR}=DIR, or give the sequence's "
                          f'folder); the scene is otherwise {SCENE_HELP}')
    if (root / scene / data.META_FILE).is_file():
        return SequenceSource(root / scene)
    known = ', '.join(p.name for p in data.find_sequences(root)) or 'none'
    raise SourceError(f'no sequence {scene!r} in the data root {root} (known: {known})')


def default_bag() -> Path:
    """The bundled sample bag."""
    return share_path('bags/vtest')


def device_index(arg: str) -> int:
    """
    The N of ``device:N`` (empty: 0); raises SourceError unless it is a whole number >= 0
    (OpenCV's capture crashes the process on a negative index).
    """
    try:
        index = int(arg or 0)
    except ValueError:
        raise SourceError(f'device source needs a number >= 0, got {arg!r}') from None
    if index < 0:
        raise SourceError(f'device source needs a number >= 0, got {arg!r}')
    return index


def open_source(spec: str, *, clock, image_topic: str = '', folder_fps: float = 10.0,
                realsense_size: tuple[int, int] = (640, 480), realsense_fps: int = 30
                ) -> Source:
    """Open the source a spec string names; raises SourceError with the reason if it cannot."""
    kind, _, arg = spec.partition(':')
    if kind == 'bag' and arg:
        return BagSource(Path(arg), topic=image_topic)
    if kind == 'video' and arg:
        return VideoSource(Path(arg))
    if kind == 'folder' and arg:
        return FolderSource(Path(arg), fps=folder_fps)
    if kind == 'device':
        return DeviceSource(device_index(arg), clock=clock)
    if kind == 'realsense':
        return RealSenseSource(width=realsense_size[0], height=realsense_size[1],
                               fps=realsense_fps, clock=clock)
    raise SourceError(f'unknown camera source {spec!r}: use bag:PATH, video:PATH, '
                      'folder:PATH, device:N or realsense (a scene on the virtual screen is '
                      "the sim node's)")


class Playback:
    """
    A recorded source as a node plays it: the next frame, from the start again at the
    end with ``loop``; each reason frames were skipped for, reported once; and how the
    stream ended (the source's error, every frame skipped, or its end).

    :param spec: the source as the user named it, for messages.
    :param warn: called with each message about a new problem.
    """

    def __init__(self, source: Source, spec: str, *, warn: Callable[[str], None]):
        self.source, self.spec, self.warn = source, spec, warn
        self.failure: str | None = None    # why the stream ended in error
        self._reported: set[str] = set()

    def read(self, *, loop: bool = False) -> Frame | None:
        """The next frame; None at the end or on an error (then ``failure`` says why)."""
        try:
            frame = self.source.read()
            if frame is None and loop:
                self.source.rewind()
                frame = self.source.read()
        except SourceError as exc:
            self.failure = str(exc)
            return None
        self.report(self.source.skipped, 'skipping frames')
        return frame

    def report(self, problems, what: str) -> None:
        """Warn once about each of ``problems`` (e.g. a Counter's keys) not reported yet."""
        for problem in sorted(set(problems) - self._reported):
            self.warn(f'{what}: {problem}')
            self._reported.add(problem)

    def ended(self, published: int) -> str | None:
        """At the end of the stream, after ``published`` frames: the failure, if any."""
        skipped = self.source.skipped
        if self.failure is None and published == 0 and skipped:
            self.failure = (f'{self.spec}: no frame could be published, all '
                            f'{sum(skipped.values())} were skipped: '
                            + '; '.join(f'{problem} ({n})' for problem, n in skipped.items()))
        return self.failure

    def summary(self, why: str, published: int) -> str:
        skipped = sum(self.source.skipped.values())
        return (f'{why}: {published} frames published'
                + (f', {skipped} skipped' if skipped else ''))


class Pacer:
    """
    When each recorded frame is due on the wall clock: replays the source's timing at `rate`.

    Frame stamps that go backwards (a loop restart) re-anchor the schedule.
    """

    def __init__(self, rate: float = 1.0):
        if not rate > 0:
            raise SourceError(f'replay rate must be > 0, got {rate}')
        self.rate = rate
        self._anchor: tuple[float, float] | None = None   # (stamp, wall time)
        self._last_stamp = -math.inf

    def set_rate(self, rate: float) -> None:
        """Change the speed from the next frame on (it is due at once, then at `rate`)."""
        if not rate > 0:
            raise SourceError(f'replay rate must be > 0, got {rate}')
        self.rate = rate
        self._anchor = None

    def due(self, stamp: float, now: float) -> float:
        if self._anchor is None or stamp < self._last_stamp:
            self._anchor = (stamp, now)
        self._last_stamp = stamp
        first_stamp, first_wall = self._anchor
        return first_wall + (stamp - first_stamp) / self.rate
