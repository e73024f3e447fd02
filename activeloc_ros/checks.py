"""Pure value checks for configuration: each returns an error message, or None when valid.

ROS-free, so the model's config and the nodes' ROS parameters share them.
"""
from typing import Any, Callable

Check = Callable[[Any], 'str | None']


def one_of(*choices: str) -> Check:
    def check(value):
        return None if value in choices else f'must be one of {list(choices)}, got {value!r}'
    return check


def in_range(lo: float, hi: float) -> Check:
    def check(value):
        return None if lo <= value <= hi else f'must be in [{lo}, {hi}], got {value}'
    return check


def at_least(lo: float) -> Check:
    def check(value):
        return None if value >= lo else f'must be >= {lo}, got {value}'
    return check


def above(lo: float) -> Check:
    def check(value):
        return None if value > lo else f'must be > {lo}, got {value}'
    return check


positive = above(0)
non_negative = at_least(0)
