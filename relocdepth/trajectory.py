"""Pose I/O in numpy: quaternions, TUM trajectory files, Sim(3) alignment dicts.

TUM format (what ``evo`` reads): one line per pose, ``timestamp tx ty tz qx qy qz qw``, the
pose being world-from-camera (camera centre and orientation in the world), quaternion
Hamilton, scalar last.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from relocdepth.errors import UserError
from relocdepth.fileio import write_text_atomic
from relocdepth.metrics import apply_sim3, project_to_so3


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations -> (..., 4) unit quaternions (qx, qy, qz, qw), qw >= 0.

    Shepperd's method: picks the numerically largest component, so it is stable near 180 deg.
    """
    R = np.asarray(R, np.float64)
    flat = R.reshape(-1, 3, 3)
    q = np.empty((flat.shape[0], 4))
    for n, m in enumerate(flat):
        tr = np.trace(m)
        cand = np.array([m[0, 0], m[1, 1], m[2, 2], tr])
        i = int(np.argmax(cand))
        if i == 3:
            s = 2.0 * np.sqrt(max(1.0 + tr, 0.0))
            q[n] = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
        else:
            j, k = (i + 1) % 3, (i + 2) % 3
            s = 2.0 * np.sqrt(max(1.0 + m[i, i] - m[j, j] - m[k, k], 0.0))
            v = np.empty(4)
            v[i] = s / 4
            v[j] = (m[j, i] + m[i, j]) / s
            v[k] = (m[k, i] + m[i, k]) / s
            v[3] = (m[k, j] - m[j, k]) / s
            q[n] = v
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    q[q[:, 3] < 0] *= -1.0
    return q.reshape(R.shape[:-2] + (4,))


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions (qx, qy, qz, qw), any norm -> (..., 3, 3) rotations."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def tum_lines(timestamps: Sequence[float], T_wc: np.ndarray) -> list[str]:
    """TUM lines ``timestamp tx ty tz qx qy qz qw`` for (N, 4, 4) world-from-camera poses."""
    T_wc = np.asarray(T_wc, np.float64)
    q = rotmat_to_quat(T_wc[:, :3, :3])
    return [
        f"{float(ts):.6f} " + " ".join(f"{v:.9g}" for v in (*T[:3, 3], *qq))
        for ts, T, qq in zip(timestamps, T_wc, q)
    ]


def write_tum(path: str | Path, timestamps: Sequence[float], T_wc: np.ndarray) -> None:
    """Write a TUM trajectory file (atomically)."""
    write_text_atomic(path, "".join(line + "\n" for line in tum_lines(timestamps, T_wc)))


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM file -> (timestamps (N,), T_wc (N, 4, 4)); '#' lines are comments."""
    rows = []
    for n, line in enumerate(Path(path).read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 8:
            raise UserError(f"{path}:{n}: a TUM line has 8 numbers, found {len(parts)}")
        rows.append([float(p) for p in parts])
    data = np.array(rows, dtype=np.float64).reshape(-1, 8)
    T = np.tile(np.eye(4), (len(data), 1, 1))
    T[:, :3, 3] = data[:, 1:4]
    if len(data):
        T[:, :3, :3] = quat_to_rotmat(data[:, 4:8])
    return data[:, 0], T


# ----------------------------------------------------------------------------- Sim(3) dicts


def sim3_to_dict(scale: float, R: np.ndarray, t: np.ndarray, **extra) -> dict:
    """A JSON-friendly Sim(3) ``x -> s R x + t`` (world of the predictions -> ground-truth frame)."""
    return {
        "scale": float(scale),
        "rotation": np.asarray(R, np.float64).tolist(),
        "translation": np.asarray(t, np.float64).reshape(3).tolist(),
        **extra,
    }


def sim3_from_dict(d: dict) -> tuple[float, np.ndarray, np.ndarray]:
    """(scale, R (3, 3), t (3,)) from :func:`sim3_to_dict`'s dict; R re-orthonormalised."""
    try:
        s = float(d["scale"])
        R = project_to_so3(np.asarray(d["rotation"], np.float64).reshape(3, 3))
        t = np.asarray(d["translation"], np.float64).reshape(3)
    except (KeyError, TypeError, ValueError) as e:
        raise UserError(f"the stored alignment is malformed ({e}); re-run reloc evaluate --save-alignment")
    if not np.isfinite(s) or s <= 0 or not np.all(np.isfinite(t)):
        raise UserError("the stored alignment has a non-positive or non-finite scale")
    return s, R, t


def apply_sim3_dict(d: dict, T_wc: np.ndarray) -> np.ndarray:
    """Apply a stored alignment to (N, 4, 4) poses."""
    s, R, t = sim3_from_dict(d)
    return apply_sim3(s, R, t, T_wc)
