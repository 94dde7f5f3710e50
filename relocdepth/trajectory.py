"""Pose I/O in numpy: TUM trajectory files, Sim(3) alignment dicts.

TUM format (what ``evo`` reads): one line per pose, ``timestamp tx ty tz qx qy qz qw``, the
pose being world-from-camera (camera centre and orientation in the world), quaternion
Hamilton, scalar last.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from relocdepth.errors import UserError
from relocdepth.eval_geometry import (
    apply_sim3,
    poses_from_tum_rows,
    poses_to_tum_rows,
    project_to_so3,
)
from relocdepth.fileio import write_text_atomic


def tum_lines(timestamps: Sequence[float], T_wc: np.ndarray) -> list[str]:
    """TUM lines ``timestamp tx ty tz qx qy qz qw`` for (N, 4, 4) world-from-camera poses."""
    return [
        f"{float(ts):.6f} " + " ".join(f"{v:.9g}" for v in row)
        for ts, row in zip(timestamps, poses_to_tum_rows(T_wc))
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
    return data[:, 0], poses_from_tum_rows(data[:, 1:])


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
