"""
The reactive controller: action pixel -> angular error -> PD -> guarded joint command.

All times are explicit arguments in seconds (ROS time in the node, simulated time in the
benchmark); nothing here reads a clock.
"""
import bisect
from collections import deque
from dataclasses import dataclass, field
import math
from typing import Sequence

from activeloc_ros.checks import check_field_types
from activeloc_ros.control.braccio import (
    ArmMapping, check_pose, clamp_to_limits, JointGuard, speed_deg_s)
from activeloc_ros.control.geometry import angular_error, Intrinsics
from activeloc_ros.control.pd import PDConfig, PDController
from activeloc_ros.errors import ConfigError


@dataclass(frozen=True)
class ControllerConfig:
    """
    Everything the reactive controller needs besides the intrinsics.

    :param watchdog_timeout: seconds without an accepted action location before holding.
    :param step_delay_ms: the servos' ms per degree (10-30), which sets the speed limit.
    :param min_peak: locations whose map's peak is below this are ignored: such a map
        carries no information. A uniform 14x14 map (a first frame, a model reset) peaks at
        1/196 = 0.0051, and its argmax is an arbitrary corner cell. A real map can be
        nearly as flat: on the static dev sequences (seed 0) a still camera's maps peak at
        a median 0.010-0.016. 0 (the paper's: act on every map) is the default: twice the
        uniform peak, 0.0102, was no better on the static sequences (docs/decisions.md).
        The same rule holds for every method with a map; one without (peak None: a
        tracker, the oracle) is not judged by it.
    :param pose_slack: how far (s) a capture stamp may lie outside the joint-state history
        and still be looked up in it; farther (e.g. a replayed bag's old stamps) uses the
        newest pose.
    :param settle_time: ignore locations from frames captured while the camera moved, or
        less than this many seconds after it stopped (0: never, the paper's loop). A
        single frame seen within the gate points about as well as a still one, but a
        camera that acts on every map never stops, and then all its maps point worse
        (screen, seeds 0-2: 9.53 deg at 0 s, 8.55 at 0.1 s, 8.12 at 0.3 s;
        docs/history.md).
    :param pan_limit_deg: the controller never aims the camera farther than this from the
        home direction, left or right (the workspace, e.g. a screen's extent); the joint
        limits still apply.
    :param tilt_limit_deg: the same, up or down.
    :param confirm_deg: act on a location that calls for a move only when the location
        before it, from the previous frame a still camera saw, pointed within this many
        degrees of it (pan and tilt each, as directions in the world: the camera's pose plus
        the error). One map then decides no saccade alone: a surprise one frame shows and the
        next does not (a passer-by's step, the model's first guesses) moves nothing, at the
        cost of one frame's delay on every saccade. And a saccade once decided runs to its
        end: a move the servos' speed has not let start yet (a command at the instant of the
        last joint state, as in lockstep) is not replaced by the next location, as a camera
        that has begun to move is not. 0: act on every location (the paper).
    """

    pd: PDConfig = field(default_factory=PDConfig)
    mapping: ArmMapping = field(default_factory=ArmMapping)
    watchdog_timeout: float = 2.0
    step_delay_ms: float = 20.0
    min_peak: float = 0.0
    pose_slack: float = 0.5
    settle_time: float = 0.3
    pan_limit_deg: float = 180.0
    tilt_limit_deg: float = 180.0
    confirm_deg: float = 0.0

    def __post_init__(self):
        check_field_types(self)
        for name in ('pan_limit_deg', 'tilt_limit_deg'):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0 <= value <= 180):
                raise ConfigError(f'{name} must be within 0..180 degrees, got {value}')
        if not math.isfinite(self.watchdog_timeout) or self.watchdog_timeout <= 0:
            raise ConfigError(f'watchdog_timeout must be > 0 s, got {self.watchdog_timeout}')
        if math.isnan(self.min_peak):
            raise ConfigError('min_peak must not be NaN')
        if not math.isfinite(self.pose_slack) or self.pose_slack < 0:
            raise ConfigError(f'pose_slack must be >= 0 s, got {self.pose_slack}')
        if not math.isfinite(self.settle_time) or self.settle_time < 0:
            raise ConfigError(f'settle_time must be >= 0 s, got {self.settle_time}')
        if not (math.isfinite(self.confirm_deg) and 0 <= self.confirm_deg <= 180):
            raise ConfigError(f'confirm_deg must be within 0..180 degrees, got '
                              f'{self.confirm_deg}')
        speed_deg_s(self.step_delay_ms)  # validates the range


@dataclass(frozen=True)
class Command:
    """
    One joint command: six angles in degrees, the time it was made, why, and the capture
    stamp of the action location that caused it (None for holds).
    """

    joints_deg: tuple[float, ...]
    t: float
    reason: str
    stamp: float | None = None


class PoseHistory:
    """Recent (time, joints) samples of the arm, interpolated at a capture time."""

    def __init__(self, horizon: float = 10.0):
        self.horizon = horizon
        self._t: deque[float] = deque()
        self._q: deque[tuple[float, ...]] = deque()

    def __len__(self) -> int:
        return len(self._t)

    def add(self, t: float, joints_deg: Sequence[float]) -> bool:
        """Record a sample; out-of-order or non-finite samples are refused (False)."""
        q = tuple(float(v) for v in joints_deg)
        if not math.isfinite(t) or not all(math.isfinite(v) for v in q):
            return False
        if self._t and t <= self._t[-1]:
            return False
        self._t.append(t)
        self._q.append(q)
        while self._t[0] < t - self.horizon:
            self._t.popleft()
            self._q.popleft()
        return True

    def samples(self) -> list[tuple[float, tuple[float, ...]]]:
        return list(zip(self._t, self._q))

    @property
    def newest(self) -> tuple[float, tuple[float, ...]] | None:
        return (self._t[-1], self._q[-1]) if self._t else None

    def at(self, t: float, slack: float) -> tuple[float, ...] | None:
        """
        Joints at ``t`` (linear interpolation); the newest sample when ``t`` lies more than
        ``slack`` outside the history; None when empty.
        """
        if not self._t:
            return None
        if not math.isfinite(t) or t < self._t[0] - slack or t > self._t[-1] + slack:
            return self._q[-1]
        times = list(self._t)
        i = bisect.bisect_left(times, t)
        if i == 0:
            return self._q[0]
        if i >= len(times):
            return self._q[-1]
        t0, t1 = times[i - 1], times[i]
        w = (t - t0) / (t1 - t0)
        return tuple(a + w * (b - a) for a, b in zip(self._q[i - 1], self._q[i]))


class LatencyStats:
    """Rolling frame-to-command latencies (seconds) with percentiles."""

    def __init__(self, window: int = 1000):
        self._values: deque[float] = deque(maxlen=window)
        self.count = 0

    def add(self, latency: float) -> None:
        if math.isfinite(latency):
            self._values.append(latency)
            self.count += 1

    def percentile(self, q: float) -> float:
        """Nearest-rank percentile (q in [0, 100]) of the window; NaN when empty."""
        if not self._values:
            return math.nan
        values = sorted(self._values)
        rank = max(1, math.ceil(q / 100.0 * len(values)))
        return values[rank - 1]

    def summary(self) -> dict[str, float]:
        return {'n': len(self._values), 'p50': self.percentile(50), 'p95': self.percentile(95)}


FUTURE_SLACK = 1.0   # s a capture stamp may run ahead of the controller's clock (skew)


def controller_state(intrinsics: Intrinsics | None, holding: bool, accepted: bool) -> str:
    """
    Name what a controller (the arm's or the base's) is doing.

    Waiting (no camera intrinsics yet), holding (the watchdog holds it still), tracking
    (it has accepted a location) or idle.
    """
    if intrinsics is None:
        return 'waiting'
    if holding:
        return 'holding'
    return 'tracking' if accepted else 'idle'


def location_problem(u: float, v: float, t_capture: float, t_now: float, *,
                     intrinsics: Intrinsics | None, peak: float | None, min_peak: float,
                     last_capture: float) -> str | None:
    """
    Why a controller (the arm's or a base's) must not act on an action location, or None:
    no intrinsics, a bad time, a stamp more than `FUTURE_SLACK` ahead of now (accepted, it
    would turn every later location away as out of order), a pixel outside the image, a
    map without information (its peak below ``min_peak``; None for a pointer without a
    map), a stamp not after the last accepted one.
    """
    if intrinsics is None:
        return 'no camera info'
    if not (math.isfinite(t_capture) and math.isfinite(t_now)):
        return 'bad time'
    if t_capture > t_now + FUTURE_SLACK:
        return 'stamp in the future'
    if not intrinsics.contains(u, v):
        return 'outside image'
    if peak is not None and not (math.isfinite(peak) and peak >= min_peak):
        return 'weak or bad peak'
    if t_capture <= last_capture:
        return 'out of order'
    return None


class ReactiveController:
    """
    Turns time-stamped action locations into joint commands the arm can follow.

    States: ``'waiting'`` (no intrinsics yet), ``'idle'`` (no location yet), ``'tracking'``
    and ``'holding'`` (the watchdog fired: the arm was told to stay where it is).

    A move the servos' speed cut short (`JointGuard`: a command moves a joint at most as far
    as the servos go in the time since the previous command) goes on with every location
    it ignores (a moving camera's frames above all; reason ``'continue'``) until it is
    done or a new target replaces it. Without this a saccade stopped after one frame's
    worth of motion and waited out the settle gate before it went on (the first command
    of a run moves nothing at all).
    """

    def __init__(self, config: ControllerConfig, *, start_deg: Sequence[float] | None = None,
                 t0: float = 0.0):
        self.config = config
        self.mapping = config.mapping
        self.pd = PDController(config.pd)
        start = config.mapping.aim_only(check_pose(
            start_deg if start_deg is not None else config.mapping.home_deg, 'start pose'))
        self.guard = JointGuard(start, t0, step_delay_ms=config.step_delay_ms)
        self.history = PoseHistory()
        self.latency = LatencyStats()
        self.intrinsics: Intrinsics | None = None
        self.ignored: dict[str, int] = {}
        self.commands = 0
        self._last_capture = -math.inf
        self._last_accept = -math.inf
        self._holding = False
        self._goal: tuple[float, ...] | None = None   # a target the guard cut short
        self._seen: tuple[float, float] | None = None  # the last still frame's (pan, tilt)

    @property
    def state(self) -> str:
        return controller_state(self.intrinsics, self._holding,
                                self._last_accept != -math.inf)

    def set_intrinsics(self, intrinsics: Intrinsics) -> None:
        self.intrinsics = intrinsics

    def observe(self, joints_deg: Sequence[float], t: float) -> None:
        """
        The arm's measured pose at ``t``; before the first command it also seeds the guard,
        so the first commands ramp from where the arm really is.
        """
        pose = tuple(joints_deg)
        if len(pose) != len(self.guard.last_deg) or not all(math.isfinite(q) for q in pose):
            return
        # a servo cannot be outside its range; the joints that do not aim the camera are
        # never taken from a state (a foreign command may have moved them)
        pose = self.mapping.aim_only(clamp_to_limits(pose))
        if self.history.add(t, pose) and self.commands == 0:
            self.guard.reset(pose, t)

    def restart(self, t_now: float) -> None:
        """
        The clock ran back to ``t_now`` (a bag replayed in a loop with its ``/clock``):
        forget every time it holds (the arm's recent poses, the last location, the PD's
        derivative, a move in progress) and go on from the last command, as after a start.
        Without this every location is out of order, and the guard allows no motion, until
        the clock is back where it was.
        """
        self.guard.reset(self.guard.last_deg, t_now)
        self.history = PoseHistory(self.history.horizon)
        self.pd.reset()
        self._last_capture = self._last_accept = -math.inf
        self._holding = False
        self._goal = self._seen = None

    def ignore(self, reason: str, t_now: float) -> Command | None:
        """
        Count an ignored location; the watchdog's answer to it, else the rest of a move
        the servos' speed cut short.
        """
        self.ignored[reason] = self.ignored.get(reason, 0) + 1
        command = self.tick(t_now)
        if (command is None and self._goal is not None and not self._holding
                and math.isfinite(t_now)):
            command = self._emit(self._goal, t_now, 'continue', None)
        return command

    def _pose_at(self, t: float) -> tuple[float, ...]:
        pose = self.history.at(t, self.config.pose_slack)
        return pose if pose is not None else self.guard.last_deg

    def _moved(self, t_capture: float) -> bool:
        """Did the camera move within ``settle_time`` before ``t_capture``?"""
        now = self._pose_at(t_capture)
        start = t_capture - self.config.settle_time
        times = [t for t, _ in self.history.samples() if start < t < t_capture]
        return any(max(abs(a - b) for a, b in zip(self._pose_at(t), now)) > 0.5
                   for t in [start, *times])

    def current_pose(self, t_now: float) -> tuple[float, ...]:
        """Best estimate of where the arm is: a fresh measured state, else the last command."""
        newest = self.history.newest
        if newest is not None and t_now - newest[0] <= self.config.watchdog_timeout:
            return newest[1]
        return self.guard.last_deg

    def on_location(self, u: float, v: float, t_capture: float, t_now: float, *,
                    peak: float | None = None, box: tuple | None = None) -> Command | None:
        """
        React to an action at pixel (u, v) of a frame captured at ``t_capture``. (``box``,
        the extent of what is there, is the base controller's: an arm only aims.)

        Returns the command to send. A location can be ignored (no intrinsics, NaN/absurd
        values, out-of-order stamps, weak peak, a moving camera; the reason is counted in
        ``ignored``): then the answer is the watchdog's (`tick`), a hold once no location
        was accepted for ``watchdog_timeout``, else None. So the watchdog runs on every
        frame, whichever driver calls: the node's timer only adds the case of no frames.
        """
        intr = self.intrinsics
        problem = location_problem(u, v, t_capture, t_now, intrinsics=intr, peak=peak,
                                   min_peak=self.config.min_peak,
                                   last_capture=self._last_capture)
        if problem is not None:
            return self.ignore(problem, t_now)
        if self.config.settle_time > 0 and self._moved(t_capture):
            self._seen = None
            return self.ignore('camera moving', t_now)
        if self.config.confirm_deg > 0 and self._goal is not None:
            self._seen = None                # a saccade once decided runs to its end
            return self.ignore('saccade running', t_now)
        pose = self._pose_at(t_capture)
        pan, tilt = self.mapping.pan_tilt(pose)
        error = angular_error(u, v, intr, camera_tilt=tilt)
        if not all(math.isfinite(e) for e in error):   # never into the PD: NaN would stay
            return self.ignore('bad geometry', t_now)
        if not self._confirmed(pan + error[0], tilt + error[1], error):
            return self.ignore('unconfirmed', t_now)
        if self._holding or t_now - self._last_accept > self.config.watchdog_timeout:
            self.pd.reset()  # a fresh start: no derivative across a gap
        self._holding = False
        self._last_capture = t_capture
        self._last_accept = t_now

        d_pan, d_tilt = self.pd.update(error, t_capture, camera=(pan, tilt))
        if self.pd.within_dead_band(error):
            target = self.guard.last_deg  # on target or noise: no new motion
        else:
            pan_max = math.radians(self.config.pan_limit_deg)
            tilt_max = math.radians(self.config.tilt_limit_deg)
            target = self.mapping.joints_deg(min(max(pan + d_pan, -pan_max), pan_max),
                                             min(max(tilt + d_tilt, -tilt_max), tilt_max))
        return self._emit(target, t_now, 'track', t_capture)

    def _confirmed(self, pan: float, tilt: float, error: tuple[float, float]) -> bool:
        """
        `confirm_deg`: does the previous still frame's location agree with this one,
        pointing at (pan, tilt) in the world? Within the dead band nothing moves: no need.
        """
        seen, self._seen = self._seen, (pan, tilt)
        limit = math.radians(self.config.confirm_deg)
        return (limit == 0 or self.pd.within_dead_band(error)
                or (seen is not None and abs(pan - seen[0]) <= limit
                    and abs(tilt - seen[1]) <= limit))

    def tick(self, t_now: float) -> Command | None:
        """Watchdog: when locations stop arriving, one hold command, then silence."""
        if (self.state == 'tracking' and math.isfinite(t_now)
                and t_now - self._last_accept > self.config.watchdog_timeout):
            self._holding = True
            self.pd.reset()
            return self.hold(t_now)
        return None

    def hold(self, t_now: float) -> Command:
        """A command that keeps the arm where it is now (for the watchdog and for shutdown)."""
        return self._emit(self.current_pose(t_now), t_now, 'hold', None)

    def _emit(self, target: Sequence[float], t_now: float, reason: str,
              stamp: float | None) -> Command:
        target = self.mapping.aim_only(target)
        joints = self.guard.limit(target, t_now)
        short = max(abs(a - b) for a, b in zip(target, joints)) > 0.05
        self._goal = tuple(target) if short and reason in ('track', 'continue') else None
        self.commands += 1
        if stamp is not None:
            self.latency.add(t_now - stamp)
        return Command(joints, t_now, reason, stamp)
