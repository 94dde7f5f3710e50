"""Pinhole camera in torch: intrinsics after a resize, back-projection of a depth map.

Pixel centres sit at integer coordinates (OpenCV), so a resize by ``(sx, sy)`` maps
``x -> (x + 0.5) sx - 0.5`` (the numpy twin for stored images is :func:`relocdepth.camera.scale_K`).
"""

from __future__ import annotations

import torch
from torch import Tensor


def scale_intrinsics(K: Tensor, sx: float, sy: float) -> Tensor:
    """Camera matrices ``(..., 3, 3)`` after resizing by ``(sx, sy)`` (half-pixel convention:
    ``cx' = (cx + 0.5) sx - 0.5``, as :func:`relocdepth.camera.scale_K`)."""
    K = K.clone()
    K[..., 0, 0] = K[..., 0, 0] * sx
    K[..., 1, 1] = K[..., 1, 1] * sy
    K[..., 0, 2] = (K[..., 0, 2] + 0.5) * sx - 0.5
    K[..., 1, 2] = (K[..., 1, 2] + 0.5) * sy - 0.5
    return K


def backproject(depth: Tensor, K: Tensor) -> Tensor:
    """Camera-frame points ``D(p) K^-1 [u, v, 1]``: ``depth (B, 1, H, W)``, ``K (B, 3, 3)`` -> ``(B, 3, H, W)``."""
    B, _, H, W = depth.shape
    v, u = torch.meshgrid(
        torch.arange(H, device=depth.device, dtype=depth.dtype),
        torch.arange(W, device=depth.device, dtype=depth.dtype),
        indexing="ij",
    )
    pix = torch.stack((u, v, torch.ones_like(u)), dim=0).reshape(3, -1)  # (3, HW)
    rays = torch.linalg.inv(K) @ pix  # (B, 3, HW)
    return (rays * depth.reshape(B, 1, -1)).reshape(B, 3, H, W)
