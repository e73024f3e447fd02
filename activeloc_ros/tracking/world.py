"""
`TrackingWorld`: the simulated active-tracking world (paper Sec. 4.1, Table 1), on the
same interface as the screen rig's `world.ScreenWorld`, so `closed_loop.run_episode` steps
it with any pointer.

A mobile base carries a camera (90 deg horizontal field of view, 1.5 m up, tilted 10 deg
down) and takes velocity commands (`control.base.Twist`); a person walks ahead of it, others
walk or play clips around. One step is one control period (10 Hz)::

    for t in world.times():          # step i at t_i = i * step, until the episode ends
        world.act(twist, when)       # commands that reach the base by t
        pose = world.advance(t)      # base and people move to t; the base's odometry
        scan = world.scan()          # its range sensor (`control.base.Scan`)
        view = world.observe()       # the camera's picture, and the target's true box
        world.score(record, ...)     # AD-VAT's reward; counts steps with the target lost

Rendering: pybullet's TinyRenderer on the CPU (no GPU, no display), which also gives a
segmentation mask, so the target's box is exact. Everything is seeded: the same scene and
seed give the same episode for the same commands.
"""
import contextlib
import dataclasses
from dataclasses import dataclass
import math
import os
from pathlib import Path
import sys
import tempfile

import numpy as np

from activeloc_ros import metrics
from activeloc_ros.checks import check_field_types, field_of_view, is_number
from activeloc_ros.control.base import BaseConfig, BaseController, Scan, Twist
from activeloc_ros.control.geometry import Intrinsics
from activeloc_ros.errors import ConfigError
from activeloc_ros.tracking import reward as rewards
from activeloc_ros.tracking.people import Behaviour, Clip, clothes, Person, Walker
from activeloc_ros.tracking.scenes import build
from activeloc_ros.world import View

TARGETS = ('nav', 'ram')
DISTRACTOR_CLIPS = ('walk', 'walk', 'dance_a', 'dance_b', 'punch', 'kick', 'jump')
BASE_RADIUS = 0.3          # m: the base's footprint, as a bump and the range sensor see it
PERSON_RADIUS = 0.3        # and a person's


@dataclass(frozen=True)
class TrackingConfig:
    """
    The tracking world's settings (defaults: the paper's set-up where it gives one).

    :param target: the target's behaviour, gym-unrealcv's Nav or Ram.
    :param lost_steps: steps in a row with the target lost (r = -1) that end an episode
        (paper 10; gym-unrealcv's code 20).
    :param min_visible_px: fewer target pixels than this is out of view.
    :param scan_rays: rays of the base's planar range sensor, evenly round 360 deg (a 2D
        lidar at the base's centre; it sees the obstacles, walls and people that stop the
        base); 0: no sensor.
    :param scan_range: the sensor's range, m.
    """

    width: int = 320
    height: int = 240
    hfov_deg: float = 90.0
    camera_height: float = 1.5
    camera_tilt_deg: float = -10.0
    step: float = 0.1
    max_steps: int = 500
    lost_steps: int = 10
    target: str = 'nav'
    start_distance: float = rewards.RHO_STAR
    target_speed: tuple[float, float] = (0.5, 1.2)
    max_speed: float = 2.0
    max_turn_deg_s: float = 90.0
    min_visible_px: int = 20
    scan_rays: int = 360
    scan_range: float = 4.0

    def __post_init__(self):
        check_field_types(self)
        speeds = self.target_speed
        if not (isinstance(speeds, tuple) and len(speeds) == 2 and all(map(is_number, speeds))):
            raise ConfigError(f'target_speed must be two numbers (low, high), got {speeds!r}')
        if self.target not in TARGETS:
            raise ConfigError(f'target must be one of {list(TARGETS)}, got {self.target!r}')
        problem = field_of_view(self.hfov_deg)
        if problem:
            raise ConfigError(f'hfov_deg: {problem}')
        if self.width < 16 or self.height < 16:
            raise ConfigError(f'image must be at least 16x16, got {self.width}x{self.height}')
        if self.max_steps < 1 or self.lost_steps < 1:
            raise ConfigError('max_steps and lost_steps must be >= 1')
        if not (self.step > 0 and self.start_distance > 0 and self.scan_range > 0):
            raise ConfigError('step, start_distance and scan_range must be > 0')
        if self.scan_rays < 0:
            raise ConfigError(f'scan_rays must be >= 0, got {self.scan_rays}')
        low, high = speeds
        if not 0 < low <= high:
            raise ConfigError(f'target_speed must be 0 < low <= high, got {self.target_speed}')

    @property
    def intrinsics(self) -> Intrinsics:
        f = metrics.focal_from_fov(self.width, self.hfov_deg)
        return Intrinsics(f, f, (self.width - 1) / 2, (self.height - 1) / 2,
                          self.width, self.height)


@contextlib.contextmanager
def quiet():
    """
    Hold back what pybullet's C code prints while it starts and loads models (its build
    time, argv, URDF warnings about the humanoid's joint axes).
    """
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    with open(os.devnull, 'w') as null:
        os.dup2(null.fileno(), 1)
        os.dup2(null.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])


def camera_image(client, width: int, height: int, view, projection,
                 **light) -> tuple[np.ndarray, np.ndarray]:
    """
    TinyRenderer's RGB image (H, W, 3) and segmentation mask (body ids, -1 for none) of
    ``client`` through ``view`` and ``projection``; ``light``: getCameraImage's lighting
    options (lightDirection, lightColor, shadow...).
    """
    _, _, rgba, _, seg = client.getCameraImage(width, height, view, projection,
                                               renderer=client.ER_TINY_RENDERER, **light)
    rgb = np.asarray(rgba, np.uint8).reshape(height, width, 4)[..., :3]
    return np.ascontiguousarray(rgb), np.asarray(seg).reshape(height, width)


def mask_box(seg: np.ndarray, body: int, min_px: int) -> tuple[int, int, int, int] | None:
    """
    The box (x, y, w, h) round the pixels of ``body`` in a segmentation mask; None when
    fewer than ``min_px`` of them show.
    """
    ys, xs = np.nonzero(seg == body)
    if len(xs) < max(min_px, 1):
        return None
    return (int(xs.min()), int(ys.min()), int(xs.max() - xs.min() + 1),
            int(ys.max() - ys.min() + 1))


class TrackingWorld:
    """
    One episode of the tracking experiment in scene ``scene`` from ``seed``.

    Call `close` (or use it as a context manager) to free the physics client.
    """

    scene = None     # no screen: `closed_loop.run_episode` hands on_frame no scene frame

    def __init__(self, scene: str, seed: int, config: TrackingConfig = TrackingConfig()):
        with quiet():
            import pybullet
            import pybullet_data
            from pybullet_utils.bullet_client import BulletClient
            self.config, self.scene_name, self.seed = config, scene, seed
            self.client = BulletClient(connection_mode=pybullet.DIRECT)
            self._folder = tempfile.TemporaryDirectory(prefix='activeloc-tracking-')
            try:
                self._build(scene, seed, pybullet_data.getDataPath())
            except BaseException:
                self.close()
                raise

    def _build(self, scene: str, seed: int, data_dir: str) -> None:
        cfg, c = self.config, self.client
        rng = np.random.default_rng(seed)
        built = build(scene, c, rng, Path(self._folder.name))
        self.plan = built.plan
        self.intrinsics = cfg.intrinsics
        clips = {}

        def clip(name: str) -> Clip:
            if name not in clips:
                clips[name] = Clip.load(name, data_dir)
            return clips[name]

        # the base and the target ahead of it, facing away, on free ground
        for _ in range(1000):
            x, y = self.plan.free_point(rng, margin=1.0)
            heading = rng.uniform(-math.pi, math.pi)
            ahead = [(x + s * math.cos(heading), y + s * math.sin(heading))
                     for s in np.linspace(0.5, cfg.start_distance + 1.0, 6)]
            if all(self.plan.free(px, py, 0.6) for px, py in ahead):
                break
        else:
            raise ConfigError(f'scene {scene!r} seed {seed}: no free start')
        self.base = Walker(x, y, heading, 0.0)
        d = cfg.start_distance
        self.target = Walker(x + d * math.cos(heading), y + d * math.sin(heading), heading,
                             cfg.target_speed[0])
        self.people = [(Person(c, clip('walk'), data_dir=data_dir, colours=clothes(rng)),
                        self.target,
                        Behaviour(cfg.target, self.plan, rng, speed=cfg.target_speed))]
        for _ in range(built.distractors):
            name = DISTRACTOR_CLIPS[int(rng.integers(len(DISTRACTOR_CLIPS)))]
            for _ in range(100):
                px, py = self.plan.free_point(rng, margin=0.6)
                if math.hypot(px - x, py - y) > 3.0 and math.hypot(
                        px - self.target.x, py - self.target.y) > 1.5:
                    break
            kind = str(rng.choice(TARGETS)) if name == 'walk' else 'stay'
            self.people.append((Person(c, clip(name), data_dir=data_dir, colours=clothes(rng)),
                                Walker(px, py, rng.uniform(-math.pi, math.pi),
                                       cfg.target_speed[0]),
                                Behaviour(kind, self.plan, rng, speed=cfg.target_speed)))
        for person, walker, _ in self.people:
            person.place(walker.x, walker.y, walker.heading, 0.0, 0.0)
        self.target_body = self.people[0][0].body
        self.kinds = {**built.kinds, **{p.body: 'distractor' for p, _, _ in self.people[1:]},
                      self.target_body: 'person'}
        self._seg: np.ndarray | None = None
        vfov = 2 * math.degrees(math.atan(cfg.height / 2 / self.intrinsics.fy))
        self._projection = c.computeProjectionMatrixFOV(vfov, cfg.width / cfg.height, 0.1, 60.0)
        self.index, self.t = -1, 0.0
        self._moved_to = 0.0
        self._twists: list[tuple[float, Twist]] = [(0.0, Twist())]
        self.lost_run = 0
        self.rewards: list[float] = []
        self.rewards_relaxed: list[float] = []
        self.blocked: list[bool] = []      # per scored step: a bump held the base back
        self._held_back = False
        self.view: View | None = None
        self.pan = self.tilt = 0.0

    # -- the world interface (world.ScreenWorld's) ---------------------------------------

    def controller(self, config: BaseConfig) -> BaseController:
        """
        The controller this world's base takes commands from, told its camera: its
        intrinsics, and its height and tilt (which the ground rule reads distances with).
        """
        cfg = self.config
        ctl = BaseController(dataclasses.replace(config, camera_height=cfg.camera_height,
                                                 camera_tilt_deg=cfg.camera_tilt_deg), t0=0.0)
        ctl.set_intrinsics(self.intrinsics)
        return ctl

    @property
    def capture_period(self) -> float:
        """Time from one camera capture to the next, s: one control step."""
        return self.config.step

    def times(self):
        """
        Each control step's time, until the episode ends: ``max_steps`` steps, or the
        target lost for ``lost_steps`` steps in a row.
        """
        cfg = self.config
        for index in range(cfg.max_steps):
            if self.lost_run >= cfg.lost_steps:
                return
            self.index, self.t = index, index * cfg.step
            yield self.t

    def apply(self, command, t: float) -> None:
        """A controller's command (`control.base.BaseCommand`) reaches the base at ``t``."""
        self.act(command.twist, t)

    def act(self, twist: Twist, t: float) -> None:
        """A velocity reaches the base at ``t``, clamped to its limits."""
        cfg = self.config
        turn = math.radians(cfg.max_turn_deg_s)
        forward, rate = float(twist.forward), float(twist.turn)
        if not (math.isfinite(forward) and math.isfinite(rate)):
            raise ConfigError(f'a velocity command must be finite, got {twist}')
        self._twists.append((t, Twist(min(max(forward, -cfg.max_speed), cfg.max_speed),
                                      min(max(rate, -turn), turn))))

    def advance(self, t: float) -> tuple[float, float, float]:
        """Move the base and the people to ``t``; the base's odometry (x, y, heading)."""
        marks = sorted({self._moved_to, *(w for w, _ in self._twists if self._moved_to < w < t),
                        t})
        for start, end in zip(marks, marks[1:]):
            twist = [tw for w, tw in self._twists if w <= start][-1]
            self._drive(twist, end - start)
        now = [(w, tw) for w, tw in self._twists if w <= t][-1]     # the one in effect at t
        self._twists = [now, *((w, tw) for w, tw in self._twists if w > t)]
        dt = t - self._moved_to
        if dt > 0:
            base = [(self.base.x, self.base.y, 0.5)]
            for person, walker, behaviour in self.people:
                walked = behaviour.step(walker, t, dt, movers=base)
                person.place(walker.x, walker.y, walker.heading, walked, dt)
        self._moved_to = t
        self.pan = self.base.heading
        return self.base.x, self.base.y, self.base.heading

    def _drive(self, twist: Twist, dt: float) -> None:
        b = self.base
        b.heading = math.remainder(b.heading + twist.turn * dt, math.tau)
        # a bump does not pass: the base slides along what it touches, as gym-unrealcv's
        # tracker (an Unreal character) does, instead of staying pinned in front of a tree
        x, y = b.x, b.y
        b.x, b.y = self.plan.slide(x, y, twist.forward * dt * math.cos(b.heading),
                                   twist.forward * dt * math.sin(b.heading), BASE_RADIUS,
                                   movers=self._movers())
        if math.hypot(b.x - x, b.y - y) < 0.5 * abs(twist.forward) * dt:
            self._held_back = True

    def _movers(self) -> list[tuple[float, float, float]]:
        return [(w.x, w.y, PERSON_RADIUS) for _, w, _ in self.people]

    def scan(self) -> Scan | None:
        """
        The base's range sensor now: ``scan_rays`` rays round it from its heading (None
        without one).
        """
        cfg, b = self.config, self.base
        if not cfg.scan_rays:
            return None
        angles = np.linspace(-math.pi, math.pi, cfg.scan_rays, endpoint=False)
        ranges = self.plan.ranges(b.x, b.y, b.heading + angles, max_range=cfg.scan_range,
                                  movers=self._movers())
        return Scan(angles, ranges, self.t)

    def render(self) -> tuple[np.ndarray, np.ndarray]:
        """The camera's RGB image (H, W, 3) and the segmentation mask (body ids)."""
        cfg, b, c = self.config, self.base, self.client
        tilt = math.radians(cfg.camera_tilt_deg)
        eye = [b.x, b.y, cfg.camera_height]
        look = [b.x + math.cos(b.heading) * math.cos(tilt),
                b.y + math.sin(b.heading) * math.cos(tilt), cfg.camera_height + math.sin(tilt)]
        view = c.computeViewMatrix(eye, look, [0, 0, 1])
        return camera_image(c, cfg.width, cfg.height, view, self._projection)

    def observe(self) -> View:
        """The camera's picture now, with the target's true box (None when out of view)."""
        rgb, seg = self.render()
        self._seg = seg
        box = mask_box(seg, self.target_body, self.config.min_visible_px)
        truth = np.zeros((0, 2))
        if box is not None:
            truth = np.array([[box[0] + (box[2] - 1) / 2, box[1] + (box[3] - 1) / 2]])
        intr = self.intrinsics
        self.view = View(rgb, self.index, self.t, self.base.heading, 0.0, truth,
                         truth[0] if len(truth) else None, np.array([intr.cx, intr.cy]),
                         truth_box=box)
        return self.view

    def kind_at(self, u: float, v: float) -> str:
        """
        Name what the newest view shows at pixel (u, v).

        The scene's kinds (ground, wall, furniture, facade, glass, post, tree, hut, pillar,
        car, deck), ``person`` (the target), ``distractor`` or ``sky`` (no body).
        """
        if self._seg is None:
            raise ConfigError('kind_at before the first view')
        h, w = self._seg.shape
        row, col = min(max(int(round(v)), 0), h - 1), min(max(int(round(u)), 0), w - 1)
        body = int(self._seg[row, col])
        return 'sky' if body < 0 else self.kinds.get(body, 'prop')

    def to_scene(self, view: View, uv: tuple[float, float]) -> None:
        """No screen here: a location has no scene pixel."""
        return None

    def relative(self) -> tuple[float, float]:
        """The target's distance (m) and bearing from the base's heading (rad, > 0 left)."""
        dx, dy = self.target.x - self.base.x, self.target.y - self.base.y
        bearing = math.remainder(math.atan2(dy, dx) - self.base.heading, math.tau)
        return math.hypot(dx, dy), bearing

    def score_step(self) -> tuple[float, float, float]:
        """
        Score the step now: AD-VAT's reward, relaxed reward and the bearing (rad); counts
        the steps the target has been lost in a row.
        """
        distance, bearing = self.relative()
        r = rewards.reward(distance, bearing, rho=self.config.start_distance)
        relaxed = rewards.reward_relaxed(distance, bearing, rho=self.config.start_distance)
        self.rewards.append(r)
        self.rewards_relaxed.append(relaxed)
        self.blocked.append(self._held_back)
        self._held_back = False
        self.lost_run = self.lost_run + 1 if r <= rewards.LOST else 0
        return r, relaxed, bearing

    def score(self, record, newest_map=None, canvas=None) -> None:
        """
        Fill ``record`` with the step's scores (`score_step`), the bearing error as AAE,
        whether the target is in view and where the base and the target are.
        """
        r, relaxed, bearing = self.score_step()
        record.scored = True
        record.aae_deg = abs(math.degrees(bearing))
        record.in_view = self.view is not None and self.view.truth_box is not None
        record.reward, record.reward_relaxed = r, relaxed
        record.base_xy = (self.base.x, self.base.y)
        record.target_xy = (self.target.x, self.target.y)

    def episode_score(self) -> rewards.EpisodeScore:
        return rewards.score(self.rewards, self.rewards_relaxed, self.config.max_steps)

    def lost_cause(self, records) -> str | None:
        """
        Why the episode of these records lost its target (`rewards.lost_cause`); None
        when it ran to its end.
        """
        if len(self.rewards) >= self.config.max_steps:
            return None
        return rewards.lost_cause([r.in_view for r in records], [r.aae_deg for r in records],
                                  self.blocked, half_fov_deg=self.config.hfov_deg / 2)

    def close(self) -> None:
        """Free the physics client and the textures (twice is harmless)."""
        if self.client is not None:
            self.client.disconnect()
            self.client = None
        self._folder.cleanup()

    def __enter__(self) -> 'TrackingWorld':
        return self

    def __exit__(self, *exc) -> None:
        self.close()
