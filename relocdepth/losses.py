"""The paper's losses (Sec. III-B): photometric re-projection, edge-aware smoothness, pose coordinate.

All return per-image values ``(B,)``; the caller averages over batch, pairs and scales.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from relocdepth.geometry import quat_conj, quat_from_matrix, quat_log, quat_mul

# SSIM constants (Wang et al. 2004) for images in [0, 1], as monodepth2.
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2


def ssim_distance(x: Tensor, y: Tensor) -> Tensor:
    """``(1 - SSIM) / 2`` per pixel, clamped to [0, 1]: ``x, y (B, C, H, W)`` -> ``(B, C, H, W)``.

    monodepth2's SSIM: 3x3 box window with reflection padding. Not kornia's ``ssim``, which uses a
    Gaussian window with zero padding (different values at borders and a different loss).
    The window's means are sums of shifted views (:func:`_box3`), as ``avg_pool2d(., 3, 1)`` but
    2.1-2.3x faster forward and backward on a CPU thread at 128x96-256x192 (README, Performance:
    SSIM's window means).
    """
    x = F.pad(x, (1, 1, 1, 1), mode="reflect")
    y = F.pad(y, (1, 1, 1, 1), mode="reflect")
    mu_x, mu_y = _box3(x), _box3(y)
    sigma_x = _box3(x * x) - mu_x * mu_x
    sigma_y = _box3(y * y) - mu_y * mu_y
    sigma_xy = _box3(x * y) - mu_x * mu_y
    num = (2 * mu_x * mu_y + SSIM_C1) * (2 * sigma_xy + SSIM_C2)
    den = (mu_x * mu_x + mu_y * mu_y + SSIM_C1) * (sigma_x + sigma_y + SSIM_C2)
    return torch.clamp((1 - num / den) / 2, 0, 1)


def _box3(t: Tensor) -> Tensor:
    """The mean of each 3x3 window of ``t (..., H, W)`` -> ``(..., H - 2, W - 2)`` (a padded input's
    windows), as the sum of three shifted views along each axis: separable, and no pooling kernel."""
    rows = t[..., :, :-2] + t[..., :, 1:-1] + t[..., :, 2:]
    return (rows[..., :-2, :] + rows[..., 1:-1, :] + rows[..., 2:, :]) / 9.0


def photometric_error(target: Tensor, pred: Tensor, alpha: float = 0.85) -> Tensor:
    """Per-pixel ``alpha (1 - SSIM) / 2 + (1 - alpha) |I_t - I_hat|`` (channel mean):
    ``(B, C, H, W)`` x2 -> ``(B, 1, H, W)``."""
    l1 = (target - pred).abs().mean(1, keepdim=True)
    ssim = ssim_distance(target, pred).mean(1, keepdim=True)
    return alpha * ssim + (1 - alpha) * l1


def photometric_loss(target: Tensor, pred: Tensor, valid: Tensor, alpha: float = 0.85) -> Tensor:
    """``L_p`` per image: mean of :func:`photometric_error` over valid pixels.

    Args:
        target, pred: ``(B, C, H, W)``; valid: ``(B, 1, H, W)`` in {0, 1}.

    Returns:
        ``(B,)``; 0 for an image without valid pixels.
    """
    err = photometric_error(target, pred, alpha) * valid
    return err.sum(dim=(1, 2, 3)) / valid.sum(dim=(1, 2, 3)).clamp_min(1.0)


def smoothness_loss(disp: Tensor, image: Tensor) -> Tensor:
    """``L_s`` per image: ``mean_p (exp(-|grad I|) * grad d*)^2`` over x and y, summed.

    The paper's squared form of monodepth2's edge-aware term, on the mean-normalised disparity
    ``d* = d / mean(d)`` (so it cannot be lowered by shrinking the disparity).

    Args:
        disp: ``(B, 1, h, w)`` disparity at its decoder scale; image: ``(B, C, h, w)`` at that size.

    Returns:
        ``(B,)``.
    """
    d = disp / (disp.mean(dim=(2, 3), keepdim=True) + 1e-7)
    gdx = (d[..., :, :-1] - d[..., :, 1:]).abs()
    gdy = (d[..., :-1, :] - d[..., 1:, :]).abs()
    gix = (image[..., :, :-1] - image[..., :, 1:]).abs().mean(1, keepdim=True)
    giy = (image[..., :-1, :] - image[..., 1:, :]).abs().mean(1, keepdim=True)
    sx = (gdx * torch.exp(-gix)) ** 2
    sy = (gdy * torch.exp(-giy)) ** 2
    return sx.mean(dim=(1, 2, 3)) + sy.mean(dim=(1, 2, 3))


def pose_coordinate_loss(q_cells: Tensor, c_cells: Tensor, q: Tensor, c: Tensor) -> Tensor:
    """``L_c`` per image: ``mean_p || P - P(p) ||_2`` with ``P = [rotation, centre]``.

    The rotation difference is the rotation vector of ``R^T R(p)`` (radians), not a difference of
    axis-angle vectors (which is no distance and breaks near pi); the centre difference is in depth
    units.

    Args:
        q_cells: ``(B, N, 4)``, c_cells: ``(B, N, 3)``; q: ``(B, 4)``, c: ``(B, 3)`` their aggregate.

    Returns:
        ``(B,)``.
    """
    dr = quat_log(quat_mul(quat_conj(q).unsqueeze(1), q_cells))
    dt = c_cells - c.unsqueeze(1)
    return torch.linalg.vector_norm(torch.cat((dr, dt), dim=-1), dim=-1).mean(dim=1)


def relative_pose_consistency(T_a: Tensor, T_b: Tensor, t_weight: Tensor | None = None) -> Tensor:
    """Distance between relative poses ``(N, 4, 4)``: ``|| [log(R_a^T R_b), w (t_a - t_b)] ||_2`` per
    pair ``(N,)`` (radians and depth units, like ``L_c``), ``w = t_weight (N,)`` (default 1; 0 compares
    the rotations only). Used by the training bootstrap to teach the DSC network another source's
    relative poses; the gradient is finite where they agree."""
    dr = quat_log(quat_from_matrix(T_a[:, :3, :3].transpose(-1, -2) @ T_b[:, :3, :3]))
    dt = T_a[:, :3, 3] - T_b[:, :3, 3]
    if t_weight is not None:
        dt = dt * t_weight[:, None]
    return torch.linalg.vector_norm(torch.cat((dr, dt), dim=-1), dim=-1)


def translation_direction_angle(t_a: Tensor, t_b: Tensor, eps: float = 1e-12) -> Tensor:
    """Angle (radians) between translations ``(N, 3)``, per row ``(N,)``, whatever their lengths
    (the bootstrap measures directions; its lengths come from the current depth). 0 for a row where
    either is (nearly) zero: no direction there. The gradient is finite everywhere, also where the
    directions agree (``eps`` under the cross product's norm)."""
    tiny = 1e-9
    n_a, n_b = torch.linalg.vector_norm(t_a, dim=-1), torch.linalg.vector_norm(t_b, dim=-1)
    ok = (n_a > tiny) & (n_b > tiny)
    e_x = torch.zeros_like(t_a)
    e_x[..., 0] = 1.0
    u_a = torch.where(ok[..., None], t_a, e_x) / torch.where(ok, n_a, torch.ones_like(n_a))[..., None]
    u_b = torch.where(ok[..., None], t_b, e_x) / torch.where(ok, n_b, torch.ones_like(n_b))[..., None]
    cross = torch.linalg.cross(u_a, u_b, dim=-1)
    angle = torch.atan2(torch.sqrt((cross * cross).sum(-1) + eps), (u_a * u_b).sum(-1))
    return torch.where(ok, angle, torch.zeros_like(angle))
