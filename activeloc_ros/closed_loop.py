"""The projected-screen experiment's closed loop without ROS, in simulated time.

scene frame -> virtual camera (``screen.VirtualScreen``, aimed by the simulated arm) ->
a pointer (the perception model, a tracker, a baseline) -> ``ReactiveController`` ->
``SimArm`` -> the next render. The same core objects the ROS nodes run.

Time: scene frame i is shown at ``t_i = i / fps`` (the scene's own rate) and the arm moves
at its servos' speed. The camera captures at ``camera_fps`` (default: every scene frame);
a capture sees the scene frame on the screen at that moment. Two modes:

- ``lockstep``: every captured frame is processed and its command reaches the arm at its
  capture time (zero compute time); deterministic. The ROS graph reproduces it with a
  simulated clock.
- ``realtime``: processing a frame takes the pointer's measured wall time; frames that
  arrive while it is busy wait in a one-deep queue where the newest wins (the perception
  node's image queue), and each command reaches the arm when its computation ends.

Scoring, at every scene frame with an annotated actor: the angle between the optical axis
and the ray to the closest actor's centre (AAE), whether any actor's centre is in view, and
AUC-Judd of the pointer's newest map laid on the screen where the camera looked
(``VirtualScreen.place_map``) against the closest actor's centre. At every such frame the
pointer processed (in realtime mode also later, from the queue), the pointing error: the
angle between the camera's ray to the location it gave and its ray to the actor's centre
nearest that location, both at capture. It scores the perception alone: the AAE also pays
for the arm's lag and the controller's rules.
"""
from dataclasses import dataclass, field
import math
import time
from typing import Callable, Iterable, Protocol

import numpy as np

from activeloc_ros import metrics
from activeloc_ros.control import ControllerConfig, ReactiveController, SimArm
from activeloc_ros.data import FrameTruth
from activeloc_ros.errors import ConfigError
from activeloc_ros.screen import VirtualScreen

MODES = ('lockstep', 'realtime')
GRID = (14, 14)               # the map a pointer without one is given (the model's grid)
CANVAS = (96, 54)             # AUC canvas over the whole screen (16:9), cells
GAZE_SIGMA_CELLS = 1.0        # spread of a map made from a point


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


@dataclass
class Pointing:
    """A pointer's answer: where the action is in the camera image, and its map if any."""
    location: tuple[float, float] | None
    heat: np.ndarray | None = None     # (rows, cols) over the camera image
    peak: float | None = None


class Pointer(Protocol):
    name: str

    def reset(self) -> None:
        """A new sequence begins."""

    def locate(self, view: View) -> Pointing:
        """Where to look next."""


@dataclass
class FrameRecord:
    index: int
    t: float
    pan: float                        # camera pose at t, radians
    tilt: float
    processed: bool                   # this frame went through the pointer
    scored: bool                      # annotated and inside the evaluation range
    aae_deg: float = math.nan
    in_view: bool = False
    auc: float = math.nan
    pointing_deg: float = math.nan                   # processed frames with a location
    truth_xy: tuple[float, float] | None = None      # closest actor centre, scene px
    predicted_xy: tuple[float, float] | None = None  # newest location, scene px


@dataclass
class Episode:
    name: str
    pointer: str
    mode: str
    records: list[FrameRecord] = field(default_factory=list)
    compute_s: list[float] = field(default_factory=list)
    commands: int = 0

    def scored(self) -> list[FrameRecord]:
        return [r for r in self.records if r.scored]

    def summary(self) -> dict:
        rows = self.scored()
        aucs = [r.auc for r in rows if math.isfinite(r.auc)]
        pointing = [r.pointing_deg for r in rows if math.isfinite(r.pointing_deg)]
        return {
            'frames': len(self.records),
            'scored': len(rows),
            'processed': sum(r.processed for r in self.records),
            'aae_deg': float(np.mean([r.aae_deg for r in rows])) if rows else math.nan,
            'auc_judd': float(np.mean(aucs)) if aucs else math.nan,
            'in_view': float(np.mean([r.in_view for r in rows])) if rows else math.nan,
            'pointing_deg': float(np.mean(pointing)) if pointing else math.nan,
            'compute_ms': float(np.mean(self.compute_s) * 1e3) if self.compute_s else 0.0,
        }


def gaze_map(location: tuple[float, float] | None, image_wh: tuple[int, int], *,
             grid: tuple[int, int] = GRID, sigma_cells: float = GAZE_SIGMA_CELLS
             ) -> np.ndarray:
    """The map of a pointer that gives only a point: a Gaussian there; uniform without one."""
    rows, cols = grid
    if location is None:
        return np.ones(grid, np.float32)
    w, h = image_wh
    cx, cy = (location[0] + 0.5) * cols / w - 0.5, (location[1] + 0.5) * rows / h - 0.5
    r, c = np.mgrid[0:rows, 0:cols]
    return np.exp(-((c - cx) ** 2 + (r - cy) ** 2) / (2 * sigma_cells ** 2)).astype(np.float32)


def _centre(box) -> tuple[float, float]:
    # box pixels cover [x, x + w); the screen puts pixel centres on integers
    x, y = box.centre
    return x - 0.5, y - 0.5


def run_episode(frames: Iterable[tuple[int, np.ndarray, FrameTruth]], pointer: Pointer, *,
                fps: float, screen: VirtualScreen, controller: ControllerConfig,
                mode: str = 'lockstep', camera_fps: float | None = None, name: str = '',
                on_frame: Callable[[np.ndarray, FrameRecord, np.ndarray | None], None]
                | None = None) -> Episode:
    """Run one sequence through the closed loop.

    :param frames: (index, scene RGB, truth) in order.
    :param camera_fps: the camera's frame rate; None or a rate above the scene's captures
        every scene frame.
    :param on_frame: called with each scene frame, its record and the camera image (None
        when the camera captured nothing at that frame), e.g. to write a video.
    """
    if mode not in MODES:
        raise ConfigError(f'mode must be one of {list(MODES)}, got {mode!r}')
    if not (math.isfinite(fps) and fps > 0):
        raise ConfigError(f'fps must be > 0, got {fps}')
    if camera_fps is not None and not (math.isfinite(camera_fps) and camera_fps > 0):
        raise ConfigError(f'camera_fps must be > 0, got {camera_fps}')
    period = 0.0 if camera_fps is None or camera_fps >= fps else 1.0 / camera_fps
    captures = 0
    episode = Episode(name, pointer.name, mode)
    pointer.reset()
    home = controller.mapping.home_deg
    arm = SimArm(home, 0.0, step_delay_ms=controller.step_delay_ms)
    ctl = ReactiveController(controller, start_deg=home, t0=0.0)
    ctl.set_intrinsics(screen.intrinsics)
    pending: list[tuple[float, tuple[float, ...]]] = []   # (time it reaches the arm, joints)
    queued: tuple[View, tuple[int, int]] | None = None
    busy_until = -math.inf
    newest_map: tuple[np.ndarray, float, float] | None = None   # (heat, pan, tilt)
    newest_xy: tuple[float, float] | None = None
    results: list[tuple[float, np.ndarray, float, float, tuple | None]] = []  # for realtime
    pointing_deg: dict[int, float] = {}   # scene frame index -> error of its location
    intr = screen.intrinsics
    camera = {'fx': intr.fx, 'fy': intr.fy, 'cx': intr.cx, 'cy': intr.cy}
    recorded: dict[int, FrameRecord] = {}

    def process(view: View, scene_wh: tuple[int, int], start: float) -> float:
        t0 = time.perf_counter()
        pointing = pointer.locate(view)
        spent = time.perf_counter() - t0
        episode.compute_s.append(spent)
        done = start if mode == 'lockstep' else start + spent
        heat = pointing.heat if pointing.heat is not None else gaze_map(
            pointing.location, screen.size)
        xy = None
        if pointing.location is not None:
            u, v = pointing.location
            actors = [metrics.pixel_ray(p, **camera) for p in view.truth_px
                      if np.all(np.isfinite(p))]
            if actors:
                pointing_deg[view.index] = metrics.closest_angle(
                    metrics.pixel_ray((u, v), **camera), actors)
            hit = screen.to_scene([(u, v)], view.pan, view.tilt, scene_wh)[0]
            xy = (float(hit[0]), float(hit[1])) if np.all(np.isfinite(hit)) else None
            cmd = ctl.on_location(u, v, view.t, done, peak=pointing.peak)
        else:
            cmd = ctl.tick(done)
        if cmd is not None:
            pending.append((done, cmd.joints_deg))
            episode.commands += 1
        results.append((done, heat, view.pan, view.tilt, xy))
        return done

    for index, scene, truth in frames:
        t = index / fps
        scene_wh = (scene.shape[1], scene.shape[0])
        # the perception finishes the queued frame, and may start it, before t
        if queued is not None and busy_until <= t:
            view, wh = queued
            queued = None
            busy_until = process(view, wh, max(busy_until, view.t))
        for when, joints in sorted(p for p in pending if p[0] <= t):
            arm.command(joints, when)
        pending[:] = [p for p in pending if p[0] > t]
        joints = arm.advance(t)
        ctl.observe_joints(joints, t)
        pan, tilt = screen.pan_tilt(joints)
        points = np.array([_centre(b) for b in truth.actors], np.float64).reshape(-1, 2)
        processed = False
        rgb = None
        if t + 1e-9 >= captures * period:
            captures += 1
            rgb = screen.render(scene, pan, tilt)  # a dropped frame may still wait in the queue
        view = None
        if rgb is not None:
            primary = (screen.project([_centre(truth.primary)], pan, tilt, scene_wh)[0]
                       if truth.primary else None)
            centre = screen.project([((scene_wh[0] - 1) / 2, (scene_wh[1] - 1) / 2)],
                                    pan, tilt, scene_wh)[0]
            view = View(rgb, index, t, pan, tilt, screen.project(points, pan, tilt, scene_wh),
                        primary, centre)
        if view is not None and (mode == 'lockstep' or busy_until <= t):
            busy_until = process(view, scene_wh, t)
            processed = True
        elif view is not None:
            queued = (view, scene_wh)
        # the newest result available at t
        while results and results[0][0] <= t:
            done, heat, mpan, mtilt, xy = results.pop(0)
            newest_map, newest_xy = (heat, mpan, mtilt), xy
        record = FrameRecord(index, t, pan, tilt, processed,
                             scored=truth.scored and len(points) > 0,
                             predicted_xy=newest_xy)
        if record.scored:
            angles = screen.angles_deg(points, pan, tilt, scene_wh)
            closest = int(np.argmin(angles))
            record.aae_deg = float(angles[closest])
            record.in_view = bool(np.any(screen.in_view(points, pan, tilt, scene_wh)))
            record.truth_xy = (float(points[closest, 0]), float(points[closest, 1]))
            if newest_map is not None:
                heat, mpan, mtilt = newest_map
                placed = screen.place_map(heat, mpan, mtilt, CANVAS)
                fixation = np.zeros(placed.shape, np.uint8)
                cw, ch = CANVAS
                col = min(max(int((points[closest, 0] + 0.5) * cw / scene_wh[0]), 0), cw - 1)
                row = min(max(int((points[closest, 1] + 0.5) * ch / scene_wh[1]), 0), ch - 1)
                fixation[row, col] = 1
                record.auc = metrics.auc_judd(placed, fixation)
        episode.records.append(record)
        recorded[index] = record
        for i, value in pointing_deg.items():   # realtime: also frames taken from the queue
            if recorded[i].scored:
                recorded[i].pointing_deg = value
        pointing_deg.clear()
        if on_frame is not None:
            on_frame(scene, record, rgb)
    return episode
