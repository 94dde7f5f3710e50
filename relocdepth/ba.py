"""Bundle adjustment of a sequence's odometry over multi-frame point tracks (no ground truth).

The odometry (:func:`relocdepth.vo.chain`) joins frames pair by pair: each pair's rotation and
translation direction come from its own essential matrix, so each pair's error stays in the chain.
Here the same images give tracks over several frames (KLT from each frame to the next, checked
against the pair's fundamental matrix; new corners where the tracks thinned out). Every track is one
scene point, and all poses and points are fitted to every observation at once (reprojection error
in pixels, Huber-robust; Levenberg-Marquardt with the points eliminated by their Schur complement,
the classical sparse bundle adjustment). A point seen from three frames ties the three poses
together. On the real walk-through (60 frames ~20 cm apart, 192x128, depth from a network at
AbsRel ~0.2) the trajectory's error fell from 0.223-0.252 m to 0.142-0.147 m (README, Quality:
trial 29).

Two things the tracks cannot do alone. A fast turn leaves a pair of frames a dozen shared tracks,
too few to fix their relative pose, so each neighbouring pair's rotation is also held softly to the
starting poses' (``BAConfig.rotation_prior_px_per_deg``); with a hundred shared tracks the tracks
decide (on the walk-through it took the error from 0.154 to 0.143 m). And the fit has no scale:
the points start at a depth map's depth along their first ray, frame 0 is held, and the result is
scaled about it so that the points' depths match the maps' (the median ratio over every
observation), so it is in the depth's units, as the odometry is. (Fitting the points' depths to
the maps as well made it worse with a network's depth, 0.27-0.45 m: its errors are not noise.)

Conventions (DESIGN.md): poses are world-from-camera ``T_wc`` (4, 4), OpenCV axes.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from relocdepth.twoview import TrackConfig, as_grey, detect_corners, track_mask


@dataclass(frozen=True)
class BAConfig:
    """Tracks and the fit."""

    track: TrackConfig = TrackConfig()
    # a track step that misses the pair's fundamental matrix (MAGSAC++) by more than this (px)
    # ends the track (0: no check)
    epipolar_px: float = 1.0
    # Each track step is tracked again from the track's first view (its own first patch, starting
    # where the frame-to-frame step put it); a track whose two positions differ by more than this
    # (px) ends (0: frame to frame only). Frame-to-frame steps drift (0.1 px after one step, 0.25
    # after eight on the demo scene), and the drift bends the fit: on the demo scene's first path
    # (true depth) the fitted path came out 20 % too long and turned 4.7 deg off, 2 % and 1.0
    # with the first views (README, Quality: trial 31).
    first_view_px: float = 1.0
    min_observations: int = 2  # a track seen in fewer frames is not used
    min_ray_deg: float = 0.5  # ... nor one whose rays meet at a smaller angle (its depth is noise)
    huber_px: float = 1.0  # reprojection errors beyond this count linearly (robust to bad tracks)
    # each neighbouring pair's rotation is held to the starting poses' by a residual of this many px
    # per degree (0: not held)
    rotation_prior_px_per_deg: float = 1.0
    max_iterations: int = 30  # Levenberg-Marquardt steps at most
    # With depth maps: after the fit, each step of the path is rescaled so that the points' depths
    # in each frame match the maps' there, the per-frame scales smoothed over a Gaussian window of
    # this many frames (0: one scale for the whole path). The tracks leave the scale along a path
    # without loops free: on the real walk-through the fit run to convergence (100 iterations) took
    # the rotation drift from 4.6 to 1.7 deg but the path's error from 0.087 to 0.136 m with the
    # true depth, and held to the true depth per frame it came to 0.071-0.118 m (README, Quality:
    # trial 34). A network's per-frame scale is noisy (log std 0.17-0.20), hence the window.
    scale_window: float = 0.0
    # ... or fitted by a polynomial of this degree in the frame's place along the path, weighted by
    # each frame's observations (None: not fitted; exclusive with ``scale_window``). A network's
    # per-frame scale errs in stretches of several frames, and a window averages them in; the
    # path's own scale error drifts slowly, and a low-order fit follows the drift, not the
    # stretches (README, Training: a drift of the scale along the path).
    scale_degree: int | None = None
    min_scale_observations: int = 10  # a frame with fewer observations has no scale of its own

    def __post_init__(self) -> None:
        if not (self.scale_window >= 0 and np.isfinite(self.scale_window)):
            raise ValueError(f"scale_window must be a number of frames >= 0, not {self.scale_window}")
        if self.scale_degree is not None and self.scale_degree < 0:
            raise ValueError(f"scale_degree must be >= 0, not {self.scale_degree}")
        if self.scale_degree is not None and self.scale_window > 0:
            raise ValueError("scale_window and scale_degree are two ways to hold the scale: give one")
        if self.min_scale_observations < 1:
            raise ValueError(f"min_scale_observations must be at least 1, not {self.min_scale_observations}")
        if self.max_iterations < 0:
            raise ValueError(f"max_iterations must be >= 0, not {self.max_iterations}")


@dataclass
class Tracks:
    """Observations of tracked points, in frame order: frame index, track id and pixel ``(x, y)``."""

    frame: np.ndarray  # (M,) int
    track: np.ndarray  # (M,) int
    xy: np.ndarray  # (M, 2) float64

    @property
    def n_tracks(self) -> int:
        return int(self.track.max()) + 1 if len(self.track) else 0


@dataclass
class Adjusted:
    """The adjusted poses ``T_wc (N, 4, 4)``; the tracks and observations the fit used; the median
    reprojection error (px) before and after; the scale applied from the depth maps; where the
    scale was held along the path, the least and greatest factor its frames were given."""

    T_wc: np.ndarray
    tracks: int
    observations: int
    start_px: float
    final_px: float
    scale: float
    held: tuple[float, float] | None = None

    def summary(self) -> dict:
        """The figures for a log: tracks, observations, median reprojection error before / after,
        and the range of the scale held along the path where it was."""
        out = {"tracks": self.tracks, "observations": self.observations,
               "start_px": round(self.start_px, 3), "final_px": round(self.final_px, 3)}
        if self.held is not None:
            out["held"] = [round(v, 3) for v in self.held]
        return out


def _epipolar_inliers(a: np.ndarray, b: np.ndarray, keep: np.ndarray, threshold_px: float) -> np.ndarray:
    """Which of the moves ``a -> b (N, 2)`` to keep: those in ``keep`` that fit the pair's
    fundamental matrix (MAGSAC++, ``threshold_px``); all of them when none can be fitted."""
    import cv2

    out = keep.copy()
    if threshold_px <= 0 or keep.sum() < 15:
        return out
    try:
        F, mask = cv2.findFundamentalMat(a[keep], b[keep], cv2.USAC_MAGSAC, threshold_px, 0.999)
    except cv2.error:  # MAGSAC++ asserts on some sets of moves (repeated points): none fitted
        return out
    if F is not None and mask is not None:
        out[np.flatnonzero(keep)] = mask.ravel() > 0
    return out


def build_tracks(images: Sequence[np.ndarray], cfg: TrackConfig = TrackConfig(),
                 epipolar_px: float = 1.0, first_view_px: float = 1.0) -> Tracks:
    """Multi-frame tracks over ``images`` in order: the points of frame j tracked into frame j+1
    (forward-backward checked, :func:`relocdepth.twoview.track_mask`), each step then tracked
    again from the track's first view (:func:`_from_first_views`; off with ``first_view_px`` 0),
    a step off the pair's fundamental matrix by more than ``epipolar_px`` ending the track; and new
    corners detected in every frame away from the tracks that go on (up to ``cfg.max_corners`` in
    all)."""
    import cv2

    frames, ids, xys = [], [], []
    act_id, act_xy = np.zeros(0, int), np.zeros((0, 2), np.float32)
    act_first, act_first_xy = np.zeros(0, int), np.zeros((0, 2), np.float32)  # each track's first view
    greys: list[np.ndarray] = []
    next_id, prev = 0, None
    for j, image in enumerate(images):
        grey = as_grey(image)
        greys.append(grey)
        if prev is not None and len(act_xy):
            q, keep = track_mask(prev, grey, act_xy, cfg)
            if first_view_px > 0:
                q, keep = _from_first_views(greys, act_first, act_first_xy, q, keep, cfg, first_view_px)
            keep = _epipolar_inliers(act_xy, q, keep, epipolar_px)
            act_id, act_xy = act_id[keep], q[keep]
            act_first, act_first_xy = act_first[keep], act_first_xy[keep]
        room = cfg.max_corners - len(act_xy)
        if room > 0:
            mask = np.full(grey.shape, 255, np.uint8)
            for x, y in act_xy:
                cv2.circle(mask, (int(round(x)), int(round(y))), int(np.ceil(cfg.min_distance)), 0, -1)
            new = detect_corners(grey, cfg, mask)[:room]
            act_id = np.concatenate([act_id, np.arange(next_id, next_id + len(new))])
            act_xy = np.concatenate([act_xy, new]).astype(np.float32)
            act_first = np.concatenate([act_first, np.full(len(new), j)])
            act_first_xy = np.concatenate([act_first_xy, new]).astype(np.float32)
            next_id += len(new)
        frames.append(np.full(len(act_id), j))
        ids.append(act_id.copy())
        xys.append(act_xy.astype(np.float64))
        prev = grey
    return Tracks(np.concatenate(frames), np.concatenate(ids), np.concatenate(xys))


def _from_first_views(greys: list[np.ndarray], first: np.ndarray, first_xy: np.ndarray, q: np.ndarray,
                      keep: np.ndarray, cfg: TrackConfig, max_px: float) -> tuple[np.ndarray, np.ndarray]:
    """The kept steps ``q (N, 2)`` into the newest image ``greys[-1]`` tracked again from each
    track's first view (image ``greys[first]`` at ``first_xy``; one LK step from ``q``, at full
    resolution, the same window): frame-to-frame steps add up their errors, this one does not. A
    track whose step moves more than ``max_px`` or is lost ends. Tracks born in the previous image
    keep their step (it already is from their first view)."""
    import cv2

    q, keep = q.copy(), keep.copy()
    lk = {"winSize": (cfg.win_size, cfg.win_size), "maxLevel": 0, "flags": cv2.OPTFLOW_USE_INITIAL_FLOW,
          "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.03)}
    newest = len(greys) - 1
    for f in np.unique(first[keep]):
        if f == newest - 1:
            continue
        sel = np.flatnonzero(keep & (first == f))
        start = np.ascontiguousarray(q[sel], np.float32).reshape(-1, 1, 2)
        r, st, _ = cv2.calcOpticalFlowPyrLK(greys[f], greys[newest],
                                            np.ascontiguousarray(first_xy[sel], np.float32).reshape(-1, 1, 2),
                                            start.copy(), **lk)
        r = r.reshape(-1, 2)
        ok = (st.ravel() == 1) & (np.linalg.norm(r - q[sel], axis=1) <= max_px)
        q[sel[ok]] = r[ok]
        keep[sel[~ok]] = False
    return q, keep


def rotvec_to_matrix(r: np.ndarray) -> np.ndarray:
    """Rotation vectors ``(N, 3)`` (radians) to matrices ``(N, 3, 3)``, float64
    (:func:`relocdepth.geometry.rotations.so3_exp` on NumPy arrays)."""
    import torch

    from relocdepth.geometry.rotations import so3_exp

    return so3_exp(torch.from_numpy(np.asarray(r, np.float64).reshape(-1, 3))).numpy()


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(N, 3, 3)`` to rotation vectors ``(N, 3)`` (radians), float64; exact for
    small angles too, which OpenCV's Rodrigues rounds to 0 below 1e-5 rad
    (:func:`relocdepth.geometry.rotations.so3_log` on NumPy arrays)."""
    import torch

    from relocdepth.geometry.rotations import so3_log

    return so3_log(torch.from_numpy(np.asarray(R, np.float64).reshape(-1, 3, 3))).numpy()


def _skew(v: np.ndarray) -> np.ndarray:
    """``[v]_x (..., 3, 3)``: ``[v]_x u = v x u``."""
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2], S[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    return S - np.swapaxes(S, -1, -2)


def triangulate(T_cw: np.ndarray, rays: np.ndarray, frame: np.ndarray, track: np.ndarray,
                n_tracks: int) -> np.ndarray:
    """Each track's point ``(n_tracks, 3)`` in the world by linear least squares (DLT) over its
    observations: normalised pixels ``rays (M, 2)`` seen from cameras ``T_cw[frame] (M, 4, 4)``
    (camera from world). NaN or far off for a track with one observation."""
    P = T_cw[frame][:, :3, :]  # (M, 3, 4)
    rows = np.concatenate([rays[:, :1, None] * P[:, 2:3] - P[:, 0:1],
                           rays[:, 1:2, None] * P[:, 2:3] - P[:, 1:2]], axis=1)  # (M, 2, 4)
    A = np.zeros((n_tracks, 4, 4))
    np.add.at(A, track, np.einsum("mri,mrj->mij", rows, rows))
    _, vecs = np.linalg.eigh(A)
    X = vecs[:, :, 0]  # the smallest eigenvalue's vector: the homogeneous point
    with np.errstate(divide="ignore", invalid="ignore"):
        return X[:, :3] / X[:, 3:4]


def _in_camera(R: np.ndarray, t: np.ndarray, X: np.ndarray) -> np.ndarray:
    return np.einsum("mij,mj->mi", R, X) + t


def bundle_adjust(images: Sequence[np.ndarray], K: np.ndarray, T_wc: np.ndarray,
                  depth: Callable[[int], np.ndarray] | None = None,
                  cfg: BAConfig = BAConfig(), tracks: Tracks | None = None) -> Adjusted:
    """Refine the poses ``T_wc (N, 4, 4)`` of ``images`` (one camera ``K (3, 3)``; e.g. the
    odometry's) by bundle adjustment over their tracks (``tracks``, or :func:`build_tracks`).

    Frame 0's pose is held. With ``depth`` (frame j's depth map ``depth(j)``, any units, <= 0
    unknown) each track's point starts along its first ray at the map's depth there, and the
    result is scaled about frame 0 so that the points' depths match the maps' (the median ratio
    over all observations); without it the points are triangulated from the starting poses and
    the scale is the fit's own (about theirs). A frame with no observation in the fit keeps its
    starting pose relative to the frame before it. Nothing to fit (no track seen from two frames
    from rays that meet): the poses are returned as given.
    """
    T_wc = np.asarray(T_wc, np.float64)
    K = np.asarray(K, np.float64)
    n = len(T_wc)
    tr = tracks if tracks is not None else build_tracks(images, cfg.track, cfg.epipolar_px, cfg.first_view_px)
    f = np.array([K[0, 0], K[1, 1]])
    rays = (tr.xy - K[:2, 2]) / f
    T_cw = np.linalg.inv(T_wc)

    # every observation's depth from the maps (NaN: unknown)
    o_depth = np.full(len(tr.frame), np.nan)
    if depth is not None:
        from relocdepth.vo import sample_depth

        for j in np.unique(tr.frame):
            sel = tr.frame == j
            o_depth[sel] = sample_depth(depth(int(j)), tr.xy[sel])
    # The tracks' points to start from: along a track's first ray with a depth, at that depth;
    # else triangulated from the starting poses (whose errors put many such points behind a
    # camera where the steps are short: a pair off by 0.4 deg, 3 cm apart, at 2-5 m).
    X = triangulate(T_cw, rays, tr.frame, tr.track, tr.n_tracks)
    has = np.flatnonzero(np.isfinite(o_depth) & (o_depth > 0))
    first = has[np.unique(tr.track[has], return_index=True)[1]]  # observations are in frame order
    X[tr.track[first]] = np.einsum("mij,mj->mi", T_wc[tr.frame[first], :3, :3],
                                   np.c_[rays[first], np.ones(len(first))] * o_depth[first, None]) \
        + T_wc[tr.frame[first], :3, 3]
    # ... to be used: seen often enough, in front of every camera and from rays that do meet. (Not
    # also near every pixel: the starting poses' errors are what the fit is for, and dropping the
    # tracks they miss by 4 px left the walk-through's trajectory 0.20-0.25 m off instead of 0.14.)
    Xc = _in_camera(T_cw[tr.frame, :3, :3], T_cw[tr.frame, :3, 3], X[tr.track])
    with np.errstate(divide="ignore", invalid="ignore"):
        dirs = X[tr.track] - T_wc[tr.frame, :3, 3]
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    bad = np.zeros(tr.n_tracks, bool)
    np.logical_or.at(bad, tr.track, ~(Xc[:, 2] > 0))
    dirs = np.nan_to_num(dirs)
    mean = np.zeros((tr.n_tracks, 3))
    np.add.at(mean, tr.track, dirs)
    mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-12)
    spread = np.zeros(tr.n_tracks)  # the widest angle between a track's rays is about twice this
    np.maximum.at(spread, tr.track, np.degrees(np.arccos(np.clip(np.sum(dirs * mean[tr.track], axis=1), -1, 1))))
    counts = np.bincount(tr.track, minlength=tr.n_tracks)
    good = (counts >= max(cfg.min_observations, 2)) & ~bad & (2 * spread >= cfg.min_ray_deg)
    use = good[tr.track]
    seen = np.zeros(n, bool)
    seen[tr.frame[use]] = True
    free = np.flatnonzero(seen & (np.arange(n) > 0))  # fitted; frame 0 held, unseen ones follow
    if len(free) == 0:
        return Adjusted(T_wc.copy(), 0, 0, float("nan"), float("nan"), 1.0)
    pt_col = np.cumsum(good) - 1  # a used track's row among the fitted points
    o_frame, o_pt, o_ray = tr.frame[use], pt_col[tr.track[use]], rays[use]
    R_prior = T_cw[:, :3, :3] if cfg.rotation_prior_px_per_deg > 0 else None
    R, t, P, start, final = _levenberg_marquardt(T_cw[:, :3, :3].copy(), T_cw[:, :3, 3].copy(), X[good],
                                                 free, o_frame, o_pt, o_ray, f, R_prior, cfg)
    out = np.repeat(np.eye(4)[None], n, axis=0)
    out[:, :3, :3] = np.swapaxes(R, 1, 2)
    out[:, :3, 3] = -np.einsum("nji,nj->ni", R, t)
    for j in range(1, n):
        if not seen[j]:
            out[j] = out[j - 1] @ np.linalg.inv(T_wc[j - 1]) @ T_wc[j]
    scale, held = 1.0, None
    z = _in_camera(R[o_frame], t[o_frame], P[o_pt])[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = o_depth[use] / z
    fine = np.isfinite(ratio) & (ratio > 0)
    if fine.any():
        scale = float(np.median(ratio[fine]))
        origin = out[0, :3, 3].copy()
        out[:, :3, 3] = origin + scale * (out[:, :3, 3] - origin)
        if cfg.scale_window > 0 or cfg.scale_degree is not None:
            log_scale = path_scale(o_frame[fine], np.log(ratio[fine] / scale), n, cfg.scale_window,
                                   cfg.min_scale_observations, cfg.scale_degree)
            out = rescale_steps(out, log_scale)
            held = (float(np.exp(log_scale.min())), float(np.exp(log_scale.max())))
    return Adjusted(out, int(good.sum()), len(o_frame), start, final, scale, held)


def path_scale(frame: np.ndarray, log_ratio: np.ndarray, n: int, window: float,
               min_observations: int = 10, degree: int | None = None) -> np.ndarray:
    """The log scale ``(n,)`` of each of ``n`` frames along a path: per frame, the median of its
    observations' ``log_ratio`` (depth map over the fitted point's depth; observation o in frame
    ``frame[o]``), where it has ``min_observations``; smoothed over a Gaussian window of ``window``
    frames (frames without a scale of their own take their neighbours'), or, with ``degree``, a
    polynomial of that degree in the frame index fitted to the frames' scales, each weighted by
    the square root of its observations (the degree lowered where too few frames have a scale).
    Zeros where no frame has one."""
    own, count = np.full(n, np.nan), np.zeros(n)
    for j in np.unique(frame):
        sel = frame == j
        if sel.sum() >= min_observations:
            own[j], count[j] = np.median(log_ratio[sel]), sel.sum()
    has = np.flatnonzero(np.isfinite(own))
    if len(has) == 0:
        return np.zeros(n)
    if degree is not None:
        x = np.arange(n) / max(n - 1, 1)  # in [0, 1]: a well-conditioned fit
        fit = np.polynomial.Polynomial.fit(x[has], own[has], min(degree, len(has) - 1), w=np.sqrt(count[has]))
        return fit(x)
    w = np.exp(-0.5 * ((np.arange(n)[:, None] - has[None, :]) / window) ** 2)
    return (w @ own[has]) / np.maximum(w.sum(axis=1), 1e-300)


def rescale_steps(T_wc: np.ndarray, log_scale: np.ndarray) -> np.ndarray:
    """The path ``T_wc (N, 4, 4)`` with each step's translation, frame j-1 to j, scaled by
    ``exp`` of the two frames' mean ``log_scale``; rotations and frame 0 as they are."""
    out = T_wc.copy()
    for j in range(1, len(T_wc)):
        step = T_wc[j, :3, 3] - T_wc[j - 1, :3, 3]
        out[j, :3, 3] = out[j - 1, :3, 3] + np.exp(0.5 * (log_scale[j] + log_scale[j - 1])) * step
    return out


def reprojection_jacobians(Xc: np.ndarray, R: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Derivatives of pixels ``f * X_c[:2] / X_c[2]`` (``Xc (M, 3)`` in cameras ``R (M, 3, 3)``,
    camera from world; focal lengths ``f (2,)``): with respect to the camera's move
    ``X_c -> exp(w) X_c + v``, ``(M, 2, 6)`` for ``(w, v)``, and to the world point, ``(M, 2, 3)``."""
    z = Xc[:, 2]
    dproj = np.zeros((len(Xc), 2, 3))  # d(pixel) / d(X_c)
    dproj[:, 0, 0], dproj[:, 0, 2] = f[0] / z, -f[0] * Xc[:, 0] / z ** 2
    dproj[:, 1, 1], dproj[:, 1, 2] = f[1] / z, -f[1] * Xc[:, 1] / z ** 2
    return np.concatenate([dproj @ -_skew(Xc), dproj], axis=2), dproj @ R


def rotation_prior_jacobians(M_T: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Derivatives ``(N-1, 2, 3, 3)`` of ``log(M_j^T R_{j+1} R_j^T)`` (``M_T (N-1, 3, 3)`` the
    measured pairs' rotations transposed, ``R (N, 3, 3)`` camera from world) with respect to
    ``w_j`` and ``w_{j+1}`` of the moves ``R -> exp(w) R``, to first order in the residual."""
    return np.stack([-M_T @ R[1:] @ np.swapaxes(R[:-1], 1, 2), M_T], axis=1)


# Up to this many cameras in one adjustment the cameras' reduced system is formed and solved dense
# (6 values a camera: 1000 cameras make a 6000 x 6000 matrix, 288 MB): a sequence's tracks last
# dozens of frames, so the system is nearly dense, and dense products and a Cholesky factorisation
# beat the sparse ones (benchmarks/bench_ba.py). Beyond, sparse.
DENSE_CAMERAS = 1000


def sparse_blocks(values: np.ndarray, rows: np.ndarray, cols: np.ndarray, size: tuple[int, int]) -> Any:
    """A CSR matrix of ``size`` from dense blocks ``values (B, r, c)`` placed at block rows ``rows``
    and block columns ``cols`` (blocks at the same place add)."""
    import scipy.sparse as sp

    r, c = values.shape[1:]
    ri = np.broadcast_to(r * rows[:, None, None] + np.arange(r)[None, :, None], values.shape)
    ci = np.broadcast_to(c * cols[:, None, None] + np.arange(c)[None, None, :], values.shape)
    return sp.csr_matrix((values.ravel(), (ri.ravel(), ci.ravel())), shape=size)


def schur_product(E: np.ndarray, B: np.ndarray, cam: np.ndarray, pt: np.ndarray, n_cam: int) -> Any:
    """``E B E^T`` as a sparse ``(6 n_cam, 6 n_cam)`` matrix, for ``E`` given by its blocks ``E (M, 6,
    3)`` at block row ``cam[m]`` and block column ``pt[m]`` (a camera's block of an observation
    of a point; blocks at the same place add) and ``B`` block-diagonal, its blocks ``B (n_pt, 3,
    3)``: the points' part of the cameras' reduced system. Multiplied block by block (scipy's
    BSR): the same sum as the scalar sparse product, about twice as fast where every point is
    seen from dozens of cameras (benchmarks/bench_ba.py)."""
    import scipy.sparse as sp

    n_pt = len(B)
    F = np.einsum("mij,mjk->mik", E, B[pt])  # E_m B_p
    by_cam, by_pt = np.lexsort((pt, cam)), np.lexsort((cam, pt))
    left = sp.bsr_matrix((F[by_cam], pt[by_cam], np.searchsorted(cam[by_cam], np.arange(n_cam + 1))),
                         shape=(6 * n_cam, 3 * n_pt))
    right = sp.bsr_matrix((np.swapaxes(E, 1, 2)[by_pt], cam[by_pt], np.searchsorted(pt[by_pt], np.arange(n_pt + 1))),
                          shape=(3 * n_pt, 6 * n_cam))
    return (left @ right).tocsr()


def dense_schur_product(E: np.ndarray, B: np.ndarray, cam: np.ndarray, pt: np.ndarray, n_cam: int,
                        chunk: int = 24) -> np.ndarray:
    """:func:`schur_product` as a dense ``(6 n_cam, 6 n_cam)`` array, multiplied by dense matrix
    products over groups of points: the points sorted by how many cameras their track spans (in
    classes of powers of two), then by the first camera that sees them, and cut into groups of
    ``chunk`` (and where the class changes); each group's blocks are laid out over the cameras
    it spans only and multiplied at once. A track spans a run of consecutive frames, so a group
    spans little more than its tracks do, whose lengths differ by 2x at most: on a 500-frame
    sequence's tracks (most a few frames long, a tenth 85 to 318) about twice the work of the
    exact sum and 3x faster than the block-sparse product (benchmarks/bench_ba.py)."""
    n_pt = len(B)
    S = np.zeros((6 * n_cam, 6 * n_cam))
    if not len(pt):
        return S
    keys, inverse = np.unique(cam.astype(np.int64) * n_pt + pt, return_inverse=True)
    if len(keys) < len(pt):  # blocks at one place: added first, each place laid out once below
        summed = np.zeros((len(keys), 6, 3))
        np.add.at(summed, inverse.ravel(), E)
        E, cam, pt = summed, keys // n_pt, keys % n_pt
    F = np.einsum("mij,mjk->mik", E, B[pt])  # E_m B_p
    first, last = np.full(n_pt, n_cam), np.full(n_pt, -1)
    np.minimum.at(first, pt, cam)
    np.maximum.at(last, pt, cam)
    span = np.maximum(last - first + 1, 1)  # points seen by no camera: span 1, an empty group
    length_class = np.floor(np.log2(span)).astype(np.int64)
    order = np.lexsort((span, first, length_class))
    rank = np.empty(n_pt, dtype=np.int64)
    rank[order] = np.arange(n_pt)
    starts = np.union1d(np.arange(0, n_pt, chunk), np.flatnonzero(np.diff(length_class[order])) + 1)
    starts = np.append(starts, n_pt)
    r = rank[pt]
    obs = np.argsort(r, kind="stable")
    bounds = np.searchsorted(r[obs], starts)
    for k in range(len(starts) - 1):
        o = obs[bounds[k]:bounds[k + 1]]
        if not len(o):
            continue
        c, q, size = cam[o], r[o] - starts[k], int(starts[k + 1] - starts[k])
        lo, hi = int(c.min()), int(c.max()) + 1
        left, right = np.zeros((hi - lo, 6, size, 3)), np.zeros((hi - lo, 6, size, 3))
        left[c - lo, :, q], right[c - lo, :, q] = F[o], E[o]
        n = 6 * (hi - lo)
        S[6 * lo:6 * hi, 6 * lo:6 * hi] += left.reshape(n, 3 * size) @ right.reshape(n, 3 * size).T
    return S


def _solve_positive_definite(S: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``S^-1 b`` for the cameras' damped reduced system (symmetric positive definite) by Cholesky;
    by LU where rounding left it indefinite; NaN where it is singular (the step is then damped more)."""
    import scipy.linalg as sla

    try:
        return sla.cho_solve(sla.cho_factor(S, lower=True, check_finite=False), b, check_finite=False)
    except sla.LinAlgError:
        pass
    try:
        return np.linalg.solve(S, b)
    except np.linalg.LinAlgError:
        return np.full_like(b, np.nan)


def _levenberg_marquardt(R: np.ndarray, t: np.ndarray, P: np.ndarray, free: np.ndarray, o_frame: np.ndarray,
                         o_pt: np.ndarray, o_ray: np.ndarray, f: np.ndarray, R_prior: np.ndarray | None,
                         cfg: BAConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    """Minimise the Huber-robust reprojection error (px) over the cameras ``free`` (``R, t``: camera
    from world, ``(N, 3, 3), (N, 3)``) and the points ``P (n_pts, 3)``; observation o is point
    ``o_pt[o]`` at normalised pixel ``o_ray[o]`` in camera ``o_frame[o]``, ``f`` the focal lengths;
    with ``R_prior (N, 3, 3)`` each pair (j, j+1)'s rotation is held to ``R_prior``'s. A camera
    moves as ``X_c -> exp(w) X_c + v``; the points are eliminated from each step's normal equations
    by their Schur complement, and the cameras' reduced system is solved dense by Cholesky (up to
    DENSE_CAMERAS cameras: tracks last dozens of frames) or sparse (it is banded: a camera shares
    tracks with its neighbours only). Returns ``R, t, P`` and the median reprojection
    error before and after."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import spsolve

    n_cam, n_pt = len(free), len(P)
    cam = np.full(len(R), -1)
    cam[free] = np.arange(n_cam)
    oc = cam[o_frame]
    mv = oc >= 0  # observations in a fitted camera
    wr = np.degrees(cfg.rotation_prior_px_per_deg)  # px per radian
    meas_T = None if R_prior is None else np.swapaxes(R_prior[1:] @ np.swapaxes(R_prior[:-1], 1, 2), 1, 2)

    def errors(R: np.ndarray, t: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        Xc = _in_camera(R[o_frame], t[o_frame], P[o_pt])
        with np.errstate(divide="ignore", invalid="ignore"):
            e = (Xc[:, :2] / Xc[:, 2:3] - o_ray) * f
        return np.where(np.isfinite(e) & (Xc[:, 2:3] > 0), e, 1e6), Xc

    def prior_residuals(R: np.ndarray) -> np.ndarray:  # r = log(M^T R_{j+1} R_j^T), in px
        if meas_T is None:
            return np.zeros((0, 3))
        return wr * matrix_to_rotvec(meas_T @ R[1:] @ np.swapaxes(R[:-1], 1, 2))

    def cost(e: np.ndarray, R: np.ndarray) -> float:
        a, k = np.linalg.norm(e, axis=1), cfg.huber_px
        return float(np.sum(np.where(a <= k, 0.5 * a ** 2, k * (a - 0.5 * k)))
                     + 0.5 * np.sum(prior_residuals(R) ** 2))

    e, Xc = errors(R, t, P)
    start = float(np.median(np.linalg.norm(e, axis=1)))
    current, lam = cost(e, R), 1e-3
    for _ in range(cfg.max_iterations):
        a = np.linalg.norm(e, axis=1)
        w = np.where(a <= cfg.huber_px, 1.0, cfg.huber_px / np.maximum(a, 1e-12))  # IRLS weights
        Jc, Jp = reprojection_jacobians(Xc, R[o_frame], f)
        Jc = Jc[mv]
        we = w[:, None] * e
        Hpp = np.zeros((n_pt, 3, 3))
        np.add.at(Hpp, o_pt, np.einsum("mki,m,mkj->mij", Jp, w, Jp))
        gp = np.zeros((n_pt, 3))
        np.add.at(gp, o_pt, np.einsum("mki,mk->mi", Jp, we))
        Hcc = np.zeros((n_cam, 6, 6))
        np.add.at(Hcc, oc[mv], np.einsum("mki,m,mkj->mij", Jc, w[mv], Jc))
        gc = np.zeros((n_cam, 6))
        np.add.at(gc, oc[mv], np.einsum("mki,mk->mi", Jc, we[mv]))
        Eb = np.einsum("mki,m,mkj->mij", Jc, w[mv], Jp[mv])
        E = sparse_blocks(Eb, oc[mv], o_pt[mv], (6 * n_cam, 3 * n_pt))
        H_prior, g_prior = sp.csr_matrix((6 * n_cam, 6 * n_cam)), np.zeros(6 * n_cam)
        if meas_T is not None:
            r = prior_residuals(R)
            J = wr * rotation_prior_jacobians(meas_T, R)  # (n-1, 2, 3, 3)
            c = np.stack([cam[:-1], cam[1:]], axis=1)  # (n-1, 2): -1 where a camera is held
            for i in range(2):
                ok = c[:, i] >= 0
                np.add.at(g_prior, (6 * c[ok, i])[:, None] + np.arange(3), np.einsum("nki,nk->ni", J[ok, i], r[ok]))
                for k in range(2):
                    both = ok & (c[:, k] >= 0)
                    H_prior = H_prior + sparse_blocks(np.einsum("nki,nkj->nij", J[both, i], J[both, k]),
                                                      2 * c[both, i], 2 * c[both, k], (6 * n_cam, 6 * n_cam))
        improved = 0.0
        while lam <= 1e6:
            Hpp_d = Hpp + (lam * np.diagonal(Hpp, axis1=1, axis2=2)[:, None, :] + 1e-9) * np.eye(3)
            Hcc_d = Hcc + (lam * np.diagonal(Hcc, axis1=1, axis2=2)[:, None, :] + 1e-6) * np.eye(6)
            Binv_b = np.linalg.inv(Hpp_d)
            Binv = sparse_blocks(Binv_b, np.arange(n_pt), np.arange(n_pt), (3 * n_pt, 3 * n_pt))
            ar = np.arange(n_cam)
            rhs = -gc.ravel() - g_prior + E @ (Binv @ gp.ravel())
            if n_cam <= DENSE_CAMERAS:
                S = dense_schur_product(Eb, Binv_b, oc[mv], o_pt[mv], n_cam)
                S *= -1.0
                S.reshape(n_cam, 6, n_cam, 6)[ar, :, ar, :] += Hcc_d
                Hp = H_prior.tocoo()
                np.add.at(S, (Hp.row, Hp.col), Hp.data)
                dc = _solve_positive_definite(S, rhs)
            else:
                S = (sparse_blocks(Hcc_d, ar, ar, (6 * n_cam, 6 * n_cam))
                     - schur_product(Eb, Binv_b, oc[mv], o_pt[mv], n_cam) + H_prior).tocsc()
                dc = spsolve(S, rhs)
            dp = -(Binv @ (gp.ravel() + E.T @ dc))
            if not (np.all(np.isfinite(dc)) and np.all(np.isfinite(dp))):
                lam *= 10
                continue
            dc, dp = dc.reshape(-1, 6), dp.reshape(-1, 3)
            step = rotvec_to_matrix(dc[:, :3])
            Rn, tn = R.copy(), t.copy()
            Rn[free] = step @ R[free]
            tn[free] = np.einsum("nij,nj->ni", step, t[free]) + dc[:, 3:]
            Pn = P + dp
            en, Xcn = errors(Rn, tn, Pn)
            new = cost(en, Rn)
            if new < current:
                improved = (current - new) / max(current, 1e-12)
                R, t, P, e, Xc, current = Rn, tn, Pn, en, Xcn, new
                lam = max(lam / 10, 1e-9)
                break
            lam *= 10
        if improved < 1e-6:
            break
    return R, t, P, start, float(np.median(np.linalg.norm(e, axis=1)))
