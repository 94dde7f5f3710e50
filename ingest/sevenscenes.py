"""Microsoft 7-Scenes layout: ``seq-XX/frame-XXXXXX.{color.png,depth.png,pose.txt}`` + split files.

A scene folder holds ``seq-XX`` folders and ``TrainSplit.txt`` / ``TestSplit.txt`` (lines like
``sequence1``). A root holding several scene folders needs ``--scene NAME``.
Intrinsics, first match wins: ``--K``; an ``intrinsics.yaml`` in the scene folder (what
``reloc synth`` writes); the RGB camera values DSAC* and ACE use for 7-Scenes.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterator
from pathlib import Path

from relocdepth.ingest.imagecheck import BrokenImage, png_size
from relocdepth.ingest.intrinsics import Calibration, load_calibration
from relocdepth.ingest.source import Frame, SequencePlan, SourcePlan, calibrate

from relocdepth.camera import Intrinsics
from relocdepth.errors import UserError

log = logging.getLogger(__name__)

SPLIT_FILES = {"train": "TrainSplit.txt", "test": "TestSplit.txt"}
SCENE_INTRINSICS = "intrinsics.yaml"
FRAME_RE = re.compile(r"^frame-(\d+)\.color\.png$")
SEQ_RE = re.compile(r"^seq-(\d+)$")


def _sequence_dirs(path: Path) -> list[Path]:
    try:
        return sorted(p for p in path.iterdir() if p.is_dir() and SEQ_RE.match(p.name))
    except OSError:
        return []


def is_scene(path: Path) -> bool:
    """A 7-Scenes scene: ``seq-XX`` folders, or split files naming them."""
    return bool(_sequence_dirs(path)) or any((path / f).is_file() for f in SPLIT_FILES.values())


def find_scenes(root: Path) -> list[Path]:
    """Scene folders directly under ``root`` (a 7-Scenes download root)."""
    try:
        return sorted(p for p in root.iterdir() if p.is_dir() and _sequence_dirs(p))
    except OSError:
        return []


def resolve_scene(path: Path, scene: str | None) -> Path:
    """The scene folder to ingest: ``path`` itself, or ``path/scene`` for a root of several."""
    if _sequence_dirs(path):
        return path
    scenes = find_scenes(path)
    if scene is not None:
        if not (path / scene).is_dir() or not _sequence_dirs(path / scene):
            names = ", ".join(p.name for p in scenes) or "none"
            raise UserError(f"{path}: no 7-Scenes scene named '{scene}' (scenes here: {names})")
        return path / scene
    if len(scenes) == 1:
        return scenes[0]
    raise UserError(
        f"{path} holds several 7-Scenes scenes ({', '.join(p.name for p in scenes)}); "
        "pick one with --scene NAME"
    )


def _parse_split(path: Path) -> list[str]:
    names = []
    for line in path.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        m = re.fullmatch(r"(?:sequence|seq-?)(\d+)", line, flags=re.IGNORECASE)
        if not m:
            raise UserError(f"{path}: cannot read split line '{line}' (expected e.g. 'sequence1')")
        names.append(f"seq-{int(m.group(1)):02d}")
    return names


def read_splits(scene: Path) -> dict[str, str]:
    """Sequence name -> split, from TrainSplit.txt / TestSplit.txt (empty if neither exists)."""
    out: dict[str, str] = {}
    for split, fname in SPLIT_FILES.items():
        f = scene / fname
        if f.is_file():
            for name in _parse_split(f):
                out[name] = split
    return out


def scene_calibration(scene: Path, k_file: str | None, default: tuple) -> Calibration:
    if k_file is not None:
        return load_calibration(k_file)
    if (scene / SCENE_INTRINSICS).is_file():
        log.info("using the scene's intrinsics file %s", scene / SCENE_INTRINSICS)
        return load_calibration(scene / SCENE_INTRINSICS)
    fx, fy, cx, cy, w, h = default
    log.info("using the 7-Scenes RGB intrinsics fx=%g fy=%g cx=%g cy=%g at %dx%d", fx, fy, cx, cy, w, h)
    return Calibration(Intrinsics(float(fx), float(fy), float(cx), float(cy), int(w), int(h)))


def _frame_list(seq_dir: Path, stride: int, fps: float) -> list[Frame]:
    found = []
    for p in seq_dir.iterdir():
        m = FRAME_RE.match(p.name)
        if m:
            found.append((int(m.group(1)), p))
    found.sort()
    frames = []
    for index, color in found[::stride]:
        stem = color.name[: -len(".color.png")]
        depth, pose = seq_dir / f"{stem}.depth.png", seq_dir / f"{stem}.pose.txt"
        frames.append(Frame(
            index=index, timestamp=index / fps, source=str(color), image_path=color,
            depth_path=depth if depth.is_file() else None, pose_path=pose if pose.is_file() else None,
        ))
    return frames


def _first_size(path: Path) -> tuple[int, int]:
    try:
        return png_size(path.read_bytes())
    except (OSError, BrokenImage) as e:
        raise UserError(f"{path}: the first frame is unreadable ({e})") from None


def plan_sevenscenes(
    path: Path, *, scene: str | None, k_file: str | None, default_intrinsics: tuple,
    stride: int, fps: float, split: str | None,
) -> SourcePlan:
    """Check a 7-Scenes scene and list its sequences (nothing is read beyond file names and headers)."""
    scene_dir = resolve_scene(path, scene)
    splits = read_splits(scene_dir)
    if not splits and split is None:
        log.warning("%s has no TrainSplit.txt/TestSplit.txt: every sequence goes to 'train'", scene_dir)
    calib = scene_calibration(scene_dir, k_file, default_intrinsics)
    plans = []
    for seq_dir in _sequence_dirs(scene_dir):
        seq_split = split or splits.get(seq_dir.name, "train" if not splits else None)
        if seq_split is None:
            log.warning("%s is in neither split file: left out", seq_dir)
            continue
        frames = _frame_list(seq_dir, stride, fps)
        if not frames:
            log.warning("%s holds no frame-XXXXXX.color.png: left out", seq_dir)
            continue
        w, h = _first_size(frames[0].image_path)
        seq_calib = calibrate(calib, w, h, str(seq_dir))

        def gen(frames: list[Frame] = frames) -> Iterator[Frame]:
            return iter(frames)

        plans.append(SequencePlan(seq_dir.name, seq_split, seq_calib, (w, h), len(frames), gen))
    if not plans:
        raise UserError(f"empty 7-Scenes scene: {scene_dir} has no frames to ingest")
    return SourcePlan(path, "sevenscenes", plans)
