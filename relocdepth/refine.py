"""Refine a network pose against the training frames nearest it (``--refine``).

The DSC network fits its training frames far better than it places new ones: on the demo scene
a trained network's training cameras are 3-5 cm from the truth after the protocol's Sim(3), its
test cameras ~20 cm (README, *Quality*), and its test errors follow the test camera's distance
to the nearest training camera: it recalls training places rather than placing the camera
between them. Refinement keeps what it does well and measures the rest:

1. the training frames' poses ``T_wc`` in the network's world and units are the map: the run's
   anchors when it has them (:func:`map_anchors`: the poses its DSC network was pulled towards,
   from odometry and bundle adjustment of the training video; on a generated scene of 2000
   training frames 4 cm from the truth where the network's own poses were 18 cm, and the refined
   test poses 7 cm where the network's were 22: README, *Localize, evaluate, demo*), else the
   network's own poses of the training frames;
2. a query's network pose picks the ``neighbours`` training frames whose centres are nearest
   (among those looking within ``max_view_deg`` of it, when there are any);
3. each pair (training frame -> query) gets its relative pose from two-view geometry, as the
   bootstrap measures it (:func:`relocdepth.vo.pair_pose`: KLT tracks, the essential matrix,
   the translation's length from the network's depth of the training frame, so in its units;
   ``matcher`` "klt+sift" falls back to SIFT matches, :func:`relocdepth.vo.wide_pair_pose`,
   where the tracks fail: wider baselines, less precise;
   both images resized to the training frame's stored size up to ``track_width`` px wide, as the
   bootstrap's ``--bootstrap-track-width``: more pixels, more precise pairs on real images; a
   pair with too little parallax to measure a translation puts the query at the training
   frame's centre, which is then closer than the parallax floor, ~1 px of baseline);
4. every pair proposes ``T_wc[n] T_{q<-n}^-1``, and :func:`relocdepth.vo.robust_mean_transform`
   averages the proposals (rotation medoid, inliers within ``inlier_deg``);
5. direct alignment (``align``, :mod:`relocdepth.photoalign`): the pairs' mean and the network's
   pose are each aligned to the neighbours pixel by pixel (their images, the network's depth,
   their map poses), and the aligned pose that explains the neighbours better is kept when it
   explains them clearly better than their mean brightness does. Where the views overlap the
   pairs reach a few centimetres, the alignment millimetres on rendered frames and 1-2 cm on real
   ones (true depth); a start that the pairs got wrong loses to the network's. The alignment is
   as good as the map and the depth (README, *Quality*: on the demo it lands on the network's
   map).

One round: picking the neighbours again from the refined pose and pairing again was measured
worse on trained networks (README, *Quality*).

A query with fewer than ``min_pairs`` agreeing proposals has no pairs' start (the network's pose
is aligned alone, and kept when that alignment is not trusted): one pair alone is not checked by
another, and on real images the lone pairs were the wrong ones (a pair across ~0.5 m of a
walk-through at 192x128 either fails or misleads; README, *Quality*). Nothing here needs ground
truth: the map is the run's (its anchors or its network's poses), depth the network's; the
protocol's alignment, fitted on the map's training poses, applies to the refined pose. The paper
localizes with the network alone, so this is an
addition (off by default; README, fidelity table).
"""

from __future__ import annotations

import hashlib
import json
import logging
import zipfile
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from relocdepth.camera import Intrinsics
from relocdepth.errors import UserError
from relocdepth.eval_geometry import rotation_angle_deg
from relocdepth.fileio import atomic_write
from relocdepth.photoalign import AlignConfig, View, align_from
from relocdepth.predictor import Predictor, resize_to
from relocdepth.vo import VOConfig, pair_pose, robust_mean_transform, wide_pair_pose

log = logging.getLogger(__name__)

MATCHERS = ("klt", "sift", "klt+sift")
MAP_NAME = "refine-map.npz"  # beside a run's checkpoints: the training poses of the last --refine
# Where the map's poses come from (--refine-map): the run's anchors when its checkpoint has them
# (auto), those only (anchors), or the network's own poses of the training frames (network).
MAPS = ("auto", "anchors", "network")


@dataclass(frozen=True)
class RefineConfig:
    neighbours: int = 3  # training frames paired with each query
    max_view_deg: float = 30.0  # prefer neighbours looking within this angle of the query
    inlier_deg: float = 5.0  # a proposal this far (rotation) from the proposals' medoid is dropped
    min_pairs: int = 2  # agreeing proposals needed to replace the network's pose
    track_width: int = 640  # pairs tracked at the stored size, at most this wide (0: network size)
    # "klt" (the bootstrap's tracks: precise, short baselines), "sift" (descriptors: wider
    # baselines, less precise) or "klt+sift" (SIFT where KLT fails)
    matcher: str = "klt+sift"
    cache: int = 512  # training frames whose image and depth are kept in memory
    # direct alignment to the neighbours (relocdepth.photoalign) from the two-view pose and from
    # the network's, the one that explains the neighbours' pixels better kept
    align: bool = True
    photometric: AlignConfig = AlignConfig()

    @classmethod
    def from_options(cls, neighbours: int, min_pairs: int, matcher: str, align: bool = True) -> RefineConfig:
        """The config of the ``--refine-*`` options; a bad value is a :class:`UserError`."""
        if matcher not in MATCHERS:
            raise UserError(f"unknown --refine-matcher {matcher!r}; use one of {', '.join(MATCHERS)}")
        if min(neighbours, min_pairs) < 1:
            raise UserError("--refine-neighbours and --refine-min-pairs must be at least 1")
        return cls(neighbours=neighbours, min_pairs=min_pairs, matcher=matcher, align=align)


@dataclass
class RefFrame:
    """One training frame as a pair needs it: RGB at its tracking size, K and the network's depth
    (any units) at that size."""

    image: np.ndarray
    K: np.ndarray
    depth: np.ndarray


class Reference:
    """The map: the network's poses ``T_wc (N, 4, 4)`` of N training frames, and ``load(i)``
    giving frame i's :class:`RefFrame` (asked only for frames that become neighbours; cached)."""

    def __init__(self, T_wc: np.ndarray, load: Callable[[int], RefFrame], cache: int = 512) -> None:
        T_wc = np.asarray(T_wc, np.float64)
        if T_wc.ndim != 3 or T_wc.shape[1:] != (4, 4) or len(T_wc) == 0:
            raise ValueError(f"expected (N, 4, 4) training poses with N >= 1, got {T_wc.shape}")
        self.T_wc, self._load, self._cache_size = T_wc, load, max(1, cache)
        self._cache: OrderedDict[int, RefFrame] = OrderedDict()

    def frame(self, i: int) -> RefFrame:
        if i in self._cache:
            self._cache.move_to_end(i)
            return self._cache[i]
        f = self._cache[i] = self._load(i)
        if len(self._cache) > self._cache_size:
            self._cache.popitem(last=False)
        return f

    def neighbours(self, T_wc: np.ndarray, k: int, max_view_deg: float) -> np.ndarray:
        """Indices of the ``k`` training frames whose centres are nearest ``T_wc``'s, taken first
        from those whose viewing direction is within ``max_view_deg`` of it."""
        dist = np.linalg.norm(self.T_wc[:, :3, 3] - T_wc[:3, 3], axis=1)
        view = rotation_angle_deg(np.einsum("nji,jk->nik", self.T_wc[:, :3, :3], T_wc[:3, :3]))
        order = np.lexsort((dist, view > max_view_deg))  # facing the same way first, then nearest
        return order[:k]


@dataclass
class Refined:
    """A refined pose: ``T_wc (4, 4)`` in the map's world and units, the pairs that agreed, and
    what placed it (:data:`REFINED_BY`): "aligned" (direct alignment to the neighbours), "pairs"
    (the pairs' robust mean; alignment off or not trusted) or "none" (the network's pose)."""

    T_wc: np.ndarray
    pairs: int
    by: str


REFINED_BY = ("aligned", "pairs", "none")


def align_refined(results: list[Refined], on_map: tuple, on_network: tuple) -> np.ndarray:
    """The refined poses ``(N, 4, 4)`` of ``results`` in the ground truth's frame: those the
    refinement placed lie in the map's world and go by its Sim(3) ``on_map``, those that kept the
    network's pose ("none") by the network's ``on_network`` (each ``(scale, R, t)``)."""
    from relocdepth.eval_geometry import apply_sim3

    T = np.stack([r.T_wc for r in results])
    out = apply_sim3(*on_network, T)
    placed = np.array([r.by != "none" for r in results])
    if placed.any():
        out[placed] = apply_sim3(*on_map, T[placed])
    return out


def refine_pose(ref: Reference, image: np.ndarray, intrinsics: Intrinsics, T_wc: np.ndarray,
                cfg: RefineConfig = RefineConfig()) -> Refined:
    """The query's refined pose. ``image``: RGB uint8 at any size, ``intrinsics`` its camera; it is
    resized to each training frame's size for the pairs. With ``cfg.min_pairs`` agreeing pairs
    their robust mean is a start; the network's ``T_wc`` is the other. With ``cfg.align`` each start
    is aligned to the neighbours (:func:`relocdepth.photoalign.align`) and the aligned pose that
    explains them better is the answer when it explains them clearly
    (:attr:`~relocdepth.photoalign.AlignResult.accepted`); otherwise the pairs' mean, or without
    it the network's pose."""
    if cfg.matcher not in MATCHERS:
        raise ValueError(f"matcher must be one of {MATCHERS}, not {cfg.matcher!r}")
    T_net = np.asarray(T_wc, np.float64)
    proposals, views = [], []
    for n in ref.neighbours(T_net, cfg.neighbours, cfg.max_view_deg):
        f = ref.frame(int(n))
        views.append(View(f.image, f.depth, f.K, ref.T_wc[n]))
        h, w = f.image.shape[:2]
        args = (f.image, resize_to(image, (w, h)), f.K, intrinsics.scaled(w, h).K(), f.depth, VOConfig())
        p = pair_pose(*args) if cfg.matcher != "sift" else None
        if cfg.matcher != "klt" and (p is None or not p.ok):
            p = wide_pair_pose(*args)
        if p.ok:  # unmeasured translation: under the parallax floor, the query is about there
            proposals.append(ref.T_wc[n] @ np.linalg.inv(p.T))
    out = Refined(T_net, 0, "none")
    if proposals:
        T, inl = robust_mean_transform(np.stack(proposals), cfg.inlier_deg)
        out.pairs = int(inl.sum())
        if out.pairs >= cfg.min_pairs:
            out.T_wc, out.by = T, "pairs"
    if cfg.align:
        K_q = intrinsics.scaled(image.shape[1], image.shape[0]).K()
        starts = [T_net] + ([out.T_wc] if out.by == "pairs" else [])
        best = min(align_from(views, image, K_q, starts, cfg.photometric), key=lambda r: r.cost)
        if best.accepted:
            out.T_wc, out.by = best.T_wc, "aligned"
    return out


class Refiner:
    """A :class:`Reference` built from a predictor and training images, refining its poses."""

    def __init__(self, predictor: Predictor, ref: Reference, cfg: RefineConfig = RefineConfig(),
                 map_name: str = "network") -> None:
        self.predictor, self.ref, self.cfg = predictor, ref, cfg
        self.map_name = map_name  # whose poses the map's are (MAPS): the refined poses lie in their world

    @classmethod
    def from_images(cls, predictor: Predictor, read: Callable[[int], np.ndarray],
                    intrinsics: list[Intrinsics], T_wc: np.ndarray,
                    cfg: RefineConfig = RefineConfig(), map_name: str = "network") -> Refiner:
        """The map of N training images (``read(i)``: RGB uint8, ``intrinsics[i]``) whose poses
        are ``T_wc``: the predictor's (:func:`predict_poses`, or stored; ``map_name`` "network") or
        the run's anchors ("anchors")."""

        def load(i: int) -> RefFrame:
            img = read(i)
            depth = predictor.predict([img], [intrinsics[i]], with_depth=True).depth[0]
            w, h = track_size(img.shape[1], img.shape[0], predictor.input_size, cfg.track_width)
            return RefFrame(resize_to(img, (w, h)), intrinsics[i].scaled(w, h).K(),
                            cv2.resize(depth, (w, h), interpolation=cv2.INTER_LINEAR))

        return cls(predictor, Reference(T_wc, load, cfg.cache), cfg, map_name)

    def refine(self, image: np.ndarray, intrinsics: Intrinsics, T_wc: np.ndarray) -> Refined:
        """:func:`refine_pose` of one query image (RGB uint8 at any size, its intrinsics) whose
        network pose is ``T_wc``."""
        return refine_pose(self.ref, image, intrinsics, T_wc, self.cfg)


def predict_poses(predictor: Predictor, read: Callable[[int], np.ndarray], intrinsics: list[Intrinsics],
                  batch_size: int = 16, on_batch: Callable[[int], None] | None = None) -> np.ndarray:
    """The predictor's ``T_wc (N, 4, 4)`` of N images (``read(i)``), in batches; ``on_batch(n)``
    after each."""
    poses = []
    for s in range(0, len(intrinsics), batch_size):
        idx = range(s, min(s + batch_size, len(intrinsics)))
        poses.append(predictor.predict([read(i) for i in idx], [intrinsics[i] for i in idx],
                                       with_depth=False).T_wc)
        if on_batch is not None:
            on_batch(len(idx))
    return np.concatenate(poses) if poses else np.zeros((0, 4, 4))


def map_anchors(which: str, meta: dict, ds: Any, keys: list[str]) -> np.ndarray | None:
    """The map's poses of the training frames ``keys`` of the dataset ``ds`` when they are the
    run's anchors, as ``(len(keys), 4, 4)``; None when the map is the network's own poses (the
    caller's to predict). ``meta``: the checkpoint's (:func:`relocdepth.checkpoint.load_for_inference`),
    whose ``anchors`` are the poses its DSC network was pulled towards (``--anchor vo``: odometry
    and bundle adjustment of the training video, no ground truth; the networks' world and units),
    in the order of the training frames it was trained on. ``which`` (:data:`MAPS`): "auto" takes
    them when the checkpoint has them for these shards' frames; "anchors" only them (none:
    :class:`UserError`); "network" never."""
    if which not in MAPS:
        raise UserError(f"unknown --refine-map {which!r}; use one of {', '.join(MAPS)}")
    if which == "network":
        return None
    T, order = meta.get("anchors"), {r.key: i for i, r in enumerate(ds.frames("train"))}
    if (T is None or meta.get("manifest_hash") != ds.manifest_hash or len(T) != len(order)
            or any(k not in order for k in keys)):
        if which == "anchors":
            raise UserError(f"--refine-map anchors: {meta['path']} holds no anchors of the training frames "
                            f"of {ds.root} (a run trained on them with --anchor vo has them)")
        return None
    return np.asarray(T, np.float64)[[order[k] for k in keys]]


def cached_map_poses(ckpt_path: Path, manifest_hash: str, keys: list[str],
                     compute: Callable[[], np.ndarray]) -> np.ndarray:
    """The map's poses from ``checkpoints/refine-map.npz`` when it was built by this checkpoint
    file (name, size, modification time) from these frames (the shards' manifest hash and the
    frames' keys); else ``compute()``, stored there for the next time (a run folder that cannot
    be written to only costs the next call the same pass)."""
    path = ckpt_path.parent / MAP_NAME
    st = ckpt_path.stat()
    ident = hashlib.sha256(json.dumps(
        [ckpt_path.name, st.st_size, st.st_mtime_ns, manifest_hash, keys]).encode()).hexdigest()
    try:
        with np.load(path) as z:
            if str(z["ident"]) == ident and z["T_wc"].shape == (len(keys), 4, 4):
                log.info("the map's %d training poses from %s", len(keys), path)
                return np.asarray(z["T_wc"], np.float64)
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile):
        pass  # none yet, or unreadable: build it
    T_wc = compute()
    try:
        atomic_write(path, lambda f: np.savez(f, ident=np.array(ident), T_wc=T_wc))
    except OSError as e:
        log.warning("could not store the map in %s (%s); the next --refine builds it again", path, e)
    return T_wc


def track_size(width: int, height: int, input_size: tuple[int, int], track_width: int) -> tuple[int, int]:
    """Where a stored ``width x height`` training frame is tracked: its own size up to
    ``track_width`` px wide (aspect kept), never below the network's ``input_size (W, H)``;
    ``track_width`` 0 (or no wider than the network's): the network's size."""
    if track_width <= input_size[0] or width <= input_size[0]:
        return input_size
    w = min(width, track_width)
    return w, max(1, round(height * w / width))
