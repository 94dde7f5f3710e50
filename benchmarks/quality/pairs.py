"""How good are the essential-matrix bootstrap's pairs, against ground truth?

For frames k apart in each training sequence (shards from `reloc ingest`, or one walk-through
folder as `vo_trajectory.py` reads it), `relocdepth.twoview.bootstrap_pair` at a tracking size:
how many pairs work, how many have a measured translation (the rest are rotation only), the
rotation error (median, 90th percentile) of the pairs that work, and the translation direction's
error (median, 75th percentile) of the measured ones, and the CPU time per pair (ground truth
comparisons included; small). `--levels` compares KLT pyramid depths
(`TrackConfig.max_level`; OpenCV stops where a level would be no larger than the window).

    python benchmarks/quality/pairs.py /tmp/demo640/shards --offsets 1,3,5,10 --levels 3,5
    python benchmarks/quality/pairs.py ../shared/data/hololens-office --frames 120 --offsets 1,2
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from vo_trajectory import _resize, load  # noqa: E402

from relocdepth.eval_geometry import rotation_angle_deg  # noqa: E402
from relocdepth.twoview import TrackConfig, bootstrap_pair  # noqa: E402


def score(seq, k: int, every: int, track: TrackConfig) -> dict:
    """Pairs (i, i + k) for every ``every``-th frame i of one sequence, against its ground truth."""
    K = seq.intrinsics.K()
    n = ok_n = 0
    rot, direction = [], []
    t0 = time.process_time()
    for i in range(0, len(seq.images) - k, every):
        T, _, ok = bootstrap_pair(seq.images[i], seq.images[i + k], K, K, cfg=track)
        T_gt = np.linalg.inv(seq.T_gt[i + k]) @ seq.T_gt[i]  # b <- a
        n += 1
        if not ok:
            continue
        ok_n += 1
        rot.append(rotation_angle_deg(T[:3, :3].T @ T_gt[:3, :3]))
        t, t_gt = T[:3, 3], T_gt[:3, 3]
        if np.linalg.norm(t) > 0 and np.linalg.norm(t_gt) > 0:
            c = t @ t_gt / (np.linalg.norm(t) * np.linalg.norm(t_gt))
            direction.append(float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))))
    return {"pairs": n, "ok": ok_n, "measured": len(direction), "rot": rot, "dir": direction,
            "seconds": time.process_time() - t0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", type=Path, help="shards from `reloc ingest`, or a walk-through folder")
    ap.add_argument("--size", help="track at WxH (default: as stored)")
    ap.add_argument("--frames", type=int, default=90, help="walk-through: its first N frames")
    ap.add_argument("--offsets", default="1,3,5,10", help="frame offsets k")
    ap.add_argument("--every", type=int, default=2, help="a pair from every Nth frame")
    ap.add_argument("--levels", default=str(TrackConfig.max_level), help="KLT pyramid levels to compare")
    a = ap.parse_args()
    size = tuple(int(v) for v in a.size.lower().split("x")) if a.size else None
    seqs = [_resize(s, size) for s in load(a.data, a.frames)]
    print(f"{a.data}: {', '.join(f'{s.name} ({len(s.images)})' for s in seqs)} at "
          f"{seqs[0].intrinsics.width}x{seqs[0].intrinsics.height}")
    print("| levels | k | pairs | work | measured | rotation error median / p90 (deg) "
          "| direction error median / p75 (deg) | ms / pair |")
    print("|---|---|---|---|---|---|---|---|")
    for levels in (int(v) for v in a.levels.split(",")):
        for k in (int(v) for v in a.offsets.split(",")):
            rows = [score(s, k, a.every, TrackConfig(max_level=levels)) for s in seqs]
            rot = np.concatenate([r["rot"] for r in rows] + [[]])
            d = np.concatenate([r["dir"] for r in rows] + [[]])

            def q(x: np.ndarray, p: float) -> str:
                return f"{np.percentile(x, p):.2f}" if len(x) else "-"

            print(f"| {levels} | {k} | {sum(r['pairs'] for r in rows)} | {sum(r['ok'] for r in rows)} | "
                  f"{sum(r['measured'] for r in rows)} | {q(rot, 50)} / {q(rot, 90)} | {q(d, 50)} / {q(d, 75)} | "
                  f"{1000 * sum(r['seconds'] for r in rows) / max(1, sum(r['pairs'] for r in rows)):.1f} |")


if __name__ == "__main__":
    main()
