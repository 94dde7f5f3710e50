"""What ``--refine`` costs per query, against the network's pose alone, measured in one run.

Needs a trained run and its shards (refinement is only meaningful with a network that has learned
the place: its neighbours, and so its pairs, depend on the network's poses). On the shards' test
frames, interleaved passes, best of ``--reps``:

- ``network``: the localize path (``localize_frames``, batch 1) without refinement;
- ``refined``: the same with a :class:`relocdepth.refine.Refiner` whose map (the training frames'
  poses) is built beforehand (the defaults: pairs, then direct alignment); the depth of the
  neighbours is cached across passes only from the second pass on, so the first refined pass's
  time is reported apart (``cold``);
- ``pairs``: the same refiner without the direct alignment (``--no-refine-align``);
- ``map``: building the map once (one forward pass per training frame, batch 16);
- with a run that has anchors (``--anchor vo``), also the map taken from them
  (:func:`relocdepth.refine.map_anchors`, what ``--refine-map auto`` does: no forward pass) and
  ``refined (anchors)``: the refined path against that map.

    python benchmarks/bench_refine.py SHARDS --checkpoint RUN [--frames 40] [--reps 2] [--threads 1]
"""

from __future__ import annotations

import argparse
import os
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("shards", help="the run's shards (training frames: the map; test frames: queries)")
    ap.add_argument("--checkpoint", required=True, help="run folder or checkpoint file")
    ap.add_argument("--frames", type=int, default=40, help="test frames timed")
    ap.add_argument("--reps", type=int, default=2, help="interleaved passes (best of)")
    ap.add_argument("--threads", type=int, default=1, help="torch intra-op threads (0: torch's default)")
    a = ap.parse_args()

    import torch

    if a.threads > 0:
        torch.set_num_threads(a.threads)
    from relocdepth.dataset import open_dataset
    from relocdepth.localize import Frame, localize_frames
    from relocdepth.predictor import Predictor
    from dataclasses import replace

    from relocdepth.refine import Refiner, map_anchors, predict_poses

    print(f"load average at start: {os.getloadavg()[0]:.2f}; torch threads {torch.get_num_threads()}")
    ds = open_dataset(a.shards)
    train = [r for r in ds.records if r.split == "train"]
    test = [r for r in ds.records if r.split == "test"][: a.frames]
    predictor = Predictor.from_checkpoint(a.checkpoint)
    t0 = time.perf_counter()
    read, intrinsics = (lambda i: ds.read_image(train[i])), [r.intrinsics for r in train]
    refiner = Refiner.from_images(predictor, read, intrinsics, predict_poses(predictor, read, intrinsics))
    map_s = time.perf_counter() - t0
    pairs = Refiner(predictor, refiner.ref, replace(refiner.cfg, align=False))  # same map and cache
    t0 = time.perf_counter()
    anchors = map_anchors("auto", predictor.meta, ds, [r.key for r in train])
    anchors_s = time.perf_counter() - t0
    by_anchors = None if anchors is None else Refiner.from_images(predictor, read, intrinsics, anchors)
    frames = [Frame(r.key, str(ds.root), float(i), ds.read_image(r)) for i, r in enumerate(test)]

    def timed(ref: Refiner | None) -> float:
        t = time.perf_counter()
        localize_frames(predictor, iter(frames), 1, refiner=ref)
        return (time.perf_counter() - t) / len(frames)

    cold = timed(refiner)
    if by_anchors is not None:
        timed(by_anchors)  # its neighbours' depth cached, as the others' after the cold pass
    best = {"network": float("inf"), "refined": float("inf"), "pairs": float("inf"), "anchors": float("inf")}
    for _ in range(a.reps):
        best["network"] = min(best["network"], timed(None))
        best["refined"] = min(best["refined"], timed(refiner))
        best["pairs"] = min(best["pairs"], timed(pairs))
        if by_anchors is not None:
            best["anchors"] = min(best["anchors"], timed(by_anchors))
    n, r, p = best["network"] * 1e3, best["refined"] * 1e3, best["pairs"] * 1e3
    print(f"map of {len(train)} training frames: {map_s:.1f} s ({map_s / len(train) * 1e3:.0f} ms a frame)")
    print(f"{len(frames)} queries at {predictor.input_size[0]}x{predictor.input_size[1]}, batch 1: network "
          f"{n:.0f} ms/image, refined {r:.0f} ms/image ({r / n:.2f}x; pairs alone {p:.0f} ms/image, "
          f"{p / n:.2f}x), refined cold (neighbours' depth not cached yet) {cold * 1e3:.0f} ms/image")
    if by_anchors is None:
        print("the run has no anchors of these frames: no map from them")
    else:
        print(f"map from the run's anchors: {anchors_s * 1e3:.1f} ms; refined against it "
              f"{best['anchors'] * 1e3:.0f} ms/image ({best['anchors'] / best['network']:.2f}x)")
    print(f"load average at end: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
