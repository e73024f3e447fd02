"""
The tracker baselines: EdgeBoxes proposals on gradient edges, and each OpenCV tracker
following a synthetic target from its first-frame proposal.
"""
import cv2
import numpy as np
import pytest

from activeloc_ros.bench.trackers import create_tracker, propose_boxes, TrackerPointer, TRACKERS
from activeloc_ros.errors import ConfigError, FrameError

H, W = 240, 320
SIZE = 40  # side of the moving target


def background(seed: int) -> np.ndarray:
    """Smooth colour noise around grey 110: texture with weak edges everywhere."""
    rng = np.random.default_rng(seed)
    noise = rng.normal(0.0, 1.0, (H // 4, W // 4, 3)).astype(np.float32)
    noise = cv2.resize(noise, (W, H), interpolation=cv2.INTER_CUBIC)
    return np.clip(110 + 12 * noise, 0, 255).astype(np.uint8)


def target() -> np.ndarray:
    """A yellow square with a blue cross and a white spot: bright and not self-similar."""
    yy, xx = np.mgrid[0:SIZE, 0:SIZE] / (SIZE - 1)
    patch = np.empty((SIZE, SIZE, 3), np.uint8)
    patch[...] = (230, 200, 60)
    patch[(np.abs(xx - yy) < 0.1) | (np.abs(xx + yy - 1) < 0.1)] = (40, 40, 160)
    patch[(xx - 0.25) ** 2 + (yy - 0.75) ** 2 < 0.02] = (250, 250, 250)
    return patch


def moving_target(n: int, start: tuple[int, int] = (80, 90), step: tuple[int, int] = (4, 2),
                  seed: int = 1) -> list[tuple[np.ndarray, tuple[float, float]]]:
    """Frames with the target moving `step` pixels a frame, and its true centre."""
    frames, patch, bg = [], target(), background(seed)
    for i in range(n):
        x, y = start[0] + step[0] * i, start[1] + step[1] * i
        frame = bg.copy()
        frame[y:y + SIZE, x:x + SIZE] = patch
        frames.append((frame, (x + SIZE / 2, y + SIZE / 2)))
    return frames


def iou(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> float:
    iw = max(0, min(a[0] + a[2], b[0] + b[2]) - max(a[0], b[0]))
    ih = max(0, min(a[1] + a[3], b[1] + b[3]) - max(a[1], b[1]))
    inter = iw * ih
    return inter / (a[2] * a[3] + b[2] * b[3] - inter)


@pytest.mark.parametrize('rects', [
    # (x, y, w, h, RGB): a white and a blue rectangle, then a dark and a red one elsewhere
    [(40, 50, 70, 60, (240, 240, 240)), (200, 120, 60, 80, (20, 20, 200))],
    [(180, 30, 90, 50, (15, 15, 15)), (30, 140, 50, 70, (220, 30, 30))],
])
def test_proposals_cover_high_contrast_rectangles(rects):
    image = background(0)
    for x, y, w, h, colour in rects:
        image[y:y + h, x:x + w] = colour
    proposals = propose_boxes(image, max_boxes=20)
    boxes = [box for box, _ in proposals]
    for x, y, w, h, _ in rects:
        assert max(iou(box, (x, y, w, h)) for box in boxes) > 0.6
    # the best box is on one of the rectangles, not on the texture
    assert max(iou(boxes[0], r[:4]) for r in rects) > 0.6


@pytest.mark.parametrize('min_area, max_area, max_boxes', [
    (0.01, 0.25, 50),
    (0.05, 0.10, 5),
    (0.0, 1.0, 100),
])
def test_proposals_respect_limits_and_are_sorted(min_area, max_area, max_boxes):
    image = moving_target(1)[0][0]
    proposals = propose_boxes(image, max_boxes=max_boxes, min_area=min_area, max_area=max_area)
    assert 0 < len(proposals) <= max_boxes
    for (x, y, w, h), _ in proposals:
        assert min_area <= w * h / (W * H) <= max_area
        assert x >= 0 and y >= 0 and x + w <= W and y + h <= H
    scores = [score for _, score in proposals]
    assert scores == sorted(scores, reverse=True)


def test_a_blank_frame_has_no_proposals():
    assert propose_boxes(np.full((H, W, 3), 110, np.uint8)) == []


@pytest.mark.parametrize('kwargs', [
    {'min_area': 0.3, 'max_area': 0.2},
    {'min_area': -0.1},
    {'max_area': 1.5},
    {'max_boxes': 0},
])
def test_bad_proposal_options_are_config_errors(kwargs):
    with pytest.raises(ConfigError):
        propose_boxes(np.zeros((H, W, 3), np.uint8), **kwargs)


@pytest.mark.parametrize('frame', [
    np.zeros((H, W), np.uint8),
    np.zeros((H, W, 4), np.uint8),
    np.zeros((H, W, 3), np.float32),
])
def test_bad_frames_are_frame_errors(frame):
    with pytest.raises(FrameError):
        propose_boxes(frame)
    with pytest.raises(FrameError):
        TrackerPointer('kcf').locate(frame)


@pytest.mark.parametrize('kind', TRACKERS)
def test_create_tracker_makes_a_fresh_working_tracker(kind):
    tracker = create_tracker(kind)
    assert tracker is not create_tracker(kind)
    # OpenCV 4.11's MOSSE (the numpy1 pins) reports failure on 7 of 8 of these backgrounds
    # (its peak-to-sidelobe test); OpenCV 5's tracks all 8. Background 2 suits both.
    frames = moving_target(2, seed=2 if kind == 'mosse' else 1)
    bgr = [cv2.cvtColor(frame, cv2.COLOR_RGB2BGR) for frame, _ in frames]
    tracker.init(bgr[0], (80, 90, SIZE, SIZE))
    ok, (x, y, w, h) = tracker.update(bgr[1])
    (u, v) = frames[1][1]
    assert ok and np.hypot(x + w / 2 - u, y + h / 2 - v) < 8


@pytest.mark.parametrize('kind', ['', 'TLD', 'boosting', 'medianflow', 'goturn'])
def test_unknown_tracker_is_a_config_error(kind):
    with pytest.raises(ConfigError, match='unknown tracker'):
        create_tracker(kind)
    with pytest.raises(ConfigError):
        TrackerPointer(kind)


# Largest centre error (px) over 16 frames while the target travels 67 px. KCF, CSRT and
# MOSSE stay within ~3 px here; TLD and MIL follow too but wander (up to 23 px in 60
# runs: their internal random sampling is not reset by cv2.setRNGSeed).
# MOSSE may also report failure from the second frame on when its box holds much
# background (seen with other backgrounds), so this sequence is one where it does not.
@pytest.mark.parametrize('kind, tolerance', [
    ('kcf', 8.0),
    ('csrt', 8.0),
    ('mosse', 8.0),
    ('tld', 30.0),
    ('mil', 30.0),
])
def test_pointer_follows_a_moving_target(kind, tolerance):
    cv2.setRNGSeed(0)
    pointer = TrackerPointer(kind)
    assert pointer.name == kind and pointer.init_box is None
    frames = moving_target(16)
    errors = []
    for frame, (u, v) in frames:
        point = pointer.locate(frame)
        assert point is not None, f'{kind} lost the target at frame {len(errors)}'
        errors.append(float(np.hypot(point[0] - u, point[1] - v)))
    assert iou(pointer.init_box, (80, 90, SIZE, SIZE)) > 0.5
    assert max(errors) < tolerance, errors


def test_first_locate_returns_the_init_box_centre():
    pointer = TrackerPointer('kcf')
    point = pointer.locate(moving_target(1)[0][0])
    x, y, w, h = pointer.init_box
    assert point == (x + w / 2, y + h / 2)


@pytest.mark.parametrize('kind', ['tld', 'mosse', 'csrt'])
def test_a_failure_is_none_and_never_reinitialises(kind):
    pointer = TrackerPointer(kind)
    frames = moving_target(2)
    pointer.locate(frames[0][0])
    tracker, box = pointer.tracker, pointer.init_box
    assert pointer.locate(np.full((H, W, 3), 110, np.uint8)) is None  # target gone
    pointer.locate(frames[1][0])  # back again: updated (found or not), never re-proposed
    assert pointer.tracker is tracker and pointer.init_box == box


def test_an_opencv_error_in_update_is_a_failed_frame():
    pointer = TrackerPointer('tld')  # TLD's optical flow asserts on a change of frame size
    pointer.locate(moving_target(1)[0][0])
    assert pointer.locate(np.zeros((20, 20, 3), np.uint8)) is None


def test_without_proposals_it_waits_and_proposes_again():
    pointer = TrackerPointer('kcf')
    blank = np.full((H, W, 3), 110, np.uint8)
    assert pointer.locate(blank) is None and pointer.locate(blank) is None
    assert pointer.init_box is None and pointer.tracker is None
    frame, (u, v) = moving_target(1)[0]
    point = pointer.locate(frame)
    assert point is not None and np.hypot(point[0] - u, point[1] - v) < 8


def test_reset_forgets_tracker_and_init_box():
    pointer = TrackerPointer('kcf')
    pointer.locate(moving_target(1, start=(40, 40))[0][0])
    first_box = pointer.init_box
    pointer.reset()
    assert pointer.init_box is None and pointer.tracker is None
    frame, (u, v) = moving_target(1, start=(220, 160), seed=2)[0]
    point = pointer.locate(frame)  # a new sequence: proposes again, on the new frame
    assert pointer.init_box != first_box
    assert np.hypot(point[0] - u, point[1] - v) < 8
