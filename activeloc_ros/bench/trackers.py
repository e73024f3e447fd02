"""
Tracker baselines of the active benchmark: Active TLD / MIL / MOSSE, plus KCF and CSRT.

Each tracker starts on the first camera frame of a sequence from the best EdgeBoxes region
proposal (paper: "We initialize all trackers with region proposals from an EdgeBox detector
to remove any actor-specific constraints") and is updated on every later frame; the centre
of its box is where the controller steers the camera. A tracker that loses its target is
never re-initialised: the paper's point is that these trackers do not recover.

Substitution: OpenCV's EdgeBoxes wants the structured-forest edge map (`model.yml.gz` of
opencv_extra), which is not available here. The edge map is instead the Sobel gradient
magnitude of the Gaussian-blurred image (sigma 1.5, strongest colour channel), divided by
its maximum and thinned by non-maximum suppression along the gradient direction; the
orientation map is computed from that edge map as the structured-edge code does
(triangle-smoothed E, second derivatives, O = mod(atan(Oyy * sign(-Oxy) / (Oxx + eps)), pi)).
Gradient edges keep texture that learned boundaries would suppress, so EdgeBoxes ignores
edges below 0.2 of the maximum (its default is 0.1). Proposals are computed on the frame
scaled to at most 320 px wide; by default, boxes under 1% or over 25% of the image are dropped.

A tracker that reports failure gives None for that frame (MOSSE does so whenever its peak
to sidelobe ratio is low, e.g. from the start when its box is mostly background).
"""
from typing import Callable

import cv2
import numpy as np

from activeloc_ros.errors import ConfigError, FrameError

TRACKERS: tuple[str, ...] = ('tld', 'mil', 'mosse', 'kcf', 'csrt')

Box = tuple[int, int, int, int]  # x, y, w, h in pixels

# TLD and MOSSE exist only in cv2.legacy (init returns a bool there).
_FACTORIES: dict[str, Callable[[], object]] = {
    'tld': cv2.legacy.TrackerTLD_create,
    'mil': cv2.TrackerMIL_create,
    'mosse': cv2.legacy.TrackerMOSSE_create,
    'kcf': cv2.TrackerKCF_create,
    'csrt': cv2.TrackerCSRT_create,
}
# Proposals are computed at most at this width; boxes are scaled back to the frame.
_PROPOSAL_WIDTH = 320


def _check_rgb(rgb: np.ndarray) -> None:
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise FrameError(f'expected an HxWx3 uint8 RGB frame, got {rgb.shape} {rgb.dtype}')


def _triangle_blur(image: np.ndarray, radius: int) -> np.ndarray:
    """The structured-edge code's `convTri`: a separable triangle filter of that radius."""
    kernel = np.concatenate([np.arange(1, radius + 2), np.arange(radius, 0, -1)])
    kernel = (kernel / kernel.sum()).astype(np.float32)
    return cv2.sepFilter2D(image, -1, kernel, kernel, borderType=cv2.BORDER_REFLECT)


def _gradient(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Central differences (one-sided at the borders), x then y, like MATLAB's gradient."""
    gy, gx = np.gradient(image)
    return gx.astype(np.float32), gy.astype(np.float32)


def edge_maps(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A thinned gradient edge map in [0, 1] and its orientation map in [0, pi), float32."""
    # sigma 1.5 at the proposal width: weaker texture edges, fewer and cleaner proposals
    blurred = cv2.GaussianBlur(rgb, (0, 0), 1.5).astype(np.float32)
    gx = cv2.Sobel(blurred, cv2.CV_32F, 1, 0, ksize=3)  # (H, W, 3)
    gy = cv2.Sobel(blurred, cv2.CV_32F, 0, 1, ksize=3)
    magnitude = np.sqrt(gx * gx + gy * gy)
    channel = magnitude.argmax(axis=2)[..., None]  # the strongest channel per pixel
    magnitude = np.take_along_axis(magnitude, channel, axis=2)[..., 0]
    gx = np.take_along_axis(gx, channel, axis=2)[..., 0]
    gy = np.take_along_axis(gy, channel, axis=2)[..., 0]
    # By the max, not a percentile: in a frame with a few strong contours on a textured
    # background a percentile scales the texture up to 1 (and EdgeBoxes gets slow).
    scale = float(magnitude.max())
    edges = magnitude / scale if scale > 0 else np.zeros_like(magnitude)

    # Non-maximum suppression: keep a pixel only if it is no weaker than both neighbours
    # along its gradient direction (quantised to 0, 45, 90, 135 degrees).
    angle = np.mod(np.degrees(np.arctan2(gy, gx)), 180.0)
    sector = (np.round(angle / 45.0).astype(np.int32)) % 4
    padded = np.pad(edges, 1)
    h, w = edges.shape
    keep = np.zeros_like(edges, dtype=bool)
    for index, (dy, dx) in enumerate(((0, 1), (1, 1), (1, 0), (1, -1))):
        ahead = padded[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
        behind = padded[1 - dy:1 - dy + h, 1 - dx:1 - dx + w]
        keep |= (sector == index) & (edges >= ahead) & (edges >= behind)
    edges = np.where(keep, edges, 0.0).astype(np.float32)

    # Orientation from the edge map itself, as edgesDetect.m / computeOrientation do.
    ox, oy = _gradient(_triangle_blur(edges, 4))
    oxx, _ = _gradient(ox)
    oxy, oyy = _gradient(oy)
    orientation = np.mod(np.arctan(oyy * np.sign(-oxy) / (oxx + 1e-5)), np.pi)
    return edges, orientation.astype(np.float32)


def propose_boxes(rgb: np.ndarray, *, max_boxes: int = 50, min_area: float = 0.01,
                  max_area: float = 0.25) -> list[tuple[Box, float]]:
    """
    EdgeBoxes proposals (x, y, w, h) with their scores, best first.

    :param max_boxes: at most this many proposals are returned.
    :param min_area: drop boxes smaller than this fraction of the image area.
    :param max_area: drop boxes larger than this fraction of the image area.
    """
    _check_rgb(rgb)
    if not 0.0 <= min_area <= max_area <= 1.0 or max_boxes < 1:
        raise ConfigError(f'need 0 <= min_area <= max_area <= 1 and max_boxes >= 1, got '
                          f'min_area={min_area}, max_area={max_area}, max_boxes={max_boxes}')
    h, w = rgb.shape[:2]
    scale = min(1.0, _PROPOSAL_WIDTH / w)
    small = cv2.resize(rgb, (round(w * scale), round(h * scale)),
                       interpolation=cv2.INTER_AREA) if scale < 1.0 else rgb
    edges, orientation = edge_maps(small)
    small_area = small.shape[0] * small.shape[1]
    detector = cv2.ximgproc.createEdgeBoxes()
    # Ask for more than needed: the area filter below removes some of them.
    detector.setMaxBoxes(max(200, 4 * max_boxes))
    detector.setMinBoxArea(max(1.0, min_area * small_area))
    # Gradient edges keep texture at ~0.1-0.2 of the max (learned edges would not): ignoring
    # it keeps the object contours' boxes on top and makes EdgeBoxes several times faster.
    detector.setEdgeMinMag(0.2)
    boxes, scores = detector.getBoundingBoxes(edges, orientation)
    if len(boxes) == 0:
        return []
    proposals = []
    for box, score in zip(np.asarray(boxes), np.asarray(scores).ravel()):
        bx, by, bw, bh = (int(round(v / scale)) for v in box)
        bw, bh = min(bw, w - bx), min(bh, h - by)  # rounding may step over the edge
        fraction = bw * bh / (w * h)
        if min_area <= fraction <= max_area:
            proposals.append(((bx, by, bw, bh), float(score)))
    proposals.sort(key=lambda item: -item[1])
    return proposals[:max_boxes]


def create_tracker(kind: str):
    """A fresh OpenCV tracker of that kind; ConfigError for an unknown kind."""
    if kind not in _FACTORIES:
        raise ConfigError(f'unknown tracker {kind!r}; choose from {", ".join(TRACKERS)}')
    return _FACTORIES[kind]()


class TrackerPointer:
    """One tracker baseline for the closed loop: where in this frame is the target?"""

    def __init__(self, kind: str) -> None:
        create_tracker(kind)  # fail at once on an unknown kind
        self.name = kind
        self.tracker = None
        self.init_box: Box | None = None

    def reset(self) -> None:
        """A new sequence: forget the tracker and its initial box."""
        self.tracker = None
        self.init_box = None
        self.box: Box | None = None      # the newest box, None after a failure

    def locate(self, rgb: np.ndarray, *, start: Box | None = None
               ) -> tuple[float, float] | None:
        """
        (u, v) pixel of the tracked box centre in this camera frame (RGB uint8, HxWx3),
        or None when the tracker reports failure (or nothing could initialise it). The first
        frame starts the tracker on ``start`` if given (the target's true box), else on the
        best EdgeBoxes proposal.
        """
        _check_rgb(rgb)
        bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
        self.box = None
        if self.tracker is None:
            if start is None:
                proposals = propose_boxes(rgb, max_boxes=1)
                start = proposals[0][0] if proposals else None
            return None if start is None else self._initialise(bgr, start)
        try:
            ok, box = self.tracker.update(bgr)
        except cv2.error:
            return None
        if not ok:
            return None
        self.box = tuple(int(round(v)) for v in box)
        x, y, w, h = box
        return x + w / 2.0, y + h / 2.0

    def _initialise(self, bgr: np.ndarray, box: Box) -> tuple[float, float] | None:
        tracker = create_tracker(self.name)
        try:
            # Legacy trackers return False on failure; the others return None or raise.
            if tracker.init(bgr, tuple(int(v) for v in box)) is False:
                return None
        except cv2.error:
            return None
        self.tracker, self.init_box, self.box = tracker, box, box
        x, y, w, h = box
        return x + w / 2.0, y + h / 2.0
