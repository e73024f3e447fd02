"""
From a pixel and the camera intrinsics to the pan/tilt angles that centre it.

Pixels follow the ROS/OpenCV convention (u right, v down, integer pixel centres); the
intrinsics are a CameraInfo's ``K`` (full-resolution, before binning and ROI, REP 104).
"""
from dataclasses import dataclass
import math
from typing import Sequence

import numpy as np

from activeloc_ros.errors import ConfigError

_RADIAL_MODELS = ('plumb_bob', 'rational_polynomial')


@dataclass(frozen=True)
class Intrinsics:
    """
    Pinhole intrinsics plus what is needed to use them on a published (binned/ROI) image.

    :param width: width of the calibrated (full-resolution) image, pixels.
    :param dist: distortion coefficients for ``plumb_bob`` / ``rational_polynomial``
        (k1, k2, p1, p2, k3[, k4, k5, k6]); other models are used as undistorted.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    dist: tuple[float, ...] = ()
    binning_x: int = 1
    binning_y: int = 1
    roi_x: int = 0
    roi_y: int = 0
    roi_width: int = 0
    roi_height: int = 0

    def __post_init__(self):
        values = (self.fx, self.fy, self.cx, self.cy, *self.dist)
        if not all(math.isfinite(v) for v in values) or self.fx <= 0 or self.fy <= 0:
            raise ConfigError(f'camera intrinsics need finite fx, fy > 0, got {self}')
        if self.width <= 0 or self.height <= 0:
            raise ConfigError(
                f'camera image size must be positive, got {self.width}x{self.height}')
        object.__setattr__(self, 'binning_x', max(1, int(self.binning_x)))
        object.__setattr__(self, 'binning_y', max(1, int(self.binning_y)))

    @classmethod
    def from_camera_info(cls, k: Sequence[float], width: int, height: int, *,
                         d: Sequence[float] = (), distortion_model: str = '',
                         binning_x: int = 0, binning_y: int = 0,
                         roi: tuple[int, int, int, int] = (0, 0, 0, 0)) -> 'Intrinsics':
        """Build from CameraInfo fields (``k`` row-major 3x3, ``roi`` = x, y, width, height)."""
        if len(k) != 9:
            raise ConfigError(f'K must have 9 entries, got {len(k)}')
        dist = tuple(float(c) for c in d) if distortion_model in _RADIAL_MODELS else ()
        return cls(float(k[0]), float(k[4]), float(k[2]), float(k[5]), int(width), int(height),
                   dist, binning_x or 1, binning_y or 1, *(int(r) for r in roi))

    @property
    def matrix(self) -> np.ndarray:
        """The 3x3 camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def image_size(self) -> tuple[float, float]:
        """Size of the published image (after ROI and binning) in which pixels are given."""
        w = self.roi_width or self.width
        h = self.roi_height or self.height
        return w / self.binning_x, h / self.binning_y

    def contains(self, u: float, v: float) -> bool:
        """True when (u, v) is a finite point of the published image (half a pixel of slack)."""
        w, h = self.image_size
        return (math.isfinite(u) and math.isfinite(v)
                and -0.5 <= u <= w - 0.5 and -0.5 <= v <= h - 0.5)

    def normalized(self, u: float, v: float) -> tuple[float, float]:
        """Undistorted normalised image coordinates (x right, y down) of a published pixel."""
        uf = u * self.binning_x + self.roi_x
        vf = v * self.binning_y + self.roi_y
        x = (uf - self.cx) / self.fx
        y = (vf - self.cy) / self.fy
        if any(self.dist):
            x, y = _undistort(x, y, self.dist)
        return x, y


UNDISTORT_TOLERANCE = 1e-4   # normalised units (0.05 px at fx 500): a converged inverse


def _distort(x: float, y: float, k: Sequence[float]) -> tuple[float, float, float]:
    """The Brown-Conrady model at an undistorted point: (radial factor, dx, dy)."""
    k1, k2, p1, p2, k3, k4, k5, k6 = k
    r2 = x * x + y * y
    radial = (1 + ((k3 * r2 + k2) * r2 + k1) * r2) / (1 + ((k6 * r2 + k5) * r2 + k4) * r2)
    return (radial, 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
            p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)


def _undistort(xd: float, yd: float, dist: Sequence[float]) -> tuple[float, float]:
    """
    Invert the Brown-Conrady model by fixed-point iteration (as OpenCV does). Where it
    does not converge (far outside the calibrated region, where strong distortion folds
    the image) the point is left as measured: the iteration's last step there can lie
    anywhere, even at infinity.
    """
    k = (list(dist) + [0.0] * 8)[:8]
    x, y = xd, yd
    for _ in range(20):
        radial, dx, dy = _distort(x, y, k)
        if not math.isfinite(radial) or radial <= 0.0:
            return xd, yd
        x, y = (xd - dx) / radial, (yd - dy) / radial
    radial, dx, dy = _distort(x, y, k)
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(radial)
            and math.hypot(x * radial + dx - xd, y * radial + dy - yd) <= UNDISTORT_TOLERANCE):
        return xd, yd
    return x, y


def angular_error(u: float, v: float, intrinsics: Intrinsics, *,
                  camera_tilt: float = 0.0) -> tuple[float, float]:
    """
    Pan and tilt changes (radians) that put pixel (u, v) on the optical axis.

    The camera sits on a pan (vertical axis) then tilt head, currently raised by
    ``camera_tilt`` above the horizon. Pan > 0 = turn left, tilt > 0 = raise. With the
    camera level this is ``(atan(-x), atan2(-y, hypot(1, x)))`` of the normalised ray.
    """
    x, y = intrinsics.normalized(u, v)
    # The ray in the camera body frame: forward, left, up.
    fwd, left, up = 1.0, -x, -y
    c, s = math.cos(camera_tilt), math.sin(camera_tilt)
    fwd, up = fwd * c - up * s, fwd * s + up * c  # into the (level) pan frame
    d_pan = math.atan2(left, fwd)
    elevation = math.atan2(up, math.hypot(fwd, left))
    return d_pan, elevation - camera_tilt
