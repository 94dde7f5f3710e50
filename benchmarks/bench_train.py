"""Trainer benchmarks, printed as ratios measured in one run.

(a) loader triplets/s (read + decode + augment + collate, batch 6) at 128x96 and 640x480 with
    0/1/2 workers vs the triplets/s a train step consumes at that size; plus the streaming
    (webdataset over the tars) vs indexed random access read rate of image bytes;
(b) a full train step (batch to device, forward, losses, finite check, backward, Adam step, log)
    vs the bare forward + backward of the networks through ``triplet_loss`` on the same batch;
(c) peak RSS of a training process at 640x480, batch 6 (a child process, 2 steps);
(d) at 128x96, the bare forward + backward with the novel views' term (``--w-novel-view``) vs without.
At 640x480 the step runs with ``recompute_warps=True`` (without it, > 21 GB: the OOM killer here).

    python benchmarks/bench_train.py [--quick] [--threads N]
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def make_shards(root: Path, w: int, h: int, frames: int) -> Path:
    from relocdepth.ingest.run import IngestConfig, ingest

    from relocdepth.synth import SynthConfig, generate_scene

    scene, shards = root / f"scene{w}", root / f"shards{w}"
    generate_scene(scene, SynthConfig(seed=0, frames=frames, width=w, height=h))
    ingest([scene], shards, IngestConfig(shard_size=64))
    return shards


def loader_rate(shards: Path, w: int, h: int, workers: int, batches: int) -> float:
    from relocdepth.data import AugmentConfig, ImageFrames, TripletData, make_loader
    from relocdepth.sampler import SamplerConfig, TripletSampler

    frames = ImageFrames.open(shards)
    sampler = TripletSampler(frames.keys(), SamplerConfig())
    loader = make_loader(TripletData(frames, AugmentConfig(w, h)), sampler, 0, 0, 6, workers)
    it = iter(loader)
    next(it)  # worker start-up is not throughput
    t0, n = time.perf_counter(), 0
    for _ in range(batches):
        try:
            n += next(it)["images"].shape[0]
        except StopIteration:
            break
    return n / (time.perf_counter() - t0)


def read_rates(shards: Path) -> tuple[float, float]:
    """Image frames/s: random access by offset (training order) vs streaming every tar member."""
    import webdataset as wds

    from relocdepth.data import ImageFrames
    from relocdepth.imageio import decode_rgb
    from relocdepth.sampler import SamplerConfig, TripletSampler

    frames = ImageFrames.open(shards)
    order = [t.target for t in TripletSampler(frames.keys(), SamplerConfig()).iter_epoch(0)]
    t0 = time.perf_counter()
    for i in order:
        decode_rgb(frames.read_image_bytes(i))
    ra = len(order) / (time.perf_counter() - t0)
    urls = sorted(str(p) for p in shards.glob("shard-*.tar"))
    t0, n = time.perf_counter(), 0
    for s in wds.WebDataset(urls, shardshuffle=False):
        ext = "png" if "png" in s else "jpg"
        decode_rgb(s[ext])
        n += 1
    return ra, n / (time.perf_counter() - t0)


def step_rates(shards: Path, w: int, h: int, reps: int, novel_view: bool = False) -> tuple[float, float, float]:
    """Seconds of (full train step, bare forward+backward, the bare one with ``w_novel_view`` 0.5
    when ``novel_view``, else NaN) on one batch of 6 triplets, interleaved."""
    import dataclasses

    import torch

    from relocdepth.data import collate
    from relocdepth.method import triplet_loss
    from relocdepth.train import (
        RunState,
        TrainConfig,
        forward_losses,
        log_step,
        optimizer_step,
        sample,
        setup,
    )

    with tempfile.TemporaryDirectory() as tmp:
        # 640x480 x 6 triplets needs > 21 GB on CPU unless the warps are recomputed in backward
        # with the weights' moving average, as the CPU recipes keep it (its update is in the full step)
        cfg = TrainConfig.from_dict({"size": (w, h), "pretrained": None, "workers": 0, "ema_decay": 0.99,
                                     "progress": False, "recompute_warps": w * h >= 640 * 480})
        tr, state = setup(shards, Path(tmp) / "run", cfg)
        trips = list(tr.sampler.iter_epoch(0))[:6]
        raw = collate([tr.data[t] for t in trips])
        full, bare, nv = [], [], []
        nv_cfg = dataclasses.replace(tr.cfg.method, w_novel_view=0.5)

        def sync() -> None:
            if tr.device.type == "cuda":
                torch.cuda.synchronize()

        for _ in range(reps):
            sync()
            t0 = time.perf_counter()
            b = sample(tr, state, raw)
            loss, parts, diag = forward_losses(tr, b)
            optimizer_step(tr, state, loss)
            log_step(tr, state, loss, parts, diag, 0.0, 0.0)
            sync()
            full.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            loss2, _, _ = triplet_loss(tr.nets, b["images"], b["inputs"], b["K"], tr.cfg.method)
            tr.optimizer.zero_grad(set_to_none=True)
            loss2.backward()
            sync()
            bare.append(time.perf_counter() - t0)
            if novel_view:
                t0 = time.perf_counter()
                loss3, _, _ = triplet_loss(tr.nets, b["images"], b["inputs"], b["K"], nv_cfg)
                tr.optimizer.zero_grad(set_to_none=True)
                loss3.backward()
                sync()
                nv.append(time.perf_counter() - t0)
        tr.log.close()
        assert isinstance(state, RunState) and torch.isfinite(loss)
    nv_s = statistics.median(nv[1:] or nv) if nv else float("nan")
    return statistics.median(full[1:] or full), statistics.median(bare[1:] or bare), nv_s


def child_rss(shards: str) -> None:
    """Run 2 steps at 640x480, batch 6, workers 0; print the peak RSS (MiB)."""
    from relocdepth.train import TrainConfig, train

    with tempfile.TemporaryDirectory() as tmp:
        train(shards, Path(tmp) / "run", TrainConfig.from_dict({"size": (640, 480),
                                                                "pretrained": None, "workers": 0,
                                                                "recompute_warps": True,
                                                                "progress": False, "max_steps": 2,
                                                                "checkpoint_every": 100}))
    print(json.dumps({"peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="fewer repetitions")
    ap.add_argument("--child-rss", help=argparse.SUPPRESS)
    ap.add_argument("--threads", type=int, default=0,
                    help="torch threads (0: default); 1 avoids oversubscribing a CPU shared with another job")
    args = ap.parse_args()
    if args.threads:
        import os

        import torch

        os.environ["OMP_NUM_THREADS"] = str(args.threads)  # inherited by the RSS child
        torch.set_num_threads(args.threads)
    if args.child_rss:
        child_rss(args.child_rss)
        return
    reps, batches = (2, 4) if args.quick else (4, 8)
    with tempfile.TemporaryDirectory() as tmp:
        sizes = {(128, 96): make_shards(Path(tmp), 128, 96, 60), (640, 480): make_shards(Path(tmp), 640, 480, 30)}
        for (w, h), shards in sizes.items():
            step_s, bare_s, nv_s = step_rates(shards, w, h, reps if w == 128 else 2, novel_view=w == 128)
            consume = 6 / step_s
            print(f"\n== {w}x{h}, batch 6 ==")
            print(f"(b) train step {step_s:.2f} s vs bare forward+backward {bare_s:.2f} s: "
                  f"ratio {step_s / bare_s:.3f} (goal <= 1.15)")
            if w == 128:
                print(f"(d) bare forward+backward with --w-novel-view {nv_s:.2f} s: ratio {nv_s / bare_s:.3f} to without")
            print(f"    a train step consumes {consume:.2f} triplets/s")
            for workers in (0, 1, 2):
                r = loader_rate(shards, w, h, workers, batches)
                print(f"(a) loader, {workers} workers: {r:.1f} triplets/s = {r / consume:.1f}x what the step consumes")
            ra, st = read_rates(shards)
            print(f"    read+decode: random access {ra:.0f} frames/s vs webdataset streaming {st:.0f} frames/s "
                  f"(ratio {ra / st:.2f})")
        out = subprocess.run([sys.executable, __file__, "--child-rss", str(sizes[(640, 480)])],
                             capture_output=True, text=True, check=True).stdout
        rss = json.loads(out.strip().splitlines()[-1])["peak_rss_mib"]
        print(f"\n(c) peak RSS, 640x480, batch 6, 0 workers, --recompute-warps: {rss:.0f} MiB")


if __name__ == "__main__":
    main()
