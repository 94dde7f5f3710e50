"""Refinement on real images, with a perfect map: how precise are the pairs and the alignment?

A walk-through folder (images/, depth/, poses.txt, K.txt; e.g. shared/data/hololens-office) is
split as ``walkthrough.py`` splits it (the last ``--test`` frames, or ``--blocks`` blocks inside the
walk). The map is the training frames with their *true* poses and depth (what a perfectly trained
network would give), so what is measured is the refinement alone: each test frame starts from
its true pose moved ``--offset-m`` in a random direction and turned ``--offset-deg`` about a random
axis (a network's error), and is refined (``relocdepth.refine.refine_pose``) against its
neighbours, once per mode:

- ``two-view``: the pairs' robust mean (``align`` off), the network's pose kept under
  ``--min-pairs`` agreeing pairs;
- ``aligned``: the same, then direct alignment from it and from the start, the better kept (the
  default);
- ``align-only``: direct alignment from the start alone (no pairs).

    python benchmarks/quality/refine_real.py ../shared/data/hololens-office --blocks 3
    python benchmarks/quality/refine_real.py ../shared/data/hololens-office --test 30 --offset-m 0.2
    python benchmarks/quality/refine_real.py ../shared/data/hololens-office --blocks 3 --depth-error 0.15

Prints a markdown table (median translation / rotation error, the share within 5 cm / 5 deg, the
frames beyond 10 cm, with enough agreeing pairs, placed by the alignment, seconds a query) and writes the per-frame errors as JSON with ``--out``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from walkthrough import test_ranges  # noqa: E402

from relocdepth.camera import Intrinsics  # noqa: E402
from relocdepth.eval_geometry import rotation_angle_deg  # noqa: E402
from relocdepth.refine import Reference, RefFrame, RefineConfig, refine_pose  # noqa: E402

MODES = ("two-view", "aligned", "align-only")


def perturb(T: np.ndarray, metres: float, degrees: float, rng: np.random.Generator) -> np.ndarray:
    """``T`` moved ``metres`` in a random direction and turned ``degrees`` about a random axis."""
    d, a = rng.normal(size=3), rng.normal(size=3)
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ cv2.Rodrigues(np.radians(degrees) * a / np.linalg.norm(a))[0]
    out[:3, 3] += metres * d / np.linalg.norm(d)
    return out


def smooth_factor(shape: tuple[int, int], mean_rel: float, rng: np.random.Generator) -> np.ndarray:
    """A smooth positive field (a 4x3 random grid, bicubic) whose mean |factor - 1| is ``mean_rel``."""
    grid = rng.normal(size=(3, 4)).astype(np.float32)
    field = cv2.resize(grid, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)
    field *= np.log1p(mean_rel) / max(float(np.mean(np.abs(field))), 1e-9)
    return np.exp(field)


def errors(T: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    return (float(np.linalg.norm(T[:3, 3] - truth[:3, 3])),
            float(rotation_angle_deg(T[:3, :3].T @ truth[:3, :3])))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", type=Path, help="walk-through folder: images/, depth/, poses.txt, K.txt")
    ap.add_argument("--test", type=int, default=30, help="test frames (default 30)")
    ap.add_argument("--blocks", type=int, default=1, help="test blocks inside the walk (1: the last frames)")
    ap.add_argument("--offset-m", type=float, default=0.10, help="start this far from the truth (m)")
    ap.add_argument("--offset-deg", type=float, default=3.0, help="start turned this much (deg)")
    ap.add_argument("--neighbours", type=int, default=3, help="training frames paired with each query")
    ap.add_argument("--min-pairs", type=int, default=2, help="agreeing pairs needed")
    ap.add_argument("--modes", default=",".join(MODES), help=f"comma-separated, of {', '.join(MODES)}")
    ap.add_argument("--depth-error", type=float, default=0.0,
                    help="the map's depth off by a smooth random factor of about this mean relative error "
                         "(a network's depth: AbsRel ~0.1-0.2), fixed per map frame (default 0: true depth)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, help="per-frame errors as JSON")
    args = ap.parse_args()

    images = sorted((args.data / "images").glob("*.png"))
    depths = sorted((args.data / "depth").glob("*.png"))
    poses = np.loadtxt(args.data / "poses.txt").reshape(-1, 4, 4)
    K = np.loadtxt(args.data / "K.txt").reshape(3, 3)
    tests = [i for lo, hi in test_ranges(len(images), args.test, args.blocks) for i in range(lo, hi)]
    train = [i for i in range(len(images)) if i not in set(tests)]

    def read(i: int) -> np.ndarray:
        return cv2.cvtColor(cv2.imread(str(images[i])), cv2.COLOR_BGR2RGB)

    def load(j: int) -> RefFrame:
        i = train[j]
        depth = cv2.imread(str(depths[i]), cv2.IMREAD_UNCHANGED).astype(np.float32) / 1000.0
        if args.depth_error > 0:
            depth *= smooth_factor(depth.shape, args.depth_error, np.random.default_rng([args.seed, i]))
        return RefFrame(read(i), K, depth)

    h, w = read(0).shape[:2]
    intr = Intrinsics(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], width=w, height=h)
    ref = Reference(poses[train], load)
    rng = np.random.default_rng(args.seed)
    starts = {i: perturb(poses[i], args.offset_m, args.offset_deg, rng) for i in tests}
    base = RefineConfig(neighbours=args.neighbours, min_pairs=args.min_pairs)
    configs = {"two-view": replace(base, align=False), "aligned": base,
               "align-only": replace(base, min_pairs=10**6)}
    rows, frames = [], {}
    for mode in args.modes.split(","):
        cfg, out, secs = configs[mode], [], 0.0
        for i in tests:
            img = read(i)
            t0 = time.perf_counter()
            r = refine_pose(ref, img, intr, starts[i], cfg)
            secs += time.perf_counter() - t0
            out.append((*errors(r.T_wc, poses[i]), r.pairs, r.by == "aligned"))
        e = np.array(out)
        frames[mode] = {str(i): list(map(float, r)) for i, r in zip(tests, out)}
        rows.append(f"| {mode} | {np.median(e[:, 0]):.3f} / {np.median(e[:, 1]):.2f} | "
                    f"{np.mean((e[:, 0] < 0.05) & (e[:, 1] < 5)) * 100:.0f} % | {np.sum(e[:, 0] > 0.1)} | "
                    f"{np.sum(e[:, 2] >= args.min_pairs)} | {np.sum(e[:, 3] > 0)} | {secs / len(tests):.2f} |")
        print(rows[-1], flush=True)
    start = np.array([errors(starts[i], poses[i]) for i in tests])
    print(f"\n{len(train)} map frames, {len(tests)} queries ({args.blocks} block(s)), start "
          f"{np.median(start[:, 0]):.3f} m / {np.median(start[:, 1]):.2f} deg\n")
    print("| mode | median t (m) / r (deg) | 5cm/5deg | beyond 0.1 m | pairs agreeing | aligned | s / query |")
    print("|---|---|---|---|---|---|---|")
    print("\n".join(rows))
    if args.out:
        args.out.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()},
                                        "frames": frames}, indent=1))


if __name__ == "__main__":
    main()
