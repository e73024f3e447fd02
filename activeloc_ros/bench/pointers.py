"""
What steers the camera in the projected-screen benchmark: the model and the baselines.

Each is a ``closed_loop.Pointer``; the trackers are in ``bench.trackers``. All of them
drive the same controller and arm.
"""
import time

import cv2
import numpy as np

from activeloc_ros import metrics
from activeloc_ros.closed_loop import Pointing
from activeloc_ros.errors import ConfigError
from activeloc_ros.world import View

# Paper Table 3 rows that change the perception (the controller rows are PD variants).
ABLATIONS: dict[str, dict] = {
    'full': {},
    'predlearn': {'mode': 'predlearn'},           # PredLearn (Aakur & Sarkar) + PID
    'no_norm_motion': {'motion': 'raw'},          # w/o normalized motion
    'no_attn': {'use_attn_loss': False},          # w/o L_attn
    'resnet50': {'encoder': 'resnet50'},          # w/ ResNet-50 encoder
}


class ModelPointer:
    """
    The perception model, fresh (same seed) for every sequence. Its encoder is shared
    between sequences only when frozen: one that learns online starts again from its
    weights, so nothing learned on one sequence carries into the next.

    :param settings: PerceptionConfig fields (a Table 3 ablation already applied).
    """

    def __init__(self, name: str, settings: dict):
        from activeloc_ros.perception.config import PerceptionConfig
        from activeloc_ros.perception.model import SurpriseModel
        self.name = name
        self.config = PerceptionConfig.from_dict(settings)
        self._model_class = SurpriseModel
        self.model = SurpriseModel(self.config)   # fails now if the weights are missing
        self._fresh = True

    def reset(self, sequence: str) -> None:
        if not self._fresh:
            frozen = not self.model.train_encoder
            self.model = self._model_class(self.config,
                                           encoder=self.model.encoder if frozen else None)
        self._fresh = False

    def locate(self, view: View) -> Pointing:
        """
        The model's step; its location is ready when its map is, before the optimiser
        step, as the perception node publishes it, and a late frame's step is skipped as
        the node skips it.
        """
        t0 = time.perf_counter()
        ready: list[float] = []
        result = self.model.step(view.rgb, t=view.t,
                                 on_map=lambda _: ready.append(time.perf_counter() - t0),
                                 late=view.late)
        h, w = view.rgb.shape[:2]
        return Pointing(result.location_px, result.surprise_map, result.peak,
                        ready_s=ready[0] if ready else None,
                        box=metrics.blob_box(result.surprise_map, (w, h)),
                        learnt=result.updated)


class TrackerMethod:
    """
    An OpenCV tracker baseline (``bench.trackers``) started on the first camera frame,
    steering to its box centre.

    :param start: ``'proposal'``: from the best EdgeBoxes proposal (the paper's screen
        experiment); ``'truth'``: from the target's true box (the tracking standard, the
        tracking experiment).
    """

    def __init__(self, kind: str, *, start: str = 'proposal'):
        from activeloc_ros.bench.trackers import TrackerPointer
        if start not in ('proposal', 'truth'):
            raise ConfigError(f"tracker start must be 'proposal' or 'truth', got {start!r}")
        self.tracker = TrackerPointer(kind)
        self.name = self.tracker.name
        self.start = start

    def reset(self, sequence: str) -> None:
        self.tracker.reset()

    def locate(self, view: View) -> Pointing:
        start = view.truth_box if self.start == 'truth' else None
        location = self.tracker.locate(view.rgb, start=start)
        return Pointing(location, box=self.tracker.box)


class CentrePointer:
    """The camera never moves (it looks at the screen centre from the home pose)."""

    name = 'centre'

    def reset(self, sequence: str) -> None:
        pass

    def locate(self, view: View) -> Pointing:
        return Pointing(None)


class RandomPointer:
    """
    Paper: 'a random location around the center of the screen' each frame, steered to.

    :param spread: standard deviation of the target around the screen centre, as a share of
        the camera image size (its width and height).
    """

    name = 'random'

    def __init__(self, *, seed: int = 0, spread: float = 0.25):
        if not spread > 0:
            raise ConfigError(f'random spread must be > 0, got {spread}')
        self.seed = seed
        self.spread = spread
        self.reset('')

    def reset(self, sequence: str) -> None:
        self.rng = np.random.default_rng(self.seed)

    def locate(self, view: View) -> Pointing:
        h, w = view.rgb.shape[:2]
        u, v = view.centre_px + self.rng.normal(0.0, self.spread, 2) * (w, h)
        # the controller acts on pixels of the image only: a target beyond the border pulls
        # the camera as far as the border does
        return Pointing((float(np.clip(u, 0, w - 1)), float(np.clip(v, 0, h - 1))))


class OraclePointer:
    """
    The ground truth fed to the controller (the primary actor, else the closest one):
    the upper bound, limited only by the arm. Points beyond the image are pulled in to its
    border, where the controller takes them.
    """

    name = 'oracle'

    def reset(self, sequence: str) -> None:
        pass

    def locate(self, view: View) -> Pointing:
        h, w = view.rgb.shape[:2]
        target = view.primary_px
        if target is None or not np.all(np.isfinite(target)):
            finite = view.truth_px[np.all(np.isfinite(view.truth_px), axis=1)]
            if len(finite) == 0:
                return Pointing(None)
            centre = np.array([(w - 1) / 2, (h - 1) / 2])
            target = finite[np.argmin(np.linalg.norm(finite - centre, axis=1))]
        return Pointing((float(np.clip(target[0], 0, w - 1)),
                         float(np.clip(target[1], 0, h - 1))), box=view.truth_box)


def _map_pointing(heat: np.ndarray | None, image_wh: tuple[int, int]) -> Pointing:
    """
    A pointer's answer from a non-negative map: its peak cell, the map normalised to sum
    1, and its peak value, which the controller's information rule (`min_peak`) judges as it
    judges the model's. No map, or nothing in it: no location.
    """
    total = 0.0 if heat is None else float(heat.sum())
    if not total > 0:
        return Pointing(None)
    heat = (heat / total).astype(np.float32)
    return Pointing(metrics.peak_point(heat, image_wh), heat, float(heat.max()))


class _MotionPointer:
    """Steer to the cell that moved most in a motion map (``motion``: ``reset``, ``step``)."""

    def reset(self, sequence: str) -> None:
        self.motion.reset()

    def locate(self, view: View) -> Pointing:
        h, w = view.rgb.shape[:2]
        return _map_pointing(self.motion.step(view.rgb), (w, h))


class FrameDiffPointer(_MotionPointer):
    """
    Steer by frame differencing, the camera's own motion taken out as the model's is.

    `perception.motion.FrameDifference`: to the cell that changed most.
    """

    def __init__(self, name: str = 'framediff'):
        from activeloc_ros.perception.motion import FrameDifference
        self.name = name
        self.motion = FrameDifference()


class FlowPointer(_MotionPointer):
    """
    Steer by the length of DIS dense optical flow, the camera's own motion taken out.

    `perception.motion.FlowMagnitude`, as for framediff: to the cell that moved most.
    """

    name = 'flow'

    def __init__(self):
        from activeloc_ros.perception.motion import FlowMagnitude
        self.motion = FlowMagnitude()


class Mog2Pointer:
    """
    OpenCV's BackgroundSubtractorMOG2: steers to the centroid of the foreground. The
    background model starts again whenever the camera moved (the same ego-motion estimate
    as framediff's), since a moved view is all foreground to it.

    :param width: working width of the image (the height keeps the aspect).
    :param min_share: less foreground than this share of the image is no foreground.
    """

    name = 'mog2'

    def __init__(self, *, width: int = 320, min_share: float = 0.001):
        from activeloc_ros.perception.motion import FrameDifference
        self.camera = FrameDifference()
        self.width = width
        self.min_share = min_share
        self.reset('')

    def reset(self, sequence: str) -> None:
        self.camera.reset()
        self.subtractor = None

    def locate(self, view: View) -> Pointing:
        h, w = view.rgb.shape[:2]
        self.camera.step(view.rgb)
        if self.subtractor is None or self.camera.moved:
            self.subtractor = cv2.createBackgroundSubtractorMOG2(detectShadows=False)
        small = cv2.resize(view.rgb, (self.width, max(1, round(h * self.width / w))),
                           interpolation=cv2.INTER_AREA)
        mask = self.subtractor.apply(small)
        mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
        ys, xs = np.nonzero(mask)
        if len(xs) < self.min_share * mask.size:
            return Pointing(None)
        scale = w / self.width
        location = ((xs.mean() + 0.5) * scale - 0.5, (ys.mean() + 0.5) * h / mask.shape[0] - 0.5)
        heat = cv2.resize((mask > 0).astype(np.float32), (14, 14), interpolation=cv2.INTER_AREA)
        heat = heat / heat.sum()
        return Pointing(location, heat, float(heat.max()))
