"""Writing the generated scene in the exact Microsoft 7-Scenes layout (plus mp4 videos and
``synth.json``), into a temporary folder renamed at the end."""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

import numpy as np

from relocdepth.camera import Intrinsics
from relocdepth.errors import UserError
from relocdepth.synth.config import SEVEN_SCENES_INTRINSICS, SynthConfig, check_config
from relocdepth.synth.paths import camera_paths, format_pose_value, motion_steps
from relocdepth.synth.render import render
from relocdepth.synth.scene import Scene, build_scene

log = logging.getLogger(__name__)


def _check_output(out: Path, force: bool) -> None:
    if out.exists() and not force:
        if not out.is_dir():
            raise UserError(f"{out} exists and is not a folder; pass --force to replace it")
        if any(out.iterdir()):
            raise UserError(f"{out} exists and is not empty; pass --force to replace it")


def write_pose(path: Path, T_wc: np.ndarray) -> None:
    """A 7-Scenes pose file: 4 lines of 4 tab-separated floats (world-from-camera)."""
    path.write_text("".join("\t".join(format_pose_value(v) for v in row) + "\t\n" for row in T_wc))


def _write_sequence(seq_dir: Path, video: Path, scene: Scene, poses: np.ndarray,
                    intr: Intrinsics, cfg: SynthConfig, tick: Callable[[], None]) -> None:
    import cv2

    seq_dir.mkdir()
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), cfg.fps,
                             (intr.width, intr.height))
    if not writer.isOpened():
        raise RuntimeError(f"OpenCV cannot write an mp4v video to {video}")
    try:
        for i, T in enumerate(poses):
            rgb, depth = render(scene, T, intr, cfg.texture_blur_px)
            bgr = np.ascontiguousarray(rgb[:, :, ::-1])
            stem = seq_dir / f"frame-{i:06d}"
            mm = np.clip(np.rint(depth * 1000.0), 0, 65535).astype(np.uint16)
            if not (cv2.imwrite(f"{stem}.color.png", bgr) and cv2.imwrite(f"{stem}.depth.png", mm)):
                raise RuntimeError(f"could not write {stem}.*.png")
            write_pose(Path(f"{stem}.pose.txt"), T)
            writer.write(bgr)
            tick()
    finally:
        writer.release()


def generate_scene(out_dir: str | Path, cfg: SynthConfig | None = None, *, force: bool = False,
                   progress: Callable[[int], None] | None = None) -> dict:
    """Write the scene to ``out_dir`` in the 7-Scenes layout and return a summary dict.

    Writes ``seq-XX/frame-XXXXXX.{color.png,depth.png,pose.txt}``, ``TrainSplit.txt``,
    ``TestSplit.txt``, ``intrinsics.yaml``, ``videos/seq-XX.mp4`` and ``synth.json`` (config and
    motion statistics), into a temporary folder beside ``out_dir`` renamed at the end; ``cfg``
    defaults to ``SynthConfig()``. ``progress(n)`` is called with the number of frames written so
    far (of frames x sequences).
    """
    import yaml

    cfg = cfg or SynthConfig()
    check_config(cfg)
    out = Path(out_dir)
    _check_output(out, force)
    start = time.perf_counter()
    intr = SEVEN_SCENES_INTRINSICS.scaled(cfg.width, cfg.height)
    scene = build_scene(cfg.seed, cfg)
    paths = camera_paths(cfg)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    done = 0

    def tick() -> None:
        nonlocal done
        done += 1
        if progress is not None:
            progress(done)

    sequences = []
    try:
        (tmp / "videos").mkdir()
        for i, (name, poses) in enumerate(paths.items()):
            _write_sequence(tmp / name, tmp / "videos" / f"{name}.mp4", scene, poses, intr, cfg, tick)
            trans, rot = motion_steps(poses)
            split = "train" if i < cfg.train_sequences else "test"
            sequences.append({
                "name": name, "split": split, "frames": len(poses),
                "median_step_cm": float(np.median(trans) * 100) if len(trans) else 0.0,
                "median_step_deg": float(np.median(rot)) if len(rot) else 0.0,
            })
        train = "".join(f"sequence{i + 1}\n" for i in range(cfg.train_sequences))
        (tmp / "TrainSplit.txt").write_text(train)
        (tmp / "TestSplit.txt").write_text(f"sequence{cfg.train_sequences + 1}\n")
        (tmp / "intrinsics.yaml").write_text(
            "# pinhole intrinsics of the colour images (pixels; 7-Scenes RGB camera, scaled)\n"
            + yaml.safe_dump(intr.to_dict(), sort_keys=False))
        summary = {"out": str(out), "config": asdict(cfg), "intrinsics": intr.to_dict(),
                   "sequences": sequences}
        (tmp / "synth.json").write_text(json.dumps(summary, indent=2) + "\n")
        _replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    summary["seconds"] = time.perf_counter() - start
    log.info("wrote %d frames to %s in %.1f s", done, out, summary["seconds"])
    return summary


def _replace(tmp: Path, out: Path) -> None:
    """Move the finished ``tmp`` to ``out``, replacing what is there (checked beforehand)."""
    if out.is_dir() and not any(out.iterdir()):
        out.rmdir()
    if out.exists() or out.is_symlink():
        old = out.parent / f".{out.name}.old-{os.getpid()}"
        os.replace(out, old)
        os.replace(tmp, out)
        if old.is_dir() and not old.is_symlink():
            shutil.rmtree(old)
        else:
            old.unlink()
    else:
        os.replace(tmp, out)
