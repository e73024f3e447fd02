"""
Synthetic static-camera clips: one dominant person playing an action in a tracking-world
scene (`scenes`), seen by a camera that never moves, with each person's exact box per frame.

A clip is decided whole before it is rendered, from ``numpy.random.default_rng([seed,
index])``: the scene (room, urban, snow or parking, with their seeded textures and props),
the camera (where it stands, its height, tilt and field of view), the actor (its action,
size, distance and path), extra props, zero to six distractors and the light. Then every
frame is posed (`people.Person` plays the DeepMimic clips) and rendered by TinyRenderer,
whose segmentation mask gives the boxes::

    with SyntheticClip(seed, index, ClipConfig()) as clip:
        for frame in clip.frames():     # frame.rgb, frame.actor (x, y, w, h) or None
            ...
        clip.describe()                 # the scene's parameters, JSON-ready

The actor stays in view by construction: its path joins waypoints where a person is wholly
in the picture and seen past every prop (a convex region, so the legs between are too).
Distractors keep 40 % (and 1.2 m) farther than the actor ever is: smaller, never in front.
"""
from dataclasses import dataclass
import math
from pathlib import Path
import tempfile
from typing import Iterator

import numpy as np

from activeloc_ros.checks import check_field_types
from activeloc_ros.errors import ConfigError
from activeloc_ros.tracking.clip_camera import Camera
from activeloc_ros.tracking.people import Clip, clothes, follow, Person, TRAVEL_CLIPS
from activeloc_ros.tracking.scenes import build, Builder, SCENES, TEXTURES
from activeloc_ros.tracking.world import camera_image, mask_box, quiet

# bump when the same seed and settings would render another clip: `bench scenes` redoes a
# folder whose recorded version differs
VERSION = 1
ACTIONS = {'walk': ('walk',), 'run': ('run',), 'dance': ('dance_a', 'dance_b'),
           'kick': ('kick',), 'punch': ('punch',), 'jump': ('jump',)}
SPEEDS = {'walk': (0.8, 1.5), 'run': (2.0, 3.2)}    # m/s of the locomotion actions
DRIFT_SPEED = (0.1, 0.35)      # m/s: an in-place action that moves slowly
PATHS = ('across', 'across', 'toward', 'away', 'wander')   # a locomotion actor's, 2:1:1:1
IDLE_CLIPS = ('dance_a', 'dance_b', 'punch')         # played slowly: swaying, shifting
DISTRACTOR_KINDS = ('walker', 'slow walker', 'idle')
MAX_DISTRACTORS = 6
CAMERA_TOP = {'room': 2.6, 'parking': 2.6, 'urban': 4.0, 'snow': 4.0}   # m: below ceilings
# every distractor stays this much farther than the actor ever is: 1.2 m and 40 %, so it
# looks at most about 0.7 times as tall
BEHIND = (1.2, 1.4)
LIGHT_NAMES = {'lightDirection': 'direction', 'lightColor': 'colour', 'lightDistance':
               'distance', 'shadow': 'shadows', 'lightAmbientCoeff': 'ambient',
               'lightDiffuseCoeff': 'diffuse', 'lightSpecularCoeff': 'specular'}


@dataclass(frozen=True)
class ClipConfig:
    """
    What every clip of a set shares.

    :param min_visible_px: fewer of a person's pixels than this is not visible (0: by the
        image's area, 12 at 640x360).
    """

    width: int = 640
    height: int = 360
    frames: int = 120
    fps: float = 15.0
    min_visible_px: int = 0

    def __post_init__(self):
        check_field_types(self)
        if not (32 <= self.width <= 4096 and 32 <= self.height <= 4096) or (
                self.width % 2 or self.height % 2):
            raise ConfigError('width and height must be even and 32 to 4096 (H.264 video), '
                              f'got {self.width}x{self.height}')
        if self.frames < 1 or self.min_visible_px < 0 or not 1.0 <= self.fps <= 120.0:
            raise ConfigError(f'frames must be >= 1, min_visible_px >= 0 and fps in [1, 120], '
                              f'got {self.frames}, {self.min_visible_px}, {self.fps!r}')

    @property
    def visible_px(self) -> int:
        return self.min_visible_px or max(4, round(self.width * self.height / 20000))


@dataclass
class Motion:
    """
    One person's part in a clip, decided before rendering: which clip it plays and where
    it is in each frame.
    """

    role: str               # 'actor', or one of DISTRACTOR_KINDS
    clip: str
    scale: float            # its size against the 1.7 m humanoid
    rate: float             # playback rate of a clip that does not travel; 0: a still pose
    phase: float            # where in its clip it starts, cycles
    speed: float            # m/s along its path; 0: in place
    path: str               # 'across', 'toward', 'away', 'wander', 'drift', 'in place'
    waypoints: np.ndarray   # (K, 2) m
    xy: np.ndarray          # (F, 2) m, per frame
    heading: np.ndarray     # (F,) rad
    walked: np.ndarray      # (F,) m since the frame before
    colours: dict

    def describe(self) -> dict:
        return {'role': self.role, 'clip': self.clip, 'scale': self.scale, 'rate': self.rate,
                'speed_m_s': self.speed, 'path': self.path, 'waypoints': self.waypoints,
                'colours': {k: v[:3] for k, v in self.colours.items()}}


@dataclass(frozen=True)
class Frame:
    """
    A rendered frame, RGB (H, W, 3), and the actor's and each distractor's box (x, y,
    w, h; None: not visible).
    """

    index: int
    rgb: np.ndarray
    actor: tuple[int, int, int, int] | None
    distractors: tuple


def _plain(value):
    """``value`` for JSON: numpy made plain, floats to 3 decimals (mm, 0.001 deg)."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_plain(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return round(float(value), 3)
    return int(value) if isinstance(value, np.integer) else value


class SyntheticClip:
    """
    Clip ``index`` of ``seed``, built and planned in its own pybullet client; `frames`
    renders it. Close it (or use it as a context manager) to free the client.
    """

    def __init__(self, seed: int, index: int, config: ClipConfig = ClipConfig()):
        self.config, self.seed, self.index = config, seed, index
        self.client = None
        self._folder = tempfile.TemporaryDirectory(prefix='activeloc-clips-')
        try:
            with quiet():   # pybullet's banner and URDF warnings
                import pybullet
                import pybullet_data
                from pybullet_utils.bullet_client import BulletClient
                self.client = BulletClient(connection_mode=pybullet.DIRECT)
                self._build(np.random.default_rng([seed, index]), pybullet_data.getDataPath())
        except BaseException:
            self.close()
            raise

    def _build(self, rng: np.random.Generator, data_dir: str) -> None:
        self.style = str(rng.choice(SCENES))
        self.plan = build(self.style, self.client, rng, Path(self._folder.name)).plan
        self.action = str(rng.choice(list(ACTIONS)))
        clip = str(rng.choice(ACTIONS[self.action]))
        for _ in range(400):
            self.camera = self._camera(rng)
            actor = self._actor(rng, clip)
            if actor is not None:
                break
        else:
            raise ConfigError(f'clip {self.index} of seed {self.seed}: found no camera that '
                              f'sees a path for the {self.action} actor')
        self.motions = [actor]
        self.props = self._props(rng, Builder(self.client, rng, Path(self._folder.name)))
        self.wanted = int(rng.integers(0, MAX_DISTRACTORS + 1))
        for _ in range(self.wanted):
            motion = self._distractor(rng)
            if motion is not None:
                self.motions.append(motion)
        self.lighting = _lighting(rng)
        clips: dict[str, Clip] = {}
        self.people = []
        for m in self.motions:
            if m.clip not in clips:
                loaded = Clip.load(m.clip, data_dir)   # held in place: the planned spot holds
                clips[m.clip] = loaded if m.clip in TRAVEL_CLIPS else loaded.in_place()
            person = Person(self.client, clips[m.clip], data_dir=data_dir, colours=m.colours,
                            scale=m.scale)
            person.phase = m.phase
            self.people.append(person)
        self.view, self.projection = self.camera.matrices(self.client)

    # -- planning ---------------------------------------------------------------------------

    def _camera(self, rng: np.random.Generator) -> Camera:
        x, y = self.plan.free_point(rng, margin=0.4)
        for _ in range(100):    # look at a point far enough away to leave room ahead
            gx, gy = self.plan.free_point(rng, margin=0.5)
            if math.hypot(gx - x, gy - y) >= 7.0:
                break
        z = rng.uniform(1.0, CAMERA_TOP[self.style])
        aim = rng.uniform(5.0, 15.0)        # where the optical axis meets the ground, m
        tilt = -math.degrees(math.atan2(z, aim)) + rng.uniform(-2.0, 2.0)
        return Camera(x, y, z, math.atan2(gy - y, gx - x), tilt, rng.uniform(55.0, 85.0),
                      self.config.width, self.config.height)

    def _point(self, rng: np.random.Generator, ahead: tuple[float, float],
               across: tuple[float, float]) -> tuple[float, float]:
        """A ground point ``ahead`` m in front, ``across`` its half-width to the right."""
        cam = self.camera
        d = rng.uniform(*ahead)
        half = d * math.tan(math.radians(cam.hfov_deg) / 2)
        return cam.ground(d, rng.uniform(*across) * half)

    def _seen(self, points: np.ndarray, scale: float) -> bool:
        """
        Is a person at every point wholly in the picture, on free ground, and seen past
        every prop?
        """
        cam, plan = self.camera, self.plan
        points = np.asarray(points, float).reshape(-1, 2)
        if not cam.sees_person(points, scale).all():
            return False
        dx, dy = points[:, 0] - cam.x, points[:, 1] - cam.y
        distance = np.hypot(dx, dy)
        hits = plan.ranges(cam.x, cam.y, np.arctan2(dy, dx), max_range=float(distance.max()))
        return bool(np.all(hits > distance) and all(plan.free(x, y, 0.45) for x, y in points))

    def _leg_clear(self, a, b, *, scale: float, seen: bool) -> bool:
        points = np.linspace(a, b, max(2, int(math.hypot(b[0] - a[0], b[1] - a[1]) / 0.4) + 1))
        return self._seen(points, scale) if seen else all(
            self.plan.free(x, y, 0.4) for x, y in points)

    def _route(self, rng: np.random.Generator, sample, length: float, *, min_leg: float,
               scale: float, seen: bool) -> np.ndarray | None:
        """
        Waypoints from ``sample(rng, k)`` (the k-th) whose legs are clear and add up to
        ``length`` m; None if none is found.
        """
        first = next((p for p in (sample(rng, 0) for _ in range(60)) if self._seen([p], scale)),
                     None)
        if first is None:
            return None
        points = [first]
        total = 0.0
        while total < length and len(points) < 40:
            for _ in range(60):
                p = sample(rng, len(points))
                leg = math.hypot(p[0] - points[-1][0], p[1] - points[-1][1])
                if leg >= min_leg and self._leg_clear(points[-1], p, scale=scale, seen=seen):
                    break
            else:
                return None
            points.append(p)
            total += leg
        return np.array(points)

    def _actor(self, rng: np.random.Generator, clip: str) -> Motion | None:
        cfg = self.config
        duration = cfg.frames / cfg.fps
        scale = rng.uniform(0.92, 1.08)
        colours = clothes(rng)
        heading = rng.uniform(-math.pi, math.pi)
        if self.action in SPEEDS:
            speed = rng.uniform(*SPEEDS[self.action])
            path = str(rng.choice(PATHS))
            near = rng.uniform(4.5, 9.0) if self.action == 'run' else rng.uniform(3.0, 7.0)
            far = near + (rng.uniform(1.0, 2.0) if path == 'across' else rng.uniform(2.5, 5.0))
        else:
            speed = rng.uniform(*DRIFT_SPEED) if rng.random() < 0.5 else 0.0
            path = 'drift' if speed else 'in place'
            near = rng.uniform(2.5, 7.0)
            far = near + 1.5
        side = rng.choice([-1.0, 1.0])
        start_near = path == 'away'

        def sample(g: np.random.Generator, k: int) -> tuple[float, float]:
            if path == 'across':            # from one side to the other, and back
                s = side * (-1) ** k
                return self._point(g, (near, far), tuple(sorted((0.45 * s, 0.85 * s))))
            if path in ('toward', 'away'):  # between the near and the far end
                at_near = (k % 2 == 0) == start_near
                ends = (near, near + 0.7) if at_near else (far - 0.7, far)
                return self._point(g, ends, (-0.5, 0.5))
            # kicks and punches reach out farther than a walker's shoulders: keep off the edges
            spread = 0.8 if path == 'wander' else 0.65
            return self._point(g, (near, far), (-spread, spread))

        if speed == 0:
            waypoints = self._route(rng, sample, 0.0, min_leg=0.0, scale=scale, seen=True)
        elif path == 'drift':               # one straight, slow leg
            length = speed * duration + 0.2
            start = sample(rng, 0)
            end = (start[0] + length * math.cos(heading), start[1] + length * math.sin(heading))
            ok = self._leg_clear(start, end, scale=scale, seen=True)
            waypoints = np.array([start, end]) if ok else None
        else:
            waypoints = self._route(rng, sample, speed * duration + 0.5,
                                    min_leg=2.0 if path == 'wander' else 1.0, scale=scale,
                                    seen=True)
        if waypoints is None:
            return None
        xy, headings, walked = follow(waypoints, speed, cfg.frames, cfg.fps, heading=heading)
        rate = 1.0 if clip in TRAVEL_CLIPS else rng.uniform(0.85, 1.15)
        return Motion('actor', clip, scale, rate, rng.uniform(), speed, path, waypoints, xy,
                      headings, walked, colours)

    def _props(self, rng: np.random.Generator, b: Builder) -> list[dict]:
        """Up to four crates, drums, bushes and boards, clear of the actor's sight lines."""
        cam, actor = self.camera, self.motions[0]
        sight = actor.xy[::max(1, len(actor.xy) // 20)]
        made = []
        for _ in range(int(rng.integers(0, 5))):
            kind = str(rng.choice(['crate', 'drum', 'bush', 'board']))
            size = rng.uniform(0.3, 0.6)
            for _ in range(50):
                x, y = self._point(rng, (1.5, 20.0), (-1.2, 1.2))
                if self.plan.free(x, y, size + 0.2) and _clear_of(
                        (x, y), size + 0.4, (cam.x, cam.y), sight):
                    break
            else:
                continue
            yaw = rng.uniform(0, math.pi)
            if kind == 'crate':
                texture = str(rng.choice(TEXTURES)) if rng.random() < 0.6 else None
                b.box((x, y, size), (size, size, size), b.colour(), texture=texture, yaw=yaw)
            elif kind == 'drum':
                b.cylinder(x, y, size * 0.7, size * 3.0, b.colour(0.05, 0.95))
            elif kind == 'bush':
                green = (rng.uniform(0.05, 0.3), rng.uniform(0.3, 0.6), rng.uniform(0.05, 0.25), 1)
                b.sphere(x, y, size * 0.8, size * 1.3, green)
            else:
                texture = str(rng.choice(['facade', 'glass', 'wall']))
                b.box((x, y, size * 1.6), (size * 2.0, 0.05, size * 1.6), texture=texture,
                      yaw=yaw)
            self.plan.obstacles.append((x, y, size * 2.0 if kind == 'board' else size * 1.3))
            made.append({'kind': kind, 'x': x, 'y': y, 'size_m': size})
        return made

    def _distractor(self, rng: np.random.Generator) -> Motion | None:
        """
        A smaller, farther person: a walker, a slow walker or one standing idle, always
        `BEHIND` the actor, and clear of everyone else.
        """
        cfg = self.config
        kind = str(rng.choice(DISTRACTOR_KINDS, p=[0.4, 0.3, 0.3]))
        scale, colours = rng.uniform(0.82, 1.0), clothes(rng)
        far = float(self.camera.ahead(self.motions[0].xy).max())
        beyond = max(far + BEHIND[0], far * BEHIND[1])
        depth = (beyond, beyond + 9.0)
        for _ in range(5):
            if kind == 'idle':
                clip, speed, path = str(rng.choice(IDLE_CLIPS)), 0.0, 'in place'
                rate = 0.0 if rng.random() < 0.3 else rng.uniform(0.1, 0.35)
                waypoints = self._route(rng, lambda g, k: self._point(g, depth, (-0.9, 0.9)),
                                        0.0, min_leg=0.0, scale=scale, seen=True)
            else:
                clip, rate, path = 'walk', 1.0, 'wander'
                speed = rng.uniform(0.8, 1.4) if kind == 'walker' else rng.uniform(0.25, 0.6)
                # it may walk out of the picture and back in: only its start must be seen
                waypoints = self._route(
                    rng, lambda g, k: self._point(g, depth, (-1.4, 1.4) if k else (-0.9, 0.9)),
                    speed * cfg.frames / cfg.fps + 0.5, min_leg=1.5, scale=scale, seen=False)
            if waypoints is None:
                continue
            heading = rng.uniform(-math.pi, math.pi)
            xy, headings, walked = follow(waypoints, speed, cfg.frames, cfg.fps, heading=heading)
            if all(np.hypot(*(xy - m.xy).T).min() >= 0.8 for m in self.motions):
                return Motion(kind, clip, scale, rate, rng.uniform(), speed, path, waypoints,
                              xy, headings, walked, colours)
        return None

    # -- rendering --------------------------------------------------------------------------

    def frames(self) -> Iterator[Frame]:
        """Pose everyone and render each frame in turn (once: the people's clips advance)."""
        cfg, c = self.config, self.client
        for k in range(cfg.frames):
            dt = 1.0 / cfg.fps if k else 0.0
            for person, m in zip(self.people, self.motions):
                person.place(float(m.xy[k, 0]), float(m.xy[k, 1]), float(m.heading[k]),
                             float(m.walked[k]), dt * m.rate)
            rgb, seg = camera_image(c, cfg.width, cfg.height, self.view, self.projection,
                                    **self.lighting)
            boxes = [mask_box(seg, p.body, cfg.visible_px) for p in self.people]
            yield Frame(k, rgb, boxes[0], tuple(boxes[1:]))

    def describe(self) -> dict:
        """The clip's parameters, JSON-ready."""
        actor = self.motions[0]
        ahead = self.camera.ahead(actor.xy)
        return _plain({
            'scene': self.style, 'action': self.action, 'camera': self.camera.describe(),
            'actor': {**actor.describe(), 'distance_m': [ahead.min(), ahead.max()]},
            'distractor_count': len(self.motions) - 1,
            'distractors': [m.describe() for m in self.motions[1:]],
            'distractors_wanted': self.wanted, 'props': self.props,
            'lighting': {LIGHT_NAMES[k]: v for k, v in self.lighting.items()}})

    def close(self) -> None:
        """Free the physics client and the textures (twice is harmless)."""
        if self.client is not None:
            self.client.disconnect()
            self.client = None
        self._folder.cleanup()

    def __enter__(self) -> 'SyntheticClip':
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _clear_of(point, radius: float, eye, targets: np.ndarray) -> bool:
    """
    Does a disc at ``point`` keep off every sight line from ``eye`` to ``targets`` (N, 2)
    and off the targets themselves?
    """
    p, e = np.asarray(point, float), np.asarray(eye, float)
    seg = np.asarray(targets, float) - e
    along = np.clip(((p - e) @ seg.T) / np.maximum((seg ** 2).sum(1), 1e-9), 0.0, 1.0)
    nearest = e + along[:, None] * seg
    return bool(np.hypot(*(nearest - p).T).min() >= radius)


def _lighting(rng: np.random.Generator) -> dict:
    """
    TinyRenderer's light: from a random side and height, tinted, with shadows half the
    time (they double the rendering time).
    """
    azimuth, elevation = rng.uniform(0, math.tau), rng.uniform(math.radians(25), math.radians(80))
    tint = rng.uniform(0.75, 1.0, 3)
    return {'lightDirection': [math.cos(elevation) * math.cos(azimuth),
                               math.cos(elevation) * math.sin(azimuth), math.sin(elevation)],
            'lightColor': (tint / tint.max()).tolist(), 'lightDistance': 10.0,
            'shadow': int(rng.random() < 0.5),
            'lightAmbientCoeff': float(rng.uniform(0.45, 0.75)),
            'lightDiffuseCoeff': float(rng.uniform(0.25, 0.6)),
            'lightSpecularCoeff': float(rng.uniform(0.0, 0.15))}
