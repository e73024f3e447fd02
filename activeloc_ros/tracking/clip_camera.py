"""The fixed pinhole camera of a synthetic clip (`clips`): where it looks and what it sees."""
from dataclasses import dataclass
import math

import numpy as np

from activeloc_ros import metrics

PERSON_TOP = 1.8               # m: the humanoid's head and raised hands at scale 1


@dataclass(frozen=True)
class Camera:
    """
    A fixed pinhole camera at (x, y, z) m looking along ``yaw`` (rad), ``tilt_deg`` above
    the horizon (< 0: down), ``hfov_deg`` across a ``width`` x ``height`` px picture.
    """

    x: float
    y: float
    z: float
    yaw: float
    tilt_deg: float
    hfov_deg: float
    width: int
    height: int

    @property
    def focal(self) -> float:
        return metrics.focal_from_fov(self.width, self.hfov_deg)

    def axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Forward, right and up unit vectors in the world."""
        t = math.radians(self.tilt_deg)
        forward = np.array([math.cos(t) * math.cos(self.yaw), math.cos(t) * math.sin(self.yaw),
                            math.sin(t)])
        right = np.array([math.sin(self.yaw), -math.cos(self.yaw), 0.0])
        return forward, right, np.cross(right, forward)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (N, 2) of world points (N, 3) and their depth along the optical axis (N,)."""
        forward, right, up = self.axes()
        d = np.asarray(points, float).reshape(-1, 3) - (self.x, self.y, self.z)
        depth = d @ forward
        with np.errstate(divide='ignore', invalid='ignore'):
            u = (self.width - 1) / 2 + self.focal * (d @ right) / depth
            v = (self.height - 1) / 2 - self.focal * (d @ up) / depth
        return np.stack([u, v], -1), depth

    def ground(self, ahead: float, right: float) -> tuple[float, float]:
        """The ground point ``ahead`` m in front (horizontally) and ``right`` m to the right."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return self.x + ahead * c + right * s, self.y + ahead * s - right * c

    def ahead(self, xy: np.ndarray) -> np.ndarray:
        """How far in front of the camera, horizontally, ground points (N, 2) lie, m."""
        xy = np.asarray(xy, float).reshape(-1, 2)
        return (xy[:, 0] - self.x) * math.cos(self.yaw) + (xy[:, 1] - self.y) * math.sin(self.yaw)

    def sees_person(self, xy: np.ndarray, scale: float = 1.0, margin: float = 2.0
                    ) -> np.ndarray:
        """
        Per ground point (N, 2): is a person standing there wholly in the picture (feet,
        head and shoulders ``margin`` px inside)?
        """
        xy = np.asarray(xy, float).reshape(-1, 2)
        side = 0.4 * scale * self.axes()[1][:2]
        ok = np.ones(len(xy), bool)
        for dx, dy, z in ((0, 0, 0.0), (0, 0, PERSON_TOP * scale),
                          (side[0], side[1], scale), (-side[0], -side[1], scale)):
            uv, depth = self.project(np.column_stack([xy[:, 0] + dx, xy[:, 1] + dy,
                                                      np.full(len(xy), z)]))
            ok &= ((depth > 0.5) & (uv[:, 0] >= margin) & (uv[:, 0] <= self.width - 1 - margin)
                   & (uv[:, 1] >= margin) & (uv[:, 1] <= self.height - 1 - margin))
        return ok

    def matrices(self, client) -> tuple[list, list]:
        """pybullet's view and projection matrices of this camera."""
        eye = np.array([self.x, self.y, self.z])
        view = client.computeViewMatrix(eye.tolist(), (eye + self.axes()[0]).tolist(), [0, 0, 1])
        vfov = 2 * math.degrees(math.atan(self.height / 2 / self.focal))
        return view, client.computeProjectionMatrixFOV(vfov, self.width / self.height, 0.1, 80.0)

    def describe(self) -> dict:
        return {'x': self.x, 'y': self.y, 'height_m': self.z, 'yaw_deg': math.degrees(self.yaw),
                'tilt_deg': self.tilt_deg, 'hfov_deg': self.hfov_deg}
