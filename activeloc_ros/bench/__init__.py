"""Benchmarks: `python -m activeloc_ros.bench {perception,passive,...} --help`."""
