"""An image folder: one sequence, frames in natural sort order, optional ``times.txt``.

``times.txt`` (optional, beside the images) gives timestamps in seconds, one non-empty line per
image: either ``<timestamp>`` (in the images' sort order) or ``<file name> <timestamp>``.
Lines starting with ``#`` are comments. Without it, frame ``i`` is at ``i / fps``.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from relocdepth.ingest.imagecheck import BrokenImage, ext_of, image_size
from relocdepth.ingest.intrinsics import load_calibration
from relocdepth.ingest.source import (
    Frame,
    SequencePlan,
    SourcePlan,
    calibrate,
    natural_key,
    sanitize_name,
)

from relocdepth.errors import UserError

TIMES_FILE = "times.txt"


def list_images(folder: Path) -> list[Path]:
    """PNG/JPEG files directly in ``folder``, in natural sort order."""
    try:
        files = [p for p in folder.iterdir() if p.is_file() and ext_of(p.name)]
    except OSError as e:
        raise UserError(f"source not readable: {folder} ({e.strerror})") from None
    return sorted(files, key=lambda p: natural_key(p.name))


def read_times(path: Path, images: list[Path]) -> list[float]:
    """Timestamps for ``images`` from a times.txt (format in the module docstring)."""
    by_name: dict[str, float] = {}
    ordered: list[float] = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        try:
            if len(parts) == 1:
                ordered.append(float(parts[0]))
            elif len(parts) == 2:
                by_name[parts[0]] = float(parts[1])
            else:
                raise ValueError
        except ValueError:
            raise UserError(
                f"{path}:{n}: expected '<timestamp>' or '<file name> <timestamp>', got '{line}'"
            ) from None
    if by_name and ordered:
        raise UserError(f"{path}: mixes lines with and without file names")
    if by_name:
        missing = [p.name for p in images if p.name not in by_name]
        if missing:
            raise UserError(f"{path}: no timestamp for {missing[0]} ({len(missing)} images missing)")
        return [by_name[p.name] for p in images]
    if len(ordered) != len(images):
        raise UserError(f"{path}: {len(ordered)} timestamps for {len(images)} images")
    return ordered


def plan_images(
    folder: Path, *, k_file: str | None, stride: int, fps: float, split: str | None,
) -> SourcePlan:
    """Check an image folder (intrinsics required, first frame fits them) and list its frames."""
    images = list_images(folder)
    if not images:
        raise UserError(f"empty folder: {folder} holds no .png/.jpg images")
    if k_file is None:
        raise UserError(f"{folder} is an image folder: give the camera intrinsics with --K FILE")
    calib = load_calibration(k_file)
    times_path = folder / TIMES_FILE
    times = read_times(times_path, images) if times_path.is_file() else [i / fps for i in range(len(images))]
    frames = [
        Frame(index=i, timestamp=times[i], source=str(images[i]), image_path=images[i])
        for i in range(0, len(images), stride)
    ]
    first = frames[0].image_path
    try:
        w, h = image_size(first.read_bytes(), ext_of(first.name) or "png")
    except (OSError, BrokenImage) as e:
        raise UserError(f"{first}: the first image is unreadable ({e})") from None
    seq_calib = calibrate(calib, w, h, str(folder))

    def gen() -> Iterator[Frame]:
        return iter(frames)

    name = sanitize_name(folder.resolve().name)
    return SourcePlan(folder, "images", [SequencePlan(name, split or "train", seq_calib, (w, h), len(frames), gen)])
