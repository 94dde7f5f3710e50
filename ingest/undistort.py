"""Removing lens distortion, the same way for ingest and for ``reloc localize``.

K is kept as the new camera matrix (``initUndistortRectifyMap(K, dist, None, K, ...)``), so the
intrinsics do not change; pixels that map from outside the source image become black. The
remap tables are built once per frame size and reused (building them costs far more than
applying them).
"""

from __future__ import annotations

import threading

import numpy as np
from relocdepth.ingest.intrinsics import Calibration


class Undistorter:
    """Cached undistortion maps per calibration size; thread-safe."""

    def __init__(self) -> None:
        self._maps: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
        self._lock = threading.Lock()

    def maps(self, calib: Calibration) -> tuple[np.ndarray, np.ndarray]:
        """The (fixed-point) remap tables of ``calib`` at its own size."""
        import cv2

        intr = calib.intrinsics
        key = (intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy, calib.distortion)
        with self._lock:
            if key not in self._maps:
                K = intr.K()
                dist = np.asarray(calib.distortion, dtype=np.float64)
                size = (intr.width, intr.height)
                self._maps[key] = cv2.initUndistortRectifyMap(K, dist, None, K, size, cv2.CV_16SC2)
            return self._maps[key]

    def apply(self, img: np.ndarray, calib: Calibration, nearest: bool = False) -> np.ndarray:
        """``img`` (of ``calib``'s size) without distortion; ``nearest`` for depth maps."""
        import cv2

        if not calib.distorted:
            return img
        m1, m2 = self.maps(calib)
        interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
        return cv2.remap(img, m1, m2, interp, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
