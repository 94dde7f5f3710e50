"""The training loop: sample -> forward + losses -> step -> log -> checkpoint, over named steps.

``train(shards, run_dir, cfg)`` trains the depth and DSC networks on a shard dataset's training
split with the paper's recipe (Sec. IV-B), writing ``run_dir/config.json``, ``logs/train.jsonl``
and versioned checkpoints. Under ``torchrun`` every rank draws its own triplets and rank 0 alone
writes. Faults: a non-finite loss skips the step (``max_nonfinite`` in a row stop the run), an
unreadable frame drops its triplet from the batch, a kill leaves the newest complete checkpoint,
Ctrl-C / SIGTERM stop after the current step with a final checkpoint.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import random
import signal
import threading
import time
from collections.abc import Collection, Mapping
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

import relocdepth
from relocdepth import checkpoint as ckpt_io
from relocdepth.data import AugmentConfig, ImageFrames, TripletData, make_loader
from relocdepth.distributed import (
    Dist,
    any_rank,
    broadcast_buffers,
    init_distributed,
    max_over_ranks,
    parameter_digest,
    shutdown_distributed,
)
from relocdepth.errors import TrainingDiverged, UserError
from relocdepth.fileio import write_json_atomic
from relocdepth.method import MethodConfig
from relocdepth.models import ModelConfig
from relocdepth.sampler import PairParallax, SamplerConfig, TripletSampler
from relocdepth.trainlog import TrainLog
from relocdepth.weightavg import WeightAverage

log = logging.getLogger(__name__)

CONFIG_NAME = "config.json"
# Sources of the relative-pose bootstrap (TrainConfig.bootstrap); "oracle-gt" reads ground truth.
BOOTSTRAP_SOURCES = ("off", "posenet", "essential", "oracle-gt")
# Sources of the DSC network's absolute anchors (TrainConfig.anchor).
ANCHOR_SOURCES = ("off", "vo", "linked")


# The configs a TrainConfig is composed of, by their key in it (and in a run's config.json).
SECTIONS: dict[str, type] = {"sampler": SamplerConfig, "augment": AugmentConfig, "method": MethodConfig,
                             "model": ModelConfig}


def _paper_model() -> ModelConfig:
    return ModelConfig(pretrained="imagenet")  # paper III-D: ImageNet-pretrained encoders


def _as_tuples(value: Any) -> Any:
    """``value`` with its lists (as YAML/JSON give them) as the config's tuples, nested too."""
    return tuple(_as_tuples(v) for v in value) if isinstance(value, (list, tuple)) else value


@dataclass(frozen=True)
class TrainConfig:
    """What a training run is given: the sampler, augmentation, method and model configs, which
    hold their own options (with the paper's defaults), plus the trainer's own options below.

    Build it from option names with :meth:`from_dict`: flat names as the command line and the
    recipes use them (``window``, ``size``, ``use_dsc``, ``batch_size``), the nested layout of
    :meth:`to_dict` (a run's ``config.json``), or both mixed. ``model.relpose`` is not an option:
    it follows ``bootstrap``.
    """

    sampler: SamplerConfig = field(default_factory=SamplerConfig)  # triplets, epochs, seed
    augment: AugmentConfig = field(default_factory=AugmentConfig)  # input size, scale, colour jitter
    method: MethodConfig = field(default_factory=MethodConfig)  # losses, LCVS and DSC ablations
    model: ModelConfig = field(default_factory=_paper_model)  # networks, their initialisation
    batch_size: int = 6  # paper IV-B: batch size 6
    lr: float = 1e-4  # paper IV-B: Adam, learning rate 0.0001
    beta1: float = 0.9  # paper IV-B: beta1 = 0.9
    beta2: float = 0.999  # paper IV-B: beta2 = 0.999
    # Relative-pose bootstrap (not in the paper; README, fidelity): for the first bootstrap_steps the
    # warps use relative poses from "posenet" (a two-frame network trained by the same photometric
    # loss), "essential" (essential matrix of KLT tracks, translation scaled by the current depth) or
    # "oracle-gt" (RESEARCH ONLY: the dataset's ground-truth poses), while the DSC network
    # learns them through a consistency term of weight w_bootstrap, which then fades out linearly over
    # bootstrap_fade_steps steps while the warps use the DSC poses (the paper's loss).
    bootstrap: str = "off"
    # RESEARCH ONLY: the dataset's ground-truth depth replaces the depth network's in the poses and
    # warps, so that the pose half learns alone (how fast can it learn when depth is right?).
    oracle_gt_depth: bool = False
    bootstrap_steps: int = 0
    bootstrap_fade_steps: int = 500
    w_bootstrap: float = 1.0
    # Weight (times w_bootstrap's) of the term that holds the DSC's translation directions to the
    # bootstrap's where it measured them (relocdepth.method.Bootstrap.w_direction; 0: none).
    w_direction: float = 0.0
    # The essential bootstrap tracks its pairs on the stored images down-sized to at most this width
    # (0: on the training images): finer tracks give finer poses on real video (README, Training).
    bootstrap_track_width: int = 0
    # Absolute anchors for the DSC network (not in the paper; README, fidelity): at step anchor_step
    # (and every anchor_every steps after, 0: once) every training frame gets a world pose without
    # ground truth (relocdepth.anchors), and every DSC cell's pose is pulled towards its frame's
    # pose there with weight w_anchor, for as long as the bootstrap lasts (fading with it). "vo":
    # keyframe odometry of each sequence (the bootstrap's two-view geometry with the depth
    # network's depth) registered into one world; "linked": the DSC network's own poses, each
    # sequence registered into the first one's world by links between similar frames. Both need a
    # bootstrap: depth must have learned, and the anchors' weight fades with it (unless anchor_hold).
    anchor: str = "off"
    # Keep the anchors' weight (and their rebuilds every anchor_every steps) after the bootstrap has
    # faded out, for the whole run: the DSC's positions stay in its orientations' world after the
    # hand-over ("linked": each build turns the centres again).
    anchor_hold: bool = False
    # "linked": turn the anchors' centres so that the frames' displacements point where their
    # orientations and the bootstrap's measured directions say (relocdepth.anchors.direction_turn).
    anchor_turn: bool = True
    # ... only when at least this fraction of the measured directions agree with the fitted turn
    # (relocdepth.anchors.TURN_MIN_AGREEMENT): early on the network's own directions are noise.
    anchor_turn_agreement: float = 0.65
    anchor_step: int = 150
    anchor_every: int = 0
    # Let the rebuild interval grow with the run: after a build at step s the next comes
    # max(anchor_every, anchor_every_growth * s) steps on (0: every anchor_every steps). Builds stay
    # dense early, while the network changes fast, and their number grows with the logarithm of
    # the steps, so that their share of the run's time does not grow with a scene's frames as
    # fast as a fixed interval's does (a build's cost grows with the frames).
    anchor_every_growth: float = 0.0
    # Let the rebuild interval follow the builds' cost: after a build that took B seconds the next
    # comes at least ceil(B (1 - F) / (F s)) steps on, s the run's mean seconds a step outside the
    # builds (0: off), so that the builds take at most this fraction F of the run's time whatever
    # a scene's frames make them cost. The interval is measured on the machine at each build and
    # kept in the checkpoint (a resumed run builds where the run said it would); with anchor_every
    # and anchor_every_growth, the longest of the three.
    anchor_budget: float = 0.0
    w_anchor: float = 1.0
    # "vo": builds from this step on refine the odometry by direct alignment of each frame to the
    # previous one with the depth network's depth (relocdepth.vo.VOConfig.align; None: never). Worth
    # it only once depth has learned: on the real walk-through the odometry's ATE fell 8-22 % with
    # depth at AbsRel 0.16-0.19 and rose 29 % at AbsRel 0.25 (README, Quality: trial 25).
    anchor_align_step: int | None = None
    # "vo": refine each build's odometry by bundle adjustment over the training frames' multi-frame
    # tracks (relocdepth.ba; before any alignment). On the real walk-through its error fell from
    # 0.223-0.252 m to 0.142-0.147 m with the depth network's depth at steps 150-400 (README,
    # Quality: trial 29).
    anchor_bundle: bool = False
    # "vo": a pair of frames that KLT tracks at fewer than this many points (a fast turn) is measured
    # by PnP on SIFT and KLT matches lifted by the depth network's depth instead of by the essential
    # matrix of its tracks (relocdepth.vo.VOConfig.pnp_below; 0: never).
    anchor_pnp_below: int = 0
    # "vo": the odometry tracks the stored images down-sized to at most this width (0: the training
    # images), with the depth network's depth upsampled to them.
    anchor_track_width: int = 0
    # "vo" with anchor_bundle: run the bundle adjustment to convergence (ANCHOR_BUNDLE_ITERATIONS)
    # and hold its scale along the path to the depth network's depth per frame, smoothed over this
    # many frames (relocdepth.ba.BAConfig.scale_window; 0: the adjustment's 30 iterations, one
    # scale). Offline on 14 checkpoints of a real walk-through run, 10 frames: builds 0.064-0.176 m
    # (mean 0.119) against 0.072-0.231 (0.134), closer at 10 of the 14 (README, Training: the
    # scale along the path; Quality: trials 34-35).
    anchor_bundle_scale: float = 0.0
    # ... or hold it by a polynomial of this degree along the path, fitted to the depth network's
    # per-frame scale after the adjustment's usual 30 iterations (relocdepth.ba.BAConfig.scale_degree;
    # None: not; exclusive with anchor_bundle_scale). Offline on a real walk-through, degree 1:
    # closer than the default at 9 of 10 checkpoints to step 600 on seed 0 and at 12 of 12 to 700
    # on seed 1 (means 0.095 and 0.097 m against 0.133 and 0.138), but farther at all 6 of seed 0's
    # from step 650, where its network's depth had a drift of its own along the walk (README,
    # Training: a drift of the scale along the path; Quality: trial 36).
    anchor_bundle_scale_degree: int | None = None
    # "vo": the anchors are the last this many builds combined (relocdepth.anchors.combine_builds:
    # per frame the median centre and the mean orientation, the older builds scaled into the
    # newest's units); until there are that many, the newest alone (1: the newest build, always).
    anchor_combine: int = 1
    # "vo": each build's odometry runs on every this-many-th frame of each sequence (and its last),
    # the frames between taking poses interpolated between theirs; the sequences are registered
    # on all frames (relocdepth.anchors.build_anchors). A build's bundle adjustment grows faster
    # than the frames (its tracks grow longer); frames 7 mm apart (30 fps) give it little more
    # than frames 14 mm apart (README, Training: builds that scale with the scene; 1: every frame;
    # 0: each sequence its own, every frame up to relocdepth.anchors.ODOMETRY_FRAMES of them).
    anchor_stride: int = 0
    # "vo": hold the depth network's scale where it was at the first anchors' build, with this
    # weight (relocdepth.method.Bootstrap.w_depth_scale; 0: free, the paper's). Monocular training
    # leaves the scale of all depths free, and the anchors are rebuilt in whatever units it has
    # drifted to, so that the DSC network's targets change scale from build to build.
    w_depth_scale: float = 0.0
    # An exponential moving average of the weights (not in the paper), kept beside them with this
    # decay per step and written into every checkpoint, whose networks it then is for localisation
    # and evaluation (0: none). Training itself (the anchors too) uses the raw weights, so a run
    # takes the same steps with or without it. Early on the decay is capped at (1 + n) / (10 + n)
    # after n steps, so that the average does not hold on to the random initialisation. A resumed
    # run keeps its own average; a decay given when resuming changes it, or starts one.
    ema_decay: float = 0.0
    workers: int = 2  # DataLoader worker processes (0: load in the training process)
    device: str = "auto"  # auto | cpu | cuda
    amp: bool = False  # CUDA/CPU autocast
    amp_dtype: str = "bf16"  # bf16 | fp16 (fp16 uses a GradScaler)
    channels_last: bool = False  # CUDA memory format for the convolutions
    max_steps: int | None = None  # stop after this many steps (None: run all epochs)
    max_minutes: float | None = None  # stop after this much training wall time (minutes)
    log_every: int = 10  # JSONL/TensorBoard every N steps
    checkpoint_every: int = 500  # steps between checkpoints (plus one at the end)
    keep_last: int = 3  # checkpoints kept (older ones deleted)
    max_nonfinite: int = 20  # this many non-finite steps in a row stop the run
    progress: bool = True  # rich progress bar on rank 0
    resume: bool = False  # continue the run in run_dir from its latest checkpoint

    def __post_init__(self) -> None:
        for key, cls in SECTIONS.items():
            if not isinstance(getattr(self, key), cls):
                raise TypeError(f"TrainConfig.{key} must be a {cls.__name__}")
        if self.model.relpose != (self.bootstrap == "posenet"):  # the bootstrap's two-frame network
            object.__setattr__(self, "model", dataclasses.replace(self.model, relpose=self.bootstrap == "posenet"))
        for name, places in _SHARED_FIELDS.items():
            values = {key: getattr(getattr(self, key), name) for key in places}
            if len(set(values.values())) > 1:
                given = ", ".join(f"{key}.{name} = {v!r}" for key, v in values.items())
                raise UserError(f"{name} must be the same everywhere ({given}): give it once, as {name}")
        if self.batch_size < 1:
            raise UserError(f"--batch-size must be >= 1, not {self.batch_size}")
        if not (self.lr > 0 and math.isfinite(self.lr)):
            raise UserError(f"--lr must be a positive number, not {self.lr}")
        if self.amp_dtype not in ("bf16", "fp16"):
            raise UserError(f"--amp-dtype must be bf16 or fp16, not {self.amp_dtype!r}")
        for name in ("log_every", "checkpoint_every", "max_nonfinite"):
            if getattr(self, name) < 1:
                raise UserError(f"--{name.replace('_', '-')} must be >= 1")
        if self.max_steps is not None and self.max_steps < 0:
            raise UserError("--max-steps must be >= 0")
        if self.max_minutes is not None and not self.max_minutes > 0:
            raise UserError(f"--max-minutes must be > 0, not {self.max_minutes}")
        if self.bootstrap not in BOOTSTRAP_SOURCES:
            raise UserError(f"--bootstrap must be one of {', '.join(BOOTSTRAP_SOURCES)}, not {self.bootstrap!r}")
        if self.bootstrap != "off" and self.bootstrap_steps < 1:
            raise UserError(f"--bootstrap {self.bootstrap} needs --bootstrap-steps >= 1")
        if self.anchor not in ANCHOR_SOURCES:
            raise UserError(f"--anchor must be one of {', '.join(ANCHOR_SOURCES)}, not {self.anchor!r}")
        if self.anchor != "off" and self.bootstrap == "off":
            raise UserError(f"--anchor {self.anchor} needs a --bootstrap (the anchors need the depth it "
                            "teaches first, and their weight fades with it)")
        if not 0.0 <= self.anchor_turn_agreement <= 1.0:  # NaN fails too
            raise UserError("--anchor-turn-agreement must be a fraction in [0, 1], "
                            f"not {self.anchor_turn_agreement}")
        if self.anchor_hold and self.anchor == "off":
            raise UserError("--anchor-hold needs an --anchor (it keeps the anchors' weight after the bootstrap)")
        if self.anchor_step < 0 or self.anchor_every < 0 or self.w_anchor < 0:
            raise UserError("--anchor-step, --anchor-every and --w-anchor must be >= 0")
        if not (self.anchor_every_growth >= 0 and math.isfinite(self.anchor_every_growth)):
            raise UserError(f"--anchor-every-growth must be a number >= 0, not {self.anchor_every_growth}")
        if self.anchor_every_growth and not self.anchor_every:
            raise UserError("--anchor-every-growth needs --anchor-every (it lets the rebuild interval grow)")
        if not (0 <= self.anchor_budget < 1):
            raise UserError(f"--anchor-budget must be a fraction of the run's time in [0, 1), not {self.anchor_budget}")
        if self.anchor_budget and not self.anchor_every:
            raise UserError("--anchor-budget needs --anchor-every (the shortest interval between builds)")
        if self.anchor_align_step is not None and self.anchor != "vo":
            raise UserError("--anchor-align-step needs --anchor vo (it refines the anchors' odometry)")
        if self.anchor_align_step is not None and self.anchor_align_step < 0:
            raise UserError(f"--anchor-align-step must be >= 0, not {self.anchor_align_step}")
        if self.anchor_bundle and self.anchor != "vo":
            raise UserError("--anchor-bundle needs --anchor vo (it refines the anchors' odometry)")
        if self.anchor_pnp_below and self.anchor != "vo":
            raise UserError("--anchor-pnp-below needs --anchor vo (it measures the anchors' odometry)")
        if self.anchor_pnp_below < 0:
            raise UserError(f"--anchor-pnp-below must be >= 0 tracks, not {self.anchor_pnp_below}")
        if self.anchor_track_width and self.anchor != "vo":
            raise UserError("--anchor-track-width needs --anchor vo (it is where the anchors' odometry tracks)")
        if self.anchor_track_width < 0:
            raise UserError(f"--anchor-track-width must be >= 0 pixels, not {self.anchor_track_width}")
        if self.anchor_bundle_scale and not self.anchor_bundle:
            raise UserError("--anchor-bundle-scale needs --anchor-bundle (it holds the adjusted path's scale)")
        if not (self.anchor_bundle_scale >= 0 and math.isfinite(self.anchor_bundle_scale)):
            raise UserError(f"--anchor-bundle-scale must be a number of frames >= 0, not {self.anchor_bundle_scale}")
        if self.anchor_bundle_scale_degree is not None:
            if not self.anchor_bundle:
                raise UserError("--anchor-bundle-scale-degree needs --anchor-bundle (it holds the adjusted path's scale)")
            if self.anchor_bundle_scale:
                raise UserError("--anchor-bundle-scale and --anchor-bundle-scale-degree are two ways to hold the "
                                "path's scale: give one")
            if self.anchor_bundle_scale_degree < 0:
                raise UserError(f"--anchor-bundle-scale-degree must be >= 0, not {self.anchor_bundle_scale_degree}")
        if self.anchor_combine < 1:
            raise UserError(f"--anchor-combine must be a number of builds >= 1, not {self.anchor_combine}")
        if self.anchor_combine > 1 and self.anchor != "vo":
            raise UserError("--anchor-combine needs --anchor vo (it combines the odometry's builds)")
        if self.anchor_stride < 0:
            raise UserError(f"--anchor-stride must be a number of frames >= 1, or 0 (by each sequence's "
                            f"length), not {self.anchor_stride}")
        if self.anchor_stride > 1 and self.anchor != "vo":
            raise UserError("--anchor-stride needs --anchor vo (it thins the odometry's frames)")
        if not (self.w_depth_scale >= 0 and math.isfinite(self.w_depth_scale)):
            raise UserError(f"--w-depth-scale must be a number >= 0, not {self.w_depth_scale}")
        if self.w_depth_scale and self.anchor != "vo":
            raise UserError("--w-depth-scale needs --anchor vo (it holds the depth's scale where the first "
                            "anchors were built)")
        if self.bootstrap_steps < 0 or self.bootstrap_fade_steps < 0 or self.w_bootstrap < 0:
            raise UserError("--bootstrap-steps, --bootstrap-fade-steps and --w-bootstrap must be >= 0")
        if not (self.w_direction >= 0 and math.isfinite(self.w_direction)):
            raise UserError(f"--w-direction must be a number >= 0, not {self.w_direction}")
        if self.w_direction and (self.bootstrap == "off" or not self.w_bootstrap):
            raise UserError("--w-direction needs a --bootstrap and --w-bootstrap > 0 (it holds the DSC's "
                            "translation directions to the bootstrap's, weighted and faded with that term)")
        if not 0.0 <= self.ema_decay < 1.0:  # NaN fails too
            raise UserError(f"--ema-decay must be in [0, 1), not {self.ema_decay}")
        if self.bootstrap_track_width < 0:
            raise UserError(f"--bootstrap-track-width must be >= 0 pixels, not {self.bootstrap_track_width}")
        if self.bootstrap_track_width and self.bootstrap != "essential":
            raise UserError("--bootstrap-track-width is for --bootstrap essential (it tracks that bootstrap's pairs)")

    @property
    def size(self) -> tuple[int, int]:
        """Network input (W, H): the augmentation's output size."""
        return self.augment.width, self.augment.height

    @property
    def epochs(self) -> int:
        return self.sampler.epochs

    @property
    def seed(self) -> int:
        """Seed of the initial weights as well as of the sampler's triplets and augmentation."""
        return self.sampler.seed

    def to_dict(self) -> dict[str, Any]:
        """The nested layout: one entry per section, then the trainer's own options."""
        return asdict(self)

    def values(self) -> dict[str, Any]:
        """Every option by its place: ``{"sampler.window": 20, ..., "batch_size": 6, ...}``."""
        out: dict[str, Any] = {}
        for name, value in self.to_dict().items():
            if name in SECTIONS:
                out.update({f"{name}.{k}": v for k, v in value.items()})
            else:
                out[name] = value
        return out

    @classmethod
    def values_of(cls, options: Mapping[str, Any], where: str = "") -> dict[str, Any]:
        """Options given by name -> values by place (see :meth:`values`), to layer with ``update``.

        Names are flat (a field of a section, or ``size`` for ``augment.width`` and ``height``: a
        flat name sets the field in every section that has one, e.g. ``use_dsc`` in method and
        model) or a section holding a mapping of its fields. Unknown names are a UserError
        (``where`` prefixes its message)."""
        out: dict[str, Any] = {}
        unknown: list[str] = []
        own = {f.name for f in dataclasses.fields(cls)} - set(SECTIONS)
        for name, value in options.items():
            if name in SECTIONS:
                if not isinstance(value, Mapping):
                    raise UserError(f"{where}{name} must be a mapping of its options, not {value!r}")
                fields = {f.name for f in dataclasses.fields(SECTIONS[name])}
                unknown += [f"{name}.{k}" for k in value if k not in fields]
                out.update({f"{name}.{k}": v for k, v in value.items() if k in fields})
            elif name == "size":
                try:
                    out["augment.width"], out["augment.height"] = value
                except (TypeError, ValueError):
                    raise UserError(f"{where}size must be [width, height], not {value!r}") from None
            elif name in own:
                out[name] = value
            elif name in _FLAT_FIELDS:
                out.update({f"{key}.{name}": value for key in _FLAT_FIELDS[name]})
            else:
                unknown.append(name)
        if unknown:
            raise UserError(f"{where}unknown option(s) {', '.join(sorted(unknown))}")
        return out

    @classmethod
    def from_values(cls, values: Mapping[str, Any]) -> TrainConfig:
        """The config with ``values`` (by place, see :meth:`values`) over the defaults."""
        sections: dict[str, dict[str, Any]] = {key: {} for key in SECTIONS}
        own: dict[str, Any] = {}
        for place, value in values.items():
            key, _, name = place.rpartition(".")
            if key and key not in SECTIONS:
                raise UserError(f"unknown option {place}")
            (sections[key] if key else own)[name] = value
        if "window_schedule" in sections["sampler"]:
            sections["sampler"]["window_schedule"] = _as_tuples(sections["sampler"]["window_schedule"])
        default = cls()
        built = {}
        for key, given in sections.items():
            try:
                built[key] = dataclasses.replace(getattr(default, key), **given)
            except ValueError as e:  # the method's checks of its option values
                raise UserError(str(e)) from None
        return cls(**built, **own)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> TrainConfig:
        """The config of options given by name (see :meth:`values_of`) over the defaults: a run's
        ``config.json`` ``train`` entry (nested, or flat as runs wrote before the sections), a
        checkpoint's, or options in code: ``TrainConfig.from_dict({"size": (128, 96)})``."""
        return cls.from_values(cls.values_of(d))


def _sections_by_field() -> dict[str, tuple[str, ...]]:
    out: dict[str, tuple[str, ...]] = {}
    for key, cls in SECTIONS.items():
        for f in dataclasses.fields(cls):
            out[f.name] = (*out.get(f.name, ()), key)
    return out


# The sections each flat field name goes to; those of more than one section are one option (set
# once, by its flat name: use_dsc, min_depth, max_depth in method and model).
_FLAT_FIELDS = _sections_by_field()
_SHARED_FIELDS = {name: keys for name, keys in _FLAT_FIELDS.items() if len(keys) > 1}


def _bootstrap_fraction(cfg: TrainConfig, step: int) -> float:
    """1 during the bootstrap, falling linearly to 0 over the fade after it; 0 without one."""
    if cfg.bootstrap == "off":
        return 0.0
    if step < cfg.bootstrap_steps:
        return 1.0
    done = step - cfg.bootstrap_steps
    return 0.0 if done >= cfg.bootstrap_fade_steps else 1.0 - done / cfg.bootstrap_fade_steps


def bootstrap_at(cfg: TrainConfig, step: int) -> tuple[bool, float]:
    """(warps use the bootstrap poses, weight of the consistency term) at ``step``."""
    return cfg.bootstrap != "off" and step < cfg.bootstrap_steps, cfg.w_bootstrap * _bootstrap_fraction(cfg, step)


def novel_view_at(cfg: TrainConfig, step: int) -> bool:
    """Whether L_nv is in the loss at ``step`` (its weight set, and before ``novel_view_steps``)."""
    m = cfg.method
    return m.w_novel_view > 0 and (m.novel_view_steps == 0 or step < m.novel_view_steps)


def anchor_at(cfg: TrainConfig, step: int) -> float:
    """Weight of the DSC-vs-anchor term at ``step`` (0 before ``anchor_step`` and without anchors;
    it fades out with the bootstrap unless ``anchor_hold``)."""
    if cfg.anchor == "off" or step < cfg.anchor_step:
        return 0.0
    return cfg.w_anchor * (1.0 if cfg.anchor_hold else _bootstrap_fraction(cfg, step))


def anchor_due(cfg: TrainConfig, step: int, built_at: int | None, next_at: int | None = None) -> bool:
    """Whether the anchors are (re)built before ``step`` (``built_at``: the step of the current ones;
    ``next_at``: the step the last build set for the next, :func:`anchor_interval`, if it did)."""
    if anchor_at(cfg, step) <= 0:
        return False
    if built_at is None:
        return True
    if cfg.anchor_every <= 0:
        return False
    return step >= (built_at + anchor_interval(cfg, built_at) if next_at is None else next_at)


def anchor_interval(cfg: TrainConfig, built_at: int, build_seconds: float | None = None,
                    step_seconds: float | None = None) -> int:
    """Steps from a build at step ``built_at`` to the next (with ``anchor_every``): at least
    ``anchor_every``, ``anchor_every_growth * built_at``, and with ``anchor_budget`` F as many as
    keep a build of ``build_seconds`` to F of the time, ``step_seconds`` a step (when both known)."""
    steps = max(cfg.anchor_every, math.floor(cfg.anchor_every_growth * built_at))
    if cfg.anchor_budget > 0 and build_seconds is not None and step_seconds:
        f = cfg.anchor_budget
        steps = max(steps, math.ceil(build_seconds * (1.0 - f) / (f * step_seconds)))
    return steps


# Fields a resumed run may change (how it runs, not what it learns); the rest come from the run.
RUN_CONTROL_FIELDS = ("workers", "device", "amp", "amp_dtype", "channels_last", "method.recompute_warps",
                      "max_steps", "max_minutes", "log_every", "checkpoint_every", "keep_last", "max_nonfinite",
                      "progress", "resume", "sampler.epochs", "ema_decay")


def resume_config(values: Mapping[str, Any]) -> TrainConfig:
    """The config that resumes a run with ``values`` (by place) asked for: their run controls over
    the defaults; pass ``values`` as ``given`` to :func:`train`. A resumed run keeps its own
    training options, so those asked for are not checked against each other (an option that needs
    another the run has, given alone, is no error), only named where the run keeps its own."""
    return TrainConfig.from_values({k: v for k, v in values.items() if k in RUN_CONTROL_FIELDS})


@dataclass
class RunState:
    """What changes as training runs (all of it goes into the checkpoint)."""

    step: int = 0
    epoch: int = 0
    position: int = 0  # triplets of `epoch` this rank has consumed
    nonfinite_skipped: int = 0
    nonfinite_streak: int = 0
    samples_skipped: int = 0
    last_checkpoint: str | None = None
    stop: str | None = None  # why the loop ended early
    timing: dict[str, float] = field(default_factory=dict)
    anchors: Any = None  # (N, 4, 4) float32 tensor: the DSC's anchors (TrainConfig.anchor), else None
    anchors_step: int | None = None  # the step they were built at (or a build was not used)
    anchors_next: int | None = None  # the step the next build is due at (None: from anchors_step)
    # the last builds as built, oldest first (TrainConfig.anchor_combine of them at most): (N, 4, 4) tensors
    anchor_builds: list = field(default_factory=list)
    # (N,) float32 tensor: each training frame's mean log depth at the first anchors' build, which
    # TrainConfig.w_depth_scale holds the depth's scale to (None: not yet, or not held)
    depth_ref: Any = None


@dataclass
class Trainer:
    """The objects the named steps share (built once by :func:`setup`)."""

    cfg: TrainConfig
    run_dir: Path
    dist: Dist
    device: Any
    frames: ImageFrames
    sampler: TripletSampler
    data: TripletData
    nets: Any  # relocdepth.models.Networks
    loss_module: Any  # the (DDP-wrapped) module whose forward returns triplet_loss(...)
    optimizer: Any
    scaler: Any
    log: TrainLog
    gt_poses: Any = None  # (N, 4, 4) float32 tensor of the research oracle, else None
    gt_depths: Any = None  # list of (H, W) float32 depth maps of the research oracle, else None
    ema: WeightAverage | None = None  # TrainConfig.ema_decay


# -- setup -----------------------------------------------------------------------------------------
class _LossModule:
    """Created lazily as an nn.Module subclass so that DDP wraps the loss computation (a DDP
    wrapper only synchronises gradients for work done through its own forward)."""

    @staticmethod
    def build(nets: Any, method_cfg: Any) -> Any:
        import torch

        from relocdepth.method import triplet_loss

        without_nv = dataclasses.replace(method_cfg, w_novel_view=0.0)  # past novel_view_steps

        class TripletLossModule(torch.nn.Module):
            def __init__(self) -> None:
                super().__init__()
                self.nets = nets

            def forward(self, images: Any, inputs: Any, K: Any, boot: Any = None, depth: Any = None,
                        novel_view: bool = True) -> Any:
                return triplet_loss(self.nets, images, inputs, K, method_cfg if novel_view else without_nv, boot, depth)

        return TripletLossModule()


# The bundle adjustment's iterations where --anchor-bundle-scale holds the scale over a window (the
# default 30 stop early, which is what keeps the scale without it: README, Quality, trial 34; the
# polynomial hold of --anchor-bundle-scale-degree keeps the 30, as 100 were no better offline).
ANCHOR_BUNDLE_ITERATIONS = 100


def _anchor_bundle_config(cfg: TrainConfig) -> Any:
    """The anchors' bundle adjustment: the defaults; its defaults with the scale held along the path
    by a polynomial (``anchor_bundle_scale_degree``); or run to convergence with the scale held over
    a window (``anchor_bundle_scale``)."""
    from relocdepth.ba import BAConfig

    if cfg.anchor_bundle_scale_degree is not None:
        return BAConfig(scale_degree=cfg.anchor_bundle_scale_degree)
    if cfg.anchor_bundle_scale:
        return BAConfig(max_iterations=ANCHOR_BUNDLE_ITERATIONS, scale_window=cfg.anchor_bundle_scale)
    return BAConfig()


def _resolve_config(cfg: TrainConfig, run_dir: Path,
                    given: Collection[str] | Mapping[str, Any] | None = None,
                    ) -> tuple[TrainConfig, dict | None, Path | None]:
    """The config to use and the checkpoint to resume (None when starting fresh).

    A resumed run keeps its own options but takes the run controls (:data:`RUN_CONTROL_FIELDS`)
    from ``cfg`` where ``given`` names them, so that one left out (the weights' average, the
    checkpoint interval, the step budget) keeps the run's. ``given``: the places (see
    :meth:`TrainConfig.values`) the caller set on purpose; None, those where ``cfg`` differs from
    the defaults; or a mapping of them to the values asked for, when these need not make a valid
    config on their own (see :func:`resume_config`). Given values the run keeps over are named in
    a warning."""
    latest = ckpt_io.latest_checkpoint(run_dir) if run_dir.exists() else None
    if not cfg.resume:
        if latest is not None:
            raise UserError(
                f"{run_dir} already holds checkpoints (latest {latest.name}); pass --resume to continue "
                "that run, or choose another -o"
            )
        return cfg, None, None
    if latest is None:
        raise UserError(f"nothing to resume: {run_dir} holds no checkpoint; drop --resume to start a run")
    ck = ckpt_io.load_checkpoint(latest)
    saved = TrainConfig.from_dict(ck["meta"]["train"])  # flat in checkpoints written before sections
    values, kept = cfg.values(), saved.values()
    if given is None:
        default = TrainConfig().values()
        given = [k for k in values if values[k] != default[k]]
    elif isinstance(given, Mapping):  # as asked (lists, from a config file, as the config's tuples)
        values = {**values, **{k: _as_tuples(v) for k, v in given.items()}}
    overrides = {k: values[k] for k in RUN_CONTROL_FIELDS if k in given or k == "resume"}
    ignored = [k for k in given if k not in overrides and k != "model.relpose" and values[k] != kept[k]]
    if ignored:
        log.warning("resuming %s: keeping the run's %s (given values ignored)", run_dir,
                    ", ".join(f"{k} = {kept[k]!r}" for k in ignored))
    return TrainConfig.from_values({**kept, **overrides}), ck, latest


def _research_ground_truth(shards: str | Path, frames: ImageFrames, kind: str, option: str) -> list[Any]:
    """RESEARCH ORACLES ONLY: the ground truth (``kind`` "pose" or "depth") of ``frames``, in their
    order. Training never reads ground truth otherwise (``ImageFrames`` holds none); the oracles
    measure what one half of the method learns when the other half is right. Refused (UserError,
    naming ``option``) on data without it."""
    from relocdepth.dataset import open_dataset
    from relocdepth.remote import local_dataset

    ds = open_dataset(local_dataset(shards))
    try:
        by_key = {r.key: r for r in ds.frames()}
        missing = [f.key for f in frames.frames if not getattr(by_key[f.key], f"has_{kind}")]
        if missing:
            raise UserError(f"{option} needs ground-truth {kind}s, and {len(missing)} training frames of {shards} "
                            f"have none (first: {missing[0]})")
        read = ds.read_pose if kind == "pose" else ds.read_depth
        return [read(by_key[f.key]) for f in frames.frames]
    finally:
        ds.close()


def research_gt_poses(shards: str | Path, frames: ImageFrames) -> np.ndarray:
    """The ground-truth poses ``(N, 4, 4)`` of ``frames`` for ``--bootstrap oracle-gt`` (what depth
    learns when the warps get true relative poses); see :func:`_research_ground_truth`."""
    return np.stack(_research_ground_truth(shards, frames, "pose", "--bootstrap oracle-gt")).astype(np.float32)


def research_gt_depths(shards: str | Path, frames: ImageFrames) -> list[np.ndarray]:
    """The ground-truth depth maps (metres, stored size) of ``frames`` for ``--oracle-gt-depth``, their
    invalid pixels filled with the frame's median; see :func:`_research_ground_truth`."""
    out = []
    for d in _research_ground_truth(shards, frames, "depth", "--oracle-gt-depth"):
        valid = d > 0
        out.append(np.where(valid, d, np.median(d[valid]) if valid.any() else 1.0).astype(np.float32))
    return out


def _oracle_depth_batch(gt: list[np.ndarray], index: Any, crop: Any, width: int, height: int) -> Any:
    """The triplets' ground-truth depth ``(B, 3, 1, H, W)``, resized and cropped as their images were
    (``crop`` rows: resized width, height, crop corner), nearest neighbour."""
    import cv2
    import torch

    out = np.empty((*index.shape, 1, height, width), np.float32)
    for b, i in np.ndindex(*index.shape):
        sw, sh, x0, y0 = (int(v) for v in crop[b, i])
        d = cv2.resize(gt[int(index[b, i])], (sw, sh), interpolation=cv2.INTER_NEAREST)
        out[b, i, 0] = d[y0:y0 + height, x0:x0 + width]
    return torch.from_numpy(out)


def setup(shards: str | Path, run_dir: Path, cfg: TrainConfig,
          given: Collection[str] | Mapping[str, Any] | None = None) -> tuple[Trainer, RunState]:
    import torch

    frames = ImageFrames.open(shards)  # user errors before anything is written
    cfg, ck, ck_path = _resolve_config(cfg, run_dir, given)
    gt_poses = None
    gt_depths = research_gt_depths(shards, frames) if cfg.oracle_gt_depth else None
    if gt_depths is not None:
        log.warning("RESEARCH ORACLE: ground-truth depth replaces the depth network's in poses and warps")
    if cfg.bootstrap == "oracle-gt":
        gt_poses = torch.from_numpy(research_gt_poses(shards, frames))
        log.warning("RESEARCH ORACLE: the warps of the first %d steps use ground-truth poses", cfg.bootstrap_steps)
    if ck is not None:
        ckpt_io.check_same_dataset(ck["meta"], frames.manifest_hash, ck_path)  # type: ignore[arg-type]
    parallax = _pair_parallax(frames, cfg) if cfg.sampler.min_parallax is not None else None
    dist, device = init_distributed(cfg.device)
    torch.manual_seed(cfg.seed)  # same initial weights on every rank
    random.seed(cfg.seed)
    np.random.seed(cfg.seed % 2**32)
    sampler = TripletSampler(frames.keys(), cfg.sampler, dist.rank, dist.world_size, parallax)
    data = TripletData(frames, cfg.augment, two_view=cfg.bootstrap == "essential", track_width=cfg.bootstrap_track_width)
    from relocdepth.models import build_networks

    nets = build_networks(cfg.model).to(device)
    if cfg.channels_last:
        nets = nets.to(memory_format=torch.channels_last)
    optimizer = _adam(nets, cfg)
    use_scaler = cfg.amp and cfg.amp_dtype == "fp16" and device.type == "cuda"
    scaler = torch.amp.GradScaler("cuda", enabled=use_scaler)
    state = RunState()
    if ck is not None:
        _restore(ck, nets, optimizer, scaler, state)
        log.info("resuming %s at step %d (epoch %d, triplet %d)", ck_path, state.step, state.epoch, state.position)
    ema = WeightAverage(nets, cfg.ema_decay) if cfg.ema_decay else None
    if ema is not None and ck is not None:
        if ck.get("ema"):
            ema.load_state_dict(ck["ema"])
        else:
            log.info("no weight average in %s: it starts from the weights of step %d", ck_path, state.step)
    loss_module = _LossModule.build(nets, cfg.method)
    if dist.enabled:
        from torch.nn.parallel import DistributedDataParallel as DDP

        # The bootstrap's two-frame network gets no gradient once the warps use the DSC poses.
        loss_module = DDP(loss_module, device_ids=[device.index] if device.type == "cuda" else None,
                          find_unused_parameters=cfg.bootstrap != "off")
    if dist.is_main:
        run_dir.mkdir(parents=True, exist_ok=True)
        write_json_atomic(run_dir / CONFIG_NAME, {
            "tool_version": relocdepth.__version__, "shards": str(shards), "world_size": dist.world_size,
            "train": cfg.to_dict(),
        }, sort_keys=True)
    total = _total_steps(sampler, cfg)
    tlog = TrainLog(run_dir if dist.is_main else None, cfg.progress and dist.is_main, total, state.step, cfg.epochs,
                    log_every=cfg.log_every, max_seconds=None if cfg.max_minutes is None else 60.0 * cfg.max_minutes)
    tr = Trainer(cfg, run_dir, dist, device, frames, sampler, data, nets, loss_module, optimizer, scaler,
                 tlog, gt_poses, gt_depths, ema)
    return tr, state


def _pair_parallax(frames: ImageFrames, cfg: TrainConfig) -> PairParallax:
    """The training frames' pair parallax in pixels at the training width (UserError if absent)."""
    from relocdepth.dataset import parallax_for_frames

    offsets, px = parallax_for_frames(frames.root, [(f.key, f.sequence, f.frame) for f in frames.frames])
    widths = np.array([f.intrinsics.width for f in frames.frames], dtype=np.float64)
    return PairParallax(offsets, px * (cfg.size[0] / widths)[:, None])


def _adam(nets: Any, cfg: TrainConfig) -> Any:
    """Adam per the paper; the fused kernel when this torch has it (4x faster steps on CPU)."""
    import torch

    try:
        return torch.optim.Adam(nets.parameters(), lr=cfg.lr, betas=(cfg.beta1, cfg.beta2), fused=True)
    except (RuntimeError, TypeError, ValueError):  # older torch / device without a fused Adam
        return torch.optim.Adam(nets.parameters(), lr=cfg.lr, betas=(cfg.beta1, cfg.beta2))


def _total_steps(sampler: TripletSampler, cfg: TrainConfig) -> int:
    total = 0
    for e in range(cfg.epochs):
        total += math.ceil(math.ceil(len(sampler.targets(e)) / sampler.world_size) / cfg.batch_size)
        if cfg.max_steps is not None and total >= cfg.max_steps:
            return cfg.max_steps
    return total


# -- checkpoint state ------------------------------------------------------------------------------
def _rng_state() -> dict[str, Any]:
    import torch

    name, keys, pos, has_gauss, cached = np.random.get_state()
    return {
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
        "numpy": [name, torch.from_numpy(keys.astype(np.int64)), int(pos), int(has_gauss), float(cached)],
        "python": random.getstate(),
    }


def _set_rng_state(s: dict[str, Any]) -> None:
    import torch

    torch.set_rng_state(s["torch"])
    if s["cuda"] and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(s["cuda"])
    name, keys, pos, has_gauss, cached = s["numpy"]
    np.random.set_state((name, keys.numpy().astype(np.uint32), pos, has_gauss, cached))
    v, internal, gauss = s["python"]
    random.setstate((v, tuple(internal), gauss))


def _restore(ck: dict[str, Any], nets: Any, optimizer: Any, scaler: Any, state: RunState) -> None:
    nets.load_state_dict(ck["model"])
    optimizer.load_state_dict(ck["optimizer"])
    if ck.get("scaler"):
        scaler.load_state_dict(ck["scaler"])
    meta = ck["meta"]
    state.step, state.epoch, state.position = meta["step"], meta["epoch"], meta["position"]
    counters = meta.get("counters", {})
    state.nonfinite_skipped = counters.get("nonfinite_skipped", 0)
    state.samples_skipped = counters.get("samples_skipped", 0)
    _set_rng_state(ck["rng"])
    if ck.get("anchors"):
        state.anchors, state.anchors_step = ck["anchors"]["T_wc"], int(ck["anchors"]["step"])
        state.anchor_builds = list(ck["anchors"].get("builds") or [state.anchors])
        state.anchors_next = ck["anchors"].get("next")
        state.depth_ref = ck["anchors"].get("depth_ref")


def checkpoint(tr: Trainer, state: RunState) -> None:
    """Named step: write a checkpoint of the current state (rank 0)."""
    if not tr.dist.is_main:
        return
    f0 = tr.frames.frames[0]
    W, H = tr.cfg.size
    meta = {
        "format": ckpt_io.FORMAT, "format_version": ckpt_io.FORMAT_VERSION,
        "tool_version": relocdepth.__version__,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "step": state.step, "epoch": state.epoch, "position": state.position,
        "manifest_hash": tr.frames.manifest_hash,
        "dataset": {"name": tr.frames.name, "root": tr.frames.root},
        "input_size": [W, H], "intrinsics": f0.intrinsics.scaled(W, H).to_dict(), "intrinsics_policy": "resize",
        "model": asdict(tr.cfg.model), "method": asdict(tr.cfg.method), "train": tr.cfg.to_dict(),
        "world_size": tr.dist.world_size,
        "counters": {"nonfinite_skipped": state.nonfinite_skipped, "samples_skipped": state.samples_skipped},
        "alignment": None,
    }
    path = ckpt_io.save_checkpoint(tr.run_dir, {
        "meta": meta, "model": tr.nets.state_dict(), "optimizer": tr.optimizer.state_dict(),
        "scaler": tr.scaler.state_dict() if tr.scaler.is_enabled() else None,
        "sampler": {"epoch": state.epoch, "position": state.position}, "rng": _rng_state(),
        "anchors": None if state.anchors is None else {"T_wc": state.anchors, "step": state.anchors_step,
                                                       "builds": state.anchor_builds,
                                                       "next": state.anchors_next,
                                                       "depth_ref": state.depth_ref},
        "ema": None if tr.ema is None else tr.ema.state_dict(),
    }, keep_last=tr.cfg.keep_last)
    state.last_checkpoint = str(path)
    tr.log.event("checkpoint", state.step, path=path.name)


# -- the named steps -------------------------------------------------------------------------------
def sample(tr: Trainer, state: RunState, batch: dict[str, Any]) -> dict[str, Any] | None:
    """Named step: account for unreadable frames and move the batch to the device as floats."""
    for key, err in batch["skipped"]:
        state.samples_skipped += 1
        log.warning("skipping an unreadable frame %s (%s); %d skipped so far", key, err, state.samples_skipped)
        tr.log.event("skipped_sample", state.step, key=key, error=err)
    if "images" not in batch:
        return None
    dev = tr.device
    nb = dev.type == "cuda"
    return {
        "images": batch["images"].to(dev, non_blocking=nb).float().div_(255.0),
        "inputs": batch["inputs"].to(dev, non_blocking=nb).float().div_(255.0),
        "K": batch["K"].to(dev, non_blocking=nb),
        "index": batch["index"],
        "crop": batch["crop"],
        **{k: batch[k].to(dev) for k in ("two_view_T", "two_view_points", "two_view_ok") if k in batch},
        "n": int(batch["images"].shape[0]),
        "global_frac": batch["global_frac"],
    }


def forward_losses(tr: Trainer, b: dict[str, Any], step: int = 0, anchors: Any = None,
                   depth_ref: Any = None) -> tuple[Any, dict[str, Any], dict[str, float]]:
    """Named step: both networks on the triplets, the paper's loss (plus the bootstrap's, while it
    lasts, with the DSC's ``anchors (N, 4, 4)`` when given, and the depth's scale held to the
    frames' ``depth_ref (N,)`` with ``TrainConfig.w_depth_scale``), its parts and diagnostics."""
    import torch

    from relocdepth.method import Bootstrap

    boot = None
    warps, w = bootstrap_at(tr.cfg, step)
    w_anchor = anchor_at(tr.cfg, step) if anchors is not None else 0.0
    if warps or w > 0 or w_anchor > 0:
        T_wc = None if tr.gt_poses is None else tr.gt_poses[b["index"]].to(tr.device)
        two_view = (b["two_view_T"], b["two_view_points"], b["two_view_ok"]) if "two_view_T" in b else None
        T_anchor = anchors[b["index"]].to(tr.device) if w_anchor > 0 else None
        held = depth_ref is not None and tr.cfg.w_depth_scale > 0
        boot = Bootstrap(warps, w, T_wc, two_view, T_anchor, w_anchor, tr.cfg.w_direction,
                         depth_ref[b["index"]].to(tr.device) if held else None, tr.cfg.w_depth_scale)
    depth = None
    if tr.gt_depths is not None:
        W, H = tr.cfg.size
        depth = _oracle_depth_batch(tr.gt_depths, b["index"].numpy(), b["crop"].numpy(), W, H).to(tr.device)
    dtype = torch.bfloat16 if tr.cfg.amp_dtype == "bf16" else torch.float16
    with torch.autocast(tr.device.type, dtype=dtype, enabled=tr.cfg.amp):
        return tr.loss_module(b["images"], b["inputs"], b["K"], boot, depth, novel_view_at(tr.cfg, step))


def build_anchors(tr: Trainer, state: RunState, step_seconds: float | None = None) -> float:
    """Named step: the DSC's anchors (``tr.cfg.anchor``) from the training frames with the current
    networks (every rank builds the same ones: same weights, same frames), and the step of the
    next build (``step_seconds``: the run's seconds a step outside the builds, None: not known
    yet; ``TrainConfig.anchor_budget``). Returns the build's seconds."""
    import torch

    from relocdepth import anchors as A
    from relocdepth.vo import VOConfig

    t0 = time.perf_counter()
    m = tr.cfg.method
    if tr.cfg.anchor == "linked":
        a = A.build_linked_anchors(tr.frames, lambda ims, K: A.network_poses(tr.nets, ims, K, tr.device),
                                   tr.cfg.size, turn=tr.cfg.anchor_turn,
                                   min_agreement=tr.cfg.anchor_turn_agreement)
        how = f"the DSC's own poses of {len(a.T_wc)} frames"
        if a.turn_deg is not None:
            how += (f", centres turned {a.turn_deg:.2f} deg to {a.turn_pairs} of {a.turn_measured} "
                    "measured directions")
        elif a.turn_measured:
            how += (f", centres not turned: {a.turn_pairs} of {a.turn_measured} measured directions agree "
                    f"(under {tr.cfg.anchor_turn_agreement:.0%})")
    else:
        align = tr.cfg.anchor_align_step is not None and state.step >= tr.cfg.anchor_align_step
        log_depth: dict[int, float] = {}  # each frame's mean log depth in this build

        def depth_of(ix: list[int], ims: list[Any]) -> list[Any]:
            maps = A.network_depth(tr.nets.depth, ims, tr.device, m.min_depth, m.max_depth)
            log_depth.update({i: float(np.log(d).mean()) for i, d in zip(ix, maps)})
            return maps

        a = A.build_anchors(tr.frames, depth_of, tr.cfg.size,
                            VOConfig(align=align, bundle=tr.cfg.anchor_bundle, pnp_below=tr.cfg.anchor_pnp_below,
                                     bundle_cfg=_anchor_bundle_config(tr.cfg)),
                            track_width=tr.cfg.anchor_track_width, stride=tr.cfg.anchor_stride)
        extra = "" if a.aligned is None else f", {a.aligned} frames aligned"
        if tr.cfg.anchor_pnp_below:
            extra += f", {a.pnp} by PnP"
        if a.bundled is not None:
            extra += ", bundle-adjusted: " + "; ".join(
                f"{b['tracks']} tracks, {b['start_px']:.2f} -> {b['final_px']:.2f} px"
                + (f", scale held along the path at {b['held'][0]:.2f}-{b['held'][1]:.2f}" if "held" in b else "")
                for b in a.bundled)
        size = "x".join(map(str, a.track_size))
        every = "" if a.odometry_frames == len(a.T_wc) else f" (run on {a.odometry_frames}, the rest interpolated)"
        how = f"odometry of {len(a.T_wc)} frames{every} at {size} ({a.keyframes} keyframes, {a.lost} lost{extra})"
    if a.unlinked:  # no consensus on where those sequences lie: such anchors would misplace them
        weak = ", ".join(f"{a.registration[k - 1][0]}/{a.registration[k - 1][1]}" for k in a.unlinked)
        log.warning("anchors at step %d not used: %d of %d sequences linked by fewer than %d agreeing links "
                    "(%s); %s", state.step, len(a.unlinked), len(a.registration) + 1, A.MIN_LINK_INLIERS,
                    weak, "no anchors yet" if state.anchors is None else "keeping the previous ones")
    used = not a.unlinked
    combined = 0  # builds the anchors were combined from (0: this one not used)
    state.anchors_step = state.step  # also when not used: the next try is one interval on
    took = time.perf_counter() - t0
    # every rank must build at the same steps: the longest interval any rank measured
    interval = int(max_over_ranks(tr.dist, [anchor_interval(tr.cfg, state.step, took, step_seconds)], tr.device)[0])
    state.anchors_next = state.step + interval if tr.cfg.anchor_every > 0 else None
    after = "" if state.anchors_next is None else f", next at step {state.anchors_next}"
    if used:
        k = tr.cfg.anchor_combine
        state.anchor_builds = ([*state.anchor_builds, torch.from_numpy(a.T_wc)])[-k:]
        if k > 1 and len(state.anchor_builds) == k:
            state.anchors = torch.from_numpy(A.combine_builds([b.numpy() for b in state.anchor_builds]))
            how += f", combined with the {k - 1} builds before"
            combined = k
        else:
            state.anchors = torch.from_numpy(a.T_wc)
            combined = 1
        if tr.cfg.w_depth_scale and state.depth_ref is None:  # the units of the first build used, for good
            state.depth_ref = torch.tensor([log_depth[i] for i in range(len(a.T_wc))], dtype=torch.float32)
            how += ", the depth's scale held from here"
        reg = ", ".join(f"{i}/{n}" for i, n in a.registration) or "one sequence"
        log.info("anchors at step %d: %s, registration inliers %s, %.1f s%s", state.step, how, reg, took, after)
    tr.log.event("anchors", state.step, keyframes=a.keyframes, lost=a.lost, seconds=round(took, 2),
                 registration=[list(r) for r in a.registration], turn_deg=a.turn_deg, turn_pairs=a.turn_pairs,
                 turn_measured=a.turn_measured, aligned=a.aligned, bundled=a.bundled, pnp=a.pnp,
                 track_size=None if a.track_size is None else list(a.track_size),
                 odometry_frames=a.odometry_frames, used=used,
                 combined=combined, next_step=state.anchors_next,
                 step_seconds=None if step_seconds is None else round(step_seconds, 3))
    return took


def optimizer_step(tr: Trainer, state: RunState, loss: Any) -> bool:
    """Named step: backward + Adam unless the loss is non-finite on any rank, or a gradient is
    non-finite (then skip, count)."""
    import torch

    nonfinite = any_rank(tr.dist, [not bool(torch.isfinite(loss.detach()).item())], tr.device)[0]
    tr.optimizer.zero_grad(set_to_none=True)
    if nonfinite:
        if tr.dist.enabled:  # every rank must join the gradient all-reduce; the result is dropped
            tr.scaler.scale(loss * 0.0).backward()
            tr.optimizer.zero_grad(set_to_none=True)
        state.nonfinite_skipped += 1
        state.nonfinite_streak += 1
        log.warning("non-finite loss at step %d: step skipped (%d in a row)", state.step, state.nonfinite_streak)
        tr.log.event("nonfinite_loss", state.step, streak=state.nonfinite_streak, loss=float(loss.detach()))
        return False
    tr.scaler.scale(loss).backward()
    # A finite loss can still have non-finite gradients (e.g. a 0/0 in a backward pass): those
    # must not reach the weights either. After DDP's all-reduce every rank sees the same gradients,
    # so every rank decides alike. (The fp16 GradScaler checks and skips on its own.)
    if not tr.scaler.is_enabled() and not _gradients_finite(tr.nets):
        tr.optimizer.zero_grad(set_to_none=True)
        state.nonfinite_skipped += 1
        state.nonfinite_streak += 1
        log.warning("non-finite gradient at step %d: step skipped (%d in a row)", state.step, state.nonfinite_streak)
        tr.log.event("nonfinite_gradient", state.step, streak=state.nonfinite_streak)
        return False
    tr.scaler.step(tr.optimizer)
    tr.scaler.update()
    if tr.ema is not None:
        tr.ema.update(tr.nets)
    state.nonfinite_streak = 0
    return True


def _gradients_finite(module: Any) -> bool:
    import torch

    grads = [p.grad for p in module.parameters() if p.grad is not None]
    # One NaN or Inf makes the sum non-finite; summing is ~15x cheaper than isfinite().all() per
    # tensor (measured: 9 vs 125 ms for both networks' 27 M gradients on one core), which matters
    # against a ~2 s CPU step.
    return not grads or bool(torch.isfinite(torch.stack([g.sum() for g in grads]).sum()))


def log_step(tr: Trainer, state: RunState, loss: Any, parts: dict[str, Any], diag: dict[str, float],
             rate: float, global_frac: float) -> None:
    """Named step: the JSONL/TensorBoard record (every ``log_every`` steps)."""
    tr.log.step({
        "step": state.step, "epoch": state.epoch, "loss": float(loss.detach()),
        "parts": {k: float(v.detach()) if hasattr(v, "detach") else float(v) for k, v in parts.items()},
        "diagnostics": {k: float(v) for k, v in diag.items()},
        "lr": tr.optimizer.param_groups[0]["lr"], "triplets_per_s": rate, "global_pair_frac": global_frac,
        "nonfinite_skipped": state.nonfinite_skipped, "samples_skipped": state.samples_skipped,
    })


def log_images(tr: Trainer, state: RunState, b: dict[str, Any]) -> None:
    """Named step: the first triplet's target, depth and DSC-warped source in TensorBoard."""
    from relocdepth.method import preview

    was_training = tr.nets.training
    try:
        view = preview(tr.nets, b["images"], b["inputs"], b["K"], tr.cfg.method)
    finally:
        tr.nets.train(was_training)
    tr.log.images(state.step, {f"train/{k}": v for k, v in view.items()})


# -- the loop --------------------------------------------------------------------------------------
class _StopRequest:
    """First Ctrl-C / SIGTERM asks to stop after the current step; a second one aborts."""

    def __init__(self) -> None:
        self.requested = False
        self._old: dict[int, Any] = {}

    def __enter__(self) -> _StopRequest:  # noqa: PYI034
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._old[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum: int, frame: Any) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        log.warning("stop requested: finishing this step and writing a checkpoint (again to abort)")

    def __exit__(self, *exc: object) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)


def _epoch_batches(tr: Trainer, state: RunState, stop: _StopRequest):
    """Yield this rank's batches of the current epoch from ``state.position``; on a stop request
    a dying worker's error ends the epoch quietly."""
    # The essential-matrix bootstrap's tracking runs in the loader only while the bootstrap is in
    # use (checked per epoch: the loader is made anew each epoch)
    tr.data.two_view = tr.cfg.bootstrap == "essential" and any(bootstrap_at(tr.cfg, state.step))
    loader = make_loader(tr.data, tr.sampler, state.epoch, state.position, tr.cfg.batch_size,
                         tr.cfg.workers, pin_memory=tr.device.type == "cuda")
    it = iter(loader)
    while True:
        try:
            yield next(it)
        except StopIteration:
            return
        except Exception:
            if stop.requested:
                return
            raise


def run_loop(tr: Trainer, state: RunState, stop: _StopRequest) -> None:
    cfg = tr.cfg
    last_t, last_n = time.perf_counter(), 0
    started, started_step, building = last_t, state.step, 0.0  # the steps' time, builds apart
    deadline = None if cfg.max_minutes is None else last_t + 60.0 * cfg.max_minutes
    rate: float | None = None
    while state.epoch < cfg.epochs:
        if cfg.max_steps is not None and state.step >= cfg.max_steps:
            state.stop = "max_steps"
            return
        if state.position >= tr.sampler.epoch_length(state.epoch):
            state.epoch, state.position = state.epoch + 1, 0
            continue
        for raw in _epoch_batches(tr, state, stop):
            b = sample(tr, state, raw)
            no_data, stopping = any_rank(tr.dist, [b is None, stop.requested], tr.device)
            if stopping:
                state.stop = "interrupted"
                return
            if no_data:
                tr.log.event("empty_batch", state.step)
            else:
                if anchor_due(cfg, state.step, state.anchors_step, state.anchors_next):
                    done = state.step - started_step
                    per_step = (time.perf_counter() - started - building) / done if done else None
                    building += build_anchors(tr, state, per_step)
                loss, parts, diag = forward_losses(tr, b, state.step, state.anchors, state.depth_ref)
                stepped = optimizer_step(tr, state, loss)
                if not stepped and state.nonfinite_streak >= cfg.max_nonfinite:
                    state.stop = "diverged"
                    return
                last_n += b["n"]
            state.step += 1
            state.position += raw["attempted"]
            now = time.perf_counter()
            if now - last_t > 0.5 or rate is None:
                rate = last_n * tr.dist.world_size / max(now - last_t, 1e-9)
                last_t, last_n = now, 0
            cur_loss = None if no_data else float(loss.detach())
            if not no_data and (state.step % cfg.log_every == 0 or state.step == 1):
                log_step(tr, state, loss, parts, diag, rate, b["global_frac"])
            if not no_data and tr.log.wants_images(state.step):
                log_images(tr, state, b)
            tr.log.tick(state.step, state.epoch, cur_loss, rate)
            if state.step % cfg.checkpoint_every == 0:
                checkpoint(tr, state)
            if cfg.max_steps is not None and state.step >= cfg.max_steps:
                state.stop = "max_steps"
                return
            # every rank stops at the same step
            if deadline is not None and any_rank(tr.dist, [time.perf_counter() >= deadline], tr.device)[0]:
                state.stop = "max_minutes"
                return
        if state.position >= tr.sampler.epoch_length(state.epoch):
            state.epoch, state.position = state.epoch + 1, 0
    state.stop = "epochs"


def train(shards: str | Path, run_dir: str | Path, cfg: TrainConfig = TrainConfig(),
          given: Collection[str] | Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Train on ``shards`` into ``run_dir``; returns a summary (steps, stop reason, checkpoint...).

    ``given``: the options (places, see :meth:`TrainConfig.values`) set on purpose, e.g. those typed
    on the command line, or a mapping of them to their values (see :func:`resume_config`); a
    resumed run keeps its own values of the others (None: the options where ``cfg`` differs from
    the defaults count as given).

    Raises :class:`UserError` for bad inputs and :class:`TrainingDiverged` when the loss diverges
    (``max_nonfinite`` non-finite losses in a row; the last good checkpoint stays the newest).
    """
    run_dir = Path(run_dir)
    tr, state = setup(shards, run_dir, cfg, given)
    start_step = state.step
    tr.log.event("resume" if tr.cfg.resume else "start", state.step, world_size=tr.dist.world_size,
                 device=str(tr.device), pretrained=tr.cfg.model.pretrained)
    t0 = time.perf_counter()
    try:
        # The final checkpoint is written inside the handler too, so that a second Ctrl-C aborts it
        # even where the process started with SIGINT ignored (a background job of a script).
        with _StopRequest() as stop:
            run_loop(tr, state, stop)
            broadcast_buffers(tr.dist, tr.nets)  # every rank ends with the checkpoint's BatchNorm statistics
            if state.stop != "diverged" and (state.last_checkpoint is None or state.step % tr.cfg.checkpoint_every):
                checkpoint(tr, state)
        tr.log.event("stop", state.step, reason=state.stop)
    finally:
        tr.log.close()
        digest = parameter_digest(tr.nets)
        log.info("rank %d: final parameters sha256 %s", tr.dist.rank, digest)
        shutdown_distributed(tr.dist)
    latest = ckpt_io.latest_checkpoint(run_dir) if tr.dist.is_main else None
    if state.stop == "diverged":
        raise TrainingDiverged(
            f"training diverged: {state.nonfinite_streak} non-finite losses in a row at step {state.step}; "
            f"the last good checkpoint is {latest or 'none'}; try a lower --lr"
        )
    elapsed = time.perf_counter() - t0
    return {
        "run_dir": str(run_dir), "steps": state.step, "steps_this_run": state.step - start_step,
        "epoch": state.epoch, "position": state.position, "stop": state.stop,
        "checkpoint": str(latest) if latest else None, "seconds": round(elapsed, 2),
        "nonfinite_skipped": state.nonfinite_skipped, "samples_skipped": state.samples_skipped,
        "param_digest": digest, "rank": tr.dist.rank, "world_size": tr.dist.world_size,
    }
