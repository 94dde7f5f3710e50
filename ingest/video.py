"""Video files (anything OpenCV's FFmpeg backend decodes): one sequence per video.

Timestamps come from the container (``CAP_PROP_POS_MSEC`` of each decoded frame); ``--stride N``
keeps every Nth frame (the others are grabbed but not converted); the frame index is the
frame's position in the video, so strided sequences have gaps.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path

from relocdepth.ingest.intrinsics import load_calibration
from relocdepth.ingest.source import Frame, SequencePlan, SourcePlan, calibrate, sanitize_name

from relocdepth.errors import UserError

log = logging.getLogger(__name__)

VIDEO_SUFFIXES = frozenset(
    {".mp4", ".m4v", ".mov", ".avi", ".mkv", ".webm", ".mpg", ".mpeg", ".wmv", ".flv", ".ts", ".3gp"}
)


def is_video(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES


def _open(path: Path):
    import cv2

    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        cap.release()
        raise UserError(f"video has no decodable frame: {path} (OpenCV cannot open it)")
    return cap


def iter_video(path: Path, stride: int, fps_fallback: float) -> Iterator[Frame]:
    """Decoded frames (BGR uint8) with container timestamps, every ``stride``-th frame."""
    import cv2

    cap = _open(path)
    fps = cap.get(cv2.CAP_PROP_FPS) or fps_fallback
    last_t = -1.0
    try:
        index = 0
        while cap.grab():
            if index % stride == 0:
                t = cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
                if not t > last_t and index > 0:  # a container without usable timestamps
                    t = index / fps
                ok, img = cap.retrieve()
                if ok and img is not None:
                    last_t = t
                    yield Frame(index=index, timestamp=round(t, 6), source=f"{path}#{index}", pixels=img)
                else:
                    yield Frame(index=index, timestamp=round(t, 6), source=f"{path}#{index}")
            index += 1
    finally:
        cap.release()


def plan_video(
    path: Path, *, k_file: str | None, stride: int, fps: float, split: str | None,
) -> SourcePlan:
    """Check a video (intrinsics given, first frame decodes and fits them)."""
    import cv2

    if k_file is None:
        raise UserError(f"{path} is a video: give the camera intrinsics with --K FILE")
    calib = load_calibration(k_file)
    cap = _open(path)
    try:
        ok, img = cap.read()
        count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
    finally:
        cap.release()
    if not ok or img is None:
        raise UserError(f"video has no decodable frame: {path}")
    h, w = img.shape[:2]
    seq_calib = calibrate(calib, w, h, str(path))
    expected = max(1, (count + stride - 1) // stride) if count > 0 else 1

    def gen() -> Iterator[Frame]:
        return iter_video(path, stride, fps)

    name = sanitize_name(path.stem)
    return SourcePlan(path, "video", [SequencePlan(name, split or "train", seq_calib, (w, h), expected, gen)])
