"""Turning one source frame into shard members: copy bytes, or undistort/resize and re-encode.

Images are copied byte-for-byte unless undistortion or a resize is asked (or the source is a
video, whose frames arrive decoded). Undistortion (:mod:`relocdepth.ingest.undistort`) keeps K
as the new camera matrix, so the intrinsics do not change. Depth follows with nearest-neighbour
sampling (interpolating depth across edges invents surfaces).
"""

from __future__ import annotations

import json
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from relocdepth.ingest.imagecheck import BrokenImage, ext_of, image_size, png_bit_depth, png_size
from relocdepth.ingest.intrinsics import Calibration
from relocdepth.ingest.source import Frame, SequencePlan, calibrate
from relocdepth.ingest.undistort import Undistorter
from relocdepth.ingest.writer import Sample

from relocdepth.camera import Intrinsics
from relocdepth.imageio import decode_bgr, decode_unchanged


@dataclass(frozen=True)
class Encoding:
    """How re-encoded images are written (fields of IngestConfig)."""

    resize: tuple[int, int] | None
    video_format: str
    jpeg_quality: int
    png_compression: int
    decode_check: bool


@dataclass(frozen=True)
class Prepared:
    """A frame ready to write, or the reason it was skipped."""

    sample: Sample | None
    meta: dict | None
    skipped: str | None = None


class Skip(Exception):
    """A frame that cannot be ingested; the message is the reason (recorded in the manifest)."""


class SequenceProcessor:
    """Prepares the frames of one sequence (thread-safe: called from a worker pool)."""

    def __init__(self, seq: SequencePlan, enc: Encoding) -> None:
        self.seq = seq
        self.enc = enc
        self._calibs: dict[tuple[int, int], Calibration] = {seq.frame_size: seq.calibration}
        self._undistort = Undistorter()
        self._lock = threading.Lock()

    def calibration(self, size: tuple[int, int]) -> Calibration:
        # A frame of another size gets the calibration rescaled; another aspect is a UserError.
        with self._lock:
            if size not in self._calibs:
                self._calibs[size] = calibrate(self.seq.calibration, size[0], size[1], self.seq.name)
            return self._calibs[size]

    def _transform(self, img: np.ndarray, calib: Calibration, nearest: bool) -> np.ndarray:
        import cv2

        img = self._undistort.apply(img, calib, nearest)
        if self.enc.resize is not None and (img.shape[1], img.shape[0]) != self.enc.resize:
            if nearest:
                interp = cv2.INTER_NEAREST
            elif self.enc.resize[0] < img.shape[1]:
                interp = cv2.INTER_AREA  # anti-aliased downscale
            else:
                interp = cv2.INTER_LINEAR
            img = cv2.resize(img, self.enc.resize, interpolation=interp)
        return img

    def _encode(self, img: np.ndarray, ext: str) -> bytes:
        import cv2

        if ext == "jpg":
            # 4:4:4: no chroma subsampling, colour edges matter to the photometric loss
            params = [cv2.IMWRITE_JPEG_QUALITY, self.enc.jpeg_quality,
                      cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444]
        else:
            params = [cv2.IMWRITE_PNG_COMPRESSION, self.enc.png_compression]
        ok, buf = cv2.imencode(f".{ext}", img, params)
        if not ok:
            raise Skip(f"cannot encode as {ext}")
        return buf.tobytes()

    def _out_intrinsics(self, calib: Calibration) -> Intrinsics:
        if self.enc.resize is None:
            return calib.intrinsics
        return calib.intrinsics.scaled(*self.enc.resize)

    def _image(self, frame: Frame) -> tuple[bytes, str, Calibration]:
        if frame.pixels is not None:  # a decoded video frame
            h, w = frame.pixels.shape[:2]
            calib = self.calibration((w, h))
            ext = self.enc.video_format
            return self._encode(self._transform(frame.pixels, calib, nearest=False), ext), ext, calib
        if frame.image_path is None:
            raise Skip("cannot decode the frame")
        data = _read(frame.image_path, "image")
        ext = ext_of(frame.image_path.name) or "png"
        try:
            w, h = image_size(data, ext)
        except BrokenImage as e:
            raise Skip(str(e)) from None
        calib = self.calibration((w, h))
        reencode = calib.distorted or (self.enc.resize is not None and self.enc.resize != (w, h))
        if not reencode and not self.enc.decode_check:
            return data, ext, calib
        img = decode_bgr(data)
        if img is None:
            raise Skip(f"cannot decode the {ext} image")
        if (img.shape[1], img.shape[0]) != (w, h):
            raise Skip(f"the {ext} header says {w}x{h} but it decodes to {img.shape[1]}x{img.shape[0]}")
        if not reencode:
            return data, ext, calib
        return self._encode(self._transform(img, calib, nearest=False), ext), ext, calib

    def _depth(self, path: Path, calib: Calibration) -> bytes:
        data = _read(path, "depth")
        try:
            png_size(data)
        except BrokenImage as e:
            raise Skip(f"depth {path.name}: {e}") from None
        if png_bit_depth(data) != 16:
            raise Skip(f"depth {path.name}: not a 16-bit PNG")
        if not calib.distorted and self.enc.resize is None:
            return data
        d = decode_unchanged(data)
        if d is None:
            raise Skip(f"depth {path.name}: cannot decode")
        if (d.shape[1], d.shape[0]) != (calib.intrinsics.width, calib.intrinsics.height):
            calib = Calibration(calib.intrinsics.scaled(d.shape[1], d.shape[0]), calib.distortion)
        return self._encode(self._transform(d, calib, nearest=True), "png")

    def prepare(self, frame: Frame, key: str) -> Prepared:
        """Members of one frame, or why it is skipped (a UserError still propagates)."""
        try:
            image, ext, calib = self._image(frame)
            members = {ext: image}
            depth = self._depth(frame.depth_path, calib) if frame.depth_path is not None else None
            pose = _pose(frame.pose_path) if frame.pose_path is not None else None
        except Skip as e:
            return Prepared(None, None, str(e))
        meta = {
            "key": key, "sequence": self.seq.name, "frame": int(frame.index),
            "timestamp": float(frame.timestamp), "split": self.seq.split,
            "intrinsics": self._out_intrinsics(calib).to_dict(), "source": frame.source, "image": ext,
        }
        members["json"] = json.dumps(meta, sort_keys=True).encode()
        if depth is not None:
            members["depth.png"] = depth
        if pose is not None:
            members["pose.txt"] = pose
        return Prepared(Sample(key, members), meta)


def _read(path: Path, what: str) -> bytes:
    try:
        return path.read_bytes()
    except OSError as e:
        raise Skip(f"cannot read the {what} ({e.strerror})") from None


def _pose(path: Path) -> bytes:
    data = _read(path, "pose")
    try:
        T = np.array(data.decode().split(), dtype=np.float64)
    except (UnicodeDecodeError, ValueError):
        raise Skip(f"pose {path.name}: not numbers") from None
    if T.size != 16 or not np.all(np.isfinite(T)):
        raise Skip(f"pose {path.name}: not a finite 4x4 matrix")
    return data
