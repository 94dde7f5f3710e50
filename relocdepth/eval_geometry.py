"""Evaluation geometry in numpy: Sim(3) alignment, pose errors, rotation means, quaternions.

Poses are ``(N, 4, 4)`` world-from-camera matrices (OpenCV axes), float64. This is the geometry
of the paper's protocol (Sec. IV: a Sim(3) fitted with Umeyama's method on the training frames'
camera centres, then position/attitude errors) and of the trajectory files (TUM quaternions).
The training geometry, in torch with gradients, is :mod:`relocdepth.geometry`.

Quaternions are Hamilton; the component order is in every name: ``_wxyz`` (scalar first, as
kornia and :mod:`relocdepth.geometry`) or ``_xyzw`` (scalar last, as TUM files and ``evo``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Umeyama needs three positions, not on one line, to fix a rotation.
MIN_ALIGN_POSES = 3
# A point set whose second-largest spread (std along its second principal axis) is below this
# fraction of its largest is treated as collinear: the rotation about the line is then fixed by
# noise alone. The cross-covariance's second singular value is held to the square of it (it is a
# product of two spreads).
COLLINEAR_RATIO = 1e-2
# Positions whose RMS spread is below this fraction of their magnitude coincide to float32
# precision (a collapsed prediction): the fitted scale is then meaningless.
COINCIDENT_RTOL = 1e-6

__all__ = [
    "COINCIDENT_RTOL",
    "COLLINEAR_RATIO",
    "MIN_ALIGN_POSES",
    "Sim3",
    "apply_sim3",
    "chordal_mean_rotation",
    "mean_pose",
    "pose_errors",
    "pose_spread",
    "poses_from_tum_rows",
    "poses_to_tum_rows",
    "project_to_so3",
    "quat_wxyz_to_rotmat",
    "quat_wxyz_to_xyzw",
    "quat_xyzw_to_wxyz",
    "rotation_alignment",
    "rotation_angle_deg",
    "rotation_only_errors",
    "rotmat_to_quat_wxyz",
    "umeyama",
]


# ----------------------------------------------------------------------------- rotations


def rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    """Rotation angle in degrees, in [0, 180], of ``(..., 3, 3)`` rotation matrices.

    ``atan2(sin, cos)`` with the sine from the skew part and the cosine from the trace: precise
    near 0 (where ``acos`` of the trace loses half the digits) and near 180 degrees.
    """
    R = np.asarray(R, np.float64)
    cos = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    skew = np.stack(
        (R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]), -1
    )
    return np.degrees(np.arctan2(np.linalg.norm(skew, axis=-1) / 2.0, cos))


def project_to_so3(M: np.ndarray) -> np.ndarray:
    """The rotation nearest (Frobenius) to a (3, 3) matrix, via SVD with the det-1 fix."""
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    return U @ D @ Vt


def chordal_mean_rotation(R: np.ndarray) -> np.ndarray:
    """Chordal L2 mean of (N, 3, 3) rotations (a true rotation mean, unlike averaging angles)."""
    return project_to_so3(np.asarray(R, dtype=np.float64).sum(axis=0))


# ----------------------------------------------------------------------------- quaternions


def rotmat_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """``(..., 3, 3)`` rotations -> ``(..., 4)`` unit quaternions ``(w, x, y, z)`` with ``w >= 0``.

    Shepperd's method, vectorised: the entries of ``4 q q^T`` are linear in ``R``; the row of its
    largest diagonal entry (at least 1, since the diagonal sums to 4) divided by twice that
    entry's square root is ``q``, so no division is ever by a small number, also near 180 deg.
    """
    R = np.asarray(R, np.float64)
    m = R.reshape(-1, 3, 3)
    m00, m01, m02 = m[:, 0, 0], m[:, 0, 1], m[:, 0, 2]
    m10, m11, m12 = m[:, 1, 0], m[:, 1, 1], m[:, 1, 2]
    m20, m21, m22 = m[:, 2, 0], m[:, 2, 1], m[:, 2, 2]
    # 4 q q^T for q = (w, x, y, z)
    outer = np.stack(
        [
            np.stack([1 + m00 + m11 + m22, m21 - m12, m02 - m20, m10 - m01], -1),
            np.stack([m21 - m12, 1 + m00 - m11 - m22, m01 + m10, m02 + m20], -1),
            np.stack([m02 - m20, m01 + m10, 1 - m00 + m11 - m22, m12 + m21], -1),
            np.stack([m10 - m01, m02 + m20, m12 + m21, 1 - m00 - m11 + m22], -1),
        ],
        -2,
    )
    i = np.argmax(np.diagonal(outer, axis1=-2, axis2=-1), axis=-1)
    rows = outer[np.arange(len(m)), i]  # (N, 4) = 4 q_i q
    q = rows / (2.0 * np.sqrt(rows[np.arange(len(m)), i]))[:, None]
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    q[q[:, 0] < 0] *= -1.0
    return q.reshape(R.shape[:-2] + (4,))


def quat_wxyz_to_rotmat(q: np.ndarray) -> np.ndarray:
    """``(..., 4)`` quaternions ``(w, x, y, z)``, any norm -> ``(..., 3, 3)`` rotations."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def quat_wxyz_to_xyzw(q: np.ndarray) -> np.ndarray:
    """Reorder ``(..., 4)`` quaternions from scalar-first to scalar-last."""
    return np.roll(np.asarray(q, np.float64), -1, axis=-1)


def quat_xyzw_to_wxyz(q: np.ndarray) -> np.ndarray:
    """Reorder ``(..., 4)`` quaternions from scalar-last to scalar-first."""
    return np.roll(np.asarray(q, np.float64), 1, axis=-1)


def poses_to_tum_rows(T_wc: np.ndarray) -> np.ndarray:
    """``(N, 4, 4)`` world-from-camera poses -> ``(N, 7)`` TUM rows ``tx ty tz qx qy qz qw``."""
    T_wc = np.asarray(T_wc, np.float64)
    q = quat_wxyz_to_xyzw(rotmat_to_quat_wxyz(T_wc[:, :3, :3]))
    return np.concatenate((T_wc[:, :3, 3], q), axis=-1)


def poses_from_tum_rows(rows: np.ndarray) -> np.ndarray:
    """``(N, 7)`` TUM rows ``tx ty tz qx qy qz qw`` (quaternion of any norm) -> ``(N, 4, 4)``."""
    rows = np.asarray(rows, np.float64).reshape(-1, 7)
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    T[:, :3, 3] = rows[:, :3]
    if len(rows):
        T[:, :3, :3] = quat_wxyz_to_rotmat(quat_xyzw_to_wxyz(rows[:, 3:]))
    return T


# ----------------------------------------------------------------------------- alignment


@dataclass(frozen=True)
class Sim3:
    """A similarity ``x -> scale R x + t`` fitted by :func:`umeyama`.

    ``degenerate`` says why the fit is not determined by the data (too few points, coincident
    or collinear points, a rank-deficient cross-covariance), or is None for a sound fit.
    """

    scale: float
    R: np.ndarray
    t: np.ndarray
    degenerate: str | None = None


def _spread_problem(x: np.ndarray, name: str) -> str | None:
    """Why the centred points ``x (N, 3)`` cannot fix a rotation, or None."""
    centred = x - x.mean(0)
    rms = float(np.sqrt(np.mean(np.sum(centred * centred, axis=-1))))
    if rms <= COINCIDENT_RTOL * (rms + float(np.linalg.norm(x.mean(0)))):
        return f"the {name} positions coincide (RMS spread {rms:.3g})"
    var = np.linalg.eigvalsh(centred.T @ centred / len(x))[::-1]  # descending
    if var[1] <= COLLINEAR_RATIO**2 * var[0]:
        ratio = np.sqrt(max(var[1], 0.0) / var[0])
        return (f"the {name} positions are collinear (spread across their line {ratio:.2g} of "
                "the spread along it): the rotation about that line is undetermined")
    return None


def umeyama(
    src: np.ndarray, dst: np.ndarray, with_scale: bool = True,
    names: tuple[str, str] = ("source", "target"),
) -> Sim3:
    """Least-squares similarity ``dst ~ s R src + t`` (Umeyama 1991), with a degeneracy check.

    Args:
        src, dst: ``(N, 3)`` corresponding points (N >= 1).
        with_scale: estimate ``s`` (Sim(3)); else ``s = 1`` (SE(3)).
        names: what ``src`` and ``dst`` are, for the ``degenerate`` message.

    Returns:
        The :class:`Sim3`; its ``degenerate`` is set when fewer than 3 points are given, when
        either point set coincides or is collinear, or when the cross-covariance has rank < 2
        (Umeyama's condition for a unique rotation; coplanar points are fine). The fit is
        returned all the same (the least-squares solution, one of many when degenerate).

    Example:
        >>> fit = umeyama(pred_centres, gt_centres)
        >>> aligned = fit.scale * pred_centres @ fit.R.T + fit.t
    """
    x, y = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    if x.ndim != 2 or x.shape[-1] != 3 or x.shape != y.shape or len(x) == 0:
        raise ValueError(f"umeyama needs two (N>=1, 3) arrays, got {x.shape} and {y.shape}")
    n = len(x)
    mx, my = x.mean(0), y.mean(0)
    xc, yc = x - mx, y - my
    cov = yc.T @ xc / n
    U, S, Vh = np.linalg.svd(cov)
    D = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vh) < 0:
        D[2] = -1.0
    R = U @ np.diag(D) @ Vh
    var_x = float(np.sum(xc * xc) / n)
    s = float(np.sum(S * D) / var_x) if with_scale and var_x > 0 else 1.0
    t = my - s * R @ mx

    problem = None
    if n < MIN_ALIGN_POSES:
        problem = f"{n} positions; the alignment needs at least {MIN_ALIGN_POSES} not on one line"
    problem = problem or _spread_problem(x, names[0]) or _spread_problem(y, names[1])
    if problem is None and S[1] <= COLLINEAR_RATIO**2 * S[0]:
        problem = "the cross-covariance of the positions has rank < 2: the rotation is undetermined"
    return Sim3(s, R, t, problem)


def apply_sim3(scale: float, R: np.ndarray, t: np.ndarray, T_wc: np.ndarray) -> np.ndarray:
    """Map (N, 4, 4) poses through x -> s R x + t: rotation R R_wc, centre s R c + t (rigid)."""
    T = np.array(T_wc, dtype=np.float64, copy=True)
    T[..., :3, :3] = R @ T[..., :3, :3]
    T[..., :3, 3] = scale * T[..., :3, 3] @ np.asarray(R).T + np.asarray(t)
    return T


def rotation_alignment(R_est: np.ndarray, R_gt: np.ndarray) -> np.ndarray:
    """The rotation A minimising sum ||A R_est_i - R_gt_i||_F (fitted on rotations only).

    Unlike the Sim(3) fitted on camera centres, it stays meaningful when the predicted centres
    collapse to a point (DESIGN.md Pitfalls).
    """
    return project_to_so3(np.einsum("nij,nkj->ik", R_gt, R_est))


# ----------------------------------------------------------------------------- errors, spreads


def pose_errors(T_est: np.ndarray, T_gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame translation error (distance of camera centres) and rotation error (deg).

    T_est, T_gt: (N, 4, 4) world-from-camera. Returns (t_err (N,), r_err_deg (N,)).
    """
    T_est, T_gt = np.asarray(T_est, np.float64), np.asarray(T_gt, np.float64)
    if T_est.shape != T_gt.shape or T_est.shape[-2:] != (4, 4):
        raise ValueError(f"pose_errors: shapes {T_est.shape} vs {T_gt.shape}, want (N, 4, 4)")
    t_err = np.linalg.norm(T_est[:, :3, 3] - T_gt[:, :3, 3], axis=-1)
    R_rel = np.swapaxes(T_est[:, :3, :3], -1, -2) @ T_gt[:, :3, :3]
    return t_err, rotation_angle_deg(R_rel)


def rotation_only_errors(
    R_est_fit: np.ndarray, R_gt_fit: np.ndarray, R_est: np.ndarray, R_gt: np.ndarray
) -> np.ndarray:
    """Rotation errors (deg) of R_est after the rotation-only alignment fitted on (fit) frames."""
    A = rotation_alignment(R_est_fit, R_gt_fit)
    return rotation_angle_deg(np.swapaxes(A @ R_est, -1, -2) @ R_gt)


def mean_pose(T: np.ndarray) -> np.ndarray:
    """The mean pose of (N, 4, 4) poses: mean centre, chordal mean rotation."""
    T = np.asarray(T, np.float64)
    out = np.eye(4)
    out[:3, :3] = chordal_mean_rotation(T[:, :3, :3])
    out[:3, 3] = T[:, :3, 3].mean(axis=0)
    return out


def pose_spread(T: np.ndarray) -> dict:
    """How spread out a set of poses is: RMS distance of centres from their mean (units of T)
    and the median angle (deg) of rotations from their chordal mean."""
    T = np.asarray(T, np.float64)
    c = T[:, :3, 3]
    mean_R = chordal_mean_rotation(T[:, :3, :3])
    return {
        "centre_rms": float(np.sqrt(np.mean(np.sum((c - c.mean(0)) ** 2, axis=-1)))),
        "rot_median_deg": float(np.median(rotation_angle_deg(mean_R.T @ T[:, :3, :3]))),
    }
