"""Evaluation and preview images drawn with OpenCV (no matplotlib dependency).

- :func:`trajectory_plot`: a top-down view of ground-truth and predicted camera centres with
  an error line per frame (the paper's Fig. 5).
- :func:`depth_strips`: rows of image | predicted depth | ground-truth depth.
- :func:`colourise_depth`: a depth map as a colour image (near = bright), shared by localize.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

# BGR colours
GT_COLOUR = (60, 160, 40)
TRAIN_COLOUR = (200, 200, 200)
EST_COLOUR = (200, 80, 20)
ERR_COLOUR = (60, 60, 230)
TEXT_COLOUR = (30, 30, 30)
CANVAS = 900  # pixels per side of the trajectory plot
MARGIN = 60
STRIP_HEIGHT = 192  # each depth-strip row is resized to this height


def write_png(path: str | Path, image: np.ndarray) -> None:
    """Encode and write a PNG via a temp file + rename (no half-written images)."""
    import cv2

    from relocdepth.fileio import write_bytes_atomic

    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise RuntimeError(f"cannot encode {path}")
    write_bytes_atomic(path, buf.tobytes())


def colourise_depth(
    depth: np.ndarray, lo: float | None = None, hi: float | None = None
) -> np.ndarray:
    """(H, W) depth -> (H, W, 3) BGR uint8, inverse depth through the magma colour map.

    lo/hi: the depth range mapped to the colour scale (default: 2nd-98th percentile of the
    valid pixels). Invalid pixels (<= 0 or not finite) are black.
    """
    import cv2

    d = np.asarray(depth, np.float64)
    valid = np.isfinite(d) & (d > 0)
    if not valid.any():
        return np.zeros(d.shape + (3,), np.uint8)
    if lo is None or hi is None:
        p_lo, p_hi = np.percentile(d[valid], [2, 98])
        lo = p_lo if lo is None else lo
        hi = p_hi if hi is None else hi
    lo = max(lo, 1e-6)
    hi = max(hi, lo * (1 + 1e-6))
    inv = np.zeros_like(d)
    inv[valid] = 1.0 / np.clip(d[valid], lo, hi)
    norm = np.clip((inv - 1.0 / hi) / (1.0 / lo - 1.0 / hi), 0.0, 1.0)
    out = cv2.applyColorMap((norm * 255).astype(np.uint8), cv2.COLORMAP_MAGMA)
    out[~valid] = 0
    return out


def _top_down_axes(points: np.ndarray) -> np.ndarray:
    """The two principal directions of the centres (3, 2): the plane the camera moves in most,
    i.e. a top-down view for a handheld camera walking through a room."""
    c = points - points.mean(axis=0)
    _, _, Vt = np.linalg.svd(c, full_matrices=False)
    return Vt[:2].T


def trajectory_plot(
    path: str | Path,
    gt_by_seq: dict[str, np.ndarray],
    est_by_seq: dict[str, np.ndarray],
    train_gt: np.ndarray | None = None,
    title: str = "",
) -> None:
    """Top-down plot: GT test trajectories (green lines), predictions (blue dots), an error
    line per frame (red), training GT in grey. Centres are (N, 3) in metres (GT frame)."""
    import cv2

    gts = [np.asarray(v, np.float64) for v in gt_by_seq.values()]
    all_gt = np.concatenate(gts + ([train_gt] if train_gt is not None else []))
    axes = _top_down_axes(all_gt)
    origin = all_gt.mean(axis=0)

    def proj(p: np.ndarray) -> np.ndarray:
        return (np.asarray(p, np.float64) - origin) @ axes

    gt2 = proj(all_gt)
    lo, hi = gt2.min(axis=0), gt2.max(axis=0)
    span = max(float((hi - lo).max()), 1e-3)
    # The view covers the predictions too, but at most one GT extent beyond the GT: points of a
    # diverged model are clipped to the frame edge rather than shrinking the GT to a dot.
    est2 = proj(np.concatenate([np.asarray(v, np.float64) for v in est_by_seq.values()]))
    lo = np.maximum(np.minimum(lo, est2.min(axis=0)), lo - span) - 0.05 * span
    hi = np.minimum(np.maximum(hi, est2.max(axis=0)), hi + span) + 0.05 * span
    extent = max(float((hi - lo).max()), 1e-6)
    scale = (CANVAS - 2 * MARGIN) / extent
    centre = (lo + hi) / 2

    def px(p2: np.ndarray) -> np.ndarray:
        xy = (p2 - centre) * scale + CANVAS / 2
        xy[..., 1] = CANVAS - xy[..., 1]  # image y grows downwards
        return np.clip(xy, 2, CANVAS - 3).round().astype(np.int32)

    img = np.full((CANVAS, CANVAS, 3), 255, np.uint8)
    if train_gt is not None and len(train_gt) > 1:
        cv2.polylines(img, [px(proj(train_gt))], False, TRAIN_COLOUR, 1, cv2.LINE_AA)
    for seq, gt in gt_by_seq.items():
        g, e = px(proj(gt)), px(proj(est_by_seq[seq]))
        for a, b in zip(g, e):
            cv2.line(img, tuple(int(v) for v in a), tuple(int(v) for v in b), ERR_COLOUR, 1, cv2.LINE_AA)
        cv2.polylines(img, [g], False, GT_COLOUR, 2, cv2.LINE_AA)
        for b in e:
            cv2.circle(img, tuple(int(v) for v in b), 3, EST_COLOUR, -1, cv2.LINE_AA)
    _legend(img, title, scale)
    write_png(path, img)


def _legend(img: np.ndarray, title: str, px_per_m: float) -> None:
    import cv2

    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.putText(img, title, (MARGIN // 2, 30), font, 0.6, TEXT_COLOUR, 1, cv2.LINE_AA)
    items = [("ground truth (test)", GT_COLOUR), ("prediction", EST_COLOUR),
             ("error", ERR_COLOUR), ("ground truth (train)", TRAIN_COLOUR)]
    for i, (label, colour) in enumerate(items):
        y = CANVAS - 20 - 22 * i
        cv2.line(img, (MARGIN // 2, y - 5), (MARGIN // 2 + 25, y - 5), colour, 3)
        cv2.putText(img, label, (MARGIN // 2 + 35, y), font, 0.5, TEXT_COLOUR, 1, cv2.LINE_AA)
    # scale bar: a round length near a fifth of the canvas
    target = CANVAS / 5 / px_per_m
    bar = 10 ** np.floor(np.log10(target))
    bar = max(b for b in (bar, 2 * bar, 5 * bar) if b <= target)
    x1 = CANVAS - MARGIN // 2
    x0 = round(x1 - bar * px_per_m)
    cv2.line(img, (x0, CANVAS - 25), (x1, CANVAS - 25), TEXT_COLOUR, 2)
    cv2.putText(img, f"{bar:g} m", (x0, CANVAS - 35), font, 0.5, TEXT_COLOUR, 1, cv2.LINE_AA)


def depth_strips(
    path: str | Path, rows: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray | None]]
) -> None:
    """Rows of RGB image | predicted depth | GT depth (any sizes; each panel resized to the
    row height). The prediction is median-scaled to the GT and both share its colour range."""
    import cv2

    out_rows = []
    for rgb, pred, gt in rows:
        h = STRIP_HEIGHT
        w = round(rgb.shape[1] * h / rgb.shape[0])
        img = cv2.resize(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), (w, h), interpolation=cv2.INTER_AREA)
        pred = cv2.resize(np.asarray(pred, np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
        if gt is not None:
            gt = cv2.resize(np.asarray(gt, np.float32), (w, h), interpolation=cv2.INTER_NEAREST)
            valid = gt > 0
            if valid.any() and np.median(pred[valid]) > 0:
                pred = pred * np.median(gt[valid]) / np.median(pred[valid])
            lo, hi = (np.percentile(gt[valid], [2, 98]) if valid.any() else (None, None))
            gt_img = colourise_depth(gt, lo, hi)
        else:
            lo = hi = None
            gt_img = np.zeros_like(img)
        out_rows.append(np.hstack([img, colourise_depth(pred, lo, hi), gt_img]))
    if not out_rows:
        return
    width = max(r.shape[1] for r in out_rows)
    out_rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0))) for r in out_rows]
    write_png(path, np.vstack(out_rows))
