"""SSIM's 3x3 window means: shifted views (``relocdepth.losses.ssim_distance``) vs ``avg_pool2d``.

Measures, in one run, interleaved, one CPU thread unless ``--threads``:

(a) ``ssim_distance`` forward + backward on ``(36, 3, H, W)`` (the photometric term's batch of a
    step of 6 triplets: 6 pairs and the identity references) at each size, against the same SSIM
    with ``F.avg_pool2d(., 3, 1)`` (monodepth2's, which the project used before), and the largest
    difference of their values;
(b) a full training step of ``--recipe`` (default ``cpu-anchored-views``: batch of 6 triplets,
    forward, losses, backward, Adam) at ``--step-size`` on a generated scene, with each SSIM.

Prints the seconds (median of ``--reps``) and the ratios pool / shifted (above 1: shifted faster).

    python benchmarks/bench_ssim.py [--sizes 128x96,256x192,640x480] [--reps 5] [--step-size 128x96]
                                    [--step-reps 4] [--threads 1]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch
import torch.nn.functional as F

from relocdepth import losses


def ssim_pooled(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """The reference: ``ssim_distance`` with ``avg_pool2d`` for the window means."""
    x = F.pad(x, (1, 1, 1, 1), mode="reflect")
    y = F.pad(y, (1, 1, 1, 1), mode="reflect")
    mu_x, mu_y = F.avg_pool2d(x, 3, 1), F.avg_pool2d(y, 3, 1)
    sigma_x = F.avg_pool2d(x * x, 3, 1) - mu_x * mu_x
    sigma_y = F.avg_pool2d(y * y, 3, 1) - mu_y * mu_y
    sigma_xy = F.avg_pool2d(x * y, 3, 1) - mu_x * mu_y
    c1, c2 = losses.SSIM_C1, losses.SSIM_C2
    num = (2 * mu_x * mu_y + c1) * (2 * sigma_xy + c2)
    den = (mu_x * mu_x + mu_y * mu_y + c1) * (sigma_x + sigma_y + c2)
    return torch.clamp((1 - num / den) / 2, 0, 1)


def kernel_times(w: int, h: int, reps: int) -> tuple[float, float, float]:
    gen = torch.Generator().manual_seed(0)
    x = torch.rand(36, 3, h, w, generator=gen, requires_grad=True)
    y = torch.rand(36, 3, h, w, generator=gen, requires_grad=True)
    g = torch.rand(36, 3, h, w, generator=gen)
    with torch.no_grad():
        diff = float((losses.ssim_distance(x, y) - ssim_pooled(x, y)).abs().max())
    times: dict[str, list[float]] = {"shifted": [], "pool": []}
    for _ in range(reps + 1):  # the first of each: warm-up
        for name, f in (("shifted", losses.ssim_distance), ("pool", ssim_pooled)):
            t0 = time.perf_counter()
            torch.autograd.grad(f(x, y), (x, y), g)
            times[name].append(time.perf_counter() - t0)
    return statistics.median(times["shifted"][1:]), statistics.median(times["pool"][1:]), diff


def step_times(recipe: str, w: int, h: int, reps: int) -> tuple[float, float]:
    from relocdepth.data import collate
    from relocdepth.ingest.run import IngestConfig, ingest
    from relocdepth.recipes import RECIPES
    from relocdepth.synth import SynthConfig, generate_scene
    from relocdepth.train import TrainConfig, forward_losses, optimizer_step, sample, setup

    shifted = losses.ssim_distance
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        generate_scene(root / "scene", SynthConfig(seed=0, frames=30, width=w, height=h))
        ingest([root / "scene"], root / "shards", IngestConfig(shard_size=64))
        values = {**RECIPES[recipe], "size": (w, h), "pretrained": None, "workers": 0, "progress": False}
        tr, state = setup(root / "shards", root / "run", TrainConfig.from_dict(values))
        raw = collate([tr.data[t] for t in list(tr.sampler.iter_epoch(0))[:6]])

        def step() -> float:
            t0 = time.perf_counter()
            b = sample(tr, state, raw)
            loss, _, _ = forward_losses(tr, b, step=10)
            optimizer_step(tr, state, loss)
            return time.perf_counter() - t0

        times: dict[str, list[float]] = {"shifted": [], "pool": []}
        try:
            for _ in range(reps + 1):
                for name, f in (("shifted", shifted), ("pool", ssim_pooled)):
                    losses.ssim_distance = f  # photometric_error looks it up at each call
                    times[name].append(step())
        finally:
            losses.ssim_distance = shifted
            tr.log.close()
    return statistics.median(times["shifted"][1:]), statistics.median(times["pool"][1:])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="128x96,256x192,640x480", help="kernel sizes WxH")
    ap.add_argument("--reps", type=int, default=5, help="timed kernel repetitions (median)")
    ap.add_argument("--recipe", default="cpu-anchored-views", help="recipe of the timed training step")
    ap.add_argument("--step-size", default="128x96", help="training step size WxH ('' : no step)")
    ap.add_argument("--step-reps", type=int, default=4, help="timed steps with each SSIM (median)")
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    print(f"threads {a.threads}; seconds, median; ratio = pool / shifted")
    print("| what | size | shifted views (s) | avg_pool2d (s) | ratio | max difference |")
    print("|---|---|---|---|---|---|")
    for size in filter(None, a.sizes.split(",")):
        w, h = map(int, size.split("x"))
        s, p, d = kernel_times(w, h, a.reps)
        print(f"| ssim_distance fwd+bwd, 36x3 | {w}x{h} | {s:.4f} | {p:.4f} | {p / s:.2f} | {d:.1e} |", flush=True)
    if a.step_size:
        w, h = map(int, a.step_size.split("x"))
        s, p = step_times(a.recipe, w, h, a.step_reps)
        print(f"| train step, {a.recipe} | {w}x{h} | {s:.3f} | {p:.3f} | {p / s:.2f} | |")


if __name__ == "__main__":
    sys.exit(main())
