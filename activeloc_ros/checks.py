"""Pure value checks for configuration: each returns an error message, or None when valid.

ROS-free, so the model's config and the nodes' ROS parameters share them. A closed interval
is a ``Range``, which ``ros_params`` also writes into the parameter's descriptor (so
``ros2 param describe`` shows it and rclpy enforces it): one declaration, two uses.
"""
from dataclasses import dataclass
import math
from typing import Any, Callable

Check = Callable[[Any], 'str | None']


@dataclass(frozen=True)
class Range:
    """``lo <= value <= hi`` for a finite value (an infinite bound leaves that side open)."""

    lo: float
    hi: float

    def __call__(self, value) -> 'str | None':
        if math.isfinite(value) and self.lo <= value <= self.hi:
            return None
        if math.isinf(self.hi):
            return f'must be >= {self.lo}, got {value}'
        return f'must be in [{self.lo}, {self.hi}], got {value}'


def one_of(*choices: str) -> Check:
    def check(value):
        return None if value in choices else f'must be one of {list(choices)}, got {value!r}'
    return check


def in_range(lo: float, hi: float) -> Range:
    return Range(lo, hi)


def at_least(lo: float) -> Range:
    return Range(lo, math.inf)


def above(lo: float) -> Check:
    """``value > lo`` for a finite value: an infinite timeout or rate would never act
    (a watchdog that never fires) or overflow where it is used (``Event.wait``)."""
    def check(value):
        if math.isfinite(value) and value > lo:
            return None
        return f'must be a finite number > {lo}, got {value}'
    return check


positive = above(0)
non_negative = at_least(0)
# a camera's horizontal field of view, degrees: near 180 a pinhole's focal length goes to 0
field_of_view = in_range(1.0, 170.0)
