"""Evaluation metrics (pure numpy): pose summaries, depth errors, references and baselines.

Poses are (N, 4, 4) world-from-camera matrices (OpenCV axes). The pose figures follow the
paper's protocol (Sec. IV, Table I: median position/attitude error after a Sim(3) alignment
fitted on the training frames); the depth figures follow monodepth2 / the paper's Table II
(per-frame median scaling, 0.1-10 m). The extra diagnostics (rotation-only alignment, relative
pose vs identity, raw spread, constant-depth reference) are the ones DESIGN.md's Pitfalls ask
for, because a collapsed prediction makes the centre-fitted Sim(3) meaningless.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from relocdepth.eval_geometry import mean_pose, pose_errors, rotation_angle_deg

# Accuracy thresholds: the paper's 5 cm / 5 deg and 10 cm / 10 deg, and 10 cm / 5 deg, the one
# ACE and DSAC* report (so figures compare with theirs).
POSE_THRESHOLDS: tuple[tuple[float, float], ...] = ((0.05, 5.0), (0.10, 5.0), (0.10, 10.0))
# Depth evaluation range in metres (monodepth2's indoor convention, the paper's Table II).
DEPTH_RANGE = (0.1, 10.0)
# Thumbnail size (W, H) of the retrieval baseline: small enough to ignore detail and noise.
THUMB_SIZE = (16, 12)


# ----------------------------------------------------------------------------- pose summaries


def pose_summary(t_err: np.ndarray, r_err: np.ndarray) -> dict:
    """Median/mean errors and the share (%) within the paper's thresholds."""
    t_err, r_err = np.asarray(t_err, np.float64), np.asarray(r_err, np.float64)
    n = int(t_err.size)
    out: dict = {"frames": n}
    if n == 0:
        return out | {"median_t_m": None, "median_r_deg": None, "mean_t_m": None, "mean_r_deg": None,
                      **{threshold_key(t, r): None for t, r in POSE_THRESHOLDS}}
    out |= {
        "median_t_m": float(np.median(t_err)), "median_r_deg": float(np.median(r_err)),
        "mean_t_m": float(np.mean(t_err)), "mean_r_deg": float(np.mean(r_err)),
    }
    for t_max, r_max in POSE_THRESHOLDS:
        out[threshold_key(t_max, r_max)] = float(100.0 * np.mean((t_err <= t_max) & (r_err <= r_max)))
    return out


def pose_summary_by_sequence(
    t_err: np.ndarray, r_err: np.ndarray, sequences: Sequence[str]
) -> dict[str, dict]:
    """:func:`pose_summary` for each sequence name (in order of first appearance)."""
    seqs = np.asarray(sequences)
    return {
        s: pose_summary(t_err[seqs == s], r_err[seqs == s]) for s in dict.fromkeys(sequences)
    }


def threshold_key(t_max: float, r_max: float) -> str:
    """``(0.10, 5.0)`` -> ``"pct_10cm_5deg"``, the report's name of that accuracy share."""
    return f"pct_{round(t_max * 100)}cm_{round(r_max)}deg"


def rank_average(x: np.ndarray) -> np.ndarray:
    """Ranks 1..N of a 1-D array, ties sharing their average rank."""
    x = np.asarray(x, np.float64)
    order = np.argsort(x, kind="stable")
    ranks = np.empty(len(x))
    ranks[order] = np.arange(1, len(x) + 1)
    _, inverse, counts = np.unique(x, return_inverse=True, return_counts=True)
    sums = np.bincount(inverse, weights=ranks)
    return (sums / counts)[inverse]


def spearman(a: np.ndarray, b: np.ndarray) -> float | None:
    """Spearman rank correlation of two 1-D arrays (ties averaged); None when undefined
    (fewer than 3 values, or one of them constant)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape or a.ndim != 1:
        raise ValueError(f"spearman: shapes {a.shape} vs {b.shape}, want equal 1-D")
    if a.size < 3:
        return None
    ra, rb = rank_average(a) - (a.size + 1) / 2, rank_average(b) - (b.size + 1) / 2
    denom = np.sqrt(np.sum(ra * ra) * np.sum(rb * rb))
    return None if denom == 0 else float(np.sum(ra * rb) / denom)


def confidence_ranking(confidence: np.ndarray, t_err: np.ndarray, r_err: np.ndarray) -> dict:
    """How well confidence ranks errors: Spearman of confidence vs translation / rotation error.

    Negative is good (higher confidence, smaller error); -1 is a perfect ranking, 0 none.
    """
    c = np.asarray(confidence, np.float64)
    return {"frames": int(c.size), "median": float(np.median(c)) if c.size else None,
            "spearman_t": spearman(c, t_err), "spearman_r": spearman(c, r_err)}


# ----------------------------------------------------------------------------- diagnostics


def relative_pose_errors(
    T_est: np.ndarray, T_gt: np.ndarray, sequences: Sequence[str], k: int
) -> dict:
    """Error of the relative pose between frames k apart (same sequence) vs the identity.

    The relative pose is T_i^-1 T_{i+k}; its rotation error does not depend on any alignment,
    its translation error is in the units of T_est (metres after a Sim(3)). The identity
    "prediction" (no motion) is the reference a pose network must beat.
    """
    seqs = np.asarray(sequences)
    i = np.array([j for j in range(len(seqs) - k) if seqs[j] == seqs[j + k]], dtype=np.int64)
    if i.size == 0:
        return {"k": k, "pairs": 0, "median_t_m": None, "median_r_deg": None,
                "identity_median_t_m": None, "identity_median_r_deg": None}
    inv = np.linalg.inv
    rel_est = inv(T_est[i]) @ T_est[i + k]
    rel_gt = inv(T_gt[i]) @ T_gt[i + k]
    t_err, r_err = pose_errors(rel_est, rel_gt)
    return {
        "k": k, "pairs": int(i.size),
        "median_t_m": float(np.median(t_err)), "median_r_deg": float(np.median(r_err)),
        "identity_median_t_m": float(np.median(np.linalg.norm(rel_gt[:, :3, 3], axis=-1))),
        "identity_median_r_deg": float(np.median(rotation_angle_deg(rel_gt[:, :3, :3]))),
    }


# ----------------------------------------------------------------------------- baselines


def mean_pose_baseline(T_train_gt: np.ndarray, n_test: int) -> np.ndarray:
    """Predict the mean training pose for every test frame: (n_test, 4, 4)."""
    return np.repeat(mean_pose(T_train_gt)[None], n_test, axis=0)


def thumbnail(image: np.ndarray, size: tuple[int, int] = THUMB_SIZE) -> np.ndarray:
    """A small grey thumbnail, zero mean and unit norm, flattened: (w*h,) float64.

    image: (H, W, 3) RGB or (H, W) grey, any dtype. Area averaging over a w x h grid of
    (nearly) equal cells, in numpy (needs H >= h and W >= w).
    """
    img = np.asarray(image, np.float64)
    grey = img @ np.array([0.299, 0.587, 0.114]) if img.ndim == 3 else img
    w, h = size
    H, W = grey.shape
    if H < h or W < w:
        raise ValueError(f"thumbnail: image {W}x{H} smaller than {w}x{h}")
    rows = np.linspace(0, H, h + 1).round().astype(int)
    cols = np.linspace(0, W, w + 1).round().astype(int)
    sums = np.add.reduceat(np.add.reduceat(grey, rows[:-1], axis=0), cols[:-1], axis=1)
    thumb = sums / np.outer(np.diff(rows), np.diff(cols))
    v = thumb.ravel() - thumb.mean()
    norm = np.linalg.norm(v)
    return v / norm if norm > 0 else v


def retrieval_baseline(
    train_thumbs: np.ndarray, T_train: np.ndarray, query_thumbs: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Pose of the nearest training thumbnail (largest dot product = smallest L2 for unit norm).

    train_thumbs: (N, D), T_train: (N, 4, 4), query_thumbs: (M, D).
    Returns (poses (M, 4, 4), index of the nearest training frame (M,)).
    """
    sims = np.asarray(query_thumbs) @ np.asarray(train_thumbs).T
    nn = np.argmax(sims, axis=1)
    return np.asarray(T_train)[nn], nn


def nearest_centre_baseline(
    T_train: np.ndarray, T_query: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pose of the training frame whose true camera centre is nearest the query's true centre.

    An oracle, not a method: it reads the test frames' ground truth. Its translation error is how
    far each test camera stands from every training camera, so it tells how much a test sequence
    asks a network to extrapolate beyond the places it was trained on; a regressor that only
    recalls training poses does no better.
    T_train: (N, 4, 4), T_query: (M, 4, 4). Returns (poses (M, 4, 4), index (M,), distance m (M,)).
    """
    c_train = np.asarray(T_train, np.float64)[:, :3, 3]
    c_query = np.asarray(T_query, np.float64)[:, :3, 3]
    d = np.linalg.norm(c_query[:, None, :] - c_train[None, :, :], axis=2)
    nn = np.argmin(d, axis=1)
    return np.asarray(T_train)[nn], nn, d[np.arange(len(nn)), nn]


# ----------------------------------------------------------------------------- depth


def depth_errors(
    pred: np.ndarray, gt: np.ndarray, depth_range: tuple[float, float] = DEPTH_RANGE
) -> dict | None:
    """Depth metrics of one frame after per-frame median scaling (monodepth2's protocol).

    pred, gt: (H, W) depth at the same size (gt 0 = invalid). Pixels with gt inside
    depth_range are evaluated; pred is scaled by median(gt)/median(pred) and clipped to the
    range. Returns the metrics plus "scale", or None when the frame has no valid pixel.
    """
    pred, gt = np.asarray(pred, np.float64), np.asarray(gt, np.float64)
    if pred.shape != gt.shape:
        raise ValueError(f"depth_errors: pred {pred.shape} vs gt {gt.shape}")
    lo, hi = depth_range
    mask = (gt > lo) & (gt < hi) & np.isfinite(pred) & (pred > 0)
    if not mask.any():
        return None
    p, g = pred[mask], gt[mask]
    scale = float(np.median(g) / np.median(p))
    p = np.clip(p * scale, lo, hi)
    thresh = np.maximum(g / p, p / g)
    return {
        "abs_rel": float(np.mean(np.abs(g - p) / g)),
        "sq_rel": float(np.mean((g - p) ** 2 / g)),
        "rmse": float(np.sqrt(np.mean((g - p) ** 2))),
        "rmse_log": float(np.sqrt(np.mean((np.log(g) - np.log(p)) ** 2))),
        "delta1": float(np.mean(thresh < 1.25)),
        "delta2": float(np.mean(thresh < 1.25**2)),
        "delta3": float(np.mean(thresh < 1.25**3)),
        "scale": scale,
    }


DEPTH_KEYS = ("abs_rel", "sq_rel", "rmse", "rmse_log", "delta1", "delta2", "delta3")


def depth_summary(per_frame: Sequence[dict | None]) -> dict | None:
    """Mean of the per-frame metrics, and std/median of the per-frame scale factors."""
    frames = [f for f in per_frame if f is not None]
    if not frames:
        return None
    out: dict = {"frames": len(frames)}
    for key in DEPTH_KEYS:
        out[key] = float(np.mean([f[key] for f in frames]))
    scales = np.array([f["scale"] for f in frames])
    out["scale_median"] = float(np.median(scales))
    out["scale_std_over_median"] = float(np.std(scales) / np.median(scales))
    return out


def constant_depth_errors(
    gt: np.ndarray, depth_range: tuple[float, float] = DEPTH_RANGE
) -> dict | None:
    """The constant-depth reference: a flat map, median-scaled per frame like a prediction."""
    return depth_errors(np.ones_like(gt, dtype=np.float64), gt, depth_range)
