"""`reloc train`: train the depth + DSC networks on a shard dataset (maps options onto TrainConfig)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer
from relocdepth.cli.common import (
    DEVICE_DEFAULT,
    DEVICE_HELP,
    DEVICE_METAVAR,
    parse_device,
    parse_size,
    user_errors,
)
from relocdepth.cli.main import app

from relocdepth.errors import EXIT_INTERRUPTED, UserError


def _schedule(text: str | None) -> tuple[tuple[int, int], ...]:
    if not text:
        return ()
    try:
        return tuple((int(e), int(w)) for e, w in (item.split(":") for item in text.split(",")))
    except ValueError:
        raise UserError(f"--window-schedule must look like 0:3,50:10,100:20, not {text!r}") from None


def _pixels(text: str) -> str:
    from relocdepth.method import PHOTOMETRIC_PIXELS

    if text not in PHOTOMETRIC_PIXELS:
        raise UserError(f"--photometric-pixels must be one of {', '.join(PHOTOMETRIC_PIXELS)}, not {text!r}")
    return text


def _degree(text: str | None) -> int | None:
    if text is None or text.lower() == "none":
        return None
    try:
        return int(text)
    except ValueError:
        raise UserError(f"--anchor-bundle-scale-degree must be a whole number or none, not {text!r}") from None


def _loss_resolution(text: str) -> str:
    from relocdepth.method import LOSS_RESOLUTIONS

    if text not in LOSS_RESOLUTIONS:
        raise UserError(f"--loss-resolution must be one of {', '.join(LOSS_RESOLUTIONS)}, not {text!r}")
    return text


# Options that are not training options, and those whose option has another name or type.
_NOT_FIELDS = ("ctx", "shards", "out", "recipe", "config")
_CONVERT = {
    "size": ("size", parse_size),
    "window_schedule": ("window_schedule", _schedule),
    "photometric_pixels": ("photometric_pixels", _pixels),
    "no_lcvs": ("lcvs", lambda v: not v),
    "no_dsc": ("use_dsc", lambda v: not v),
    "pretrained": ("pretrained", lambda v: None if v is None or v.lower() == "none" else v),
    "device": ("device", parse_device),
    "loss_resolution": ("loss_resolution", _loss_resolution),
    "anchor_bundle_scale_degree": ("anchor_bundle_scale_degree", _degree),
}


def _given_fields(ctx: typer.Context, values: dict[str, Any]) -> dict[str, Any]:
    """Training options (by name, see TrainConfig.values_of) given on the command line (not left at
    their default)."""
    out = {}
    for name, value in values.items():
        source = ctx.get_parameter_source(name)  # a ParameterSource (click's, or typer's vendored one)
        if name in _NOT_FIELDS or source is None or source.name == "DEFAULT":
            continue
        field, convert = _CONVERT.get(name, (name, lambda v: v))
        out[field] = convert(value)
    return out


@app.command()
@user_errors
def train(
    ctx: typer.Context,
    shards: Annotated[str, typer.Argument(help="Dataset folder written by `reloc ingest` (trains on its train split), or its URL (http(s)://, file://, s3:// ...: fetched once into ~/.cache/relocdepth).")],
    out: Annotated[Path, typer.Option("-o", "--out", help="Run folder: config.json, logs/, checkpoints/.")] = Path("runs/default"),
    recipe: Annotated[str, typer.Option(help="Named recipe: paper (the defaults), paper-bootstrap, cpu, cpu-bootstrap, cpu-posenet, cpu-anchored, cpu-anchored-views, cpu-linked, demo (README, Training). Options given here override it.")] = "paper",
    config: Annotated[Path | None, typer.Option("--config", help="YAML/JSON file of training options, or a run's config.json (repeats that run). Applied over --recipe; options given here override it.")] = None,
    epochs: Annotated[int, typer.Option(help="Epochs; one epoch = every training frame once as a target (paper: 300).")] = 300,
    batch_size: Annotated[int, typer.Option("--batch-size", help="Triplets per step and per process (paper: 6).")] = 6,
    size: Annotated[str, typer.Option(help="Network input WxH, multiples of 32 (paper: 640x480).")] = "640x480",
    lr: Annotated[float, typer.Option(help="Adam learning rate (paper: 1e-4, betas 0.9/0.999).")] = 1e-4,
    workers: Annotated[int, typer.Option(help="DataLoader worker processes decoding frames (0: in the training process).")] = 2,
    device: Annotated[str, typer.Option(metavar=DEVICE_METAVAR, help=DEVICE_HELP)] = DEVICE_DEFAULT,
    amp: Annotated[bool, typer.Option("--amp", help="Mixed precision (autocast) on CUDA or CPU.")] = False,
    amp_dtype: Annotated[str, typer.Option("--amp-dtype", help="Autocast type with --amp: bf16 or fp16 (loss scaling).")] = "bf16",
    channels_last: Annotated[bool, typer.Option("--channels-last", help="channels_last memory format (CUDA).")] = False,
    max_steps: Annotated[int | None, typer.Option("--max-steps", help="Stop after this many steps in all (a checkpoint is written).")] = None,
    max_minutes: Annotated[float | None, typer.Option("--max-minutes", help="Stop after this many minutes of training in this process (a checkpoint is written).")] = None,
    resume: Annotated[bool, typer.Option("--resume", help="Continue the run in -o from its latest checkpoint, exactly, with its own training options: of the options given with it, only how the run runs applies (workers, device, AMP, steps, minutes, epochs, logging, checkpoints, progress, --ema-decay); others are kept at the run's values, with a warning naming them; options not given keep the run's values.")] = False,
    no_lcvs: Annotated[bool, typer.Option("--no-lcvs", help="Ablation w/o LCVS: 2 pairs into the middle frame.")] = False,
    no_dsc: Annotated[bool, typer.Option("--no-dsc", help="Ablation w/o DSC: absolute pose regression head.")] = False,
    pretrained: Annotated[str, typer.Option(help="Encoder start: imagenet, a torchvision resnet18 .pth, or none.")] = "imagenet",
    seed: Annotated[int, typer.Option(help="Seed of weights, triplet order and augmentation.")] = 0,
    window: Annotated[int, typer.Option(help="Nearby frames lie within +-N frame indices of the target (paper: 20).")] = 20,
    window_seconds: Annotated[float | None, typer.Option("--window-seconds", help="Window in seconds from timestamps instead (30 fps: 20 frames = 0.667).")] = None,
    window_schedule: Annotated[str | None, typer.Option("--window-schedule", help="Window by epoch, e.g. 0:3,50:20 (default: --window throughout).")] = None,
    global_epochs: Annotated[int, typer.Option("--global-epochs", help="Last N epochs use global pairs (paper: 100).")] = 100,
    min_parallax: Annotated[float | None, typer.Option("--min-parallax", metavar="PX", help="Draw nearby sources among frames whose pair parallax to the target (motion rotation cannot explain, px at --size; estimated at ingest) is >= PX, else the two with the most. Needs the dataset's pair parallax (reloc inspect SHARDS --add-parallax). Default: the paper's uniform draw.")] = None,
    global_prob: Annotated[float, typer.Option("--global-prob", help="Probability of a global pair then (paper: 0.5).")] = 0.5,
    jitter_per_image: Annotated[bool, typer.Option("--jitter-per-image", help="Independent colour jitter per image (default: one draw per triplet).")] = False,
    scale_max: Annotated[float, typer.Option("--scale-max", help="Scale augmentation upper bound (paper: 1.1; 1 = off).")] = 1.1,
    photometric_pixels: Annotated[str, typer.Option("--photometric-pixels", help="L_p averages over 'valid' pixels (in the source image; paper) or 'all' (monodepth2, border padding: cannot be gamed by warping off-image).")] = "valid",
    recompute_warps: Annotated[bool, typer.Option("--recompute-warps", help="Recompute the warps and SSIM in the backward pass: same gradients, much less memory (640x480 batch 6 on a 24 GB CPU machine), ~10-20% more time.")] = False,
    bootstrap: Annotated[str, typer.Option(help="Relative-pose bootstrap (not the paper's): off; posenet (a two-frame pose network, trained by the same photometric loss, drives the warps while the DSC network learns its relative poses); essential (essential matrix of point tracks between the frames, translation scaled by the current depth); oracle-gt (RESEARCH ONLY: ground-truth poses drive the warps; refused on data without poses).")] = "off",
    oracle_gt_depth: Annotated[bool, typer.Option("--oracle-gt-depth", help="RESEARCH ONLY: the dataset's ground-truth depth replaces the depth network's in the poses and warps (the pose half learns alone); refused on data without depth.")] = False,
    bootstrap_steps: Annotated[int, typer.Option("--bootstrap-steps", help="Steps during which the bootstrap's poses drive the warps; then the DSC poses do (the paper's loss).")] = 0,
    bootstrap_fade_steps: Annotated[int, typer.Option("--bootstrap-fade-steps", help="Steps over which the DSC-vs-bootstrap consistency term fades to 0 after the hand-over.")] = 500,
    w_bootstrap: Annotated[float, typer.Option("--w-bootstrap", help="Weight of the DSC-vs-bootstrap relative-pose consistency term.")] = 1.0,
    w_depth_consistency: Annotated[float, typer.Option("--w-depth-consistency", metavar="WEIGHT", help="Weight of L_g, the disagreement of each warped pair's depths: the target's depth carried into the source camera against the source's own depth there, |z - D_s| / (z + D_s) (SC-SfMLearner's geometry consistency; not the paper's). It ties the frames' depth scales to each other directly, where L_p ties them only through the parallax they explain. Measured on a real walk-through from random init: it did not hold the depth's scale along the walk, and at 0.5 depth was worse. 0: off.")] = 0.0,
    w_novel_view: Annotated[float, typer.Option("--w-novel-view", metavar="WEIGHT", help="Weight of L_nv (not the paper's): each triplet's middle frame is also seen from a camera moved back along its optical axis by up to --novel-view-back times its median depth, synthesised from its image and the depth network's depth; the depth network is held to that view's depth and the DSC network's pose of it to the frame's own pose moved back (targets detached). It shows the networks views farther from the scene than the training frames, which they otherwise place at the training frames' distances. Measured: on the demo scene (test views farther back than its training frames) rung 3 from step 400-500 on two seeds at 0.5 and at 0.1, where without it rung 2; on a real walk-through (test views among the training ones) at 0.1 as without it to step 1200 on one seed (0.087-0.093 m at 900-1200) but 1-3 cm behind from step 1150 on two more, which stayed short of rung 3 to step 1500 (0.094-0.111 m; see --novel-view-steps); at 0.03 the demo kept part of the gain (rung 3 from step 700 on one seed of two) and the walk-through lost as much (0.089-0.112 m from step 1000); before the new views' passes left the BatchNorm statistics alone it cost 0.01-0.016 m; with --novel-view-depth-only 0.18-0.21 m against 0.10-0.16. A step ~1.2x. 0: off.")] = 0.0,
    novel_view_back: Annotated[float, typer.Option("--novel-view-back", metavar="FRACTION", help="With --w-novel-view: the most the new views move back, as a fraction of the frame's median depth, in (0, 1]; the views are drawn uniformly up to it. Measured at 0.1 (--w-novel-view 0.1 --novel-view-depth-only --w-depth-scale 1.0, seed 0): the demo scene at rung 3 at every checkpoint from step 1000 (0.196-0.208 m; at 0.2 from step 400) and the real walk-through closer than without the term early (0.082-0.096 m at steps 700-900) and at rung 3 at steps 1100 and 1800-1900, its late checkpoints following its anchors' builds (at 0.2: rung 2 to step 1500).")] = 0.2,
    novel_view_forward: Annotated[float, typer.Option("--novel-view-forward", metavar="FRACTION", help="With --w-novel-view: let the new views move forward too, by up to this fraction of the frame's median depth, in [0, 0.5]: the move is drawn uniformly from FRACTION forward to --novel-view-back back, so with the two equal the new views are on average where the training frames stand. Measured at 0.2 with --w-novel-view 0.1 (one seed each): the demo scene kept the absolute gain (0.187-0.202 m from step 700, rung 3 at 3 of 7 checkpoints, the others held back by the relative translation, 0.0356-0.0383 m against the bar's 0.0356); the walk-through's test cameras still stood 1-3 cm behind the true ones, seed 0 at 0.083-0.097 m from step 1050 (rung 3 at 2 of 8 checkpoints), seed 3 at 0.112-0.133 m from 1150 to 1700: no better than back only. 0: back only (the default).")] = 0.0,
    novel_view_pose: Annotated[bool, typer.Option("--novel-view-pose/--novel-view-depth-only", help="With --w-novel-view: hold the DSC network's pose of the new views too (the default), or only the depth network's depth of them (then no DSC network is needed and each step skips one DSC pass). Measured at weight 0.1: on the demo scene 0.19-0.22 m from step 400, a little above the default's 0.175-0.21 and only just below the retrieval baseline's 0.211; on the real walk-through worse than the default. With --w-depth-scale 1.0: on the demo scene rung 3 at every checkpoint from step 400 to 1600 on seed 0 and at 10 of 12 from 500 on seed 1; on the walk-through 0.089-0.109 m from step 900 (rung 2), as the default with the scale held, its depth worse (AbsRel 0.149-0.154 against 0.128-0.136).")] = True,
    novel_view_one_way: Annotated[bool, typer.Option("--novel-view-one-way/--novel-view-both-ways", help="With --w-novel-view: the depth term teaches the new view from the frame and not the frame from the new view: the frame's depth takes its gradient only through its scale (mean log over the pixels the new view shows), which keeps the term unchanged by a scale of all depths, and not through its shape, which the paper's terms alone then teach. The term's value is the same. Measured at --w-novel-view 0.1 with --novel-view-depth-only and --w-depth-scale 1.0 (seed 0 each): the demo scene at rung 3 at 9 of 14 checkpoints from step 300 (0.193-0.218 m; both ways 13 of 13), the real walk-through at retrieval's translation at steps 1350-1500 (0.084-0.087 m) with its rotation above retrieval's (3.0-3.5 deg) and depth AbsRel 0.157-0.165 (both ways 0.149-0.154): no better. Default: both ways.")] = False,
    novel_view_decoder_only: Annotated[bool, typer.Option("--novel-view-decoder-only/--novel-view-whole-network", help="With --w-novel-view: the new views teach the depth network's decoder alone; its encoder runs on them without gradient, so that its features of real images are shaped by real images only (the frames' own depth still takes the term's pull). Measured at --w-novel-view 0.1 with --novel-view-depth-only and --w-depth-scale 1.0 (seed 0): the decoder fitted the new views, but the demo scene's real farther views kept most of their depth shortfall (8-10 % shorter than the training frames', whole network 4-9 %) and it stayed at rung 2 (0.216-0.225 m from step 400 to 900, whole network 0.191-0.210 at rung 3); the real walk-through was 0.202 m at step 500 (whole network 0.126). Default: the whole network.")] = False,
    novel_view_steps: Annotated[int, typer.Option("--novel-view-steps", metavar="N", help="With --w-novel-view: the term in the first N steps only, then left out of the loss (the run's own steps: a run resumed past N goes on without it). Measured by continuing runs without the term (one seed each): the demo scene, stopped at step 600, at 0.190-0.202 m to step 1100 (0.174-0.192 with the term, 0.225-0.239 without it ever) and back at the retrieval baseline's 0.211 m by 1200-1400, stopped at step 1000 back there within 400 steps; the walk-through (seed 3), stopped at step 1000, at rung 3 at 1300-1450 (0.077-0.086 m), where with the term to the end it stayed at 0.094-0.11 m, but stopped at step 600, at 0.093-0.109 m to 1400 and 0.14 m after, with worse anchors. 0: every step (the default).")] = 0,
    w_direction: Annotated[float, typer.Option("--w-direction", help="Weight (times --w-bootstrap's) of the angle between the DSC's and the bootstrap's translation directions of the pairs whose translation it measured (0: none). The consistency term counts a translation by the image motion it causes, which leaves its direction nearly free; the direction keeps the orientations and positions in one world.")] = 0.0,
    bootstrap_track_width: Annotated[int, typer.Option("--bootstrap-track-width", metavar="PX", help="--bootstrap essential: track the pairs on the stored images down-sized to at most PX wide (0: on the training images; so too where that is no wider than the crop). Finer tracks, finer poses: on a real walk-through at 192x128, a pair's translation error falls from 26 to 17 % of its length when tracked at the stored 540x360; costs loader time.")] = 0,
    anchor: Annotated[str, typer.Option(help="Absolute anchors for the DSC network (not the paper's; needs --bootstrap): off; vo (at --anchor-step, keyframe odometry of every training sequence with the depth network's depth, registered into one world); linked (the DSC network's own poses, every sequence after the first registered into the first one's world by SIFT links between similar frames, matched on the stored images resized to 640 px wide). A build where fewer than 3 links agree on where a sequence lies is not used. Each DSC cell's pose is pulled towards its frame's pose there while the bootstrap lasts (for the whole run with --anchor-hold).")] = "off",
    anchor_turn: Annotated[bool, typer.Option("--anchor-turn/--no-anchor-turn", help="--anchor linked: turn the anchors' camera centres (about their mean) so that the displacements between frames 4-10 apart point where the frames' orientations and the pairs' two-view directions (the essential bootstrap's geometry) say: the network's positions and orientations in one world.")] = True,
    anchor_turn_agreement: Annotated[float, typer.Option("--anchor-turn-agreement", metavar="FRACTION", help="--anchor-turn: turn only when at least this fraction of the measured directions agree with the fitted turn (within 30 deg); below it the build keeps the network's own centres and logs the agreement. Early in training the network's directions are noise, and so is their turn.")] = 0.65,
    anchor_step: Annotated[int, typer.Option("--anchor-step", help="Step at which the anchors are built (the depth network must have learned by then).")] = 150,
    anchor_every: Annotated[int, typer.Option("--anchor-every", help="Rebuild the anchors every N steps with the depth network of the time (0: build once).")] = 0,
    anchor_every_growth: Annotated[float, typer.Option("--anchor-every-growth", metavar="G", help="With --anchor-every: let the rebuild interval grow with the run; after a build at step S the next comes max(--anchor-every, G*S) steps on. Builds stay dense early, while the network changes fast, and their number grows with the logarithm of the steps instead of with the steps, so that a scene with many frames (a build's cost grows with them) does not spend most of its time building. 0: every --anchor-every steps (the default).")] = 0.0,
    anchor_budget: Annotated[float, typer.Option("--anchor-budget", metavar="FRACTION", help="With --anchor-every: let the rebuild interval follow the builds' cost; after a build that took B seconds the next comes at least B*(1-F)/(F*s) steps on, s the run's mean seconds a step outside the builds, so that the builds take at most the fraction F of the run's time whatever the scene's frames make them cost (a build's cost grows faster than the frames). Measured on this machine at each build and kept in the checkpoint (a resumed run builds where the run said it would). With --anchor-every and --anchor-every-growth, the longest of the three intervals. Measured at 0.1 (--recipe cpu-anchored-views): the real walk-through's builds (3-9 s) stayed every 50 steps, 1.9 % of its time; the demo scene's (26-43 s) came 85-134 steps apart, 8.8 % of its time against 18 % every 50, at rung 3 from step 400 as before; four generated sequences of 500 frames got their second build 1555 steps after the first (399 s). On an accelerator a step costs far less and a build about as much (most of it runs on the CPU): there a larger fraction keeps the builds coming. 0: off (the default).")] = 0.0,
    w_anchor: Annotated[float, typer.Option("--w-anchor", help="Weight of the DSC-vs-anchor term (fades out with the bootstrap, unless --anchor-hold). Measured at 3 with cpu-anchored --w-novel-view 0.1 --novel-view-depth-only --w-depth-scale 1.0 (seed 0): the DSC network fitted its anchors sooner on the real walk-through (its training cameras 0.060-0.080 m off from step 800, at 1 0.070-0.086 from 900) but the anchors built from the depth came out worse (0.076-0.130 m) and its rotation too (2.9-4.1 deg against 2.4-2.7); the demo scene stayed at rung 3 at 9 of 13 checkpoints, its relative translation at rung 1's bar.")] = 1.0,
    anchor_align_step: Annotated[int | None, typer.Option("--anchor-align-step", help="--anchor vo: builds from this step on refine the odometry by aligning each frame to the previous one pixel by pixel with the depth network's depth (default: never). Worth it once depth has learned: on a real walk-through the odometry's error fell 8-22 % with depth at AbsRel 0.16-0.19 and rose 29 % at AbsRel 0.25; costs ~0.07 s a frame a build.")] = None,
    anchor_bundle: Annotated[bool, typer.Option("--anchor-bundle/--no-anchor-bundle", help="--anchor vo: refine each build's odometry by bundle adjustment over tracks that last several frames (all poses and points fitted at once). On a real walk-through its error fell from 0.22-0.25 m to 0.14-0.15 m with the depth network's depth; a few seconds a build for 60 frames at 192x128.")] = False,
    anchor_pnp_below: Annotated[int, typer.Option("--anchor-pnp-below", metavar="N", help="--anchor vo: a pair of frames that KLT tracks at fewer than N points (a fast turn) is measured by PnP on SIFT and KLT matches lifted by the depth network's depth, not by the essential matrix of its tracks (0: never). On a real walk-through at 192x128 a 19 deg turn kept 14 tracks and its essential matrix was 7 deg off; PnP brought the bundle-adjusted odometry's error from 0.173 to 0.098 m with the true depth.")] = 0,
    anchor_track_width: Annotated[int, typer.Option("--anchor-track-width", metavar="PX", help="--anchor vo: the odometry tracks the stored images down-sized to at most PX wide, with the depth network's depth upsampled to them (0: the training images; so too where that is no wider). On a real walk-through its error was 0.166 m at 540x360 against 0.237 m at 192x128 with the true depth, and 0-11 % lower with the network's.")] = 0,
    anchor_bundle_scale: Annotated[float, typer.Option("--anchor-bundle-scale", metavar="FRAMES", help="With --anchor-bundle: run the adjustment to convergence (100 iterations, not 30) and hold the path's scale to the depth network's depth frame by frame, smoothed over FRAMES frames (0: one scale for the path). The tracks alone leave the scale along a path without loops free. On 14 checkpoints of a real walk-through run (offline), FRAMES 10: builds 0.064-0.176 m against 0.072-0.231 without, closer at 10 of 14.")] = 0.0,
    anchor_bundle_scale_degree: Annotated[str | None, typer.Option("--anchor-bundle-scale-degree", metavar="DEGREE", help="With --anchor-bundle, instead of --anchor-bundle-scale: hold the adjusted path's scale to the depth network's by a polynomial of DEGREE along the path (1: a steady drift), fitted to the network's scale in each frame. The network's scale errs in stretches of several frames, which a window averages in and a low-order fit passes through. Offline on a real walk-through, DEGREE 1: closer than without at 9 of 10 checkpoints to step 600 on one seed and 12 of 12 to step 700 on another (means 0.095 and 0.097 m against 0.133 and 0.138), but farther at all 6 of the first seed's from step 650, where its depth network had a scale drift of its own along the walk; that drift grows as the depth learns, and with the new views of --novel-view-back 0.1 the builds were farther at 14 of 14 checkpoints from step 350 on a third seed (mean 0.105 m against 0.077). Trained from random init: rung 3 from step 1100 on the second seed (7 of 8 checkpoints), rung 2 on the first; with --anchor-combine 3, rung 3 on four seeds of four. Off by default (none: off, also over a recipe's); 1 in --recipe cpu-anchored.")] = None,
    anchor_combine: Annotated[int, typer.Option("--anchor-combine", metavar="N", help="--anchor vo: the anchors are the last N builds combined: per frame the median of its centres and the mean of its orientations, the older builds scaled into the newest one's units. A build that has gone astray is outvoted where the other two agree; until there are N builds, the newest alone. On a real walk-through from random init, N 3 (with --anchor-bundle-scale-degree 1): four seeds of four at rung 3 from steps 1150-1250 where without it one of two was; a build of 0.116 m used as 0.067, but the median lags behind builds that improve (0.066 m used as 0.092). 1: the newest build, always (the default); 3 in --recipe cpu-anchored.")] = 1,
    anchor_stride: Annotated[int, typer.Option("--anchor-stride", metavar="N", help="--anchor vo: each build's odometry and bundle adjustment run on every N-th frame of each sequence (and its last); the frames between take poses interpolated between theirs (centres on the line, orientations on the arc), and the sequences are registered on all frames. A build's bundle adjustment grows faster than the frames (its tracks grow longer): on a generated scene of four 500-frame sequences one build took 504 s against 38 s for two of 150; with the true depth, N 2 took it from 533 to 204 s and the sequences' own errors from 0.010-0.014 m to 0.013-0.018, N 3 to 178 s with one sequence at 0.12 m. 1: every frame. 0 (the default): each sequence its own, the smallest that keeps at most 500 of its frames (every frame of a shorter one; two 1000-frame sequences: 139 s instead of 487, 0.051 m from the truth instead of 0.047).")] = 0,
    w_depth_scale: Annotated[float, typer.Option("--w-depth-scale", metavar="W", help="--anchor vo: hold the depth network's scale where it was when the first anchors were built, with weight W (L_scale: the square of the batch's mean log depth over the frames' own then). Monocular training leaves the scale of all depths free (every other term is unchanged by it), and the anchors are rebuilt in whatever units it has drifted to, so that the DSC network's targets change scale from build to build. The log's scale_drift is the batch's difference, as a log. Measured at 1.0 with --w-novel-view 0.1: on the demo scene rung 3 at 35 of 37 checkpoints from step 400-500 to 1600 (three runs, two seeds, also with --novel-view-depth-only) with the relative pose below rung 1's bar at each, where with the scale free it crossed the bar; on the real walk-through no closer than free (0.089-0.109 m from step 900, rung 2). 0: free (the default, the paper's).")] = 0.0,
    anchor_hold: Annotated[bool, typer.Option("--anchor-hold/--no-anchor-hold", help="Keep the anchors (their weight, and their rebuilds every --anchor-every steps) after the bootstrap has faded out, for the whole run, instead of fading them out with it.")] = False,
    ema_decay: Annotated[float, typer.Option("--ema-decay", metavar="DECAY", help="Keep an exponential moving average of the weights with this decay per step (e.g. 0.99: about the last 100 steps) and write it into every checkpoint; localize and evaluate then use it instead of the raw weights (0: none; not the paper's). Training, anchors included, runs on the raw weights, so the run is the same with or without it. A resumed run keeps its own; given when resuming, it changes the decay or starts an average.")] = 0.0,
    loss_resolution: Annotated[str, typer.Option("--loss-resolution", help="Each scale's L_p at its decoder layer's size ('decoder', the paper: images downsampled, K scaled; default) or at the input size ('input', monodepth2: disparity upsampled).")] = "decoder",
    decoder_bn: Annotated[bool, typer.Option("--decoder-bn", help="Batch normalisation in the depth decoder's conv blocks (the paper; monodepth2 has none).")] = False,
    log_every: Annotated[int, typer.Option("--log-every", help="Write logs/train.jsonl every N steps.")] = 10,
    checkpoint_every: Annotated[int, typer.Option("--checkpoint-every", help="Steps between checkpoints.")] = 500,
    keep_last: Annotated[int, typer.Option("--keep-last", help="Checkpoints to keep (older are deleted).")] = 3,
    progress: Annotated[bool, typer.Option("--progress/--no-progress", help="Show a progress bar.")] = True,
) -> None:
    """Train depth + DSC networks on SHARDS (the paper's recipe by default); checkpoints go to -o.

    Settings are layered: the paper's defaults < --recipe < --config < options given here.
    """
    given = _given_fields(ctx, dict(locals()))
    from relocdepth.recipes import read_config_file
    from relocdepth.recipes import recipe as recipe_fields
    from relocdepth.train import TrainConfig, resume_config
    from relocdepth.train import train as run_training

    values = TrainConfig.values_of(recipe_fields(recipe))
    if config is not None:
        values.update(read_config_file(config))
    values.update(TrainConfig.values_of(given))
    # A resumed run keeps its own training options: only how it runs is taken from here.
    cfg = resume_config(values) if values.get("resume") else TrainConfig.from_values(values)
    summary = run_training(shards, out, cfg, given=values)
    if summary["rank"] == 0:
        typer.echo(
            f"trained {summary['steps_this_run']} steps (total {summary['steps']}, epoch {summary['epoch']}, "
            f"stop: {summary['stop']}); checkpoint {summary['checkpoint']}"
        )
        if summary["stop"] == "interrupted":
            raise typer.Exit(EXIT_INTERRUPTED)
