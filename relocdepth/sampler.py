"""Triplet sampling per the paper (Sec. IV-B): a target and two "nearby" frames.

A target is drawn uniformly over the training frames (one epoch = every eligible training frame
once as a target, as a seeded permutation split across ranks). Its two sources are distinct
frames, other than the target, of the same sequence within +-``window`` frame *indices* (so gaps
left by skipped frames count as distance), or within +-``window_seconds`` of its timestamp.
From epoch ``epochs - global_epochs`` on, with probability ``global_prob``, both sources come
from the whole training set instead ("global pairs").

Everything is a pure function of (seed, epoch, position in the epoch's permutation): a rank reads
positions ``rank, rank + world_size, ...``, so the stream is deterministic given
(seed, epoch, rank, world_size), and the sampler's whole state is ``(epoch, position)``.
Each triplet also carries its own augmentation seed, so decoding/augmenting is deterministic too.

With ``min_parallax`` (pixels at the training size), nearby sources are drawn only among the
window's frames whose pair parallax to the target (image motion that rotation cannot explain,
estimated at ingest: see ``relocdepth.ingest.parallax``) is at least that; when fewer than two
qualify, the two with the largest parallax are used. Parallax between stored offsets is
interpolated linearly; beyond the largest stored offset, or when the upper offset is unknown, the
lower one's value is used (an underestimate: parallax grows with the gap). Forward pairs serve
both directions. Global pairs are unaffected. Default None: the paper's uniform draw.
"""

from __future__ import annotations

import bisect
import itertools
import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from relocdepth.errors import UserError

log = logging.getLogger(__name__)

# Stream tags keep the permutation, pair and augmentation draws independent of each other.
_PERM, _PAIR, _AUG = 1, 2, 3


@dataclass(frozen=True)
class SamplerConfig:
    window: int = 20  # paper IV-B: nearby frames "within 20 steps before or after the target"
    window_seconds: float | None = None  # alternative to `window`, from timestamps (None: use frames)
    epochs: int = 300  # paper IV-B: 300 epochs
    global_epochs: int = 100  # paper IV-B: global pairs "in the latter 100 epochs"
    global_prob: float = 0.5  # paper IV-B: "for 50 %"
    seed: int = 0
    # ((from_epoch, window), ...) overrides `window` from each epoch on (coarse-to-fine); () = constant.
    window_schedule: tuple[tuple[int, int], ...] = ()
    # Sources need this much pair parallax (px at the training size) to the target; None: paper.
    min_parallax: float | None = None

    def __post_init__(self) -> None:
        if self.window < 1:
            raise UserError(f"--window must be at least 1 frame, not {self.window}")
        if self.window_seconds is not None and self.window_seconds <= 0:
            raise UserError(f"--window-seconds must be positive, not {self.window_seconds}")
        if self.epochs < 1:
            raise UserError(f"--epochs must be at least 1, not {self.epochs}")
        if self.global_epochs < 0:
            raise UserError(f"--global-epochs must be >= 0, not {self.global_epochs}")
        if not 0.0 <= self.global_prob <= 1.0:
            raise UserError(f"--global-prob must be in [0, 1], not {self.global_prob}")
        if self.min_parallax is not None and not (self.min_parallax >= 0 and np.isfinite(self.min_parallax)):
            raise UserError(f"--min-parallax must be a number of pixels >= 0, not {self.min_parallax}")
        for e, w in self.window_schedule:
            if e < 0 or w < 1:
                raise UserError(f"window schedule entry ({e}, {w}) needs epoch >= 0 and window >= 1")

    def window_at(self, epoch: int) -> int:
        """The frame window in effect at ``epoch`` (the schedule's last entry at or before it)."""
        w = self.window
        for e, sw in sorted(self.window_schedule):
            if epoch >= e:
                w = sw
        return w

    def global_from(self) -> int:
        """First epoch with global pairs."""
        return max(0, self.epochs - self.global_epochs)


class FrameKey(NamedTuple):
    """What the sampler needs of a training frame (nothing else: no pixels, no ground truth)."""

    sequence: str
    frame: int
    timestamp: float


class Triplet(NamedTuple):
    """Indices into the training frame list; ``target`` is the middle image. ``aug_seed`` seeds
    this triplet's augmentation draws; ``position`` is its place in the epoch's permutation."""

    source_a: int
    target: int
    source_b: int
    aug_seed: int
    is_global: bool
    epoch: int
    position: int


class PairParallax(NamedTuple):
    """Pair parallax of the sampler's frames: ``px[i, j]`` between frame i and the frame
    ``offsets[j]`` places after it in the list (pixels at the training size; NaN: unknown)."""

    offsets: np.ndarray  # (M,) increasing positive ints
    px: np.ndarray  # (N, M)

    def between(self, first: np.ndarray, gap: np.ndarray) -> np.ndarray:
        """Parallax between frames ``first`` and ``first + gap`` (arrays, gap >= 1)."""
        offs = self.offsets
        j = np.searchsorted(offs, gap, side="left")  # first stored offset >= gap
        exact = (j < len(offs)) & (offs[np.minimum(j, len(offs) - 1)] == gap)
        lo_j = np.clip(j - 1, 0, len(offs) - 1)
        hi_j = np.minimum(j, len(offs) - 1)
        lo, hi = self.px[first, lo_j], self.px[first, hi_j]
        span = np.maximum(offs[hi_j] - offs[lo_j], 1)
        w = np.clip((gap - offs[lo_j]) / span, 0.0, 1.0)
        interp = np.where(np.isfinite(hi), lo + w * (hi - lo), lo)
        below = j == 0  # gap below the smallest stored offset: scale it down linearly
        interp = np.where(below, self.px[first, 0] * gap / offs[0], interp)
        return np.where(exact, self.px[first, hi_j], interp)


def _rng(seed: int, *stream: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([seed & 0xFFFFFFFF, *stream]))


class TripletSampler:
    """Deterministic triplet stream over ``frames`` (training frames, sequence-contiguous, in order)."""

    def __init__(self, frames: Sequence[FrameKey], cfg: SamplerConfig = SamplerConfig(),
                 rank: int = 0, world_size: int = 1, parallax: PairParallax | None = None) -> None:
        if not 0 <= rank < world_size:
            raise ValueError(f"rank {rank} outside world size {world_size}")
        self.frames = list(frames)
        self.cfg = cfg
        if cfg.min_parallax is not None:
            if parallax is None:
                raise UserError("--min-parallax needs pair parallax data; add it with reloc inspect --add-parallax")
            if parallax.px.shape != (len(self.frames), len(parallax.offsets)):
                raise ValueError(f"parallax table {parallax.px.shape} does not match {len(self.frames)} frames")
        self.parallax = parallax
        self.rank, self.world_size = rank, world_size
        if len(self.frames) < 3:
            raise UserError(f"training needs at least 3 training frames, the dataset has {len(self.frames)}")
        # Sequence runs [start, end) in the list; frames sorted by index within each run.
        self._seq_of = np.empty(len(self.frames), dtype=np.int64)
        self._runs: list[tuple[int, int]] = []
        start = 0
        for i in range(1, len(self.frames) + 1):
            if i == len(self.frames) or self.frames[i].sequence != self.frames[start].sequence:
                run = self.frames[start:i]
                if any(b.frame <= a.frame for a, b in itertools.pairwise(run)):
                    raise ValueError(f"frames of sequence {run[0].sequence} are not in increasing order")
                self._seq_of[start:i] = len(self._runs)
                self._runs.append((start, i))
                start = i
        if len({self.frames[s].sequence for s, _ in self._runs}) != len(self._runs):
            raise ValueError("a sequence's frames are not contiguous in the training list")
        self._ranges: dict[tuple[str, float], tuple[np.ndarray, np.ndarray]] = {}
        skipped = len(self.frames) - len(self.targets(0))  # also: UserError when none is eligible
        if skipped:
            log.info("%d training frames have fewer than two others within the window: sources only", skipped)

    # -- neighbourhoods --------------------------------------------------------------------------
    def neighbour_range(self, epoch: int) -> tuple[np.ndarray, np.ndarray]:
        """Per frame, the list range [lo, hi) of same-sequence frames within the window (itself included)."""
        if self.cfg.window_seconds is not None:
            key: tuple[str, float] = ("s", float(self.cfg.window_seconds))
        else:
            key = ("f", float(self.cfg.window_at(epoch)))
        if key not in self._ranges:
            lo = np.empty(len(self.frames), dtype=np.int64)
            hi = np.empty(len(self.frames), dtype=np.int64)
            for s, e in self._runs:
                vals = [f.timestamp if key[0] == "s" else f.frame for f in self.frames[s:e]]
                if any(b < a for a, b in itertools.pairwise(vals)):
                    raise UserError(
                        f"timestamps of sequence {self.frames[s].sequence} go backwards; "
                        "use a window in frames (--window) instead of --window-seconds"
                    )
                for i, v in enumerate(vals):
                    lo[s + i] = s + bisect.bisect_left(vals, v - key[1])
                    hi[s + i] = s + bisect.bisect_right(vals, v + key[1])
            self._ranges[key] = (lo, hi)
        return self._ranges[key]

    def targets(self, epoch: int) -> np.ndarray:
        """Frames that can be targets at ``epoch``: at least two others within the window."""
        lo, hi = self.neighbour_range(epoch)
        eligible = np.flatnonzero(hi - lo >= 3)
        if len(eligible) == 0:
            raise UserError(
                "no training frame has two other frames of its sequence within the window; "
                "use a larger --window / --window-seconds or longer sequences"
            )
        return eligible

    # -- the stream ------------------------------------------------------------------------------
    def epoch_order(self, epoch: int) -> np.ndarray:
        """The epoch's target permutation, padded (wrapping) to a multiple of the world size."""
        eligible = self.targets(epoch)
        perm = eligible[_rng(self.cfg.seed, _PERM, epoch).permutation(len(eligible))]
        pad = (-len(perm)) % self.world_size
        return np.concatenate([perm, perm[:pad]]) if pad else perm

    def epoch_length(self, epoch: int) -> int:
        """Triplets this rank draws in ``epoch``."""
        return len(self.epoch_order(epoch)) // self.world_size

    def triplet(self, epoch: int, position: int, order: np.ndarray | None = None) -> Triplet:
        """The triplet at this rank's ``position`` of ``epoch``."""
        order = self.epoch_order(epoch) if order is None else order
        gpos = position * self.world_size + self.rank
        t = int(order[gpos])
        rng = _rng(self.cfg.seed, _PAIR, epoch, gpos)
        is_global = epoch >= self.cfg.global_from() and rng.random() < self.cfg.global_prob
        if is_global:
            lo, hi = 0, len(self.frames)
        else:
            lo_arr, hi_arr = self.neighbour_range(epoch)
            lo, hi = int(lo_arr[t]), int(hi_arr[t])
        if self.cfg.min_parallax is not None and not is_global:
            a, b = self._parallax_sources(t, lo, hi, rng)
        else:
            # Two distinct draws from [lo, hi) minus t: draw offsets in a range one shorter, skip t.
            a, b = (int(x) + lo for x in rng.choice(hi - lo - 1, size=2, replace=False))
            a, b = (a + 1 if a >= t else a), (b + 1 if b >= t else b)
        aug_seed = int(_rng(self.cfg.seed, _AUG, epoch, gpos).integers(0, 2**31 - 1))
        return Triplet(a, t, b, aug_seed, bool(is_global), epoch, position)

    def source_parallax(self, t: int, sources: np.ndarray) -> np.ndarray:
        """Pair parallax (px at the training size) between target ``t`` and same-sequence
        ``sources`` (list indices, != t); NaN where unknown."""
        assert self.parallax is not None
        sources = np.asarray(sources, dtype=np.int64)
        return self.parallax.between(np.minimum(sources, t), np.abs(sources - t))

    def _parallax_sources(self, t: int, lo: int, hi: int, rng: np.random.Generator) -> tuple[int, int]:
        cand = np.delete(np.arange(lo, hi), t - lo)
        px = self.source_parallax(t, cand)
        ok = px >= self.cfg.min_parallax  # NaN compares False: unknown never qualifies
        if ok.sum() >= 2:
            a, b = rng.choice(cand[ok], size=2, replace=False)
            return int(a), int(b)
        if not np.isfinite(px).any():  # nothing known about this window: the paper's draw
            a, b = rng.choice(cand, size=2, replace=False)
            return int(a), int(b)
        # Fewer than two qualify: the two largest (NaN last; ties to the nearer frame, then earlier).
        key = np.where(np.isfinite(px), -px, np.inf)
        order = np.lexsort((cand, np.abs(cand - t), key))
        return int(cand[order[0]]), int(cand[order[1]])

    def iter_epoch(self, epoch: int, start: int = 0) -> Iterator[Triplet]:
        """This rank's triplets of ``epoch`` from ``position = start`` on."""
        order = self.epoch_order(epoch)
        for p in range(start, len(order) // self.world_size):
            yield self.triplet(epoch, p, order)
