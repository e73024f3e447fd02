"""
The closed loop without ROS, in simulated time: `run_episode` steps a world
(`world.ScreenWorld`, the projected-screen experiment, or `tracking.world.TrackingWorld`,
active tracking) with a pointer and the world's controller.

world's camera image -> a pointer (the perception model, a tracker, a baseline) ->
``ReactiveController`` (``BaseController`` for the tracking world's base) -> the world's arm
-> the next image. The same core objects the ROS nodes run. What follows describes the
screen world; the tracking world steps at its control rate and scores AD-VAT's reward
(`tracking.world`).

Time: scene frame i is shown at ``t_i = i / fps`` (`world.frame_time`, the scene's own
rate) and the arm moves at its servos' speed. The camera captures at ``camera_fps``
(default: every scene frame); a capture sees the scene frame on the screen at that moment.
Two modes:

- ``lockstep``: every captured frame is processed and its command reaches the arm at its
  capture time (zero compute time), or a fixed ``latency_s`` after it; deterministic. The
  ROS graph reproduces it with a simulated clock.
- ``realtime``: processing a frame takes the pointer's measured wall time; frames that
  arrive while it is busy wait in a one-deep queue where the newest wins (the perception
  node's image queue). Each command reaches the arm when its location was ready: the end
  of the computation, or earlier for a pointer that hands its location over before it has
  finished (`Pointing.ready_s`: the model's map comes before its optimiser step, as the
  perception node publishes it).

Scoring, at every scene frame with an annotated actor: the angle between the optical axis
and the ray to the closest actor's centre (AAE), whether any actor's centre is in view, and
AUC-Judd of the pointer's newest map laid on the screen where the camera looked
(``VirtualScreen.place_map``) against the closest actor's centre. At every such frame the
pointer processed (in realtime mode also later, from the queue), the pointing error: the
angle between the camera's ray to the location it gave and its ray to the actor's centre
nearest that location, both at capture. It scores the perception alone: the AAE also pays
for the arm's lag and the controller's rules.
"""
import dataclasses
from dataclasses import dataclass, field
import math
import time
from typing import Callable, Iterable, Protocol

import numpy as np

from activeloc_ros import metrics
from activeloc_ros.control import ControllerConfig
from activeloc_ros.data import FrameTruth
from activeloc_ros.errors import ConfigError
from activeloc_ros.screen import VirtualScreen
from activeloc_ros.world import ScreenWorld, View

MODES = ('lockstep', 'realtime')
GRID = (14, 14)               # the map a pointer without one is given (the model's grid)
CANVAS = (96, 54)             # AUC canvas over the whole screen (16:9), cells
GAZE_SIGMA_CELLS = 1.0        # spread of a map made from a point


@dataclass
class Pointing:
    """A pointer's answer: where the action is in the camera image, and its map if any."""

    location: tuple[float, float] | None
    heat: np.ndarray | None = None     # (rows, cols) over the camera image
    peak: float | None = None
    ready_s: float | None = None       # s into `locate` the answer was ready (None: at its end)
    box: tuple | None = None           # x, y, w, h (px) of what is at the location, if known
    learnt: bool | None = None         # a learning pointer: whether it took an optimiser step


class Pointer(Protocol):
    name: str

    def reset(self, sequence: str) -> None:
        """A new sequence, named `sequence`, begins."""

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
    # the tracking world's: AD-VAT's reward, and where the base and the target are (m)
    reward: float = math.nan
    reward_relaxed: float = math.nan
    base_xy: tuple[float, float] | None = None
    target_xy: tuple[float, float] | None = None


@dataclass
class Episode:
    name: str
    pointer: str
    mode: str
    records: list[FrameRecord] = field(default_factory=list)
    compute_s: list[float] = field(default_factory=list)
    commands: int = 0
    learnt: int | None = None          # frames a learning pointer took an optimiser step on

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
            'learnt': (self.learnt / len(self.compute_s) if self.learnt is not None
                       and self.compute_s else math.nan),   # share of processed frames
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


def screen_world(frames: Iterable[tuple[int, np.ndarray, FrameTruth]], *, fps: float,
                 screen: VirtualScreen, controller: ControllerConfig,
                 camera_fps: float | None = None) -> ScreenWorld:
    """
    The projected-screen world of a sequence, its arm as ``controller`` expects it: at
    its home pose, moving at its servos' step delay.

    :param frames: (index, scene RGB, truth) in order.
    :param camera_fps: the camera's frame rate; None or a rate above the scene's captures
        every scene frame.
    """
    return ScreenWorld(frames, fps=fps, screen=screen, home_deg=controller.mapping.home_deg,
                       step_delay_ms=controller.step_delay_ms, camera_fps=camera_fps)


def run_episode(world, pointer: Pointer, *, controller,
                mode: str = 'lockstep', latency_s: float = 0.0, name: str = '',
                on_frame: Callable[[np.ndarray | None, FrameRecord, np.ndarray | None], None]
                | None = None) -> Episode:
    """
    Step a world through the closed loop until its frames end.

    :param world: the world, fresh: a `ScreenWorld` its arm at the controller's home pose
        (`screen_world`), or a `tracking.world.TrackingWorld`.
    :param controller: the config of the world's controller (`world.controller` builds it):
        `ControllerConfig` for the arm, `control.base.BaseConfig` for the base.
    :param latency_s: lockstep only: each location reaches the controller, and its command
        the actuator, this long after its frame's capture: a fixed compute time in place of
        realtime's measured one, so its cost is deterministic.
    :param on_frame: called with each scene frame (None in the tracking world), its record
        and the camera image (None when the camera captured nothing at that frame), e.g. to
        write a video.
    """
    if mode not in MODES:
        raise ConfigError(f'mode must be one of {list(MODES)}, got {mode!r}')
    if not (math.isfinite(latency_s) and latency_s >= 0):
        raise ConfigError(f'latency must be a time >= 0 s, got {latency_s}')
    if latency_s and mode != 'lockstep':
        raise ConfigError('a fixed latency is for lockstep mode: realtime measures its own')
    episode = Episode(name, pointer.name, mode)
    pointer.reset(name)
    ctl = world.controller(controller)
    pending: list[tuple[float, object]] = []   # (time it reaches the actuator, command)
    queued: View | None = None
    busy_until = -math.inf
    newest_map: tuple[np.ndarray, float, float] | None = None   # (heat, pan, tilt)
    newest_xy: tuple[float, float] | None = None
    results: list[tuple[float, np.ndarray, float, float, tuple | None]] = []  # for realtime
    pointing_deg: dict[int, float] = {}   # scene frame index -> error of its location
    intr = world.intrinsics
    camera = {'fx': intr.fx, 'fy': intr.fy, 'cx': intr.cx, 'cy': intr.cy}
    recorded: dict[int, FrameRecord] = {}

    def process(view: View, start: float) -> float:
        """Process a frame from ``start``; returns when the pointer is free again."""
        t0 = time.perf_counter()
        if mode == 'realtime':     # late once simulated time passes the next capture
            next_capture = view.t + world.capture_period
            view = dataclasses.replace(
                view, late=lambda: start + time.perf_counter() - t0 >= next_capture)
        pointing = pointer.locate(view)
        spent = time.perf_counter() - t0
        episode.compute_s.append(spent)
        if pointing.learnt is not None:
            episode.learnt = (episode.learnt or 0) + pointing.learnt
        ready = spent if pointing.ready_s is None else min(pointing.ready_s, spent)
        if mode == 'lockstep':
            done, free = start + latency_s, start
        else:
            done, free = start + ready, start + spent
        heat = pointing.heat if pointing.heat is not None else gaze_map(
            pointing.location, (view.rgb.shape[1], view.rgb.shape[0]))
        xy = None
        if pointing.location is not None:
            u, v = pointing.location
            actors = [metrics.pixel_ray(p, **camera) for p in view.truth_px
                      if np.all(np.isfinite(p))]
            if actors:
                pointing_deg[view.index] = metrics.closest_angle(
                    metrics.pixel_ray((u, v), **camera), actors)
            xy = world.to_scene(view, (u, v))
            cmd = ctl.on_location(u, v, view.t, done, peak=pointing.peak, box=pointing.box)
        else:
            cmd = ctl.tick(done)
        if cmd is not None:
            pending.append((done, cmd))
            episode.commands += 1
        results.append((done, heat, view.pan, view.tilt, xy))
        return free

    for t in world.times():
        # the perception finishes the queued frame, and may start it, before t
        if queued is not None and busy_until <= t:
            view, queued = queued, None
            busy_until = process(view, max(busy_until, view.t))
            recorded[view.index].processed = True    # later than its capture, but it was
        for when, cmd in sorted((p for p in pending if p[0] <= t), key=lambda p: p[0]):
            world.apply(cmd, when)
        pending[:] = [p for p in pending if p[0] > t]
        ctl.observe(world.advance(t), t)
        scan = world.scan()
        if scan is not None:
            ctl.observe_scan(scan)
        processed = False
        view = world.observe()                 # a dropped frame may still wait in the queue
        if view is not None and (mode == 'lockstep' or busy_until <= t):
            busy_until = process(view, t)
            processed = True
        elif view is not None:
            queued = view
        # the newest result available at t
        while results and results[0][0] <= t:
            done, heat, mpan, mtilt, xy = results.pop(0)
            newest_map, newest_xy = (heat, mpan, mtilt), xy
        record = FrameRecord(world.index, t, world.pan, world.tilt, processed, scored=False,
                             predicted_xy=newest_xy)
        world.score(record, newest_map, CANVAS)
        episode.records.append(record)
        recorded[world.index] = record
        for i, value in pointing_deg.items():   # realtime: also frames taken from the queue
            if recorded[i].scored:
                recorded[i].pointing_deg = value
        pointing_deg.clear()
        if on_frame is not None:
            on_frame(world.scene, record, None if view is None else view.rgb)
    return episode
