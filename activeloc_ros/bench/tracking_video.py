"""The tracking benchmark's overlay video of one episode."""
import math
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from activeloc_ros.bench.video import PendingVideo
from activeloc_ros.closed_loop import FrameRecord

if TYPE_CHECKING:
    from activeloc_ros.bench.tracking import Remembering


class TrackingVideo(PendingVideo):
    """
    The camera view (true box green, the method's map and choice red) beside a top-down
    map (base blue, target red, their paths), as H.264.
    """

    SIDE = 480

    def __init__(self, path: Path, world, pointer: 'Remembering', label: str):
        super().__init__(path, 1.0 / world.config.step)
        self.world, self.pointer, self.label = world, pointer, label
        self.base_path: list[tuple[float, float]] = []
        self.target_path: list[tuple[float, float]] = []

    def _plan_px(self, xy) -> tuple[int, int]:
        x0, y0, x1, y1 = self.world.plan.bounds
        scale = (self.SIDE - 20) / max(x1 - x0, y1 - y0)
        return (int(10 + (xy[0] - x0) * scale), int(self.SIDE - 10 - (xy[1] - y0) * scale))

    def top_down(self, record: FrameRecord) -> np.ndarray:
        img = np.full((self.SIDE, self.SIDE, 3), 245, np.uint8)
        x0, y0, x1, y1 = self.world.plan.bounds
        cv2.rectangle(img, self._plan_px((x0, y0)), self._plan_px((x1, y1)), (0, 0, 0), 1)
        scale = (self.SIDE - 20) / max(x1 - x0, y1 - y0)
        for ox, oy, r in self.world.plan.obstacles:
            cv2.circle(img, self._plan_px((ox, oy)), max(1, int(r * scale)), (150, 150, 150),
                       -1)
        for path, colour in ((self.base_path, (200, 80, 0)), (self.target_path, (0, 0, 220))):
            if len(path) > 1:
                cv2.polylines(img, [np.array([self._plan_px(p) for p in path], np.int32)],
                              False, colour, 1, cv2.LINE_AA)
        if record.base_xy is not None:
            bx, by = self._plan_px(record.base_xy)
            tip = (record.base_xy[0] + 0.8 * math.cos(record.pan),
                   record.base_xy[1] + 0.8 * math.sin(record.pan))
            cv2.arrowedLine(img, (bx, by), self._plan_px(tip), (200, 80, 0), 2)
        for _, walker, _ in self.world.people[1:]:      # the distractors, now
            cv2.circle(img, self._plan_px((walker.x, walker.y)), 4, (120, 120, 0), -1)
        if record.target_xy is not None:
            cv2.circle(img, self._plan_px(record.target_xy), 5, (0, 0, 220), -1)
        cv2.putText(img, f'{self.label}  step {record.index}  reward {record.reward:+.2f}',
                    (8, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        cv2.putText(img, 'base (blue), target (red), others (teal)', (8, self.SIDE - 2),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
        return img

    def add(self, scene, record: FrameRecord, camera: np.ndarray | None) -> None:
        if record.base_xy is not None:
            self.base_path.append(record.base_xy)
            self.target_path.append(record.target_xy)
        if camera is None:
            return
        h, w = camera.shape[:2]
        frame = cv2.cvtColor(camera, cv2.COLOR_RGB2BGR)
        last = self.pointer.last
        if last is not None and last.heat is not None and np.ptp(last.heat) > 0:
            heat = cv2.resize(np.asarray(last.heat, np.float32), (w, h),
                              interpolation=cv2.INTER_NEAREST)
            heat = (heat - heat.min()) / max(float(np.ptp(heat)), 1e-9)   # (H, W) in [0, 1]
            colour = cv2.applyColorMap((255 * heat).astype(np.uint8), cv2.COLORMAP_JET)
            alpha = 0.5 * heat[..., None]                      # the map where it is high
            frame = (frame * (1 - alpha) + colour * alpha).astype(np.uint8)
        view = self.world.view
        if view is not None and view.truth_box is not None:
            x, y, bw, bh = view.truth_box
            cv2.rectangle(frame, (x, y), (x + bw - 1, y + bh - 1), (0, 255, 0), 1)
        if last is not None and last.location is not None:
            u, v = last.location
            cv2.drawMarker(frame, (int(round(u)), int(round(v))), (0, 0, 255),
                           cv2.MARKER_CROSS, 14, 2)
        frame = np.hstack([cv2.resize(frame, (self.SIDE * w // h, self.SIDE)),
                           self.top_down(record)])
        self.write(frame)
