"""Ingest speed, as ratios measured in one run.

1. A 7-Scenes-layout scene (>= 1000 frames, 640x480: colour PNG + uint16 depth PNG + pose) ingested
   without resize, vs ``tar cf`` of the same files. Goal: ingest <= 1.5x tar's time.
2. Pair parallax (``--pair-parallax``): the same scene ingested with and without it. The
   option is on by default only if it costs <= 1.5x.
3. Video ingest frames/s vs plain OpenCV decoding of the same file. Goal: >= 0.8x. Printed beside
   it: the same decode + JPEG encode + sha256 done one after the other in one thread (what ingest
   would cost without overlapping them), ingest with its decode thread switched off, and the CPU
   time per frame of each (all threads of the process): with N free cores, ingest can reach at
   most N x (decode CPU) / (ingest CPU) of the decode rate (printed as the bound for N = 2).
   Each repeat measures every variant once, one after the other; the ratio of a repeat is taken
   between runs seconds apart, and the median and range over repeats are printed (on a shared
   machine the load changes between repeats far more than within one).
4. ``--profile``: where a video ingest's CPU goes, per thread role (CPU seconds of each thread,
   ``time.thread_time``): the decode thread (OpenCV's frame conversion and copy), FFmpeg's own
   decoder threads (the process's CPU not spent in any Python thread), the pool (of which the JPEG
   encode), the writing thread (of which tar writes) and the hashing thread.

The scene is random-texture frames (tracking random texture costs what tracking a room costs: same
corners, same pyramid) (rendering 1000 frames at 640x480 with ``relocdepth.synth``
takes far longer than the benchmark); it is cached in ``--cache`` (default /tmp/relocdepth-bench).
Files are read once before timing so that both sides start from a warm page cache; each side runs
``--repeats`` times alternately and the best time counts (the 7-Scenes measures).

    python benchmarks/bench_ingest.py [--frames 1002] [--video-frames 300] [--repeats 2] [--video-only]
                                      [--no-png] [--profile]
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import logging
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from relocdepth.ingest import run as ingest_run
from relocdepth.ingest.intrinsics import write_intrinsics_yaml
from relocdepth.ingest.run import IngestConfig, ingest

from relocdepth.camera import Intrinsics

SIZE = (640, 480)
SEQUENCES = 3


def _frame(rng: np.random.Generator, w: int, h: int) -> np.ndarray:
    """Blocky random colour plus fine noise: compresses like a real indoor frame (~0.5 MB PNG)."""
    small = rng.integers(0, 256, size=(h // 8, w // 8, 3), dtype=np.uint8)
    img = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC).astype(np.int16)
    img += rng.integers(-6, 7, size=img.shape, dtype=np.int16)
    return np.clip(img, 0, 255).astype(np.uint8)


def make_scene(root: Path, frames: int) -> Path:
    scene = root / f"scene-{SIZE[0]}x{SIZE[1]}-{frames}"
    if (scene / "TestSplit.txt").is_file():
        return scene
    tmp = root / (scene.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    rng = np.random.default_rng(0)
    w, h = SIZE
    per = -(-frames // SEQUENCES)
    for s in range(SEQUENCES):
        d = tmp / f"seq-{s + 1:02d}"
        d.mkdir(parents=True)
        for i in range(per):
            cv2.imwrite(str(d / f"frame-{i:06d}.color.png"), _frame(rng, w, h))
            depth = (1500 + 500 * np.sin(np.linspace(0, 6, w))[None, :] + np.zeros((h, 1))).astype(np.uint16)
            cv2.imwrite(str(d / f"frame-{i:06d}.depth.png"), depth)
            T = np.eye(4)
            T[:3, 3] = [0.0075 * i, 0.0, 0.1 * s]
            np.savetxt(d / f"frame-{i:06d}.pose.txt", T, fmt="%.6e")
    (tmp / "TrainSplit.txt").write_text("sequence1\nsequence2\n")
    (tmp / "TestSplit.txt").write_text("sequence3\n")
    tmp.rename(scene)
    return scene


def make_video(root: Path, scene: Path, frames: int) -> Path:
    path = root / f"video-{frames}.mp4"
    if path.is_file():
        return path
    colour = sorted(scene.glob("seq-*/frame-*.color.png"))[:frames]
    tmp = root / "video.tmp.mp4"
    vw = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, SIZE)
    for p in colour:
        vw.write(cv2.imread(str(p)))
    vw.release()
    tmp.rename(path)
    return path


def warm(scene: Path) -> int:
    return sum(len(p.read_bytes()) for p in scene.rglob("*") if p.is_file())


def time_tar(scene: Path, work: Path) -> float:
    out = work / "scene.tar"
    t = time.perf_counter()
    subprocess.run(["tar", "cf", str(out), "-C", str(scene.parent), scene.name], check=True)
    dt = time.perf_counter() - t
    out.unlink()
    return dt


@dataclass
class Timed:
    """Wall and CPU seconds (all threads of this process) of a ``with timed()`` block."""

    wall: float = 0.0
    cpu: float = 0.0


@contextlib.contextmanager
def timed() -> Iterator[Timed]:
    t, t0, c0 = Timed(), time.perf_counter(), time.process_time()
    yield t
    t.wall, t.cpu = time.perf_counter() - t0, time.process_time() - c0


def time_ingest(sources: list[Path], work: Path, cfg: IngestConfig) -> tuple[Timed, int]:
    out = work / "shards"
    with timed() as t:
        m = ingest(sources, out, cfg, progress=False)
    shutil.rmtree(out)
    return t, m["totals"]["frames"]


@contextlib.contextmanager
def decode_on_main_thread() -> Iterator[None]:
    """Ingest without its decode thread (frames read where they are written), for comparison."""
    saved = ingest_run.background
    ingest_run.background = lambda items, depth: items
    try:
        yield
    finally:
        ingest_run.background = saved


def time_decode(video: Path, encode: bool = False) -> tuple[Timed, int]:
    """Plain OpenCV decoding; with ``encode``, each frame also JPEG-encoded as ingest does it and
    hashed, in the same thread (the serial reference)."""
    params = [cv2.IMWRITE_JPEG_QUALITY, 95, cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444]
    sha = hashlib.sha256()
    with timed() as t:
        cap = cv2.VideoCapture(str(video))
        n = 0
        while True:
            ok, img = cap.read()
            if not ok:
                break
            if encode:
                sha.update(cv2.imencode(".jpg", img, params)[1].tobytes())
            n += 1
        cap.release()
    return t, n


VIDEO_VARIANTS = {
    "serial": "decode+encode+hash in series",
    "jpg": "ingest (jpg)",
    "main": "ingest (jpg), decoding on the main thread",
    "png": "ingest (png)",
}


def measure_video(video: Path, kfile: Path, work: Path, repeats: int, png: bool) -> None:
    """Decode vs ingest variants, each once per repeat; per-repeat ratios, median and range."""
    vcfg = IngestConfig(intrinsics=str(kfile))
    keys = ["decode", *(k for k in VIDEO_VARIANTS if png or k != "png")]
    runs: dict[str, list[Timed]] = {k: [] for k in keys}
    time_ingest([video], work, vcfg)  # untimed: imports and first-use costs (pyarrow, codecs)
    for _ in range(repeats):
        t, nv = time_decode(video)
        runs["decode"].append(t)
        runs["serial"].append(time_decode(video, encode=True)[0])
        runs["jpg"].append(time_ingest([video], work, vcfg)[0])
        with decode_on_main_thread():
            runs["main"].append(time_ingest([video], work, vcfg)[0])
        if png:
            runs["png"].append(time_ingest([video], work, replace(vcfg, video_format="png"))[0])

    def spread(values: list[float], fmt: str = ".2f") -> str:
        return (f"{statistics.median(values):{fmt}} (range {min(values):{fmt}}-{max(values):{fmt}}, "
                f"{len(values)} runs)")

    dec = runs["decode"]
    cpu_dec = [t.cpu / nv * 1e3 for t in dec]
    print(f"video: {nv} frames {SIZE[0]}x{SIZE[1]} mp4v; OpenCV decode frames/s "
          f"{spread([nv / t.wall for t in dec], '.1f')}; CPU ms/frame {spread(cpu_dec)}; "
          f"load average {os.getloadavg()[0]:.1f} at the end")
    for key in keys[1:]:
        ratios = [d.wall / t.wall for d, t in zip(dec, runs[key])]
        cpu = [t.cpu / nv * 1e3 for t in runs[key]]
        print(f"  {VIDEO_VARIANTS[key]}: ratio to decode {spread(ratios)}"
              f"{' (goal >= 0.8)' if key == 'jpg' else ''}; frames/s "
              f"{spread([nv / t.wall for t in runs[key]], '.1f')}; CPU ms/frame {spread(cpu)}")
    bound = [2 * d.cpu / t.cpu for d, t in zip(dec, runs["jpg"])]
    print(f"  bound on 2 free cores, 2 x decode CPU / ingest CPU: {spread(bound)}")


@contextlib.contextmanager
def thread_cpu_probes(cpu: dict[str, float]) -> Iterator[None]:
    """Add each ingest thread role's CPU seconds to ``cpu`` while the block runs."""
    from relocdepth.ingest import prefetch, process, writer

    lock = threading.Lock()

    def add(key: str, t0: float) -> None:
        with lock:
            cpu[key] = cpu.get(key, 0.0) + time.thread_time() - t0

    def timed_method(cls: type, name: str, key: str) -> tuple[Callable, Callable]:
        orig = getattr(cls, name)

        def wrapper(*args: Any, **kwargs: Any) -> Any:
            t0 = time.thread_time()
            try:
                return orig(*args, **kwargs)
            finally:
                add(key, t0)

        return orig, wrapper

    def background(items: Iterator, depth: int) -> Iterator:
        def produce() -> Iterator:
            t0 = time.thread_time()
            try:
                yield from items
            finally:
                add("decode thread", t0)

        return prefetch.background(produce(), depth)

    patches = [(process.SequenceProcessor, "prepare", "pool"),
               (process.SequenceProcessor, "_encode", "pool: JPEG encode"),
               (writer._Hasher, "run", "hashing thread"),
               (writer.ShardWriter, "add", "writing thread: tar writes")]
    saved = [(cls, name, *timed_method(cls, name, key)) for cls, name, key in patches]
    saved_bg = ingest_run.background
    try:
        for cls, name, _, wrapper in saved:
            setattr(cls, name, wrapper)
        ingest_run.background = background
        t0 = time.thread_time()
        yield
        add("writing thread", t0)
    finally:
        for cls, name, orig, _ in saved:
            setattr(cls, name, orig)
        ingest_run.background = saved_bg


def profile_video(video: Path, kfile: Path, work: Path, repeats: int) -> None:
    """CPU ms per frame of each thread role of a video ingest (JPEG), median and range."""
    per_role: dict[str, list[float]] = {}
    for _ in range(repeats):
        cpu: dict[str, float] = {}
        with thread_cpu_probes(cpu), timed() as t:
            n = time_ingest([video], work, IngestConfig(intrinsics=str(kfile)))[1]
        python = sum(v for k, v in cpu.items() if ":" not in k)
        cpu["FFmpeg decoder threads (process - Python threads)"] = t.cpu - python
        cpu["process"] = t.cpu
        for k, v in cpu.items():
            per_role.setdefault(k, []).append(v / n * 1e3)
    print(f"video ingest CPU ms/frame by thread, median (range) of {repeats} runs, "
          f"load average {os.getloadavg()[0]:.1f}:")
    for k, v in sorted(per_role.items()):
        print(f"  {k}: {statistics.median(v):.2f} ({min(v):.2f}-{max(v):.2f})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1002)
    ap.add_argument("--video-frames", type=int, default=300)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "relocdepth-bench")
    ap.add_argument("--video-only", action="store_true", help="skip the 7-Scenes vs tar measure")
    ap.add_argument("--no-png", action="store_true", help="skip the --video-format png measure (slow)")
    ap.add_argument("--profile", action="store_true", help="also: video ingest CPU per thread role")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    args.cache.mkdir(parents=True, exist_ok=True)
    scene = make_scene(args.cache, args.frames)
    video = make_video(args.cache, scene, args.video_frames)
    kfile = args.cache / "K.yaml"
    write_intrinsics_yaml(kfile, Intrinsics(525.0, 525.0, 319.5, 239.5, *SIZE))
    work = Path(tempfile.mkdtemp(dir=args.cache))
    print(f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f} at start")
    try:
        if not args.video_only:
            nbytes = warm(scene)
            tars, ings, pars = [], [], []
            for _ in range(args.repeats):
                tars.append(time_tar(scene, work))
                t, n = time_ingest([scene], work, IngestConfig(pair_parallax=False))
                ings.append(t.wall)
                pars.append(time_ingest([scene], work, IngestConfig(pair_parallax=True))[0].wall)
            t_tar, t_ing, t_par = min(tars), min(ings), min(pars)
            print(f"7-Scenes scene: {n} frames, {nbytes / 1e6:.0f} MB")
            print(f"  tar cf: {t_tar:.2f} s   ingest: {t_ing:.2f} s   ratio ingest/tar = {t_ing / t_tar:.2f} (goal <= 1.5)")
            print(f"  ingest --pair-parallax: {t_par:.2f} s   ratio with/without = {t_par / t_ing:.2f} "
                  f"(default on if <= 1.5); vs tar {t_par / t_tar:.2f}")
        warm(video.parent)
        measure_video(video, kfile, work, args.repeats, png=not args.no_png)
        if args.profile:
            profile_video(video, kfile, work, args.repeats)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    sys.stdout.flush()


if __name__ == "__main__":
    main()
