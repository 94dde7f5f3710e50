"""What one anchors build costs, and how close it comes to the truth, at the strides given.

:func:`relocdepth.anchors.build_anchors` on the training frames of shards that have ground truth,
with the true depth in place of the depth network's (the build's cost hardly depends on whose
depth it is; its error is then the odometry's and registration's own), as the trainer calls it
(``--anchor vo`` with the bundle adjustment and PnP below 50 tracks, as `cpu-anchored-views`).
Per stride: the build's seconds, split into each sequence's odometry and bundle adjustment and
the registration of the sequences, the frames the odometry ran on, and the anchors' median
error after one Sim(3) for all frames (and per sequence aligned alone: its drift). Stride 0 is
the automatic one (each sequence its own: every frame up to
:data:`relocdepth.anchors.ODOMETRY_FRAMES`). The ratios of the seconds are what to read: the
strides are built one after the other in one run, one thread.

    reloc synth /tmp/k1 --frames 1000 --size 128x96 && reloc ingest /tmp/k1 -o /tmp/k1s
    python benchmarks/bench_anchors.py /tmp/k1s --strides 1,0,3
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("shards", type=Path, help="shards with depth and poses (reloc synth + reloc ingest)")
    ap.add_argument("--strides", default="1,0", help="comma-separated strides (0: automatic)")
    ap.add_argument("--size", default="128x96", help="the build's image size WxH (the trainer's --size)")
    ap.add_argument("--json", type=Path, help="also write the figures here")
    args = ap.parse_args()

    import torch

    import relocdepth.anchors as A
    from relocdepth import eval_geometry as EG
    from relocdepth.ba import BAConfig
    from relocdepth.data import ImageFrames
    from relocdepth.dataset import open_dataset
    from relocdepth.evaluate import fit_sim3
    from relocdepth.vo import VOConfig

    torch.set_num_threads(1)
    W, H = (int(v) for v in args.size.lower().split("x"))
    frames = ImageFrames.open(args.shards)
    ds = open_dataset(args.shards)
    recs = {r.key: r for r in ds.frames("train")}
    T_gt = np.stack([ds.read_pose(recs[f.key]) for f in frames.frames]).astype(np.float64)
    depth_gt = [ds.read_depth(recs[f.key]) for f in frames.frames]
    seqs = A.sequences_of(frames)
    print(f"{args.shards}: {len(frames)} training frames in {len(seqs)} sequences of {[len(s) for s in seqs]}, "
          f"built at {W}x{H}")

    seconds: dict[str, float] = {}

    def timed(name: str, fn):  # noqa: ANN001, ANN202
        def run(*a, **k):  # noqa: ANN002, ANN003, ANN202
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                seconds[name] = seconds.get(name, 0.0) + time.perf_counter() - t0
        return run

    odometry, join = A.world_trajectory, A.join_sequences
    A.world_trajectory, A.join_sequences = timed("odometry", odometry), timed("registration", join)

    def error(T: np.ndarray, gt: np.ndarray) -> tuple[float, float]:
        fit = fit_sim3(T, gt)
        t, r = EG.pose_errors(EG.apply_sim3(fit.scale, fit.R, fit.t, T), gt)
        return float(np.median(t)), float(np.median(r))

    rows = []
    cfg = VOConfig(bundle=True, pnp_below=50, bundle_cfg=BAConfig())
    for stride in (int(s) for s in args.strides.split(",")):
        seconds.clear()
        t0 = time.perf_counter()
        a = A.build_anchors(frames, lambda ix, ims: [depth_gt[i] for i in ix], (W, H), cfg, stride=stride)
        took = time.perf_counter() - t0
        T = a.T_wc.astype(np.float64)
        t, r = error(T, T_gt)
        alone = [error(T[ix], T_gt[ix])[0] for ix in seqs]
        row = {"stride": stride, "strides": [A.sequence_stride(len(ix), stride) for ix in seqs],
               "seconds": round(took, 1), "odometry_s": round(seconds.get("odometry", 0.0), 1),
               "registration_s": round(seconds.get("registration", 0.0), 1),
               "odometry_frames": a.odometry_frames, "median_t_m": round(t, 4), "median_r_deg": round(r, 2),
               "per_sequence_t_m": [round(e, 4) for e in alone], "registration": a.registration}
        rows.append(row)
        print(json.dumps(row))
    base = rows[0]["seconds"]
    for row in rows[1:]:
        print(f"stride {row['stride']} ({row['strides']}): {row['seconds'] / base:.2f}x the time of "
              f"stride {rows[0]['stride']}, {row['median_t_m']:.4f} m against {rows[0]['median_t_m']:.4f}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")


if __name__ == "__main__":
    main()
