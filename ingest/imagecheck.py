"""Cheap structural checks of encoded images, so that copying bytes never copies a broken file.

Copying a frame byte-for-byte must not cost a full decode (ingest is meant to run at about the
speed of ``tar``), so a copied PNG or JPEG is checked for its signature, its size header and its
end marker: truncated and garbage files are caught; ``IngestConfig.decode_check`` adds a full
decode for bit-level damage.
"""

from __future__ import annotations

import struct

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_IEND = b"\x00\x00\x00\x00IEND\xaeB`\x82"
# JPEG start-of-frame markers carrying the image size (C4, C8 and CC are not SOF markers).
JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
# How far from the end a JPEG's end-of-image marker may sit (some writers append padding).
JPEG_EOI_WINDOW = 64


class BrokenImage(ValueError):
    """An encoded image that fails the structural check; the message is the reason."""


def ext_of(name: str) -> str | None:
    """Shard extension for a source file name: ``png`` or ``jpg`` (``None`` if neither)."""
    low = name.lower()
    if low.endswith(".png"):
        return "png"
    if low.endswith((".jpg", ".jpeg")):
        return "jpg"
    return None


def png_size(data: bytes) -> tuple[int, int]:
    if len(data) < 33 or not data.startswith(PNG_SIGNATURE) or data[12:16] != b"IHDR":
        raise BrokenImage("not a PNG file (bad signature or header)")
    w, h = struct.unpack(">II", data[16:24])
    if w == 0 or h == 0:
        raise BrokenImage("PNG header gives an empty image")
    if not data.endswith(PNG_IEND):
        raise BrokenImage("truncated PNG (no IEND chunk at the end)")
    return int(w), int(h)


def png_bit_depth(data: bytes) -> int:
    """Bits per channel from a PNG header (call :func:`png_size` first)."""
    return data[24]


def jpeg_size(data: bytes) -> tuple[int, int]:
    if len(data) < 4 or not data.startswith(b"\xff\xd8"):
        raise BrokenImage("not a JPEG file (bad signature)")
    if b"\xff\xd9" not in data[-JPEG_EOI_WINDOW:]:
        raise BrokenImage("truncated JPEG (no end-of-image marker)")
    i, n = 2, len(data)
    while i + 4 <= n:
        if data[i] != 0xFF:
            raise BrokenImage("corrupt JPEG (bad marker)")
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0x01, *range(0xD0, 0xD8)):  # markers without a length
            i += 2
            continue
        (length,) = struct.unpack(">H", data[i + 2 : i + 4])
        if marker in JPEG_SOF:
            if i + 9 > n:
                break
            h, w = struct.unpack(">HH", data[i + 5 : i + 9])
            if w == 0 or h == 0:
                raise BrokenImage("JPEG header gives an empty image")
            return int(w), int(h)
        i += 2 + length
    raise BrokenImage("corrupt JPEG (no frame header)")


def image_size(data: bytes, ext: str) -> tuple[int, int]:
    """(width, height) of an encoded ``png``/``jpg``; :class:`BrokenImage` if it fails the check."""
    return png_size(data) if ext == "png" else jpeg_size(data)
