"""
Lockstep in the ROS graph: the simulation's side of ``closed_loop``'s lockstep mode,
ROS-free.

``closed_loop.run_episode(mode='lockstep')`` shows scene frame i at ``t_i = i / fps``,
renders it with the arm's pose at ``t_i``, and the command the frame causes reaches the
arm at ``t_i`` (zero compute time). The graph reproduces it on a simulated clock that the
sim node owns (``use_sim_time`` on every node, ``lockstep`` on the sim). Frame i:

1. tick: the sim publishes ``/clock`` = t_i, moves its arm to t_i and publishes
   ``joint_states`` at t_i (``begin``).
2. pose: once its own subscription has that state back (so the state is on its way to the
   controller before the image follows), the sim renders the frame and publishes
   ``camera/image_raw``, ``camera/camera_info`` and ``camera/pose`` (pan, tilt) stamped t_i
   (``rendered``). The controller, on simulated time, also holds a location until it has
   the arm's state at the location's stamp: DDS may deliver the two in either order.
3. answer: perception publishes ``action_location`` stamped t_i; the controller, whose
   clock reads t_i, turns it into ``joint_commands`` stamped t_i, or says it ignored it on
   ``action_location/ignored`` (with a command too when it carries on a move the servos'
   speed cut short, as closed_loop's controller does).
4. the sim applies each command when it comes, at the arm's time t_i; once the frame is
   answered, frame i + 1 begins.

Every wait has a timeout, so a location the controller ignores, or a silent node, slows the
run but never hangs it; ``missed`` counts the timeouts by kind (the frame then may differ
from ``closed_loop``).
"""
from collections import Counter
import math
from pathlib import Path

from activeloc_ros.errors import ConfigError
from activeloc_ros.world import frame_time

POSE_TOPIC = '/camera/pose'   # the virtual camera's (pan, tilt) at each frame's stamp
IDLE, POSE, ANSWER = 'idle', 'pose', 'answer'
NO_POSE = "the arm's state at the frame time did not come back (rendered all the same)"
NO_LOCATION = 'no action location for the frame'
NO_COMMAND = 'no answer from the controller to an action location'
LATE_COMMAND = "a command for an earlier frame (applied later than closed_loop's)"


def time_ns(index: int, fps: float) -> int:
    """Simulated time of scene frame ``index`` (`world.frame_time`), integer nanoseconds."""
    return round(frame_time(index, fps) * 1e9)


def moot_in_lockstep(values: dict, changed: set) -> str | None:
    """
    A world node's run-time check: ``rate`` paces real time only, so in lockstep a change
    would be reported as set and never used.
    """
    if values['lockstep'] and 'rate' in changed:
        return 'rate would have no effect: in lockstep the graph sets the pace, not the clock'
    return None


class Lockstep:
    """
    The sim's lockstep state machine: fed the graph's messages, told what to do next.

    ``begin`` starts a frame (its tick and arm state are out); ``poll`` answers 'render'
    (publish the frame; then call ``rendered``), 'next' (the frame is done: begin the next)
    or 'wait'. Times ``now`` are seconds of a steady clock.

    :param timeout: longest wait for perception's location, s.
    :param command_timeout: longest wait for the arm state's echo, and for the controller's
        answer once the location is out, s.
    """

    def __init__(self, *, timeout: float = 60.0, command_timeout: float = 2.0):
        for name, value in (('timeout', timeout), ('command_timeout', command_timeout)):
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f'lockstep {name} must be > 0, got {value}')
        self.timeout = timeout
        self.command_timeout = command_timeout
        self.phase = IDLE
        self.t_ns: int | None = None   # the frame in progress
        self.missed: Counter = Counter()
        self.posed = False
        self.located_at: float | None = None
        self.answered = False
        self._since = 0.0

    def begin(self, t_ns: int, now: float) -> None:
        """The tick and the arm state of the frame at ``t_ns`` are out."""
        if self.phase != IDLE:
            raise ConfigError(f'lockstep: the frame at {self.t_ns} ns is not finished')
        self.phase, self.t_ns, self._since = POSE, t_ns, now
        self.posed, self.located_at, self.answered = False, None, False

    def on_state(self, stamp_ns: int) -> None:
        """An arm state stamped ``stamp_ns`` came back."""
        if stamp_ns == self.t_ns:
            self.posed = True

    def rendered(self, now: float) -> None:
        """The frame went out: wait for its answer."""
        self.phase, self._since = ANSWER, now

    def on_location(self, stamp_ns: int, now: float) -> None:
        if self.phase == ANSWER and stamp_ns == self.t_ns and self.located_at is None:
            self.located_at = now

    def on_command(self, stamp_ns: int) -> None:
        """A joint command stamped ``stamp_ns`` came (and was applied)."""
        if self.t_ns is None:
            return
        if stamp_ns == self.t_ns:
            self.answered = True
        elif stamp_ns < self.t_ns:
            self.missed[LATE_COMMAND] += 1

    def on_ignored(self, stamp_ns: int) -> None:
        """The controller ignored the location stamped ``stamp_ns``: no command will come."""
        if stamp_ns == self.t_ns:
            self.answered = True

    def poll(self, now: float) -> str:
        if self.phase == POSE:
            if not self.posed and now - self._since <= self.command_timeout:
                return 'wait'
            if not self.posed:
                self.missed[NO_POSE] += 1
            return 'render'
        if self.phase == ANSWER and not self.answered:
            if self.located_at is not None:
                if now - self.located_at <= self.command_timeout:
                    return 'wait'
                self.missed[NO_COMMAND] += 1
            elif now - self._since <= self.timeout:
                return 'wait'
            else:
                self.missed[NO_LOCATION] += 1
        self.phase = IDLE
        return 'next'

    def report_missed(self, logger) -> None:
        """Warn of the run's timeouts, by kind; nothing when there were none."""
        if self.missed:
            logger.warning('lockstep timeouts: ' + ', '.join(
                f'{kind}: {n}' for kind, n in sorted(self.missed.items())))


def recorded_poses(path: Path) -> list[tuple[float, float, float]]:
    """
    (t, pan, tilt) of every frame of a recorded run (``bringup --record``) with a virtual
    camera: its ``camera/pose`` messages, t in seconds of their stamp (the image's, whole
    nanoseconds: frame i is ``round(t * fps)``), pan and tilt in radians, in time order.
    """
    from activeloc_ros.bag.read import read_messages
    rows = []
    for _, _, _, msg in read_messages(Path(path), [POSE_TOPIC]):
        pose = dict(zip(msg.name, msg.position))
        stamp = msg.header.stamp
        rows.append((stamp.sec + stamp.nanosec / 1e9, float(pose['pan']), float(pose['tilt'])))
    return sorted(rows)
