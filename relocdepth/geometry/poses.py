"""Camera poses as 4x4 matrices in torch: building, inverting, comparing.

A pose is a world-from-camera matrix ``T_wc (..., 4, 4)`` with OpenCV camera axes (DESIGN.md).
"""

from __future__ import annotations

import torch
from torch import Tensor

from relocdepth.geometry.rotations import quat_to_matrix, so3_exp


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


def pose_errors(T_pred: Tensor, T_gt: Tensor) -> tuple[Tensor, Tensor]:
    """``(translation error, rotation error in degrees)``, each ``(...)``, of poses ``(..., 4, 4)``.

    For tensors inside a training step (the trainer's diagnostics); evaluation uses the numpy
    :func:`relocdepth.eval_geometry.pose_errors`. The angle is ``atan2(sin, cos)`` with the sine
    from the skew part, so it keeps its precision near 0 and 180 degrees.
    """
    R = T_pred[..., :3, :3].transpose(-1, -2) @ T_gt[..., :3, :3]
    cos = (R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0
    skew = torch.stack((R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]), -1)
    sin = skew.norm(dim=-1) / 2.0
    t_err = (T_pred[..., :3, 3] - T_gt[..., :3, 3]).norm(dim=-1)
    return t_err, torch.rad2deg(torch.atan2(sin, cos))
