"""
The camera's own motion between two frames, estimated from the images.

When the camera turns (the arm moving it, or a panning source video) every feature of the
view changes, so the frame difference and the prediction error light up the whole image and
most of all the border that new content enters from. The model can instead compare the new
frame with the previous one warped into the new view: `estimate` finds that warp (a
similarity transform: shift, rotation, scale, fitted with RANSAC to ORB matches, so the
dominant background wins over a moving actor), `warp_image` applies it to the previous
image and `warp_cells` to per-cell state (the LSTMs', the previous maps).
"""
import cv2
import numpy as np
import torch
import torch.nn.functional as F

MIN_INLIERS = 12          # fewer RANSAC inliers: no reliable estimate
RANSAC_PX = 2.0           # inlier threshold, pixels of the model's input image
MODELS = ('similarity', 'homography')


class EgoMotion:
    """
    Similarity transforms between consecutive images of one size (the encoder input).

    :param features: ORB keypoints per image.
    :param min_shift_px: a warp that moves no image corner more than this is no motion.
    :param model: 'similarity' (shift, rotation, scale) or 'homography', the exact image
        motion of a camera that turns about its optical centre, as a pan-tilt camera does:
        a similarity leaves the perspective part at the corners of a turned view unexplained.
    """

    def __init__(self, *, features: int = 500, min_shift_px: float = 0.5,
                 model: str = 'similarity'):
        if model not in MODELS:
            raise ValueError(f'ego-motion model must be one of {MODELS}, got {model!r}')
        self.model = model
        self.orb = cv2.ORB_create(nfeatures=features, edgeThreshold=15, patchSize=15)
        self.matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
        self.min_shift_px = min_shift_px

    def keypoints(self, gray: np.ndarray):
        return self.orb.detectAndCompute(gray, None)

    def estimate(self, prev, cur, image_wh: tuple[int, int]) -> np.ndarray | None:
        """
        The 3x3 matrix taking pixels of the previous image to the current one, both
        `image_wh` (width, height), from their `keypoints`; None when the camera did not
        move or the motion is unknown.
        """
        (kp0, des0), (kp1, des1) = prev, cur
        if des0 is None or des1 is None or len(kp0) < MIN_INLIERS or len(kp1) < MIN_INLIERS:
            return None
        matches = self.matcher.match(des0, des1)
        if len(matches) < MIN_INLIERS:
            return None
        src = np.float32([kp0[m.queryIdx].pt for m in matches])
        dst = np.float32([kp1[m.trainIdx].pt for m in matches])
        if self.model == 'homography':
            h, inliers = cv2.findHomography(src, dst, cv2.RANSAC, RANSAC_PX)
        else:
            affine, inliers = cv2.estimateAffinePartial2D(
                src, dst, method=cv2.RANSAC, ransacReprojThreshold=RANSAC_PX)
            h = None if affine is None else np.vstack([affine, [0.0, 0.0, 1.0]])
        if h is None or inliers is None or int(inliers.sum()) < MIN_INLIERS:
            return None
        width, height = image_wh
        corners = np.float32([[0, 0], [width, 0], [0, height], [width, height]])[:, None]
        moved = cv2.perspectiveTransform(corners, h) - corners
        if np.abs(moved).max() <= self.min_shift_px:
            return None
        return h


def warp_image(prev: np.ndarray, h: np.ndarray, cur: np.ndarray) -> np.ndarray:
    """
    The previous image as the current view would show it. What it did not see is taken
    from the current image: no change there, rather than a black edge whose features
    would differ from the new frame's over the encoder's whole receptive field.
    """
    size = (prev.shape[1], prev.shape[0])
    warped = cv2.warpPerspective(prev, h, size, flags=cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    seen = cv2.warpPerspective(np.ones(prev.shape[:2], np.uint8), h, size,
                               flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                               borderValue=0).astype(bool)
    return np.where(seen[..., None], warped, cur)


def warp_cells(values: torch.Tensor, h: np.ndarray, image_wh: tuple[int, int],
               grid: tuple[int, int]) -> torch.Tensor:
    """
    Per-cell values (K, rows*cols, ...) of the previous view moved to the current one by
    the warp `h` of images `image_wh` (width, height) that a (rows, cols) grid covers
    (bilinear; cells the previous view did not see get 0).
    """
    k, n = values.shape[:2]
    rest = values.shape[2:]
    rows, cols = grid
    width, height = image_wh
    planes = values.reshape(k, n, -1).permute(0, 2, 1).reshape(k, -1, rows, cols)
    # sampling grid: for each current cell centre, where it was in the previous image
    inv = np.linalg.inv(h)
    xs, ys = np.meshgrid((np.arange(cols) + 0.5) * width / cols,
                         (np.arange(rows) + 0.5) * height / rows)
    pts = cv2.perspectiveTransform(np.float32(np.stack([xs, ys], -1)).reshape(-1, 1, 2), inv)
    pts = pts.reshape(1, rows, cols, 2) / np.float32([width, height]) * 2.0 - 1.0
    norm = torch.from_numpy(pts).float()
    out = F.grid_sample(planes, norm.expand(k, -1, -1, -1), mode='bilinear',
                        padding_mode='zeros', align_corners=False)
    return out.reshape(k, -1, n).permute(0, 2, 1).reshape(k, n, *rest)
