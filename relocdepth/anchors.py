"""Absolute anchors for the DSC network, built from the training frames themselves (not in the paper).

The bootstrap teaches the DSC network relative poses; what it must learn is where each image was
taken, in one world. Two sources give every training frame a world pose without ground truth; the
trainer pulls each DSC cell's pose towards its frame's (:class:`relocdepth.method.Bootstrap`,
``L_anchor``):

- ``vo`` (:func:`build_anchors`): once the depth network has learned (the bootstrap's warps teach
  it in a few hundred steps), keyframe odometry over each training sequence with that depth, and
  registration of the sequences into one world, each against every sequence placed before it
  (:func:`relocdepth.vo.join_sequences`). The world is the first training sequence's first frame,
  in the depth network's units at the time of the build.
- ``linked`` (:func:`build_linked_anchors`): the DSC network's own poses, every sequence after the
  first registered into the first one's world by wide-baseline links between similar frames. The
  bootstrap makes the DSC's poses right *within* each sequence (on the demo scene 1.3-1.7 deg after
  a rotation fit per sequence) while each sequence sits in a world of its own (4.2 deg from their
  mean); the links put them in one, and the anchors keep the network's own world and units.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch

from relocdepth.data import ImageFrames, scale_and_crop
from relocdepth.models import disp_to_depth
from relocdepth.vo import MIN_LINK_INLIERS, VOConfig, join_sequences, world_trajectory

# Links are matched on the stored images resized to this width (up or down): SIFT needs the pixels.
# Demo scene stored at 128x96, nearest frames of two training paths, median rotation error of a
# link against ground truth: 14.6 deg as stored, 5.0 resized to 320x240, 2.1 to 640x480 (its
# detector finds the small features only on the enlarged image; inliers of one registration 51 ->
# 147 of 225).
LINK_WIDTH = 640
# At most this many query frames per registered sequence (each with VOConfig.links_per_frame links,
# ~0.2 s each at 640x480): a long sequence is queried sparser.
LINK_QUERIES = 75
# Linked anchors are turned (build_linked_anchors) only when at least this fraction of the measured
# pairs agree with the fitted turn. On the demo scene the DSC network's directions agreed 34-61 % up
# to step 1200 from random init, where the fitted turn missed the true one by a third, and 71-73 %
# after 1200 steps, where turning reached rung 3 (README, trial 19). The default of
# TrainConfig.anchor_turn_agreement.
TURN_MIN_AGREEMENT = 0.65


@dataclass
class Anchors:
    """``T_wc (N, 4, 4)`` float32: a world pose per training frame (``ImageFrames`` order), and what
    the build found: keyframes, frames whose pose could not be measured, registration inliers per
    sequence after the first (out of links). (The trainer times the build itself.)"""

    T_wc: np.ndarray
    keyframes: int
    lost: int
    registration: list[tuple[int, int]]
    turn_deg: float | None = None  # linked anchors: the angle their centres were turned by (None: not turned)
    turn_pairs: int = 0  # ... the measured pairs that agree with the fitted turn (within DIRECTION_MAX_DEG)
    turn_measured: int = 0  # ... out of this many measured pairs (too few agreeing: not turned)
    # the sequences (1 = the second) whose links agree too little (MIN_LINK_INLIERS) to place them in
    # the world of the others; such anchors are not to be used
    unlinked: list[int] = field(default_factory=list)
    # vo anchors refined by direct alignment (VOConfig.align): the frames whose alignment to the
    # previous frame was trusted, out of the frames after each sequence's first (None: not aligned)
    aligned: int | None = None
    track_size: tuple[int, int] | None = None  # vo anchors: the odometry's image size (W, H)
    # vo anchors refined by bundle adjustment (VOConfig.bundle): per sequence its tracks,
    # observations and median reprojection error before / after (None: not adjusted)
    bundled: list[dict] | None = None
    # vo anchors: the frames the odometry ran on (all, or every stride-th of each sequence and its
    # last; the others interpolated; None: not odometry)
    odometry_frames: int | None = None
    pnp: int = 0  # vo anchors: the frames whose pair PnP measured (VOConfig.pnp_below)


def unlinked_sequences(regs: list[Any]) -> list[int]:
    """The sequences (1 = the second) whose registration ``regs`` (one per sequence after the
    first, with ``inliers``) has fewer than :data:`MIN_LINK_INLIERS` agreeing links."""
    return [k for k, r in enumerate(regs, 1) if r.inliers < MIN_LINK_INLIERS]


def sequences_of(frames: ImageFrames) -> list[list[int]]:
    """Indices of ``frames`` per sequence, in frame order; the sequences in order of first appearance."""
    by_seq: dict[str, list[int]] = {}
    for i, f in enumerate(frames.frames):
        by_seq.setdefault(f.sequence, []).append(i)
    return [sorted(ix, key=lambda i: frames.frames[i].frame) for ix in by_seq.values()]


@torch.no_grad()
def network_depth(depth_net: Any, images: list[np.ndarray], device: Any, min_depth: float, max_depth: float,
                  batch: int = 16) -> list[np.ndarray]:
    """Depth maps ``(H, W)`` float32 of RGB uint8 ``images`` from ``depth_net`` (eval mode while it runs)."""
    was_training = depth_net.training
    depth_net.eval()
    out = []
    try:
        for i in range(0, len(images), batch):
            x = torch.from_numpy(np.stack(images[i:i + batch])).permute(0, 3, 1, 2).to(device).float() / 255.0
            d = disp_to_depth(depth_net(x)[0].float(), min_depth, max_depth)
            out += list(d[:, 0].cpu().numpy())
    finally:
        depth_net.train(was_training)
    return out


# Depth maps (H, W) of frames: given their indices and their images at the anchors' size.
DepthOf = Callable[[list[int], list[np.ndarray]], list[np.ndarray]]


def build_anchors(frames: ImageFrames, depth: DepthOf, size: tuple[int, int],
                  cfg: VOConfig | None = None, track_width: int = 0, stride: int = 1) -> Anchors:
    """World poses of every training frame from odometry at ``size`` (W, H: images resized, as the
    trainer's un-augmented input) with ``depth``'s maps (in the trainer: the depth network's,
    :func:`network_depth`). With ``track_width`` the odometry tracks the stored images resized to
    that width (:func:`relocdepth.refine.track_size`: at most theirs, their aspect, never below
    ``size``), the depth maps upsampled to them. A sequence registered by fewer than
    :data:`MIN_LINK_INLIERS` agreeing links is listed in ``unlinked``, and the anchors are not to
    be used. With ``stride`` > 1 the odometry runs on every stride-th frame of each sequence (and
    its last), and the frames between take poses interpolated between theirs (:func:`in_between`);
    ``depth`` is still asked for every frame. With ``stride`` 0 each sequence takes its own
    (:func:`sequence_stride`): every frame up to :data:`ODOMETRY_FRAMES`."""
    from relocdepth.refine import track_size

    if stride < 0:
        raise ValueError(f"stride must be >= 0 (0: by the sequence's length), not {stride}")
    W, H = size
    seqs = sequences_of(frames)
    keep = [strided(len(ix), sequence_stride(len(ix), stride)) for ix in seqs]
    images, Ks, depths = [], [], []
    for ix in seqs:
        pairs = [scale_and_crop(frames.read_image(i), frames.frames[i].intrinsics, W, H, 1.0, 0.0, 0.0) for i in ix]
        images.append([p[0] for p in pairs])
        Ks.append(pairs[0][1].K())
        depths.append(depth(ix, images[-1]))
    stored = frames.frames[0].intrinsics
    track = tuple(track_size(stored.width, stored.height, (W, H), track_width))
    if track != (W, H):  # the stored images, read when asked (a long dataset's do not fit in memory)
        images = [_LinkImages(frames, ix, *track) for ix in seqs]
        Ks = [frames.frames[ix[0]].intrinsics.scaled(*track).K() for ix in seqs]
        depths = [_Upsampled(d, track) for d in depths]
    cfg = cfg or VOConfig()
    # each sequence's odometry on its kept frames, the frames between filled in; then the
    # sequences registered into one world on all of their frames (as many links as without stride)
    own = [world_trajectory([_Kept(im, kk)], [K], [_Kept(d, kk).__getitem__], cfg)
           for im, K, d, kk in zip(images, Ks, depths, keep)]
    T_seq = [in_between(w.world[0], kk, len(ix)) for w, kk, ix in zip(own, keep, seqs)]
    regs, world = join_sequences(images, Ks, T_seq, [d.__getitem__ for d in depths], cfg)
    T = np.repeat(np.eye(4, dtype=np.float32)[None], len(frames), axis=0)
    for ix, T_w in zip(seqs, world):
        T[ix] = T_w.astype(np.float32)
    trajs = [w.trajs[0] for w in own]
    return Anchors(T, sum(len(t.keyframes) for t in trajs), sum(len(t.lost) for t in trajs),
                   [(r.inliers, r.links) for r in regs], unlinked=unlinked_sequences(regs),
                   aligned=sum(w.aligned for w in own) if cfg.align else None, track_size=track,
                   bundled=[b for w in own for b in w.bundled] if cfg.bundle else None,
                   pnp=sum(len(t.pnp) for t in trajs), odometry_frames=sum(map(len, keep)))


class _Kept:
    """The items ``kept`` of a sequence (a list, or images read when asked), in order."""

    def __init__(self, items: Any, kept: list[int]) -> None:
        self.items, self.kept = items, kept

    def __len__(self) -> int:
        return len(self.kept)

    def __getitem__(self, j: int) -> Any:
        return self.items[self.kept[j]]

    def __iter__(self) -> Iterator[Any]:
        return (self.items[k] for k in self.kept)


# With an automatic stride (build_anchors' stride 0) each sequence's odometry and bundle adjustment
# run on about this many of its frames at most: every frame of a sequence up to this long, every
# second of one up to twice as long, and so on. The adjustment's reduced system has six values a
# frame and its factorisation grows with their cube: with the true depth, a build of two generated
# sequences of 1000 frames (128x96, one thread) took 487 s on every frame and 139 s on every second,
# 0.047 m / 2.0 deg and 0.051 m / 2.8 deg from the truth; a 7-Scenes sequence has 1000 frames.
# The scenes measured in training (sequences of 90-500 frames) keep every frame (README, Training:
# builds that scale with the scene).
ODOMETRY_FRAMES = 500


def sequence_stride(n: int, stride: int) -> int:
    """The stride of a sequence of ``n`` frames: ``stride``, or with 0 the smallest that keeps at
    most :data:`ODOMETRY_FRAMES` of them (and the last)."""
    return stride if stride > 0 else max(1, math.ceil((n - 1) / ODOMETRY_FRAMES))


def strided(n: int, stride: int) -> list[int]:
    """Every ``stride``-th of ``n`` frames in order, and the last (no frame after the last one kept)."""
    kk = list(range(0, n, stride))
    return kk if kk[-1] == n - 1 else [*kk, n - 1]


def in_between(T_wc: np.ndarray, at: list[int], n: int) -> np.ndarray:
    """Poses ``(n, 4, 4)`` of ``n`` frames in order from those of the frames ``at`` (increasing,
    the first and the last among them; ``T_wc (len(at), 4, 4)``): a frame between two of them
    moves along the straight line between their centres and turns about the axis between their
    orientations (spherical interpolation), at its place between them in frames."""
    from scipy.spatial.transform import Rotation, Slerp

    T_wc = np.asarray(T_wc, np.float64)
    at_ = np.asarray(at)
    if at_[0] != 0 or at_[-1] != n - 1 or len(at_) != len(T_wc) or np.any(np.diff(at_) <= 0):
        raise ValueError(f"poses at frames {list(at)} do not span {n} frames in order")
    out = np.repeat(np.eye(4)[None], n, axis=0)
    if n > 1:  # (one frame: nothing between)
        j = np.arange(n)
        out[:, :3, :3] = Slerp(at_, Rotation.from_matrix(T_wc[:, :3, :3]))(j).as_matrix()
        out[:, :3, 3] = np.stack([np.interp(j, at_, T_wc[:, k, 3]) for k in range(3)], axis=1)
    out[at_] = T_wc  # exact where built
    return out


def combine_builds(builds: list[np.ndarray]) -> np.ndarray:
    """One set of anchors ``(N, 4, 4)`` float32 from several builds of them ``[(N, 4, 4), ...]``,
    oldest first: per frame the median of its centres (coordinate by coordinate) and the chordal
    mean of its orientations, each older build first scaled into the newest one's units (the
    least-squares scale of its centres onto the newest's). Every ``vo`` build puts the world at
    the first sequence's first frame and differs from the next one in the depth network's units
    and in its errors, so only the scale is fitted: a similarity fitted over all the centres
    would spread a build's drift along the path over the whole of it. With three builds, one
    that has gone astray is outvoted frame by frame where two agree."""
    from relocdepth.eval_geometry import chordal_mean_rotation

    if not builds:
        raise ValueError("combine_builds needs at least one build")
    T = [np.asarray(b, np.float64) for b in builds]
    if any(b.shape != T[-1].shape for b in T):
        raise ValueError(f"builds of different shapes: {[b.shape for b in T]}")
    c_new = T[-1][:, :3, 3]
    centres = []
    for b in T:
        c = b[:, :3, 3]
        denom = float(np.sum(c * c))
        centres.append(c * (float(np.sum(c * c_new)) / denom if denom > 0 else 1.0))
    out = T[-1].copy()
    out[:, :3, 3] = np.median(np.stack(centres), axis=0)
    R = np.stack([b[:, :3, :3] for b in T], axis=1)  # (N, builds, 3, 3)
    out[:, :3, :3] = [chordal_mean_rotation(r) for r in R]
    return out.astype(np.float32)


class _Upsampled:
    """Depth maps resized (bilinear) to ``size (W, H)`` when asked."""

    def __init__(self, maps: list[np.ndarray], size: tuple[int, int]) -> None:
        self.maps, self.size = maps, size

    def __getitem__(self, j: int) -> np.ndarray:
        import cv2

        return cv2.resize(self.maps[j], self.size, interpolation=cv2.INTER_LINEAR)


# World poses (N, 4, 4) and depth maps (H, W) of frames, from their images at the training size and
# their intrinsics there (N, 3, 3).
PosesOf = Callable[[list[np.ndarray], np.ndarray], tuple[np.ndarray, list[np.ndarray]]]


@torch.no_grad()
def network_poses(nets: Any, images: list[np.ndarray], K: np.ndarray, device: Any,
                  batch: int = 16) -> tuple[np.ndarray, list[np.ndarray]]:
    """The networks' poses ``T_wc (N, 4, 4)`` float64 and depth maps ``(H, W)`` of RGB uint8
    ``images`` with intrinsics ``K (N, 3, 3)``: what :func:`relocdepth.method.predict` gives
    (eval mode, median over the DSC cells)."""
    from relocdepth.method import predict

    T, depth = [], []
    for i in range(0, len(images), batch):
        x = torch.from_numpy(np.stack(images[i:i + batch])).permute(0, 3, 1, 2).to(device).float() / 255.0
        out = predict(nets, x, torch.as_tensor(K[i:i + batch], dtype=torch.float32, device=device))
        T.append(out["T_wc"].double().cpu().numpy())
        depth += list(out["depth"][:, 0].float().cpu().numpy())
    return np.concatenate(T), depth


class _LinkImages:
    """A sequence's stored images at the links' size, read when asked (a few cached): a long
    dataset's images at 640 px wide do not all fit in memory."""

    def __init__(self, frames: ImageFrames, ix: list[int], width: int, height: int) -> None:
        self.frames, self.ix, self.size = frames, ix, (width, height)
        self._cache: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        return len(self.ix)

    def __getitem__(self, j: int) -> np.ndarray:
        if j not in self._cache:
            import cv2

            if len(self._cache) >= 64:
                self._cache.pop(next(iter(self._cache)))
            img = self.frames.read_image(self.ix[j])
            if (img.shape[1], img.shape[0]) != self.size:
                down = img.shape[1] > self.size[0]
                img = cv2.resize(img, self.size, interpolation=cv2.INTER_AREA if down else cv2.INTER_LINEAR)
            self._cache[j] = img
        return self._cache[j]

    def __iter__(self) -> Iterator[np.ndarray]:
        return (self[j] for j in range(len(self)))


def link_size(width: int, height: int) -> tuple[int, int]:
    """The size links are matched at: the stored aspect, :data:`LINK_WIDTH` wide."""
    return LINK_WIDTH, max(1, round(height * LINK_WIDTH / width))


def build_linked_anchors(frames: ImageFrames, poses: PosesOf, size: tuple[int, int],
                         cfg: VOConfig | None = None, turn: bool = True,
                         min_agreement: float = TURN_MIN_AGREEMENT) -> Anchors:
    """World poses of every training frame: ``poses``' (in the trainer the networks',
    :func:`network_poses`, of the images at ``size`` (W, H), un-augmented), each sequence after the
    first registered into the first one's world by links between similar frames matched on the
    stored images resized to :data:`LINK_WIDTH` (:func:`relocdepth.vo.join_sequences`; translations' lengths from ``poses``' depth
    maps, so in the networks' units). ``keyframes`` and ``lost`` are 0 (no odometry).

    With ``turn``, the centres are then turned (about their mean, orientations kept) so that the
    displacements between frames a few apart point where the frames' orientations and the pairs'
    measured two-view directions say (:func:`direction_turn` over :func:`direction_pairs` of the
    images at ``size``): the network's positions and orientations in one world. Only when at
    least ``min_agreement`` of the measured pairs agree with the fitted turn (within
    :data:`DIRECTION_MAX_DEG`): a network whose own directions are mostly noise gives a turn that
    is noise too (README, trial 19).

    A sequence whose links agree fewer than :data:`MIN_LINK_INLIERS` times is not placed by
    them: it is listed in ``unlinked``, nothing is turned, and the anchors are not to be used."""
    import cv2

    W, H = size
    seqs = sequences_of(frames)
    T_seq, link_K, link_depth = [], [], []
    link_images: list[_LinkImages | None] = []
    measured: list[tuple[int, int, np.ndarray]] = []  # (frame, frame, direction) over all sequences
    for ix in seqs:
        pairs = [scale_and_crop(frames.read_image(i), frames.frames[i].intrinsics, W, H, 1.0, 0.0, 0.0) for i in ix]
        images, K = [p[0] for p in pairs], np.stack([p[1].K() for p in pairs])
        T, depth = poses(images, K)
        if turn:
            measured += [(ix[i], ix[j], t) for i, j, t in direction_pairs(images, K)]
        intr = frames.frames[ix[0]].intrinsics
        lw, lh = link_size(intr.width, intr.height)
        T_seq.append(T)
        link_images.append(_LinkImages(frames, ix, lw, lh))
        link_K.append(intr.scaled(lw, lh).K())
        link_depth.append(lambda j, d=depth, s=(lw, lh): cv2.resize(d[j], s, interpolation=cv2.INTER_LINEAR))
    base = cfg or VOConfig()
    regs, world = [], [T_seq[0]]
    for k in range(1, len(seqs)):  # one sequence at a time: each queried at most LINK_QUERIES times
        every = max(base.query_every, -(-len(seqs[k]) // LINK_QUERIES))
        cfg_k = replace(base, query_every=every)
        r, w = join_sequences([link_images[0], link_images[k]], [link_K[0], link_K[k]], [T_seq[0], T_seq[k]],
                              [link_depth[0], link_depth[k]], cfg_k)
        regs += r
        world.append(w[1])
        link_images[k] = None  # its cached images are no longer needed
    out = np.repeat(np.eye(4, dtype=np.float32)[None], len(frames), axis=0)
    for ix, T in zip(seqs, world):
        out[ix] = T.astype(np.float32)
    unlinked = unlinked_sequences(regs)
    turn_deg, kept = None, 0
    if turn and not unlinked:
        from relocdepth.eval_geometry import rotation_angle_deg

        W_turn, kept = direction_turn(out, measured)
        if kept and kept >= min_agreement * len(measured):
            out = turn_centres(out, W_turn).astype(np.float32)
            turn_deg = float(rotation_angle_deg(W_turn))
    return Anchors(out, 0, 0, [(r.inliers, r.links) for r in regs], turn_deg, kept,
                   len(measured) if not unlinked else 0, unlinked)


# The linked anchors' world turned to agree with the measured translation directions: a map whose
# camera centres and orientations disagree by a rotation hands that rotation to every pose the
# centre-fitted evaluation aligns (README, trial 18).
DIRECTION_GAPS = (4, 7, 10)  # frame offsets of the pairs whose two-view directions are measured
DIRECTION_MAX_DEG = 30.0  # pairs further than this from the fitted turn are outliers


def direction_pairs(images: list[np.ndarray], K: np.ndarray,
                    gaps: tuple[int, ...] = DIRECTION_GAPS) -> list[tuple[int, int, np.ndarray]]:
    """``(i, j, t)`` for frames ``j = i + gap`` of one sequence (``images`` in order, ``K (N, 3, 3)``)
    whose two-view translation the bootstrap's geometry measures (:func:`relocdepth.twoview.
    bootstrap_pair`): ``t`` = the unit direction of ``c_j - c_i`` in camera i's frame."""
    from relocdepth.twoview import bootstrap_pair

    out = []
    for gap in gaps:
        for i in range(len(images) - gap):
            j = i + gap
            T, _, ok = bootstrap_pair(images[j], images[i], K[j], K[i])  # T_{i<-j}: t = R_i^T (c_j - c_i)
            if ok and np.any(T[:3, 3] != 0):
                out.append((i, j, T[:3, 3].astype(np.float64)))
    return out


def direction_turn(T_wc: np.ndarray, pairs: list[tuple[int, int, np.ndarray]],
                   max_deg: float = DIRECTION_MAX_DEG, rounds: int = 6,
                   min_information: float = 0.1) -> tuple[np.ndarray, int]:
    """The rotation ``W (3, 3)`` that best turns the centres' displacements ``c_j - c_i`` of poses
    ``T_wc (N, 4, 4)`` to the directions ``R_i t`` that frame i's orientation and the measured ``t``
    give (``pairs`` from :func:`direction_pairs`, indices into ``T_wc``), each pair weighted by its
    displacement. Gauss-Newton on the turn's rotation vector; pairs further than ``max_deg`` from
    the current fit are dropped (all count in the first round). Displacements determine no turn
    about an axis they all lie along (a straight walk): directions of the rotation vector whose
    information is under ``min_information`` x the largest stay at 0. Returns ``W`` and the pairs
    kept; the identity and 0 with fewer than 3 usable pairs."""
    import cv2

    if not pairs:
        return np.eye(3), 0
    i, j = np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])
    T = np.asarray(T_wc, np.float64)
    u = T[j, :3, 3] - T[i, :3, 3]
    w = np.linalg.norm(u, axis=1)
    d = np.einsum("nab,nb->na", T[i, :3, :3], np.stack([p[2] for p in pairs]).astype(np.float64))
    ok = (w > 1e-12) & (np.linalg.norm(d, axis=1) > 1e-12)
    if ok.sum() < 3:
        return np.eye(3), 0
    u, w, d = u[ok] / w[ok, None], w[ok], d[ok] / np.linalg.norm(d[ok], axis=1, keepdims=True)
    W, keep = np.eye(3), np.ones(len(u), bool)
    for _ in range(rounds):
        v = u @ W.T
        if keep.sum() < 3:
            return np.eye(3), 0
        # exp(omega) v ~ v + omega x v = d  ->  [v]x^T omega = d - v, weighted least squares
        H = np.einsum("n,nab->ab", w[keep], np.eye(3)[None] - np.einsum("na,nb->nab", v[keep], v[keep]))
        g = np.einsum("n,na->a", w[keep], np.cross(v[keep], d[keep] - v[keep]))
        lam, vec = np.linalg.eigh(H)
        good = lam > min_information * lam.max()
        omega = vec[:, good] @ ((vec[:, good].T @ g) / lam[good])
        W = cv2.Rodrigues(omega.reshape(3, 1))[0] @ W
        cos = np.clip(np.einsum("na,na->n", u @ W.T, d), -1.0, 1.0)
        keep = np.degrees(np.arccos(cos)) < max_deg
    return W, int(keep.sum())


def turn_centres(T_wc: np.ndarray, W: np.ndarray) -> np.ndarray:
    """``T_wc (N, 4, 4)`` with the camera centres turned by ``W`` about their mean (orientations kept)."""
    out = np.array(T_wc, copy=True)
    c0 = out[:, :3, 3].mean(axis=0)
    out[:, :3, 3] = (out[:, :3, 3] - c0) @ np.asarray(W, out.dtype).T + c0
    return out
