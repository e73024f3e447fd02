"""
Health of a frame pipeline, ROS-free: counts and timings summarised once per period.

The perception node feeds it and turns each `Report` into a diagnostic_msgs status on
`/diagnostics` (maps/s, latency, dropped and skipped frames), as camera drivers do.
"""
from collections import Counter, deque
from dataclasses import dataclass, field

import numpy as np

OK, WARN = 0, 1     # diagnostic_msgs/DiagnosticStatus levels


@dataclass(frozen=True)
class Report:
    level: int
    message: str
    values: dict[str, str] = field(default_factory=dict)


class PipelineStats:
    """
    What happened to the frames since the start and since the last report.

    *Announced* frames are those the camera says it published (one camera_info each);
    announced frames never received were dropped on the way (a depth-1 queue keeps only
    the newest frame while the model is busy); their stamps give the camera's frame period.
    *Skipped* frames arrived but could not be used (bad encoding, too large), by reason.
    *Learnt* frames are mapped frames that got an optimiser step.
    """

    def __init__(self, now: float):
        self.announced = 0
        self.received = 0
        self.maps = 0
        self.learnt = 0
        self.skipped: Counter[str] = Counter()
        self._since = now
        self._period = {'received': 0, 'maps': 0, 'skipped': 0}
        self._learnt_before = 0        # `learnt` at the start of the period
        self._gaps: deque[float] = deque(maxlen=15)     # between announced frames' stamps, s
        self._last_stamp: float | None = None
        self._latency_s: list[float] = []
        self._compute_s: list[float] = []
        self._last_skip = ''

    def frame_announced(self, stamp_s: float | None = None) -> None:
        self.announced += 1
        if stamp_s is not None:
            if self._last_stamp is not None and stamp_s > self._last_stamp:
                self._gaps.append(stamp_s - self._last_stamp)
            self._last_stamp = stamp_s

    @property
    def camera_period(self) -> float | None:
        """
        The camera's frame period, s: the median gap between the stamps of the last
        announced frames; None before two.
        """
        return float(np.median(self._gaps)) if self._gaps else None

    def frame_received(self) -> None:
        self.received += 1
        self._period['received'] += 1

    def frame_skipped(self, reason: str) -> None:
        self.skipped[reason] += 1
        self._period['skipped'] += 1
        self._last_skip = reason

    def map_published(self, *, latency_s: float, compute_s: float) -> None:
        """:param latency_s: frame stamp to map published; compute_s: the model's step."""
        self.maps += 1
        self._period['maps'] += 1
        self._latency_s.append(latency_s)
        self._compute_s.append(compute_s)

    def frames_learnt(self, total: int) -> None:
        """The model has taken ``total`` optimiser steps since the start."""
        self.learnt = total

    @property
    def dropped(self) -> int | None:
        """Frames announced but never received; None when nothing was announced."""
        return max(0, self.announced - self.received) if self.announced else None

    def summary(self) -> str:
        """One line for the log at the end of a run."""
        text = (f'{self.maps} maps from {self.received} frames received, '
                f'{self.learnt} learnt from')
        if self.dropped is not None:
            text += f', {self.dropped} of {self.announced} announced frames dropped'
        if self.skipped:
            text += f', {sum(self.skipped.values())} skipped (' + '; '.join(
                f'{reason}: {n}' for reason, n in self.skipped.items()) + ')'
        return text

    def report(self, now: float) -> Report:
        """Summarise the period since the last report and start a new one."""
        seconds = max(now - self._since, 1e-9)
        period, latency, compute = self._period, self._latency_s, self._compute_s
        learnt = self.learnt - self._learnt_before
        values = {
            'maps per second': f'{period["maps"] / seconds:.2f}',
            'frames received per second': f'{period["received"] / seconds:.2f}',
            'latency p50 ms (stamp to map)': _ms(np.median(latency) if latency else None),
            'latency max ms (stamp to map)': _ms(max(latency) if latency else None),
            'model step mean ms': _ms(np.mean(compute) if compute else None),
            'maps learnt from (share)': (f'{learnt / period["maps"]:.2f}'
                                         if period['maps'] else 'n/a'),
            'maps': str(self.maps),
            'frames received': str(self.received),
            'frames dropped': 'unknown (no camera_info)' if self.dropped is None
            else str(self.dropped),
            'frames skipped': str(sum(self.skipped.values())),
        }
        if period['skipped']:
            level, message = WARN, f'skipping frames: {self._last_skip}'
        elif not period['received']:
            level, message = WARN, 'no image received'
        else:
            level, message = OK, f'{period["maps"] / seconds:.1f} maps/s'
        self._since = now
        self._period = dict.fromkeys(period, 0)
        self._learnt_before = self.learnt
        self._latency_s, self._compute_s = [], []
        return Report(level, message, values)


def _ms(seconds: float | None) -> str:
    return 'n/a' if seconds is None else f'{seconds * 1000:.1f}'
