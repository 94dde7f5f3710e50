"""Shards -> training batches: read image bytes, decode, resize, augment, collate.

The chain, each stage a small function: ``ImageFrames`` (an image-only view of the shards: the
training path holds no depth or pose offsets, so it cannot read ground truth) ->
``TripletData[triplet]`` (read 3 images by byte offset, decode, per-image scale 1.0-1.1 + crop back
to the training size with K following, colour jitter on the network inputs only) -> ``collate``.

Frames are read by indexed random access (``os.pread`` at the offsets in ``index.parquet``, what the
webdataset project's ``wids`` does) rather than streamed: the paper's sampler draws targets
uniformly over all training frames and, in the last epochs, sources from anywhere, which a
streaming shuffle buffer cannot do exactly; measured in ``benchmarks/bench_train.py`` (README,
*training*), random access also costs less per triplet than streaming the tars.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from relocdepth.camera import Intrinsics
from relocdepth.errors import UserError
from relocdepth.imageio import check_size, decode_rgb
from relocdepth.sampler import FrameKey, Triplet, TripletSampler
from relocdepth.shardformat import MemberReader

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class AugmentConfig:
    width: int = 640  # paper IV-B: 640x480 inputs
    height: int = 480
    scale_min: float = 1.0  # paper IV-B: "scaled in the range of 1.0 ~ 1.1 and cropped"
    scale_max: float = 1.1
    brightness: float = 0.2  # paper IV-B: colour jitter +-0.2, +-0.2, +-0.2, +-0.1
    contrast: float = 0.2
    saturation: float = 0.2
    hue: float = 0.1
    # DESIGN.md: one jitter draw per triplet (monodepth2 style); True = independent per image.
    jitter_per_image: bool = False

    def __post_init__(self) -> None:
        if self.width % 32 or self.height % 32 or self.width < 32 or self.height < 32:
            raise UserError(f"--size must be multiples of 32 (e.g. 640x480), not {self.width}x{self.height}")
        if not 1.0 <= self.scale_min <= self.scale_max:
            raise UserError(f"scale augmentation needs 1 <= min <= max, not {self.scale_min}-{self.scale_max}")


@dataclass(frozen=True)
class TrainFrame:
    """What training may know of a frame: where its image bytes are, and its camera."""

    key: str
    shard_path: str
    sequence: str
    frame: int
    timestamp: float
    intrinsics: Intrinsics
    image_ext: str
    image_offset: int
    image_size: int


class ImageFrames:
    """Image-only view of a shard dataset's training split (no depth, no pose: by construction)."""

    def __init__(self, frames: list[TrainFrame], name: str, root: str, manifest_hash: str) -> None:
        self.frames = frames
        self.name, self.root, self.manifest_hash = name, root, manifest_hash
        self._reader = MemberReader()

    @classmethod
    def open(cls, shards: str | os.PathLike, split: str = "train") -> ImageFrames:
        from relocdepth.dataset import open_dataset
        from relocdepth.remote import local_dataset

        ds = open_dataset(local_dataset(shards))  # a URL is fetched into the local cache first
        frames = [
            TrainFrame(r.key, ds.shard_path(r), r.sequence, r.frame, r.timestamp, r.intrinsics,
                       r.image_ext, r.image_offset, r.image_size)
            for r in ds.frames(split)
        ]
        if not frames:
            raise UserError(f"{shards} has no '{split}' frames to train on (see its manifest's sequences)")
        view = cls(frames, str(ds.manifest.get("name", "")), ds.root, ds.manifest_hash)
        ds.close()
        return view

    def __len__(self) -> int:
        return len(self.frames)

    def keys(self) -> list[FrameKey]:
        return [FrameKey(f.sequence, f.frame, f.timestamp) for f in self.frames]

    def read_image_bytes(self, i: int) -> bytes:
        f = self.frames[i]
        return self._reader.read(f.shard_path, f.image_offset, f.image_size)

    def read_image(self, i: int) -> np.ndarray:
        """RGB uint8 (H, W, 3) at exactly the size its intrinsics describe (ValueError otherwise:
        a mismatch is never rescaled silently)."""
        img = decode_rgb(self.read_image_bytes(i))
        check_size(img, self.frames[i].intrinsics, self.frames[i].key)
        return img


# -- pure image stages ---------------------------------------------------------------------------
def scale_and_crop(img: np.ndarray, intr: Intrinsics, width: int, height: int, scale: float,
                   fx0: float, fy0: float) -> tuple[np.ndarray, Intrinsics]:
    """Resize the whole image to ``scale x (width, height)``, crop ``width x height`` back.

    ``fx0, fy0`` in [0, 1] place the crop within the slack. Intrinsics follow both steps.
    """
    import cv2

    sw, sh, x0, y0 = crop_box(width, height, scale, fx0, fy0)
    interp = cv2.INTER_AREA if sw < img.shape[1] else cv2.INTER_LINEAR
    if (sw, sh) != (img.shape[1], img.shape[0]):
        img = cv2.resize(img, (sw, sh), interpolation=interp)
    out = np.ascontiguousarray(img[y0:y0 + height, x0:x0 + width])
    return out, intr.scaled(sw, sh).cropped(x0, y0, width, height)


def crop_box(width: int, height: int, scale: float, fx0: float, fy0: float) -> tuple[int, int, int, int]:
    """``(sw, sh, x0, y0)``: the size the image is resized to and the crop's corner (scale_and_crop)."""
    sw, sh = max(width, round(width * scale)), max(height, round(height * scale))
    return sw, sh, round(fx0 * (sw - width)), round(fy0 * (sh - height))


def _gray(img: np.ndarray) -> np.ndarray:
    return img @ np.array([0.299, 0.587, 0.114], dtype=np.float32)


def color_jitter(img: np.ndarray, params: tuple[float, float, float, float, tuple[int, ...]]) -> np.ndarray:
    """torchvision-style jitter on RGB uint8: brightness, contrast, saturation factors and a hue
    shift (fraction of a turn), applied in ``params[4]`` order, clamped after each."""
    import cv2

    b, c, s, h, order = params
    x = img.astype(np.float32) / 255.0
    for op in order:
        if op == 0:
            x = x * b
        elif op == 1:
            m = float(_gray(x).mean())
            x = (x - m) * c + m
        elif op == 2:
            g = _gray(x)[..., None]
            x = (x - g) * s + g
        else:
            hsv = cv2.cvtColor(np.clip(x, 0, 1), cv2.COLOR_RGB2HSV)  # float32: H in degrees
            hsv[..., 0] = np.mod(hsv[..., 0] + h * 360.0, 360.0)
            x = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)
        x = np.clip(x, 0.0, 1.0)
    return (x * 255.0 + 0.5).astype(np.uint8)


def draw_jitter(rng: np.random.Generator, cfg: AugmentConfig) -> tuple[float, float, float, float, tuple[int, ...]]:
    return (
        float(rng.uniform(1 - cfg.brightness, 1 + cfg.brightness)),
        float(rng.uniform(1 - cfg.contrast, 1 + cfg.contrast)),
        float(rng.uniform(1 - cfg.saturation, 1 + cfg.saturation)),
        float(rng.uniform(-cfg.hue, cfg.hue)),
        tuple(int(i) for i in rng.permutation(4)),
    )


# -- torch stages --------------------------------------------------------------------------------
class TripletData:
    """Map-style dataset indexed by :class:`Triplet`: the three frames decoded and augmented.

    Returns a dict of numpy arrays, or ``{"skipped": key, "error": msg}`` when a frame cannot be
    read or decoded (the trainer counts it and goes on). With ``two_view``, also the essential-matrix
    bootstrap's pairs from the middle frame to each source (``relocdepth.twoview.bootstrap_pair`` on
    the un-jittered images): ``two_view_T (2, 4, 4)``, ``two_view_points (2, N, 3)``, ``two_view_ok (2,)``.
    With ``track_width`` the pairs are tracked on the stored images down-sized to at most that
    width (0: on the training images; also when that is no wider than the middle frame's resized
    crop: a scene stored at the training size is tracked on its crops), their points mapped into
    the middle frame's crop (NaN rows where they fall outside it; a measured pair left without any is a failed one), and the
    rotation-only threshold scaled to the tracked size (the same parallax counts as rotation only).
    """

    def __init__(self, frames: ImageFrames, cfg: AugmentConfig, two_view: bool = False, track_width: int = 0) -> None:
        if track_width < 0:
            raise ValueError(f"track_width must be >= 0, not {track_width}")
        self.frames, self.cfg, self.two_view, self.track_width = frames, cfg, two_view, track_width

    def __getitem__(self, t: Triplet) -> dict[str, Any]:
        cfg = self.cfg
        rng = np.random.default_rng(t.aug_seed)
        idx = (t.source_a, t.target, t.source_b)
        geo = [(rng.uniform(cfg.scale_min, cfg.scale_max), rng.random(), rng.random()) for _ in idx]
        shared = draw_jitter(rng, cfg)
        images, inputs, Ks, raws = [], [], [], []
        boxes = [crop_box(cfg.width, cfg.height, *g) for g in geo]
        for i, (scale, fx0, fy0) in zip(idx, geo):
            f = self.frames.frames[i]
            try:
                raw = self.frames.read_image(i)
            except (OSError, ValueError) as e:
                return {"skipped": f.key, "error": str(e)}
            raws.append(raw)
            img, k = scale_and_crop(raw, f.intrinsics, cfg.width, cfg.height, scale, fx0, fy0)
            jit = draw_jitter(rng, cfg) if cfg.jitter_per_image else shared
            images.append(img)
            inputs.append(color_jitter(img, jit))
            Ks.append(k.K())
        out = {
            "images": np.stack(images).transpose(0, 3, 1, 2),  # (3, 3, H, W) uint8
            "inputs": np.stack(inputs).transpose(0, 3, 1, 2),
            "K": np.stack(Ks).astype(np.float32),  # (3, 3, 3)
            "index": np.array(idx, dtype=np.int64),
            "crop": np.array(boxes, dtype=np.int64),  # (3, 4): resized size and crop corner per frame
            "is_global": t.is_global,
        }
        if self.two_view:
            # The stored images only where they are finer than the middle frame's resized crop: at
            # the training size the crops tracked better (README, Quality: the demo scene).
            finer = self.track_width and min(self.track_width, raws[1].shape[1]) > boxes[1][0]
            pairs = (self._tracked_pairs(idx, raws, boxes) if finer
                     else [_bootstrap_pair(images[1], images[i], Ks[1], Ks[i]) for i in (0, 2)])
            out["two_view_T"] = np.stack([p[0] for p in pairs])
            out["two_view_points"] = np.stack([p[1] for p in pairs])
            out["two_view_ok"] = np.array([p[2] for p in pairs])
        return out


    def _tracked_pairs(self, idx: tuple[int, int, int], raws: list[np.ndarray],
                       boxes: list[tuple[int, int, int, int]]) -> list[tuple[np.ndarray, np.ndarray, bool]]:
        """The bootstrap's pairs tracked on the stored images at ``track_width``, the points in
        the middle frame's crop (``boxes``: each frame's resized size and crop corner)."""
        import cv2

        from relocdepth.twoview import BOOTSTRAP_MIN_PARALLAX_PX

        imgs, Ks = [], []
        for i, raw in zip(idx, raws):
            intr = self.frames.frames[i].intrinsics
            tw = min(self.track_width, raw.shape[1])
            th = max(1, round(raw.shape[0] * tw / raw.shape[1]))
            imgs.append(raw if (tw, th) == (raw.shape[1], raw.shape[0])
                        else cv2.resize(raw, (tw, th), interpolation=cv2.INTER_AREA))
            Ks.append(intr.scaled(tw, th).K())
        th, tw = imgs[1].shape[:2]
        pairs = []
        for i in (0, 2):
            # parallax is measured in the source's pixels: the crop path's threshold at this size
            threshold = BOOTSTRAP_MIN_PARALLAX_PX * imgs[i].shape[1] / boxes[i][0]
            T, points, ok = _bootstrap_pair(imgs[1], imgs[i], Ks[1], Ks[i], min_parallax_px=threshold)
            points = track_to_crop(points, (tw, th), boxes[1], (self.cfg.width, self.cfg.height))
            if ok and np.any(T[:3, 3] != 0) and not np.isfinite(points[:, 2]).any():
                ok = False  # a measured translation whose points all left the crop: no length for it
            pairs.append((T, points, ok))
        return pairs


def track_to_crop(points: np.ndarray, track_size: tuple[int, int], box: tuple[int, int, int, int],
                  size: tuple[int, int]) -> np.ndarray:
    """``points (N, 3)`` (pixel x, y in an image resized to ``track_size`` (W, H); anything) with x, y
    moved into the crop of ``box`` (:func:`crop_box`: resized size and corner) of ``size`` (W, H),
    pixel centres as :meth:`Intrinsics.scaled` has them; rows falling outside the crop are NaN."""
    (tw, th), (sw, sh, x0, y0), (W, H) = track_size, box, size
    out = np.array(points, dtype=np.float32, copy=True)
    out[:, 0] = (out[:, 0] + 0.5) * sw / tw - 0.5 - x0
    out[:, 1] = (out[:, 1] + 0.5) * sh / th - 0.5 - y0
    outside = ~((out[:, 0] >= 0) & (out[:, 0] <= W - 1) & (out[:, 1] >= 0) & (out[:, 1] <= H - 1))
    out[outside] = np.nan
    return out


def _bootstrap_pair(*args: Any, **kw: Any) -> tuple[np.ndarray, np.ndarray, bool]:
    from relocdepth.twoview import bootstrap_pair

    return bootstrap_pair(*args, **kw)


def collate(items: list[dict[str, Any]]) -> dict[str, Any]:
    """Stack the readable triplets; list the keys of unreadable ones under ``skipped``."""
    import torch

    ok = [it for it in items if "skipped" not in it]
    batch: dict[str, Any] = {
        "skipped": [(it["skipped"], it["error"]) for it in items if "skipped" in it],
        "attempted": len(items),
    }
    if ok:
        for k in ("images", "inputs", "K", "index", "crop", "two_view_T", "two_view_points", "two_view_ok"):
            if k in ok[0]:
                batch[k] = torch.from_numpy(np.stack([it[k] for it in ok]))
        batch["global_frac"] = float(np.mean([it["is_global"] for it in ok]))
    return batch


class _EpochTriplets:
    """torch Sampler over this rank's triplets of one epoch from a start position."""

    def __init__(self, sampler: TripletSampler, epoch: int, start: int) -> None:
        self.sampler, self.epoch, self.start = sampler, epoch, start
        self._len = sampler.epoch_length(epoch) - start

    def __iter__(self) -> Iterator[Triplet]:
        return self.sampler.iter_epoch(self.epoch, self.start)

    def __len__(self) -> int:
        return self._len


def make_loader(data: TripletData, sampler: TripletSampler, epoch: int, start: int, batch_size: int,
                workers: int = 0, pin_memory: bool = False) -> Any:
    """A DataLoader over this rank's batches of ``epoch`` from triplet ``start`` on (order kept)."""
    from torch.utils.data import DataLoader

    return DataLoader(
        data, sampler=_EpochTriplets(sampler, epoch, start), batch_size=batch_size,  # type: ignore[arg-type]
        num_workers=workers, collate_fn=collate, pin_memory=pin_memory, drop_last=False,
        persistent_workers=False, prefetch_factor=4 if workers > 0 else None,
    )
