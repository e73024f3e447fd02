"""
The simulated world a closed loop steps, without ROS: its clock, what its camera sees and
what its actuator does. `closed_loop.run_episode` steps a world with any pointer; the
tracking experiment's `tracking.world.TrackingWorld` has the same interface.

`ScreenWorld` is the projected-screen experiment (paper Table 2): a sequence's scene frames
on the virtual screen (`screen.VirtualScreen`), seen by a camera the simulated Braccio
(`control.SimArm`) aims. One step is one scene frame:

    ctl = world.controller(config)   # the controller its actuator takes commands from
    for t in world.times():          # scene frame i is shown at t_i = i / fps
        world.apply(command, when)   # commands that reach the arm by t
        joints = world.advance(t)    # the arm moves to t
        scan = world.scan()          # its range sensor's reading (the arm has none: None)
        view = world.observe()       # a camera capture, when one is due
        world.score(record, ...)     # the frame's scores
"""
from dataclasses import dataclass
import math
from typing import Callable, Iterable, Iterator, Sequence

import numpy as np

from activeloc_ros import metrics
from activeloc_ros.control import Command, ControllerConfig, ReactiveController, SimArm
from activeloc_ros.data import FrameTruth
from activeloc_ros.errors import ConfigError
from activeloc_ros.screen import VirtualScreen


@dataclass
class View:
    """What a pointer is shown: the camera image and, for the oracles, the truth in it."""

    rgb: np.ndarray                    # (H, W, 3) uint8 camera image
    index: int                         # scene frame index
    t: float                           # capture time, s
    pan: float                         # camera pose at capture, radians
    tilt: float
    truth_px: np.ndarray               # (N, 2) camera pixels of the annotated actors
    primary_px: np.ndarray | None      # (2,) camera pixel of the primary actor, if annotated
    centre_px: np.ndarray              # (2,) camera pixel of the screen centre
    truth_box: tuple[int, int, int, int] | None = None   # x, y, w, h of the target, if known
    # realtime: whether the camera has captured its next frame by now (the model's
    # skip_late_updates); None: never late
    late: Callable[[], bool] | None = None


def frame_time(index: int, fps: float) -> float:
    """When scene frame ``index`` is shown, s: frame 0 at 0, then one every 1 / fps."""
    return index / fps


def pixel_centre(box) -> tuple[float, float]:
    """
    A box's centre where the screen and the camera put pixel centres: on integers (the
    box's pixels cover [x, x + w)).
    """
    x, y = box.centre
    return x - 0.5, y - 0.5


class ScreenWorld:
    """
    The projected-screen rig in simulated time.

    :param frames: (index, scene RGB, truth) in order.
    :param fps: the scene's frame rate.
    :param home_deg: the arm's start pose.
    :param camera_fps: the camera's frame rate; None or a rate above the scene's captures
        every scene frame.
    """

    def __init__(self, frames: Iterable[tuple[int, np.ndarray, FrameTruth]], *, fps: float,
                 screen: VirtualScreen, home_deg: Sequence[float], step_delay_ms: float,
                 camera_fps: float | None = None):
        if not (math.isfinite(fps) and fps > 0):
            raise ConfigError(f'fps must be > 0, got {fps}')
        if camera_fps is not None and not (math.isfinite(camera_fps) and camera_fps > 0):
            raise ConfigError(f'camera_fps must be > 0, got {camera_fps}')
        self.frames, self.fps, self.screen = frames, fps, screen
        self.period = 0.0 if camera_fps is None or camera_fps >= fps else 1.0 / camera_fps
        self.captures = 0
        self.arm = SimArm(home_deg, 0.0, step_delay_ms=step_delay_ms)
        self.intrinsics = screen.intrinsics
        self.index, self.t = -1, 0.0
        self.scene: np.ndarray | None = None
        self.truth: FrameTruth | None = None
        self.pan = self.tilt = 0.0

    @property
    def capture_period(self) -> float:
        """Time from one camera capture to the next, s."""
        return max(self.period, 1.0 / self.fps)

    def times(self) -> Iterator[float]:
        """Shows each scene frame in turn; yields the time it is shown at."""
        for index, scene, truth in self.frames:
            yield self.show(index, scene, truth)

    def show(self, index: int, scene: np.ndarray, truth: FrameTruth,
             t: float | None = None) -> float:
        """
        Put scene frame ``index`` on the screen at ``t`` (default: its own time, i / fps;
        a world on a wall clock gives the time it is shown at); returns ``t``.
        """
        self.index, self.scene, self.truth = index, scene, truth
        self.t = frame_time(index, self.fps) if t is None else t
        return self.t

    @property
    def scene_wh(self) -> tuple[int, int]:
        return self.scene.shape[1], self.scene.shape[0]

    def controller(self, config: ControllerConfig) -> ReactiveController:
        """The controller this world's arm takes commands from, told its camera."""
        ctl = ReactiveController(config, start_deg=config.mapping.home_deg, t0=0.0)
        ctl.set_intrinsics(self.intrinsics)
        return ctl

    def apply(self, command: Command, t: float) -> None:
        """A controller's command reaches the arm at ``t``."""
        self.act(command.joints_deg, t)

    def act(self, joints_deg: Sequence[float], t: float) -> None:
        """A joint command reaches the arm at ``t``."""
        self.arm.command(joints_deg, t)

    def advance(self, t: float) -> tuple[int, ...]:
        """Move the arm to ``t``; its joints (degrees), which aim the camera."""
        joints = self.arm.advance(t)
        self.pan, self.tilt = self.screen.pan_tilt(joints)
        return joints

    def scan(self) -> None:
        """The arm has no range sensor (`tracking.world.TrackingWorld.scan`)."""
        return None

    def _actors(self) -> np.ndarray:
        """(N, 2) scene pixels of the annotated actors' centres."""
        return np.array([pixel_centre(b) for b in self.truth.actors], np.float64).reshape(-1, 2)

    def observe(self) -> View | None:
        """The camera's capture of the shown frame, if one is due now; else None."""
        if self.t + 1e-9 < self.captures * self.period:
            return None
        self.captures += 1
        pan, tilt, wh = self.pan, self.tilt, self.scene_wh
        rgb = self.screen.render(self.scene, pan, tilt)
        primary = (self.screen.project([pixel_centre(self.truth.primary)], pan, tilt, wh)[0]
                   if self.truth.primary else None)
        centre = self.screen.project([((wh[0] - 1) / 2, (wh[1] - 1) / 2)], pan, tilt, wh)[0]
        return View(rgb, self.index, self.t, pan, tilt,
                    self.screen.project(self._actors(), pan, tilt, wh), primary, centre)

    def to_scene(self, view: View, uv: tuple[float, float]) -> tuple[float, float] | None:
        """Scene pixel at camera pixel ``uv`` of ``view`` (None off the screen)."""
        hit = self.screen.to_scene([uv], view.pan, view.tilt, self.scene_wh)[0]
        return (float(hit[0]), float(hit[1])) if np.all(np.isfinite(hit)) else None

    def score(self, record, newest_map: tuple[np.ndarray, float, float] | None,
              canvas: tuple[int, int]) -> None:
        """
        Fill ``record`` with the shown frame's scores: the angle between the optical axis
        and the closest actor (AAE), whether any actor is in view, and AUC-Judd of the
        newest map ``(heat, pan, tilt)`` laid on the screen where the camera looked.
        """
        points = self._actors()
        record.scored = self.truth.scored and len(points) > 0
        if not record.scored:
            return
        pan, tilt, wh = self.pan, self.tilt, self.scene_wh
        angles = self.screen.angles_deg(points, pan, tilt, wh)
        closest = int(np.argmin(angles))
        record.aae_deg = float(angles[closest])
        record.in_view = bool(np.any(self.screen.in_view(points, pan, tilt, wh)))
        record.truth_xy = (float(points[closest, 0]), float(points[closest, 1]))
        if newest_map is not None:
            heat, mpan, mtilt = newest_map
            placed = self.screen.place_map(heat, mpan, mtilt, canvas)
            fixation = np.zeros(placed.shape, np.uint8)
            cw, ch = canvas
            col = min(max(int((points[closest, 0] + 0.5) * cw / wh[0]), 0), cw - 1)
            row = min(max(int((points[closest, 1] + 0.5) * ch / wh[1]), 0), ch - 1)
            fixation[row, col] = 1
            record.auc = metrics.auc_judd(placed, fixation)
