"""The graph in lockstep moves the camera exactly as the screen benchmark's closed loop."""
import math
import re

import pytest

from activeloc_ros.bench import graph_check
from conftest import GRAPH_DOMAIN


def test_compare_reports_the_largest_difference():
    graph = [(0.0, 0.0, 0.0), (0.1, math.radians(3.0), 0.0)]
    ok, report = graph_check.compare(graph, [(0.0, 0.0, 0.0), (0.1, math.radians(3.2), 0.0)],
                                     0.5)
    assert ok and '0.2000 deg' in report
    ok, report = graph_check.compare(graph, [(0.0, 0.0, 0.0), (0.1, 0.0, 0.0)], 0.5)
    assert not ok and 'DIFFERENT' in report
    assert not graph_check.compare(graph, graph[:1], 0.5)[0]            # a frame missing
    assert 'times differ' in graph_check.compare(graph, [(0.0, 0, 0), (0.2, 0, 0)], 0.5)[1]


def test_bundled_bag_graph_and_benchmark_agree(capfd, monkeypatch):
    """
    bringup (four processes, real DDS, packaged params) against run_episode. The
    recording holds every frame's map: the sim starts once bringup hears perception.
    """
    monkeypatch.setenv('ROS_DOMAIN_ID', GRAPH_DOMAIN)
    assert graph_check.main(['--frames', '6']) == 0
    out = capfd.readouterr().out          # bringup's summary included
    assert 'frames: graph 6, bench 6' in out and 'SAME' in out
    # every frame's map recorded, and the controller's commands (how many depends on the
    # controller's settings: with the paper's min_peak 0 the first map is acted on too)
    assert '/surprise_map 6,' in out and re.search(r'/joint_commands [1-9]\d*,', out)


def test_bad_options(capsys):
    assert graph_check.main(['--frames', '0']) == 2
    with pytest.raises(SystemExit) as exc:
        graph_check.main(['--help'])
    assert exc.value.code == 0
