"""
Change detection with the camera's own motion taken out (perception.motion), and the
unsupervised anchors of the screen table that use it (framediff, mog2).
"""
import numpy as np
import pytest

from activeloc_ros.bench.pointers import FrameDiffPointer, Mog2Pointer
from activeloc_ros.perception import motion
from activeloc_ros.world import View
from test_trackers import SIZE, target

H, W = 240, 320


def moving_target(n: int, *, step: int = 4):
    """
    The trackers' target moving right over a richly textured still background (ORB
    finds the background's motion, which is none, rather than the target's).
    """
    rng = np.random.default_rng(3)
    bg = np.repeat(np.repeat(rng.integers(0, 255, (H // 4, W // 4, 3), np.uint8), 4, 0), 4, 1)
    frames = []
    for i in range(n):
        x, y = 60 + step * i, 100
        frame = bg.copy()
        frame[y:y + SIZE, x:x + SIZE] = target()
        frames.append((frame, (x + SIZE / 2, y + SIZE / 2)))
    return frames


def view(rgb, index):
    none = np.zeros((0, 2))
    return View(rgb, index, index / 10, 0.0, 0.0, none, None, np.zeros(2))


def test_a_shifted_still_picture_leaves_no_change_once_the_shift_is_taken_out():
    rng = np.random.default_rng(0)
    picture = (rng.random((120, 160)) * 255).astype(np.float32)
    shifted = np.roll(picture, 5, axis=1)
    warp = np.array([[1, 0, 5], [0, 1, 0], [0, 0, 1]], np.float64)
    raw = motion.residual(picture, shifted, None, tolerance_px=0)
    compensated = motion.residual(picture, shifted, warp)
    assert raw.mean() > 20
    assert compensated[:, 8:].max() == 0.0      # and the strip the old view missed is 0


@pytest.mark.parametrize('make', [FrameDiffPointer, Mog2Pointer])
def test_the_motion_anchors_point_at_the_moving_target(make):
    pointer = make()
    pointer.reset('square')
    errors = []
    for i, (frame, (u, v)) in enumerate(moving_target(12)):
        answer = pointer.locate(view(frame, i))
        if i >= 3:
            assert answer.location is not None and answer.peak > 1.0 / 196
            errors.append(np.hypot(answer.location[0] - u, answer.location[1] - v))
    assert max(errors) < SIZE, errors


@pytest.mark.parametrize('make', [FrameDiffPointer, Mog2Pointer])
def test_a_still_scene_gives_no_location(make):
    pointer = make()
    pointer.reset('square')
    frame = moving_target(1)[0][0]
    answers = [pointer.locate(view(frame, i)) for i in range(5)]
    assert all(a.location is None for a in answers[1:])
