"""Shared fixtures: a per-test rclpy Context, an isolated DDS domain, the data root."""
import os
from pathlib import Path
import time

import pytest

# Before any rclpy import: keep DDS traffic on this machine and away from other runs.
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
# Domains stay within 0-101, the range ROS 2 calls safe on Linux: above it the DDS ports
# fall among the ephemeral ports other sockets are given.
os.environ.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % 50))
# graphs run as processes use another domain: nodes a failed in-process test leaves behind
# must not join them
GRAPH_DOMAIN = str(51 + os.getpid() % 50)

REPO = Path(__file__).resolve().parents[1]
PARAMS = REPO / 'params'


@pytest.fixture
def context():
    import rclpy
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.try_shutdown(context=ctx)


@pytest.fixture
def graph_env():
    """The environment for a graph run as processes (bringup) in its own domain."""
    return dict(os.environ, ROS_DOMAIN_ID=GRAPH_DOMAIN, PYTHONPATH=str(REPO),
                ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')


def spin_until(executor, condition, timeout):
    """Spin `executor` until `condition()` holds or `timeout` seconds pass; return it."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not condition():
        executor.spin_once(timeout_sec=0.02)
    return condition()


def params_args(*extra: str) -> list[str]:
    """
    cli_args loading the package's params file as bringup gives it to every node (the
    robot's), then `-p name:=value` extras.
    """
    args = ['--ros-args', '--params-file', str(PARAMS / 'robot.yaml')]
    for item in extra:
        args += ['-p', item]
    return args


@pytest.fixture(scope='session')
def data_root() -> Path:
    root = Path(os.environ.get('ACTIVELOC_DATA', REPO.parent / 'shared' / 'data' / 'sequences'))
    if not root.is_dir():
        pytest.skip(f'annotated sequences not found at {root} (set ACTIVELOC_DATA)')
    return root


def pytest_configure(config):
    # rosidl's parser (lark) imports modules Python 3.11 deprecates; not ours to fix.
    config.addinivalue_line('filterwarnings', 'ignore::DeprecationWarning:lark.*')
