"""Motion and depth-parallax statistics of the `reloc synth` default scene vs real 7-Scenes video.

For every sequence of the scene (default: seed 0, 3 x 300 frames) and frame offsets k, this prints
the median over frame pairs (t, t + k) of the camera translation and rotation between them (from
the poses alone, every t) and of the depth part of the warp (benchmarks/quality/parallax.py: how far
a pixel's reprojection into frame t + k moves when the true depth replaces the frame's median
depth), per pair its median and 90th percentile over pixels, then the median over pairs. Depth is
rendered with `relocdepth.synth.render` for every ``--every``-th frame as a target at ``--size``;
pixel figures are also given scaled to 640 px width (they scale with fx). The reference column
is a real 7-Scenes kitchen (two sequences, 1000 frames, 640x480, fx 525) measured the same way.

    python benchmarks/quality/synth_stats.py [--size 640x480] [--every 5] [--seed 0] [--frames 300]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from parallax import depth_flow

from relocdepth.synth import (
    SEVEN_SCENES_INTRINSICS,
    SynthConfig,
    build_scene,
    camera_paths,
    pair_motion,
    render,
)

# Real 7-Scenes kitchen (640x480, fx 525): k -> (translation cm, rotation deg, depth part median
# px, depth part p90 px), medians over frame pairs k apart.
SEVEN_SCENES_KITCHEN = {1: (0.74, 1.57, 0.33, 1.5), 5: (3.46, 2.38, 1.51, 7.1),
                        10: (6.93, 3.72, 2.95, 14.1), 20: (14.0, 6.60, 6.00, 29.1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="640x480", help="render size WIDTHxHEIGHT for the depth part")
    ap.add_argument("--every", type=int, default=5, help="every Nth frame is a target")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--frames", type=int, default=SynthConfig.frames)
    ap.add_argument("--offsets", default="1,5,10,20")
    ap.add_argument("--no-render", action="store_true", help="poses only")
    a = ap.parse_args()
    w, h = (int(v) for v in a.size.split("x"))
    offsets = [int(k) for k in a.offsets.split(",")]
    cfg = SynthConfig(seed=a.seed, frames=a.frames)
    paths = camera_paths(cfg)
    scene = build_scene(cfg.seed, cfg)
    intr = SEVEN_SCENES_INTRINSICS.scaled(w, h)
    K = intr.K()
    depth: dict[tuple[str, int], np.ndarray] = {}
    start = time.process_time()  # CPU time: steadier than wall time on a shared machine
    if not a.no_render:
        for name, T in paths.items():
            for t in range(0, len(T) - min(offsets), a.every):
                depth[name, t] = render(scene, T[t], intr)[1].astype(np.float64)
    ms = 1000 * (time.process_time() - start) / max(len(depth), 1)
    print(f"synth seed {cfg.seed}, {len(paths)} x {cfg.frames} frames; depth part rendered at "
          f"{w}x{h} for {len(depth)} targets ({ms:.0f} ms CPU per frame), shown scaled to 640 px width")
    print("| k | translation cm synth / real | rotation deg synth / real "
          "| depth part median px synth / real | depth part p90 px synth / real |")
    print("|---|---|---|---|---|")
    scale = 640 / w
    for k in offsets:
        trans, rot = zip(*(pair_motion(T, k) for T in paths.values()))
        med, p90 = [], []
        for name, T in paths.items():
            for t in range(0, len(T) - k, a.every):
                if (name, t) in depth:
                    flow, _ = depth_flow(K, depth[name, t], T[t], T[t + k])
                    med.append(np.median(flow) * scale)
                    p90.append(np.percentile(flow, 90) * scale)
        real = SEVEN_SCENES_KITCHEN.get(k, (np.nan,) * 4)
        dm = f"{np.median(med):.2f}" if med else "-"
        dp = f"{np.median(p90):.1f}" if p90 else "-"
        print(f"| {k} | {100 * np.median(np.concatenate(trans)):.2f} / {real[0]:.2f} "
              f"| {np.median(np.concatenate(rot)):.2f} / {real[1]:.2f} "
              f"| {dm} / {real[2]:.2f} | {dp} / {real[3]:.1f} |")


if __name__ == "__main__":
    main()
