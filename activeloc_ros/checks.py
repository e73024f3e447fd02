"""
Pure value checks for configuration: each returns an error message, or None when valid
(but ``check_field_types``, which raises, for a config dataclass's ``__post_init__``); and
`Param`, a parameter's name, default, description and check, as every node declares it.

ROS-free, so the model's config and the nodes' ROS parameters share them. A closed interval
is a ``Range``, which ``nodes.params`` also writes into the parameter's descriptor (so
``ros2 param describe`` shows it and rclpy enforces it): one declaration, two uses.
"""
from dataclasses import dataclass, fields
import math
import numbers
import os
from typing import Any, Callable, Sequence

from activeloc_ros.errors import ConfigError

Check = Callable[[Any], 'str | None']


def is_number(value) -> bool:
    """
    A real number (int or float, not bool): what the range checks can compare; a string
    such as 'nan' or '1.5' from a command line is not one.
    """
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


@dataclass(frozen=True)
class Range:
    """``lo <= value <= hi`` for a finite value (an infinite bound leaves that side open)."""

    lo: float
    hi: float

    def __call__(self, value) -> 'str | None':
        if not is_number(value):
            return f'must be a number, got {value!r}'
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
    """
    ``value > lo`` for a finite value: an infinite timeout or rate would never act
    (a watchdog that never fires) or overflow where it is used (``Event.wait``).
    """
    def check(value):
        if not is_number(value):
            return f'must be a number, got {value!r}'
        if math.isfinite(value) and value > lo:
            return None
        return f'must be a finite number > {lo}, got {value}'
    return check


def file_or_empty(value) -> 'str | None':
    """An optional path: empty, or a file that exists."""
    if value == '' or os.path.isfile(value):
        return None
    return f'must be empty or an existing file, got {value!r}'


def argument(check: Check, kind: type = float) -> Callable[[str], Any]:
    """
    An argparse ``type`` that parses a command-line word as ``kind`` and applies
    ``check``: ``--timeout nan`` or ``--count -1`` is refused with the check's message.
    """
    import argparse

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            noun = 'whole number' if kind is int else 'number'
            raise argparse.ArgumentTypeError(f'not a {noun}: {text!r}') from None
        problem = check(value)
        if problem:
            raise argparse.ArgumentTypeError(problem)
        return value
    parse.__name__ = kind.__name__        # argparse names the type in its messages
    return parse


def finite(value) -> 'str | None':
    """Any finite number (`nan` and `inf` are refused)."""
    return None if math.isfinite(value) else f'must be a finite number, got {value}'


positive = above(0)
non_negative = at_least(0)
# a camera's horizontal field of view, degrees: near 180 a pinhole's focal length goes to 0
field_of_view = in_range(1.0, 170.0)


def check_field_types(config, what: str = '') -> None:
    """
    Check that every field of a config dataclass holds a value of its annotated kind.

    Float: a number, int: a whole number, bool, str. The first that does not raises
    ConfigError, its text led by ``what``. Values from a command line (``--set hidden=abc``,
    ``width=100.5``) are caught here with the field's name, not by a TypeError where they
    are first used.
    """
    for f in fields(config):
        value, kind = getattr(config, f.name), f.type
        kind = getattr(kind, '__name__', kind)     # a class, or its name as a string
        if kind == 'float' and not is_number(value):
            problem = 'must be a number'
        elif kind == 'int' and (not isinstance(value, numbers.Integral)
                                or isinstance(value, bool)):
            problem = 'must be a whole number'
        elif kind == 'bool' and not isinstance(value, bool):
            problem = 'must be true or false'
        elif kind == 'str' and not isinstance(value, str):
            problem = 'must be a string'
        else:
            continue
        raise ConfigError(f'{what}{f.name} {problem}, got {value!r}')


@dataclass(frozen=True)
class Param:
    name: str
    default: Any
    description: str
    check: Check | None = None
    read_only: bool = False


def validate(params: Sequence[Param], values: dict[str, Any]) -> list[str]:
    """Return one message per invalid value, naming the parameter."""
    by_name = {p.name: p for p in params}
    errors = []
    for name, value in values.items():
        spec = by_name.get(name)
        if spec is not None and spec.check is not None:
            problem = spec.check(value)
            if problem:
                errors.append(f'parameter {name!r} {problem}')
    return errors
