"""View synthesis in torch: the relative pose of two cameras and the warp of one image into the other.

``T_{t->s} = T(P_s)^-1 T(P_t)``; the synthesised target samples ``I_s`` at
``K_s T_{t->s} D_t K_t^-1 p`` (paper Sec. III-B). Which pairs of a triplet are warped is
:mod:`relocdepth.geometry.lcvs`.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from kornia.geometry.conversions import normalize_pixel_coordinates
from torch import Tensor

from relocdepth.geometry.intrinsics import backproject
from relocdepth.geometry.poses import invert_pose

# Points closer than this (in depth units) to the source camera plane are invalid for warping.
MIN_WARP_DEPTH = 1e-3


def relative_pose(T_wc_t: Tensor, T_wc_s: Tensor) -> Tensor:
    """``T_{t->s} = T(P_s)^-1 T(P_t)`` ``(B, 4, 4)``: maps points in camera t to camera s."""
    return invert_pose(T_wc_s) @ T_wc_t


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
    grid, _, valid = _project(depth_t, T_t2s, K_t, K_s)
    warped = F.grid_sample(image_s, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return warped, valid.to(image_s.dtype)


def depth_disagreement(
    depth_t: Tensor, depth_s: Tensor, T_t2s: Tensor, K_t: Tensor, K_s: Tensor
) -> tuple[Tensor, Tensor]:
    """How far the target's depth, carried into the source camera, is from the source's own depth.

    Each target pixel's point ``T_{t->s} D_t K_t^-1 p`` lands at depth ``z`` in front of the source
    camera, where the source's depth map says ``D_s(p')`` (bilinear at its projection ``p'``); the
    disagreement is ``|z - D_s(p')| / (z + D_s(p'))``, in [0, 1) and unchanged by a common scale of
    the two depths and the translation (SC-SfMLearner's geometry consistency, Bian et al. 2019).

    Args:
        depth_t, depth_s: ``(B, 1, H, W)`` target and source depth (same size).
        T_t2s, K_t, K_s: as for :func:`warp`.

    Returns:
        ``disagreement (B, 1, H, W)`` and the ``valid (B, 1, H, W)`` float mask of :func:`warp`
        (0 disagreement where not valid).
    """
    grid, z, valid = _project(depth_t, T_t2s, K_t, K_s)
    d_s = F.grid_sample(depth_s, grid, mode="bilinear", padding_mode="border", align_corners=True)
    z = torch.where(valid, z, d_s.detach())  # invalid: no disagreement, no gradient
    return (z - d_s).abs() / (z + d_s), valid.to(depth_t.dtype)


def _project(depth_t: Tensor, T_t2s: Tensor, K_t: Tensor, K_s: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Target pixels' points in the source camera: ``grid (B, H, W, 2)`` for ``grid_sample``, their
    depth ``z (B, 1, H, W)`` there and ``valid (B, 1, H, W)`` (bool; see :func:`warp`)."""
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
    valid = (inside & in_front.reshape(B, H, W)).unsqueeze(1)
    # kornia maps pixel indices to [-1, 1] with pixel centres at +-1 (align_corners=True).
    return normalize_pixel_coordinates(uv, H, W), z.reshape(B, 1, H, W), valid


def moved_view(
    image: Tensor, depth: Tensor, t: Tensor, K: Tensor, iters: int = 5, tol: float = 0.01
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The view of a camera moved by ``t`` (its centre in the source camera's frame, the orientation
    unchanged), synthesised from the source image and depth: a new view of the same scene.

    Each new pixel ``p'`` looks along ``t + z' K^-1 p'``; its depth ``z'`` is found by fixed-point
    iteration, ``z' = D(p) - t_z`` at the source pixel ``p`` it projects to (starting from
    ``z' = D(p') - t_z``).
    A camera moved back (``t_z < 0``) sees the source's content within a narrower part of its
    image, and points seen only by the new camera (beyond the source image's edge, behind an
    occluding edge) have no value: where the source pixel falls outside the image or the iteration
    has not settled (depth steps), the pixel is not valid.

    Args:
        image: ``(B, C, H, W)`` source image.
        depth: ``(B, 1, H, W)`` source depth (z along the optical axis).
        t: ``(B, 3)`` the new camera's centre in the source camera's frame (same units as depth).
        K: ``(B, 3, 3)`` intrinsics of both cameras.
        iters: fixed-point iterations.
        tol: relative change of ``z'`` in the last iteration under which a pixel counts as settled.

    Returns:
        ``image' (B, C, H, W)`` (bilinear, border padding), ``depth' (B, 1, H, W)`` (z in the new
        camera), ``valid (B, 1, H, W)`` (bool) and ``grid (B, H, W, 2)``: where each new pixel
        samples the source (``grid_sample``'s coordinates, ``align_corners=True``), to carry other
        maps of the source into the new view.
    """
    B, _, H, W = depth.shape
    T = torch.eye(4, dtype=depth.dtype, device=depth.device).repeat(B, 1, 1)
    T[:, :3, 3] = t  # new camera -> source camera: a point X' in the new camera is X' + t
    t_z = t[:, 2].reshape(B, 1, 1, 1)
    z = (depth - t_z).clamp(min=MIN_WARP_DEPTH)
    prev = z
    for _ in range(iters):
        grid, _, _ = _project(z, T, K, K)
        d_src = F.grid_sample(depth, grid, mode="bilinear", padding_mode="border", align_corners=True)
        prev, z = z, (d_src - t_z).clamp(min=MIN_WARP_DEPTH)
    grid, _, inside = _project(z, T, K, K)
    settled = (z - prev).abs() <= tol * z
    warped = F.grid_sample(image, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return warped, z, inside & settled, grid
