"""
Conversions between the ROS messages the nodes exchange and the core's plain values, in
the spirit of cv_bridge (images: `images`).

Stamps: a `builtin_interfaces/Time` (or anything with `sec` and `nanosec`) to and from
integer nanoseconds or float seconds. Joints: `sensor_msgs/JointState` carries radians; the
core works in degrees. Regions: a box (x, y, w, h; px) as a `geometry_msgs/PolygonStamped`
of its two corners. Range scans: a `control.base.Scan` as a `sensor_msgs/LaserScan` (REP
117: +inf where nothing lies within range). Reading needs no ROS; the message types are
imported only to build messages.
"""
import importlib
import math
from typing import Sequence

import numpy as np

from activeloc_ros.control import JOINT_NAMES
from activeloc_ros.control.base import Scan
from activeloc_ros.errors import ConfigError


def stamp_ns(stamp) -> int:
    """Integer nanoseconds of a stamp."""
    return stamp.sec * 10**9 + stamp.nanosec


def stamp_s(stamp) -> float:
    """Float seconds of a stamp."""
    return stamp.sec + stamp.nanosec * 1e-9


def time_from_ns(ns: int):
    """A builtin_interfaces/Time of integer nanoseconds."""
    from builtin_interfaces.msg import Time
    return Time(sec=ns // 10**9, nanosec=ns % 10**9)


def time_from_s(t: float):
    """A builtin_interfaces/Time of float seconds, to the nearest nanosecond."""
    return time_from_ns(round(t * 1e9))


def joint_state(joints_deg: Sequence[float], stamp=None):
    """
    A sensor_msgs/JointState of the six Braccio joints at ``joints_deg`` (radians on the
    wire), stamped with ``stamp``.
    """
    from sensor_msgs.msg import JointState
    msg = JointState(name=list(JOINT_NAMES), position=[math.radians(q) for q in joints_deg])
    if stamp is not None:
        msg.header.stamp = stamp
    return msg


def camera_info(k, width: int, height: int, header):
    """A sensor_msgs/CameraInfo of a distortion-free pinhole camera with matrix ``k`` (3x3)."""
    from sensor_msgs.msg import CameraInfo
    info = CameraInfo(header=header, width=width, height=height, distortion_model='plumb_bob')
    info.k = [float(v) for v in k.ravel()]
    info.d = [0.0] * 5
    info.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    info.p = [float(k[0, 0]), 0.0, float(k[0, 2]), 0.0,
              0.0, float(k[1, 1]), float(k[1, 2]), 0.0, 0.0, 0.0, 1.0, 0.0]
    return info


def region_message(box: Sequence[float], header):
    """
    A geometry_msgs/PolygonStamped of the box's top-left and bottom-right corners (float32
    on the wire: `metrics.blob_box` gives corners that survive it exactly).
    """
    from geometry_msgs.msg import Point32, PolygonStamped
    x, y, w, h = (float(v) for v in box)
    msg = PolygonStamped(header=header)
    msg.polygon.points = [Point32(x=x, y=y), Point32(x=x + w, y=y + h)]
    return msg


def region_box(msg) -> tuple[float, float, float, float] | None:
    """The box (x, y, w, h) of a `region_message`; None unless it has two corners."""
    points = msg.polygon.points
    if len(points) != 2:
        return None
    return (points[0].x, points[0].y, points[1].x - points[0].x, points[1].y - points[0].y)


def arm_joints_deg(msg) -> list[float] | None:
    """
    The six Braccio joints in degrees, in `JOINT_NAMES` order, from a JointState that
    names them all (in any order, among others); None if it does not.
    """
    index = {name: i for i, name in enumerate(msg.name)}
    if len(msg.position) != len(msg.name) or any(n not in index for n in JOINT_NAMES):
        return None
    return [math.degrees(msg.position[index[n]]) for n in JOINT_NAMES]


def scan_message(scan: Scan, *, max_range: float, header):
    """
    A sensor_msgs/LaserScan of a `Scan` whose rays are evenly spaced, counterclockwise
    from ``scan.angles[0]`` (ranges beyond ``max_range``: +inf).
    """
    from sensor_msgs.msg import LaserScan
    angles = scan.angles
    step = float(angles[1] - angles[0]) if len(angles) > 1 else 0.0
    return LaserScan(header=header, angle_min=float(angles[0]), angle_max=float(angles[-1]),
                     angle_increment=step, range_min=0.0, range_max=float(max_range),
                     ranges=[float(r) for r in scan.ranges])


def scan_from(msg, t: float) -> Scan:
    """
    The `Scan` of a sensor_msgs/LaserScan taken at ``t`` (s): returns outside
    [range_min, range_max] are no return (inf); ConfigError for a scan whose angles do not
    fit its ranges.
    """
    ranges = np.asarray(msg.ranges, float)
    n = len(ranges)
    if n == 0 or not (math.isfinite(msg.angle_min) and math.isfinite(msg.angle_increment)):
        raise ConfigError('a LaserScan needs ranges and finite angles')
    if n > 1 and not math.isclose(msg.angle_min + (n - 1) * msg.angle_increment,
                                  msg.angle_max, abs_tol=1e-3):
        raise ConfigError(f'a LaserScan of {n} ranges from {msg.angle_min:.4f} by '
                          f'{msg.angle_increment:.4f} rad does not end at its angle_max '
                          f'{msg.angle_max:.4f}')
    valid = (ranges >= msg.range_min) & (ranges <= msg.range_max)   # NaN: no return either
    return Scan(msg.angle_min + msg.angle_increment * np.arange(n),
                np.where(valid, ranges, np.inf), t)


def message_class(msgtype: str):
    """The Python class of a message type named ``package/msg/Name``."""
    package, kind, name = msgtype.split('/')
    return getattr(importlib.import_module(f'{package}.{kind}'), name)
