"""
The reactive controller of a mobile base (the tracking experiment, paper Sec. 4.1):
action pixel -> bearing error -> the paper's PD law -> a velocity command.

The PD law (Eq. 4) gives the change of heading that centres the action; the base makes it
over one control step, so the turn rate is that change divided by the step, within the
base's limit. The paper's PD only turns; how fast to go forward is our own rule
(``forward``), a proportional law on the distance to keep (``distance``) from what the
pointer says is at the location (its box: a tracker's, the true one, the surprise map's
blob):

- ``ground`` (default): the distance from where the box stands on the ground. The camera's
  height and tilt are known, so the image row of the box's bottom gives the distance to its
  foot on a flat floor;
- ``size``: keep the box as large as it first was (the median of the first ``size_frames``
  boxes, taken while the target stands at the start distance); the distance is inversely
  proportional to the box's size (square root of its area);
- ``constant``: ``pace`` m/s whenever a location is accepted;
- ``none``: turn only.

The speed is ``distance_gain`` times the distance error, within ``-max_reverse`` and
``max_speed``: a target nearer than ``distance`` makes the base back away, so a person who
turns back is not lost past the edge of the view (docs/tracking.md); without a box
the base keeps ``pace``. It slows as cos(bearing error): it turns first, then goes. No
location for ``watchdog_timeout`` s stops the base. ``actions: discrete`` snaps each command
to AD-VAT's seven actions (stop, forward, backward, turn left or right, forward and turn
left or right).

Going round obstacles (``avoid``, our addition too: the paper's reactive agent has no
planner, and a base that drives straight at the person slides only slowly round a tree
between them, docs/tracking.md): with a planar range scan (`Scan`), a base going forward heads
for the direction nearest the PD's that leaves a corridor ``avoid_radius`` wide on each
side clear for ``avoid_reach`` m, looking no more than ``avoid_max_deg`` away from the
action so that it stays in view; when every such direction is blocked it only turns. Off by
default: the oracle keeps the person far longer with it, but ours' base, reading a person's
distance from its map's blob less well, takes her for an obstacle and steers round her.

All times are explicit arguments in seconds; nothing here reads a clock.
"""
from dataclasses import dataclass, field
import math
import statistics

import numpy as np

from activeloc_ros.checks import check_field_types
from activeloc_ros.control.geometry import angular_error, Intrinsics
from activeloc_ros.control.pd import PDConfig, PDController
from activeloc_ros.control.reactive import (
    controller_state, LatencyStats, location_problem)
from activeloc_ros.errors import ConfigError

FORWARD_RULES = ('ground', 'size', 'constant', 'none')
ACTION_SETS = ('continuous', 'discrete')
# the base's PD law, its own since the arm's returned to the paper's (kd 0.1 on the error,
# no dead band): no derivative (on the action's direction, were one set), a 2 deg dead band
BASE_PD = PDConfig(kd=0.0, derivative='target', dead_band=math.radians(2.0))


@dataclass(frozen=True)
class Twist:
    """A base's velocity: forward (m/s) and turn rate (rad/s, > 0 = left)."""

    forward: float = 0.0
    turn: float = 0.0


@dataclass(frozen=True)
class Scan:
    """
    A planar range scan from the base: ``ranges`` (m; inf: nothing within range) along
    ``angles`` (radians from the base's heading, > 0 left), taken at ``t`` (s).
    """

    angles: np.ndarray
    ranges: np.ndarray
    t: float


def clear_direction(scan: Scan, want: float, action: float, *, reach: float, radius: float,
                    max_detour: float, resolution: float = math.radians(2.0)
                    ) -> float | None:
    """
    The direction (radians from the heading) nearest ``want`` whose corridor, ``radius``
    m to each side and ``reach`` m long, holds no scan return, among the directions at most
    ``max_detour`` from ``action`` (the action's direction); None when all are blocked.
    """
    seen = np.isfinite(scan.ranges)
    px = scan.ranges[seen] * np.cos(scan.angles[seen])
    py = scan.ranges[seen] * np.sin(scan.angles[seen])
    steps = int(max_detour // resolution)
    candidates = action + resolution * np.arange(-steps, steps + 1)
    candidates = candidates[np.argsort(np.abs(candidates - want), kind='stable')]
    if abs(want - action) <= max_detour:
        candidates = np.concatenate([[want], candidates])
    for h in candidates:
        along = px * math.cos(h) + py * math.sin(h)
        across = -px * math.sin(h) + py * math.cos(h)
        if not np.any((along > 0) & (along <= reach) & (np.abs(across) < radius)):
            return float(h)
    return None


@dataclass(frozen=True)
class BaseConfig:
    """
    Everything the base controller needs besides the intrinsics.

    :param step: the control period (s) over which the PD's heading change is made.
    :param camera_tilt_deg: the camera's fixed tilt above the horizon.
    :param camera_height: the camera's height above the floor, m (the ``ground`` rule).
    :param distance: the distance to keep, m (AD-VAT's 2.5).
    :param distance_gain: forward speed per metre of distance error, 1/s.
    :param max_reverse: top backward speed (m/s) when the target is nearer than
        ``distance``; 0: never back away (AD-VAT's action set has a backward action).
    :param min_peak: as the arm controller's: a weaker map carries no information. The
        base keeps 0.0102, a 2 deg dead band and kd 0 (`BASE_PD`) where the arm returned
        to the paper's values: only the tracking benchmark judges the base's.
    :param discrete_speed: forward speed (m/s) of AD-VAT's moving actions.
    :param discrete_turn_deg_s: turn rate of its turning actions.
    :param avoid: go round obstacles the range scan shows (needs scans: `observe_scan`).
    :param avoid_reach: how far ahead the path must be clear, m.
    :param avoid_radius: half the width of the clear path, m (the base's radius and a
        margin).
    :param avoid_max_deg: the farthest the base heads from the action's direction to go
        round an obstacle (the camera sees 45 deg each side).
    """

    pd: PDConfig = field(default_factory=lambda: BASE_PD)
    step: float = 0.1
    max_speed: float = 2.0
    max_turn_deg_s: float = 90.0
    camera_tilt_deg: float = -10.0
    camera_height: float = 1.5
    forward: str = 'ground'
    distance: float = 2.5
    distance_gain: float = 1.5
    pace: float = 1.0
    max_reverse: float = 0.5
    size_frames: int = 5
    min_peak: float = 0.0102
    watchdog_timeout: float = 2.0
    actions: str = 'continuous'
    discrete_speed: float = 1.0
    discrete_turn_deg_s: float = 30.0
    avoid: bool = False
    avoid_reach: float = 1.5
    avoid_radius: float = 0.45
    avoid_max_deg: float = 40.0

    def __post_init__(self):
        check_field_types(self)
        for name in ('step', 'max_speed', 'max_turn_deg_s', 'watchdog_timeout',
                     'discrete_speed', 'discrete_turn_deg_s', 'camera_height', 'distance',
                     'avoid_reach', 'avoid_radius'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f'{name} must be > 0, got {value}')
        for name in ('pace', 'distance_gain', 'max_reverse'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ConfigError(f'{name} must be >= 0, got {value}')
        if not math.isfinite(self.camera_tilt_deg) or abs(self.camera_tilt_deg) >= 90:
            raise ConfigError(f'camera_tilt_deg must be within +-90, got {self.camera_tilt_deg}')
        if self.size_frames < 1:
            raise ConfigError(f'size_frames must be >= 1, got {self.size_frames}')
        if not (math.isfinite(self.avoid_max_deg) and 0 <= self.avoid_max_deg <= 90):
            raise ConfigError(f'avoid_max_deg must be within 0-90, got {self.avoid_max_deg}')
        if math.isnan(self.min_peak):
            raise ConfigError('min_peak must not be NaN')
        if self.forward not in FORWARD_RULES:
            raise ConfigError(f'forward must be one of {list(FORWARD_RULES)}, '
                              f'got {self.forward!r}')
        if self.actions not in ACTION_SETS:
            raise ConfigError(f'actions must be one of {list(ACTION_SETS)}, '
                              f'got {self.actions!r}')


@dataclass(frozen=True)
class BaseCommand:
    """
    One velocity command, the time it was made, why, and the capture stamp of the action
    location that caused it (None for stops).
    """

    twist: Twist
    t: float
    reason: str
    stamp: float | None = None


class BaseController:
    """Turns time-stamped action locations into velocity commands for a mobile base."""

    def __init__(self, config: BaseConfig, *, t0: float = 0.0):
        self.config = config
        self.pd = PDController(config.pd)
        self.intrinsics: Intrinsics | None = None
        self.ignored: dict[str, int] = {}
        self.commands = 0
        self.yaw: list[tuple[float, float]] = []     # (t, heading) odometry, newest last
        self.sizes: list[float] = []
        self.scan: Scan | None = None
        self.latency = LatencyStats()
        self._last_capture = -math.inf
        self._last_accept = t0
        self._accepted = False
        self._moving = False
        self._holding = False

    @property
    def state(self) -> str:
        return controller_state(self.intrinsics, self._holding, self._accepted)

    @property
    def newest_state_time(self) -> float | None:
        """When the newest odometry was taken (None before any)."""
        return self.yaw[-1][0] if self.yaw else None

    def set_intrinsics(self, intrinsics: Intrinsics) -> None:
        self.intrinsics = intrinsics

    def observe(self, pose: tuple[float, float, float], t: float) -> None:
        """
        The base's odometry (x, y, heading in radians) at ``t``. The heading is kept
        continuous (unwrapped): odometry wraps it at +-pi, and the PD's derivative of the
        target's direction would see a 2 pi jump there and turn the base the wrong way.
        """
        if len(pose) == 3 and all(math.isfinite(v) for v in pose) and math.isfinite(t):
            heading = float(pose[2])
            if self.yaw:
                last = self.yaw[-1][1]
                heading = last + math.remainder(heading - last, math.tau)
            self.yaw = [s for s in self.yaw if s[0] > t - 2.0] + [(t, heading)]

    def observe_scan(self, scan: Scan) -> None:
        """The base's newest range scan (a malformed or non-finite-stamped one is refused)."""
        angles, ranges = np.asarray(scan.angles, float), np.asarray(scan.ranges, float)
        if angles.shape != ranges.shape or angles.ndim != 1 or not math.isfinite(scan.t) \
                or not np.all(np.isfinite(angles)) or np.any(np.isnan(ranges)):
            raise ConfigError('a scan needs as many finite angles as ranges (no NaN) and a '
                              'finite time')
        self.scan = Scan(angles, ranges, float(scan.t))

    def restart(self, t_now: float) -> None:
        """
        The clock ran back to ``t_now``: forget the odometry's times, the last location and
        the PD's derivative (as `ReactiveController.restart`). Without this the watchdog
        never stopped a moving base until the clock was back where it was.
        """
        self.yaw = []
        self.scan = None
        self.pd.reset()
        self._last_capture = -math.inf
        self._last_accept = t_now

    def _heading_at(self, t: float) -> float:
        before = [h for s, h in self.yaw if s <= t]
        return before[-1] if before else (self.yaw[0][1] if self.yaw else 0.0)

    def ignore(self, reason: str, t_now: float) -> BaseCommand | None:
        self.ignored[reason] = self.ignored.get(reason, 0) + 1
        return self.tick(t_now)

    def on_location(self, u: float, v: float, t_capture: float, t_now: float, *,
                    peak: float | None = None, box: tuple | None = None
                    ) -> BaseCommand | None:
        """
        React to an action at pixel (u, v) of a frame captured at ``t_capture``; ``box``
        (x, y, w, h; px) is the extent of what is there, if the pointer knows it.
        """
        cfg, intr = self.config, self.intrinsics
        problem = location_problem(u, v, t_capture, t_now, intrinsics=intr, peak=peak,
                                   min_peak=cfg.min_peak, last_capture=self._last_capture)
        if problem is not None:
            return self.ignore(problem, t_now)
        error, _ = angular_error(u, v, intr, camera_tilt=math.radians(cfg.camera_tilt_deg))
        if not math.isfinite(error):                  # never into the PD: NaN would stay
            return self.ignore('bad geometry', t_now)
        if t_now - self._last_accept > cfg.watchdog_timeout:
            self.pd.reset()
        self._last_capture, self._last_accept = t_capture, t_now
        self._accepted, self._holding = True, False
        heading = self._heading_at(t_capture)
        change, _ = self.pd.update((error, 0.0), t_capture, camera=(heading, 0.0))
        max_turn = math.radians(cfg.max_turn_deg_s)
        turn = 0.0 if self.pd.within_dead_band((error, 0.0)) else change / cfg.step
        forward = max(math.cos(error), 0.0) * self._speed(box)
        if cfg.avoid and forward > 0 and self.scan is not None \
                and t_now - self.scan.t <= cfg.watchdog_timeout:
            want = turn * cfg.step
            way = clear_direction(self.scan, want, error, reach=cfg.avoid_reach,
                                  radius=cfg.avoid_radius,
                                  max_detour=math.radians(cfg.avoid_max_deg))
            if way is None:
                forward = 0.0                        # nowhere to go: only turn
            elif way != want:
                turn = way / cfg.step
        turn = min(max(turn, -max_turn), max_turn)
        return self._emit(Twist(forward, turn), t_now, 'track', t_capture)

    def distance_to(self, box: tuple) -> float | None:
        """
        The distance (m) to what ``box`` holds by the forward rule; None when it cannot
        tell (no box, a box not on the floor, the reference still being taken).
        """
        cfg = self.config
        if box is None or len(box) != 4 or not all(math.isfinite(b) for b in box) \
                or box[2] <= 0 or box[3] <= 0:
            return None
        if cfg.forward == 'ground':
            x, y, w, h = box
            _, below = angular_error(x + w / 2 - 0.5, y + h - 0.5, self.intrinsics,
                                     camera_tilt=math.radians(cfg.camera_tilt_deg))
            down = -(below + math.radians(cfg.camera_tilt_deg))   # below the horizon
            return cfg.camera_height / math.tan(down) if down > 0.01 else None
        size = math.sqrt(box[2] * box[3])
        if len(self.sizes) < cfg.size_frames:
            self.sizes.append(size)
            return None if len(self.sizes) < cfg.size_frames else cfg.distance
        return cfg.distance * statistics.median(self.sizes) / size

    def _speed(self, box: tuple | None) -> float:
        cfg = self.config
        if cfg.forward == 'none':
            return 0.0
        distance = None if cfg.forward == 'constant' else self.distance_to(box)
        if distance is None:
            return min(cfg.pace, cfg.max_speed)
        return min(max(cfg.distance_gain * (distance - cfg.distance), -cfg.max_reverse),
                   cfg.max_speed)

    def tick(self, t_now: float) -> BaseCommand | None:
        """Watchdog: when locations stop arriving, one stop command, then silence."""
        if (self._moving and math.isfinite(t_now)
                and t_now - self._last_accept > self.config.watchdog_timeout):
            self.pd.reset()
            self._holding = True
            return self.hold(t_now)
        return None

    def hold(self, t_now: float) -> BaseCommand:
        """Stop the base."""
        return self._emit(Twist(), t_now, 'hold', None)

    def _emit(self, twist: Twist, t_now: float, reason: str,
              stamp: float | None) -> BaseCommand:
        if self.config.actions == 'discrete':
            twist = self.discrete(twist)
        self._moving = twist != Twist()
        self.commands += 1
        if stamp is not None:
            self.latency.add(t_now - stamp)
        return BaseCommand(twist, t_now, reason, stamp)

    def discrete(self, twist: Twist) -> Twist:
        """
        The AD-VAT action nearest ``twist``: forward, backward or neither, combined with
        a left or right turn or none (never backward and turning). Backward runs at
        ``max_reverse`` at most (0: no backward action) and is taken once ``twist`` backs
        away at half that: the continuous rule never backs away faster than ``max_reverse``.
        """
        cfg = self.config
        speed, rate = cfg.discrete_speed, math.radians(cfg.discrete_turn_deg_s)
        back = min(speed, cfg.max_reverse)
        forward = speed if twist.forward > speed / 2 else (
            -back if back > 0 and twist.forward <= -back / 2 else 0.0)
        turn = rate if twist.turn > rate / 2 else -rate if twist.turn < -rate / 2 else 0.0
        return Twist(forward, 0.0 if forward < 0 else turn)
