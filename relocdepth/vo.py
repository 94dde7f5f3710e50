"""A camera trajectory from the essential-matrix bootstrap's own geometry (no ground truth).

Visual odometry by keyframes: each frame's pose relative to the current keyframe comes from
:func:`relocdepth.twoview.bootstrap_pair` (KLT tracks + essential matrix; a pair with too little
parallax keeps its rotation and a zero translation), the unit translation scaled by a depth map
of the keyframe (the median, over the pair's triangulated points, of depth at the point over the
point's depth in baselines, as :func:`relocdepth.method.two_view_poses` does in training). The
first pair with a measured translation (over a minimum baseline) becomes the next keyframe. Every translation is thus in the
depth's units (metres for ground-truth depth, network units for a trained depth network), so the
chain needs no scale propagation. With ``VOConfig.pnp_below`` a pair that KLT tracks at few points
(a fast turn) is measured instead by PnP on the keyframe's depth (:func:`depth_pair_pose`).
With ``VOConfig.bundle`` the poses are then refined jointly by
bundle adjustment over tracks that last several frames (:mod:`relocdepth.ba`). With
``VOConfig.align`` each frame's pose is then refined by
direct alignment to the frame before it (:func:`align_chain`, :mod:`relocdepth.photoalign`): it
uses every textured pixel and the depth, where the pairs use a few tracks and the depth's median.

Several sequences of one place are brought into one world by :func:`register`: frames of a
sequence are linked to their most similar frames of a reference sequence (thumbnail retrieval),
each link gives one reference-world-from-sequence-world transform, and a robust average of the
links is the answer.

Conventions (DESIGN.md): poses are world-from-camera ``T_wc`` (4, 4), OpenCV axes; a sequence's
world is its first frame.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from relocdepth.ba import BAConfig
from relocdepth.errors import UserError
from relocdepth.eval_geometry import chordal_mean_rotation, rotation_angle_deg
from relocdepth.metrics import thumbnail
from relocdepth.photoalign import AlignConfig, View, align
from relocdepth.twoview import (
    BOOTSTRAP_MIN_PARALLAX_PX,
    as_grey,
    bootstrap_pair,
    detect_corners,
    relative_pose_essential,
    track_points,
)

LINK_MATCHERS = ("sift", "klt")

# A sequence counts as placed (:func:`join_sequences`) only when at least this many of its links
# agree on where it lies (the robust mean's inliers, the medoid included); fewer is no consensus. On
# the real walk-through (192x128, step 600) the network's links agreed 1 of 45, 1 of 45 and 1 of 24,
# and the sequences so placed were 65 deg apart in orientation while each was within 1-20 deg of the
# truth on its own; the demo scene's agree 45-75 of 225 (README, trial 20).
MIN_LINK_INLIERS = 3
# A sequence whose links agree this many times is linked to no more sequences (join_sequences): on
# the generated scene of four 500-frame paths, paths that overlap agree 109-300 times, the fourth
# path with the first, which it barely overlaps, 4 times (README, *Sequences placed by the ones they
# overlap*); more sequences would only add links to average.
ENOUGH_LINK_INLIERS = 50

DepthSource = Callable[[int], np.ndarray]


@dataclass(frozen=True)
class VOConfig:
    """Keyframe odometry and cross-sequence registration."""

    min_parallax_px: float = BOOTSTRAP_MIN_PARALLAX_PX  # below: rotation only (the bootstrap's)
    # A measured pair becomes the next keyframe from this baseline (px: the baseline seen at the
    # median depth of its points). Shorter baselines let the rotation absorb part of the
    # translation's motion, and their translations come out short.
    keyframe_baseline_px: float = 1.0
    links_per_frame: int = 3  # reference frames retrieved per query frame (thumbnail similarity)
    # How a link's pair is matched: "sift" (descriptors, for the wide baselines between sequences:
    # on the demo scene the nearest frames of two paths are 25-40 cm and 15-35 deg apart, which KLT
    # does not track) or "klt" (the bootstrap's own pairs).
    link_matcher: str = "sift"
    sift_ratio: float = 0.8  # Lowe's ratio test
    # SIFT links: the essential matrix's RANSAC threshold, and a triangulated match farther than
    # this from its pixel in either image is dropped (SIFT positions are good to ~1 px at 128x96)
    reprojection_px: float = 2.0
    query_every: int = 2  # query every Nth frame of the registered sequence
    inlier_deg: float = 5.0  # a link whose rotation is this far from the links' medoid is dropped
    # Refine the odometry by direct alignment to the previous frame (align_chain). Its precision is
    # the depth's: on the real walk-through (60 frames 20 cm apart, 192x128) ATE 0.237 -> 0.027 m
    # with the true depth, 0.250 -> 0.194 m with a depth network at AbsRel 0.18 and 0.281 -> 0.362
    # at AbsRel 0.25 (README, Quality: trial 25). Off by default: the anchors are built from the
    # network's depth early in training (TrainConfig.anchor_align_step turns it on from a step).
    align: bool = False
    # Refine each sequence's odometry by bundle adjustment over its multi-frame tracks
    # (relocdepth.ba), before any alignment. On the real walk-through (192x128, a depth network at
    # AbsRel ~0.2) ATE 0.223-0.252 -> 0.142-0.147 m; on the demo scene (128x96, true depth) 0.035 /
    # 0.046 -> 0.010 / 0.007 m per sequence (README, Quality: trial 29).
    bundle: bool = False
    bundle_cfg: BAConfig = BAConfig()  # the bundle adjustment's tracks and fit
    # A pair that KLT tracks at fewer than this many points (a fast turn: on the real walk-through
    # at 192x128 a 19 deg turn keeps 14 tracks, and their essential matrix is 7 deg off) is measured
    # instead by PnP: SIFT and KLT matches, image a's points lifted by its depth (depth_pair_pose).
    # 0: never.
    pnp_below: int = 0
    pnp_min_inliers: int = 12  # fewer PnP inliers: the essential matrix's pose is kept


@dataclass
class PairPose:
    """``T (4, 4)`` = ``T_{b<-a}`` with its translation in depth units; whether the pair has a
    measured translation (enough parallax and depth at its points); whether the pair worked; the
    baseline in pixels of image a (focal length / median depth of the points in baselines; 0
    when not measured); whether PnP on the depth measured it (:func:`depth_pair_pose`)."""

    T: np.ndarray
    measured: bool
    ok: bool
    baseline_px: float = 0.0
    pnp: bool = False


@dataclass
class Trajectory:
    """Poses ``T_wc (N, 4, 4)`` (world = first frame), the keyframe indices, the frames whose
    pose could not be measured (they repeat the previous pose), the frames whose pose PnP measured
    (``VOConfig.pnp_below``)."""

    T_wc: np.ndarray
    keyframes: list[int]
    lost: list[int]
    pnp: list[int] = field(default_factory=list)


@dataclass
class Registration:
    """``T (4, 4)``: reference world from the sequence's world; ``links`` tried, ``used`` (had a
    pose), ``inliers`` (agreed with the average)."""

    T: np.ndarray
    links: int
    used: int
    inliers: int


def sample_depth(depth: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Bilinear depth at pixels ``xy (N, 2)`` (x, y; pixel centres at integers) of ``depth (H, W)``;
    NaN outside the image or where a neighbour is invalid (<= 0 or not finite)."""
    depth = np.asarray(depth, np.float64)
    H, W = depth.shape
    x, y = np.asarray(xy, np.float64).T
    out = np.full(len(x), np.nan)
    inside = np.isfinite(x) & np.isfinite(y) & (x >= 0) & (y >= 0) & (x <= W - 1) & (y <= H - 1)
    x0 = np.clip(np.floor(x[inside]).astype(int), 0, max(W - 2, 0))
    y0 = np.clip(np.floor(y[inside]).astype(int), 0, max(H - 2, 0))
    x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
    fx, fy = x[inside] - x0, y[inside] - y0
    d = np.stack([depth[y0, x0], depth[y0, x1], depth[y1, x0], depth[y1, x1]])
    w = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy])
    valid = np.all(np.isfinite(d) & (d > 0), axis=0)
    out[np.flatnonzero(inside)[valid]] = np.sum(d * w, axis=0)[valid]
    return out


def pair_pose(image_a: np.ndarray, image_b: np.ndarray, K_a: np.ndarray, K_b: np.ndarray,
              depth_a: np.ndarray, cfg: VOConfig = VOConfig()) -> PairPose:
    """``T_{b<-a}`` of two images with the translation's length from ``depth_a (H, W)`` (image a's
    depth at its pixels, any units; <= 0 = unknown). A pair that KLT tracks at fewer than
    ``cfg.pnp_below`` points is measured by :func:`depth_pair_pose` where that works."""
    tracked = None  # tracked here only when the count decides (bootstrap_pair tracks otherwise)
    if cfg.pnp_below > 0:
        grey_a = as_grey(image_a)
        tracked = track_points(grey_a, as_grey(image_b), detect_corners(grey_a))
        if len(tracked[0]) < cfg.pnp_below:
            p = depth_pair_pose(image_a, image_b, K_a, K_b, depth_a, cfg, tracked)
            if p.ok:
                return p
    T, points, ok = bootstrap_pair(image_a, image_b, np.asarray(K_a), np.asarray(K_b),
                                   min_parallax_px=cfg.min_parallax_px, tracked=tracked)
    T = T.astype(np.float64)
    has = np.isfinite(points[:, 2])
    if not ok or not has.any():
        return PairPose(T, False, bool(ok))
    ratio = sample_depth(depth_a, points[has, :2]) / points[has, 2]
    ratio = ratio[np.isfinite(ratio)]
    if len(ratio) == 0:  # a translation of unknown length is no pose
        return PairPose(np.eye(4), False, False)
    T[:3, 3] *= float(np.median(ratio))
    baseline_px = float(K_a[0, 0] / np.median(points[has, 2]))
    return PairPose(T, True, True, baseline_px)


def depth_pair_pose(image_a: np.ndarray, image_b: np.ndarray, K_a: np.ndarray, K_b: np.ndarray,
                    depth_a: np.ndarray, cfg: VOConfig = VOConfig(),
                    tracked: tuple[np.ndarray, np.ndarray] | None = None) -> PairPose:
    """``T_{b<-a}`` by PnP: SIFT matches and KLT tracks (``tracked``: already tracked ``(pa, pb)``)
    from a to b, the points of a lifted to 3-D by ``depth_a`` (any units, <= 0 unknown), EPnP in
    RANSAC (``cfg.reprojection_px`` in b), Levenberg-Marquardt on the inliers. Unlike the
    essential matrix it needs no baseline, and with the depth a few matches fix the rotation of a
    fast turn; its translation is in the depth's units and as good as the depth. Not ``ok`` with
    fewer than ``cfg.pnp_min_inliers`` inliers."""
    import cv2

    fail = PairPose(np.eye(4), False, False)
    if tracked is None:
        grey_a = as_grey(image_a)
        tracked = track_points(grey_a, as_grey(image_b), detect_corners(grey_a))
    sa, sb = sift_matches(image_a, image_b, cfg.sift_ratio)
    pa = np.concatenate([tracked[0], sa]).astype(np.float64)
    pb = np.concatenate([tracked[1], sb]).astype(np.float64)
    z = sample_depth(depth_a, pa)
    has = np.isfinite(z)
    if has.sum() < max(cfg.pnp_min_inliers, 4):
        return fail
    Ka, Kb = np.asarray(K_a, np.float64), np.asarray(K_b, np.float64)
    X = np.c_[(pa[has] - Ka[:2, 2]) / np.diag(Ka)[:2], np.ones(has.sum())] * z[has, None]
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(X, pb[has], Kb, None, reprojectionError=cfg.reprojection_px,
                                                 iterationsCount=500, confidence=0.999,
                                                 flags=cv2.SOLVEPNP_EPNP)
    if not ok or inliers is None or len(inliers) < cfg.pnp_min_inliers:
        return fail
    inl = inliers.ravel()
    rvec, tvec = cv2.solvePnPRefineLM(X[inl], pb[has][inl], Kb, None, rvec, tvec)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
    baseline_px = float(Ka[0, 0] * np.linalg.norm(T[:3, 3]) / np.median(X[inl, 2]))
    return PairPose(T, True, True, baseline_px, pnp=True)


def sift_matches(image_a: np.ndarray, image_b: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """SIFT matches ``(N, 2), (N, 2)`` (x, y pixels in a and in b) that pass the ratio test."""
    import cv2

    sift = cv2.SIFT_create()
    ka, da = sift.detectAndCompute(as_grey(image_a), None)
    kb, db = sift.detectAndCompute(as_grey(image_b), None)
    if da is None or db is None or len(ka) < 2 or len(kb) < 2:
        return np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32)
    good = [m[0] for m in cv2.BFMatcher().knnMatch(da, db, k=2)
            if len(m) == 2 and m[0].distance < ratio * m[1].distance]
    pa = np.float32([ka[m.queryIdx].pt for m in good]).reshape(-1, 2)
    pb = np.float32([kb[m.trainIdx].pt for m in good]).reshape(-1, 2)
    return pa, pb


def wide_pair_pose(image_a: np.ndarray, image_b: np.ndarray, K_a: np.ndarray, K_b: np.ndarray,
                   depth_a: np.ndarray, cfg: VOConfig = VOConfig()) -> PairPose:
    """:func:`pair_pose` for views far apart: SIFT matches, the essential matrix of the normalised
    matches, the matches triangulated (kept within ``cfg.reprojection_px`` in both images, in
    front of both cameras), the translation's length from ``depth_a`` at them."""
    import cv2

    pa, pb = sift_matches(image_a, image_b, cfg.sift_ratio)
    if len(pa) < 5:  # the essential matrix needs five
        return PairPose(np.eye(4), False, False)
    Ka, Kb = np.asarray(K_a, np.float64), np.asarray(K_b, np.float64)
    na = cv2.undistortPoints(pa.reshape(-1, 1, 2), Ka, None).reshape(-1, 2)
    nb = cv2.undistortPoints(pb.reshape(-1, 1, 2), Kb, None).reshape(-1, 2)
    try:
        rel = relative_pose_essential(na, nb, np.eye(3), cfg.reprojection_px / Ka[0, 0])
    except UserError:
        return PairPose(np.eye(4), False, False)
    P_b = np.hstack((rel.R, rel.t[:, None]))
    X = cv2.triangulatePoints(np.eye(3, 4), P_b, na.T, nb.T)
    with np.errstate(divide="ignore", invalid="ignore"):
        X = (X[:3] / X[3]).T  # (N, 3) in camera a, baselines
        Xb = X @ rel.R.T + rel.t
        err_a = np.linalg.norm(X[:, :2] / X[:, 2:] - na, axis=1) * Ka[0, 0]
        err_b = np.linalg.norm(Xb[:, :2] / Xb[:, 2:] - nb, axis=1) * Kb[0, 0]
    good = (X[:, 2] > 0) & (Xb[:, 2] > 0) & (err_a < cfg.reprojection_px) & (err_b < cfg.reprojection_px)
    ratio = sample_depth(depth_a, pa[good]) / X[good, 2]
    ratio = ratio[np.isfinite(ratio)]
    if len(ratio) < 5:
        return PairPose(np.eye(4), False, False)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = rel.R, rel.t * float(np.median(ratio))
    return PairPose(T, True, True, float(Ka[0, 0] / np.median(X[good, 2])))


def chain(images: Sequence[np.ndarray], K: np.ndarray, depth: DepthSource,
          cfg: VOConfig = VOConfig()) -> Trajectory:
    """Keyframe odometry of one sequence: ``images`` in order (same camera ``K (3, 3)``),
    ``depth(i)`` the depth map of frame i (asked for keyframes only).

    Frame j's pose comes from its pair with the current keyframe; the first frame whose pair has a
    measured translation over a baseline of ``cfg.keyframe_baseline_px`` becomes the next keyframe. When a pair fails, the frame before it becomes
    the keyframe and the pair is tried once more; when that fails too, the frame keeps the previous
    pose (listed in ``lost``) and becomes the keyframe itself.
    """
    n = len(images)
    T_wc = np.repeat(np.eye(4)[None], n, axis=0)
    kf, keyframes, lost, pnp = 0, [0], [], []
    kf_depth = depth(0) if n else None
    for j in range(1, n):
        p = pair_pose(images[kf], images[j], K, K, kf_depth, cfg)
        if not p.ok and j - 1 > kf:
            kf = j - 1
            keyframes.append(kf)
            kf_depth = depth(kf)
            p = pair_pose(images[kf], images[j], K, K, kf_depth, cfg)
        if not p.ok:
            T_wc[j] = T_wc[j - 1]
            lost.append(j)
        else:
            T_wc[j] = T_wc[kf] @ np.linalg.inv(p.T)
            if p.pnp:
                pnp.append(j)
        if (p.measured and p.baseline_px >= cfg.keyframe_baseline_px) or not p.ok:
            kf = j
            keyframes.append(kf)
            kf_depth = depth(kf)
    return Trajectory(T_wc, keyframes, lost, pnp)


def robust_mean_transform(T: np.ndarray, inlier_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """A robust average of rigid transforms ``T (M, 4, 4)``: the rotation medoid (least summed
    angle to the others) picks the inliers (within ``inlier_deg``), whose chordal mean rotation and
    per-axis median translation are the answer. Returns ``(T (4, 4), inlier mask (M,))``."""
    T = np.asarray(T, np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or len(T) == 0:
        raise ValueError(f"expected (M, 4, 4) transforms with M >= 1, got {T.shape}")
    R = T[:, :3, :3]
    angles = rotation_angle_deg(np.einsum("aji,bjk->abik", R, R))  # (M, M) pairwise
    medoid = int(np.argmin(angles.sum(axis=1)))
    inl = angles[medoid] <= inlier_deg
    out = np.eye(4)
    out[:3, :3] = chordal_mean_rotation(R[inl])
    out[:3, 3] = np.median(T[inl, :3, 3], axis=0)
    return out, inl


def register(ref_images: Sequence[np.ndarray], ref_T: np.ndarray, ref_K: np.ndarray,
             ref_depth: DepthSource, images: Sequence[np.ndarray], T: np.ndarray, K: np.ndarray,
             cfg: VOConfig = VOConfig()) -> Registration:
    """The reference world from a sequence's world, both trajectories from :func:`chain` with
    depth in the same units.

    Every ``cfg.query_every``-th frame b of the sequence is linked to its ``cfg.links_per_frame``
    most similar reference frames a (normalised grey thumbnails, as the evaluation's retrieval
    reference); each link's pair pose (``cfg.link_matcher``: :func:`wide_pair_pose` or
    :func:`pair_pose`) gives ``ref_T[a] T_{b<-a}^-1 T[b]^-1``, and
    :func:`robust_mean_transform` averages them.
    """
    ref_thumbs = np.stack([thumbnail(im) for im in ref_images])
    candidates, links = link_transforms(ref_images, ref_T, ref_K, ref_depth, ref_thumbs, images, T, K, cfg)
    return average_links(candidates, links, cfg)


def link_transforms(ref_images: Sequence[np.ndarray], ref_T: np.ndarray, ref_K: np.ndarray,
                    ref_depth: DepthSource, ref_thumbs: np.ndarray, images: Sequence[np.ndarray],
                    T: np.ndarray, K: np.ndarray, cfg: VOConfig = VOConfig()) -> tuple[list[np.ndarray], int]:
    """:func:`register`'s links (``ref_thumbs``: the reference frames' thumbnails): the transforms
    (reference world from the sequence's world) of those whose pair pose was measured, and how
    many links were tried."""
    if cfg.link_matcher not in LINK_MATCHERS:
        raise ValueError(f"link_matcher must be one of {LINK_MATCHERS}, not {cfg.link_matcher!r}")
    link_pose = wide_pair_pose if cfg.link_matcher == "sift" else pair_pose
    queries = list(range(0, len(images), cfg.query_every))
    sims = np.stack([thumbnail(images[b]) for b in queries]) @ ref_thumbs.T
    candidates, links = [], 0
    depth_cache: dict[int, np.ndarray] = {}
    for qi, b in enumerate(queries):
        for a in np.argsort(-sims[qi])[: cfg.links_per_frame]:
            a = int(a)
            links += 1
            if a not in depth_cache:
                depth_cache[a] = ref_depth(a)
            p = link_pose(ref_images[a], images[b], ref_K, K, depth_cache[a], cfg)
            if p.ok:
                candidates.append(ref_T[a] @ np.linalg.inv(p.T) @ np.linalg.inv(T[b]))
    return candidates, links


def average_links(candidates: list[np.ndarray], links: int, cfg: VOConfig = VOConfig()) -> Registration:
    """The :class:`Registration` of a sequence's link transforms (:func:`link_transforms`, out of
    ``links`` tried): their robust mean (:func:`robust_mean_transform`)."""
    if not candidates:
        return Registration(np.eye(4), links, 0, 0)
    M, inl = robust_mean_transform(np.stack(candidates), cfg.inlier_deg)
    return Registration(M, links, len(candidates), int(inl.sum()))


def align_chain(images: Sequence[np.ndarray], K: np.ndarray, depth: DepthSource, T_wc: np.ndarray,
                cfg: AlignConfig = AlignConfig()) -> tuple[np.ndarray, int]:
    """Odometry ``T_wc (N, 4, 4)`` of ``images`` (camera ``K``; from :func:`chain`) refined frame by
    frame: frame j starts from frame j-1's refined pose moved by the odometry's step between them,
    and is aligned to frame j-1 (its image, ``depth(j - 1)`` and refined pose;
    :func:`relocdepth.photoalign.align`). An alignment that is not trusted keeps the start.
    Returns the refined poses (frame 0 as given) and how many alignments were trusted."""
    T_wc = np.asarray(T_wc, np.float64)
    out = T_wc.copy()
    trusted = 0
    for j in range(1, len(images)):
        start = out[j - 1] @ np.linalg.inv(T_wc[j - 1]) @ T_wc[j]
        r = align([View(images[j - 1], depth(j - 1), K, out[j - 1])], images[j], K, start, cfg)
        out[j] = r.T_wc if r.accepted else start
        trusted += r.accepted
    return out, trusted


@dataclass
class World:
    """Every sequence's odometry (:func:`chain`), the registrations of sequences 2.. into the first
    one's world (:func:`join_sequences`), each sequence's poses in that world ``(N_i, 4, 4)``, the CPU
    seconds of odometry and of registration, how many frame-to-frame alignments were trusted
    (``VOConfig.align``; 0 without it), and per sequence what the bundle adjustment did
    (``VOConfig.bundle``: :meth:`relocdepth.ba.Adjusted.summary`; None without it)."""

    trajs: list[Trajectory]
    regs: list[Registration]
    world: list[np.ndarray]
    vo_s: float
    reg_s: float
    aligned: int = 0
    bundled: list[dict] | None = None


def world_trajectory(images: Sequence[Sequence[np.ndarray]], K: Sequence[np.ndarray],
                     depth: Sequence[DepthSource], cfg: VOConfig = VOConfig()) -> World:
    """One world for several sequences of one place: odometry per sequence (``images[i]`` in order,
    camera ``K[i]``, depth maps ``depth[i](j)``), every sequence after the first registered into the
    first one's world (whose origin is its first frame; units: the depth's) by
    :func:`join_sequences`."""
    if not (len(images) == len(K) == len(depth)) or not images:
        raise ValueError("world_trajectory needs images, K and depth for each of >= 1 sequences")
    t0 = time.process_time()
    trajs = [chain(im, k, d, cfg) for im, k, d in zip(images, K, depth)]
    bundled = None
    if cfg.bundle:
        from relocdepth.ba import bundle_adjust

        adjusted = [bundle_adjust(im, k, tr.T_wc, d, cfg.bundle_cfg)
                    for tr, im, k, d in zip(trajs, images, K, depth)]
        trajs = [replace(tr, T_wc=a.T_wc) for tr, a in zip(trajs, adjusted)]
        bundled = [a.summary() for a in adjusted]
    aligned = 0
    if cfg.align:
        refined = [align_chain(im, k, d, tr.T_wc) for tr, im, k, d in zip(trajs, images, K, depth)]
        trajs = [replace(tr, T_wc=T) for tr, (T, _) in zip(trajs, refined)]
        aligned = sum(n for _, n in refined)
    vo_s, t0 = time.process_time() - t0, time.process_time()
    regs, world = join_sequences(images, K, [tr.T_wc for tr in trajs], depth, cfg)
    return World(trajs, regs, world, vo_s, time.process_time() - t0, aligned, bundled)


def join_sequences(images: Sequence[Sequence[np.ndarray]], K: Sequence[np.ndarray], T_wc: Sequence[np.ndarray],
                   depth: Sequence[DepthSource], cfg: VOConfig = VOConfig()) -> tuple[list[Registration], list[np.ndarray]]:
    """Sequences whose poses ``T_wc[i] (N_i, 4, 4)`` are each in a world of their own (the same
    units: ``depth``'s), put in the first one's world; returns the registrations (one per sequence
    after the first, in order) and every sequence's poses in that world.

    The sequences are placed one at a time, best linked first. Every sequence not yet placed is
    linked (:func:`link_transforms`) to each placed one in turn, until :data:`ENOUGH_LINK_INLIERS`
    of its links agree; its links to all the placed ones are averaged together
    (:func:`average_links`), and the sequence whose links agree most is placed next. So a sequence
    that shares little view with the first is placed by those it does share views with, and the
    sequences placed on the strongest links are the references of the weaker ones, whatever the
    order given. Placing stops when no sequence left has :data:`MIN_LINK_INLIERS` agreeing links;
    those keep their best registration (its ``inliers`` say so). With two sequences this is
    :func:`register` of the second into the first.
    """
    if not (len(images) == len(K) == len(T_wc) == len(depth)) or not images:
        raise ValueError("join_sequences needs images, K, poses and depth for each of >= 1 sequences")
    n = len(images)
    world = [np.asarray(T, np.float64) for T in T_wc]
    thumbs = [np.stack([thumbnail(im) for im in seq]) for seq in images]
    pool: dict[int, list[np.ndarray]] = {k: [] for k in range(1, n)}  # link transforms into the world
    links = dict.fromkeys(pool, 0)
    regs = {k: Registration(np.eye(4), 0, 0, 0) for k in pool}
    placed, new = [0], 0
    while len(placed) < n:
        left = [k for k in pool if k not in placed]
        for k in left:  # links to the sequence placed last; those to the others are pooled already
            if regs[k].inliers >= ENOUGH_LINK_INLIERS:
                continue
            c, m = link_transforms(images[new], world[new], K[new], depth[new], thumbs[new],
                                   images[k], world[k], K[k], cfg)
            pool[k] += c
            links[k] += m
            regs[k] = average_links(pool[k], links[k], cfg)
        best = max(left, key=lambda k: regs[k].inliers)
        if regs[best].inliers < MIN_LINK_INLIERS:
            break
        world[best] = regs[best].T @ world[best]
        placed.append(best)
        new = best
    for k in pool:
        if k not in placed:  # no consensus: where its best registration puts it
            world[k] = regs[k].T @ world[k]
    return [regs[k] for k in range(1, n)], world

