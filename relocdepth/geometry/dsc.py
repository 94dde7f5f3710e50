"""Directed scene coordinates (DSC) <-> camera poses, in torch (paper Sec. III-A).

Per DSC cell ``p`` (centre pixel ``u = 32 i + 15.5``, ``v = 32 j + 15.5``) with the depth ``D(p)``
average-pooled over the cell's 32x32 block:

- ``ray = K^-1 [u, v, 1]``, ``|Q| = D(p) |ray|`` (distance along the ray, not the depth value);
- ``R_p`` = the minimal rotation taking ``e_z`` to ``ray / |ray|``;
- the DSC ``S(p) = [theta, tau]``: ``G = R(theta)`` maps ``e_z`` to the pixel's ray in the world,
  ``tau`` is the scene point hit by that ray;
- camera of the cell: ``R_wc(p) = G R_p^T`` and centre ``c(p) = tau - |Q| G e_z``;
- one pose per image: the mean of the cell poses in training (:func:`mean_cell_pose`), a robust
  median at test time (:func:`median_cell_pose`); their spread is the confidence signal.

Rotation averaging is on SO(3) (a per-component mean or median of axis-angle vectors is no
rotation mean and breaks near pi; DESIGN.md, pitfalls).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from kornia.geometry.conversions import axis_angle_to_quaternion
from torch import Tensor

from relocdepth.geometry import rotations as rot

# The DSC network outputs one cell per 32x32 block of the input image (ResNet18 at 1/32 scale).
DSC_STRIDE = 32


# --------------------------------------------------------------------------------------------
# the DSC grid


def check_image_size(height: int, width: int) -> None:
    """Raise :class:`~relocdepth.errors.UserError` unless both sides are positive multiples of 32."""
    from relocdepth.errors import UserError

    if height <= 0 or width <= 0 or height % DSC_STRIDE or width % DSC_STRIDE:
        raise UserError(
            f"network input size {width}x{height} is not a multiple of {DSC_STRIDE} on both sides; "
            f"choose a size such as 640x480, 256x192 or 128x96"
        )


def dsc_grid_size(height: int, width: int) -> tuple[int, int]:
    """DSC grid ``(h, w)`` for an input of ``height x width`` (multiples of 32)."""
    check_image_size(height, width)
    return height // DSC_STRIDE, width // DSC_STRIDE


def dsc_cell_centres(
    h: int, w: int, *, device: torch.device | None = None, dtype: torch.dtype = torch.float32
) -> Tensor:
    """Input-image pixel coordinates of the DSC cell centres, ``(h * w, 2)`` as ``(u, v)``, row-major.

    Cell (row j, column i) covers pixels ``32 i .. 32 i + 31``; its centre is ``u = 32 i + 15.5``.
    """
    half = (DSC_STRIDE - 1) / 2.0
    v, u = torch.meshgrid(
        torch.arange(h, device=device, dtype=dtype) * DSC_STRIDE + half,
        torch.arange(w, device=device, dtype=dtype) * DSC_STRIDE + half,
        indexing="ij",
    )
    return torch.stack((u.reshape(-1), v.reshape(-1)), dim=-1)


def pool_depth(depth: Tensor) -> Tensor:
    """Average-pool a depth map ``(B, 1, H, W)`` over 32x32 blocks -> ``(B, 1, H/32, W/32)``."""
    return F.avg_pool2d(depth, kernel_size=DSC_STRIDE, stride=DSC_STRIDE)


def cell_rays(K: Tensor, h: int, w: int) -> Tensor:
    """Unnormalised rays ``K^-1 [u, v, 1]`` of the DSC cell centres: ``K (B, 3, 3)`` -> ``(B, h*w, 3)``."""
    uv = dsc_cell_centres(h, w, device=K.device, dtype=K.dtype)
    uv1 = torch.cat((uv, torch.ones_like(uv[:, :1])), dim=-1)  # (N, 3)
    return torch.einsum("bij,nj->bni", torch.linalg.inv(K), uv1)


# --------------------------------------------------------------------------------------------
# DSC <-> per-cell camera poses


def cell_poses(dsc: Tensor, depth_cells: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
    """Per-cell camera poses from the DSC and the pooled depth.

    Args:
        dsc: ``(B, 6, h, w)`` = ``[theta (axis-angle of G), tau (scene point)]`` per cell.
        depth_cells: ``(B, 1, h, w)`` depth average-pooled to the DSC grid (:func:`pool_depth`).
        K: ``(B, 3, 3)`` intrinsics at the network input size (``h = H / 32``).

    Returns:
        ``q_wc (B, N, 4)`` camera rotations as quaternions (``R_wc = G R_p^T``) and
        ``c (B, N, 3)`` camera centres (``c = tau - |Q| G e_z``), ``N = h * w`` row-major.
    """
    B, C, h, w = dsc.shape
    if C != 6:
        raise ValueError(f"dsc must have 6 channels, got {tuple(dsc.shape)}")
    if depth_cells.shape != (B, 1, h, w):
        raise ValueError(f"depth_cells must be {(B, 1, h, w)}, got {tuple(depth_cells.shape)}")
    s = dsc.flatten(2).transpose(1, 2)  # (B, N, 6)
    theta, tau = s[..., :3], s[..., 3:]
    ray = cell_rays(K, h, w)  # (B, N, 3)
    ray_len = ray.norm(dim=-1, keepdim=True)
    dist = depth_cells.flatten(2).transpose(1, 2) * ray_len  # |Q|, (B, N, 1)
    q_p = rot.minimal_rotation_quat(ray / ray_len)
    q_g = axis_angle_to_quaternion(theta)
    q_wc = rot.quat_mul(q_g, rot.quat_conj(q_p))
    g_ez = rot.quat_to_matrix(q_g)[..., :, 2]  # G e_z: the ray in the world
    return q_wc, tau - dist * g_ez


def dsc_from_pose(T_wc: Tensor, depth_cells: Tensor, K: Tensor) -> Tensor:
    """Inverse of :func:`cell_poses`: the DSC that a camera ``T_wc`` with this depth would have.

    Args:
        T_wc: ``(B, 4, 4)`` world-from-camera poses.
        depth_cells: ``(B, 1, h, w)`` pooled depths (positive).
        K: ``(B, 3, 3)``.

    Returns:
        ``(B, 6, h, w)`` with ``theta = log(R_wc R_p)`` and ``tau = c + |Q| G e_z`` (the scene point).
    """
    B, _, h, w = depth_cells.shape
    ray = cell_rays(K, h, w)
    ray_len = ray.norm(dim=-1, keepdim=True)
    q_p = rot.minimal_rotation_quat(ray / ray_len)
    q_wc = rot.quat_from_matrix(T_wc[:, :3, :3]).unsqueeze(1)  # (B, 1, 4)
    q_g = rot.quat_mul(q_wc, q_p)  # G = R_wc R_p
    theta = rot.quat_log(q_g)
    dist = depth_cells.flatten(2).transpose(1, 2) * ray_len
    tau = T_wc[:, None, :3, 3] + dist * rot.quat_to_matrix(q_g)[..., :, 2]
    return torch.cat((theta, tau), dim=-1).transpose(1, 2).reshape(B, 6, h, w)


# --------------------------------------------------------------------------------------------
# one pose per image from the per-cell poses


def mean_cell_pose(q: Tensor, c: Tensor) -> tuple[Tensor, Tensor]:
    """Training-time aggregate: quaternion mean of rotations, arithmetic mean of centres.

    The rotation is the sign-aligned, renormalised mean of the quaternions: every ``q_i`` is
    flipped to the hemisphere of a reference (the chordal L2 mean, i.e. the top eigenvector of
    ``sum q q^T``, computed without gradient), then averaged. For clustered rotations this equals
    the chordal mean to second order, and unlike an eigen/SVD solve its gradient has no
    ``1 / (lambda_i - lambda_j)`` terms (those blow up when all cells agree).

    Args:
        q: ``(B, N, 4)`` unit quaternions; c: ``(B, N, 3)``.

    Returns:
        ``q_mean (B, 4)`` (``w >= 0``), ``c_mean (B, 3)``.
    """
    with torch.no_grad():
        M = torch.einsum("bni,bnj->bij", q, q)
        ref = torch.linalg.eigh(M)[1][..., -1]  # (B, 4), top eigenvector
    sign = torch.where((q * ref.unsqueeze(1)).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(q.dtype)
    qm = (q * sign).mean(dim=1)
    qm = qm / qm.norm(dim=-1, keepdim=True)
    qm = torch.where(qm[..., :1] < 0, -qm, qm)
    return qm, c.mean(dim=1)


def median_cell_pose(q: Tensor, c: Tensor, iters: int = 5) -> tuple[Tensor, Tensor]:
    """Test-time robust aggregate: geodesic L1 median of rotations, per-component median of centres.

    The rotation starts at the medoid (the cell rotation with the least summed geodesic distance
    to all others; exact when the cells agree) and takes ``iters`` Weiszfeld steps on SO(3)
    (Hartley et al., "L1 rotation averaging").

    Args:
        q: ``(B, N, 4)``; c: ``(B, N, 3)``.

    Returns:
        ``q_med (B, 4)`` (``w >= 0``), ``c_med (B, 3)``.
    """
    dist = rot.quat_angle(q.unsqueeze(2), q.unsqueeze(1))  # (B, N, N)
    idx = dist.sum(-1).argmin(dim=1)  # (B,)
    qm = q[torch.arange(q.shape[0], device=q.device), idx]  # (B, 4)
    for _ in range(iters):
        v = rot.quat_log(rot.quat_mul(rot.quat_conj(qm).unsqueeze(1), q))  # (B, N, 3) tangent at qm
        wgt = 1.0 / v.norm(dim=-1, keepdim=True).clamp_min(1e-9)
        step = (v * wgt).sum(1) / wgt.sum(1)
        qm = rot.quat_mul(qm, axis_angle_to_quaternion(step))
        qm = qm / qm.norm(dim=-1, keepdim=True)
    qm = torch.where(qm[..., :1] < 0, -qm, qm)
    return qm, c.median(dim=1).values


def cell_pose_spread(q: Tensor, c: Tensor, q_ref: Tensor, c_ref: Tensor) -> tuple[Tensor, Tensor]:
    """Median distance of the per-cell poses to their aggregate (the per-image confidence signal).

    Args:
        q: ``(B, N, 4)``, c: ``(B, N, 3)``; q_ref: ``(B, 4)``, c_ref: ``(B, 3)``.

    Returns:
        ``spread_t (B,)`` median centre distance (depth units) and ``spread_r_deg (B,)`` median
        rotation angle (degrees).
    """
    t = (c - c_ref.unsqueeze(1)).norm(dim=-1).median(dim=1).values
    r = rot.quat_angle(q, q_ref.unsqueeze(1)).median(dim=1).values
    return t, torch.rad2deg(r)
