"""
Evaluation metrics (pure numpy): AUC-Judd, angular errors, the grid 'hit' rule.

Conventions: maps are 2-D arrays over a grid laid evenly over the image, cell (row, col)
covering x in [col * W / cols, (col + 1) * W / cols) and likewise for y; points are (x, y)
pixels with a top-left origin; boxes are (x, y, w, h) pixels (`data.Box` fits).
"""
from dataclasses import dataclass
import math
from typing import Iterable, Sequence

import cv2
import numpy as np

from activeloc_ros.errors import DataError

BoxLike = Sequence[float]  # (x, y, w, h)


def auc_judd(saliency: np.ndarray, fixations: np.ndarray, *, jitter: bool = False,
             rng: np.random.Generator | None = None) -> float:
    """
    AUC-Judd of the MIT saliency benchmark (`AUC_Judd.m`), on the map's own grid.

    The map is min-max normalised; the thresholds are its values at the fixated cells,
    sorted descending; for threshold i (1-based), TP rate = i / Nfix and FP rate =
    (#cells >= threshold - i) / (Ncells - Nfix); (0, 0) and (1, 1) are added and the
    curve is integrated with the trapezoid rule.

    Ties are counted pessimistically (every cell equal to a threshold is 'above' it), as
    the definition reads. Consequences: a constant map scores exactly
    (N - F^2) / (2 F (N - F)) for F fixated cells out of N (0.5 for one fixation); one
    fixation always scores 1 - FP/2 >= 0.5, so a random map averages 0.75 there (chance
    nears 0.5 only with many fixations). The MIT code's `jitter` option (default on
    there) adds uniform noise in [0, 1e-7) before normalising to break ties at random;
    it is off here unless asked for. A constant map is left as it is (the MIT code would
    divide 0 by 0 and return nan); normalising does not change the ranking anyway.

    :param saliency: the map, any real values.
    :param fixations: same shape; cells > 0 are fixated (several fixations in one cell
        count once, as in a binary fixation map).
    :returns: the area, or nan when there is no fixation.
    """
    sal = np.asarray(saliency, dtype=np.float64)
    fix = np.asarray(fixations)
    if sal.shape != fix.shape or sal.ndim != 2:
        raise DataError(f'auc_judd: saliency {sal.shape} and fixations {fix.shape} '
                        'must be 2-D of the same shape')
    if not np.all(np.isfinite(sal)):
        raise DataError('auc_judd: saliency map has non-finite values')
    if jitter:
        rng = rng if rng is not None else np.random.default_rng(0)
        sal = sal + rng.random(sal.shape) / 1e7
    span = sal.max() - sal.min()
    if span > 0:
        sal = (sal - sal.min()) / span
    values = sal.ravel()
    thresholds = np.sort(values[fix.ravel() > 0])[::-1]
    n_fix, n_cells = thresholds.size, values.size
    if n_fix == 0:
        return float('nan')
    if n_fix == n_cells:
        raise DataError('auc_judd: every cell is fixated; there are no negatives')
    ascending = np.sort(values)
    above = n_cells - np.searchsorted(ascending, thresholds, side='left')
    i = np.arange(1, n_fix + 1)
    tp = np.concatenate(([0.0], i / n_fix, [1.0]))
    fp = np.concatenate(([0.0], (above - i) / (n_cells - n_fix), [1.0]))
    return float(np.sum((fp[1:] - fp[:-1]) * (tp[1:] + tp[:-1]) / 2.0))


def cell_size(grid_shape: tuple[int, int], image_wh: tuple[float, float]
              ) -> tuple[float, float]:
    """(width, height) in pixels of one grid cell."""
    rows, cols = grid_shape
    return image_wh[0] / cols, image_wh[1] / rows


def cell_of(point_xy: tuple[float, float], grid_shape: tuple[int, int],
            image_wh: tuple[float, float]) -> tuple[int, int]:
    """(row, col) of the cell holding a pixel point; points outside go to the edge cell."""
    cw, ch = cell_size(grid_shape, image_wh)
    col = min(max(int(math.floor(point_xy[0] / cw)), 0), grid_shape[1] - 1)
    row = min(max(int(math.floor(point_xy[1] / ch)), 0), grid_shape[0] - 1)
    return row, col


def cell_centre(cell: tuple[int, int], grid_shape: tuple[int, int],
                image_wh: tuple[float, float]) -> tuple[float, float]:
    """(x, y) pixel centre of grid cell (row, col)."""
    cw, ch = cell_size(grid_shape, image_wh)
    return (cell[1] + 0.5) * cw, (cell[0] + 0.5) * ch


def peak_cell(heatmap: np.ndarray) -> tuple[int, int]:
    """(row, col) of the maximum; the first in row-major order on ties."""
    m = np.asarray(heatmap)
    if m.ndim != 2 or m.size == 0:
        raise DataError(f'peak_cell: expected a non-empty 2-D map, got shape {m.shape}')
    row, col = np.unravel_index(int(np.argmax(m)), m.shape)
    return int(row), int(col)


def peak_point(heatmap: np.ndarray, image_wh: tuple[float, float]) -> tuple[float, float]:
    """Pixel centre of the map's peak cell."""
    m = np.asarray(heatmap)
    return cell_centre(peak_cell(m), m.shape, image_wh)


def blob_box(heatmap: np.ndarray, image_wh: tuple[float, float], *,
             share: float = 0.15) -> tuple[float, float, float, float] | None:
    """
    The box (x, y, w, h; px) of the map's blob: the cells connected to its peak cell
    whose logarithm lies at least ``share`` of the way from the map's smallest positive
    value up to its peak. None for a map with no positive peak.

    A surprise map is a softmax of the prediction error, so the bar stands ``share`` of
    the way up the error's range over the cells: at 0.15 the blob spans the moving person,
    whose top (head, shoulders) is the most surprising. The earlier rule, cells above half
    the peak, held only that top; the base read its bottom as the person's feet and drove
    up to within 0.8-0.9 m of them (docs/tracking.md).

    Its corners are float32 numbers, the precision of the message that carries them
    (`action_region`, geometry_msgs/Point32), so a controller in the graph and one in the
    benchmark steer on the same numbers: a rounding step apart, a closed loop parts.
    """
    m = np.asarray(heatmap, np.float64)
    peak = float(m.max()) if m.size else 0.0
    if not (math.isfinite(peak) and peak > 0):
        return None
    floor = float(m[m > 0].min())
    with np.errstate(divide='ignore'):
        level = np.log(m / floor)                 # -inf where the map is 0: never kept
    keep = level >= share * math.log(peak / floor)
    _, labels = cv2.connectedComponents(keep.astype(np.uint8), connectivity=4)
    rows, cols = np.nonzero(labels == labels[peak_cell(m)])
    cw, ch = cell_size(m.shape, image_wh)
    x0, y0, x1, y1 = (float(np.float32(v)) for v in (
        cols.min() * cw, rows.min() * ch, (cols.max() + 1) * cw, (rows.max() + 1) * ch))
    return (x0, y0, x1 - x0, y1 - y0)


def fixation_map(points_xy: Iterable[tuple[float, float]], grid_shape: tuple[int, int],
                 image_wh: tuple[float, float]) -> np.ndarray:
    """Boolean grid with the cells holding the points set."""
    fix = np.zeros(grid_shape, dtype=bool)
    for p in points_xy:
        fix[cell_of(p, grid_shape, image_wh)] = True
    return fix


def is_hit(point_xy: tuple[float, float], boxes: Iterable[BoxLike], *,
           cell_wh: tuple[float, float]) -> bool:
    """The point lies inside any box grown by one cell on every side (borders count)."""
    x, y = point_xy
    cw, ch = cell_wh
    for bx, by, bw, bh in boxes:
        if bx - cw <= x <= bx + bw + cw and by - ch <= y <= by + bh + ch:
            return True
    return False


def map_hit(heatmap: np.ndarray, boxes: Iterable[BoxLike],
            image_wh: tuple[float, float]) -> bool:
    """The hit rule: the map's peak cell centre falls in an actor's box grown by one cell."""
    m = np.asarray(heatmap)
    return is_hit(peak_point(m, image_wh), boxes, cell_wh=cell_size(m.shape, image_wh))


def chance_hit_rate(boxes: Iterable[BoxLike], grid_shape: tuple[int, int],
                    image_wh: tuple[float, float]) -> float:
    """Hit probability of a peak drawn uniformly among the cells (a random map)."""
    boxes = list(boxes)
    cw, ch = cell_size(grid_shape, image_wh)
    hits = sum(is_hit(cell_centre((r, c), grid_shape, image_wh), boxes, cell_wh=(cw, ch))
               for r in range(grid_shape[0]) for c in range(grid_shape[1]))
    return hits / (grid_shape[0] * grid_shape[1])


def centre_gaussian(grid_shape: tuple[int, int], *, sigma: float = 0.25) -> np.ndarray:
    """
    Centre-bias map: isotropic Gaussian at the image centre, sums to 1.

    Evaluated at the cell centres in normalised coordinates (u, v in [0, 1] across the
    width and height), exp(-((u - .5)^2 + (v - .5)^2) / (2 sigma^2)).
    """
    rows, cols = grid_shape
    v = (np.arange(rows) + 0.5) / rows
    u = (np.arange(cols) + 0.5) / cols
    d2 = (v[:, None] - 0.5) ** 2 + (u[None, :] - 0.5) ** 2
    m = np.exp(-d2 / (2.0 * sigma ** 2))
    return (m / m.sum()).astype(np.float32)


def angle_between(u: Sequence[float], v: Sequence[float]) -> float:
    """Angle in degrees between two 3-D vectors (atan2 form, accurate near 0 and 180)."""
    a = np.asarray(u, dtype=np.float64)
    b = np.asarray(v, dtype=np.float64)
    if a.shape != (3,) or b.shape != (3,):
        raise DataError(f'angle_between: expected two 3-vectors, got {a.shape}, {b.shape}')
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if not (np.isfinite(na) and np.isfinite(nb)) or na == 0 or nb == 0:
        raise DataError('angle_between: vectors must be finite and non-zero')
    return math.degrees(math.atan2(np.linalg.norm(np.cross(a, b)), float(np.dot(a, b))))


def axis_error(ray: Sequence[float], axis: Sequence[float] = (0.0, 0.0, 1.0)) -> float:
    """Angle in degrees between the optical axis (camera +z by default) and a ray."""
    return angle_between(axis, ray)


def closest_angle(axis: Sequence[float], rays: Iterable[Sequence[float]]) -> float:
    """Angle to the closest of several target rays (the paper scores the closest action)."""
    angles = [angle_between(axis, r) for r in rays]
    if not angles:
        raise DataError('closest_angle: no target ray')
    return min(angles)


def pixel_ray(point_xy: tuple[float, float], *, fx: float, fy: float, cx: float,
              cy: float) -> np.ndarray:
    """Pinhole ray (camera frame: x right, y down, z forward) through a pixel."""
    return np.array([(point_xy[0] - cx) / fx, (point_xy[1] - cy) / fy, 1.0])


def focal_from_fov(size_px: float, fov_deg: float) -> float:
    """Focal length in pixels from an image size and its field of view along it."""
    if not 0.0 < fov_deg < 180.0:
        raise DataError(f'focal_from_fov: field of view {fov_deg} not in (0, 180)')
    return size_px / 2.0 / math.tan(math.radians(fov_deg) / 2.0)


def average_angular_error(errors_deg: Iterable[float]) -> float:
    """AAE: mean of per-frame angular errors in degrees (nan when empty)."""
    e = np.asarray(list(errors_deg), dtype=np.float64)
    return float(e.mean()) if e.size else float('nan')


@dataclass(frozen=True)
class Summary:
    """Mean of some per-frame (or per-sequence) values with its spread."""

    n: int
    mean: float
    std: float
    sem: float

    def as_dict(self) -> dict:
        return {'n': self.n, 'mean': self.mean, 'std': self.std, 'sem': self.sem}


def summarise(values: Iterable[float]) -> Summary:
    """n, mean, sample std and standard error of the finite values (nan ones dropped)."""
    v = np.asarray([float(x) for x in values], dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return Summary(0, float('nan'), float('nan'), float('nan'))
    std = float(v.std(ddof=1)) if v.size > 1 else 0.0
    return Summary(int(v.size), float(v.mean()), std, std / math.sqrt(v.size))
