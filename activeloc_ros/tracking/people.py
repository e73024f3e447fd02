"""
People of the tracking world: pybullet's DeepMimic humanoid playing motion-capture clips,
the two target behaviours of gym-unrealcv's tracking worlds, and `follow`, a walk along
given waypoints (the synthetic clips' people).

The humanoid (``humanoid/humanoid.urdf``, scaled to 1.7 m) and its clips
(``data/motions/humanoid3d_*.txt``: 30 frames/s, root position, root and joint rotations,
Y up, in metres for the humanoid at that scale) ship in pybullet's wheel. A clip is played
kinematically: no physics, the joints are set to the clip's pose each step. The clip's own
forward travel is taken out; a behaviour moves the person over the ground and the clip's
phase advances with the distance walked, so the feet keep pace with the ground.
"""
import dataclasses
from dataclasses import dataclass
import json
import math
from pathlib import Path
from typing import Sequence

import numpy as np

from activeloc_ros.errors import ConfigError

HUMANOID_SCALE = 0.25            # the URDF's units to metres: a 1.7 m person
# the humanoid's joints in a clip frame's order (index, degrees of freedom: 4 = quaternion)
CLIP_JOINTS = ((1, 4), (2, 4), (3, 4), (4, 1), (5, 4), (6, 4), (7, 1),
               (9, 4), (10, 1), (11, 4), (12, 4), (13, 1))
TRAVEL_CLIPS = ('walk', 'run')   # clips that travel: their phase follows the distance walked
CLIPS = ('walk', 'run', 'dance_a', 'dance_b', 'punch', 'kick', 'spin', 'jump', 'spinkick')
TURN_RATE = math.radians(300)   # rad/s: how fast `follow` turns a walker onto its next leg


def _xyzw(wxyz) -> list[float]:
    return [float(wxyz[1]), float(wxyz[2]), float(wxyz[3]), float(wxyz[0])]


@dataclass
class Clip:
    """
    One motion-capture clip: per frame the root's height and sideways offset (m), its
    rotation (Y up, x,y,z,w) and the joints' values in `CLIP_JOINTS` order.
    """

    name: str
    frame_s: float
    height: np.ndarray            # (F,) m
    side: np.ndarray              # (F,) m
    root: np.ndarray              # (F, 4)
    joints: list[list[list[float]]]
    stride_m: float               # forward travel over one cycle (0: in place)

    @classmethod
    def load(cls, name: str, data_dir: str) -> 'Clip':
        if name not in CLIPS:
            raise ConfigError(f'unknown motion clip {name!r}; known: {", ".join(CLIPS)}')
        path = Path(data_dir) / 'data' / 'motions' / f'humanoid3d_{name}.txt'
        try:
            frames = np.asarray(json.loads(path.read_text())['Frames'], np.float64)
        except (OSError, ValueError, KeyError) as err:
            raise ConfigError(f'cannot read motion clip {path}: {err}') from err
        joints = []
        for frame in frames:
            values, at = [], 8
            for _, dof in CLIP_JOINTS:
                values.append(_xyzw(frame[at:at + 4]) if dof == 4 else [float(frame[at])])
                at += dof
            joints.append(values)
        travel = float(frames[-1, 1] - frames[0, 1]) if name in TRAVEL_CLIPS else 0.0
        return cls(name, float(frames[0, 0]), frames[:, 2].copy(), frames[:, 3].copy(),
                   np.array([_xyzw(f[4:8]) for f in frames]), joints, abs(travel))

    def in_place(self) -> 'Clip':
        """
        This clip with its root held over the spot it is played on: without the sideways
        drift (up to 1.5 m in punch) that a looping clip jumps back from at every loop.
        """
        return dataclasses.replace(self, side=np.zeros_like(self.side))

    def __len__(self) -> int:
        return len(self.height)

    def frame(self, phase: float) -> int:
        """The clip frame at ``phase`` (cycles; wraps)."""
        return int(phase % 1.0 * (len(self) - 1))


def clothes(rng: np.random.Generator) -> dict[str, tuple]:
    """Random RGBA colours for a person's body parts (`Person`'s ``colours``)."""
    skin = rng.uniform(0.45, 0.95) * np.array([1.0, 0.8, 0.65])
    return {'torso': (*rng.uniform(0.05, 0.95, 3), 1.0),
            'limbs': (*rng.uniform(0.05, 0.7, 3), 1.0), 'head': (*skin, 1.0)}


class Person:
    """
    A humanoid in a pybullet world that plays a clip where a behaviour puts it.

    :param client: a ``pybullet_utils.bullet_client.BulletClient``.
    :param colours: RGBA per body part (torso, limbs, head).
    :param scale: its size against the 1.7 m humanoid (0.9: 1.53 m tall).
    """

    def __init__(self, client, clip: Clip, *, data_dir: str, colours: dict[str, tuple],
                 scale: float = 1.0):
        self.client, self.clip, self.scale = client, clip, scale
        self.body = client.loadURDF(str(Path(data_dir) / 'humanoid' / 'humanoid.urdf'),
                                    [0, 0, 0], globalScaling=HUMANOID_SCALE * scale,
                                    useFixedBase=True, flags=client.URDF_MAINTAIN_LINK_ORDER)
        for link in range(-1, client.getNumJoints(self.body)):
            name = 'torso' if link in (-1, 1) else 'head' if link == 2 else 'limbs'
            client.changeVisualShape(self.body, link, rgbaColor=colours[name])
        self._y_up = client.getQuaternionFromEuler([math.pi / 2, 0, 0])
        self.phase = 0.0

    def place(self, x: float, y: float, heading: float, step_m: float, dt: float) -> None:
        """
        Pose the person at (x, y) facing ``heading`` (rad), having walked ``step_m`` m
        (travel clips) or played ``dt`` s (the others) since the last pose.
        """
        clip, c = self.clip, self.client
        if clip.stride_m > 0:
            self.phase += step_m / (clip.stride_m * self.scale)
        else:
            self.phase += dt / (clip.frame_s * (len(clip) - 1))
        i = clip.frame(self.phase)
        turn = c.getQuaternionFromEuler([0, 0, heading])
        _, orn = c.multiplyTransforms([0, 0, 0], turn, [0, 0, 0], self._y_up)
        _, orn = c.multiplyTransforms([0, 0, 0], orn, [0, 0, 0], clip.root[i].tolist())
        side = clip.side[i] * self.scale   # the clip is in metres for the 1.7 m humanoid
        pos = [x + side * math.sin(heading), y - side * math.cos(heading),
               clip.height[i] * self.scale]
        c.resetBasePositionAndOrientation(self.body, pos, orn)
        c.resetJointStatesMultiDof(self.body, [j for j, _ in CLIP_JOINTS], clip.joints[i])


def follow(waypoints: np.ndarray, speed: float, frames: int, fps: float, *,
           heading: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Positions (F, 2), headings (F,) and distance walked since the frame before (F,) of a
    person going along ``waypoints`` at ``speed`` from frame 0 (standing at the first one,
    facing ``heading``, when there is a single waypoint or no speed).
    """
    points = np.asarray(waypoints, float).reshape(-1, 2)
    if len(points) == 1 or speed <= 0:
        return (np.repeat(points[:1], frames, 0), np.full(frames, heading), np.zeros(frames))
    legs = np.diff(points, axis=0)
    ends = np.concatenate([[0.0], np.cumsum(np.hypot(legs[:, 0], legs[:, 1]))])
    s = np.minimum(speed * np.arange(frames) / fps, ends[-1])
    xy = np.column_stack([np.interp(s, ends, points[:, 0]), np.interp(s, ends, points[:, 1])])
    leg = np.clip(np.searchsorted(ends, s, side='right') - 1, 0, len(legs) - 1)
    want = np.arctan2(legs[leg, 1], legs[leg, 0])
    headings = np.empty(frames)
    headings[0] = want[0]
    for k in range(1, frames):     # turn onto a new leg at a person's pace, not at once
        turn = math.remainder(want[k] - headings[k - 1], math.tau)
        limit = TURN_RATE / fps
        headings[k] = headings[k - 1] + max(-limit, min(limit, turn))
    return xy, headings, np.diff(s, prepend=0.0)


@dataclass
class Walker:
    """Where a person is on the ground and how it moves: x, y (m), heading (rad), speed."""

    x: float
    y: float
    heading: float
    speed: float


class Behaviour:
    """
    A target behaviour of gym-unrealcv's tracking worlds, on a 2D ground plan.

    - ``ram``: random turns and speeds, a new pair every 1-3 s (*Ram*);
    - ``nav``: walks to random goals in free space, a new speed for each (*Nav*);
    - ``stay``: plays its clip where it stands (a distractor that dances, kicks...).

    Both walking behaviours turn away from obstacles and the scene's bounds.
    """

    KINDS = ('ram', 'nav', 'stay')

    def __init__(self, kind: str, plan, rng: np.random.Generator, *,
                 speed: tuple[float, float] = (0.5, 1.2), max_turn_deg_s: float = 120.0):
        if kind not in self.KINDS:
            raise ConfigError(f'unknown target behaviour {kind!r}; known: {self.KINDS}')
        self.kind, self.plan, self.rng = kind, plan, rng
        self.speed_range = speed
        self.max_turn = math.radians(max_turn_deg_s)
        self.until = 0.0
        self.goal: tuple[float, float] | None = None
        self.want: float | None = None

    def step(self, w: Walker, t: float, dt: float, *,
             movers: Sequence[tuple[float, float, float]] = ()) -> float:
        """
        Move ``w`` over ``dt`` s ending at ``t``, never into ``movers`` (x, y, r: the
        base); returns the distance walked.
        """
        if self.kind == 'stay':
            return 0.0
        rng = self.rng
        if self.kind == 'ram' and t >= self.until:
            self.until = t + rng.uniform(1.0, 3.0)
            self.want = w.heading + math.radians(rng.uniform(-60, 60))
            w.speed = rng.uniform(*self.speed_range)
        if self.kind == 'nav':
            if self.goal is None or math.hypot(self.goal[0] - w.x, self.goal[1] - w.y) < 0.5:
                self.goal = self.plan.free_point(rng, margin=1.0)
                w.speed = rng.uniform(*self.speed_range)
            self.want = math.atan2(self.goal[1] - w.y, self.goal[0] - w.x)
        want = self.plan.steer_clear(w.x, w.y, self.want, reach=1.2, movers=movers)
        if want != self.want and self.kind == 'ram':
            self.want = want
        turn = math.remainder(want - w.heading, math.tau)
        w.heading = math.remainder(
            w.heading + max(-self.max_turn * dt, min(self.max_turn * dt, turn)), math.tau)
        nx = w.x + w.speed * dt * math.cos(w.heading)
        ny = w.y + w.speed * dt * math.sin(w.heading)
        # a mover blocks only a step towards it, so a person it came too close to walks off
        ahead = [m for m in movers
                 if math.hypot(nx - m[0], ny - m[1]) < math.hypot(w.x - m[0], w.y - m[1])]
        if not self.plan.free(nx, ny, 0.3, movers=ahead):
            self.until = t          # blocked: a new choice next step (Ram), or wait (Nav)
            return 0.0
        w.x, w.y = nx, ny
        return w.speed * dt
