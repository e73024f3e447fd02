"""
Annotated evaluation sequences: load a folder, stream RGB frames with their ground truth.

A sequence folder holds `meta.json`, `gt_xywh.txt` (one `x,y,w,h` row per frame, `nan` rows
where the target is not visible) and, for multi-actor sequences, `gt_all_xywh.txt`
(`frame0,track_id,x,y,w,h,conf`). Frames come from `meta['video']` (decoded with OpenCV) or
`meta['frames_glob']` (image files sorted by name). See /work/shared/data/README.md.

Everything is checked when a sequence is loaded, except the frames themselves, which are
only decoded while streaming; any defect raises `DataError` naming the file (and line).
The data are read in place and never copied.
"""
from dataclasses import dataclass, field
import json
import math
import os
from pathlib import Path
import re
from typing import Iterator, NamedTuple

import cv2
import numpy as np

from activeloc_ros.errors import DataError

ENV_VAR = 'ACTIVELOC_DATA'
META_FILE = 'meta.json'
GT_FILE = 'gt_xywh.txt'
GT_ALL_FILE = 'gt_all_xywh.txt'
REQUIRED_META = ('W', 'H', 'frames', 'camera')
CAMERA_KINDS = ('static', 'moving', 'pan')
# the order benchmark tables list them in: still cameras first
KIND_ORDER = {'static': 0, 'pan': 1, 'moving': 2}
DEFAULT_FPS = 30.0  # OTB and VOT give no rate; they were filmed at about 30 frames/s


class Box(NamedTuple):
    """An axis-aligned box in pixels, top-left origin."""

    x: float
    y: float
    w: float
    h: float

    @property
    def centre(self) -> tuple[float, float]:
        return (self.x + self.w / 2.0, self.y + self.h / 2.0)

    def grown(self, dx: float, dy: float) -> 'Box':
        """The box enlarged by `dx` on the left and right and `dy` above and below."""
        return Box(self.x - dx, self.y - dy, self.w + 2.0 * dx, self.h + 2.0 * dy)

    def contains(self, x: float, y: float) -> bool:
        """Whether the point lies inside the box or on its border."""
        return self.x <= x <= self.x + self.w and self.y <= y <= self.y + self.h


@dataclass(frozen=True)
class FrameTruth:
    """
    Ground truth of one frame.

    :param primary: the primary actor's box, None when it is not visible.
    :param actors: every annotated actor's box in this frame (just the primary when the
        sequence has a single target); empty when nobody is annotated.
    :param scored: the frame lies inside `meta['eval_frames']` (all frames when absent).
    """

    index: int
    primary: Box | None
    actors: tuple[Box, ...]
    scored: bool = True


@dataclass(frozen=True)
class Sample:
    """One frame, RGB uint8 (H, W, 3), with its ground truth."""

    index: int
    image: np.ndarray
    truth: FrameTruth


@dataclass(frozen=True)
class Sequence:
    """A loaded, checked sequence; `frames()` streams its images."""

    name: str
    path: Path
    width: int
    height: int
    camera: str
    truth: tuple[FrameTruth, ...]
    meta: dict = field(repr=False, compare=False)

    @property
    def fps(self) -> float:
        """
        The original frame rate: the leading number of `meta['fps']` ('25 (mpg header)',
        '~30 (n/a)'), 30 when absent or unreadable.
        """
        match = re.match(r'\s*~?\s*([0-9.]+)', str(self.meta.get('fps', '')))
        try:
            fps = float(match.group(1)) if match else DEFAULT_FPS
        except ValueError:
            fps = DEFAULT_FPS
        return fps if 1.0 <= fps <= 1000.0 else DEFAULT_FPS

    def __len__(self) -> int:
        return len(self.truth)

    @property
    def camera_kind(self) -> str:
        return camera_kind(self.camera)

    def frames(self, *, max_frames: int | None = None) -> Iterator[Sample]:
        """
        Decode the frames in order, each with its ground truth.

        Raises `DataError` if the source has fewer frames than ground-truth rows (or more,
        when it is read to the end), or a frame of the wrong size.
        """
        limit = len(self.truth) if max_frames is None else min(max_frames, len(self.truth))
        if 'video' in self.meta:
            images = _video_frames(self.path / self.meta['video'], limit, len(self.truth))
        else:
            images = _image_frames(_frame_files(self.path, self.meta)[:limit])
        for index, (source, bgr) in enumerate(images):
            if bgr.shape[:2] != (self.height, self.width):
                raise DataError(
                    f'{source}: frame {index} is {bgr.shape[1]}x{bgr.shape[0]}, '
                    f'{self.path / META_FILE} says {self.width}x{self.height}')
            rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
            yield Sample(index, rgb, self.truth[index])


def camera_kind(camera: str) -> str:
    """
    'static', 'moving' or 'pan' from the free-text `meta['camera']`.

    The first of those words found wins, so 'MOVING (pans to follow)' is moving.
    """
    text = camera.lower()
    for kind in CAMERA_KINDS:
        if kind in text:
            return kind
    return 'moving'


def default_data_root() -> Path | None:
    """`$ACTIVELOC_DATA`, else `../shared/data/sequences` beside the repository if present."""
    env = os.environ.get(ENV_VAR)
    if env:
        return Path(env)
    candidate = Path(__file__).resolve().parents[2] / 'shared' / 'data' / 'sequences'
    return candidate if candidate.is_dir() else None


def resolve_data_root(arg: str | os.PathLike | None = None) -> Path:
    """The data root from a CLI argument, the environment or the default; must exist."""
    root = Path(arg) if arg else default_data_root()
    if root is None:
        raise DataError(f'no data root: pass --data DIR or set {ENV_VAR}')
    if not root.is_dir():
        raise DataError(f'{root}: data root is not a directory')
    return root


def find_sequences(root: str | os.PathLike) -> list[Path]:
    """
    Sequence folders (those holding a `meta.json`) under `root`, sorted by name.

    `root` may itself be a sequence folder.
    """
    root = Path(root)
    if (root / META_FILE).is_file():
        return [root]
    if not root.is_dir():
        raise DataError(f'{root}: not a directory')
    return sorted(p for p in root.iterdir() if (p / META_FILE).is_file())


def load_sequence(path: str | os.PathLike) -> Sequence:
    """Read and check `meta.json`, the ground truth and the frame source of one folder."""
    path = Path(path)
    meta = _read_meta(path / META_FILE)
    n = meta['frames']
    if 'video' in meta:
        if not (path / meta['video']).is_file():
            raise DataError(f'{path / META_FILE}: video {meta["video"]!r} does not exist')
    else:
        files = _frame_files(path, meta)
        if len(files) != n:
            raise DataError(f'{path / META_FILE}: frames_glob {meta["frames_glob"]!r} '
                            f'matches {len(files)} files, frames is {n}')
    primary = _read_gt(path / GT_FILE, n)
    first, last = _eval_frames(path / META_FILE, meta)
    all_path = path / GT_ALL_FILE
    actors = _read_gt_all(all_path, n) if all_path.is_file() else None
    truth = []
    for i, box in enumerate(primary):
        boxes = actors[i] if actors is not None else ((box,) if box else ())
        truth.append(FrameTruth(i, box, tuple(boxes), first <= i <= last))
    return Sequence(name=path.name, path=path, width=meta['W'], height=meta['H'],
                    camera=str(meta['camera']), truth=tuple(truth), meta=meta)


NO_SUCH_SEQUENCE = 'no such sequence'


def load_sequences(root: str | os.PathLike, *, names: list[str] | None = None,
                   cameras: list[str] | None = None,
                   ) -> tuple[list[Sequence], list[tuple[str, str]]]:
    """
    Load every sequence under `root` (or only `names`), skipping the bad ones.

    :param cameras: keep only these camera kinds ('static', 'pan', 'moving').
    :returns: the loaded sequences and `(name, reason)` for each one skipped.
    """
    paths = find_sequences(root)
    skipped: list[tuple[str, str]] = []
    if names:
        known = {p.name: p for p in paths}
        skipped += [(n, NO_SUCH_SEQUENCE) for n in names if n not in known]
        paths = [known[n] for n in names if n in known]
    loaded = []
    for p in paths:
        try:
            seq = load_sequence(p)
        except DataError as err:
            skipped.append((p.name, str(err)))
            continue
        if cameras and seq.camera_kind not in cameras:
            continue
        loaded.append(seq)
    return loaded, skipped


def _read_meta(path: Path) -> dict:
    if not path.is_file():
        raise DataError(f'{path}: missing')
    try:
        meta = json.loads(path.read_text(encoding='utf-8'))
    except json.JSONDecodeError as err:
        raise DataError(f'{path}:{err.lineno}: not valid JSON ({err.msg})') from err
    except (OSError, UnicodeDecodeError) as err:
        raise DataError(f'{path}: cannot read ({err})') from err
    if not isinstance(meta, dict):
        raise DataError(f'{path}: expected a JSON object')
    missing = [k for k in REQUIRED_META if k not in meta]
    if 'video' not in meta and 'frames_glob' not in meta:
        missing.append('video or frames_glob')
    if missing:
        raise DataError(f'{path}: missing key(s) {", ".join(missing)}')
    for key in ('W', 'H', 'frames'):
        value = meta[key]
        if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
            raise DataError(f'{path}: {key} must be a positive integer, got {value!r}')
    for key in ('video', 'frames_glob'):
        if key in meta and (not isinstance(meta[key], str) or not meta[key]):
            raise DataError(f'{path}: {key} must be a non-empty string')
    return meta


def _eval_frames(path: Path, meta: dict) -> tuple[int, int]:
    n = meta['frames']
    value = meta.get('eval_frames')
    if value is None:
        return 0, n - 1
    ok = (isinstance(value, list) and len(value) == 2
          and all(isinstance(v, int) and not isinstance(v, bool) for v in value))
    if not ok or not 0 <= value[0] <= value[1] < n:
        raise DataError(f'{path}: eval_frames must be [first, last] within 0..{n - 1}, '
                        f'got {value!r}')
    return value[0], value[1]


def _data_lines(path: Path) -> Iterator[tuple[int, str]]:
    """(line number, text) of the non-blank, non-comment lines of a text file."""
    if not path.is_file():
        raise DataError(f'{path}: missing')
    try:
        text = path.read_text(encoding='utf-8')
    except (OSError, UnicodeDecodeError) as err:
        raise DataError(f'{path}: cannot read ({err})') from err
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if line and not line.startswith('#'):
            yield number, line


def _floats(path: Path, number: int, fields: list[str]) -> list[float]:
    try:
        return [float(f) for f in fields]
    except ValueError as err:
        raise DataError(f'{path}:{number}: not a number ({err})') from err


def _box(path: Path, number: int, values: list[float]) -> Box | None:
    nans = sum(math.isnan(v) for v in values)
    if nans == 4:
        return None
    if nans or not all(math.isfinite(v) for v in values):
        raise DataError(f'{path}:{number}: a box must be four finite numbers or all nan')
    if values[2] <= 0 or values[3] <= 0:
        raise DataError(f'{path}:{number}: box width and height must be positive')
    return Box(*values)


def _read_gt(path: Path, n_frames: int) -> list[Box | None]:
    boxes = []
    for number, line in _data_lines(path):
        fields = line.replace(' ', '').split(',')
        if len(fields) != 4:
            raise DataError(f'{path}:{number}: expected x,y,w,h, got {len(fields)} values')
        boxes.append(_box(path, number, _floats(path, number, fields)))
    if len(boxes) != n_frames:
        raise DataError(f'{path}: {len(boxes)} ground-truth rows, meta.json frames is '
                        f'{n_frames}')
    return boxes


def _read_gt_all(path: Path, n_frames: int) -> list[list[Box]]:
    """Per frame, the boxes of every track; rows with conf 0 are MOT 'ignore' entries."""
    per_frame: list[list[Box]] = [[] for _ in range(n_frames)]
    for number, line in _data_lines(path):
        fields = line.replace(' ', '').split(',')
        if len(fields) != 7:
            raise DataError(f'{path}:{number}: expected frame0,track_id,x,y,w,h,conf, '
                            f'got {len(fields)} values')
        values = _floats(path, number, fields)
        frame = values[0]
        if not frame.is_integer() or not 0 <= frame < n_frames:
            raise DataError(f'{path}:{number}: frame {fields[0]} outside 0..{n_frames - 1}')
        box = _box(path, number, values[2:6])
        if box is not None and values[6] != 0:
            per_frame[int(frame)].append(box)
    return per_frame


def _frame_files(path: Path, meta: dict) -> list[Path]:
    return sorted(p for p in path.glob(meta['frames_glob']) if p.is_file())


def _image_frames(files: list[Path]) -> Iterator[tuple[Path, np.ndarray]]:
    for f in files:
        bgr = cv2.imread(str(f), cv2.IMREAD_COLOR)
        if bgr is None:
            raise DataError(f'{f}: cannot decode image')
        yield f, bgr


def _video_frames(path: Path, limit: int, n_frames: int) -> Iterator[tuple[Path, np.ndarray]]:
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            raise DataError(f'{path}: cannot open video')
        for index in range(limit):
            ok, bgr = cap.read()
            if not ok or bgr is None:
                raise DataError(f'{path}: video ends after {index} frames, the ground '
                                f'truth has {n_frames} rows')
            yield path, bgr
        if limit == n_frames and cap.read()[0]:
            raise DataError(f'{path}: video has more than the {n_frames} frames of the '
                            'ground truth')
    finally:
        cap.release()
