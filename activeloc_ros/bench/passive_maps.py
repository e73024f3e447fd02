"""
The passive benchmark's reference maps on its 14 x 14 grid: chance, the centre prior and
frame differencing.
"""
import zlib

import cv2
import numpy as np

from activeloc_ros import metrics
from activeloc_ros.closed_loop import Pointing
from activeloc_ros.world import View

GRID = (14, 14)


class RandomMap:
    """Uniform noise, seeded per sequence: the chance level of the hit rate and the AUC."""

    name = 'random'

    def __init__(self, seed: int = 0) -> None:
        self.seed = seed
        self.rng = np.random.default_rng(seed)

    def reset(self, sequence: str) -> None:
        self.rng = np.random.default_rng([self.seed, zlib.crc32(sequence.encode())])

    def locate(self, view: View) -> Pointing:
        heat = self.rng.random(GRID)
        heat = heat / heat.sum()
        return Pointing(None, heat, float(heat.max()))


class CentreBias:
    """
    Always the image centre; its map, a centred Gaussian, is a prior to score (AUC), not
    a measurement, so it has no peak and its hits are scored at the centre itself.
    """

    name = 'centre'

    def __init__(self) -> None:
        self.heat = metrics.centre_gaussian(GRID)

    def reset(self, sequence: str) -> None:
        pass

    def locate(self, view: View) -> Pointing:
        h, w = view.rgb.shape[:2]
        return Pointing((w / 2.0, h / 2.0), self.heat)


class FrameDiff:
    """Per-cell mean |I_t - I_{t-1}| of blurred grey frames (a constant map on frame 0)."""

    name = 'framediff'

    def __init__(self) -> None:
        self.previous: np.ndarray | None = None

    def reset(self, sequence: str) -> None:
        self.previous = None

    def locate(self, view: View) -> Pointing:
        grey = cv2.cvtColor(view.rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
        grey = cv2.GaussianBlur(grey, (5, 5), 0)
        previous, self.previous = self.previous, grey
        if previous is None or previous.shape != grey.shape:
            heat = np.full(GRID, 1.0 / (GRID[0] * GRID[1]), np.float32)
        else:
            heat = cv2.resize(cv2.absdiff(grey, previous), (GRID[1], GRID[0]),
                              interpolation=cv2.INTER_AREA)
            total = float(heat.sum())
            heat = heat / total if total > 0 else np.full(GRID, 1.0 / heat.size, np.float32)
        return Pointing(None, heat, float(heat.max()))
