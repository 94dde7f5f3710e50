"""How good is a trajectory built from the bootstrap's own geometry (no ground truth)?

Per training sequence, keyframe visual odometry from the essential-matrix bootstrap
(`relocdepth.vo.chain`: KLT + essential matrix per pair, each translation's length from a depth
map of the keyframe), then every other training sequence registered into the first one's world
(`relocdepth.vo.register`: thumbnail retrieval links, robust average). Depth comes from a trained
checkpoint (its depth network only) and, as the upper bound, from ground truth. Scored against the
ground-truth poses after a Sim(3) alignment (Umeyama): ATE (RMSE and median) per sequence (each
aligned alone: drift) and jointly (one alignment for all: drift plus registration), the relative
pose error of frames k apart vs the identity's, the fitted scale, the registration's own error,
and the time per frame. With --bundle each sequence's odometry is also refined by bundle
adjustment over its multi-frame tracks (`relocdepth.ba`), with --align by direct alignment.

    python benchmarks/quality/vo_trajectory.py /tmp/q1/data/shards \
        --checkpoint runs/kitchen-w10
    python benchmarks/quality/vo_trajectory.py ../shared/data/hololens-office --size 192x128

Data: shards from `reloc ingest` (the training split, every sequence), or one walk-through folder
(images/, depth/, poses.txt, K.txt, e.g. shared/data/hololens-office: its first --frames frames,
the quality rows' training part).
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from relocdepth import eval_geometry as EG
from relocdepth import metrics as M
from relocdepth.ba import BAConfig
from relocdepth.camera import Intrinsics
from relocdepth.dataset import DEPTH_SCALE, open_dataset
from relocdepth.evaluate import fit_sim3
from relocdepth.vo import LINK_MATCHERS, VOConfig, World, world_trajectory

GAP_DEG = 15.0  # "looks the same way" for the gap between two paths


@dataclass
class Sequence:
    name: str
    images: list[np.ndarray]  # RGB uint8 at the tracking size
    intrinsics: Intrinsics  # at the tracking size
    T_gt: np.ndarray  # (N, 4, 4)
    depth_gt: list[np.ndarray]  # metres at the tracking size, 0 = invalid


def _resize(seq: Sequence, size: tuple[int, int] | None) -> Sequence:
    if size is None or size == (seq.intrinsics.width, seq.intrinsics.height):
        return seq
    w, h = size
    images = [cv2.resize(im, (w, h), interpolation=cv2.INTER_AREA) for im in seq.images]
    depth = [cv2.resize(d, (w, h), interpolation=cv2.INTER_NEAREST) for d in seq.depth_gt]
    return Sequence(seq.name, images, seq.intrinsics.scaled(w, h), seq.T_gt, depth)


def load(path: Path, frames: int) -> list[Sequence]:
    """The training sequences at ``path`` (shards, or a walk-through folder's first ``frames``)."""
    if (path / "poses.txt").is_file():
        K = np.loadtxt(path / "K.txt").reshape(3, 3)
        T = np.loadtxt(path / "poses.txt").reshape(-1, 4, 4)[:frames]
        imgs = [cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB)
                for p in sorted((path / "images").glob("*.png"))[:frames]]
        depth = [cv2.imread(str(p), cv2.IMREAD_UNCHANGED).astype(np.float32) / DEPTH_SCALE
                 for p in sorted((path / "depth").glob("*.png"))[:frames]]
        h, w = imgs[0].shape[:2]
        intr = Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], w, h)
        return [Sequence(path.name, imgs, intr, T, depth)]
    ds = open_dataset(path)
    out = []
    for name in ds.sequences():
        recs = sorted((r for r in ds.frames("train") if r.sequence == name), key=lambda r: r.frame)
        if recs:
            out.append(Sequence(name, [ds.read_image(r) for r in recs], recs[0].intrinsics,
                                np.stack([ds.read_pose(r) for r in recs]),
                                [ds.read_depth(r) for r in recs]))
    return out


def network_depth(checkpoint: str, seqs: list[Sequence],
                  raw: bool = False) -> tuple[list[list[np.ndarray]], float]:
    """Depth of every frame from the checkpoint's depth network, at each sequence's size; and the
    seconds per frame it took. ``raw``: the trained weights, not their moving average where the
    checkpoint holds one (training builds its anchors with the weights it trains)."""
    from relocdepth.predictor import Predictor

    pred = Predictor.from_checkpoint(checkpoint, raw=raw)
    out, n, t0 = [], 0, time.process_time()
    for s in seqs:
        w, h = s.intrinsics.width, s.intrinsics.height
        maps = []
        for i in range(0, len(s.images), 16):
            batch = s.images[i:i + 16]
            d = pred.predict(batch, [s.intrinsics] * len(batch), with_depth=True).depth
            maps += [cv2.resize(x, (w, h), interpolation=cv2.INTER_LINEAR) for x in d]
        out.append(maps)
        n += len(s.images)
    return out, (time.process_time() - t0) / max(n, 1)


def ate(T_est: np.ndarray, T_gt: np.ndarray, fit: EG.Sim3 | None = None) -> dict:
    """Sim(3)-aligned camera-centre errors (m): RMSE, median; and the fitted scale (``fit``: the
    alignment when it is already fitted)."""
    fit = fit or fit_sim3(T_est, T_gt)
    s, R, t = fit.scale, fit.R, fit.t
    err = np.linalg.norm(EG.apply_sim3(s, R, t, T_est)[:, :3, 3] - T_gt[:, :3, 3], axis=1)
    return {"rmse_m": float(np.sqrt(np.mean(err ** 2))), "median_m": float(np.median(err)),
            "scale": s}


def odometry_world(seqs: list[Sequence], depths: list[list[np.ndarray]], cfg: VOConfig) -> World:
    """Odometry per sequence and registration into the first one's world."""
    return world_trajectory([s.images for s in seqs], [s.intrinsics.K() for s in seqs],
                            [d.__getitem__ for d in depths], cfg)


def run(seqs: list[Sequence], depths: list[list[np.ndarray]], cfg: VOConfig, k: int) -> dict:
    """Odometry per sequence, registration into the first, and the scores."""
    w = odometry_world(seqs, depths, cfg)
    trajs, world, ref = w.trajs, w.world, seqs[0]
    out: dict = {"sequences": {}, "vo_s_per_frame": w.vo_s / sum(len(s.images) for s in seqs)}
    for s, reg in zip(seqs[1:], w.regs):
        out["sequences"][s.name] = {"registration": {"links": reg.links, "used": reg.used,
                                                     "inliers": reg.inliers, "T": reg.T}}
    links = sum(reg.links for reg in w.regs)
    if links:
        out["registration_s_per_link"] = w.reg_s / links
    T_est, T_gt = np.concatenate(world), np.concatenate([s.T_gt for s in seqs])
    names = [s.name for s in seqs for _ in s.images]
    fit = fit_sim3(T_est, T_gt)
    joint = ate(T_est, T_gt, fit)
    s_, R_, t_ = fit.scale, fit.R, fit.t
    T_al = EG.apply_sim3(s_, R_, t_, T_est)
    out["joint"] = joint | {"relative": M.relative_pose_errors(T_al, T_gt, names, k)}
    # The registration's own error: the true reference-from-sequence transform vs the estimate
    # (its translation scaled to metres by the joint scale).
    for s, tr, T_w in zip(seqs, trajs, world):
        sel = np.array(names) == s.name
        err = np.linalg.norm(T_al[sel, :3, 3] - T_gt[sel, :3, 3], axis=1)
        row = out["sequences"].setdefault(s.name, {})
        # rotation drift: both trajectories start at the first frame, so no alignment is needed
        R_gt = np.linalg.inv(s.T_gt[0])[:3, :3] @ s.T_gt[:, :3, :3]
        drift = EG.rotation_angle_deg(np.swapaxes(tr.T_wc[:, :3, :3], -1, -2) @ R_gt)
        row |= {"frames": len(s.images), "keyframes": len(tr.keyframes), "lost": len(tr.lost),
                "alone": ate(tr.T_wc, s.T_gt),
                "rotation_drift_deg": {"median": float(np.median(drift)), "max": float(drift.max())},
                "joint": {"rmse_m": float(np.sqrt(np.mean(err ** 2))), "median_m": float(np.median(err))}}
        if "registration" in row:
            T_true = np.linalg.inv(ref.T_gt[0]) @ s.T_gt[0]
            T_reg = row["registration"].pop("T")
            row["registration"]["r_err_deg"] = float(EG.rotation_angle_deg(T_reg[:3, :3].T @ T_true[:3, :3]))
            row["registration"]["t_err_m"] = float(np.linalg.norm(s_ * T_reg[:3, 3] - T_true[:3, 3]))
            # how far apart the two paths are: per frame, the nearest reference frame that looks
            # within GAP_DEG the same way (ground truth; what a link's pair has to bridge)
            dist = np.linalg.norm(s.T_gt[:, None, :3, 3] - ref.T_gt[None, :, :3, 3], axis=-1)
            ang = EG.rotation_angle_deg(np.einsum("bji,ajk->baik", s.T_gt[:, :3, :3], ref.T_gt[:, :3, :3]))
            gap = np.where(ang < GAP_DEG, dist, np.inf).min(axis=1)
            row["registration"]["path_gap_m"] = float(np.median(gap))
    return out


def print_table(rows: dict[str, dict]) -> None:
    print("| depth | sequence | frames (keyframes, lost) | ATE alone RMSE / median (m) | scale alone "
          "| rotation drift median / max (deg) | ATE joint RMSE / median (m) "
          f"| registration: inliers / links, error (deg / m), path gap (m, < {GAP_DEG:g} deg) |")
    print("|---|---|---|---|---|---|---|---|")
    for label, r in rows.items():
        for name, q in r["sequences"].items():
            reg = q.get("registration")
            reg_s = (f"{reg['inliers']} / {reg['links']}, {reg['r_err_deg']:.2f} / {reg['t_err_m']:.3f}, "
                     f"{reg['path_gap_m']:.3f}"
                     if reg else "(reference)")
            print(f"| {label} | {name} | {q['frames']} ({q['keyframes']}, {q['lost']}) | "
                  f"{q['alone']['rmse_m']:.3f} / {q['alone']['median_m']:.3f} | {q['alone']['scale']:.3f} | "
                  f"{q['rotation_drift_deg']['median']:.2f} / {q['rotation_drift_deg']['max']:.2f} | "
                  f"{q['joint']['rmse_m']:.3f} / {q['joint']['median_m']:.3f} | {reg_s} |")
    print()
    print("| depth | ATE joint RMSE / median (m) | scale | rel. pose k apart t (m) / r (deg) "
          "| identity t / r | VO s/frame | registration s/link | depth net s/frame |")
    print("|---|---|---|---|---|---|---|---|")
    for label, r in rows.items():
        j, rel = r["joint"], r["joint"]["relative"]
        print(f"| {label} | {j['rmse_m']:.3f} / {j['median_m']:.3f} | {j['scale']:.3f} | "
              f"{rel['median_t_m']:.4f} / {rel['median_r_deg']:.2f} (k={rel['k']}) | "
              f"{rel['identity_median_t_m']:.4f} / {rel['identity_median_r_deg']:.2f} | "
              f"{r['vo_s_per_frame']:.4f} | {r.get('registration_s_per_link', float('nan')):.4f} | "
              f"{r.get('depth_s_per_frame', float('nan')):.4f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", type=Path, help="shards from `reloc ingest`, or a walk-through folder")
    ap.add_argument("--checkpoint", help="a run or checkpoint file: depth from its depth network")
    ap.add_argument("--raw-weights", action="store_true",
                    help="--checkpoint: depth from the trained weights, not their moving average")
    ap.add_argument("--size", help="track at WxH (images and depth resized; K follows)")
    ap.add_argument("--frames", type=int, default=90, help="walk-through: its first N frames")
    ap.add_argument("--k", type=int, default=5, help="relative pose error between frames k apart")
    ap.add_argument("--min-parallax", type=float, default=VOConfig.min_parallax_px,
                    help="px; pairs below are rotation only (the bootstrap's threshold)")
    ap.add_argument("--keyframe-baseline", type=float, default=VOConfig.keyframe_baseline_px,
                    help="px; a measured pair over this baseline becomes the next keyframe")
    ap.add_argument("--links", type=int, default=VOConfig.links_per_frame)
    ap.add_argument("--link-matcher", choices=LINK_MATCHERS, default=VOConfig.link_matcher,
                    help="registration links: SIFT matches (wide baselines) or the bootstrap's KLT")
    ap.add_argument("--query-every", type=int, default=VOConfig.query_every)
    ap.add_argument("--align", action="store_true",
                    help="also refine each sequence's odometry by direct alignment (rows marked 'aligned')")
    ap.add_argument("--bundle", action="store_true",
                    help="also refine each sequence's odometry by bundle adjustment (rows marked 'bundled')")
    ap.add_argument("--first-view-px", type=float, default=BAConfig.first_view_px,
                    help="--bundle: each track step tracked again from the track's first view; a step "
                         "that moves more than this (px) ends its track (0: frame to frame only)")
    ap.add_argument("--scale-degree", type=int, default=BAConfig.scale_degree,
                    help="--bundle: hold the adjusted path's scale to the depth maps' by a polynomial of "
                         "this degree along it (the trainer's --anchor-bundle-scale-degree)")
    ap.add_argument("--scale-window", type=float, default=BAConfig.scale_window,
                    help="--bundle: ... or over a Gaussian window of this many frames (the trainer's "
                         "--anchor-bundle-scale runs the adjustment to 100 iterations with it: --iterations)")
    ap.add_argument("--iterations", type=int, default=BAConfig.max_iterations,
                    help="--bundle: the adjustment's Levenberg-Marquardt steps at most")
    ap.add_argument("--pnp-below", type=int, default=VOConfig.pnp_below,
                    help="pairs KLT tracks at fewer points than this are measured by PnP on the depth")
    ap.add_argument("--json", type=Path, help="also write the figures here")
    a = ap.parse_args()
    size = tuple(int(v) for v in a.size.lower().split("x")) if a.size else None
    seqs = [_resize(s, size) for s in load(a.data, a.frames)]
    cfg = VOConfig(min_parallax_px=a.min_parallax, keyframe_baseline_px=a.keyframe_baseline,
                   links_per_frame=a.links, link_matcher=a.link_matcher, query_every=a.query_every,
                   pnp_below=a.pnp_below,
                   bundle_cfg=BAConfig(first_view_px=a.first_view_px, scale_degree=a.scale_degree,
                                       scale_window=a.scale_window, max_iterations=a.iterations))
    print(f"{a.data}: {', '.join(f'{s.name} ({len(s.images)})' for s in seqs)} at "
          f"{seqs[0].intrinsics.width}x{seqs[0].intrinsics.height}; {cfg}")
    rows = {}
    sources = [("ground truth", [s.depth_gt for s in seqs], {})]
    if a.checkpoint:
        depths, per_frame = network_depth(a.checkpoint, seqs, a.raw_weights)
        sources.insert(0, ("network", depths, {"depth_s_per_frame": per_frame}))
    for label, depths, extra in sources:
        rows[label] = run(seqs, depths, cfg, a.k) | extra
        if a.align:
            rows[f"{label}, aligned"] = run(seqs, depths, replace(cfg, align=True), a.k) | extra
        if a.bundle:
            rows[f"{label}, bundled"] = run(seqs, depths, replace(cfg, bundle=True), a.k) | extra
    print_table(rows)
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
