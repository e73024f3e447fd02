"""Benchmarks: `python -m activeloc_ros.bench {perception,passive,screen,...} --help`."""
import json

from activeloc_ros.errors import ConfigError


def names(values: list[str] | None) -> list[str]:
    """Command-line names given as separate words or comma-separated."""
    return [v for item in values or [] for v in item.split(',') if v]


def key_values(items: list[str], option: str) -> dict:
    """KEY=VALUE words as a dict; values are JSON when they parse, else strings."""
    out = {}
    for item in items:
        key, sep, value = item.partition('=')
        if not sep or not key:
            raise ConfigError(f'{option} expects KEY=VALUE, got {item!r}')
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out
