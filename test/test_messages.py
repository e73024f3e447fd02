"""The message conversions every node shares (`activeloc_ros.nodes.messages`)."""
import math

import numpy as np
import pytest
from sensor_msgs.msg import JointState
from std_msgs.msg import Header

from activeloc_ros.control import JOINT_NAMES
from activeloc_ros.control.base import Scan
from activeloc_ros.errors import ConfigError
from activeloc_ros.nodes.messages import (
    arm_joints_deg, joint_state, region_box, region_message, scan_from, scan_message, stamp_ns,
    stamp_s, time_from_ns, time_from_s)


def test_stamps_round_trip_in_nanoseconds_and_seconds():
    stamp = time_from_ns(12_345_678_901)
    assert (stamp.sec, stamp.nanosec) == (12, 345_678_901)
    assert stamp_ns(stamp) == 12_345_678_901
    assert stamp_s(stamp) == pytest.approx(12.345678901)
    # to the nearest nanosecond: 3.9999999999 s is 4 s (cut into sec and nanosec parts
    # separately, it was 3 s and a nanosec part rounded to 0)
    assert stamp_ns(time_from_s(3.9999999999)) == 4_000_000_000
    assert stamp_ns(time_from_s(1.25)) == 1_250_000_000


def test_joint_states_carry_radians_and_are_read_back_by_name():
    pose = [90.0, 80.0, 45.0, 30.0, 90.0, 73.0]
    msg = joint_state(pose, time_from_ns(5))
    assert list(msg.name) == list(JOINT_NAMES) and stamp_ns(msg.header.stamp) == 5
    assert msg.position[0] == pytest.approx(math.pi / 2)
    assert arm_joints_deg(msg) == pytest.approx(pose)
    shuffled = JointState(name=list(reversed(msg.name)) + ['extra'],
                          position=list(reversed(msg.position)) + [0.0])
    assert arm_joints_deg(shuffled) == pytest.approx(pose)        # any order, extras ignored


def test_a_joint_state_without_all_six_joints_is_none():
    msg = joint_state([90.0] * 6)
    assert arm_joints_deg(JointState(name=list(msg.name)[:5],
                                     position=list(msg.position)[:5])) is None
    assert arm_joints_deg(JointState(name=list(msg.name), position=[0.0])) is None


@pytest.mark.parametrize('image_wh', [(320, 240), (640, 480), (1280, 720)])
def test_a_blob_box_crosses_the_wire_unchanged(image_wh):
    """
    The controller in the graph gets the very box the benchmark's controller gets: the
    region's float32 corners lose nothing, so a lockstep graph does not part from the
    benchmark (a box a rounding step off once sent a tracking episode elsewhere).
    """
    from geometry_msgs.msg import PolygonStamped
    from rclpy.serialization import deserialize_message, serialize_message
    from activeloc_ros.metrics import blob_box
    rng = np.random.default_rng(0)
    for _ in range(50):
        heat = rng.random((14, 14)) ** 8
        box = blob_box(heat, image_wh)
        wire = serialize_message(region_message(box, PolygonStamped().header))
        assert region_box(deserialize_message(wire, PolygonStamped)) == box
    assert region_box(PolygonStamped()) is None


def test_a_range_scan_crosses_the_wire_with_no_return_as_inf():
    angles = np.linspace(-math.pi, math.pi, 8, endpoint=False)
    ranges = np.array([1.0, np.inf, 2.5, 0.0, 3.75, np.inf, 0.5, 1.25])   # float32 on the wire
    msg = scan_message(Scan(angles, ranges, 1.5), max_range=4.0, header=Header())
    back = scan_from(msg, 1.5)
    assert np.allclose(back.angles, angles) and np.array_equal(back.ranges, ranges)
    msg.ranges[0] = float('nan')            # a driver's "no reading", and one past its range
    msg.ranges[1] = 7.0
    assert np.all(np.isinf(scan_from(msg, 1.5).ranges[:2]))
    msg.angle_max = 1.0                     # angles that do not fit the ranges
    with pytest.raises(ConfigError, match='angle_max'):
        scan_from(msg, 1.5)
