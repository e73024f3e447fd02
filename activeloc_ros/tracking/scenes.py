"""
The four scenes of the tracking experiment, analogues of the paper's Table 1 worlds, and
their ground plan.

Each scene is built from its seed: layout, textures, props and people's clothes. The props
are static boxes and cylinders; only their footprint matters to the walkers (`Plan`):
circles they steer clear of, inside a rectangle.

- ``room`` (DuelingRoom): a 12 x 10 m room, textured walls and floor, furniture, one
  distractor;
- ``urban`` (UrbanCity): a street between busy facades, shiny glass panels, poles, a crowd
  of five;
- ``snow`` (SnowVillage): white ground, trees and huts that occlude, two distractors;
- ``parking`` (ParkingLot): a grid of pillars and rows of parked cars, two distractors.
"""
from dataclasses import dataclass, field
import math
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from activeloc_ros.errors import ConfigError

SCENES = ('room', 'urban', 'snow', 'parking')
# the procedural textures `Builder.texture` makes
TEXTURES = ('floor', 'wall', 'facade', 'glass', 'road', 'snow', 'concrete')
# the Table 1 world each scene stands in for
PAPER_NAMES = {'room': 'DuelingRoom', 'urban': 'UrbanCity', 'snow': 'SnowVillage',
               'parking': 'ParkingLot'}


@dataclass
class Plan:
    """The ground plan: a rectangle (x0, y0, x1, y1) and circular obstacles (x, y, r), m."""

    bounds: tuple[float, float, float, float]
    obstacles: list[tuple[float, float, float]] = field(default_factory=list)

    def free(self, x: float, y: float, radius: float = 0.0, *,
             movers: Sequence[tuple[float, float, float]] = ()) -> bool:
        """
        Is a disc of ``radius`` at (x, y) inside the bounds and clear of the obstacles
        and of ``movers`` (x, y, r: the base, other people)?
        """
        x0, y0, x1, y1 = self.bounds
        if not (x0 + radius <= x <= x1 - radius and y0 + radius <= y <= y1 - radius):
            return False
        return all(math.hypot(x - ox, y - oy) >= r + radius
                   for ox, oy, r in (*self.obstacles, *movers))

    def slide(self, x: float, y: float, dx: float, dy: float, radius: float, *,
              movers: Sequence[tuple[float, float, float]] = ()) -> tuple[float, float]:
        """
        Where a disc of ``radius`` at (x, y) that moves by (dx, dy) ends: there if that is
        free; else the part of the move along what it touches, with the part into each
        obstacle, mover or wall taken out (it slides along them, as a character of a game
        engine does); else where it is.
        """
        nx, ny = x + dx, y + dy
        if self.free(nx, ny, radius, movers=movers):
            return nx, ny
        x0, y0, x1, y1 = self.bounds
        if (nx - radius < x0 and dx < 0) or (nx + radius > x1 and dx > 0):
            dx = 0.0
        if (ny - radius < y0 and dy < 0) or (ny + radius > y1 and dy > 0):
            dy = 0.0
        for ox, oy, r in (*self.obstacles, *movers):
            if math.hypot(nx - ox, ny - oy) < r + radius:
                away = math.hypot(x - ox, y - oy)
                if away > 0:
                    ux, uy = (x - ox) / away, (y - oy) / away
                    into = dx * ux + dy * uy
                    if into < 0:
                        dx, dy = dx - into * ux, dy - into * uy
        if (dx or dy) and self.free(x + dx, y + dy, radius, movers=movers):
            return x + dx, y + dy
        return x, y

    def free_point(self, rng: np.random.Generator, *, margin: float) -> tuple[float, float]:
        x0, y0, x1, y1 = self.bounds
        for _ in range(1000):
            x, y = rng.uniform(x0 + margin, x1 - margin), rng.uniform(y0 + margin, y1 - margin)
            if self.free(x, y, margin):
                return x, y
        raise ConfigError(f'no free point {margin} m from every obstacle in {self.bounds}')

    def ranges(self, x: float, y: float, directions: np.ndarray, *, max_range: float,
               movers: Sequence[tuple[float, float, float]] = ()) -> np.ndarray:
        """
        What a planar range sensor at (x, y) measures along ``directions`` (radians, in
        the plan's frame): the distance to the nearest obstacle, mover or wall, m; inf
        where nothing lies within ``max_range``. A sensor inside an obstacle reads 0.
        """
        dx, dy = np.cos(directions), np.sin(directions)
        x0, y0, x1, y1 = self.bounds
        with np.errstate(divide='ignore'):
            wall_x = np.where(dx > 0, (x1 - x) / dx, np.where(dx < 0, (x0 - x) / dx, np.inf))
            wall_y = np.where(dy > 0, (y1 - y) / dy, np.where(dy < 0, (y0 - y) / dy, np.inf))
        hits = np.maximum(np.minimum(wall_x, wall_y), 0.0)
        circles = np.asarray([*self.obstacles, *movers], float).reshape(-1, 3)
        for ox, oy, r in circles:
            along = (ox - x) * dx + (oy - y) * dy           # closest approach along each ray
            miss2 = (ox - x) ** 2 + (oy - y) ** 2 - along ** 2
            half = np.sqrt(np.maximum(r * r - miss2, 0.0))
            entry = np.where((miss2 <= r * r) & (along + half >= 0),
                             np.maximum(along - half, 0.0), np.inf)
            hits = np.minimum(hits, entry)
        return np.where(hits <= max_range, hits, np.inf)

    def steer_clear(self, x: float, y: float, heading: float, *, reach: float,
                    movers: Sequence[tuple[float, float, float]] = ()) -> float:
        """
        ``heading``, or the nearest heading (in 15 degree steps) whose path of ``reach`` m
        stays free.
        """
        for k in range(13):
            for sign in (1, -1):
                h = heading + sign * math.radians(15 * k)
                if all(self.free(x + s * math.cos(h), y + s * math.sin(h), 0.4, movers=movers)
                       for s in (reach / 3, 2 * reach / 3, reach)):
                    return h
        return heading + math.pi


def _texture(kind: str, rng: np.random.Generator, folder: Path) -> str:
    """A procedural texture written as PNG; its path."""
    size = 256
    if kind == 'floor':        # wooden boards
        base = rng.uniform(90, 160, 3)
        img = np.zeros((size, size, 3), np.float32) + base
        for i in range(0, size, 32):
            img[i:i + 32] *= rng.uniform(0.8, 1.2)
            img[i:i + 1] *= 0.5
        img += rng.normal(0, 8, (size, size, 1))
    elif kind == 'wall':       # paint with a picture rail and frames
        img = np.zeros((size, size, 3), np.float32) + rng.uniform(120, 220, 3)
        img[100:108] *= 0.6
        for _ in range(2):
            x, y = rng.integers(10, 180, 2)
            img[y:y + 60, x:x + 50] = rng.uniform(30, 230, 3)
    elif kind == 'facade':     # windows in rows, busy
        img = np.zeros((size, size, 3), np.float32) + rng.uniform(80, 200, 3)
        glass = rng.uniform(20, 90, 3)
        for y in range(12, size, 48):
            for x in range(12, size, 40):
                img[y:y + 30, x:x + 24] = glass + rng.uniform(0, 120)
        img += rng.normal(0, 6, (size, size, 1))
    elif kind == 'glass':      # a shiny panel: streaks of reflected light
        img = np.zeros((size, size, 3), np.float32) + rng.uniform(40, 90, 3)
        for _ in range(6):
            x = int(rng.integers(0, size))
            cv2.line(img, (x, 0), (x + int(rng.integers(-80, 80)), size - 1),
                     (230, 230, 240), int(rng.integers(3, 14)))
    elif kind == 'road':       # asphalt with lane markings
        img = np.zeros((size, size, 3), np.float32) + rng.uniform(55, 80)
        img += rng.normal(0, 10, (size, size, 1))
        img[:, 124:132] = (220, 220, 200)
        img[0:128, 124:132] = img[0:128, 0:8]
    elif kind == 'snow':       # white with faint drifts
        img = np.zeros((size, size, 3), np.float32) + 235
        img += cv2.GaussianBlur(rng.normal(0, 25, (size, size)).astype(np.float32),
                                (0, 0), 6)[..., None]
    elif kind == 'concrete':
        img = np.zeros((size, size, 3), np.float32) + rng.uniform(110, 150)
        img += rng.normal(0, 12, (size, size, 1))
        img[:, 0:3] *= 0.6
        img[0:3] *= 0.6
    else:
        raise ConfigError(f'unknown texture {kind!r}')
    path = folder / f'{kind}_{int(rng.integers(1 << 30))}.png'
    cv2.imwrite(str(path), np.clip(img, 0, 255).astype(np.uint8))
    return str(path)


class Builder:
    """Puts static props into a pybullet world."""

    def __init__(self, client, rng: np.random.Generator, folder: Path):
        self.client, self.rng, self.folder = client, rng, folder
        self.textures: dict[str, int] = {}
        self.kinds: dict[int, str] = {}    # body id -> what it is (tree, car, facade...)

    def _made(self, body: int, kind: str) -> int:
        self.kinds[body] = kind
        return body

    def texture(self, kind: str) -> int:
        if kind not in self.textures:
            self.textures[kind] = self.client.loadTexture(_texture(kind, self.rng, self.folder))
        return self.textures[kind]

    def box(self, centre, half, rgba=(1, 1, 1, 1), texture: str | None = None,
            yaw: float = 0.0, kind: str = 'prop') -> int:
        c = self.client
        shape = c.createVisualShape(c.GEOM_BOX, halfExtents=list(half), rgbaColor=list(rgba))
        body = c.createMultiBody(0, -1, shape, list(centre),
                                 c.getQuaternionFromEuler([0, 0, yaw]))
        if texture:
            c.changeVisualShape(body, -1, textureUniqueId=self.texture(texture))
        return self._made(body, kind)

    def cylinder(self, x, y, radius, height, rgba, z0: float = 0.0, kind: str = 'prop') -> int:
        c = self.client
        shape = c.createVisualShape(c.GEOM_CYLINDER, radius=radius, length=height,
                                    rgbaColor=list(rgba))
        return self._made(c.createMultiBody(0, -1, shape, [x, y, z0 + height / 2]), kind)

    def sphere(self, x, y, z, radius, rgba, kind: str = 'prop') -> int:
        c = self.client
        shape = c.createVisualShape(c.GEOM_SPHERE, radius=radius, rgbaColor=list(rgba))
        return self._made(c.createMultiBody(0, -1, shape, [x, y, z]), kind)

    def ground(self, size: float, texture: str) -> int:
        return self.box((0, 0, -0.05), (size, size, 0.05), texture=texture, kind='ground')

    def walls(self, bounds, height: float, texture: str) -> None:
        x0, y0, x1, y1 = bounds
        cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
        for centre, half in (((cx, y0 - 0.1, height / 2), ((x1 - x0) / 2 + 0.2, 0.1, height / 2)),
                             ((cx, y1 + 0.1, height / 2), ((x1 - x0) / 2 + 0.2, 0.1, height / 2)),
                             ((x0 - 0.1, cy, height / 2), (0.1, (y1 - y0) / 2, height / 2)),
                             ((x1 + 0.1, cy, height / 2), (0.1, (y1 - y0) / 2, height / 2))):
            self.box(centre, half, texture=texture, kind='wall')

    def colour(self, low: float = 0.1, high: float = 0.9) -> tuple[float, float, float, float]:
        return (*self.rng.uniform(low, high, 3), 1.0)


@dataclass
class Scene:
    """
    What a scene builder made.

    Its plan, how many distractors walk or play in it and what each static body is.
    """

    plan: Plan
    distractors: int
    kinds: dict[int, str]


def build(name: str, client, rng: np.random.Generator, folder: Path) -> Scene:
    """Build scene ``name`` into ``client`` from ``rng``; ConfigError for an unknown name."""
    if name not in SCENES:
        raise ConfigError(f'unknown scene {name!r}; known: {", ".join(SCENES)}')
    b = Builder(client, rng, folder)
    plan, distractors = {'room': _room, 'urban': _urban, 'snow': _snow,
                         'parking': _parking}[name](b)
    return Scene(plan, distractors, b.kinds)


def _room(b: Builder) -> tuple[Plan, int]:
    plan = Plan((-6.0, -5.0, 6.0, 5.0))
    b.ground(8, 'floor')
    b.walls(plan.bounds, 3.0, 'wall')
    for _ in range(4):          # tables and cabinets along the walls
        x, y = b.rng.uniform(-5, 5), b.rng.choice([-4.3, 4.3])
        w, d, h = b.rng.uniform(0.4, 0.9), b.rng.uniform(0.3, 0.5), b.rng.uniform(0.7, 1.8)
        b.box((x, y, h / 2), (w, d, h), b.colour(), kind='furniture')
        plan.obstacles.append((x, y, max(w, d) + 0.1))
    return plan, 1


def _urban(b: Builder) -> tuple[Plan, int]:
    plan = Plan((-12.0, -4.0, 12.0, 4.0))
    b.ground(14, 'road')
    for side in (-1, 1):
        for k in range(6):     # facades, every other one with a glass front
            x = -12.5 + 4.5 * k
            glass = (k + (side > 0)) % 2
            b.box((x, side * 4.8, 4.0), (2.2, 0.6, 4.0), texture='glass' if glass else 'facade',
                  kind='glass' if glass else 'facade')
        for x in np.arange(-10, 11, 5.0):   # lamp posts along the pavement
            b.cylinder(x, side * 3.6, 0.08, 3.5, (0.2, 0.2, 0.25, 1), kind='post')
            plan.obstacles.append((x, side * 3.6, 0.25))
    return plan, 5


def _snow(b: Builder) -> tuple[Plan, int]:
    plan = Plan((-12.0, -12.0, 12.0, 12.0))
    b.ground(14, 'snow')
    for _ in range(14):        # trees: trunk and a dark crown
        x, y = b.rng.uniform(-11, 11, 2)
        if math.hypot(x, y) < 3:
            continue
        b.cylinder(x, y, 0.15, 1.2, (0.35, 0.25, 0.15, 1), kind='tree')
        b.sphere(x, y, 2.0, b.rng.uniform(0.7, 1.1), (0.1, 0.3, 0.15, 1), kind='tree')
        plan.obstacles.append((x, y, 0.5))
    for _ in range(3):         # huts
        x, y = b.rng.uniform(-9, 9, 2)
        if math.hypot(x, y) < 4:
            continue
        b.box((x, y, 1.2), (1.4, 1.2, 1.2), (0.45, 0.3, 0.2, 1), yaw=b.rng.uniform(0, 3),
              kind='hut')
        plan.obstacles.append((x, y, 2.0))
    return plan, 2


def _parking(b: Builder) -> tuple[Plan, int]:
    plan = Plan((-12.0, -10.0, 12.0, 10.0))
    b.ground(14, 'concrete')
    b.box((0, 0, 3.1), (12.5, 10.5, 0.1), (0.5, 0.5, 0.52, 1), kind='deck')   # above
    for x in np.arange(-9, 10, 6.0):   # pillars
        for y in np.arange(-7.5, 8, 5.0):
            b.box((x, y, 1.5), (0.3, 0.3, 1.5), texture='concrete', kind='pillar')
            plan.obstacles.append((x, y, 0.5))
    for y in (-9.0, 9.0):              # rows of parked cars along two sides
        for x in np.arange(-10, 11, 2.6):
            if b.rng.random() < 0.25:
                continue
            colour = b.colour(0.05, 0.95)
            b.box((x, y, 0.45), (1.0, 2.1, 0.45), colour, kind='car')
            b.box((x, y, 1.1), (0.8, 1.1, 0.25), (0.15, 0.18, 0.22, 1), kind='car')
            plan.obstacles.append((x, y, 2.2))
    return plan, 2
