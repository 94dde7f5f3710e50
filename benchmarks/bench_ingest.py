"""Ingest speed, as ratios measured in one run.

1. A 7-Scenes-layout scene (>= 1000 frames, 640x480: colour PNG + uint16 depth PNG + pose) ingested
   without resize, vs ``tar cf`` of the same files. Goal: ingest <= 1.5x tar's time.
2. Pair parallax (``--pair-parallax``): the same scene ingested with and without it. The
   option is on by default only if it costs <= 1.5x.
3. Video ingest frames/s vs plain OpenCV decoding of the same file. Goal: >= 0.8x.

The scene is random-texture frames (tracking random texture costs what tracking a room costs: same
corners, same pyramid) (rendering 1000 frames at 640x480 with ``relocdepth.synth``
takes far longer than the benchmark); it is cached in ``--cache`` (default /tmp/relocdepth-bench).
Files are read once before timing so that both sides start from a warm page cache; each side runs
``--repeats`` times alternately and the best time counts.

    python benchmarks/bench_ingest.py [--frames 1002] [--video-frames 300] [--repeats 2]
"""

from __future__ import annotations

import argparse
import logging
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
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


def time_ingest(sources: list[Path], work: Path, cfg: IngestConfig) -> tuple[float, int]:
    out = work / "shards"
    t = time.perf_counter()
    m = ingest(sources, out, cfg, progress=False)
    dt = time.perf_counter() - t
    shutil.rmtree(out)
    return dt, m["totals"]["frames"]


def time_decode(video: Path) -> tuple[float, int]:
    t = time.perf_counter()
    cap = cv2.VideoCapture(str(video))
    n = 0
    while True:
        ok, _ = cap.read()
        if not ok:
            break
        n += 1
    cap.release()
    return time.perf_counter() - t, n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1002)
    ap.add_argument("--video-frames", type=int, default=300)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "relocdepth-bench")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    args.cache.mkdir(parents=True, exist_ok=True)
    scene = make_scene(args.cache, args.frames)
    video = make_video(args.cache, scene, args.video_frames)
    kfile = args.cache / "K.yaml"
    write_intrinsics_yaml(kfile, Intrinsics(525.0, 525.0, 319.5, 239.5, *SIZE))
    work = Path(tempfile.mkdtemp(dir=args.cache))
    try:
        nbytes = warm(scene)
        tars, ings, pars = [], [], []
        for _ in range(args.repeats):
            tars.append(time_tar(scene, work))
            dt, n = time_ingest([scene], work, IngestConfig(pair_parallax=False))
            ings.append(dt)
            pars.append(time_ingest([scene], work, IngestConfig(pair_parallax=True))[0])
        t_tar, t_ing, t_par = min(tars), min(ings), min(pars)
        print(f"7-Scenes scene: {n} frames, {nbytes / 1e6:.0f} MB")
        print(f"  tar cf: {t_tar:.2f} s   ingest: {t_ing:.2f} s   ratio ingest/tar = {t_ing / t_tar:.2f} (goal <= 1.5)")
        print(f"  ingest --pair-parallax: {t_par:.2f} s   ratio with/without = {t_par / t_ing:.2f} "
              f"(default on if <= 1.5); vs tar {t_par / t_tar:.2f}")
        warm(video.parent)
        decs, vids = [], {"jpg": [], "png": []}
        for _ in range(args.repeats):
            dt, nv = time_decode(video)
            decs.append(dt)
            for fmt, times in vids.items():
                dt, _ = time_ingest([video], work, IngestConfig(intrinsics=str(kfile), video_format=fmt,
                                                                pair_parallax=False))
                times.append(dt)
        fps_dec = nv / min(decs)
        print(f"video: {nv} frames {SIZE[0]}x{SIZE[1]} mp4v; OpenCV decode {fps_dec:.1f} frames/s")
        for fmt, ts in vids.items():
            fps = nv / min(ts)
            print(f"  ingest ({fmt}): {fps:.1f} frames/s   ratio ingest/decode = {fps / fps_dec:.2f} (goal >= 0.8)")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    sys.stdout.flush()


if __name__ == "__main__":
    main()
