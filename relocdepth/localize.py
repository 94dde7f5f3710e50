"""Localize single images: pose (+ confidence) and depth from a trained checkpoint.

Inputs are image files, folders of images (natural order; in a 7-Scenes sequence folder only
the ``.color.png`` frames) or videos. Each image goes through :class:`Predictor` in batches;
each batch's output can be handed on as soon as it is done (``reloc localize`` streams JSON
lines to stdout), and progress goes to stderr.
With a stored alignment (``reloc evaluate --save-alignment``) poses are mapped into the
ground-truth frame (metres) and depth is scaled to metres; without one, they are in the
networks' own frame and units.
"""

from __future__ import annotations

import json
import logging
import shutil
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from relocdepth.camera import Intrinsics
from relocdepth.errors import UserError
from relocdepth.eval_geometry import quat_wxyz_to_xyzw, rotmat_to_quat_wxyz
from relocdepth.imageio import read_rgb
from relocdepth.ingest.source import natural_key
from relocdepth.ingest.video import VIDEO_SUFFIXES, iter_video
from relocdepth.predictor import Prediction, Predictor
from relocdepth.refine import RefineConfig, Refiner, align_refined, cached_map_poses, map_anchors, predict_poses
from relocdepth.trajectory import apply_sim3_dict, sim3_from_dict, tum_lines

log = logging.getLogger(__name__)

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".ppm", ".pgm")
SEVENSCENES_COLOR = ".color.png"
DEPTH_PNG_SCALE = 1000.0  # 16-bit depth PNGs hold depth x 1000 (millimetres once aligned)
FORMATS = ("json", "tum")
VIDEO_FPS_FALLBACK = 30.0  # frame rate for timestamps when a container has neither times nor a rate


@dataclass(frozen=True)
class LocalizeConfig:
    """Options of ``reloc localize`` (one field per CLI option)."""

    checkpoint: str | None = None  # run folder or .pt; None = newest run under ./runs
    K_file: str | None = None  # intrinsics of the query images; None = the training camera
    depth_out: str | None = None  # folder for 16-bit depth PNGs + colour previews
    format: str = "json"  # "json" (one object per line) or "tum"
    output: str | None = None  # file to write; None = the caller prints the lines
    batch_size: int = 8
    device: str = "auto"  # auto | cpu | cuda | cuda:N
    # Shards whose training frames refine each pose (relocdepth.refine); None = the network's pose.
    refine: str | None = None
    refine_neighbours: int = 3
    refine_min_pairs: int = 2
    refine_matcher: str = "klt+sift"
    refine_align: bool = True
    refine_map: str = "auto"  # the map's poses (relocdepth.refine.MAPS)


@dataclass(frozen=True)
class Frame:
    name: str  # output stem (file stem, or video stem + frame index)
    source: str  # path of the image / video
    timestamp: float  # video time (s), else the frame's position in order
    image: np.ndarray  # RGB uint8 (H, W, 3)


def list_folder(folder: Path) -> list[Path]:
    """Images of a folder in natural order; only the colour frames of a 7-Scenes folder."""
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTS]
    colour = [p for p in files if p.name.endswith(SEVENSCENES_COLOR)]
    if colour:
        files = colour
    return sorted(files, key=lambda p: natural_key(p.name))


def expand_inputs(inputs: list[str | Path]) -> list[tuple[str, Path]]:
    """Check the inputs and list them as ("image"|"video", path); UserError on anything else."""
    import cv2

    if not inputs:
        raise UserError("give at least one image, folder of images or video")
    out: list[tuple[str, Path]] = []
    for raw in inputs:
        p = Path(raw)
        if p.is_dir():
            imgs = list_folder(p)
            if not imgs:
                raise UserError(f"{p} holds no images ({', '.join(IMAGE_EXTS)})")
            out += [("image", q) for q in imgs]
        elif not p.exists():
            raise UserError(f"input {p} does not exist")
        elif p.suffix.lower() in VIDEO_SUFFIXES:
            out.append(("video", p))
        elif p.suffix.lower() in IMAGE_EXTS or cv2.haveImageReader(str(p)):
            out.append(("image", p))
        else:
            raise UserError(f"{p} is neither an image ({', '.join(IMAGE_EXTS)}) nor a video")
    return out


def read_image(path: Path) -> np.ndarray:
    """RGB uint8 (H, W, 3), orientation tags ignored; UserError if it cannot be decoded."""
    try:
        return read_rgb(path)
    except (OSError, ValueError):
        raise UserError(f"cannot read image {path} (missing, truncated or not an image)") from None


def _video_frames(path: Path) -> Iterator[tuple[int, float, np.ndarray]]:
    """(frame index, container timestamp, RGB) of every frame, read as ``reloc ingest`` reads
    videos (:func:`relocdepth.ingest.video.iter_video`); a frame that does not decode is skipped
    with a warning (its index is then missing from the names)."""
    import cv2

    n = 0
    for fr in iter_video(path, stride=1, fps_fallback=VIDEO_FPS_FALLBACK):
        if fr.pixels is None:
            log.warning("%s: frame %d does not decode; skipped", path, fr.index)
            continue
        n += 1
        yield fr.index, fr.timestamp, cv2.cvtColor(fr.pixels, cv2.COLOR_BGR2RGB)
    if n == 0:
        raise UserError(f"video {path} has no frames (empty or undecodable)")


def count_frames(items: list[tuple[str, Path]]) -> int | None:
    """How many frames :func:`iter_frames` will give (videos: the container's count), or None
    when a video does not say."""
    import cv2

    n = 0
    for kind, path in items:
        if kind == "image":
            n += 1
            continue
        cap = cv2.VideoCapture(str(path))
        frames = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0) if cap.isOpened() else 0
        cap.release()
        if frames <= 0:
            return None
        n += frames
    return n


def iter_frames(items: list[tuple[str, Path]]) -> Iterator[Frame]:
    """Decode the inputs in order; image timestamps are their position in the order."""
    n_images = 0
    for kind, path in items:
        if kind == "image":
            name = path.name[: -len(SEVENSCENES_COLOR)] if path.name.endswith(SEVENSCENES_COLOR) else path.stem
            yield Frame(name, str(path), float(n_images), read_image(path))
            n_images += 1
        else:
            for i, ts, img in _video_frames(path):
                yield Frame(f"{path.stem}-{i:06d}", str(path), ts, img)


class Calibrated:
    """Query intrinsics from --K (a calibration file); distortion is removed as ingest removes it
    (:class:`relocdepth.ingest.undistort.Undistorter`, K kept as the new camera matrix)."""

    def __init__(self, K_file: str | Path) -> None:
        from relocdepth.ingest.intrinsics import load_calibration
        from relocdepth.ingest.undistort import Undistorter

        self.calib = load_calibration(K_file)
        self.undistorter = Undistorter()

    def apply(self, image: np.ndarray) -> tuple[np.ndarray, Intrinsics]:
        h, w = image.shape[:2]
        cal = self.calib.for_frame_size(w, h)
        return self.undistorter.apply(image, cal), cal.intrinsics


def _record(frame: Frame, index: int, T: np.ndarray, pred: Prediction, i: int, aligned: bool) -> dict:
    return {
        "source": frame.source,
        "name": frame.name,
        "index": index,
        "timestamp": frame.timestamp,
        "T_wc": T.tolist(),
        "t": [float(v) for v in T[:3, 3]],
        "q": [float(v) for v in quat_wxyz_to_xyzw(rotmat_to_quat_wxyz(T[:3, :3]))],  # x, y, z, w
        "confidence": float(pred.confidence[i]),
        "spread_t": float(pred.spread_t[i]),
        "spread_r_deg": float(pred.spread_r_deg[i]),
        "aligned": aligned,
        "units": "m" if aligned else "network",
    }


class DepthWriter:
    """Writes depth PNGs into a staging folder, moved into place only when all succeeded."""

    def __init__(self, out_dir: str | Path) -> None:
        self.out = Path(out_dir)
        if self.out.exists() and not self.out.is_dir():
            raise UserError(f"--depth-out {self.out} exists and is not a folder")
        self.out.mkdir(parents=True, exist_ok=True)
        self.stage = Path(tempfile.mkdtemp(prefix=".partial-", dir=self.out))
        self.names: set[str] = set()

    def write(self, name: str, depth: np.ndarray) -> dict:
        import cv2

        from relocdepth.plots import colourise_depth

        stem = name if name not in self.names else f"{name}-{len(self.names)}"
        self.names.add(stem)
        raw = np.clip(np.nan_to_num(depth) * DEPTH_PNG_SCALE, 0, 65535).round().astype(np.uint16)
        cv2.imwrite(str(self.stage / f"{stem}.depth.png"), raw)
        cv2.imwrite(str(self.stage / f"{stem}.depth_preview.png"), colourise_depth(depth))
        return {"depth_png": str(self.out / f"{stem}.depth.png"), "depth_scale": 1.0 / DEPTH_PNG_SCALE,
                "depth_preview": str(self.out / f"{stem}.depth_preview.png")}

    def commit(self) -> None:
        for f in sorted(self.stage.iterdir()):
            f.replace(self.out / f.name)
        self.stage.rmdir()

    def abort(self) -> None:
        shutil.rmtree(self.stage, ignore_errors=True)


def localize_frames(
    predictor: Predictor, frames: Iterator[Frame], batch_size: int,
    calibrated: Calibrated | None = None, depth: DepthWriter | None = None,
    on_batch: Callable[[list[dict]], None] | None = None, total: int | None = None,
    refiner: Refiner | None = None,
) -> list[dict]:
    """Localize frames in batches; returns one record per frame (see README, localize).

    ``on_batch`` gets each batch's records as soon as the batch is done (streaming output);
    ``total`` (frames expected, if known) sizes the progress report on stderr; ``refiner``
    refines each network pose against its training frames (before any alignment).
    """
    import cv2

    from relocdepth.progress import progress_bar

    if batch_size < 1:
        raise UserError("--batch-size must be at least 1")
    align = predictor.alignment
    scale = sim3_from_dict(align)[0] if align else 1.0
    # poses refined against the run's anchors lie in the anchors' world: their own alignment
    on_anchors = None
    if align and refiner is not None and refiner.map_name == "anchors":
        on_anchors = align.get("anchors")
        if on_anchors is None:
            log.warning("the stored alignment was fitted on the network's poses alone; re-run `reloc evaluate "
                        "--save-alignment` to align the poses refined against the run's anchors by theirs")
    records: list[dict] = []
    batch: list[tuple[Frame, Intrinsics]] = []

    def flush() -> None:
        imgs = [f.image for f, _ in batch]
        pred = predictor.predict(imgs, [k for _, k in batch], with_depth=depth is not None)
        T, refined = pred.T_wc, None
        if refiner is not None:
            refined = [refiner.refine(f.image, k, T[i]) for i, (f, k) in enumerate(batch)]
            T = np.stack([r.T_wc for r in refined])
        if align and on_anchors is not None:  # those refined (not the network's kept) lie in the anchors' world
            T = align_refined(refined, sim3_from_dict(on_anchors), sim3_from_dict(align))
        elif align:
            T = apply_sim3_dict(align, T)
        for i, (f, _) in enumerate(batch):
            rec = _record(f, len(records), T[i], pred, i, align is not None)
            if refined is not None:
                rec["refined_pairs"], rec["refined_by"] = refined[i].pairs, refined[i].by
            if depth is not None:
                h, w = f.image.shape[:2]
                d = cv2.resize(pred.depth[i] * scale, (w, h), interpolation=cv2.INTER_LINEAR)
                rec |= depth.write(f.name, d)
            records.append(rec)
        if on_batch is not None:
            on_batch(records[-len(batch):])
        bar.advance(task, len(batch))
        batch.clear()

    with progress_bar("localize", "images") as bar:
        task = bar.add_task("", total=total)
        for f in frames:
            if calibrated is not None:
                img, K = calibrated.apply(f.image)
                f = Frame(f.name, f.source, f.timestamp, img)
            else:
                K = predictor.intrinsics_for(f.image.shape[1], f.image.shape[0])
            batch.append((f, K))
            if len(batch) >= batch_size:
                flush()
        if batch:
            flush()
    return records


def training_refiner(predictor: Predictor, shards: str | Path, cfg: RefineConfig,
                     which: str = "auto") -> Refiner:
    """A :class:`Refiner` whose map is the training frames of ``shards``, posed as ``which``
    (:func:`relocdepth.refine.map_anchors`) says: the run's anchors, or the network's poses of them
    (from the run's stored map when this checkpoint built it from these frames, else predicted
    here with a progress report)."""
    from relocdepth.dataset import open_dataset
    from relocdepth.progress import progress_bar

    ds = open_dataset(shards)
    recs = [r for r in ds.records if r.split == "train"]
    if not recs:
        raise UserError(f"--refine {shards}: the shards have no training frames to refine against")
    if predictor.meta.get("manifest_hash") != ds.manifest_hash:
        log.warning("--refine: the checkpoint was trained on other shards than %s", ds.root)
    read, intrinsics = (lambda i: ds.read_image(recs[i])), [r.intrinsics for r in recs]

    def compute() -> np.ndarray:
        with progress_bar("localize", "frames") as bar:
            task = bar.add_task("map: training frames", total=len(recs))
            return predict_poses(predictor, read, intrinsics, on_batch=lambda n: bar.advance(task, n))

    keys = [r.key for r in recs]
    T_wc = map_anchors(which, predictor.meta, ds, keys)
    log.info("--refine: the map is the %s of %d training frames",
             "network's poses" if T_wc is None else "run's anchors", len(recs))
    if T_wc is not None:
        return Refiner.from_images(predictor, read, intrinsics, T_wc, cfg, "anchors")
    T_wc = cached_map_poses(Path(predictor.meta["path"]), ds.manifest_hash, keys, compute)
    return Refiner.from_images(predictor, read, intrinsics, T_wc, cfg, "network")


def format_records(records: list[dict], fmt: str) -> str:
    """JSON lines (one object per image) or a TUM trajectory (timestamp tx ty tz qx qy qz qw)."""
    if fmt == "json":
        return "".join(json.dumps(r) + "\n" for r in records)
    if fmt == "tum":
        T = np.array([r["T_wc"] for r in records], np.float64).reshape(-1, 4, 4)
        return "".join(line + "\n" for line in tum_lines([r["timestamp"] for r in records], T))
    raise UserError(f"unknown --format {fmt!r}; use one of {', '.join(FORMATS)}")


def localize(
    inputs: list[str | Path], cfg: LocalizeConfig, on_text: Callable[[str], None] | None = None,
) -> tuple[list[dict], str]:
    """The ``reloc localize`` job: check inputs, predict, write outputs.

    Returns (records, text in cfg.format); when ``cfg.output`` is set the text is also written
    there (atomically). ``on_text`` receives the text of each batch as soon as the batch is
    done (what ``reloc localize`` prints to stdout). The inputs are listed and the checkpoint
    and calibration loaded before anything is written; an image that turns out undecodable
    later stops the job with the lines of the batches before it already streamed.
    """
    from relocdepth.distributed import pick_device
    from relocdepth.fileio import write_text_atomic

    if cfg.format not in FORMATS:
        raise UserError(f"unknown --format {cfg.format!r}; use one of {', '.join(FORMATS)}")
    if cfg.batch_size < 1:
        raise UserError("--batch-size must be at least 1")
    items = expand_inputs(inputs)
    refine_cfg = None if cfg.refine is None else RefineConfig.from_options(
        cfg.refine_neighbours, cfg.refine_min_pairs, cfg.refine_matcher, cfg.refine_align)
    calibrated = Calibrated(cfg.K_file) if cfg.K_file else None
    predictor = Predictor.from_checkpoint(cfg.checkpoint, device=str(pick_device(cfg.device)))
    if cfg.output and Path(cfg.output).is_dir():
        raise UserError(f"--output {cfg.output} is a folder; give a file name")
    refiner = None if cfg.refine is None else training_refiner(predictor, cfg.refine, refine_cfg, cfg.refine_map)
    depth = DepthWriter(cfg.depth_out) if cfg.depth_out else None
    try:
        stream = None if on_text is None else (lambda recs: on_text(format_records(recs, cfg.format)))
        records = localize_frames(predictor, iter_frames(items), cfg.batch_size, calibrated, depth,
                                  on_batch=stream, total=count_frames(items), refiner=refiner)
    except BaseException:
        if depth is not None:
            depth.abort()
        raise
    if depth is not None:
        depth.commit()
    text = format_records(records, cfg.format)
    if cfg.output:
        write_text_atomic(cfg.output, text)
    if predictor.alignment is None:
        log.info("no stored alignment: poses are in the networks' frame and units "
                 "(run `reloc evaluate --save-alignment` on shards with ground truth for metres)")
    return records, text
