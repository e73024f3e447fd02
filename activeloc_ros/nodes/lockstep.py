"""Lockstep in the ROS graph: the camera's side of ``closed_loop``'s lockstep mode, ROS-free.

``closed_loop.run_episode(mode='lockstep')`` shows scene frame i at ``t_i = i / fps``,
renders it with the arm's pose at ``t_i``, and the command the frame causes reaches the
arm at ``t_i`` (zero compute time). The graph reproduces it on a simulated clock that the
camera node owns (``use_sim_time`` on every node, ``lockstep`` on the camera). Frame i:

1. tick: the camera publishes ``/clock`` = t_i (again every ``retick`` s while unanswered).
2. pose: the simulated arm answers every clock message with its ``joint_states`` at t_i;
   the first one stamped t_i or later is the pose the camera renders with.
3. the camera publishes ``camera/image_raw``, ``camera/camera_info`` and ``camera/pose``
   (pan, tilt) stamped t_i.
4. answer: perception publishes ``action_location`` stamped t_i; the controller, whose
   clock still reads t_i, turns it into ``joint_commands`` stamped t_i, or says it ignored
   it on ``action_location/ignored`` (closed_loop then sends no command either).
5. applied: the arm applies each command at t_i and answers it with ``joint_states`` at t_i.
   Once the camera has counted one answer per clock message it sent and per command it
   saw during t_i, every command is in the arm and the clock may move on.

Every wait has a timeout, so a location the controller ignores, or a silent node, slows the
run but never hangs it; ``missed`` counts the timeouts by kind (the frame then may differ
from ``closed_loop``).
"""
from collections import Counter
import math
from pathlib import Path
from typing import Sequence

from activeloc_ros.errors import ConfigError
from activeloc_ros.world import frame_time

POSE_TOPIC = '/camera/pose'   # the virtual camera's (pan, tilt) at each frame's stamp
IDLE, POSE, ANSWER, APPLIED = 'idle', 'pose', 'answer', 'applied'
NO_POSE = 'no arm state at the frame time (rendered with the newest pose)'
NO_LOCATION = 'no action location for the frame'
NO_COMMAND = 'no answer from the controller to an action location'
NOT_APPLIED = 'the arm did not confirm every command'
LATE_COMMAND = "a command for an earlier frame (applied later than closed_loop's)"


def time_ns(index: int, fps: float) -> int:
    """Simulated time of scene frame ``index`` (`world.frame_time`), integer nanoseconds."""
    return round(frame_time(index, fps) * 1e9)


class Lockstep:
    """The camera's lockstep state machine: fed the graph's messages, told what to do next.

    ``begin`` starts the next frame (publish its tick); ``poll`` answers 'tick' (publish the
    tick again), 'render' (publish the frame with ``pose``; then call ``rendered``), 'next'
    (the frame is done) or 'wait'. Times ``now`` are seconds of a steady clock.

    :param timeout: longest wait for the arm's pose and for perception's location, s.
    :param command_timeout: longest wait for the controller's answer once the location is
        out, and for the arm's confirmations, s.
    :param retick: publish the tick again after this long without the arm's answer, s.
    """

    def __init__(self, fps: float, *, timeout: float = 60.0, command_timeout: float = 2.0,
                 retick: float = 1.0):
        for name, value in (('fps', fps), ('timeout', timeout),
                            ('command_timeout', command_timeout), ('retick', retick)):
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f'lockstep {name} must be > 0, got {value}')
        self.fps = fps
        self.timeout = timeout
        self.command_timeout = command_timeout
        self.retick = retick
        self.index = -1
        self.t_ns = 0
        self.phase = IDLE
        self.missed: Counter = Counter()
        self.newest_pose: tuple[float, ...] | None = None
        self.pose: tuple[float, ...] | None = None   # the frame's render pose
        self.ticks = 0            # clock messages sent for this frame
        self.states = 0           # arm states stamped with this frame's time
        self.commands = 0         # joint commands seen since the frame's tick
        self.located_at: float | None = None
        self.answered = False     # the controller commanded or ignored this frame's location
        self._since = self._ticked_at = 0.0

    def begin(self, now: float) -> int:
        """Start the next frame; returns its time (ns) for the tick to publish."""
        if self.phase != IDLE:
            raise ConfigError(f'lockstep: frame {self.index} is not finished ({self.phase})')
        self.index += 1
        self.t_ns = time_ns(self.index, self.fps)
        self.phase = POSE
        self.pose = None
        self.ticks = 1
        self.states = 0
        self.commands = 0
        self.located_at = None
        self.answered = False
        self._since = self._ticked_at = now
        return self.t_ns

    def on_state(self, stamp_ns: int, joints_deg: Sequence[float]) -> None:
        self.newest_pose = tuple(joints_deg)
        if self.phase == IDLE:
            return
        if stamp_ns == self.t_ns:
            self.states += 1
        if self.phase == POSE and self.pose is None and stamp_ns >= self.t_ns:
            self.pose = self.newest_pose

    def on_location(self, stamp_ns: int, now: float) -> None:
        if self.phase != IDLE and stamp_ns == self.t_ns and self.located_at is None:
            self.located_at = now

    def on_command(self, stamp_ns: int) -> None:
        if self.phase == IDLE:
            return
        self.commands += 1
        if stamp_ns == self.t_ns:
            self.answered = True
        elif stamp_ns < self.t_ns:
            self.missed[LATE_COMMAND] += 1

    def on_ignored(self, stamp_ns: int) -> None:
        """The controller ignored the location stamped ``stamp_ns``: no command will come."""
        if self.phase != IDLE and stamp_ns == self.t_ns:
            self.answered = True

    def rendered(self, now: float) -> None:
        """The frame went out: wait for perception and the controller."""
        self.phase = ANSWER
        self._since = now

    def poll(self, now: float) -> str:
        if self.phase == POSE:
            if self.pose is not None:
                return 'render'
            if now - self._since > self.timeout:
                self.missed[NO_POSE] += 1
                self.pose = self.newest_pose
                self.ticks = 0          # an arm that did not answer will not confirm them
                return 'render'
            if now - self._ticked_at >= self.retick:
                self.ticks += 1
                self._ticked_at = now
                return 'tick'
            return 'wait'
        if self.phase == ANSWER:
            if self.answered:
                self._applied(now)
            elif self.located_at is not None:
                if now - self.located_at > self.command_timeout:
                    self.missed[NO_COMMAND] += 1
                    self._applied(now)
            elif now - self._since > self.timeout:
                self.missed[NO_LOCATION] += 1
                self._applied(now)
        if self.phase == APPLIED:
            if self.states >= self.ticks + self.commands:
                self.phase = IDLE
                return 'next'
            if now - self._since > self.command_timeout:
                self.missed[NOT_APPLIED] += 1
                self.phase = IDLE
                return 'next'
        return 'wait'

    def _applied(self, now: float) -> None:
        self.phase = APPLIED
        self._since = now


def recorded_poses(path: Path) -> list[tuple[float, float, float]]:
    """(t, pan, tilt) of every frame of a recorded run (``bringup --record``) with a virtual
    camera: its ``camera/pose`` messages, t in seconds of their stamp (the image's, whole
    nanoseconds: frame i is ``round(t * fps)``), pan and tilt in radians, in time order."""
    from activeloc_ros import bag
    rows = []
    for _, _, _, msg in bag.read_messages(Path(path), [POSE_TOPIC]):
        pose = dict(zip(msg.name, msg.position))
        stamp = msg.header.stamp
        rows.append((stamp.sec + stamp.nanosec / 1e9, float(pose['pan']), float(pose['tilt'])))
    return sorted(rows)
