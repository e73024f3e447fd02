"""
The controller node's parameters and the controller configs made from their values,
ROS-free: the node declares them, bringup checks them before any node starts, and the
benchmarks read them.
"""
import math

from activeloc_ros.checks import in_range, non_negative, one_of, Param, positive
from activeloc_ros.control.base import ACTION_SETS, BASE_PD, BaseConfig, FORWARD_RULES
from activeloc_ros.control.braccio import STEP_DELAY_MS_RANGE
from activeloc_ros.control.pd import DERIVATIVE_MODES, PD_VARIANTS, PDConfig
from activeloc_ros.control.reactive import ControllerConfig
from activeloc_ros.errors import ConfigError
from activeloc_ros.settings import mapping_from, MAPPING_PARAMS

# The gains, limits and filters apply at once when set at run time (ros2 param set); the
# servo speed, the mapping and the report period are read-only. Defaults are the core's.
PARAMS = (
    Param('actuator', 'arm', "what the commands move: 'arm' (the Braccio: joint_commands) or "
          "'base' (a mobile base: cmd_vel)", one_of('arm', 'base'), read_only=True),
    Param('pd_variant', '', 'A PD variant of the paper (Table 3) overriding kp/kd: '
          + ', '.join(f'{k}={v}' for k, v in PD_VARIANTS.items()) + '; empty uses kp/kd',
          one_of('', *PD_VARIANTS)),
    Param('kp', PDConfig.kp, 'lambda_p of Eq. 4', non_negative),
    Param('kd', PDConfig.kd, "The arm's: lambda_d of Eq. 4, seconds (the paper's 0.1; a "
          'base keeps its own 0)', non_negative),
    Param('derivative', PDConfig.derivative,
          "The arm's: 'error': d/dt of the camera-frame error, as printed in the paper; "
          "'target': d/dt of the action's direction (a base keeps its own 'target')",
          one_of(*DERIVATIVE_MODES)),
    Param('derivative_tau', PDConfig.derivative_tau,
          'Low-pass time constant on the derivative, s (0: off)', non_negative),
    Param('dead_band_deg', round(math.degrees(PDConfig.dead_band), 9),
          "The arm's: errors below this (per axis, degrees) are ignored (0: the paper; a "
          'base keeps its own 2)', in_range(0.0, 30.0)),
    Param('watchdog_timeout', ControllerConfig.watchdog_timeout,
          'No action location for this long (s): hold still', positive),
    Param('min_peak', ControllerConfig.min_peak,
          "The arm's: ignore action locations whose surprise peak (z) is below this: no "
          'information (a uniform 14x14 map peaks at 1/196 = 0.0051; 0: the paper; a base '
          'keeps its own 0.0102)'),
    Param('settle_time', ControllerConfig.settle_time,
          'Ignore action locations from frames captured while the camera moved or less than '
          'this long after it stopped, s (0: never, the paper)', in_range(0.0, 5.0)),
    Param('confirm_deg', ControllerConfig.confirm_deg,
          "Act on a location that calls for a move only when the previous still frame's "
          'location pointed within this many degrees of it (0: on every location, the '
          'paper; arm only)', in_range(0.0, 180.0)),
    Param('pan_limit_deg', ControllerConfig.pan_limit_deg,
          'Never aim farther than this left or right of the home direction, degrees (the '
          'workspace; the joint limits still apply)', in_range(0.0, 180.0)),
    Param('tilt_limit_deg', ControllerConfig.tilt_limit_deg,
          'Never aim farther than this up or down, degrees', in_range(0.0, 180.0)),
    Param('step_delay_ms', 20, 'Servo step delay, ms per degree (sets the speed limit; must '
          "match the arm's)", in_range(*STEP_DELAY_MS_RANGE), read_only=True),
    *MAPPING_PARAMS,
    # the base (actuator: base; control.base)
    Param('forward', BaseConfig.forward, 'base: how fast to go forward: ' + ', '.join(
        FORWARD_RULES) + ' (control.base)', one_of(*FORWARD_RULES)),
    Param('distance', BaseConfig.distance, 'base: distance to keep, m', positive),
    Param('distance_gain', BaseConfig.distance_gain,
          'base: forward speed per metre of distance error, 1/s', non_negative),
    Param('pace', BaseConfig.pace, 'base: forward speed of the constant rule, m/s',
          non_negative),
    Param('max_speed', BaseConfig.max_speed, 'base: top forward speed, m/s', positive),
    Param('max_reverse', BaseConfig.max_reverse, 'base: top backward speed when the target '
          'is nearer than distance, m/s (0: never back away)', non_negative),
    Param('max_turn_deg_s', BaseConfig.max_turn_deg_s, 'base: top turn rate, deg/s', positive),
    Param('camera_height', BaseConfig.camera_height, "base: the camera's height, m",
          positive),
    Param('camera_tilt_deg', BaseConfig.camera_tilt_deg,
          "base: the camera's tilt above the horizon, degrees", in_range(-89.0, 89.0)),
    Param('actions', BaseConfig.actions, "base: 'continuous' or AD-VAT's seven 'discrete' "
          'actions', one_of(*ACTION_SETS)),
    Param('avoid', BaseConfig.avoid, 'base: go round obstacles the range scan (scan) shows'),
    Param('avoid_reach', BaseConfig.avoid_reach, 'base: how far ahead the path must be clear, '
          'm', positive),
    Param('avoid_radius', BaseConfig.avoid_radius, 'base: half the width of the clear path, m',
          positive),
    Param('avoid_max_deg', BaseConfig.avoid_max_deg, 'base: the farthest to head from the '
          'action to go round an obstacle, degrees', in_range(0.0, 90.0)),
    Param('latency_report_period', 10.0, 'Log frame-to-command latency p50/p95 every this '
          'many seconds (0: only at shutdown)', non_negative, read_only=True),
)


# the PD law's settings, in the node's names and units (the dead band in degrees)
PD_PARAMS = ('kp', 'kd', 'dead_band_deg', 'derivative', 'derivative_tau')
# the base's own values of the arm's PD settings (kp, derivative_tau and pd_variant are
# both's)
BASE_PD_SETTINGS = {'kd': BASE_PD.kd, 'derivative': BASE_PD.derivative,
                    'dead_band_deg': math.degrees(BASE_PD.dead_band)}


def pd_from(settings: dict, variant: str = '') -> PDConfig:
    """
    The PD law from those of `PD_PARAMS` that ``settings`` holds (the core's defaults for
    the rest): a Table 3 ``variant``'s gains, whatever kp and kd say, else kp and kd.
    """
    options = {name: settings[name] for name in PD_PARAMS if name in settings}
    if 'dead_band_deg' in options:
        options['dead_band'] = math.radians(options.pop('dead_band_deg'))
    if variant:
        return PDConfig.variant(variant, **{k: v for k, v in options.items()
                                            if k not in ('kp', 'kd')})
    return PDConfig(**options)


def config_from(values: dict) -> ControllerConfig:
    """The core's config from validated parameter values (raises ConfigError)."""
    return ControllerConfig(pd=pd_from(values, values['pd_variant']),
                            mapping=mapping_from(values),
                            watchdog_timeout=values['watchdog_timeout'],
                            step_delay_ms=values['step_delay_ms'], min_peak=values['min_peak'],
                            settle_time=values['settle_time'],
                            confirm_deg=values['confirm_deg'],
                            pan_limit_deg=values['pan_limit_deg'],
                            tilt_limit_deg=values['tilt_limit_deg'])


BASE_PARAMS = ('forward', 'distance', 'distance_gain', 'pace', 'max_speed', 'max_reverse',
               'max_turn_deg_s', 'camera_height', 'camera_tilt_deg', 'actions', 'avoid',
               'avoid_reach', 'avoid_radius', 'avoid_max_deg')
# the settings only the arm's controller reads (its joint mapping and servo speed are
# read-only besides)
ARM_PARAMS = ('settle_time', 'confirm_deg', 'pan_limit_deg', 'tilt_limit_deg', 'step_delay_ms',
              'min_peak', *BASE_PD_SETTINGS, *(p.name for p in MAPPING_PARAMS))


def unread(actuator: str) -> tuple[str, ...]:
    """The parameters the controller of ``actuator`` does not read: the other one's."""
    return ARM_PARAMS if actuator == 'base' else BASE_PARAMS


def unread_reason(actuator: str, count: int = 1) -> str:
    """Why ``count`` settings of the other actuator do nothing on ``actuator``'s controller."""
    return (f'this controller drives {"a mobile base" if actuator == "base" else "the arm"} '
            f'(actuator {actuator!r}), which does not read {"it" if count == 1 else "them"}')


def base_config_from(values: dict) -> BaseConfig:
    """
    The base controller's config from validated parameter values (raises ConfigError):
    kp (or a PD variant's gains) and the watchdog the arm's would have, its own kd,
    derivative, dead band and information rule (those parameters are the arm's), and the
    base's own settings.
    """
    settings = {**values, **BASE_PD_SETTINGS}
    return BaseConfig(pd=pd_from(settings, values['pd_variant']),
                      watchdog_timeout=values['watchdog_timeout'],
                      **{name: values[name] for name in BASE_PARAMS})


def check_change(values: dict, changed: set) -> 'str | None':
    """
    Refuse a run-time change that would be accepted but have no effect, or a set of
    values the core refuses.
    """
    moot = sorted(changed & set(unread(values['actuator'])))
    if moot:
        return (f'{", ".join(moot)} would have no effect: '
                + unread_reason(values['actuator'], len(moot)))
    ignored = sorted(changed & {'kp', 'kd'})
    if values['pd_variant'] and ignored and 'pd_variant' not in changed:
        return (f'{", ".join(ignored)} would have no effect: pd_variant '
                f'{values["pd_variant"]!r} sets the gains; set pd_variant to \'\' with them')
    try:
        base_config_from(values) if values['actuator'] == 'base' else config_from(values)
    except ConfigError as exc:
        return str(exc)
    return None
