"""
Settings read in more than one place: the ROS parameters, and the core object built from
their values, in one place.

The arm mapping (how the Braccio's joints aim the camera) is declared by the controller,
which steers through it, and by the sim node, whose camera renders what the arm aims at.
The virtual screen is declared by the sim node; bringup and graph-check build the same
screen from its parameter values, without the node.
"""
from activeloc_ros.checks import one_of, Param
from activeloc_ros.control import ArmMapping, HOME_DEG, JOINT_NAMES, pose_problem
from activeloc_ros.errors import ConfigError
from activeloc_ros.screen import ScreenConfig


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


# sim node parameter -> ScreenConfig field
SCREEN_FIELDS = {'screen_width_m': 'screen_width_m', 'screen_height_m': 'screen_height_m',
                 'view_fraction': 'view_fraction', 'distance_m': 'distance_m',
                 'virtual_width': 'width', 'virtual_height': 'height',
                 'virtual_hfov_deg': 'hfov_deg'}
SCREEN_HELP = {
    'screen_width_m': 'virtual screen width, m (paper: 2.214)',
    'screen_height_m': 'virtual screen height, m (paper: 1.245)',
    'view_fraction': "share of the screen's area the virtual camera sees at home (paper: 0.3)",
    'distance_m': 'virtual camera to screen, m (0: set by view_fraction)',
    'virtual_width': 'virtual camera image width, pixels',
    'virtual_height': 'virtual camera image height, pixels',
    'virtual_hfov_deg': 'virtual camera horizontal field of view, degrees',
}


def _screen_check(field: str):
    """ScreenConfig's own check of one field, as a pure parameter check."""
    def check(value):
        try:
            ScreenConfig(**{field: value})
        except (ConfigError, TypeError) as exc:
            return str(exc)
        return None
    return check


SCREEN_PARAMS = tuple(Param(name, getattr(ScreenConfig, field), SCREEN_HELP[name],
                            _screen_check(field), read_only=True)
                      for name, field in SCREEN_FIELDS.items())


def screen_from(values: dict) -> ScreenConfig:
    """The virtual screen's config from validated SCREEN_PARAMS values."""
    return ScreenConfig(**{field: values[name] for name, field in SCREEN_FIELDS.items()})
