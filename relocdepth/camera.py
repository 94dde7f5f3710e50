"""Pinhole intrinsics and how they follow resizes and crops.

Convention (OpenCV): pixel centres sit at integer coordinates, so the continuous image
spans [-0.5, W - 0.5]. A resize by (sx, sy) maps x -> (x + 0.5) * sx - 0.5; hence
``cx' = (cx + 0.5) * sx - 0.5`` (the half-pixel offset) and ``fx' = fx * sx``.
A crop at (x0, y0) shifts the principal point by (-x0, -y0).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from relocdepth.errors import UserError

# Two image sizes "have the same aspect" when the rescale factors agree to this relative
# tolerance; rounding a size to whole pixels changes the ratio by at most ~1/min(W, H).
ASPECT_TOLERANCE = 0.01


@dataclass(frozen=True)
class Intrinsics:
    """Intrinsics of a stored image, in pixels of that image."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def K(self) -> np.ndarray:
        """The 3x3 camera matrix (float64)."""
        return np.array(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=np.float64
        )

    def to_dict(self) -> dict:
        return {k: (float(v) if k in ("fx", "fy", "cx", "cy") else int(v)) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> Intrinsics:
        return cls(
            fx=float(d["fx"]), fy=float(d["fy"]), cx=float(d["cx"]), cy=float(d["cy"]),
            width=int(d["width"]), height=int(d["height"]),
        )

    def same_aspect(self, width: int, height: int) -> bool:
        sx, sy = width / self.width, height / self.height
        return abs(sx - sy) <= ASPECT_TOLERANCE * max(sx, sy)

    def scaled(self, width: int, height: int) -> Intrinsics:
        """Intrinsics after resizing the whole image to ``width x height`` (any aspect)."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(
            fx=self.fx * sx, fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5, cy=(self.cy + 0.5) * sy - 0.5,
            width=int(width), height=int(height),
        )

    def scaled_uniform(self, width: int, height: int) -> Intrinsics:
        """Like :meth:`scaled`, but a change of aspect ratio is a user error."""
        if not self.same_aspect(width, height):
            raise UserError(
                f"intrinsics are for {self.width}x{self.height} but the frames are {width}x{height}, "
                "a different aspect ratio; give intrinsics calibrated at this frame size (--K)"
            )
        return self.scaled(width, height)

    def cropped(self, x0: float, y0: float, width: int, height: int) -> Intrinsics:
        """Intrinsics of the crop whose top-left pixel is (x0, y0) of this image."""
        return Intrinsics(
            fx=self.fx, fy=self.fy, cx=self.cx - x0, cy=self.cy - y0, width=int(width), height=int(height)
        )


def scale_K(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Scale a (..., 3, 3) camera matrix for a resize by (sx, sy), with the half-pixel offset."""
    K = np.array(K, dtype=np.float64, copy=True)
    K[..., 0, 0] *= sx
    K[..., 1, 1] *= sy
    K[..., 0, 2] = (K[..., 0, 2] + 0.5) * sx - 0.5
    K[..., 1, 2] = (K[..., 1, 2] + 0.5) * sy - 0.5
    return K
