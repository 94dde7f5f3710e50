"""Decoding images: the one way ingest, training, evaluation and localization turn bytes into pixels.

**Orientation tags are ignored.** Phone JPEGs carry an EXIF Orientation tag, which OpenCV
applies by default (a 100x60 sensor image tagged "rotate 90" decodes as 60x100). Intrinsics
describe the sensor's pixel grid, as calibration tools see it, and ingest reads the image size
from the file header, so every decode here passes ``IMREAD_IGNORE_ORIENTATION``: the pixels are
always the ones the intrinsics describe.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from relocdepth.camera import Intrinsics


class SizeMismatch(ValueError):
    """A decoded image whose size is not the one its intrinsics describe."""


def _color_flags() -> int:
    import cv2

    return cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION


def decode_bgr(data: bytes) -> np.ndarray | None:
    """Encoded image bytes -> BGR uint8 (H, W, 3) in sensor orientation; ``None`` if undecodable."""
    import cv2

    return cv2.imdecode(np.frombuffer(data, np.uint8), _color_flags())


def decode_rgb(data: bytes) -> np.ndarray:
    """Encoded image bytes -> RGB uint8 (H, W, 3) in sensor orientation; ValueError if undecodable."""
    import cv2

    img = decode_bgr(data)
    if img is None:
        raise ValueError("undecodable image")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def decode_unchanged(data: bytes) -> np.ndarray | None:
    """Encoded bytes -> the stored array as is (e.g. uint16 depth), ``None`` if undecodable.

    ``IMREAD_UNCHANGED`` never applies an orientation tag.
    """
    import cv2

    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)


def read_rgb(path: str | Path) -> np.ndarray:
    """An image file -> RGB uint8 (H, W, 3); OSError if unreadable, ValueError if undecodable."""
    return decode_rgb(Path(path).read_bytes())


def check_size(img: np.ndarray, intr: Intrinsics, what: str) -> None:
    """:class:`SizeMismatch` unless ``img`` is ``intr.width x intr.height`` pixels."""
    h, w = img.shape[:2]
    if (w, h) != (intr.width, intr.height):
        raise SizeMismatch(
            f"{what} decodes to {w}x{h} but its intrinsics describe {intr.width}x{intr.height}"
        )
