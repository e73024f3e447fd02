"""
The TinkerKit Braccio: joint names, limits, home pose, pan/tilt mapping and a command guard.

Joint angles are in whole or fractional degrees, as the Braccio library takes them; camera
pan and tilt are in radians. Sign conventions: pan > 0 turns the camera to its left (counter-
clockwise seen from above, REP 103), tilt > 0 raises it.

The default home pose and gains assume the camera is fixed to the gripper looking along the
last link, with every joint bending the same way as its angle grows (as the library's folded
"safety" pose 0/40/180/170/0/73 suggests): shoulder upright (90), elbow and wrist bent 45
degrees each, so the camera looks straight ahead, horizontal, with 45 degrees of tilt room
either way on the wrist. Check the signs on the real arm and flip a gain if needed.
"""
from dataclasses import dataclass, field
import math
from typing import Mapping, Sequence

from activeloc_ros.errors import ConfigError

JOINT_NAMES: tuple[str, ...] = (
    'base', 'shoulder', 'elbow', 'wrist_ver', 'wrist_rot', 'gripper')

LIMITS_DEG: Mapping[str, tuple[int, int]] = {
    'base': (0, 180),
    'shoulder': (15, 165),
    'elbow': (0, 180),
    'wrist_ver': (0, 180),
    'wrist_rot': (0, 180),
    'gripper': (10, 73),
}

# Camera straight ahead (see the module docstring); the gripper closed on the camera mount.
HOME_DEG: tuple[int, ...] = (90, 90, 45, 45, 90, 73)

# Where Braccio.begin() puts the arm at power-up (the library's "safety" pose).
SAFETY_DEG: tuple[int, ...] = (0, 40, 180, 170, 0, 73)

# ServoMovement's stepDelay: milliseconds per degree.
STEP_DELAY_MS_RANGE: tuple[int, int] = (10, 30)

_LO = tuple(LIMITS_DEG[n][0] for n in JOINT_NAMES)
_HI = tuple(LIMITS_DEG[n][1] for n in JOINT_NAMES)


def speed_deg_s(step_delay_ms: float) -> float:
    """Servo speed in degrees per second for a ServoMovement step delay (ms per degree)."""
    lo, hi = STEP_DELAY_MS_RANGE
    if not lo <= step_delay_ms <= hi:
        raise ConfigError(f'step delay must be in [{lo}, {hi}] ms per degree, got {step_delay_ms}')
    return 1000.0 / step_delay_ms


def within_limits(joints_deg: Sequence[float], *, tol: float = 0.0) -> bool:
    """True when all six angles are finite and inside the Braccio limits (+- tol)."""
    return len(joints_deg) == len(JOINT_NAMES) and all(
        math.isfinite(q) and lo - tol <= q <= hi + tol
        for q, lo, hi in zip(joints_deg, _LO, _HI))


def clamp_to_limits(joints_deg: Sequence[float]) -> tuple[float, ...]:
    """Clamp six finite angles into the limits; raises ConfigError on a wrong length or NaN."""
    if len(joints_deg) != len(JOINT_NAMES):
        raise ConfigError(f'need {len(JOINT_NAMES)} joint angles, got {len(joints_deg)}')
    if not all(math.isfinite(q) for q in joints_deg):
        raise ConfigError(f'joint angles must be finite, got {tuple(joints_deg)}')
    return tuple(min(max(float(q), lo), hi) for q, lo, hi in zip(joints_deg, _LO, _HI))


def pose_problem(value: Sequence[float]) -> 'str | None':
    """A parameter check: why `value` is not a pose inside the limits, or None."""
    try:
        check_pose(value)
    except ConfigError as exc:
        return str(exc)
    return None


def check_pose(joints_deg: Sequence[float], what: str = 'pose') -> tuple[float, ...]:
    """Return the pose as a tuple; raise ConfigError unless it is inside the limits."""
    pose = tuple(float(q) for q in joints_deg)
    if not within_limits(pose):
        raise ConfigError(f'{what} {pose} is outside the Braccio limits {dict(LIMITS_DEG)}')
    return pose


def fixed_moves(target_deg: Sequence[float], current_deg: Sequence[float], *,
                home_deg: Sequence[float], aiming: Sequence[str],
                tolerance: float = 0.5) -> dict[str, float]:
    """
    The joints not in ``aiming`` that ``target_deg`` would move away from both their home
    angle and ``current_deg``: name -> target, degrees. A command with any is refused
    (moving such a joint towards home, or leaving it, is allowed): nobody but the
    configuration moves the gripper that holds the camera.
    """
    return {name: float(q) for name, q, now, h in
            zip(JOINT_NAMES, target_deg, current_deg, home_deg)
            if name not in aiming and abs(q - h) > tolerance and abs(q - now) > tolerance}


def refusal_text(moved: Mapping[str, float], aiming: Sequence[str], count: int) -> str:
    """The warning for a command refused by `fixed_moves`."""
    return ('refused a joint command that moves '
            + ', '.join(f'{n} to {q:.1f} deg' for n, q in moved.items())
            + f': only {", ".join(aiming)} aim the camera, the other joints stay at home '
            f'(params/robot.yaml) ({count} refused so far)')


def clamp_text(target: Sequence[float], safe: Sequence[float], count: int) -> str:
    """The warning for a command clamped into the joint limits."""
    return ('clamped a joint command outside the limits: '
            + ', '.join(f'{n} {q:.1f} -> {c:.1f} deg'
                        for n, q, c in zip(JOINT_NAMES, target, safe) if q != c)
            + f' ({count} so far)')


@dataclass(frozen=True)
class ArmMapping:
    """
    Camera pan/tilt <-> joint angles around a home pose.

    ``joint = home + gain * angle_deg``: pan drives ``pan_joint`` only; tilt is shared by
    ``tilt_joints`` with ``tilt_gains`` (degrees of joint per degree of camera tilt; for a
    chain of parallel joints the magnitudes should sum to 1). A negative gain flips a sign.
    """

    home_deg: tuple[float, ...] = HOME_DEG
    pan_joint: str = 'base'
    pan_gain: float = 1.0
    tilt_joints: tuple[str, ...] = ('wrist_ver',)
    tilt_gains: tuple[float, ...] = (1.0,)
    _index: dict = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        object.__setattr__(self, 'home_deg', check_pose(self.home_deg, 'home pose'))
        object.__setattr__(self, 'tilt_joints', tuple(self.tilt_joints))
        object.__setattr__(self, 'tilt_gains', tuple(float(g) for g in self.tilt_gains))
        names = (self.pan_joint, *self.tilt_joints)
        unknown = [n for n in names if n not in JOINT_NAMES]
        if unknown:
            raise ConfigError(f'unknown joint(s) {unknown}; joints are {list(JOINT_NAMES)}')
        if len(set(names)) != len(names):
            raise ConfigError(f'pan and tilt joints must be distinct, got {list(names)}')
        if not self.tilt_joints or len(self.tilt_joints) != len(self.tilt_gains):
            raise ConfigError('need one tilt gain per tilt joint and at least one tilt joint, '
                              f'got {list(self.tilt_joints)} / {list(self.tilt_gains)}')
        gains = (self.pan_gain, *self.tilt_gains)
        if not all(math.isfinite(g) and g != 0.0 for g in gains):
            raise ConfigError(f'pan/tilt gains must be finite and non-zero, got {list(gains)}')
        object.__setattr__(self, '_index', {n: i for i, n in enumerate(JOINT_NAMES)})

    def joints_deg(self, pan: float, tilt: float) -> tuple[float, ...]:
        """Joint angles (degrees, not clamped) that point the camera at (pan, tilt) radians."""
        q = list(self.home_deg)
        q[self._index[self.pan_joint]] += self.pan_gain * math.degrees(pan)
        for name, gain in zip(self.tilt_joints, self.tilt_gains):
            q[self._index[name]] += gain * math.degrees(tilt)
        return tuple(q)

    @property
    def aiming_joints(self) -> tuple[str, ...]:
        """The joints that aim the camera; every other one stays at home."""
        return (self.pan_joint, *self.tilt_joints)

    def aim_only(self, joints_deg: Sequence[float]) -> tuple[float, ...]:
        """
        ``joints_deg`` with every joint that does not aim the camera at its home angle: a
        pose reported or commanded by anyone else never moves those (the gripper holds the
        camera).
        """
        aiming = self.aiming_joints
        return tuple(float(q) if name in aiming else h
                     for name, q, h in zip(JOINT_NAMES, joints_deg, self.home_deg))

    def fixed_moves(self, target_deg: Sequence[float], current_deg: Sequence[float]
                    ) -> dict[str, float]:
        """`fixed_moves` of this mapping's home pose and aiming joints."""
        return fixed_moves(target_deg, current_deg, home_deg=self.home_deg,
                           aiming=self.aiming_joints)

    def pan_tilt(self, joints_deg: Sequence[float]) -> tuple[float, float]:
        """Camera (pan, tilt) in radians of a joint pose (least squares over the tilt joints)."""
        i = self._index[self.pan_joint]
        pan = (joints_deg[i] - self.home_deg[i]) / self.pan_gain
        num = den = 0.0
        for name, gain in zip(self.tilt_joints, self.tilt_gains):
            j = self._index[name]
            num += gain * (joints_deg[j] - self.home_deg[j])
            den += gain * gain
        return math.radians(pan), math.radians(num / den)


class JointGuard:
    """
    Keeps every command inside the joint limits and within the servos' speed.

    Each command may move a joint at most ``1000 / step_delay_ms * (t - t_prev)`` degrees
    from the previous command; time that runs backwards or is not finite allows no motion.
    """

    def __init__(self, start_deg: Sequence[float], t0: float, *, step_delay_ms: float = 20.0):
        self.speed = speed_deg_s(step_delay_ms)
        self.last_deg = clamp_to_limits(start_deg)
        self.last_t = float(t0) if math.isfinite(t0) else 0.0

    def reset(self, joints_deg: Sequence[float], t: float) -> None:
        """Restart from a known pose (e.g. the arm's measured state)."""
        self.last_deg = clamp_to_limits(joints_deg)
        if math.isfinite(t):
            self.last_t = float(t)

    def limit(self, target_deg: Sequence[float], t: float) -> tuple[float, ...]:
        """The closest command to ``target_deg`` that the arm can follow at time ``t``."""
        if len(target_deg) != len(JOINT_NAMES):
            raise ConfigError(f'need {len(JOINT_NAMES)} joint angles, got {len(target_deg)}')
        dt = t - self.last_t if math.isfinite(t) else 0.0
        step = self.speed * dt if dt > 0.0 else 0.0
        out = []
        for q, prev, lo, hi in zip(target_deg, self.last_deg, _LO, _HI):
            if not math.isfinite(q):
                q = prev
            q = min(max(q, lo), hi)
            q = prev + min(max(q - prev, -step), step)
            out.append(min(max(q, lo), hi))  # again: float rounding must not leave the limits
        self.last_deg = tuple(out)
        if dt > 0.0:
            self.last_t = float(t)
        return self.last_deg
