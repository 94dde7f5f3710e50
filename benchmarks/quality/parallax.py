"""How many pixels of warp does depth explain, for frames k apart?

Photometric losses learn depth only from the part of the warp that depth changes. For target
frames t and sources s = t + k of a dataset with ground-truth depth and poses (shards written by
`reloc ingest`, read with the project's reader; or one walk-through folder of depth/ (uint16 mm),
poses.txt (a row-major 4x4 camera-to-world matrix per line) and K.txt, as
shared/data/hololens-office), this measures |warp with the true depth - warp with a constant depth
(the frame's median)| in pixels, over valid pixels, and prints its median per offset k. Rotation
moves pixels by the same amount at any depth, so only translation (parallax) shows up here.

    python benchmarks/quality/parallax.py /tmp/quality/data/shards [--offsets 1,2,3,5,10,20]
    python benchmarks/quality/parallax.py ../shared/data/hololens-office --offsets 1,2,3,5
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from relocdepth.dataset import DEPTH_SCALE, open_dataset


def sequences(path: Path) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(K, T_wc per frame, depth in metres per frame) of each sequence at ``path``."""
    if (path / "poses.txt").is_file():  # one walk-through: depth/, poses.txt, K.txt
        K = np.loadtxt(path / "K.txt").reshape(3, 3)
        T = np.loadtxt(path / "poses.txt").reshape(-1, 4, 4)
        D = np.stack([cv2.imread(str(p), cv2.IMREAD_UNCHANGED) / DEPTH_SCALE
                      for p in sorted((path / "depth").glob("*.png"))])
        if len(D) != len(T):
            raise SystemExit(f"{path}: {len(T)} poses but {len(D)} depth maps")
        return [(K, T, D)]
    ds = open_dataset(path)
    out = []
    for name in ds.sequences():
        recs = [r for r in ds.records if r.sequence == name and r.has_pose and r.has_depth]
        if recs:
            out.append((recs[0].intrinsics.K(), np.stack([ds.read_pose(r) for r in recs]),
                        np.stack([ds.read_depth(r).astype(np.float64) for r in recs])))
    if not out:
        raise SystemExit(f"{path}: no frames with ground-truth depth and poses")
    return out


def depth_flow(K: np.ndarray, D: np.ndarray, T_t: np.ndarray, T_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per valid pixel: |project(true depth) - project(median depth)| and |project(true depth) - pixel|."""
    h, w = D.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    ok = D > 0
    rays = np.linalg.inv(K) @ np.stack([u[ok], v[ok], np.ones(ok.sum())])
    T = np.linalg.inv(T_s) @ T_t  # source-from-target
    out = []
    for d in (D[ok], np.full(ok.sum(), np.median(D[ok]))):
        X = T[:3, :3] @ (rays * d) + T[:3, 3:4]
        x = K @ X
        out.append(x[:2] / x[2:3])
    return np.linalg.norm(out[0] - out[1], axis=0), np.linalg.norm(out[0] - np.stack([u[ok], v[ok]]), axis=0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", type=Path, help="shards from `reloc ingest`, or a folder with depth/, poses.txt, K.txt")
    ap.add_argument("--offsets", default="1,2,3,5,10,20", help="frame offsets k")
    ap.add_argument("--every", type=int, default=10, help="use every Nth frame as a target")
    a = ap.parse_args()
    offsets = [int(k) for k in a.offsets.split(",")]
    seqs = sequences(a.data)
    print(f"{a.data}: fx {seqs[0][0][0, 0]:.1f}; |warp(true depth) - warp(median depth)| in pixels, "
          "median over frame pairs of the per-pair median and 90th percentile; the whole warp beside it")
    for k in offsets:
        vals, p90s, flows, moves = [], [], [], []
        for K, T, D in seqs:
            for t in range(0, len(T) - k, a.every):
                dflow, flow = depth_flow(K, D[t], T[t], T[t + k])
                vals.append(np.median(dflow))
                p90s.append(np.percentile(dflow, 90))
                flows.append(np.median(flow))
                moves.append(np.linalg.norm(T[t + k][:3, 3] - T[t][:3, 3]))
        print(f"  k={k:3d}: depth part median {np.median(vals):5.2f} px, p90 {np.median(p90s):5.2f} px; "
              f"whole warp {np.median(flows):6.2f} px; camera moved {100 * np.median(moves):.1f} cm")


if __name__ == "__main__":
    main()
