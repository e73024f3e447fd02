"""
`SurpriseModel.learn` hands the map over before its optimiser step, and `Pipeline`
(observing the next frame while learning from this one) gives exactly what
`SurpriseModel.step` gives, frame by frame; a failure surfaces in the caller.
"""
import threading

import numpy as np
import pytest
import torch

from activeloc_ros.errors import FrameError
from activeloc_ros.perception.pipeline import Pipeline, PipelineError
from test_model import clip, make, panning


def test_the_map_is_handed_over_before_the_optimiser_step():
    model = make()
    frames = clip(3)
    model.step(frames[0])
    model.step(frames[1])
    before = [p.detach().clone() for p in model.predictor.parameters()]

    def unchanged() -> bool:
        return all(torch.equal(a, b) for a, b in zip(before, model.predictor.parameters()))

    handed = []
    result = model.learn(model.observe(frames[2]),
                         on_map=lambda r: handed.append((r.surprise_map, unchanged())))
    (early_map, weights_then), = handed
    assert weights_then and not unchanged()          # the step came after the handover
    np.testing.assert_array_equal(early_map, result.surprise_map)
    assert result.updated and result.lr > 0


@pytest.mark.parametrize('settings', [{}, {'ego_motion': 'homography', 'ego_warp': 'image'}])
def test_the_pipeline_gives_the_maps_step_gives_in_order(settings):
    frames = panning(8, square=True) + clip(4, h=64, w=64)
    frames[5] = frames[5].astype(np.float32)
    frames[5][0, 0, 0] = np.nan                   # a bad frame restarts the sequence
    reference = make(**settings)
    expected = [reference.step(f, t=i / 30) for i, f in enumerate(frames)]  # 30 frames/s
    got = []
    pipeline = Pipeline(make(**settings), lambda result, tag: got.append((tag, result)))
    for i, frame in enumerate(frames):
        pipeline.submit(frame, tag=i, t=i / 30)
    assert pipeline.drain(timeout=60)
    pipeline.close()
    assert [tag for tag, _ in got] == list(range(len(frames)))
    for want, (_, result) in zip(expected, got):
        np.testing.assert_allclose(result.surprise_map, want.surprise_map, rtol=1e-5,
                                   atol=1e-7)
        assert result.updated == want.updated and result.nan_events == want.nan_events
    assert got[-1][1].nan_events == 1 and got[-1][1].updated


def test_a_malformed_frame_is_refused_and_the_pipeline_goes_on():
    got = []
    pipeline = Pipeline(make(), lambda result, tag: got.append(tag))
    pipeline.submit(clip(1)[0], tag='a')
    with pytest.raises(FrameError):
        pipeline.submit(np.zeros((8, 8), np.uint8), tag='bad')
    pipeline.submit(clip(2)[1], tag='b')
    pipeline.close()
    assert got == ['a', 'b']


def test_busy_while_an_observed_frame_waits_for_the_learner():
    """What the perception node asks before it takes a camera frame."""
    learning, release = threading.Event(), threading.Event()

    def hold(result, tag):
        learning.set()
        assert release.wait(30)

    pipeline = Pipeline(make(), hold)
    frames = clip(2)
    pipeline.submit(frames[0], tag=0)
    assert learning.wait(30)                 # the learner has frame 0 in hand
    assert not pipeline.busy()
    pipeline.submit(frames[1], tag=1)        # observed, it waits for the learner
    assert pipeline.busy()
    release.set()
    assert pipeline.drain(timeout=60)
    assert not pipeline.busy()
    pipeline.close()


def test_a_failure_while_learning_is_raised_in_the_callers_thread():
    def publish(result, tag):
        raise RuntimeError('publisher gone')

    pipeline = Pipeline(make(), publish)
    pipeline.submit(clip(1)[0])
    assert not pipeline.drain(timeout=30)
    with pytest.raises(PipelineError, match='publisher gone'):
        pipeline.submit(clip(2)[1])


def test_a_caller_that_asks_busy_learns_of_the_failure():
    """
    The perception node asks `busy` before it takes a frame. After the learner died with
    a frame waiting, `busy` stayed True for ever: every frame skipped, nothing raised.
    """
    queued = threading.Event()

    def publish(result, tag):
        queued.wait(30)               # the next frame is waiting when this one fails
        raise RuntimeError('publisher gone')

    pipeline = Pipeline(make(), publish)
    frames = clip(2)
    pipeline.submit(frames[0])
    pipeline.submit(frames[1])
    queued.set()
    assert not pipeline.drain(timeout=30)
    with pytest.raises(PipelineError, match='publisher gone'):
        pipeline.busy()
