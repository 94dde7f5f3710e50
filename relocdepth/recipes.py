"""Named training recipes, defined once: `reloc train --recipe NAME`, the demo and the quality rows.

A recipe is a set of training options by name (the command line's, see
:meth:`~relocdepth.train.TrainConfig.values_of`) on top of the defaults (which are the paper's).
A config file (``--config``: YAML or JSON of options, flat or in TrainConfig's sections, or a run's
own ``config.json``) goes on top of the recipe, and options given on the command line on top of
both: ``defaults < recipe < config file < command line``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from relocdepth.errors import UserError

# The measured CPU recipe (README, Quality): +-3 frames, lr 3e-4, L_p over all pixels (the
# in-image mask can be gamed by warping off-image), at 128x96, L_p at the input size (as measured).
# Checkpoints carry a moving average of the weights (decay 0.99), which localisation and evaluation
# use: the raw weights swing from checkpoint to checkpoint at lr 3e-4. Training is the same; the
# average's depth and relative pose were better at nearly every checkpoint of the demo scene and the
# real walk-through (README, Quality: trial 28).
_CPU: dict[str, Any] = {"size": (128, 96), "window": 3, "lr": 3e-4, "photometric_pixels": "all",
                        "loss_resolution": "input", "ema_decay": 0.99}
# The relative-pose bootstrap (README, Training): for the first steps the warps take their relative
# poses from the essential matrix of point tracks (right from the first step; measured on the demo
# scene and the real walk-through, README Quality), so that depth learns before the DSC network
# knows where it is. `cpu-posenet`: the two-frame pose network instead (learned ego-motion too
# slowly from random init in the measured rows).
# With the bootstrap the sources come from +-10 frames: its poses stay right at any gap, and the
# larger baselines teach depth more (AbsRel 0.165 -> 0.109 at step 100 from +-3 to +-10; README,
# Quality). Held for 2000 steps (about 2 hours on a 2-core CPU), then handed over to the DSC.
# L_p at each decoder layer's resolution, the paper's (its steps take 0.64-0.69x the time here).
# The pairs are tracked on the stored images up to 640 px wide: on the real walk-through depth
# reached the ground-truth-pose oracle's level that way at steps 181-250 (not steadily: 0.265 at
# 345) and stayed at the constant level tracked on the 192x128 crops (README, Quality). A scene
# stored at the training size (the demo's) is tracked on its crops: there the stored frames tracked
# worse (README, Quality: the demo's depth, and cpu-linked's pose at step 1000).
_BOOTSTRAP: dict[str, Any] = {"bootstrap": "essential", "bootstrap_steps": 2000, "bootstrap_fade_steps": 500,
                              "window": 10, "loss_resolution": "decoder", "bootstrap_track_width": 640}

# `cpu-anchored`'s anchors (below): the training frames' bundle-adjusted odometry, fast turns by PnP.
_ANCHORS: dict[str, Any] = {"anchor": "vo", "anchor_step": 150, "anchor_every": 250, "anchor_bundle": True,
                            "anchor_pnp_below": 50}

RECIPES: dict[str, dict[str, Any]] = {
    # The paper's recipe (Sec. IV-B): the defaults, 640x480, +-20 frames, lr 1e-4.
    "paper": {},
    # The paper's recipe with the relative-pose bootstrap.
    "paper-bootstrap": {**_BOOTSTRAP, "window": 20, "bootstrap_fade_steps": 1000},
    # CPU-sized recipes (random init, minutes to hours on 2 cores).
    "cpu": dict(_CPU),
    "cpu-bootstrap": {**_CPU, **_BOOTSTRAP},
    "cpu-posenet": {**_CPU, **_BOOTSTRAP, "bootstrap": "posenet", "bootstrap_track_width": 0},
    # `cpu-bootstrap` + absolute anchors for the DSC network from the training frames' own odometry,
    # built at step 150 and rebuilt every 250 steps (README, Training; Quality trial 14: a better
    # absolute pose, a steadier relative one up to ~600 steps and a worse one after, the same depth).
    # On real images of one training sequence (the walk-through, every 2nd frame a test frame) it
    # reached rung 2 within 30-34 minutes on two seeds, where the bootstrap alone stayed at rung 0
    # (README, Quality trial 25). With --anchor-align-step 400 its anchors were 22-26 % closer there
    # and the relative pose better at 9 of 10 checkpoints (one seed; trial 26): not yet measured on
    # the demo scene, so not part of the recipe. Bundle-adjusted (anchor_bundle) its anchors were
    # 15-43 % closer on the walk-through and 21-30 % on the demo scene, and the network's absolute
    # and relative translation better at most checkpoints of both (two seeds and one; trial 29).
    # Pairs that KLT tracks at fewer than 50 points (fast turns) measured by PnP on the depth
    # (anchor_pnp_below): on the walk-through the anchors' rotation error fell from 7-9 to 2-5 deg
    # and the network's rotation by about half at every checkpoint of two seeds; its translation
    # was better on one seed and worse on the other from step 450; the first seed reached rung 3
    # at step 1250 (README, Quality: trial 30). The demo scene's anchors are unchanged: none of
    # its pairs has so few tracks. The bundle adjustment tracks every step again from the track's
    # first view (BAConfig.first_view_px): on the demo scene the anchors went from 0.052-0.056 to
    # 0.012-0.019 m and the network's rotation from 24-26 to 3.7-5.7 deg; on the walk-through rung
    # 3 at 5 of 7 checkpoints from step 950 instead of 1 (README, Quality: trial 31). The bundle's
    # scale along the path follows a line through the network's per-frame scales
    # (anchor_bundle_scale_degree 1) and the anchors are the last three builds combined frame by
    # frame (anchor_combine 3): on the walk-through all four seeds from random init reached rung 3,
    # at steps 1150-1250, and held it at 35 of 39 checkpoints to step 2050 (README, Quality: trials
    # 39-40); on the demo scene the anchors (0.013 m) and the network stayed where they were.
    # No hand-over within a CPU run, as in `cpu-linked`: handed over at step 2000, the walk-through's
    # depth went from AbsRel 0.127 to 0.23 within 300 steps and its rotation above retrieval's
    # (trial 40), as the demo scene's had (trials 21-22).
    "cpu-anchored": {**_CPU, **_BOOTSTRAP, **_ANCHORS, "anchor_bundle_scale_degree": 1, "anchor_combine": 3,
                     "bootstrap_steps": 100_000},
    # `cpu-anchored` with the novel views of the depth alone (L_nv at 0.1, views moved back by up
    # to a tenth of their median depth), the depth's scale held from the first build
    # (w_depth_scale 1), the anchors rebuilt every 50 steps at least and the last eight builds
    # combined, without the scale's line. On the walk-through (192x128, +-2 frames) and the demo
    # scene from random init all six runs of three seeds each reached rung 3 within 2 hours, the
    # walk-through from steps 1050-1200, the demo scene from 400-900 (README, Quality: trial 52).
    # The builds take at most a tenth of the run's time (anchor_budget): every 50 steps on the
    # walk-through (1.9 % of its time), every 85-134 on the demo scene, where every 50 took 18 %;
    # so, walk-through seed 2 at rung 3 from step 1050 and the demo from step 400 (trial 54).
    # On 2000 generated frames (4 x 500) the builds came 1555 steps apart and the network stayed
    # at rung 0 within 2 hours, its depth learned (trial 54).
    "cpu-anchored-views": {**_CPU, **_BOOTSTRAP, **_ANCHORS, "anchor_every": 50, "anchor_budget": 0.1,
                           "anchor_combine": 8, "w_novel_view": 0.1, "novel_view_pose": False,
                           "novel_view_back": 0.1, "w_depth_scale": 1.0, "bootstrap_steps": 100_000},
    # `cpu-bootstrap` + anchors from the DSC network's own poses with the training sequences linked
    # into one world (built once its relative poses are right, step 600, then every 300 steps).
    # No hand-over within a CPU run: the bootstrap's warps and the anchors stay for 100000 steps.
    # Handed over (at 1600 or 2000), the DSC's warps doubled the depth error within 100 steps and
    # the absolute pose was no better; kept, depth stayed (README, Quality: trials 21-22).
    "cpu-linked": {**_CPU, **_BOOTSTRAP, "anchor": "linked", "anchor_step": 600, "anchor_every": 300,
                   "bootstrap_steps": 100_000},
    # What `reloc demo` trains (its minutes end well inside the bootstrap): `cpu-anchored` with the
    # first anchors at step 100, so that the DSC network has them for half of the demo's ~240 steps,
    # and without the scale's line and the combined builds (two builds in its budget; the line was
    # not measured there).
    # At steps 200 and 240 of the demo scene it was at rung 2 on three seeds (relative pose better
    # than identity's, rotation after a rotation-only fit 4.3-7.0 deg) where `cpu-bootstrap` stayed
    # at rung 0 (9.5-12.2 deg), depth within 0.007 AbsRel (README, Quality: trial 32).
    "demo": {**_CPU, **_BOOTSTRAP, **_ANCHORS, "anchor_step": 100},
}


def recipe(name: str) -> dict[str, Any]:
    """The options of recipe ``name`` by name (UserError naming the known ones otherwise)."""
    if name not in RECIPES:
        raise UserError(f"unknown recipe {name!r}; known: {', '.join(RECIPES)}")
    return dict(RECIPES[name])


def read_config_file(path: str | Path) -> dict[str, Any]:
    """Training options by place (:meth:`~relocdepth.train.TrainConfig.values`) from a YAML/JSON
    file: a mapping of options (flat names, or TrainConfig's sections), or a run's
    ``config.json`` (its ``train`` entry, flat as runs wrote it before the sections, or nested).
    Unknown options are a UserError naming them."""
    from relocdepth.train import TrainConfig

    path = Path(path)
    try:
        text = path.read_text()
    except OSError as e:
        raise UserError(f"cannot read --config {path}: {e.strerror or e}") from None
    import yaml

    kind = "JSON" if path.suffix.lower() == ".json" else "YAML"
    try:
        data = json.loads(text) if kind == "JSON" else yaml.safe_load(text)
    except (ValueError, yaml.YAMLError) as e:
        raise UserError(f"--config {path} is not valid {kind}: {str(e).splitlines()[0]}") from None
    if isinstance(data, dict) and isinstance(data.get("train"), dict):
        data = data["train"]  # a run's config.json
    if not isinstance(data, dict):
        raise UserError(f"--config {path} must hold a mapping of training options (or a run's config.json)")
    values = TrainConfig.values_of(data, where=f"--config {path}: ")
    # A repeated run starts afresh unless --resume is given on the command line.
    values.pop("resume", None)
    return values
