"""
Where the picture changed between two frames once the camera's own motion is taken out.

Pixel-level and ROS-free. The previous grey image is warped into the new view with the
camera's estimated motion (`egomotion`), and a pixel counts as changed by as much as it
differs from every previous pixel within `tolerance_px` of it, so a warp that is off by a
pixel does not light up sharp static edges. Pixels the previous view did not see have not
changed. Used by the model's motion weighting (`motion_source: image`) and by the
frame-differencing baseline, so both see the same compensation.
"""
import cv2
import numpy as np

from activeloc_ros.perception import egomotion

BLUR = (5, 5)


def grey(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) RGB -> (H, W) float32 grey, blurred against sensor noise."""
    g = cv2.cvtColor(np.asarray(image, dtype=np.uint8), cv2.COLOR_RGB2GRAY)
    return cv2.GaussianBlur(g.astype(np.float32), BLUR, 0)


def into_view(previous: np.ndarray, warp: np.ndarray | None
              ) -> tuple[np.ndarray, np.ndarray | None]:
    """
    (`previous` moved by `warp` into the new view, the mask (uint8, 1) of the pixels the
    previous view saw); the image as it is and no mask when the camera did not move.
    """
    if warp is None:
        return previous, None
    h, w = previous.shape[:2]
    moved = cv2.warpPerspective(previous, warp, (w, h), flags=cv2.INTER_LINEAR,
                                borderMode=cv2.BORDER_REPLICATE)
    seen = cv2.warpPerspective(np.ones((h, w), np.uint8), warp, (w, h),
                               flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                               borderValue=0)
    return moved, seen


def residual(previous: np.ndarray, current: np.ndarray, warp: np.ndarray | None, *,
             tolerance_px: int = 1) -> np.ndarray:
    """
    (H, W) change of `current` against `previous` (grey, float32) moved by `warp` (3x3,
    previous -> current pixels; None: the camera did not move). 0 where the previous view
    saw nothing.
    """
    previous, seen = into_view(previous, warp)
    if tolerance_px > 0:
        kernel = np.ones((2 * tolerance_px + 1,) * 2, np.uint8)
        high, low = cv2.dilate(previous, kernel), cv2.erode(previous, kernel)
        change = np.maximum(np.maximum(current - high, low - current), 0.0)
    else:
        change = np.abs(current - previous)
    if seen is not None:
        if tolerance_px > 0:             # the border's own interpolation is no change either
            seen = cv2.erode(seen, np.ones((2 * tolerance_px + 1,) * 2, np.uint8))
        change[seen == 0] = 0.0
    return change


def cell_means(change: np.ndarray, grid: tuple[int, int]) -> np.ndarray:
    """(rows, cols) mean of a per-pixel map over each grid cell."""
    rows, cols = grid
    return cv2.resize(change, (cols, rows), interpolation=cv2.INTER_AREA)


class FrameDifference:
    """
    Ego-motion compensated frame differencing on a fixed working size: per grid cell, the
    mean residual change (grey levels) between consecutive frames.

    :param size: square working size (the model's input, so its grid cells are the same).
    :param ego_motion: estimate and remove the camera's motion, as a homography (False:
        plain differencing).
    """

    def __init__(self, *, size: int = 224, grid: tuple[int, int] = (14, 14),
                 ego_motion: bool = True, tolerance_px: int = 1):
        self.size = size
        self.grid = grid
        self.ego = egomotion.EgoMotion(model='homography') if ego_motion else None
        self.tolerance_px = tolerance_px
        self.reset()

    def reset(self) -> None:
        self.previous = None          # (S, S) grey of the previous frame
        self.keys = None              # its ORB keypoints
        self.moved = False            # the camera moved between the last two frames

    def step(self, rgb: np.ndarray) -> np.ndarray | None:
        """(rows, cols) change per cell, grey levels; None on the first frame."""
        img = cv2.resize(np.asarray(rgb, dtype=np.uint8), (self.size, self.size),
                         interpolation=cv2.INTER_AREA)
        current = self._picture(img)
        warp = None
        if self.ego is not None:
            keys = self.ego.keypoints(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY))
            if self.keys is not None:
                warp = self.ego.estimate(self.keys, keys, (self.size, self.size))
            self.keys = keys
        previous, self.previous = self.previous, current
        self.moved = warp is not None
        if previous is None:
            return None
        return cell_means(self._change(previous, current, warp), self.grid)

    def _picture(self, img: np.ndarray) -> np.ndarray:
        """What is kept of a frame to compare the next with: blurred grey, float32."""
        return grey(img)

    def _change(self, previous: np.ndarray, current: np.ndarray,
                warp: np.ndarray | None) -> np.ndarray:
        return residual(previous, current, warp, tolerance_px=self.tolerance_px)


class FlowMagnitude(FrameDifference):
    """
    Dense optical flow (OpenCV's DIS) with the camera's own motion taken out as
    `FrameDifference` takes it out: per grid cell, the mean length (pixels of the working
    size) of the flow from the previous frame, warped into the new view, to this one.

    :param size: square working size (the model's input, so its grid cells are the same).
    """

    def __init__(self, *, size: int = 224, grid: tuple[int, int] = (14, 14)):
        super().__init__(size=size, grid=grid, ego_motion=True)
        self.flow = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)

    def _picture(self, img: np.ndarray) -> np.ndarray:
        return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)       # DIS takes uint8 grey

    def _change(self, previous: np.ndarray, current: np.ndarray,
                warp: np.ndarray | None) -> np.ndarray:
        previous, seen = into_view(previous, warp)
        flow = self.flow.calc(previous, current, None)
        length = np.hypot(flow[..., 0], flow[..., 1]).astype(np.float32)
        if seen is not None:      # what the old view did not see has no flow to measure
            length[cv2.erode(seen, np.ones((3, 3), np.uint8)) == 0] = 0.0
        return length
