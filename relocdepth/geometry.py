"""Geometry of the method: directed scene coordinates (DSC) + depth -> camera pose, view synthesis.

Conventions (DESIGN.md): a pose is a 4x4 world-from-camera matrix ``T_wc`` with OpenCV camera axes
(x right, y down, z forward); pixel centres sit at integer coordinates; quaternions are
``(w, x, y, z)`` as in kornia. All functions are pure, batched, and follow the device and dtype of
their inputs.

Per DSC cell ``p`` (centre pixel ``u = 32 i + 15.5``, ``v = 32 j + 15.5``) with the depth ``D(p)``
average-pooled over the cell's 32x32 block:

- ``ray = K^-1 [u, v, 1]``, ``|Q| = D(p) |ray|`` (distance along the ray, not the depth value);
- ``R_p`` = the minimal rotation taking ``e_z`` to ``ray / |ray|``;
- the DSC ``S(p) = [theta, tau]``: ``G = R(theta)`` maps ``e_z`` to the pixel's ray in the world,
  ``tau`` is the scene point hit by that ray;
- camera of the cell: ``R_wc(p) = G R_p^T`` and centre ``c(p) = tau - |Q| G e_z``.

kornia does the axis-angle <-> quaternion/matrix conversions and pixel-coordinate normalisation.
Written here because kornia lacks them or their gradients are not safe where we need them:
the quaternion log map (kornia's ``quaternion_to_axis_angle`` divides ``atan2(s, w)`` by ``s``, whose
gradient loses all precision for ``s -> 0``; ours has a series branch and is finite at 0 and pi),
rotation averaging (mean and robust median on SO(3)), and Umeyama's Sim(3) alignment.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from kornia.geometry.conversions import (
    axis_angle_to_quaternion,
    axis_angle_to_rotation_matrix,
    normalize_pixel_coordinates,
    quaternion_to_rotation_matrix,
    rotation_matrix_to_quaternion,
)
from torch import Tensor

# The DSC network outputs one cell per 32x32 block of the input image (ResNet18 at 1/32 scale).
DSC_STRIDE = 32
# Points closer than this (in depth units) to the source camera plane are invalid for warping.
MIN_WARP_DEPTH = 1e-3
# Below this |v| of a unit quaternion the log map uses its series expansion.
_LOG_SERIES_EPS = 1e-6

__all__ = [
    "DSC_STRIDE",
    "apply_sim3",
    "backproject",
    "cell_poses",
    "cell_rays",
    "check_image_size",
    "dsc_cell_centres",
    "dsc_from_pose",
    "dsc_grid_size",
    "invert_pose",
    "mean_pose",
    "median_pose",
    "minimal_rotation_quat",
    "pool_depth",
    "pose_errors",
    "pose_matrix",
    "pose_spread",
    "pose_vector_to_matrix",
    "quat_angle",
    "quat_conj",
    "quat_from_matrix",
    "quat_log",
    "quat_mul",
    "quat_to_matrix",
    "relative_pose",
    "rotation_error_deg",
    "scale_intrinsics",
    "so3_exp",
    "so3_log",
    "translation_error",
    "umeyama",
    "warp",
]


# --------------------------------------------------------------------------------------------
# rotations


def so3_exp(rotvec: Tensor) -> Tensor:
    """Axis-angle ``(..., 3)`` -> rotation matrix ``(..., 3, 3)`` (kornia; safe gradient at 0)."""
    return axis_angle_to_rotation_matrix(rotvec)


def quat_mul(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product ``a * b`` of quaternions ``(..., 4)`` (w, x, y, z); broadcasts."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        dim=-1,
    )


def quat_conj(q: Tensor) -> Tensor:
    """Conjugate (= inverse for unit quaternions) of ``(..., 4)``."""
    return torch.cat((q[..., :1], -q[..., 1:]), dim=-1)


def quat_to_matrix(q: Tensor) -> Tensor:
    """Unit quaternion ``(..., 4)`` -> rotation matrix ``(..., 3, 3)`` (kornia)."""
    return quaternion_to_rotation_matrix(q)


def quat_from_matrix(R: Tensor) -> Tensor:
    """Rotation matrix ``(..., 3, 3)`` -> unit quaternion ``(..., 4)`` with ``w >= 0``.

    kornia's conversion (exact branches, no eps bias), renormalised and sign-canonicalised.
    Not used on the training path (its branch switches make gradients piecewise).
    """
    q = rotation_matrix_to_quaternion(R.contiguous())
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def quat_log(q: Tensor) -> Tensor:
    """Log map of a unit quaternion ``(..., 4)`` -> rotation vector ``(..., 3)``, angle in [0, pi].

    ``q`` and ``-q`` give the same result. The gradient is finite at the identity (series branch
    for ``|v| -> 0``) and at pi (``w -> 0`` needs no special case for ``atan2``).
    """
    q = torch.where(q[..., :1] < 0, -q, q)
    w, v = q[..., 0], q[..., 1:]
    s2 = (v * v).sum(-1)
    small = s2 < _LOG_SERIES_EPS**2
    s = torch.sqrt(torch.where(small, torch.ones_like(s2), s2))
    # 2 atan2(s, w) / s, and its series 2/w (1 - s^2 / (3 w^2)) near s = 0 (w ~ 1 there).
    w_safe = torch.where(small, w, torch.ones_like(w))
    k_big = 2.0 * torch.atan2(s, w) / s
    k_small = 2.0 / w_safe * (1.0 - s2 / (3.0 * w_safe * w_safe))
    k = torch.where(small, k_small, k_big)
    return v * k.unsqueeze(-1)


def so3_log(R: Tensor) -> Tensor:
    """Rotation matrix ``(..., 3, 3)`` -> rotation vector ``(..., 3)`` (angle in [0, pi])."""
    return quat_log(quat_from_matrix(R))


def quat_angle(qa: Tensor, qb: Tensor) -> Tensor:
    """Geodesic angle (radians, in [0, pi]) between unit quaternions ``(..., 4)``; broadcasts."""
    rel = quat_mul(quat_conj(qa), qb)
    return 2.0 * torch.atan2(rel[..., 1:].norm(dim=-1), rel[..., 0].abs())


def minimal_rotation_quat(r: Tensor) -> Tensor:
    """Quaternion ``(..., 4)`` of the minimal rotation taking ``e_z`` to the unit vector ``r (..., 3)``.

    ``q = normalize([1 + e_z.r, e_z x r])``; smooth for every ``r`` except ``-e_z`` (a ray behind
    the camera, which cannot occur for pixels).
    """
    x, y, z = r.unbind(-1)
    q = torch.stack((1.0 + z, -y, x, torch.zeros_like(z)), dim=-1)
    return q / q.norm(dim=-1, keepdim=True)


# --------------------------------------------------------------------------------------------
# intrinsics, image grid, back-projection


def scale_intrinsics(K: Tensor, sx: float, sy: float) -> Tensor:
    """Camera matrices ``(..., 3, 3)`` after resizing by ``(sx, sy)`` (half-pixel convention:
    ``cx' = (cx + 0.5) sx - 0.5``, as :func:`relocdepth.camera.scale_K`)."""
    K = K.clone()
    K[..., 0, 0] = K[..., 0, 0] * sx
    K[..., 1, 1] = K[..., 1, 1] * sy
    K[..., 0, 2] = (K[..., 0, 2] + 0.5) * sx - 0.5
    K[..., 1, 2] = (K[..., 1, 2] + 0.5) * sy - 0.5
    return K


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
    q_p = minimal_rotation_quat(ray / ray_len)
    q_g = axis_angle_to_quaternion(theta)
    q_wc = quat_mul(q_g, quat_conj(q_p))
    g_ez = quat_to_matrix(q_g)[..., :, 2]  # G e_z: the ray in the world
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
    q_p = minimal_rotation_quat(ray / ray_len)
    q_wc = quat_from_matrix(T_wc[:, :3, :3]).unsqueeze(1)  # (B, 1, 4)
    q_g = quat_mul(q_wc, q_p)  # G = R_wc R_p
    theta = quat_log(q_g)
    dist = depth_cells.flatten(2).transpose(1, 2) * ray_len
    tau = T_wc[:, None, :3, 3] + dist * quat_to_matrix(q_g)[..., :, 2]
    return torch.cat((theta, tau), dim=-1).transpose(1, 2).reshape(B, 6, h, w)


# --------------------------------------------------------------------------------------------
# aggregation of per-cell poses


def mean_pose(q: Tensor, c: Tensor) -> tuple[Tensor, Tensor]:
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


def median_pose(q: Tensor, c: Tensor, iters: int = 5) -> tuple[Tensor, Tensor]:
    """Test-time robust aggregate: geodesic L1 median of rotations, per-component median of centres.

    The rotation starts at the medoid (the cell rotation with the least summed geodesic distance
    to all others; exact when the cells agree) and takes ``iters`` Weiszfeld steps on SO(3)
    (Hartley et al., "L1 rotation averaging"). A per-component median of axis-angle vectors
    would be no rotation median and breaks near pi (DESIGN.md, pitfalls).

    Args:
        q: ``(B, N, 4)``; c: ``(B, N, 3)``.

    Returns:
        ``q_med (B, 4)`` (``w >= 0``), ``c_med (B, 3)``.
    """
    dist = quat_angle(q.unsqueeze(2), q.unsqueeze(1))  # (B, N, N)
    idx = dist.sum(-1).argmin(dim=1)  # (B,)
    qm = q[torch.arange(q.shape[0], device=q.device), idx]  # (B, 4)
    for _ in range(iters):
        v = quat_log(quat_mul(quat_conj(qm).unsqueeze(1), q))  # (B, N, 3) tangent at qm
        wgt = 1.0 / v.norm(dim=-1, keepdim=True).clamp_min(1e-9)
        step = (v * wgt).sum(1) / wgt.sum(1)
        qm = quat_mul(qm, axis_angle_to_quaternion(step))
        qm = qm / qm.norm(dim=-1, keepdim=True)
    qm = torch.where(qm[..., :1] < 0, -qm, qm)
    return qm, c.median(dim=1).values


def pose_spread(q: Tensor, c: Tensor, q_ref: Tensor, c_ref: Tensor) -> tuple[Tensor, Tensor]:
    """Median distance of the per-cell poses to their aggregate (the per-image confidence signal).

    Args:
        q: ``(B, N, 4)``, c: ``(B, N, 3)``; q_ref: ``(B, 4)``, c_ref: ``(B, 3)``.

    Returns:
        ``spread_t (B,)`` median centre distance (depth units) and ``spread_r_deg (B,)`` median
        rotation angle (degrees).
    """
    t = (c - c_ref.unsqueeze(1)).norm(dim=-1).median(dim=1).values
    r = quat_angle(q, q_ref.unsqueeze(1)).median(dim=1).values
    return t, torch.rad2deg(r)


# --------------------------------------------------------------------------------------------
# poses as matrices


def pose_matrix(q: Tensor, c: Tensor) -> Tensor:
    """``T_wc (..., 4, 4)`` from rotation quaternion ``(..., 4)`` and camera centre ``(..., 3)``."""
    T = torch.zeros(*q.shape[:-1], 4, 4, device=q.device, dtype=q.dtype)
    T[..., :3, :3] = quat_to_matrix(q)
    T[..., :3, 3] = c
    T[..., 3, 3] = 1.0
    return T


def pose_vector_to_matrix(p: Tensor) -> Tensor:
    """``[axis-angle, centre] (..., 6)`` -> ``T_wc (..., 4, 4)``."""
    T = torch.zeros(*p.shape[:-1], 4, 4, device=p.device, dtype=p.dtype)
    T[..., :3, :3] = so3_exp(p[..., :3])
    T[..., :3, 3] = p[..., 3:]
    T[..., 3, 3] = 1.0
    return T


def invert_pose(T: Tensor) -> Tensor:
    """Inverse of rigid transforms ``(..., 4, 4)`` (``[R^T, -R^T t]``)."""
    R, t = T[..., :3, :3], T[..., :3, 3:]
    Rt = R.transpose(-1, -2)
    out = torch.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3:] = -Rt @ t
    out[..., 3, 3] = 1.0
    return out


def relative_pose(T_wc_t: Tensor, T_wc_s: Tensor) -> Tensor:
    """``T_{t->s} = T(P_s)^-1 T(P_t)`` ``(B, 4, 4)``: maps points in camera t to camera s."""
    return invert_pose(T_wc_s) @ T_wc_t


# --------------------------------------------------------------------------------------------
# view synthesis


def warp(
    image_s: Tensor, depth_t: Tensor, T_t2s: Tensor, K_t: Tensor, K_s: Tensor
) -> tuple[Tensor, Tensor]:
    """Synthesise the target view from the source: sample ``I_s`` at ``K_s T_{t->s} D_t K_t^-1 p``.

    Args:
        image_s: ``(B, C, H, W)`` source image.
        depth_t: ``(B, 1, H, W)`` target depth (same size).
        T_t2s: ``(B, 4, 4)`` target-to-source transform (:func:`relative_pose`).
        K_t, K_s: ``(B, 3, 3)`` intrinsics of target and source at ``H x W``.

    Returns:
        ``warped (B, C, H, W)`` (bilinear, border padding) and ``valid (B, 1, H, W)`` float mask:
        the point lies in front of the source camera and projects inside the source image.

    Example:
        >>> T_ts = relative_pose(T_wc_t, T_wc_s)
        >>> I_hat, valid = warp(I_s, D_t, T_ts, K_t, K_s)
    """
    B, _, H, W = depth_t.shape
    pts = backproject(depth_t, K_t).reshape(B, 3, -1)
    pts_s = T_t2s[:, :3, :3] @ pts + T_t2s[:, :3, 3:]
    z = pts_s[:, 2:3]
    in_front = z > MIN_WARP_DEPTH
    proj = K_s @ pts_s
    uv = proj[:, :2] / torch.where(in_front, z, torch.ones_like(z))  # (B, 2, HW)
    uv = uv.transpose(1, 2).reshape(B, H, W, 2)
    # in image = inside its continuous extent [-0.5, W - 0.5] (pixel centres at integers); the
    # half-pixel rim samples the border pixel, and an identity warp stays valid despite roundoff
    u, v = uv[..., 0], uv[..., 1]
    inside = (u >= -0.5) & (u <= W - 0.5) & (v >= -0.5) & (v <= H - 0.5)
    valid = (inside & in_front.reshape(B, H, W)).unsqueeze(1).to(image_s.dtype)
    # kornia maps pixel indices to [-1, 1] with pixel centres at +-1 (align_corners=True).
    grid = normalize_pixel_coordinates(uv, H, W)
    warped = F.grid_sample(image_s, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return warped, valid


# --------------------------------------------------------------------------------------------
# alignment and errors (evaluation)


def _as_tensor(x: Tensor | np.ndarray) -> Tensor:
    return x if isinstance(x, Tensor) else torch.as_tensor(np.asarray(x, dtype=np.float64))


def umeyama(
    src: Tensor | np.ndarray, dst: Tensor | np.ndarray, with_scale: bool = True
) -> tuple[float, Tensor, Tensor]:
    """Least-squares similarity ``dst ~ s R src + t`` (Umeyama 1991).

    Args:
        src, dst: ``(N, 3)`` corresponding points (N >= 3, not collinear); numpy or torch.
        with_scale: estimate ``s`` (else ``s = 1``).

    Returns:
        ``(s, R (3, 3), t (3,))``, float64 tensors (``s`` a Python float).

    Example:
        >>> s, R, t = umeyama(pred_centres, gt_centres)
        >>> aligned = s * pred_centres @ R.T + t
    """
    x, y = _as_tensor(src).double(), _as_tensor(dst).double()
    if x.ndim != 2 or x.shape[-1] != 3 or x.shape != y.shape or x.shape[0] < 3:
        raise ValueError(f"umeyama needs two (N>=3, 3) arrays, got {tuple(x.shape)} and {tuple(y.shape)}")
    mx, my = x.mean(0), y.mean(0)
    xc, yc = x - mx, y - my
    cov = yc.T @ xc / x.shape[0]
    U, S, Vh = torch.linalg.svd(cov)
    D = torch.ones(3, dtype=x.dtype, device=x.device)
    if torch.det(U) * torch.det(Vh) < 0:
        D[2] = -1.0
    R = U @ torch.diag(D) @ Vh
    var_x = (xc * xc).sum() / x.shape[0]
    s = float((S * D).sum() / var_x) if with_scale and var_x > 0 else 1.0
    t = my - s * R @ mx
    return s, R, t


def apply_sim3(s: float, R: Tensor, t: Tensor, T_wc: Tensor) -> Tensor:
    """Map poses ``T_wc (..., 4, 4)`` by the similarity ``x -> s R x + t``: centres ``s R c + t``,
    rotations ``R R_wc`` (scale leaves rotations alone)."""
    R = R.to(T_wc)
    out = T_wc.clone()
    out[..., :3, :3] = R @ T_wc[..., :3, :3]
    out[..., :3, 3] = s * T_wc[..., :3, 3] @ R.T + t.to(T_wc)
    return out


def rotation_error_deg(R_a: Tensor, R_b: Tensor) -> Tensor:
    """Geodesic angle (degrees) between rotations ``(..., 3, 3)``; numerically safe near 0 and 180."""
    R = R_a.transpose(-1, -2) @ R_b
    cos = (R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0
    # sin from the skew part keeps precision at small angles where acos(cos) loses it
    skew = torch.stack((R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]), -1)
    sin = skew.norm(dim=-1) / 2.0
    return torch.rad2deg(torch.atan2(sin, cos))


def translation_error(t_a: Tensor, t_b: Tensor) -> Tensor:
    """Euclidean distance between positions ``(..., 3)``."""
    return (t_a - t_b).norm(dim=-1)


def pose_errors(T_pred: Tensor, T_gt: Tensor) -> tuple[Tensor, Tensor]:
    """``(translation error, rotation error in degrees)``, each ``(...)``, of poses ``(..., 4, 4)``."""
    return (
        translation_error(T_pred[..., :3, 3], T_gt[..., :3, 3]),
        rotation_error_deg(T_pred[..., :3, :3], T_gt[..., :3, :3]),
    )
