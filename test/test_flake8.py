"""
The code passes the checks ament_flake8 runs on a ROS 2 package (its configuration:
Google import order, single quotes, lines up to 99 characters, the plugins it depends on).
The docstring rules (pep257, `D` codes) are ament_pep257's: test_pep257.py.
"""
from pathlib import Path
import subprocess
import sys

import pytest

REPO = Path(__file__).resolve().parents[1]
# ament_flake8's configuration/ament_flake8.ini, without the D codes (pep257's)
ARGS = ['--max-line-length=99', '--import-order-style=google',
        '--application-import-names=activeloc_ros,conftest,test_model,test_screen,'
        'test_trackers', '--extend-ignore=B902,C816,D,I202', '--show-source']


def test_the_code_passes_ament_flake8():
    pytest.importorskip('flake8_import_order', reason="install the 'test' extra")
    done = subprocess.run([sys.executable, '-m', 'flake8', *ARGS, 'activeloc_ros', 'test',
                           'bags/make_sample.py', 'setup.py'], cwd=REPO, capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
