"""Pair parallax: for frame pairs k apart, the image motion that camera rotation cannot explain.

Self-supervised depth learns from translation (baseline) against depth contrast; rotation moves
every pixel the same way whatever its depth, and teaches depth nothing. For each stored frame i
of a sequence and each offset k of ``offsets`` (the i+k-th stored frame of the same sequence),
this tracks corners from frame i to frame i+k on small grey copies (``track_width`` px wide),
fits a homography with RANSAC and keeps the median residual over the tracked points, in pixels of
the stored image. A rotation about the camera centre (or a single plane) gives ~0; depth contrast
seen from a baseline gives more. Tracking failures give NaN.

Only forward pairs (i, i+k) are stored: the residual is symmetric up to noise, so readers use
parallax(i, i+k) for the pair in both directions. Offsets count stored frames (positions in the
sequence), so a frame skipped as corrupt does not leave a hole in the table.

The table is ``parallax.parquet`` (one row per pair: key, sequence, frame, offset, frame_b,
parallax_px), listed with its sha256 under ``parallax`` in manifest.json. :func:`add_parallax`
adds it to an existing dataset without touching the shards (the manifest is rewritten
atomically and stays the commit point).
"""

from __future__ import annotations

import collections
import hashlib
import logging
import os
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from relocdepth.dataset import PARALLAX_FILE, FrameRecord, open_dataset
from relocdepth.errors import UserError
from relocdepth.fileio import write_json_atomic
from relocdepth.twoview import TrackConfig, detect_corners, homography_residual, track_points

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ParallaxConfig:
    """How pair parallax is estimated (saved in the manifest beside the table)."""

    offsets: tuple[int, ...] = (1, 2, 4, 8, 16, 32)  # geometric: covers the paper's +-20 window
    track_width: int = 160  # grey copy for tracking: cheap, and a 3-level pyramid spans ~100 px
    # RANSAC only rejects bad tracks: the median residual of a fit with >50 % inliers is capped by
    # the threshold, so a tight one (1 px) saturates at ~1 px x scale and ranks large parallax badly
    ransac_px: float = 3.0  # px at track_width (12 px at 640)
    min_tracks: int = 15  # fewer surviving tracks: NaN (the median would be noise)
    # 150 corners, 11 px window: ~2.5 ms of LK per pair at 160 px (300 corners, 15 px: 7-12 ms)
    track: TrackConfig = field(default_factory=lambda: TrackConfig(max_corners=150, win_size=11))

    def __post_init__(self) -> None:
        if not self.offsets or min(self.offsets) < 1 or list(self.offsets) != sorted(set(self.offsets)):
            raise UserError(f"parallax offsets must be increasing positive integers, got {self.offsets}")
        if self.track_width < 32:
            raise UserError(f"parallax track width must be >= 32 px, got {self.track_width}")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["offsets"] = list(self.offsets)
        return d


class TrackImage(NamedTuple):
    """A frame prepared for tracking: small grey copy, its corners, stored px per tracking px."""

    grey: np.ndarray
    corners: np.ndarray
    scale: float


def track_image(data: bytes, cfg: ParallaxConfig) -> TrackImage | None:
    """Decode encoded image bytes (PNG/JPEG) into a :class:`TrackImage`; None if undecodable."""
    import cv2
    from relocdepth.ingest.imagecheck import BrokenImage, image_size

    ext = "png" if data[:8] == b"\x89PNG\r\n\x1a\n" else "jpg"
    try:
        width = image_size(data, ext)[0]
    except BrokenImage:
        return None
    # The smallest reduced decode still >= track_width wide (JPEG decodes it directly, cheaply).
    flag = cv2.IMREAD_GRAYSCALE
    for factor, reduced in ((2, cv2.IMREAD_REDUCED_GRAYSCALE_2), (4, cv2.IMREAD_REDUCED_GRAYSCALE_4),
                            (8, cv2.IMREAD_REDUCED_GRAYSCALE_8)):
        if width / factor >= cfg.track_width:
            flag = reduced
    # A reduced grey decode (cheap), not relocdepth.imageio's full colour one; orientation tags are
    # ignored here too, so the tracks are in the pixels the intrinsics describe.
    grey = cv2.imdecode(np.frombuffer(data, np.uint8), flag | cv2.IMREAD_IGNORE_ORIENTATION)
    if grey is None:
        return None
    if grey.shape[1] != cfg.track_width:
        h = max(8, round(grey.shape[0] * cfg.track_width / grey.shape[1]))
        grey = cv2.resize(grey, (cfg.track_width, h), interpolation=cv2.INTER_AREA)
    return TrackImage(grey, detect_corners(grey, cfg.track), width / cfg.track_width)


def pair_parallax(a: TrackImage, b: TrackImage, cfg: ParallaxConfig) -> float:
    """Median homography residual (px of the stored image) of tracks from ``a`` into ``b``."""
    if a.grey.shape != b.grey.shape:
        return float("nan")
    pa, pb = track_points(a.grey, b.grey, a.corners, cfg.track)
    return homography_residual(pa, pb, cfg.ransac_px, cfg.min_tracks) * a.scale


class ParallaxCollector:
    """Streams frames of sequences, in stored order, and estimates every pair's parallax.

    :meth:`add` keeps the last ``max(offsets)`` frames of the current sequence and submits the
    pairs that end at the new frame to ``submit`` (a thread pool's submit, or a direct call).
    """

    def __init__(self, cfg: ParallaxConfig, submit: Callable[..., Future] | None = None) -> None:
        self.cfg = cfg
        self._submit = submit
        self._recent: collections.deque[tuple[str, int, TrackImage | None]] = collections.deque(
            maxlen=max(cfg.offsets))
        self._sequence = ""
        self._pending: list[tuple[tuple[str, str, int, int, int], Future | float]] = []

    def new_sequence(self, name: str) -> None:
        self._recent.clear()
        self._sequence = name

    def add(self, key: str, frame: int, image: TrackImage | None) -> None:
        n = len(self._recent)
        for k in self.cfg.offsets:
            if k > n:
                break
            key_a, frame_a, img_a = self._recent[n - k]
            row = (key_a, self._sequence, frame_a, k, frame)
            if img_a is None or image is None:
                self._pending.append((row, float("nan")))
            elif self._submit is None:
                self._pending.append((row, pair_parallax(img_a, image, self.cfg)))
            else:
                self._pending.append((row, self._submit(pair_parallax, img_a, image, self.cfg)))
        self._recent.append((key, frame, image))

    def rows(self) -> list[dict]:
        """Every pair so far, ordered by sequence (as streamed), frame, offset."""
        out = []
        for (key, seq, frame, k, frame_b), val in self._pending:
            px = val.result() if isinstance(val, Future) else val
            out.append({"key": key, "sequence": seq, "frame": frame, "offset": k, "frame_b": frame_b,
                        "parallax_px": float(px)})
        order = {s: i for i, s in enumerate(dict.fromkeys(r["sequence"] for r in out))}
        out.sort(key=lambda r: (order[r["sequence"]], r["frame"], r["offset"]))
        return out


def write_parallax(rows: list[dict], folder: Path, cfg: ParallaxConfig, name: str = PARALLAX_FILE) -> dict:
    """Write the table as ``folder/name`` (atomically); returns its manifest entry."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from relocdepth.dataset import parallax_arrow_schema
    from relocdepth.fileio import atomic_write

    schema = parallax_arrow_schema()
    cols = {n: [r[n] for r in rows] for n in schema.names}
    table = pa.table(cols, schema=schema)
    path = folder / name
    atomic_write(path, lambda f: pq.write_table(table, f))
    path.chmod(0o644)  # like the shards (the temp file was private)
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    finite = [r["parallax_px"] for r in rows if np.isfinite(r["parallax_px"])]
    return {"file": name, "sha256": digest, "bytes": path.stat().st_size, "pairs": len(rows),
            "failed": len(rows) - len(finite), "config": cfg.to_dict()}


def add_parallax(root: str | Path, cfg: ParallaxConfig = ParallaxConfig(), workers: int = 2) -> dict:
    """Estimate pair parallax for an existing dataset and list it in its manifest.

    The shards and the index are not touched. The table goes to a new file named by its content
    (``parallax-<sha>.parquet``) before manifest.json is replaced atomically, so a crash at any
    point leaves a consistent dataset (at worst an unlisted file). Returns the manifest entry.
    """
    ds = open_dataset(root)
    root = Path(ds.root)
    old = ds.manifest.get("parallax")
    with ThreadPoolExecutor(max_workers=workers) as pool:
        collector = ParallaxCollector(cfg, pool.submit)
        for seq in ds.sequences():
            collector.new_sequence(seq)
            recs = [r for r in ds.records if r.sequence == seq]

            def prepare(rec: FrameRecord) -> TrackImage | None:
                return track_image(ds.read_image_bytes(rec), cfg)

            images = pool.map(prepare, recs)
            for rec, img in zip(recs, images):
                collector.add(rec.key, rec.frame, img)
        rows = collector.rows()
    ds.close()
    tmp_name = f".parallax.tmp-{os.getpid()}.parquet"
    entry = write_parallax(rows, root, cfg, tmp_name)
    final = f"parallax-{entry['sha256'][:16]}.parquet"
    os.replace(root / tmp_name, root / final)
    entry["file"] = final
    manifest = dict(ds.manifest)
    manifest["parallax"] = entry
    write_json_atomic(root / "manifest.json", manifest)
    if old is not None and old["file"] != final:
        (root / old["file"]).unlink(missing_ok=True)
    log.info("%s: pair parallax for %d pairs (%d failed) in %s", root, entry["pairs"], entry["failed"], final)
    return entry
