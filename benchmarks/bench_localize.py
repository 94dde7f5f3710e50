"""Localize latency per image vs the bare forward of the two networks, measured in one run.

For each network input size (640x480, 256x192) a checkpoint is written through the project's
checkpoint API (freshly built networks, random init: the cost does not depend on the weights)
and 16 frames of the synthetic room are rendered and saved as PNGs at that size. Then, for
batch 1 (4 images, one at a time) and batch 16, best of ``--reps`` interleaved passes:

- ``nets``: ``nets.depth(x)`` + ``nets.dsc(x)`` under ``torch.inference_mode`` on the batch the
  predictor feeds them (prepared once);
- ``localize``: what ``reloc localize FOLDER --format json`` does per image once the checkpoint is
  loaded (``localize_frames`` + ``format_records``): PNG decode (``cv2.imread`` + BGR->RGB), the
  intrinsics, resize to the input size (a no-op at the same size), stacking and float conversion,
  both networks, per-cell poses, the robust median pose, spread and confidence, copy to numpy,
  the stored alignment (none here), the per-image record (quaternion, ...) and the JSON lines;
- ``rest``: the same path with the networks' outputs cached: its exact overhead, cheap enough to
  measure precisely; ``est.`` = (nets + rest) / nets is the ratio without the noise of a shared
  machine;
- ``+depth-out``: one pass with ``--depth-out`` (16-bit depth PNG + colourised preview per image).

Times are wall clock; the ratio is also given on process CPU time. Checkpoint loading (once per
process) is reported apart. Torch runs with ``--threads`` intra-op threads: default 1, because on
the shared 2-core development machine 2 OpenMP threads competing with another job made a ResNet18
forward 4-15x slower than 1 thread (``--threads 0`` keeps torch's default). The load average is
printed at the start and the end.

    python benchmarks/bench_localize.py [--sizes 640x480,256x192] [--batches 1,16] [--reps 2] [--threads 1]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from dataclasses import asdict
from datetime import datetime, timezone
from pathlib import Path

GOAL = 1.2  # localize <= 1.2x the bare forward


def make_checkpoint(run: Path, w: int, h: int) -> Path:
    """A run folder with one checkpoint of freshly built networks at input size w x h."""
    import torch

    import relocdepth
    from relocdepth import checkpoint as ckpt_io
    from relocdepth.camera import Intrinsics
    from relocdepth.method import MethodConfig
    from relocdepth.models import ModelConfig, build_networks
    from relocdepth.train import TrainConfig

    torch.manual_seed(0)
    model_cfg = ModelConfig(pretrained=None)
    nets = build_networks(model_cfg)
    cam = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480).scaled(w, h)  # 7-Scenes RGB camera
    meta = {
        "format": ckpt_io.FORMAT, "format_version": ckpt_io.FORMAT_VERSION,
        "tool_version": relocdepth.__version__,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "step": 0, "epoch": 0, "position": 0, "manifest_hash": "benchmark",
        "dataset": {"name": "benchmark", "root": str(run)},
        "input_size": [w, h], "intrinsics": cam.to_dict(), "intrinsics_policy": "resize",
        "model": asdict(model_cfg), "method": asdict(MethodConfig()),
        "train": TrainConfig.from_dict({"size": (w, h), "pretrained": None}).to_dict(), "world_size": 1, "alignment": None,
    }
    return ckpt_io.save_checkpoint(run, {"meta": meta, "model": nets.state_dict()})


def make_images(folder: Path, w: int, h: int, n: int) -> list[Path]:
    """n frames of the synthetic room (seq-01 path) rendered at w x h, saved as PNG."""
    import cv2

    from relocdepth.camera import Intrinsics
    from relocdepth.synth import SynthConfig, build_scene, camera_paths, render

    cfg = SynthConfig(seed=0, frames=n, width=w, height=h)
    poses = next(iter(camera_paths(cfg).values()))
    scene = build_scene(cfg.seed, cfg)
    cam = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480).scaled(w, h)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, T in enumerate(poses[:n]):
        rgb, _ = render(scene, T, cam)
        p = folder / f"frame-{i:06d}.png"
        cv2.imwrite(str(p), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        paths.append(p)
    return paths


class CachedNets:
    """Stands in for the networks: returns outputs computed once, so that timing the localize
    path through it measures everything *but* the forward (decode, resize, geometry, records)."""

    training = False

    def __init__(self, nets, x) -> None:
        import torch

        self.cfg = nets.cfg
        with torch.inference_mode():
            self._disp = [nets.depth(x)[0].clone()]
            self._dsc = nets.dsc(x).clone()

    def depth(self, x):
        return self._disp

    def dsc(self, x):
        return self._dsc

    def eval(self) -> CachedNets:
        return self

    def train(self, mode: bool = True) -> CachedNets:
        return self


def timed(fn) -> tuple[float, float]:
    """(wall, process CPU) seconds of one call."""
    w0, c0 = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - w0, time.process_time() - c0


def bench_batch(predictor, items: list, bs: int, reps: int, depth_dir: Path) -> dict:
    """Best (wall, CPU) seconds of each measure over ``items`` localized ``bs`` at a time."""
    import torch

    from relocdepth.localize import DepthWriter, format_records, iter_frames, localize_frames
    from relocdepth.predictor import Predictor

    nets, (w, h) = predictor.nets, predictor.input_size
    inputs = []
    for i in range(0, len(items), bs):  # the tensors localize feeds the networks, prepared once
        frames = list(iter_frames(items[i:i + bs]))
        x, _ = predictor.prepare([f.image for f in frames], [predictor.intrinsics_for(w, h) for _ in frames])
        inputs.append(x)
    rest = Predictor(CachedNets(nets, inputs[0]), predictor.meta)

    def bare() -> None:
        with torch.inference_mode():
            for x in inputs:
                nets.depth(x)
                nets.dsc(x)

    def loc(pred: Predictor = predictor) -> None:
        format_records(localize_frames(pred, iter_frames(items), bs), "json")

    def loc_depth() -> None:
        writer = DepthWriter(depth_dir)
        format_records(localize_frames(predictor, iter_frames(items), bs, depth=writer), "json")
        writer.commit()

    best = {k: [float("inf")] * 2 for k in ("nets", "localize", "rest", "depth")}

    def keep(name: str, fn) -> None:
        best[name] = [min(a, b) for a, b in zip(best[name], timed(fn))]

    if len(inputs) > 1:  # warm-up (oneDNN primitives, allocator) on one batch; at batch 16 that would
        with torch.inference_mode():  # be a whole pass, and best-of-reps drops a slow first pass anyway
            nets.depth(inputs[0])
            nets.dsc(inputs[0])
    for _ in range(reps):  # interleaved, so that a burst of load hits both alike
        keep("nets", bare)
        keep("localize", loc)
    for _ in range(5):  # cheap: no forward
        keep("rest", lambda: loc(rest))
    keep("depth", loc_depth)  # one pass: for information
    return best


def bench_size(root: Path, w: int, h: int, n_images: int, reps: int, batches: list[int]) -> list[dict]:
    from relocdepth.localize import expand_inputs
    from relocdepth.predictor import Predictor

    run = root / f"run{w}x{h}"
    make_checkpoint(run, w, h)
    paths = make_images(root / f"img{w}x{h}", w, h, n_images)
    t0 = time.perf_counter()
    predictor = Predictor.from_checkpoint(run)
    load_s = time.perf_counter() - t0
    items = expand_inputs([str(p) for p in paths])
    rows = []
    for bs in batches:
        n = n_images if bs > 1 else min(n_images, 4)  # batch 1: a few images, one at a time
        best = bench_batch(predictor, items[:n], bs, reps, root / f"depth{w}x{h}b{bs}")
        rows.append({"size": f"{w}x{h}", "batch": bs, "images": n, "load_s": load_s,
                     **{f"{k}{sfx}": 1000.0 * v[i] / n for k, v in best.items()
                        for i, sfx in ((0, ""), (1, "_cpu"))}})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="640x480,256x192")
    ap.add_argument("--batches", default="1,16")
    ap.add_argument("--images", type=int, default=16, help="images per timed pass at batch > 1")
    ap.add_argument("--reps", type=int, default=2, help="timed passes per measure (best is kept)")
    ap.add_argument("--threads", type=int, default=1,
                    help="torch intra-op threads (0: torch's default). 1 because the 2 cores are shared: "
                         "with 2 OpenMP threads and another job running, a forward was 4-15x slower")
    args = ap.parse_args()
    import torch

    if args.threads > 0:
        torch.set_num_threads(args.threads)

    load0 = os.getloadavg()
    cpu0, wall0 = time.process_time(), time.perf_counter()
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_localize-") as tmp:
        for size in args.sizes.split(","):
            w, h = (int(v) for v in size.split("x"))
            rows += bench_size(Path(tmp), w, h, args.images, args.reps,
                               [int(b) for b in args.batches.split(",")])
    wall = time.perf_counter() - wall0
    cpu = time.process_time() - cpu0
    load1 = os.getloadavg()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, {os.cpu_count()} CPUs; "
          f"best of {args.reps} interleaved passes; load average (1 min) {load0[0]:.2f} at start, "
          f"{load1[0]:.2f} at end; this process used {cpu / wall:.2f} CPUs on average over {wall:.0f} s")
    print("query: PNGs at the network input size. ms per image, wall clock. ratio: localize / nets on wall "
          "clock, and on process CPU time (less sensitive to the other job); rest: the localize path with the "
          "networks' outputs cached (decode, prepare, geometry, records, JSON); est.: (nets + rest) / nets; "
          "+depth-out: one pass with --depth-out. Checkpoint load (once per process) excluded.")
    print(f"{'size':>9} {'batch':>5} {'imgs':>4} {'nets ms':>8} {'localize ms':>11} {'ratio':>6} {'cpu ratio':>9} "
          f"{'rest ms':>8} {'est.':>5} {'+depth-out ms':>13} {'ckpt load s':>11}")
    for r in rows:
        print(f"{r['size']:>9} {r['batch']:>5} {r['images']:>4} {r['nets']:>8.1f} {r['localize']:>11.1f} "
              f"{r['localize'] / r['nets']:>6.2f} {r['localize_cpu'] / r['nets_cpu']:>9.2f} {r['rest']:>8.1f} "
              f"{(r['nets'] + r['rest']) / r['nets']:>5.2f} {r['depth']:>13.1f} {r['load_s']:>11.2f}")
    worst = max(r["localize"] / r["nets"] for r in rows)
    est = max((r["nets"] + r["rest"]) / r["nets"] for r in rows)
    print(f"goal localize / nets <= {GOAL}: measured worst {worst:.2f} ({'met' if worst <= GOAL else 'NOT met'}), "
          f"estimated from the parts worst {est:.2f} ({'met' if est <= GOAL else 'NOT met'})")


if __name__ == "__main__":
    main()
