"""Forward + backward cost of the method's networks: the floor a training step is measured against.

For a batch of 6 triplets (18 images) at each size, one fresh process per size (so its peak RSS is
its own) measures:

- ``nets``: bare forward + backward of the depth and DSC networks (a trivial loss on their outputs);
- ``step``: forward + backward of the full ``triplet_loss`` (LCVS, 6 pairs, 4 scales), same batch,
  once per loss resolution asked for (``input``: every scale warped at the input size; ``decoder``:
  each scale at its decoder layer's size), each in its own process;
- the ratio step / nets (what the method's geometry and losses add on top of the networks), and
  per size the ratios decoder / input of the step time and of the peak RSS;
- peak RSS of the process (``resource.getrusage``), RSS after building the networks, and the load
  average of the machine before and after (the numbers are only comparable on a quiet machine).

``--loss-only`` times the loss alone: the networks' outputs are computed once (one image at a time,
without gradients) and fed to ``triplet_loss`` as leaf tensors, so the step is the geometry and
losses with their backward down to those outputs, and the memory is the loss's own (for sizes where
the networks and the loss together do not fit next to other jobs).

Usage: ``python benchmarks/bench_core.py [--sizes 128x96,256x192,640x480] [--iters 3]
[--iters-large 1] [--warmup 1] [--device cpu|cuda] [--threads N] [--recompute-warps]
[--loss-resolutions input,decoder] [--loss-only]``. Prints one table; numbers go to the README (performance).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from typing import Any

THREADS = int(sys.argv[sys.argv.index("--threads") + 1]) if "--threads" in sys.argv else 0  # 0: torch's default
RECOMPUTE = "--recompute-warps" in sys.argv  # MethodConfig.recompute_warps for the loss step
LOSS_ONLY = "--loss-only" in sys.argv  # time triplet_loss on cached network outputs, without the networks
TRIPLETS = 6  # the paper's batch size (Sec. IV-B)
LARGE_PIXELS = 640 * 480


def _rss_mb() -> float:
    # ru_maxrss is in KiB on Linux
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _load() -> float:
    return os.getloadavg()[0]


class _CachedOutputs:
    """The networks' outputs on a fixed batch as leaf tensors, behind the ``.depth`` / ``.dsc`` calls
    that ``triplet_loss`` makes: the loss and its backward run, the networks do not."""

    def __init__(self, nets: Any, flat: Any) -> None:
        import torch

        with torch.no_grad():  # one image at a time: the peak stays that of one forward
            outs = [(nets.depth(x[None]), nets.dsc(x[None])) for x in flat]
        self.disps = [torch.cat([o[0][k] for o in outs]).requires_grad_() for k in range(len(outs[0][0]))]
        self.dsc_out = torch.cat([o[1] for o in outs]).requires_grad_()

    def depth(self, x: Any) -> list:
        return self.disps

    def dsc(self, x: Any) -> Any:
        return self.dsc_out

    def zero_grad(self, set_to_none: bool = True) -> None:
        for t in [*self.disps, self.dsc_out]:
            t.grad = None


def run_one(width: int, height: int, iters: int, warmup: int, device: str, loss_resolution: str) -> dict:
    import torch

    from relocdepth.method import MethodConfig, triplet_loss
    from relocdepth.models import ModelConfig, build_networks

    if THREADS:
        torch.set_num_threads(THREADS)
    torch.manual_seed(0)
    dev = torch.device(device)
    nets = build_networks(ModelConfig()).to(dev).train()
    rss_built = _rss_mb()
    images = torch.rand(TRIPLETS, 3, 3, height, width, device=dev)
    K = torch.tensor([[0.9 * width, 0, (width - 1) / 2], [0, 0.9 * width, (height - 1) / 2], [0, 0, 1]],
                     device=dev).expand(TRIPLETS, 3, 3, 3).contiguous()
    flat = images.flatten(0, 1)

    def sync() -> None:
        if dev.type == "cuda":
            torch.cuda.synchronize()

    def nets_step() -> None:
        disps = nets.depth(flat)
        dsc = nets.dsc(flat)
        (sum(d.mean() for d in disps) + dsc.mean()).backward()
        nets.zero_grad(set_to_none=True)

    model: Any = nets
    if LOSS_ONLY:
        model = _CachedOutputs(nets, flat)
        rss_built = _rss_mb()

    def loss_step() -> None:
        cfg = MethodConfig(recompute_warps=RECOMPUTE, loss_resolution=loss_resolution)
        total, _, _ = triplet_loss(model, images, images, K, cfg)
        total.backward()
        model.zero_grad(set_to_none=True)

    out: dict = {"size": f"{width}x{height}", "loss_resolution": loss_resolution, "recompute_warps": RECOMPUTE,
                 "loss_only": LOSS_ONLY, "images": TRIPLETS * 3, "iters": iters, "warmup": warmup,
                 "threads": torch.get_num_threads(), "rss_built_mb": rss_built, "load_before": _load()}
    steps = (("step", loss_step),) if LOSS_ONLY else (("nets", nets_step), ("step", loss_step))
    for name, fn in steps:
        for _ in range(warmup):  # allocator, kernels; negligible next to a 640x480 step on CPU
            fn()
        sync()
        t0 = time.perf_counter()
        for _ in range(iters):
            fn()
        sync()
        out[f"{name}_s"] = (time.perf_counter() - t0) / iters
        out[f"peak_rss_after_{name}_mb"] = _rss_mb()  # ru_maxrss only grows: nets first, then + losses
    out["peak_rss_mb"] = _rss_mb()
    out["load_after"] = _load()
    # what the loss adds to the networks: time and memory
    out["own_s"] = out["step_s"] - out.get("nets_s", 0.0)
    out["own_mb"] = out["peak_rss_mb"] - out.get("peak_rss_after_nets_mb", rss_built)
    if dev.type == "cuda":
        out["peak_cuda_mb"] = torch.cuda.max_memory_allocated() / 2**20
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="128x96,256x192,640x480")
    ap.add_argument("--iters", type=int, default=3, help="timed iterations per size")
    ap.add_argument("--iters-large", type=int, default=1, help="timed iterations at >= 640x480")
    ap.add_argument("--warmup", type=int, default=1, help="untimed iterations (0 at >= 640x480)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=0,
                    help="torch threads (0: default); 1 avoids oversubscribing a CPU shared with another job")
    ap.add_argument("--recompute-warps", action="store_true", help="the loss step with MethodConfig(recompute_warps=True)")
    ap.add_argument("--loss-only", action="store_true",
                    help="time triplet_loss on cached network outputs (the loss's own time and memory)")
    ap.add_argument("--loss-resolutions", default="input",
                    help="comma-separated MethodConfig.loss_resolution values to time (input, decoder)")
    ap.add_argument("--one", default=None, help=argparse.SUPPRESS)  # child mode: WxH
    ap.add_argument("--mode", default="input", help=argparse.SUPPRESS)  # child's loss resolution
    args = ap.parse_args()
    if args.one:
        w, h = (int(v) for v in args.one.split("x"))
        print(json.dumps(run_one(w, h, args.iters, args.warmup, args.device, args.mode)))
        return
    rows = []
    for size in args.sizes.split(","):
        w, h = (int(v) for v in size.split("x"))
        large = w * h >= LARGE_PIXELS and args.device == "cpu"
        iters = args.iters_large if large else args.iters
        warmup = 0 if large else args.warmup
        for mode in args.loss_resolutions.split(","):
            res = subprocess.run(
                [sys.executable, __file__, "--one", size, "--mode", mode, "--iters", str(iters),
                 "--warmup", str(warmup), "--device", args.device, "--threads", str(THREADS)]
                + (["--recompute-warps"] if RECOMPUTE else []) + (["--loss-only"] if LOSS_ONLY else []),
                check=False, capture_output=True, text=True,
            )
            if res.returncode != 0:  # e.g. killed by the kernel's OOM killer at 640x480 on a small machine
                print(f"{size} {mode}: child failed with exit code {res.returncode} (negative: signal; -9 is "
                      f"the OOM killer): {res.stderr.strip().splitlines()[-1:]}", flush=True)
                continue
            rows.append(json.loads(res.stdout.strip().splitlines()[-1]))
            print(f"{size} {mode}: {json.dumps(rows[-1])}", flush=True)
    if not rows:
        return
    print(f"batch: {TRIPLETS} triplets = {TRIPLETS * 3} images, device {args.device}, "
          f"torch threads {rows[0]['threads']}, recompute warps {RECOMPUTE}, "
          + ("loss only (cached network outputs)" if LOSS_ONLY else "networks + loss"))
    print(f"{'size':>9} {'loss res':>8} {'iters':>5} {'nets fwd+bwd s':>15} {'loss step s':>12} "
          f"{'step/nets':>9} {'loss own s':>10} {'RSS built MB':>12} {'peak RSS MB':>11} {'loss own MB':>11} "
          f"{'load':>9}")
    for r in rows:
        nets_s = f"{r['nets_s']:>15.2f}" if "nets_s" in r else f"{'-':>15}"
        ratio = f"{r['step_s'] / r['nets_s']:>9.2f}" if "nets_s" in r else f"{'-':>9}"
        print(f"{r['size']:>9} {r['loss_resolution']:>8} {r['iters']:>5} {nets_s} {r['step_s']:>12.2f} {ratio} "
              f"{r['own_s']:>10.2f} {r['rss_built_mb']:>12.0f} {r['peak_rss_mb']:>11.0f} {r['own_mb']:>11.0f} "
              f"{r['load_before']:>4.1f}-{r['load_after']:<4.1f}"
              + (f"  cuda peak {r['peak_cuda_mb']:.0f} MB" if "peak_cuda_mb" in r else ""))
    by_size: dict[str, dict[str, dict]] = {}
    for r in rows:
        by_size.setdefault(r["size"], {})[r["loss_resolution"]] = r
    for size, modes in by_size.items():
        if "input" in modes and "decoder" in modes:
            dec, inp = modes["decoder"], modes["input"]
            print(f"{size}: decoder / input: loss step time {dec['step_s'] / inp['step_s']:.2f} (the loss's "
                  f"own time: {dec['own_s'] / inp['own_s']:.2f}), peak RSS "
                  f"{dec['peak_rss_mb'] / inp['peak_rss_mb']:.2f} (the loss's own memory: "
                  f"{dec['own_mb'] / max(inp['own_mb'], 1.0):.2f})")


if __name__ == "__main__":
    main()
