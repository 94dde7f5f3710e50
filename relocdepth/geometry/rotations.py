"""Rotations on SO(3) in torch: axis-angle, quaternions ``(w, x, y, z)``, the log map, angles.

kornia does the axis-angle <-> quaternion/matrix conversions. Written here because kornia lacks
them or their gradients are not safe where the method needs them: the quaternion log map
(kornia's ``quaternion_to_axis_angle`` divides ``atan2(s, w)`` by ``s``, whose gradient loses all
precision for ``s -> 0``; ours has a series branch and is finite at 0 and pi), the geodesic angle,
and the minimal rotation taking ``e_z`` to a ray (``R_p`` of paper Sec. III-A).
"""

from __future__ import annotations

import torch
from kornia.geometry.conversions import (
    axis_angle_to_rotation_matrix,
    quaternion_to_rotation_matrix,
    rotation_matrix_to_quaternion,
)
from torch import Tensor

# Below this |v| of a unit quaternion the log map uses its series expansion.
_LOG_SERIES_EPS = 1e-6


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
