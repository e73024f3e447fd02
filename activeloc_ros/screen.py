"""
The virtual projection screen of the paper's real-world experiment (Sec. 4.2), ROS-free.

A scene (video frames) is stretched over a flat screen ``screen_width_m`` x
``screen_height_m``; a pinhole camera sits on the screen's normal through its centre,
``distance_m`` in front of it, and rotates about its optical centre by the arm's pan and
tilt (``ArmMapping.pan_tilt``; the arm's link offsets are neglected: the camera only
rotates). At the home pose it looks at the screen centre and sees ``view_fraction`` of the
screen's area. What it sees is a perspective warp of the current scene frame.

Frames: the world frame is the home camera's optical frame (x right, y down, z towards the
screen); scene pixels have a top-left origin with integer pixel centres, as everywhere in
the package. Pan > 0 turns the camera left, tilt > 0 raises it (``control.geometry``).
"""
from dataclasses import dataclass, fields
import math
from typing import Iterable, Sequence

import cv2
import numpy as np

from activeloc_ros import metrics
from activeloc_ros.checks import (
    above, check_field_types, field_of_view, in_range, non_negative)
from activeloc_ros.control.braccio import ArmMapping
from activeloc_ros.control.geometry import Intrinsics
from activeloc_ros.errors import ConfigError


# How far a virtual camera may turn: 'arm' = only the Braccio's joints limit it, as the
# paper's rig, whose camera could look past the screen's edge at the wall round it;
# 'screen' = never so far that any of its view leaves the screen (it caps even the oracle).
AIM_LIMITS = ('arm', 'screen')


@dataclass(frozen=True)
class ScreenConfig:
    """
    The screen, where the camera stands, and the camera itself.

    :param screen_width_m: screen width (paper: 221.4 cm).
    :param screen_height_m: screen height (paper: 124.5 cm).
    :param view_fraction: share of the screen's area the camera sees at the home pose
        (paper: 30%); it sets the distance unless ``distance_m`` is given.
    :param distance_m: camera-to-screen distance; 0 places the camera so that its view
        covers ``view_fraction`` of the screen.
    :param width: camera image width, pixels.
    :param height: camera image height, pixels.
    :param hfov_deg: horizontal field of view (Intel RealSense D435 colour: 69.4 degrees).
    :param wall_grey: grey level (0-255) of the plain wall around the screen and of rays
        that miss the screen plane: a dim, textureless surface, as the wall round the
        paper's projection screen; 0 renders it black.
    """

    screen_width_m: float = 2.214
    screen_height_m: float = 1.245
    view_fraction: float = 0.30
    distance_m: float = 0.0
    width: int = 640
    height: int = 480
    hfov_deg: float = 69.4
    wall_grey: int = 40

    def __post_init__(self):
        check_field_types(self, 'screen ')
        checks = {
            'screen_width_m': above(0.0), 'screen_height_m': above(0.0),
            'view_fraction': in_range(0.01, 1.0), 'distance_m': non_negative,
            'width': in_range(16, 8192), 'height': in_range(16, 8192),
            'hfov_deg': field_of_view, 'wall_grey': in_range(0, 255),
        }
        for name, check in checks.items():
            problem = check(getattr(self, name))
            if problem:
                raise ConfigError(f'screen {name}: {problem}')

    @classmethod
    def from_dict(cls, values: dict) -> 'ScreenConfig':
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ConfigError(f'unknown screen settings {unknown}; known: {sorted(known)}')
        return cls(**values)


class VirtualScreen:
    """Geometry and rendering of the camera looking at the screen."""

    def __init__(self, config: ScreenConfig = ScreenConfig(), *,
                 mapping: ArmMapping | None = None):
        self.config = config
        self.mapping = mapping if mapping is not None else ArmMapping()
        c = config
        self.size = (c.width, c.height)
        fx = metrics.focal_from_fov(c.width, c.hfov_deg)
        self.K = np.array([[fx, 0.0, (c.width - 1) / 2.0],
                           [0.0, fx, (c.height - 1) / 2.0], [0.0, 0.0, 1.0]])
        self.K_inv = np.linalg.inv(self.K)
        # the view's footprint on the screen at the home pose, per metre of distance
        foot = (c.width / fx) * (c.height / fx)
        if c.distance_m > 0:
            self.distance = c.distance_m
        else:
            self.distance = math.sqrt(
                c.view_fraction * c.screen_width_m * c.screen_height_m / foot)
        self.home_fraction = foot * self.distance ** 2 / (c.screen_width_m * c.screen_height_m)

    @property
    def intrinsics(self) -> Intrinsics:
        k = self.K
        return Intrinsics(k[0, 0], k[1, 1], k[0, 2], k[1, 2], *self.size)

    def describe(self) -> str:
        c = self.config
        vfov = 2 * math.degrees(math.atan(c.height / 2.0 / self.K[0, 0]))
        return (f'screen {c.screen_width_m * 100:.1f} x {c.screen_height_m * 100:.1f} cm, '
                f'camera {c.width}x{c.height} ({c.hfov_deg:g} x {vfov:.1f} deg) at '
                f'{self.distance * 100:.1f} cm, seeing {self.home_fraction:.0%} of the '
                'screen at home')

    def aim_limits_deg(self) -> tuple[float, float]:
        """
        The largest pan and tilt (degrees, either way) such that at every aim within both
        the camera's whole view lies on the screen.

        Each axis alone allows the half-angle the screen spans from the camera less half
        the field of view along it; panning and tilting at once turns the view's corners
        further out, so both limits are scaled down by one factor until the four combined
        extremes keep the view on the screen too.
        """
        c = self.config
        fx = self.K[0, 0]
        half = ((c.screen_width_m, c.width), (c.screen_height_m, c.height))
        alone = [max(0.0, math.atan(size_m / 2.0 / self.distance)
                     - math.atan(pixels / 2.0 / fx)) for size_m, pixels in half]
        low, high = 0.0, 1.0
        if self._on_screen(*alone):
            low = 1.0
        for _ in range(30 if low < 1.0 else 0):                  # bisection on the factor
            mid = (low + high) / 2.0
            low, high = (mid, high) if self._on_screen(mid * alone[0], mid * alone[1]) else (
                low, mid)
        return tuple(math.degrees(low * a) for a in alone)

    def _on_screen(self, pan: float, tilt: float) -> bool:
        """Does the whole view lie on the screen at each of the aims (+-pan, +-tilt)?"""
        w, h = self.size
        corners = [(-0.5, -0.5), (w - 0.5, -0.5), (-0.5, h - 0.5), (w - 0.5, h - 0.5)]
        extent = (1000, 1000)                                    # scene pixels over the screen
        for sp in (-1, 1):
            for st in (-1, 1):
                hit = self.to_scene(corners, sp * pan, st * tilt, extent)
                if not (np.all(np.isfinite(hit)) and np.all(hit >= -0.5 - 1e-9)
                        and np.all(hit <= extent[0] - 0.5 + 1e-9)):
                    return False
        return True

    # -- poses ------------------------------------------------------------------------------

    def pan_tilt(self, joints_deg: Sequence[float]) -> tuple[float, float]:
        """Camera (pan, tilt), radians, of an arm pose."""
        return self.mapping.pan_tilt(joints_deg)

    @staticmethod
    def rotation(pan: float, tilt: float) -> np.ndarray:
        """World-from-camera rotation: its columns are the camera's x, y, z axes."""
        cp, sp, ct, st = math.cos(pan), math.sin(pan), math.cos(tilt), math.sin(tilt)
        return np.array([[cp, -st * sp, -sp * ct],
                         [0.0, ct, -st],
                         [sp, st * cp, cp * ct]])

    def scene_to_world(self, scene_wh: tuple[int, int]) -> np.ndarray:
        """3x3 map from homogeneous scene pixels to points on the screen (metres)."""
        w, h = scene_wh
        sw, sh = self.config.screen_width_m, self.config.screen_height_m
        return np.array([[sw / w, 0.0, sw * (0.5 / w - 0.5)],
                         [0.0, sh / h, sh * (0.5 / h - 0.5)],
                         [0.0, 0.0, self.distance]])

    def homography(self, pan: float, tilt: float, scene_wh: tuple[int, int]) -> np.ndarray:
        """Camera pixels from scene pixels (valid for screen points in front of the camera)."""
        return self.K @ self.rotation(pan, tilt).T @ self.scene_to_world(scene_wh)

    # -- what the camera sees ---------------------------------------------------------------

    def render(self, scene: np.ndarray, pan: float, tilt: float) -> np.ndarray:
        """
        The camera image (H, W, 3) of the scene on the screen; off the screen it sees the
        plain wall (``wall_grey``). The wall is uniform so it holds nothing to track or to
        be surprised by: every method sees the same screen edge and nothing else there.
        """
        h, w = scene.shape[:2]
        H = self.homography(pan, tilt, (w, h))
        wall = self.config.wall_grey
        image = cv2.warpPerspective(scene, H, self.size, flags=cv2.INTER_LINEAR,
                                    borderMode=cv2.BORDER_CONSTANT, borderValue=(wall,) * 3)
        behind = self._behind_mask(pan, tilt)
        if behind is not None:
            image[behind] = wall
        return image

    def _behind_mask(self, pan: float, tilt: float) -> np.ndarray | None:
        """Camera pixels whose ray points away from the screen plane (None: there are none)."""
        R = self.rotation(pan, tilt)
        w, h = self.size
        corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1.0]]).T
        z_row = (R @ self.K_inv)[2]              # world z of a pixel's ray, linear in (u, v)
        if np.all(z_row @ corners > 1e-6):
            return None
        u, v = np.meshgrid(np.arange(w), np.arange(h))
        return z_row[0] * u + z_row[1] * v + z_row[2] <= 1e-6

    def project(self, points_xy: Iterable[Sequence[float]], pan: float, tilt: float,
                scene_wh: tuple[int, int]) -> np.ndarray:
        """Camera pixels (N, 2) of scene points; NaN for points behind the camera."""
        pts = np.asarray(list(points_xy), dtype=np.float64).reshape(-1, 2)
        homog = np.hstack([pts, np.ones((len(pts), 1))]).T
        cam = self.rotation(pan, tilt).T @ self.scene_to_world(scene_wh) @ homog  # (3, N)
        out = np.full((len(pts), 2), np.nan)
        front = cam[2] > 1e-9
        pix = self.K @ cam[:, front]
        out[front] = (pix[:2] / pix[2]).T
        return out

    def in_view(self, points_xy: Iterable[Sequence[float]], pan: float, tilt: float,
                scene_wh: tuple[int, int]) -> np.ndarray:
        """True for scene points inside the camera image."""
        pix = self.project(points_xy, pan, tilt, scene_wh)
        w, h = self.size
        with np.errstate(invalid='ignore'):
            return ((pix[:, 0] >= -0.5) & (pix[:, 0] <= w - 0.5)
                    & (pix[:, 1] >= -0.5) & (pix[:, 1] <= h - 0.5))

    def to_scene(self, pixels_uv: Iterable[Sequence[float]], pan: float, tilt: float,
                 scene_wh: tuple[int, int]) -> np.ndarray:
        """Scene pixels (N, 2) where camera pixels' rays meet the screen; NaN if they miss."""
        uv = np.asarray(list(pixels_uv), dtype=np.float64).reshape(-1, 2)
        rays = self.rotation(pan, tilt) @ self.K_inv @ np.hstack([uv, np.ones((len(uv), 1))]).T
        out = np.full((len(uv), 2), np.nan)
        hit = rays[2] > 1e-9
        world = rays[:, hit] * (self.distance / rays[2, hit])
        scene = np.linalg.solve(self.scene_to_world(scene_wh), world)
        out[hit] = (scene[:2] / scene[2]).T
        return out

    def angles_deg(self, points_xy: Iterable[Sequence[float]], pan: float, tilt: float,
                   scene_wh: tuple[int, int]) -> np.ndarray:
        """Angle (degrees) between the optical axis and the ray to each scene point."""
        pts = np.asarray(list(points_xy), dtype=np.float64).reshape(-1, 2)
        world = self.scene_to_world(scene_wh) @ np.hstack([pts, np.ones((len(pts), 1))]).T
        axis = self.rotation(pan, tilt)[:, 2]
        return np.array([metrics.angle_between(axis, ray) for ray in world.T])

    def view_outline(self, pan: float, tilt: float, scene_wh: tuple[int, int],
                     *, samples: int = 8) -> np.ndarray:
        """The border of the camera's view in scene pixels (M, 2), rays that miss dropped."""
        w, h = self.size
        t = np.linspace(0.0, 1.0, samples, endpoint=False)
        u0, u1, v0, v1 = -0.5, w - 0.5, -0.5, h - 0.5
        border = np.concatenate([
            np.stack([u0 + t * (u1 - u0), np.full_like(t, v0)], 1),
            np.stack([np.full_like(t, u1), v0 + t * (v1 - v0)], 1),
            np.stack([u1 - t * (u1 - u0), np.full_like(t, v1)], 1),
            np.stack([np.full_like(t, u0), v1 - t * (v1 - v0)], 1)])
        scene = self.to_scene(border, pan, tilt, scene_wh)
        return scene[np.all(np.isfinite(scene), axis=1)]

    def place_map(self, heat: np.ndarray, pan: float, tilt: float,
                  canvas_wh: tuple[int, int]) -> np.ndarray:
        """
        A camera-frame map laid on a screen-sized canvas where the camera looked.

        Each canvas cell takes the (bilinear) map value under it; cells outside the view
        take -1, below any map value (maps are min-max normalised to [0, 1] first).
        """
        heat = np.asarray(heat, dtype=np.float32)
        span = float(heat.max() - heat.min())
        heat = (heat - heat.min()) / span if span > 0 else np.zeros_like(heat)
        rows, cols = heat.shape
        w, h = self.size
        cam_from_map = np.array([[w / cols, 0.0, w / cols / 2 - 0.5],
                                 [0.0, h / rows, h / rows / 2 - 0.5], [0.0, 0.0, 1.0]])
        cam_from_canvas = self.homography(pan, tilt, canvas_wh)
        map_from_canvas = np.linalg.inv(cam_from_map) @ cam_from_canvas
        cw, ch = canvas_wh
        # cv2 wants dst -> src when WARP_INVERSE_MAP is set: canvas -> map is exactly that
        placed = cv2.warpPerspective(heat, map_from_canvas, (cw, ch),
                                     flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                     borderMode=cv2.BORDER_REPLICATE)
        u, v = np.meshgrid(np.arange(cw, dtype=np.float64), np.arange(ch, dtype=np.float64))
        canvas_pts = np.stack([u.ravel(), v.ravel()], 1)
        inside = self.in_view(canvas_pts, pan, tilt, canvas_wh).reshape(ch, cw)
        placed[~inside] = -1.0
        return placed
