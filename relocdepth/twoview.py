"""Two-view geometry from point tracks: KLT tracking, homography residual, essential-matrix pose.

Tracks are Shi-Tomasi corners (``cv2.goodFeaturesToTrack``) followed by pyramidal Lucas-Kanade
(``cv2.calcOpticalFlowPyrLK``) with a forward-backward check, on grey images (usually a small
copy, e.g. 160 px wide: tracking is then cheap and the pyramid covers large motions).

Conventions (DESIGN.md): poses are world-from-camera ``T_wc``, OpenCV camera axes. The relative
pose returned by :func:`relative_pose_essential` is ``T_{b<-a}``: it maps points in camera ``a``
into camera ``b`` (``X_b = R X_a + t``), the same transform as
``relocdepth.geometry.relative_pose(T_wc_a, T_wc_b) = T_wc_b^-1 T_wc_a`` (the trainer's
``T_{t->s}`` with a = target, b = source). Monocular: ``t`` has unit length, its scale is unknown.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from relocdepth.errors import UserError


@dataclass(frozen=True)
class TrackConfig:
    """Corner detection and KLT tracking (OpenCV's usual values for ~160-640 px wide images)."""

    max_corners: int = 300  # Shi-Tomasi corners per image
    quality_level: float = 0.01  # relative corner strength (OpenCV samples use 0.01-0.3)
    min_distance: float = 4.0  # px between corners: spreads tracks over the image
    win_size: int = 15  # LK window (px)
    # Pyramid levels: each one doubles the motion the window can follow (~100 px with 3). OpenCV
    # stops where a level would be no larger than the window, so 5 is the same as 3 up to 320x240
    # and is 4 from 384x256 to 640x480, where 3 lost the pairs that turn fast (the real walk-through
    # at 540x360 turns up to 12 deg, ~110 px, between frames).
    max_level: int = 5
    fb_max_px: float = 1.0  # forward-backward disagreement above this drops a track


class TwoViewPose(NamedTuple):
    """Relative pose ``T_{b<-a}`` (``X_b = R X_a + t``), unit ``t``, and RANSAC inlier count."""

    R: np.ndarray  # (3, 3)
    t: np.ndarray  # (3,) unit length
    inliers: int


def as_grey(image: np.ndarray) -> np.ndarray:
    """uint8 grey (H, W) from grey (H, W) or 3-channel (H, W, 3) images (channel order ignored)."""
    import cv2

    if image.ndim == 2:
        return np.ascontiguousarray(image, dtype=np.uint8)
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(np.ascontiguousarray(image, dtype=np.uint8), cv2.COLOR_BGR2GRAY)
    raise ValueError(f"expected an (H, W) or (H, W, 3) image, got shape {image.shape}")


def detect_corners(grey: np.ndarray, cfg: TrackConfig = TrackConfig(),
                   mask: np.ndarray | None = None) -> np.ndarray:
    """Shi-Tomasi corners ``(N, 2)`` float32 (x, y pixels) of an (H, W) uint8 image, strongest
    first; N may be 0. ``mask (H, W)`` uint8: corners only where it is non-zero."""
    import cv2

    pts = cv2.goodFeaturesToTrack(grey, cfg.max_corners, cfg.quality_level, cfg.min_distance, mask=mask)
    return np.zeros((0, 2), np.float32) if pts is None else pts.reshape(-1, 2).astype(np.float32)


def track_points(grey_a: np.ndarray, grey_b: np.ndarray, pts_a: np.ndarray,
                 cfg: TrackConfig = TrackConfig()) -> tuple[np.ndarray, np.ndarray]:
    """Track ``pts_a (N, 2)`` from ``grey_a`` into ``grey_b`` (both (H, W) uint8).

    Returns the kept points ``(M, 2)`` in a and their positions ``(M, 2)`` in b (float32): tracks
    that LK lost, that left the image, or whose backward track misses the start by more than
    ``cfg.fb_max_px`` are dropped (:func:`track_mask`).
    """
    q, keep = track_mask(grey_a, grey_b, pts_a, cfg)
    return np.ascontiguousarray(pts_a, dtype=np.float32).reshape(-1, 2)[keep], q[keep]


def track_mask(grey_a: np.ndarray, grey_b: np.ndarray, pts_a: np.ndarray,
               cfg: TrackConfig = TrackConfig()) -> tuple[np.ndarray, np.ndarray]:
    """Positions ``(N, 2)`` float32 in ``grey_b`` of ``pts_a (N, 2)`` tracked from ``grey_a``, and
    which of them to keep ``(N,)`` bool (found both ways, inside b, forward-backward within
    ``cfg.fb_max_px``)."""
    import cv2

    if len(pts_a) == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    p0 = np.ascontiguousarray(pts_a, dtype=np.float32).reshape(-1, 1, 2)
    lk = {"winSize": (cfg.win_size, cfg.win_size), "maxLevel": cfg.max_level,
          "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.03)}
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(grey_a, grey_b, p0, None, **lk)
    p0r, st2, _ = cv2.calcOpticalFlowPyrLK(grey_b, grey_a, p1, None, **lk)
    h, w = grey_b.shape[:2]
    q = p1.reshape(-1, 2)
    fb = np.linalg.norm(p0r.reshape(-1, 2) - p0.reshape(-1, 2), axis=1)
    inside = (q[:, 0] >= 0) & (q[:, 0] <= w - 1) & (q[:, 1] >= 0) & (q[:, 1] <= h - 1)
    keep = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb <= cfg.fb_max_px) & inside
    return q, keep


def homography_residual(pts_a: np.ndarray, pts_b: np.ndarray, ransac_px: float,
                        min_points: int = 8, max_iters: int = 500) -> float:
    """Median distance (px) between ``pts_b`` and the RANSAC homography's image of ``pts_a``.

    A homography explains any rotation about the camera centre and any single plane, so what is
    left is parallax: motion that depends on depth. NaN with fewer than ``min_points`` tracks or
    when no homography is found. ``max_iters`` caps RANSAC (OpenCV's 2000 costs ~10 ms on
    outlier-heavy tracks; the median needs only a rough fit).
    """
    import cv2

    if len(pts_a) < max(min_points, 4):
        return float("nan")
    H, _ = cv2.findHomography(pts_a, pts_b, cv2.RANSAC, ransac_px, maxIters=max_iters, confidence=0.995)
    if H is None or not np.all(np.isfinite(H)):
        return float("nan")
    x = np.c_[pts_a.astype(np.float64), np.ones(len(pts_a))] @ H.T
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = x[:, :2] / x[:, 2:3]
    res = np.linalg.norm(proj - pts_b, axis=1)
    res = res[np.isfinite(res)]
    return float(np.median(res)) if len(res) >= min_points else float("nan")


# Robust estimators for the essential matrix. MAGSAC++ (OpenCV's USAC) is the default: on rendered
# pairs 5-13 cm apart it recovers the translation direction to 0.3-3.4 deg where plain RANSAC is
# off by 2-17 deg (tests/test_twoview.py renders such pairs).
ESSENTIAL_METHODS = ("magsac", "ransac")


def relative_pose_essential(pts_a: np.ndarray, pts_b: np.ndarray, K: np.ndarray,
                            ransac_px: float = 1.0, prob: float = 0.999,
                            method: str = "magsac") -> TwoViewPose:
    """Relative pose ``T_{b<-a}`` from matched pixels (``cv2.findEssentialMat`` + ``recoverPose``).

    Args:
        pts_a, pts_b: ``(N, 2)`` matching pixel positions (x, y) in images a and b, N >= 5.
        K: ``(3, 3)`` intrinsics of both images (pixels of the images the points are in).
        ransac_px: RANSAC threshold (px) on the epipolar distance.
        method: ``"magsac"`` (MAGSAC++, ``cv2.USAC_MAGSAC``) or ``"ransac"`` (``cv2.RANSAC``).
    Returns:
        :class:`TwoViewPose` ``(R (3, 3), t (3,) unit, inliers)`` with ``X_b = R X_a + t``, i.e.
        ``relocdepth.geometry.relative_pose(T_wc_a, T_wc_b)`` up to the scale of ``t``.
    Raises:
        UserError: too few points, or no pose found (e.g. no translation: a pure rotation has no
        essential matrix).

    Example:
        >>> pose = relative_pose_essential(pts_a, pts_b, K)
        >>> X_b = pose.R @ X_a + pose.t  # up to the unknown scale of the translation
    """
    import cv2

    pts_a = np.ascontiguousarray(pts_a, dtype=np.float64).reshape(-1, 2)
    pts_b = np.ascontiguousarray(pts_b, dtype=np.float64).reshape(-1, 2)
    K = np.asarray(K, dtype=np.float64)
    if pts_a.shape != pts_b.shape:
        raise ValueError(f"pts_a {pts_a.shape} and pts_b {pts_b.shape} differ")
    if K.shape != (3, 3):
        raise ValueError(f"K must be (3, 3), got {K.shape}")
    if method not in ESSENTIAL_METHODS:
        raise ValueError(f"method must be one of {ESSENTIAL_METHODS}, not {method!r}")
    if len(pts_a) < 5:
        raise UserError(f"two-view pose needs at least 5 matched points, got {len(pts_a)}")
    flag = cv2.USAC_MAGSAC if method == "magsac" else cv2.RANSAC
    E, mask = cv2.findEssentialMat(pts_a, pts_b, K, flag, prob, ransac_px)
    if E is None or E.shape[0] < 3:
        raise UserError("no essential matrix found (too little translation or too few good tracks)")
    E = E[:3]  # several solutions may be stacked; the first is RANSAC's best
    n, R, t, mask = cv2.recoverPose(E, pts_a, pts_b, K, mask=mask)
    if n < 5:
        raise UserError(f"two-view pose: only {n} points in front of both cameras")
    t = t.ravel()
    return TwoViewPose(R, t / np.linalg.norm(t), int(n))


def relative_pose_images(image_a: np.ndarray, image_b: np.ndarray, K: np.ndarray,
                         cfg: TrackConfig = TrackConfig(), ransac_px: float = 1.0,
                         method: str = "magsac") -> TwoViewPose:
    """:func:`relative_pose_essential` on KLT tracks between two images (grey or 3-channel, same
    size, ``K`` in their pixels)."""
    grey_a, grey_b = as_grey(image_a), as_grey(image_b)
    if grey_a.shape != grey_b.shape:
        raise ValueError(f"images differ in size: {grey_a.shape} vs {grey_b.shape}")
    pa, pb = track_points(grey_a, grey_b, detect_corners(grey_a, cfg), cfg)
    return relative_pose_essential(pa, pb, K, ransac_px, method=method)


# Points per pair that the training bootstrap keeps for scaling the translation (padded with NaN).
BOOTSTRAP_POINTS = 64
# Below this median parallax (px: the tracks' motion that the recovered rotation does not explain)
# a pair's translation direction is noise. Measured on the demo scene at 128x96 (pairs 1-6 frames
# apart, against ground truth): median direction error 61-69 deg below 0.7 px, 21 deg at 0.7-1 px,
# 5.5 deg at 1-1.5 px, 2-4 deg above; the rotation stays within 0.1-0.4 deg throughout.
BOOTSTRAP_MIN_PARALLAX_PX = 1.0
# recoverPose counts a point only when it triangulates nearer than a distance in baselines,
# 50 by default: a parallax of f / 50 px, ~2 px at 128x96 but ~10 px at 640x480. A pair whose
# points are nearly all farther and which moves too much for a rotation alone (a 1 cm step at 1.2 m
# is ~4 px at 640x480) is counted again up to this distance, where the parallax test
# (BOOTSTRAP_MIN_PARALLAX_PX) decides: f / 1000 px is under a pixel at any size here. The demo
# rendered at 640x480, pairs 1 / 3 frames apart: 15 / 45 of 60 worked with 50 alone, 60 / 60 so.
BOOTSTRAP_FAR_BASELINES = 1000.0


def bootstrap_pair(image_a: np.ndarray, image_b: np.ndarray, K_a: np.ndarray, K_b: np.ndarray,
                   n_points: int = BOOTSTRAP_POINTS, ransac_px: float = 1.0,
                   min_parallax_px: float = BOOTSTRAP_MIN_PARALLAX_PX,
                   cfg: TrackConfig = TrackConfig(),
                   tracked: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, bool]:
    """Relative pose and triangulated depths of a training pair, for the essential-matrix bootstrap.

    The two images may have different intrinsics (training crops and scales each image), so the
    tracks are normalised by their own ``K`` before the essential matrix (identity camera, threshold
    ``ransac_px / f_a``). Returns ``T (4, 4)`` = ``T_{b<-a}`` with a unit translation (identity when
    it fails), ``points (n_points, 3)`` = pixel ``(x, y)`` in image a and the depth of the
    triangulated inlier there in units of the baseline (NaN rows past the inliers), and ``ok``.
    The depth network's depth at those pixels over these depths is the translation's length in its
    units (``relocdepth.method``).

    A pair whose inliers move less than ``min_parallax_px`` (median, pixels of image b) beyond what
    the rotation explains is *rotation only*: its translation is too small to measure, so ``T``
    carries the rotation and a zero translation, ``points`` are all NaN, and ``ok`` is True.

    ``tracked``: the pair's tracks ``(pa, pb)`` when the caller has already tracked them
    (:func:`track_points` from :func:`detect_corners` with ``cfg``).
    """
    import cv2

    T = np.eye(4, dtype=np.float32)
    points = np.full((n_points, 3), np.nan, dtype=np.float32)
    if tracked is None:
        grey_a = as_grey(image_a)
        tracked = track_points(grey_a, as_grey(image_b), detect_corners(grey_a, cfg), cfg)
    pa, pb = tracked
    if len(pa) < 8:
        return T, points, False

    def normalised(p: np.ndarray, K: np.ndarray) -> np.ndarray:
        return ((p - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])).astype(np.float64)

    na, nb = normalised(pa, K_a), normalised(pb, K_b)
    def rotation_only() -> tuple[np.ndarray, np.ndarray, bool]:
        # the essential matrix needs a baseline; a camera that (nearly) only turned has none, and
        # its rotation is the homography's
        R_h = _rotation_from_homography(na, nb, ransac_px / float(K_a[0, 0]))
        if R_h is None or _rotation_residual_px(na, pb, R_h, K_b) >= min_parallax_px:
            return T, points, False
        T[:3, :3] = R_h
        return T, points, True

    E, mask = cv2.findEssentialMat(na, nb, np.eye(3), cv2.USAC_MAGSAC, 0.999, ransac_px / float(K_a[0, 0]))
    if E is None or E.shape[0] < 3:
        return rotation_only()
    n, R, t, near = cv2.recoverPose(E[:3], na, nb, np.eye(3), mask=mask.copy())
    if n < 8:  # also when the points triangulate too far (> 50 baselines): too little baseline
        rot = rotation_only()
        if rot[2]:
            return rot
        # too much parallax for a rotation: count the far points too (see BOOTSTRAP_FAR_BASELINES)
        n, R, t, near, _ = cv2.recoverPose(E[:3], na, nb, np.eye(3), distanceThresh=BOOTSTRAP_FAR_BASELINES,
                                           mask=mask)
        if n < 8:
            return rot
    t = t.ravel() / np.linalg.norm(t)
    inl = near.ravel() > 0
    if _rotation_residual_px(na[inl], pb[inl], R, K_b) < min_parallax_px:
        T[:3, :3] = R
        return T, points, True
    X = cv2.triangulatePoints(np.eye(3, 4), np.hstack((R, t[:, None])), na[inl].T, nb[inl].T)
    z = X[2] / X[3]
    good = np.isfinite(z) & (z > 0)
    xy, z = pa[inl][good], z[good]
    if len(z) < 5:
        return T, points, False
    keep = np.linspace(0, len(z) - 1, min(n_points, len(z))).astype(int)
    points[: len(keep), :2], points[: len(keep), 2] = xy[keep], z[keep]
    T[:3, :3], T[:3, 3] = R, t
    return T, points, True


def _rotation_from_homography(na: np.ndarray, nb: np.ndarray, threshold: float) -> np.ndarray | None:
    """The rotation nearest to the RANSAC homography between normalised points ``na``, ``nb``
    ``(N, 2)`` (for a camera that only turns, the homography is that rotation), or None."""
    import cv2

    H, _ = cv2.findHomography(na, nb, cv2.RANSAC, threshold, maxIters=500, confidence=0.995)
    if H is None or not np.all(np.isfinite(H)):
        return None
    from relocdepth.eval_geometry import project_to_so3

    return project_to_so3(H * np.sign(np.linalg.det(H)))  # a positive multiple of the rotation


def _rotation_residual_px(rays_a: np.ndarray, pts_b: np.ndarray, R: np.ndarray, K_b: np.ndarray) -> float:
    """Median distance (px) between ``pts_b (N, 2)`` and where the rotation alone takes the
    normalised points ``rays_a (N, 2)`` of image a: the parallax the translation has to explain."""
    x = np.c_[rays_a, np.ones(len(rays_a))] @ np.asarray(R, np.float64).T
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = x[:, :2] / x[:, 2:3] * np.array([K_b[0, 0], K_b[1, 1]]) + K_b[:2, 2]
    res = np.linalg.norm(proj - pts_b, axis=1)
    res = res[np.isfinite(res)]
    return float(np.median(res)) if len(res) else 0.0
