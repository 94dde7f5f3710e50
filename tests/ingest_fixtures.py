"""Small generated sources for the ingest tests: 7-Scenes folders, videos, image folders."""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np
from relocdepth.ingest.intrinsics import write_intrinsics_yaml

from relocdepth.camera import Intrinsics


def texture(seed: int, w: int, h: int) -> np.ndarray:
    """A random-colour BGR image with some structure (blocks), uint8 (h, w, 3)."""
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, size=(max(h // 4, 1), max(w // 4, 1), 3), dtype=np.uint8)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_NEAREST)


def write_sevenscenes(root: Path, seqs: dict[str, str], frames: int = 4, size=(64, 48)) -> Path:
    """A 7-Scenes scene: {"seq-01": "train", ...}, PNG colour + uint16 depth + pose per frame."""
    root.mkdir(parents=True)
    w, h = size
    splits: dict[str, list[str]] = {"train": [], "test": []}
    for s, (name, split) in enumerate(seqs.items()):
        d = root / name
        d.mkdir()
        splits[split].append(f"sequence{int(name.split('-')[1])}")
        for i in range(frames):
            cv2.imwrite(str(d / f"frame-{i:06d}.color.png"), texture(100 * s + i, w, h))
            depth = np.full((h, w), 1000 + 10 * i, np.uint16)
            cv2.imwrite(str(d / f"frame-{i:06d}.depth.png"), depth)
            T = np.eye(4)
            T[:3, 3] = [0.01 * i, 0.0, s]
            np.savetxt(d / f"frame-{i:06d}.pose.txt", T, fmt="%.6e")
    (root / "TrainSplit.txt").write_text("".join(f"{n}\n" for n in splits["train"]))
    (root / "TestSplit.txt").write_text("".join(f"{n}\n" for n in splits["test"]))
    return root


def write_video(path: Path, frames: int = 12, size=(64, 48), fps: float = 10.0) -> list[np.ndarray]:
    """An mp4 (mp4v) of textured frames; returns the frames as OpenCV decodes them back."""
    w, h = size
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    assert vw.isOpened()
    for i in range(frames):
        vw.write(texture(i, w, h))
    vw.release()
    cap = cv2.VideoCapture(str(path))
    decoded = []
    while True:
        ok, img = cap.read()
        if not ok:
            break
        decoded.append(img)
    cap.release()
    return decoded


def write_images(folder: Path, names: list[str], size=(64, 48)) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, n in enumerate(names):
        p = folder / n
        assert cv2.imwrite(str(p), texture(1000 + i, *size))
        paths.append(p)
    return paths


def write_K(path: Path, size=(64, 48), distortion=None, f: float = 60.0) -> Path:
    w, h = size
    write_intrinsics_yaml(path, Intrinsics(f, f, w / 2 - 0.5, h / 2 - 0.5, w, h), distortion)
    return path


def with_exif_orientation(jpeg: bytes, orientation: int) -> bytes:
    """``jpeg`` with a minimal APP1 Exif segment (one IFD0 entry: Orientation) right after SOI,
    as phone cameras write it (6 = "rotate 90 degrees clockwise to display")."""
    assert jpeg[:2] == b"\xff\xd8"
    entry = struct.pack("<HHIHH", 0x0112, 3, 1, orientation, 0)  # tag, SHORT, count 1, value, pad
    tiff = b"II*\x00" + struct.pack("<I", 8) + struct.pack("<H", 1) + entry + struct.pack("<I", 0)
    payload = b"Exif\x00\x00" + tiff
    return jpeg[:2] + b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload + jpeg[2:]
