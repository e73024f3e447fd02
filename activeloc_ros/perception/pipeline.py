"""
Encode the next frame while the model learns from this one.

`SurpriseModel.step` is `learn(observe(frame))`. `observe` (resize, ego-motion, the encoder)
touches only its own memory of the previous frame, so a second thread can run `learn`
(prediction, losses, the optimiser step) on frame t while the caller's thread observes frame
t + 1. Each frame is still learnt from, in order, with the weights every earlier frame
updated: the maps are the ones `step` gives, one per frame, with no lag. What changes is
the time a frame costs: the longer of the two halves instead of their sum.

Give each half its own core: with 2 cores, torch and the encoder one thread each
(`PerceptionConfig.num_threads: 1`); the perception node does this.
"""
import queue
import threading
from typing import Any, Callable

import numpy as np

from activeloc_ros.errors import ActivelocError
from activeloc_ros.perception.model import PerceptionResult, SurpriseModel


class PipelineError(ActivelocError):
    """The learning thread failed; the cause is chained."""


class Pipeline:
    """
    Two-stage `step`: `submit` observes in the caller's thread, a learning thread learns
    and hands each result to `on_result(result, tag)` (called in that thread) as soon as
    its map exists, before the optimiser step.

    At most one observed frame waits for the learner: `submit` blocks while it waits, so no
    frame is ever dropped between the halves (the next warp is measured from it).
    """

    def __init__(self, model: SurpriseModel,
                 on_result: Callable[[PerceptionResult, Any], None]):
        self.model = model
        self.on_result = on_result
        self._waiting: queue.Queue = queue.Queue(maxsize=1)
        self._failure: BaseException | None = None
        self._pending = 0                # submitted, not yet learnt
        self._changed = threading.Condition()
        self._thread = threading.Thread(target=self._learn_loop, name='perception-learn',
                                        daemon=True)
        self._thread.start()

    def submit(self, frame: np.ndarray, tag: Any = None, *, t: float | None = None) -> None:
        """
        Observe `frame`, captured at `t` (s; None: unknown), now and queue it for
        learning; `tag` comes back with its result.

        :raises FrameError: the frame is malformed (nothing is queued).
        :raises PipelineError: the learning thread failed or was closed.
        """
        self._check()
        observation = self.model.observe(frame, t=t)
        with self._changed:
            self._pending += 1
        while True:                      # wait for the learner, but notice if it died
            try:
                self._waiting.put((observation, tag), timeout=0.5)
                return
            except queue.Full:
                self._check()

    def busy(self) -> bool:
        """
        Whether an observed frame already waits for the learner: a frame submitted now
        would wait for a whole learning step, so a camera's caller had better skip it and
        take a newer one once the learner is free.

        :raises PipelineError: the learning thread failed or was closed (a caller that only
            asked `busy` would otherwise skip every frame for ever: the waiting frame is
            never taken).
        """
        self._check()
        return self._waiting.full()

    def drain(self, timeout: float | None = None) -> bool:
        """Wait until every submitted frame has been learnt; False on timeout or failure."""
        with self._changed:
            self._changed.wait_for(lambda: self._pending == 0 or self._failure is not None,
                                   timeout)
            return self._pending == 0 and self._failure is None

    def close(self, timeout: float | None = 10.0) -> None:
        """Learn what was submitted, then stop the learning thread."""
        if not self._thread.is_alive():
            return
        self.drain(timeout)
        try:
            self._waiting.put(None, timeout=timeout)
        except queue.Full:
            return                       # the learner is stuck: it is a daemon thread
        self._thread.join(timeout)

    def _check(self) -> None:
        if self._failure is not None:
            raise PipelineError(f'the learning thread failed: {self._failure!r}') \
                from self._failure
        if not self._thread.is_alive():
            raise PipelineError('the pipeline is closed')

    def _learn_loop(self) -> None:
        while True:
            item = self._waiting.get()
            if item is None:
                return
            observation, tag = item
            try:                         # each map is handed over before its update
                self.model.learn(observation, on_map=lambda result: self.on_result(result, tag))
            except BaseException as exc:   # kept, and raised in the caller's thread
                with self._changed:
                    self._failure = exc
                    self._changed.notify_all()
                return
            with self._changed:
                self._pending -= 1
                self._changed.notify_all()
