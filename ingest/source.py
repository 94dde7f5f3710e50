"""What every source kind (7-Scenes, video, image folder) hands to the ingest loop."""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from relocdepth.ingest.intrinsics import Calibration

from relocdepth.errors import UserError

# Keys are "<sequence>-<frame:06d>" inside tar member names, so names stay short and plain.
MAX_SEQUENCE_NAME = 64


@dataclass(frozen=True)
class Frame:
    """One source frame: a file to copy (``image_path``) or decoded pixels (video, BGR uint8)."""

    index: int  # position in the source sequence (before --stride, so gaps are possible)
    timestamp: float  # seconds
    source: str  # where it came from, for the frame json and skip reports
    image_path: Path | None = None
    pixels: np.ndarray | None = None
    depth_path: Path | None = None
    pose_path: Path | None = None


@dataclass(frozen=True)
class SequencePlan:
    """A sequence, checked before anything is written: its calibration fits its first frame."""

    name: str
    split: str
    calibration: Calibration  # at the size of the first frame
    frame_size: tuple[int, int]  # (width, height) of the first frame
    count: int  # frames expected after --stride (an estimate for videos)
    frames: Callable[[], Iterator[Frame]] = field(repr=False)


@dataclass(frozen=True)
class SourcePlan:
    path: Path
    kind: str  # "sevenscenes" | "video" | "images"
    sequences: list[SequencePlan]


def sanitize_name(name: str) -> str:
    """A sequence/dataset name for keys: only [A-Za-z0-9_-] (no dots), at most 64 characters."""
    clean = re.sub(r"[^A-Za-z0-9_-]+", "_", name).strip("_")[:MAX_SEQUENCE_NAME]
    return clean or "seq"


def natural_key(name: str) -> list:
    """Sort key putting "img2" before "img10"."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def check_readable(path: Path) -> None:
    """A UserError unless ``path`` is a regular file or a folder this process may read.

    Opening a FIFO would block and a device is no source, so anything else is refused up front.
    """
    import os

    if not path.exists():
        raise UserError(f"source not found: {path}")
    if not (path.is_file() or path.is_dir()):
        raise UserError(f"source not readable: {path} is neither a file nor a folder (a pipe or device?)")
    if not os.access(path, os.R_OK) or (path.is_dir() and not os.access(path, os.X_OK)):
        raise UserError(f"source not readable: {path} (check its permissions)")


def calibrate(calib: Calibration, width: int, height: int, what: str) -> Calibration:
    """``calib`` at the frame size, or a UserError saying which source does not fit."""
    try:
        return calib.for_frame_size(width, height)
    except UserError as e:
        raise UserError(f"{what}: {e}") from None
