"""Intrinsics files: the project's YAML and OpenCV calibration files, and scaling to the frame size.

Formats read by :func:`load_calibration`:

- the project's YAML (or JSON): ``fx, fy, cx, cy, width, height`` and optional
  ``distortion: [k1, k2, p1, p2, k3]`` (schema ``intrinsics``);
- OpenCV FileStorage files as OpenCV's calibration tools write them (``%YAML:1.0`` or XML):
  ``camera_matrix`` (3x3), ``distortion_coefficients``, ``image_width``, ``image_height``;
- the plain-YAML variant of the same fields (``camera_matrix: {rows, cols, data}``, as ROS
  ``camera_calibration`` writes).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from relocdepth.camera import Intrinsics
from relocdepth.errors import UserError

# Distortion vector lengths OpenCV accepts (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1..s4 [tx ty]]]]).
DISTORTION_LENGTHS = (4, 5, 8, 12, 14)


@dataclass(frozen=True)
class Calibration:
    """Intrinsics at the calibration size plus optional OpenCV distortion coefficients."""

    intrinsics: Intrinsics
    distortion: tuple[float, ...] | None = None

    @property
    def distorted(self) -> bool:
        return self.distortion is not None and any(c != 0.0 for c in self.distortion)

    def for_frame_size(self, width: int, height: int) -> Calibration:
        """This calibration for frames of ``width x height``: a uniform rescale, or a UserError.

        Distortion coefficients act on normalised coordinates, so they do not change.
        """
        intr = self.intrinsics
        if (intr.width, intr.height) == (width, height):
            return self
        return Calibration(intr.scaled_uniform(width, height), self.distortion)


def _distortion(values, path: Path, field: str) -> tuple[float, ...] | None:
    if values is None:
        return None
    arr = np.asarray(values, dtype=np.float64).ravel()
    if arr.size not in DISTORTION_LENGTHS or not np.all(np.isfinite(arr)):
        raise UserError(
            f"{path}: invalid field '{field}': expected {', '.join(map(str, DISTORTION_LENGTHS))} "
            f"finite numbers (k1, k2, p1, p2, k3, ...), got {arr.size}"
        )
    return tuple(float(v) for v in arr)


def _checked(path: Path, fx, fy, cx, cy, width, height) -> Intrinsics:
    values = {"fx": fx, "fy": fy, "cx": cx, "cy": cy}
    for name, v in values.items():
        if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v):
            raise UserError(f"{path}: invalid field '{name}': expected a number, got {v!r}")
    for name, v in (("fx", fx), ("fy", fy)):
        if v <= 0:
            raise UserError(f"{path}: invalid field '{name}': must be positive, got {v}")
    for name, v in (("width", width), ("height", height)):
        if not isinstance(v, int) or isinstance(v, bool) or v < 1:
            raise UserError(f"{path}: invalid field '{name}': expected a positive integer, got {v!r}")
    return Intrinsics(float(fx), float(fy), float(cx), float(cy), int(width), int(height))


def _from_filestorage(path: Path) -> Calibration:
    import cv2

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as e:
        raise UserError(f"{path}: not a readable OpenCV calibration file ({e.msg.strip()})") from None
    try:
        if not fs.isOpened():
            raise UserError(f"{path}: not a readable OpenCV calibration file")
        node = fs.getNode("camera_matrix")
        K = None if node.empty() else node.mat()
        if K is None or K.shape != (3, 3):
            raise UserError(f"{path}: invalid field 'camera_matrix': expected a 3x3 matrix")
        K = K.astype(np.float64)
        dnode = fs.getNode("distortion_coefficients")
        dist = None if dnode.empty() else dnode.mat()
        if not dnode.empty() and dist is None:
            raise UserError(f"{path}: invalid field 'distortion_coefficients': expected a matrix")
        size = {}
        for name in ("image_width", "image_height"):
            n = fs.getNode(name)
            if n.empty() or not (n.isInt() or n.isReal()) or n.real() != int(n.real()):
                raise UserError(f"{path}: invalid field '{name}': expected an integer")
            size[name] = int(n.real())
    finally:
        fs.release()
    intr = _checked(path, K[0, 0], K[1, 1], K[0, 2], K[1, 2], size["image_width"], size["image_height"])
    return Calibration(intr, _distortion(dist, path, "distortion_coefficients"))


def _matrix_field(d: dict, field: str, path: Path) -> np.ndarray:
    v = d[field]
    data = v.get("data") if isinstance(v, dict) else v
    try:
        return np.asarray(data, dtype=np.float64)
    except (TypeError, ValueError):
        raise UserError(f"{path}: invalid field '{field}': expected numbers") from None


def _from_plain_opencv_yaml(d: dict, path: Path) -> Calibration:
    K = _matrix_field(d, "camera_matrix", path)
    if K.size != 9:
        raise UserError(f"{path}: invalid field 'camera_matrix': expected a 3x3 matrix")
    K = K.reshape(3, 3)
    for name in ("image_width", "image_height"):
        if name not in d:
            raise UserError(f"{path}: missing field '{name}'")
    dist = _matrix_field(d, "distortion_coefficients", path) if "distortion_coefficients" in d else None
    intr = _checked(path, K[0, 0], K[1, 1], K[0, 2], K[1, 2], d["image_width"], d["image_height"])
    return Calibration(intr, _distortion(dist, path, "distortion_coefficients"))


def _from_project_yaml(d: dict, path: Path) -> Calibration:
    from relocdepth.schemas import validate

    validate("intrinsics", d, what=str(path))
    intr = _checked(path, d["fx"], d["fy"], d["cx"], d["cy"], d["width"], d["height"])
    return Calibration(intr, _distortion(d.get("distortion"), path, "distortion"))


def load_calibration(path: str | Path) -> Calibration:
    """Read an intrinsics file (any format above); a malformed file is a UserError naming the field."""
    import yaml

    p = Path(path)
    if not p.is_file():
        raise UserError(f"intrinsics file not found: {p}")
    try:
        raw = p.read_bytes()
    except OSError as e:
        raise UserError(f"cannot read intrinsics file {p}: {e.strerror}") from None
    # OpenCV writes a "%YAML:1.0" (OpenCV 4) or "%YAML 1.2" (OpenCV 5) header and
    # !!opencv-matrix tags, which PyYAML cannot read.
    if raw.lstrip().startswith((b"%YAML", b"<?xml")) or b"opencv-matrix" in raw or p.suffix.lower() == ".xml":
        return _from_filestorage(p)
    try:
        d = yaml.safe_load(p.read_text())
    except (yaml.YAMLError, UnicodeDecodeError) as e:
        raise UserError(f"{p}: not valid YAML ({str(e).splitlines()[0]})") from None
    if not isinstance(d, dict):
        raise UserError(f"{p}: expected a mapping with fx, fy, cx, cy, width, height")
    if "camera_matrix" in d:
        return _from_plain_opencv_yaml(d, p)
    return _from_project_yaml(d, p)


def write_intrinsics_yaml(path: str | Path, intr: Intrinsics, distortion=None) -> None:
    """Write the project's YAML format (used by tests and tools)."""
    import yaml

    d = intr.to_dict()
    if distortion is not None:
        d["distortion"] = [float(v) for v in distortion]
    Path(path).write_text(yaml.safe_dump(d, sort_keys=False))
