"""``reloc ingest``: sources (7-Scenes scenes, videos, image folders) -> a shard dataset.

Stages: detect each source's kind and check it (intrinsics, first frame) before anything is
written -> prepare frames in a small thread pool (copy bytes, or undistort/resize/re-encode) ->
write shards in order -> index.parquet -> wids.json -> manifest.json -> rename the temporary
folder into place.
"""

from __future__ import annotations

import collections
import logging
import time
from collections.abc import Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass, replace
from datetime import datetime, timezone
from pathlib import Path

from relocdepth.ingest import images, sevenscenes, video
from relocdepth.ingest.parallax import (
    ParallaxCollector,
    ParallaxConfig,
    track_image,
    write_parallax,
)
from relocdepth.ingest.prefetch import background
from relocdepth.ingest.process import Encoding, Prepared, SequenceProcessor
from relocdepth.ingest.source import SourcePlan, check_readable, sanitize_name
from relocdepth.ingest.writer import (
    ShardWriter,
    check_output,
    publish,
    temp_folder,
    write_index,
)

from relocdepth import __version__
from relocdepth.errors import UserError
from relocdepth.fileio import write_json_atomic
from relocdepth.progress import PlainProgress, stderr_console, stderr_is_terminal
from relocdepth.shardformat import (
    FORMAT,
    INDEX,
    MANIFEST,
    SCHEMA_VERSION,
    WIDS_DESCRIPTOR,
    wids_descriptor,
)

log = logging.getLogger(__name__)

SEVENSCENES_RGB_INTRINSICS = (525.0, 525.0, 320.0, 240.0, 640, 480)
# Frames in flight per worker: enough to keep the pool busy, small enough to bound memory.
PREFETCH_PER_WORKER = 4


@dataclass(frozen=True)
class IngestConfig:
    """Options of ``reloc ingest`` (one field per CLI option, plus tuning knobs)."""

    intrinsics: str | None = None  # --K: intrinsics file; required for videos and image folders
    stride: int = 1  # keep every Nth frame of each sequence (frame indices keep their gaps)
    resize: tuple[int, int] | None = None  # (W, H) to re-encode frames at; None keeps the source size
    split: str | None = None  # force all sequences into "train"/"test"; None: 7-Scenes split files, else train
    name: str | None = None  # dataset name; None: the first source's name
    scene: str | None = None  # which scene of a 7-Scenes root holding several
    shard_size: int = 1000  # samples per shard (~0.6 GB of 640x480 PNG + depth); a shard never mixes sequences
    force: bool = False  # replace an existing output
    strict: bool = False  # a corrupt frame is an error instead of being skipped and recorded
    fps: float = 30.0  # timestamps where the source has none (7-Scenes was recorded at 30 Hz)
    sevenscenes_intrinsics: tuple[float, float, float, float, int, int] = SEVENSCENES_RGB_INTRINSICS
    # ^ fx, fy, cx, cy, W, H of the 7-Scenes RGB camera as DSAC* and ACE use (585 is the depth camera)
    video_format: str = "jpg"  # decoded video frames: jpg (q95; ~15x faster to write than PNG, and
    # the frames were lossy already) or png (lossless re-encoding of the decoded frame, ~4x larger)
    jpeg_quality: int = 95  # when writing JPEG
    png_compression: int = 1  # zlib level for written PNGs: 1 is ~3x faster than OpenCV's 3, ~10% larger
    decode_check: bool = False  # also fully decode copied images (header/end-marker checks always run)
    workers: int = 2  # threads preparing frames (OpenCV releases the GIL while coding images)
    pair_parallax: bool = False  # estimate pair parallax (parallax.parquet); off: costs > 1.5x ingest time
    parallax_offsets: tuple[int, ...] = ParallaxConfig.offsets  # pairs (i, i+k) for these k
    parallax_width: int = ParallaxConfig.track_width  # px width of the grey copies tracked

    def __post_init__(self) -> None:
        if self.stride < 1:
            raise UserError(f"--stride must be >= 1, got {self.stride}")
        if self.shard_size < 1:
            raise UserError(f"--shard-size must be >= 1, got {self.shard_size}")
        if self.split not in (None, "train", "test"):
            raise UserError(f"--split must be 'train' or 'test', got '{self.split}'")
        if self.resize is not None and (len(self.resize) != 2 or min(self.resize) < 1):
            raise UserError(f"--resize must be WxH with positive sizes, got {self.resize}")
        if self.video_format not in ("png", "jpg"):
            raise UserError(f"video_format must be 'png' or 'jpg', got '{self.video_format}'")
        if self.workers < 1:
            raise UserError(f"workers must be >= 1, got {self.workers}")
        self.parallax_config()  # validates the parallax fields

    def parallax_config(self) -> ParallaxConfig:
        return ParallaxConfig(offsets=tuple(self.parallax_offsets), track_width=self.parallax_width)


def detect_kind(path: Path) -> str:
    """``"sevenscenes"``, ``"video"`` or ``"images"``; a UserError for anything else."""
    check_readable(path)
    if path.is_file():
        if video.is_video(path):
            return "video"
        raise UserError(
            f"unknown source kind: {path} (expected a video file "
            f"({', '.join(sorted(video.VIDEO_SUFFIXES))}), a 7-Scenes folder or an image folder)"
        )
    if sevenscenes.is_scene(path) or sevenscenes.find_scenes(path):
        return "sevenscenes"
    if images.list_images(path):
        return "images"
    try:
        empty = not any(path.iterdir())
    except OSError as e:
        raise UserError(f"source not readable: {path} ({e.strerror})") from None
    if empty:
        raise UserError(f"empty folder: {path}")
    raise UserError(
        f"unknown source kind: {path} holds neither images (.png/.jpg) nor 7-Scenes seq-XX folders"
    )


def plan_source(path: Path, cfg: IngestConfig) -> SourcePlan:
    kind = detect_kind(path)
    path = path.resolve()  # frame jsons record absolute source paths
    common = {"k_file": cfg.intrinsics, "stride": cfg.stride, "fps": cfg.fps, "split": cfg.split}
    if kind == "video":
        return video.plan_video(path, **common)
    if kind == "images":
        return images.plan_images(path, **common)
    return sevenscenes.plan_sevenscenes(
        path, scene=cfg.scene, default_intrinsics=cfg.sevenscenes_intrinsics, **common
    )


def _unique_names(plans: list[SourcePlan]) -> list[list[str]]:
    """Sequence names, made unique across sources by a numeric suffix."""
    seen: set[str] = set()
    out = []
    for plan in plans:
        names = []
        for seq in plan.sequences:
            name, n = seq.name, 2
            while name in seen:
                name, n = f"{seq.name}_{n}", n + 1
            seen.add(name)
            names.append(name)
        out.append(names)
    return out


def _ordered_map(fn, items: Iterable, pool: ThreadPoolExecutor, window: int) -> Iterator:
    """``map(fn, items)`` on ``pool``, in order, with at most ``window`` items in flight."""
    pending: collections.deque[Future] = collections.deque()
    for item in items:
        pending.append(pool.submit(fn, item))
        if len(pending) >= window:
            yield pending.popleft().result()
    while pending:
        yield pending.popleft().result()


def _progress():
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TaskProgressColumn,
        TextColumn,
        TimeElapsedColumn,
    )

    return Progress(
        TextColumn("[bold]ingest[/] {task.description}"), BarColumn(), MofNCompleteColumn(),
        TaskProgressColumn(), TextColumn("{task.fields[fps]:.1f} frames/s"), TimeElapsedColumn(),
        console=stderr_console(), transient=False,
    )


def _row(meta: dict, shard: str, where: dict[str, tuple[int, int]]) -> dict:
    intr = meta["intrinsics"]
    ext = meta["image"]
    none = (-1, -1)
    row = {
        "key": meta["key"], "shard": shard, "sequence": meta["sequence"], "frame": meta["frame"],
        "timestamp": meta["timestamp"], "split": meta["split"],
        **{k: intr[k] for k in ("fx", "fy", "cx", "cy", "width", "height")},
        "has_depth": "depth.png" in where, "has_pose": "pose.txt" in where, "image_ext": ext,
    }
    for col, suffix in (("image", ext), ("json", "json"), ("depth", "depth.png"), ("pose", "pose.txt")):
        row[f"{col}_offset"], row[f"{col}_size"] = where.get(suffix, none)
    return row


def _config_dict(cfg: IngestConfig) -> dict:
    d = asdict(cfg)
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()}


def _write_all(plans: list[SourcePlan], tmp: Path, cfg: IngestConfig, progress: bool) -> dict:
    enc = Encoding(cfg.resize, cfg.video_format, cfg.jpeg_quality, cfg.png_compression, cfg.decode_check)
    writer = ShardWriter(tmp, cfg.shard_size)
    rows: list[dict] = []
    sequences: list[dict] = []
    skipped: list[dict] = []
    names = _unique_names(plans)
    total = sum(seq.count for plan in plans for seq in plan.sequences)
    pcfg = cfg.parallax_config() if cfg.pair_parallax else None
    # Without a terminal (nohup, a log file) a bar is drawn once at the end: plain lines instead.
    bar = (_progress() if stderr_is_terminal() else PlainProgress("ingest")) if progress else None
    t0 = time.perf_counter()
    with ThreadPoolExecutor(max_workers=cfg.workers) as pool:
        if bar is not None:
            bar.start()
        task = bar.add_task("", total=total, fps=0.0) if bar is not None else None
        parallax = ParallaxCollector(pcfg, pool.submit) if pcfg is not None else None
        try:
            for plan, seq_names in zip(plans, names):
                for seq, name in zip(plan.sequences, seq_names):
                    proc = SequenceProcessor(replace(seq, name=name), enc)
                    if bar is not None:
                        bar.update(task, description=name)
                    writer.new_sequence()
                    if parallax is not None:
                        parallax.new_sequence(name)
                    n = 0

                    def prepare(frame, proc=proc, name=name) -> tuple:
                        prep = proc.prepare(frame, f"{name}-{frame.index:06d}")
                        track = None
                        if pcfg is not None and prep.sample is not None:
                            track = track_image(prep.sample.members[prep.meta["image"]], pcfg)
                        return frame, prep, track

                    window = cfg.workers * PREFETCH_PER_WORKER
                    # frames are read/decoded in their own thread, prepared in the pool, written here
                    frames = background(seq.frames(), window)
                    for frame, prep, track in _ordered_map(prepare, frames, pool, window):
                        _handle_skip(frame, prep, cfg, skipped)
                        if prep.sample is not None:
                            if parallax is not None:
                                parallax.add(prep.meta["key"], prep.meta["frame"], track)
                            where = writer.add(prep.sample)
                            rows.append(_row(prep.meta, writer.current_name, where))
                            n += 1
                        if bar is not None:
                            bar.update(task, advance=1, fps=len(rows) / max(time.perf_counter() - t0, 1e-9))
                    if n:
                        sequences.append({"name": name, "split": seq.split, "frames": n})
                    else:
                        log.warning("sequence %s: no frame could be ingested", name)
            parallax_rows = parallax.rows() if parallax is not None else None
        finally:
            if bar is not None:
                bar.stop()
    shards = writer.close()
    if not rows:
        raise UserError("no frame could be ingested (every frame was skipped; see the warnings)")
    elapsed = time.perf_counter() - t0
    log.info("ingested %d frames in %.1f s (%.1f frames/s)", len(rows), elapsed, len(rows) / elapsed)
    return {"rows": rows, "sequences": sequences, "skipped": skipped, "shards": shards,
            "parallax_rows": parallax_rows}


def _handle_skip(frame, prep: Prepared, cfg: IngestConfig, skipped: list[dict]) -> None:
    if prep.skipped is None:
        return
    if cfg.strict:
        raise UserError(f"corrupt frame {frame.source}: {prep.skipped} (--strict)")
    skipped.append({"source": frame.source, "reason": prep.skipped})


def ingest(sources: list[Path], out: Path, cfg: IngestConfig = IngestConfig(), progress: bool = True) -> dict:
    """Ingest ``sources`` into the shard dataset ``out``; returns the manifest.

    Every source is checked before anything is written; the dataset is built in a temporary
    folder beside ``out`` and renamed into place at the end (``cfg.force`` replaces an old one).
    """
    import shutil

    out = Path(out)
    if not sources:
        raise UserError("no source given")
    check_output(out, cfg.force)
    plans = [plan_source(Path(s), cfg) for s in sources]
    tmp = temp_folder(out)
    try:
        result = _write_all(plans, tmp, cfg, progress)
        write_index(result["rows"], tmp / INDEX)
        manifest = _manifest(plans, result, cfg)
        if result["parallax_rows"] is not None:
            manifest["parallax"] = write_parallax(result["parallax_rows"], tmp, cfg.parallax_config())
        write_json_atomic(tmp / WIDS_DESCRIPTOR, wids_descriptor(manifest))
        write_json_atomic(tmp / MANIFEST, manifest)  # last: marks the dataset complete
        publish(tmp, out, cfg.force)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    if manifest["skipped"]:
        log.warning(
            "%d corrupt frame(s) skipped (listed under 'skipped' in %s)",
            len(manifest["skipped"]), out / MANIFEST,
        )
    return manifest


def _manifest(plans: list[SourcePlan], result: dict, cfg: IngestConfig) -> dict:
    rows = result["rows"]
    first = plans[0].path.resolve()
    name = cfg.name or sanitize_name(first.name if first.is_dir() else first.stem)
    n_train = sum(1 for r in rows if r["split"] == "train")
    return {
        "format": FORMAT,
        "schema_version": SCHEMA_VERSION,
        "tool_version": __version__,
        "name": name,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "config": _config_dict(cfg),
        "sources": [{"path": str(p.path.resolve()), "kind": p.kind} for p in plans],
        "shards": result["shards"],
        "sequences": result["sequences"],
        "skipped": result["skipped"],
        "totals": {
            "frames": len(rows), "train": n_train, "test": len(rows) - n_train,
            "sequences": len(result["sequences"]), "skipped": len(result["skipped"]),
        },
    }
