"""Run the trained networks on images: resize to the training input, scale K, predict.

Shared by ``localize`` (user images) and ``evaluate`` (shard frames). The checkpoint's
``intrinsics_policy`` is "resize": an image is resized whole to the network input size and its
intrinsics are scaled with it (half-pixel convention, :mod:`relocdepth.camera`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from relocdepth.camera import Intrinsics
from relocdepth.errors import UserError

log = logging.getLogger(__name__)


@dataclass
class Prediction:
    """Per-image outputs of one batch, numpy, in the networks' world frame (no alignment)."""

    T_wc: np.ndarray  # (B, 4, 4) float64 world-from-camera
    confidence: np.ndarray  # (B,) in (0, 1]: higher = per-cell poses agree more
    spread_t: np.ndarray  # (B,) spread of per-cell camera centres (network units)
    spread_r_deg: np.ndarray  # (B,) spread of per-cell rotations (deg)
    depth: np.ndarray | None  # (B, H, W) float32 at the network input size (network units)


def resize_to(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Resize an (H, W, 3) image to size (W, H): area averaging when shrinking, else bilinear."""
    import cv2

    w, h = size
    if image.shape[1] == w and image.shape[0] == h:
        return image
    shrink = w < image.shape[1] or h < image.shape[0]
    return cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)


class Predictor:
    """The two networks of a checkpoint plus what is needed to feed them."""

    def __init__(self, nets: Any, meta: dict, device: str = "cpu") -> None:
        self.nets = nets
        self.meta = meta
        self.device = device
        self.input_size: tuple[int, int] = tuple(int(v) for v in meta["input_size"])  # (W, H)
        self.train_intrinsics = Intrinsics.from_dict(meta["intrinsics"])
        self.alignment: dict | None = meta.get("alignment")

    @classmethod
    def from_checkpoint(cls, path_or_run: str | Path | None, device: str = "cpu", raw: bool = False) -> Predictor:
        from relocdepth.checkpoint import load_for_inference

        nets, meta = load_for_inference(path_or_run, device=device, raw=raw)
        return cls(nets, meta, device)

    def intrinsics_for(self, width: int, height: int, given: Intrinsics | None = None) -> Intrinsics:
        """Intrinsics of a query image of width x height: the given ones, or the training camera
        scaled to that size (a different aspect ratio is a :class:`UserError`: pass --K)."""
        if given is not None:
            return given
        cam = self.train_intrinsics
        if not cam.same_aspect(width, height):
            raise UserError(
                f"the image is {width}x{height} but the network was trained on a "
                f"{cam.width}x{cam.height} camera (another aspect ratio); pass its intrinsics with --K FILE"
            )
        return cam.scaled(width, height)

    def prepare(self, images: list[np.ndarray], intrinsics: list[Intrinsics]) -> tuple[Any, Any]:
        """RGB uint8 images + their intrinsics -> (inputs (B,3,H,W) in [0,1], K (B,3,3)) tensors."""
        import torch

        w, h = self.input_size
        batch = np.stack([resize_to(im, (w, h)) for im in images])
        Ks = np.stack([k.scaled(w, h).K() for k in intrinsics]).astype(np.float32)
        x = torch.from_numpy(batch).to(self.device).permute(0, 3, 1, 2).float().div_(255.0)
        return x, torch.from_numpy(Ks).to(self.device)

    def predict(
        self, images: list[np.ndarray], intrinsics: list[Intrinsics], with_depth: bool = True
    ) -> Prediction:
        """Predict poses (and depth) for one batch of RGB uint8 (H, W, 3) images."""
        from relocdepth.method import predict

        x, K = self.prepare(images, intrinsics)
        out = predict(self.nets, x, K)
        depth = out["depth"][:, 0].float().cpu().numpy() if with_depth else None
        return Prediction(
            T_wc=out["T_wc"].double().cpu().numpy(),
            confidence=out["confidence"].double().cpu().numpy(),
            spread_t=out["cell_spread_t"].double().cpu().numpy(),
            spread_r_deg=out["cell_spread_r_deg"].double().cpu().numpy(),
            depth=depth,
        )
