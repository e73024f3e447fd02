"""Settings more than one node declares: the same ROS parameters, and the core object built
from their values, in one place.

The arm mapping (how the Braccio's joints aim the camera) is declared by the controller,
which steers through it, and by the virtual camera, which renders what the arm aims at.
"""
from activeloc_ros.checks import one_of
from activeloc_ros.control import ArmMapping, HOME_DEG, JOINT_NAMES, pose_problem
from activeloc_ros.nodes.ros_params import Param


def _joint_names(value) -> 'str | None':
    bad = [n for n in value if n not in JOINT_NAMES]
    return f'unknown joints {bad}; joints are {list(JOINT_NAMES)}' if bad else None


# How joints aim the camera. Fixed at start-up: they describe the arm and the camera mount,
# which do not change mid-run.
MAPPING_PARAMS = (
    Param('home_deg', list(HOME_DEG), 'Home pose (degrees, camera straight ahead)',
          pose_problem, read_only=True),
    Param('pan_joint', 'base', 'Joint that pans the camera', one_of(*JOINT_NAMES),
          read_only=True),
    Param('pan_gain', 1.0, 'Degrees of pan joint per degree of pan (negative flips)',
          read_only=True),
    Param('tilt_joints', ['wrist_ver'], 'Joints that tilt the camera', _joint_names,
          read_only=True),
    Param('tilt_gains', [1.0], 'Degrees of each tilt joint per degree of tilt',
          read_only=True),
)


def mapping_from(values: dict) -> ArmMapping:
    """The arm mapping from validated MAPPING_PARAMS values (raises ConfigError)."""
    return ArmMapping(home_deg=tuple(values['home_deg']), pan_joint=values['pan_joint'],
                      pan_gain=values['pan_gain'], tilt_joints=tuple(values['tilt_joints']),
                      tilt_gains=tuple(values['tilt_gains']))
