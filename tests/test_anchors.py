"""Absolute anchors for the DSC network: the odometry-built world poses of the training frames,
the DSC-vs-anchor term, its schedule, and the trainer's build, checkpoint and resume."""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from reloc_fixtures import FixedDSC

from relocdepth import geometry as geo
from relocdepth.anchors import MIN_LINK_INLIERS, TURN_MIN_AGREEMENT
from relocdepth.errors import UserError
from relocdepth.eval_geometry import rotation_angle_deg
from relocdepth.method import Bootstrap, MethodConfig, triplet_loss
from relocdepth.models import ModelConfig, Networks

torch.set_num_threads(1)
H, W = 64, 96


def _poses(n: int, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    T = torch.eye(4).repeat(n, 1, 1)
    T[:, :3, :3] = geo.so3_exp((torch.rand(n, 3, generator=gen) - 0.5) * 0.2)
    T[:, :3, 3] = (torch.rand(n, 3, generator=gen) - 0.5) * 0.2
    return T


def test_anchor_term_is_the_cells_distance_to_the_anchor_in_scene_depth_units() -> None:
    """A DSC whose cells all give the true poses: L_anchor is 0 at the true anchors; one frame of
    three anchored |d| = 5 cm away costs |d| / D / 3 (D = scene depth), the same at 4x the depth
    units; a 0.1 rad rotation offset of one frame costs 0.1 / 3; the term enters the total with its
    weight, and the diagnostics say how far the DSC's poses are from the anchors."""
    torch.manual_seed(0)
    nets = Networks(ModelConfig())
    imgs = torch.rand(1, 3, 3, H, W)
    K = torch.tensor([[60.0, 0, (W - 1) / 2], [0, 60.0, (H - 1) / 2], [0, 0, 1]]).expand(1, 3, 3, 3).clone()
    T_true = _poses(3, seed=1).reshape(1, 3, 4, 4)
    cfg = MethodConfig(photometric_pixels="all")
    got = []
    for k in (1.0, 4.0):  # the same scene in two depth units
        depth = torch.full((1, 3, 1, H, W), 1.5 * k)
        T_k = T_true.clone()
        T_k[..., :3, 3] *= k
        nets.dsc = FixedDSC(geo.dsc_from_pose(T_k.reshape(3, 4, 4), geo.pool_depth(depth.reshape(3, 1, H, W)),
                                               K.reshape(3, 3, 3)))
        _, parts, diag = triplet_loss(nets, imgs, imgs, K, cfg, Bootstrap(False, 0.0, T_anchor=T_k, w_anchor=1.0),
                                      depth_override=depth)
        assert float(parts["L_anchor"]) < 1e-3 and diag["anchor_trans"] < 1e-3 * k
        off = T_k.clone()
        off[0, 2, :3, 3] += torch.tensor([0.03, 0.0, -0.04]) * k
        base, parts, diag = triplet_loss(nets, imgs, imgs, K, cfg, Bootstrap(False, 0.0, T_anchor=off, w_anchor=2.0),
                                         depth_override=depth)
        got.append(float(parts["L_anchor"]))
        assert diag["anchor_trans"] == pytest.approx(0.05 * k / 3, rel=1e-2)
        paper, _, _ = triplet_loss(nets, imgs, imgs, K, cfg, depth_override=depth)
        assert float(base.detach()) == pytest.approx(float(paper.detach()) + 2.0 * got[-1], rel=1e-5)
    assert got[0] == pytest.approx(0.05 / 1.5 / 3, rel=1e-2)
    assert got[1] == pytest.approx(got[0], rel=1e-2)
    turned = T_true.clone()
    turned[0, 0, :3, :3] = turned[0, 0, :3, :3] @ geo.so3_exp(torch.tensor([0.0, 0.1, 0.0]))
    depth = torch.full((1, 3, 1, H, W), 1.5)
    nets.dsc = FixedDSC(geo.dsc_from_pose(T_true.reshape(3, 4, 4), geo.pool_depth(depth.reshape(3, 1, H, W)),
                                           K.reshape(3, 3, 3)))
    _, parts, diag = triplet_loss(nets, imgs, imgs, K, cfg, Bootstrap(False, 0.0, T_anchor=turned, w_anchor=1.0),
                                  depth_override=depth)
    assert float(parts["L_anchor"]) == pytest.approx(0.1 / 3, rel=1e-2)
    assert diag["anchor_rot_deg"] == pytest.approx(math.degrees(0.1) / 3, rel=1e-2)


def test_anchor_term_teaches_the_dsc_network_only() -> None:
    torch.manual_seed(0)
    nets = Networks(ModelConfig())
    imgs = torch.rand(1, 3, 3, H, W)
    K = torch.tensor([[60.0, 0, (W - 1) / 2], [0, 60.0, (H - 1) / 2], [0, 0, 1]]).expand(1, 3, 3, 3).clone()
    _, parts, _ = triplet_loss(nets, imgs, imgs, K, MethodConfig(),
                               Bootstrap(False, 0.0, T_anchor=_poses(3, seed=2).reshape(1, 3, 4, 4), w_anchor=1.0))
    parts["L_anchor"].backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in nets.dsc.parameters())
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in nets.depth.parameters())


def test_anchor_schedule_and_options() -> None:
    from relocdepth.train import TrainConfig, anchor_at, anchor_due, anchor_interval

    cfg = TrainConfig.from_dict({"bootstrap": "essential", "bootstrap_steps": 10, "bootstrap_fade_steps": 4,
                                 "anchor": "vo", "anchor_step": 3, "anchor_every": 5, "w_anchor": 2.0})
    assert [anchor_at(cfg, s) for s in (0, 2, 3, 9, 10, 11, 14)] == [0.0, 0.0, 2.0, 2.0, 2.0, 1.5, 0.0]
    assert not anchor_due(cfg, 2, None) and anchor_due(cfg, 3, None)
    assert not anchor_due(cfg, 7, 3) and anchor_due(cfg, 8, 3)  # rebuilt every 5 steps
    assert not anchor_due(cfg, 14, 13)  # the bootstrap has faded out: no more anchors
    once = TrainConfig.from_dict({"bootstrap": "essential", "bootstrap_steps": 10, "anchor": "vo", "anchor_step": 3})
    assert anchor_due(once, 3, None) and not anchor_due(once, 9, 3)
    assert anchor_at(TrainConfig(), 100) == 0.0
    held = dataclasses.replace(cfg, anchor_hold=True)  # kept after the fade, and still rebuilt
    assert [anchor_at(held, s) for s in (2, 3, 11, 14, 1000)] == [0.0, 2.0, 2.0, 2.0, 2.0]
    assert not anchor_due(held, 17, 13) and anchor_due(held, 18, 13) and anchor_due(held, 1000, 995)
    # a growing interval: after a build at step s the next comes max(5, 0.25 s) steps on
    grown = dataclasses.replace(held, anchor_every_growth=0.25)
    assert not anchor_due(grown, 12, 8) and anchor_due(grown, 13, 8)  # 0.25 * 8 = 2 < 5
    assert not anchor_due(grown, 124, 100) and anchor_due(grown, 125, 100)  # 25 steps on
    built, at = [], None
    for s in range(1, 2001):
        if anchor_due(grown, s, at):
            built.append(s)
            at = s
    assert built[:7] == [3, 8, 13, 18, 23, 28, 35] and built[-3:] == [1165, 1456, 1820]
    assert len(built) == 25  # with a fixed interval of 5: 400
    # a budget: a build of 30 s with steps of 3 s at 10 % of the time: 30 * 0.9 / (0.1 * 3) = 90 steps on
    budget = dataclasses.replace(held, anchor_budget=0.1)
    assert anchor_interval(budget, 8, 30.0, 3.0) == 90 and anchor_interval(budget, 8, 1.0, 3.0) == 5
    assert anchor_interval(budget, 8) == anchor_interval(budget, 8, 30.0, None) == 5  # not measured yet
    assert anchor_interval(held, 8, 30.0, 3.0) == 5  # no budget: the time is not looked at
    assert anchor_interval(dataclasses.replace(budget, anchor_every_growth=0.25), 1000, 30.0, 3.0) == 250
    assert not anchor_due(budget, 97, 8, 98) and anchor_due(budget, 98, 8, 98)  # the step the build set
    assert anchor_due(budget, 13, 8, None)  # a checkpoint from before: the interval from the build's step
    for bad in (-0.1, 1.0, float("nan")):
        with pytest.raises(UserError, match="--anchor-budget must be a fraction"):
            TrainConfig.from_dict({"bootstrap": "essential", "bootstrap_steps": 10, "anchor": "vo",
                                   "anchor_every": 5, "anchor_budget": bad})
    with pytest.raises(UserError, match="--anchor-budget needs --anchor-every"):
        TrainConfig.from_dict({"bootstrap": "essential", "bootstrap_steps": 10, "anchor": "vo", "anchor_budget": 0.1})
    with pytest.raises(UserError, match="--anchor-every-growth needs --anchor-every"):
        TrainConfig.from_dict({"bootstrap": "essential", "bootstrap_steps": 10, "anchor": "vo",
                               "anchor_every_growth": 0.25})
    for bad in (-0.1, float("nan")):
        with pytest.raises(UserError, match="--anchor-every-growth must be a number >= 0"):
            TrainConfig.from_dict({"bootstrap": "essential", "bootstrap_steps": 10, "anchor": "vo",
                                   "anchor_every": 5, "anchor_every_growth": bad})
    with pytest.raises(UserError, match="needs a --bootstrap"):
        TrainConfig.from_dict({"anchor": "vo"})
    with pytest.raises(UserError, match="--anchor-hold needs an --anchor"):
        TrainConfig.from_dict({"bootstrap": "essential", "bootstrap_steps": 10, "anchor_hold": True})
    with pytest.raises(UserError, match="--anchor must be one of"):
        TrainConfig.from_dict({"bootstrap": "essential", "bootstrap_steps": 10, "anchor": "gps"})
    with pytest.raises(UserError, match=">= 0"):
        TrainConfig.from_dict({"bootstrap": "essential", "bootstrap_steps": 10, "anchor": "vo", "w_anchor": -1})
    # the vo-only options: with linked anchors, and below 0
    with pytest.raises(UserError, match="--anchor-bundle needs --anchor vo"):
        TrainConfig.from_dict({"bootstrap": "essential", "bootstrap_steps": 10, "anchor": "linked",
                               "anchor_bundle": True})
    for field, option, value in (("anchor_align_step", "--anchor-align-step", 300),
                                 ("anchor_track_width", "--anchor-track-width", 640),
                                 ("anchor_pnp_below", "--anchor-pnp-below", 50)):
        with pytest.raises(UserError, match=f"{option} needs --anchor vo"):
            TrainConfig.from_dict({"bootstrap": "essential", "bootstrap_steps": 10, "anchor": "linked",
                                   field: value})
        with pytest.raises(UserError, match=f"{option} must be >= 0"):
            TrainConfig.from_dict({"bootstrap": "essential", "bootstrap_steps": 10, "anchor": "vo", field: -1})
    with pytest.raises(UserError, match="--anchor-combine must be a number of builds >= 1"):
        TrainConfig.from_dict({"bootstrap": "essential", "bootstrap_steps": 10, "anchor": "vo", "anchor_combine": 0})
    with pytest.raises(UserError, match="--anchor-combine needs --anchor vo"):
        TrainConfig.from_dict({"bootstrap": "essential", "bootstrap_steps": 10, "anchor": "linked", "anchor_combine": 3})
    with pytest.raises(UserError, match="--anchor-stride must be a number of frames >= 1, or 0"):
        TrainConfig.from_dict({"bootstrap": "essential", "bootstrap_steps": 10, "anchor": "vo", "anchor_stride": -1})
    with pytest.raises(UserError, match="--anchor-stride needs --anchor vo"):
        TrainConfig.from_dict({"bootstrap": "essential", "bootstrap_steps": 10, "anchor": "linked", "anchor_stride": 2})
    with pytest.raises(UserError, match="--anchor-bundle-scale needs --anchor-bundle"):
        TrainConfig.from_dict({"bootstrap": "essential", "bootstrap_steps": 10, "anchor": "vo", "anchor_bundle_scale": 20})
    for bad in (-1.0, float("nan")):
        with pytest.raises(UserError, match="--anchor-bundle-scale must be a number of frames >= 0"):
            TrainConfig.from_dict({"bootstrap": "essential", "bootstrap_steps": 10, "anchor": "vo",
                                   "anchor_bundle": True, "anchor_bundle_scale": bad})
    vo = {"bootstrap": "essential", "bootstrap_steps": 10, "anchor": "vo"}
    for extra, message in (({}, "--anchor-bundle-scale-degree needs --anchor-bundle"),
                           ({"anchor_bundle": True, "anchor_bundle_scale": 10}, "two ways to hold"),
                           ({"anchor_bundle": True, "anchor_bundle_scale_degree": -1},
                            "--anchor-bundle-scale-degree must be >= 0")):
        with pytest.raises(UserError, match=message):
            TrainConfig.from_dict({"anchor_bundle_scale_degree": 1, **vo, **extra})


def test_held_anchors_outlast_the_bootstrap_in_the_trainer(synth_shards: Path, tmp_path: Path) -> None:
    """A bootstrap that has faded out by step 3: the anchors' term goes with it, unless held; held,
    the anchors are rebuilt after the fade and every later step carries their term."""
    from relocdepth.train import train

    for hold in (False, True):
        run = tmp_path / f"run-{hold}"
        train(synth_shards, run, _cfg(max_steps=5, bootstrap_steps=2, bootstrap_fade_steps=1, anchor_every=2,
                                      anchor_hold=hold))
        log = [json.loads(x) for x in (run / "logs" / "train.jsonl").read_text().splitlines()]
        built = [d["step"] for d in log if d.get("event") == "anchors"]
        anchored = [d["step"] for d in log if "loss" in d and "L_anchor" in d["parts"]]
        assert built == ([1, 3] if hold else [1])
        assert anchored == ([2, 3, 4, 5] if hold else [2, 3])


def _gt(shards: Path, frames) -> tuple[np.ndarray, list[np.ndarray]]:
    from relocdepth.dataset import open_dataset

    ds = open_dataset(shards)
    recs = {r.key: r for r in ds.frames("train")}
    poses = np.stack([ds.read_pose(recs[f.key]) for f in frames.frames])
    depths = [ds.read_depth(recs[f.key]) for f in frames.frames]
    return poses, depths


def test_anchors_with_true_depth_follow_each_sequence(synth_shards: Path) -> None:
    """With ground-truth depth, every training frame's anchor is its true pose in the first
    sequence's world: within each sequence the poses relative to its first frame are metric and
    right, and each frame's anchor is at its own index."""
    from relocdepth.anchors import build_anchors, sequences_of
    from relocdepth.data import ImageFrames

    frames = ImageFrames.open(synth_shards)
    T_gt, depth_gt = _gt(synth_shards, frames)
    seqs = sequences_of(frames)
    assert len(seqs) >= 2 and sorted(i for ix in seqs for i in ix) == list(range(len(frames)))
    for ix in seqs:
        assert len({frames.frames[i].sequence for i in ix}) == 1
        assert [frames.frames[i].frame for i in ix] == sorted(frames.frames[i].frame for i in ix)
    W_, H_ = frames.frames[0].intrinsics.width, frames.frames[0].intrinsics.height
    a = build_anchors(frames, lambda ix, ims: [depth_gt[i] for i in ix], (W_, H_))
    assert a.T_wc.shape == (len(frames), 4, 4) and a.T_wc.dtype == np.float32 and a.lost == 0
    assert len(a.registration) == len(seqs) - 1
    assert np.allclose(a.T_wc[seqs[0][0]], np.eye(4), atol=1e-6)  # the world: sequence 1's first frame
    # Each frame's anchor is its own pose in the odometry of its sequence...
    from relocdepth.data import scale_and_crop
    from relocdepth.vo import world_trajectory

    images = [[scale_and_crop(frames.read_image(i), frames.frames[i].intrinsics, W_, H_, 1.0, 0, 0)[0] for i in ix]
              for ix in seqs]
    K = frames.frames[0].intrinsics.K()
    w = world_trajectory(images, [K] * len(seqs), [lambda j, ix=ix: depth_gt[ix[j]] for ix in seqs])
    for ix, T_seq in zip(seqs, w.world):
        assert np.allclose(a.T_wc[ix], T_seq.astype(np.float32))
    # ...and with true depth that odometry is metric and right on the first sequence (24 frames
    # 1 cm apart at 128x96: ~30 % drift, ~3 deg); the same anchors at reversed indices are off by
    # about the whole path. (The second sequence's turns leave pairs with too little parallax for a
    # translation: its odometry is tested in test_vo on a path that suits it.)
    ix = seqs[0]
    rel_gt = np.linalg.inv(T_gt[ix[0]]) @ T_gt[ix]
    path = np.linalg.norm(np.diff(T_gt[ix, :3, 3], axis=0), axis=1).sum()
    err = np.linalg.norm(a.T_wc[ix, :3, 3] - rel_gt[:, :3, 3], axis=1)
    assert path > 0.1 and err.max() < 0.4 * path, (err, path)
    assert rotation_angle_deg(np.swapaxes(a.T_wc[ix, :3, :3], -1, -2) @ rel_gt[:, :3, :3]).max() < 5.0
    back = np.linalg.inv(a.T_wc[ix[-1]]) @ a.T_wc[ix[::-1]]
    assert np.linalg.norm(back[:, :3, 3] - rel_gt[:, :3, 3], axis=1).max() > 0.5 * path


def test_aligned_anchors_with_true_depth_are_closer_to_the_truth(synth_shards: Path) -> None:
    """``VOConfig(align=True)``: the first sequence's anchors (the world) are the odometry refined
    frame to frame, with true depth about twice as close to the true poses (rms 2 cm against 4 cm
    here), and the anchors say how many frames were aligned (every frame after each sequence's
    first, the images being clean renders)."""
    from relocdepth.anchors import build_anchors, sequences_of
    from relocdepth.data import ImageFrames
    from relocdepth.vo import VOConfig

    frames = ImageFrames.open(synth_shards)
    T_gt, depth_gt = _gt(synth_shards, frames)
    ix = sequences_of(frames)[0]
    size = frames.frames[0].intrinsics.width, frames.frames[0].intrinsics.height
    truth = np.linalg.inv(T_gt[ix[0]]) @ T_gt[ix]
    err = {}
    for align in (False, True):
        a = build_anchors(frames, lambda ix, ims: [depth_gt[i] for i in ix], size, VOConfig(align=align))
        assert a.aligned == (len(frames) - len(sequences_of(frames)) if align else None)
        err[align] = float(np.sqrt(np.mean(np.sum((a.T_wc[ix, :3, 3] - truth[:, :3, 3]) ** 2, axis=1))))
    assert err[True] < 0.7 * err[False], err


def test_anchors_track_the_stored_images_at_the_width_asked(synth_shards_320: Path) -> None:
    """``track_width``: the odometry runs on the stored 320x240 images (or down-sized to the width
    asked), with the depth maps given at the training size upsampled to them: the anchors are the
    world trajectory of exactly those images, K and depth; a width at or below the training size,
    or 0, keeps the training images."""
    import cv2

    from relocdepth.anchors import build_anchors, sequences_of
    from relocdepth.data import ImageFrames
    from relocdepth.vo import world_trajectory

    frames = ImageFrames.open(synth_shards_320)
    _, depth_gt = _gt(synth_shards_320, frames)
    small = [cv2.resize(d, (128, 96), interpolation=cv2.INTER_NEAREST) for d in depth_gt]

    def depth(ix: list[int], ims: list[np.ndarray]) -> list[np.ndarray]:
        assert all(im.shape == (96, 128, 3) for im in ims)  # the depth network's input: training size
        return [small[i] for i in ix]

    seqs = sequences_of(frames)
    plain = build_anchors(frames, depth, (128, 96))
    assert plain.track_size == (128, 96)
    for width in (0, 128):
        again = build_anchors(frames, depth, (128, 96), track_width=width)
        assert again.track_size == (128, 96) and np.array_equal(again.T_wc, plain.T_wc)
    for width, size in ((240, (240, 180)), (1000, (320, 240))):
        a = build_anchors(frames, depth, (128, 96), track_width=width)
        assert a.track_size == size
        images = [[cv2.resize(frames.read_image(i), size, interpolation=cv2.INTER_AREA) if size != (320, 240)
                   else frames.read_image(i) for i in ix] for ix in seqs]
        K = frames.frames[0].intrinsics.scaled(*size).K()
        w = world_trajectory(images, [K] * len(seqs),
                             [lambda j, ix=ix: cv2.resize(small[ix[j]], size, interpolation=cv2.INTER_LINEAR)
                              for ix in seqs])
        for ix, T_seq in zip(seqs, w.world):
            assert np.allclose(a.T_wc[ix], T_seq.astype(np.float32), atol=1e-6)
        assert not np.allclose(a.T_wc, plain.T_wc, atol=1e-3)  # other pixels, other poses


def _cfg(**kw):
    from relocdepth.train import TrainConfig

    return TrainConfig.from_dict({"size": (128, 96), "batch_size": 2, "pretrained": None, "workers": 0,
                                  "progress": False, "log_every": 1, "bootstrap": "essential",
                                  "bootstrap_steps": 10, "window": 3, "anchor": "vo", "anchor_step": 1, **kw})


def test_trainer_builds_anchors_checkpoints_and_resumes_them(synth_shards: Path, tmp_path: Path) -> None:
    from relocdepth import checkpoint as ckpt_io
    from relocdepth.train import train

    run = tmp_path / "run"
    train(synth_shards, run, _cfg(max_steps=3, checkpoint_every=2))
    log = [json.loads(x) for x in (run / "logs" / "train.jsonl").read_text().splitlines()]
    built = [d for d in log if d.get("event") == "anchors"]
    assert [d["step"] for d in built] == [1]
    steps = [d for d in log if "loss" in d]
    assert "L_anchor" not in steps[0]["parts"]  # step 1 ran before the anchors
    assert all("L_anchor" in d["parts"] and "anchor_trans" in d["diagnostics"] for d in steps[1:])
    ck = ckpt_io.load_checkpoint(ckpt_io.list_checkpoints(run)[-1])
    assert ck["anchors"]["step"] == 1 and ck["anchors"]["T_wc"].shape[1:] == (4, 4)
    train(synth_shards, run, _cfg(max_steps=4, resume=True))
    log = [json.loads(x) for x in (run / "logs" / "train.jsonl").read_text().splitlines()]
    assert [d["step"] for d in log if d.get("event") == "anchors"] == [1]  # restored, not rebuilt
    assert "L_anchor" in [d for d in log if "loss" in d][-1]["parts"]


def test_trainer_spaces_costly_builds_by_the_budget_and_resumes_where_it_said(
        synth_shards: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``anchor_budget`` 0.5 with ``anchor_every`` 1 and builds made to take 3 s more: the build at
    step 1 sets the next as many steps on as take as long as it did (step 0 measured: more than
    one, where every step would build), the checkpoint keeps that step, and a run resumed from
    step 2 builds there and not before."""
    import relocdepth.anchors as A
    from relocdepth import checkpoint as ckpt_io
    from relocdepth.train import train

    build = A.build_anchors

    def slow(*args, **kw):  # noqa: ANN002, ANN003, ANN202
        time.sleep(3.0)
        return build(*args, **kw)

    def built() -> list[dict]:
        return [d for d in map(json.loads, (run / "logs" / "train.jsonl").read_text().splitlines())
                if d.get("event") == "anchors"]

    monkeypatch.setattr(A, "build_anchors", slow)
    run = tmp_path / "run"
    cfg = dict(anchor_every=1, anchor_budget=0.5, bootstrap_steps=100, checkpoint_every=1, keep_last=100)
    train(synth_shards, run, _cfg(max_steps=2, **cfg))
    (first,) = built()
    nxt = first["next_step"]
    assert first["step"] == 1 and first["seconds"] >= 3.0 and first["step_seconds"] < 3.0
    assert nxt >= 3, first
    assert ckpt_io.load_checkpoint(ckpt_io.list_checkpoints(run)[-1])["anchors"]["next"] == nxt
    train(synth_shards, run, _cfg(max_steps=nxt + 1, resume=True, **cfg))
    assert [d["step"] for d in built()] == [1, nxt]


def test_trainer_aligns_the_anchors_odometry_from_the_step_asked(synth_shards: Path, tmp_path: Path) -> None:
    """Anchors rebuilt every step, aligned from step 2: the build at step 1 is plain odometry, the
    later ones are refined by direct alignment (the log says how many frames)."""
    from relocdepth import checkpoint as ckpt_io
    from relocdepth.data import ImageFrames
    from relocdepth.train import train

    run = tmp_path / "run"
    train(synth_shards, run, _cfg(max_steps=4, anchor_every=1, anchor_align_step=2, checkpoint_every=1,
                                  keep_last=5))
    log = [json.loads(x) for x in (run / "logs" / "train.jsonl").read_text().splitlines()]
    built = [d for d in log if d.get("event") == "anchors"]
    assert [d["step"] for d in built] == [1, 2, 3] and built[0]["aligned"] is None
    n = len(ckpt_io.load_checkpoint(ckpt_io.list_checkpoints(run)[-1])["anchors"]["T_wc"])
    seqs = len({f.sequence for f in ImageFrames.open(synth_shards).frames})
    assert all(0 < d["aligned"] <= n - seqs for d in built[1:])  # frames after each sequence's first


def test_trainer_bundle_adjusts_the_anchors_odometry_when_asked(synth_shards: Path, tmp_path: Path) -> None:
    """``anchor_bundle``: the build refines each sequence's odometry by bundle adjustment, and the
    anchors event says how (tracks, median reprojection error before and after)."""
    from relocdepth.train import train

    for bundle in (False, True):
        run = tmp_path / f"run-{bundle}"
        train(synth_shards, run, _cfg(max_steps=2, anchor_bundle=bundle))
        log = [json.loads(x) for x in (run / "logs" / "train.jsonl").read_text().splitlines()]
        built = [d for d in log if d.get("event") == "anchors"]
        assert len(built) == 1
        if not bundle:
            assert built[0]["bundled"] is None
            continue
        seqs = built[0]["bundled"]
        assert len(seqs) == len(built[0]["registration"]) + 1
        assert all(b["tracks"] > 0 and b["final_px"] <= b["start_px"] for b in seqs)


def test_trainer_measures_pairs_with_few_tracks_by_pnp_when_asked(synth_shards: Path, tmp_path: Path) -> None:
    """``anchor_pnp_below``: pairs that KLT tracks at fewer points than that are measured by PnP on
    the depth network's depth; the anchors event counts them (none when off)."""
    from relocdepth.data import ImageFrames
    from relocdepth.train import train

    counts = {}
    for below in (0, 10**6):  # never; every pair
        run = tmp_path / f"run-{below}"
        train(synth_shards, run, _cfg(max_steps=2, anchor_pnp_below=below))
        log = [json.loads(x) for x in (run / "logs" / "train.jsonl").read_text().splitlines()]
        counts[below] = [d["pnp"] for d in log if d.get("event") == "anchors"]
    n = len(ImageFrames.open(synth_shards).frames)
    assert counts[0] == [0]
    assert len(counts[10**6]) == 1 and n // 2 < counts[10**6][0] < n  # not each sequence's first frame


def test_trainer_tracks_the_anchors_odometry_at_the_width_asked(synth_shards_320: Path, tmp_path: Path) -> None:
    """``anchor_track_width``: the trainer's odometry runs on the stored images (320x240 here, at
    most the width asked) while it trains at 128x96; the anchors event says at what size."""
    from relocdepth.train import train

    run = tmp_path / "run"
    train(synth_shards_320, run, _cfg(max_steps=2, anchor_track_width=1000))
    log = [json.loads(x) for x in (run / "logs" / "train.jsonl").read_text().splitlines()]
    assert [d["track_size"] for d in log if d.get("event") == "anchors"] == [[320, 240]]


def test_trainer_holds_the_anchors_scale_when_asked(synth_shards: Path, tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """``anchor_bundle_scale``: the trainer's build runs the bundle adjustment to convergence with
    the scale held along the path over that many frames; ``anchor_bundle_scale_degree``, by a
    polynomial of that degree; without either, the adjustment's defaults."""
    import relocdepth.anchors as A
    from relocdepth.ba import BAConfig
    from relocdepth.train import ANCHOR_BUNDLE_ITERATIONS, train

    seen, build = [], A.build_anchors

    def spy(frames, depth, size, cfg=None, track_width=0, stride=1):  # noqa: ANN001, ANN202
        seen.append(cfg)
        return build(frames, depth, size, cfg, track_width, stride)

    monkeypatch.setattr(A, "build_anchors", spy)
    train(synth_shards, tmp_path / "held", _cfg(max_steps=2, anchor_bundle=True, anchor_bundle_scale=5))
    train(synth_shards, tmp_path / "plain", _cfg(max_steps=2, anchor_bundle=True))
    train(synth_shards, tmp_path / "line", _cfg(max_steps=2, anchor_bundle=True, anchor_bundle_scale_degree=1))
    assert [c.bundle for c in seen] == [True, True, True]
    assert seen[0].bundle_cfg == BAConfig(max_iterations=ANCHOR_BUNDLE_ITERATIONS, scale_window=5)
    assert seen[1].bundle_cfg == BAConfig()
    assert seen[2].bundle_cfg == BAConfig(scale_degree=1)


def test_linked_anchors_put_every_sequence_in_the_first_ones_world(synth_shards_320: Path) -> None:
    """Poses right within each sequence, each sequence in a world of its own (the second moved by a
    known 10 deg / 20 cm): the linked anchors keep the first sequence's poses as given, and put the
    second's in its world, each frame's at its own index; the networks see the training size, the
    links the stored one."""
    from relocdepth.anchors import build_linked_anchors, sequences_of
    from relocdepth.data import ImageFrames

    frames = ImageFrames.open(synth_shards_320)
    T_gt, depth_gt = _gt(synth_shards_320, frames)
    seqs = sequences_of(frames)
    world = np.linalg.inv(T_gt[seqs[0][0]])
    own = [np.eye(4)] + [np.eye(4) for _ in seqs[1:]]
    own[1][:3, :3] = geo.so3_exp(torch.tensor([[0.0, 0.17, 0.03]], dtype=torch.float64))[0].numpy()
    own[1][:3, 3] = [0.2, 0.0, -0.1]
    calls = iter(range(len(seqs)))

    def poses(images: list[np.ndarray], K: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
        k = next(calls)
        assert len(images) == len(K) == len(seqs[k]) and images[0].shape == (96, 128, 3)
        return own[k] @ world @ T_gt[seqs[k]], [cv2.resize(depth_gt[i], (128, 96), interpolation=cv2.INTER_NEAREST)
                                                for i in seqs[k]]  # at the networks' size, as promised

    a = build_linked_anchors(frames, poses, (128, 96), turn=False)  # the turn: tested below
    assert a.T_wc.shape == (len(frames), 4, 4) and a.T_wc.dtype == np.float32 and a.turn_deg is None
    assert len(a.registration) == len(seqs) - 1 and a.registration[0][0] >= MIN_LINK_INLIERS and a.unlinked == []
    assert np.allclose(a.T_wc[seqs[0]], (world @ T_gt[seqs[0]]).astype(np.float32), atol=1e-5)
    ix = seqs[1]
    truth = world @ T_gt[ix]
    before = rotation_angle_deg(np.swapaxes((own[1] @ truth)[:, :3, :3], -1, -2) @ truth[:, :3, :3])
    err_r = rotation_angle_deg(np.swapaxes(a.T_wc[ix, :3, :3], -1, -2) @ truth[:, :3, :3])
    err_t = np.linalg.norm(a.T_wc[ix, :3, 3] - truth[:, :3, 3], axis=1)
    assert before.min() > 9.0 and err_r.max() < 3.0 and err_t.max() < 0.05, (err_r.max(), err_t.max())


def test_a_sequence_its_links_do_not_agree_on_is_not_placed(synth_shards_320: Path) -> None:
    """The second sequence's own poses are noise (every frame turned at random by 57-178 deg):
    each link then puts that sequence somewhere else, fewer than MIN_LINK_INLIERS agree, and the
    build says so (``unlinked``) instead of placing it by one link, and turns nothing."""
    from relocdepth.anchors import build_linked_anchors, sequences_of
    from relocdepth.data import ImageFrames

    frames = ImageFrames.open(synth_shards_320)
    T_gt, depth_gt = _gt(synth_shards_320, frames)
    seqs = sequences_of(frames)
    world = np.linalg.inv(T_gt[seqs[0][0]]) @ T_gt
    noisy = world.copy()
    rng = np.random.default_rng(0)
    for i in seqs[1]:
        w = rng.normal(size=3)
        w *= rng.uniform(1.0, 3.1) / np.linalg.norm(w)
        noisy[i, :3, :3] = geo.so3_exp(torch.tensor(w[None], dtype=torch.float64))[0].numpy() @ noisy[i, :3, :3]
    calls = iter(range(len(seqs)))

    def poses(images: list[np.ndarray], K: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
        ix = seqs[next(calls)]
        return noisy[ix], [cv2.resize(depth_gt[i], (128, 96), interpolation=cv2.INTER_NEAREST) for i in ix]

    a = build_linked_anchors(frames, poses, (128, 96), turn=True, min_agreement=0.0)
    assert a.unlinked == [1] and a.registration[0][0] < MIN_LINK_INLIERS, a.registration
    assert a.turn_deg is None and a.turn_measured == 0  # nothing turned on a world that is not one


@pytest.mark.parametrize("source", ["linked", "vo"])
def test_trainer_does_not_use_anchors_without_consensus(source: str, synth_shards: Path, tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """Links that cannot agree enough (the bar raised past any count): the build is logged as not
    used, no step carries the anchor term, the next try comes ``anchor_every`` steps on (not every
    step), and the checkpoint holds no anchors."""
    from relocdepth import anchors as A
    from relocdepth import checkpoint as ckpt_io
    from relocdepth.train import train

    monkeypatch.setattr(A, "MIN_LINK_INLIERS", 10**6)
    run = tmp_path / "run"
    train(synth_shards, run, _cfg(anchor=source, max_steps=4, anchor_every=2, anchor_turn_agreement=0.0))
    log = [json.loads(x) for x in (run / "logs" / "train.jsonl").read_text().splitlines()]
    built = [d for d in log if d.get("event") == "anchors"]
    assert [(d["step"], d["used"]) for d in built] == [(1, False), (3, False)]
    assert not any("L_anchor" in d["parts"] for d in log if "loss" in d)
    assert ckpt_io.load_checkpoint(ckpt_io.list_checkpoints(run)[-1])["anchors"] is None


def _walk(n: int = 60) -> np.ndarray:
    """A camera walking a curve on a slope (centres spanning 3D), looking about, camera-to-world."""
    s = np.linspace(0.0, 1.0, n)
    T = np.repeat(np.eye(4)[None], n, axis=0)
    T[:, :3, 3] = np.stack([1.5 * s, 0.4 * np.sin(3 * s), 0.3 * s ** 2], axis=1)
    for k, a in enumerate(s):
        T[k, :3, :3] = geo.so3_exp(torch.tensor([[0.1 * np.sin(5 * a), 0.6 * a, 0.05]],
                                                 dtype=torch.float64))[0].numpy()
    return T


def test_combined_builds_outvote_a_build_gone_astray() -> None:
    """Three builds of a known walk in different units (0.5x, 1.3x), the middle one gone astray
    (its path drifting in scale and turning away from the first frame, its orientations turned
    6 deg): combined, the centres are the newest build's exactly and the orientations turned by
    the chordal mean's atan(sin 6 / (2 + cos 6)) = 2.0 deg; the result is in the newest build's
    units whichever that is; one build is itself."""
    from relocdepth.anchors import combine_builds

    T = _walk()
    s = np.linspace(0.0, 1.0, len(T))

    def scaled(k: float) -> np.ndarray:
        out = T.copy()
        out[:, :3, 3] *= k
        return out

    astray = T.copy()
    turn = geo.so3_exp(torch.tensor([[0.0, 0.0, math.radians(6.0)]], dtype=torch.float64))[0].numpy()
    for j, a in enumerate(s):
        bend = geo.so3_exp(torch.tensor([[0.0, math.radians(15.0) * a, 0.0]], dtype=torch.float64))[0].numpy()
        astray[j, :3, 3] = np.exp(0.5 * a) * bend @ T[j, :3, 3]
        astray[j, :3, :3] = turn @ T[j, :3, :3]
    out = combine_builds([scaled(0.5), astray, scaled(1.3)])
    assert out.dtype == np.float32 and out.shape == T.shape
    assert np.allclose(out[:, :3, 3], 1.3 * T[:, :3, 3], atol=1e-5)
    off = rotation_angle_deg(out[:, :3, :3].astype(np.float64) @ np.transpose(T[:, :3, :3], (0, 2, 1)))
    expected = math.degrees(math.atan2(math.sin(math.radians(6.0)), 2.0 + math.cos(math.radians(6.0))))
    assert expected == pytest.approx(2.0, abs=0.01)
    assert np.allclose(off, expected, atol=0.01)
    assert np.allclose(combine_builds([scaled(1.3), astray, scaled(0.5)])[:, :3, 3], 0.5 * T[:, :3, 3], atol=1e-5)
    assert np.allclose(combine_builds([astray]), astray, atol=1e-6)
    with pytest.raises(ValueError, match="at least one build"):
        combine_builds([])
    with pytest.raises(ValueError, match="different shapes"):
        combine_builds([T, T[:-1]])


def test_trainer_combines_the_last_builds_when_asked(synth_shards: Path, tmp_path: Path) -> None:
    """``anchor_combine`` 3, anchors rebuilt every step: the first two builds are used as built, the
    third and every one after are combined with the two before (the anchors event says how many);
    the checkpoint keeps the builds, and a resumed run combines its next build with the last two."""
    from relocdepth import checkpoint as ckpt_io
    from relocdepth.anchors import combine_builds
    from relocdepth.train import train

    run = tmp_path / "run"
    train(synth_shards, run, _cfg(max_steps=4, anchor_every=1, anchor_combine=3, checkpoint_every=1, keep_last=5))
    log = [json.loads(x) for x in (run / "logs" / "train.jsonl").read_text().splitlines()]
    assert [(d["step"], d["combined"]) for d in log if d.get("event") == "anchors"] == [(1, 1), (2, 1), (3, 3)]
    cks = {c["meta"]["step"]: c["anchors"] for c in map(ckpt_io.load_checkpoint, ckpt_io.list_checkpoints(run))}
    assert len(cks[3]["builds"]) == 2 and torch.equal(cks[3]["T_wc"], cks[3]["builds"][-1])  # built before step 3
    last = cks[4]
    assert len(last["builds"]) == 3 and all(torch.equal(a, b) for a, b in zip(last["builds"], cks[3]["builds"]))
    assert np.array_equal(last["T_wc"].numpy(), combine_builds([b.numpy() for b in last["builds"]]))
    assert not torch.equal(last["T_wc"], last["builds"][-1])
    train(synth_shards, run, _cfg(max_steps=5, anchor_every=1, anchor_combine=3, resume=True))
    log = [json.loads(x) for x in (run / "logs" / "train.jsonl").read_text().splitlines()]
    assert [(d["step"], d["combined"]) for d in log if d.get("event") == "anchors"][-1] == (4, 3)
    now = ckpt_io.load_checkpoint(ckpt_io.list_checkpoints(run)[-1])["anchors"]
    assert all(torch.equal(a, b) for a, b in zip(now["builds"][:2], last["builds"][1:]))
    assert np.array_equal(now["T_wc"].numpy(), combine_builds([b.numpy() for b in now["builds"]]))


def test_direction_turn_recovers_a_known_turn_of_the_centres_despite_outliers() -> None:
    """Poses whose centres were turned 8 deg about their mean (orientations kept), and the true
    directions of pairs 4-10 frames apart in the first camera's frame, a fifth of them replaced by
    random ones: direction_turn finds the turn back to within 0.3 deg, keeps the good pairs, and
    turn_centres puts the centres back; with consistent poses the turn is the identity."""
    from relocdepth.anchors import direction_turn, turn_centres

    T = _walk()
    rng = np.random.default_rng(0)
    pairs = []
    for gap in (4, 7, 10):
        for i in range(len(T) - gap):
            t = T[i, :3, :3].T @ (T[i + gap, :3, 3] - T[i, :3, 3])
            pairs.append((i, i + gap, t / np.linalg.norm(t)))
    bad = rng.choice(len(pairs), len(pairs) // 5, replace=False)
    for b in bad:
        v = rng.normal(size=3)
        pairs[b] = (pairs[b][0], pairs[b][1], v / np.linalg.norm(v))
    W0 = geo.so3_exp(torch.tensor([[0.05, -0.12, 0.06]], dtype=torch.float64))[0].numpy()
    assert rotation_angle_deg(W0) == pytest.approx(8.0, abs=0.5)
    turned = turn_centres(T, W0)
    assert np.allclose(turned[:, :3, :3], T[:, :3, :3])
    W, kept = direction_turn(turned, pairs)
    assert rotation_angle_deg(W @ W0) < 0.3
    assert len(pairs) - len(bad) - 5 <= kept <= len(pairs) - len(bad) + 5
    assert np.abs(turn_centres(turned, W)[:, :3, 3] - T[:, :3, 3]).max() < 0.01
    W_same, _ = direction_turn(T, pairs)
    assert rotation_angle_deg(W_same) < 0.3
    assert direction_turn(T, pairs[:2]) == (pytest.approx(np.eye(3)), 0)  # too few pairs: no turn


def test_linked_anchors_turn_the_centres_to_the_measured_directions(synth_shards_320: Path) -> None:
    """The networks' poses right but with every centre turned 8 deg about their mean (orientations
    kept): the protocol's centre fit then turns the world 8 deg from the orientations. The linked
    anchors measure the training pairs' two-view directions on the images (2 deg median error at
    128x96 on this scene) and turn the centres back: on the first sequence (which the links leave
    as given) the gap falls from 8 to under 3.5 deg. Asked for more agreeing pairs than there are,
    the build keeps the centres as they are and says how many agreed."""
    from relocdepth.anchors import build_linked_anchors, sequences_of, turn_centres
    from relocdepth.data import ImageFrames
    from relocdepth.evaluate import alignment_gap_deg, fit_sim3

    frames = ImageFrames.open(synth_shards_320)
    T_gt, depth_gt = _gt(synth_shards_320, frames)
    seqs = sequences_of(frames)
    W0 = geo.so3_exp(torch.tensor([[0.0, 0.12, 0.08]], dtype=torch.float64))[0].numpy()
    net = turn_centres(np.linalg.inv(T_gt[seqs[0][0]]) @ T_gt, W0)  # one world, centres turned
    calls = iter(range(len(seqs)))

    def poses(images: list[np.ndarray], K: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
        ix = seqs[next(calls)]
        return net[ix], [cv2.resize(depth_gt[i], (128, 96), interpolation=cv2.INTER_NEAREST) for i in ix]

    gaps = {}
    for turn in (False, True):
        calls = iter(range(len(seqs)))
        a = build_linked_anchors(frames, poses, (128, 96), turn=turn)
        ix = seqs[0]  # the first sequence's poses are kept as given (the links move the others)
        fit = fit_sim3(a.T_wc[ix].astype(np.float64), T_gt[ix])
        gaps[turn] = alignment_gap_deg(fit.R, a.T_wc[ix, :3, :3].astype(np.float64), T_gt[ix, :3, :3])
    assert gaps[False] == pytest.approx(rotation_angle_deg(W0), abs=0.5)
    assert gaps[True] < 3.5 and a.turn_pairs >= 20, (gaps, a.turn_pairs, a.turn_deg)
    assert a.turn_measured >= a.turn_pairs and a.turn_pairs >= 0.65 * a.turn_measured  # the default gate passed
    calls = iter(range(len(seqs)))
    strict = build_linked_anchors(frames, poses, (128, 96), turn=True,
                                  min_agreement=(a.turn_pairs + 1) / a.turn_measured)
    assert strict.turn_deg is None and (strict.turn_pairs, strict.turn_measured) == (a.turn_pairs, a.turn_measured)
    assert np.allclose(strict.T_wc[seqs[0]], net[seqs[0]], atol=1e-5)  # not turned


def test_trainer_builds_linked_anchors_from_its_own_networks(synth_shards: Path, tmp_path: Path) -> None:
    from relocdepth import checkpoint as ckpt_io
    from relocdepth.train import train

    run = tmp_path / "run"
    train(synth_shards, run, _cfg(anchor="linked", max_steps=2, anchor_turn_agreement=0.0))
    log = [json.loads(x) for x in (run / "logs" / "train.jsonl").read_text().splitlines()]
    built = [d for d in log if d.get("event") == "anchors"]
    assert [d["step"] for d in built] == [1] and built[0]["keyframes"] == 0  # no odometry
    assert len(built[0]["registration"]) == 1  # the second training sequence, linked to the first
    assert built[0]["turn_deg"] is not None and built[0]["turn_measured"] >= built[0]["turn_pairs"] >= 0  # turned
    assert _cfg(anchor="linked", anchor_turn=False).anchor_turn is False
    assert _cfg(anchor="linked").anchor_turn_agreement == pytest.approx(TURN_MIN_AGREEMENT)  # one default
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(UserError, match="anchor-turn-agreement"):
            _cfg(anchor="linked", anchor_turn_agreement=bad)
    assert "L_anchor" in [d for d in log if "loss" in d][-1]["parts"]
    T = ckpt_io.load_checkpoint(ckpt_io.list_checkpoints(run)[-1])["anchors"]["T_wc"]
    assert T.shape == (48, 4, 4) and torch.isfinite(T).all() and not torch.allclose(T[0], torch.eye(4))


def test_depth_scale_term_holds_only_the_one_scale_of_all_depths() -> None:
    """Depth maps of three frames at their references: L_scale = 0; all of them s times deeper:
    (log s)^2, ``scale_drift`` log s, the total the paper's plus w times it; each frame's depth
    reshaped with its mean log kept (half its pixels twice as deep, half half as deep): 0 again.
    Its gradient on a log scale of all depths is 2 log s (and a finite difference agrees); it
    reaches the depth network only."""
    torch.manual_seed(0)
    nets = Networks(ModelConfig())
    imgs = torch.rand(1, 3, 3, H, W)
    K = torch.tensor([[60.0, 0, (W - 1) / 2], [0, 60.0, (H - 1) / 2], [0, 0, 1]]).expand(1, 3, 3, 3).clone()
    cfg = MethodConfig(photometric_pixels="all")
    depth = 1.0 + torch.rand(1, 3, 1, H, W) * torch.tensor([1.0, 2.0, 3.0]).reshape(1, 3, 1, 1, 1)
    ref = torch.log(depth).reshape(1, 3, -1).mean(-1)

    def held(d: torch.Tensor, w: float = 1.0):
        return triplet_loss(nets, imgs, imgs, K, cfg, Bootstrap(False, 0.0, depth_ref=ref, w_depth_scale=w),
                            depth_override=d)

    _, parts, diag = held(depth)
    assert float(parts["L_scale"]) < 1e-12 and abs(diag["scale_drift"]) < 1e-6
    total, parts, diag = held(depth * 1.3, w=2.0)
    assert float(parts["L_scale"]) == pytest.approx(math.log(1.3) ** 2, rel=1e-4)
    assert diag["scale_drift"] == pytest.approx(math.log(1.3), rel=1e-4)
    paper, _, _ = triplet_loss(nets, imgs, imgs, K, cfg, depth_override=depth * 1.3)
    assert float(total.detach()) == pytest.approx(float(paper.detach()) + 2.0 * float(parts["L_scale"]), rel=1e-5)
    checker = torch.ones(H, W)
    checker[:, : W // 2] = 2.0
    checker[:, W // 2:] = 0.5
    _, parts, _ = held(depth * checker)
    assert float(parts["L_scale"]) < 1e-10

    def l_scale(a: torch.Tensor) -> torch.Tensor:
        return held(depth * torch.exp(a))[1]["L_scale"]

    a = torch.tensor(0.2, dtype=torch.float64, requires_grad=True)
    l_scale(a.float()).backward()
    eps = 1e-3
    fd = (float(l_scale(torch.tensor(0.2 + eps))) - float(l_scale(torch.tensor(0.2 - eps)))) / (2 * eps)
    assert float(a.grad) == pytest.approx(0.4, rel=1e-3) and fd == pytest.approx(0.4, rel=1e-2)
    nets.zero_grad()
    _, parts, _ = triplet_loss(nets, imgs, imgs, K, cfg,
                               Bootstrap(False, 0.0, depth_ref=ref + 0.5, w_depth_scale=1.0))
    parts["L_scale"].backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in nets.depth.parameters())
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in nets.dsc.parameters())


def test_trainer_holds_the_depth_scale_where_the_first_anchors_were_built(synth_shards: Path,
                                                                        tmp_path: Path) -> None:
    """``w_depth_scale``, anchors rebuilt every step: the references are the frames' mean log
    depth from the network as it was at the first build (recomputed here from the checkpoint
    before it), the same after every rebuild and after a resume; the steps after the first build
    log ``L_scale`` and ``scale_drift``, the step before neither; without ``--anchor vo`` or
    below 0 the option is one error."""
    from relocdepth import checkpoint as ckpt_io
    from relocdepth.anchors import network_depth, sequences_of
    from relocdepth.data import ImageFrames, scale_and_crop
    from relocdepth.train import TrainConfig, train

    run = tmp_path / "run"
    train(synth_shards, run, _cfg(max_steps=3, anchor_every=1, w_depth_scale=1.0, checkpoint_every=1, keep_last=5))
    log = [json.loads(x) for x in (run / "logs" / "train.jsonl").read_text().splitlines()]
    assert [d["step"] for d in log if d.get("event") == "anchors"] == [1, 2]
    steps = [d for d in log if "loss" in d]
    assert "L_scale" not in steps[0]["parts"] and "scale_drift" not in steps[0]["diagnostics"]
    assert all("L_scale" in d["parts"] and math.isfinite(d["diagnostics"]["scale_drift"]) for d in steps[1:])
    cks = {c["meta"]["step"]: c for c in map(ckpt_io.load_checkpoint, ckpt_io.list_checkpoints(run))}
    ref = cks[2]["anchors"]["depth_ref"]
    assert torch.equal(cks[3]["anchors"]["depth_ref"], ref)  # not moved by the rebuild at step 2
    cfg = _cfg()
    nets = Networks(cfg.model)
    nets.load_state_dict(cks[1]["model"])  # the weights the first build saw
    frames = ImageFrames.open(synth_shards)
    W_, H_ = cfg.size
    want = torch.zeros(len(frames.frames))
    for ix in sequences_of(frames):
        ims = [scale_and_crop(frames.read_image(i), frames.frames[i].intrinsics, W_, H_, 1.0, 0.0, 0.0)[0] for i in ix]
        maps = network_depth(nets.depth, ims, torch.device("cpu"), cfg.method.min_depth, cfg.method.max_depth)
        want[ix] = torch.tensor([float(np.log(d).mean()) for d in maps])
    assert ref.shape == (len(frames.frames),) and torch.allclose(ref, want, atol=1e-5)
    train(synth_shards, run, _cfg(max_steps=4, anchor_every=1, w_depth_scale=1.0, resume=True))
    assert torch.equal(ckpt_io.load_checkpoint(ckpt_io.list_checkpoints(run)[-1])["anchors"]["depth_ref"], ref)
    with pytest.raises(UserError, match="--w-depth-scale needs --anchor vo"):
        TrainConfig.from_dict({"w_depth_scale": 1.0})
    with pytest.raises(UserError, match="--w-depth-scale must be a number >= 0"):
        _cfg(w_depth_scale=-1.0)


def test_strided_frames_and_poses_in_between() -> None:
    """``strided`` keeps every n-th frame and the last; ``in_between`` puts a frame between two kept
    ones on the line between their centres and on the arc between their orientations: a camera
    moving and turning at constant rates is rebuilt exactly from every third pose."""
    from scipy.spatial.transform import Rotation

    from relocdepth.anchors import in_between, strided

    assert strided(10, 3) == [0, 3, 6, 9] and strided(11, 3) == [0, 3, 6, 9, 10]
    assert strided(5, 1) == [0, 1, 2, 3, 4] and strided(1, 4) == [0]
    n = 11
    T = np.repeat(np.eye(4)[None], n, axis=0)
    T[:, :3, :3] = Rotation.from_rotvec(np.outer(np.arange(n), np.radians([1.0, 2.0, -0.5]))).as_matrix()
    T[:, :3, 3] = np.outer(np.arange(n), [0.01, -0.02, 0.005]) + [1.0, 2.0, 3.0]
    kept = strided(n, 3)
    assert np.allclose(in_between(T[kept], kept, n), T, atol=1e-12)
    # a turn about another axis halfway between two kept frames: half the angle, the centres' midpoint
    R = Rotation.from_rotvec([0.0, 0.0, np.radians(40)]).as_matrix()
    two = np.repeat(np.eye(4)[None], 2, axis=0)
    two[1, :3, :3], two[1, :3, 3] = R, [0.2, 0.0, 0.0]
    mid = in_between(two, [0, 2], 3)[1]
    assert np.isclose(rotation_angle_deg(mid[:3, :3]), 20.0) and np.allclose(mid[:3, 3], [0.1, 0, 0])
    assert np.isclose(rotation_angle_deg(mid[:3, :3].T @ R), 20.0)
    with pytest.raises(ValueError, match="do not span"):
        in_between(T[[0, 3]], [0, 3], n)  # the last frame not among them


def test_strided_anchors_run_the_odometry_on_the_kept_frames(synth_shards: Path) -> None:
    """``stride`` 2: the first sequence's kept frames are anchored at the odometry of those frames
    alone, the others in between them; depth is asked for every frame; with true depth the first
    sequence is as metric and right as with every frame (the bounds of the test above)."""
    from relocdepth.anchors import build_anchors, in_between, sequences_of, strided
    from relocdepth.data import ImageFrames, scale_and_crop
    from relocdepth.vo import world_trajectory

    frames = ImageFrames.open(synth_shards)
    T_gt, depth_gt = _gt(synth_shards, frames)
    seqs = sequences_of(frames)
    W_, H_ = frames.frames[0].intrinsics.width, frames.frames[0].intrinsics.height
    asked: list[int] = []

    def depth(ix: list[int], ims: list[np.ndarray]) -> list[np.ndarray]:
        asked.extend(ix)
        return [depth_gt[i] for i in ix]

    a = build_anchors(frames, depth, (W_, H_), stride=2)
    assert sorted(asked) == list(range(len(frames))) and a.lost == 0 and len(a.registration) == len(seqs) - 1
    ix = seqs[0]
    kept = strided(len(ix), 2)
    assert len(kept) < len(ix)
    images = [scale_and_crop(frames.read_image(ix[k]), frames.frames[ix[k]].intrinsics, W_, H_, 1.0, 0, 0)[0]
              for k in kept]
    w = world_trajectory([images], [frames.frames[0].intrinsics.K()], [lambda j: depth_gt[ix[kept[j]]]])
    assert a.keyframes <= sum(len(strided(len(s), 2)) for s in seqs)
    assert np.allclose(a.T_wc[ix], in_between(w.world[0], kept, len(ix)).astype(np.float32), atol=1e-6)
    rel_gt = np.linalg.inv(T_gt[ix[0]]) @ T_gt[ix]
    path = np.linalg.norm(np.diff(T_gt[ix, :3, 3], axis=0), axis=1).sum()
    err = np.linalg.norm(a.T_wc[ix, :3, 3] - rel_gt[:, :3, 3], axis=1)
    assert path > 0.1 and err.max() < 0.4 * path, (err, path)
    assert rotation_angle_deg(np.swapaxes(a.T_wc[ix, :3, :3], -1, -2) @ rel_gt[:, :3, :3]).max() < 5.0
    with pytest.raises(ValueError, match="stride must be >= 0"):
        build_anchors(frames, depth, (W_, H_), stride=-1)


def test_automatic_stride_follows_each_sequences_length(synth_shards: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Stride 0: a sequence of up to ``ODOMETRY_FRAMES`` frames keeps every frame; a longer one the
    smallest stride that keeps at most that many (and its last). In a build each sequence takes its
    own: the fixture's, every frame; with the bound under half the longest's length, fewer."""
    import relocdepth.anchors as A
    from relocdepth.data import ImageFrames

    most = A.ODOMETRY_FRAMES
    assert A.sequence_stride(most, 0) == A.sequence_stride(most + 1, 0) == 1 and A.sequence_stride(most + 2, 0) == 2
    assert A.sequence_stride(1000, 0) == 2 and A.sequence_stride(7000, 0) == 14 and A.sequence_stride(1000, 3) == 3
    for n in range(1, 4000, 37):
        k = A.sequence_stride(n, 0)
        assert len(A.strided(n, k)) <= most + 1 and (k == 1 or len(A.strided(n, k - 1)) > most + 1), n
    frames = ImageFrames.open(synth_shards)
    _, depth_gt = _gt(synth_shards, frames)
    seqs = A.sequences_of(frames)

    def depth(ix: list[int], ims: list[np.ndarray]) -> list[np.ndarray]:
        return [depth_gt[i] for i in ix]

    size = (frames.frames[0].intrinsics.width, frames.frames[0].intrinsics.height)
    assert A.build_anchors(frames, depth, size, stride=0).odometry_frames == len(frames)
    monkeypatch.setattr(A, "ODOMETRY_FRAMES", (max(map(len, seqs)) - 1) // 2)
    thinned = [A.strided(len(ix), A.sequence_stride(len(ix), 0)) for ix in seqs]
    assert all(len(h) < len(ix) for h, ix in zip(thinned, seqs))
    assert A.build_anchors(frames, depth, size, stride=0).odometry_frames == sum(map(len, thinned))


def test_trainer_builds_strided_anchors(synth_shards: Path, tmp_path: Path) -> None:
    """``anchor_stride`` reaches the build: its event says on how many frames the odometry ran
    (every second of each sequence, and its last), without stride on all."""
    from relocdepth.anchors import sequences_of, strided
    from relocdepth.data import ImageFrames
    from relocdepth.train import train

    seqs = sequences_of(ImageFrames.open(synth_shards))
    for stride, frames in ((2, sum(len(strided(len(ix), 2)) for ix in seqs)), (1, sum(map(len, seqs)))):
        run = tmp_path / f"run{stride}"
        train(synth_shards, run, _cfg(max_steps=2, anchor_stride=stride))
        log = [json.loads(x) for x in (run / "logs" / "train.jsonl").read_text().splitlines()]
        assert [d["odometry_frames"] for d in log if d.get("event") == "anchors"] == [frames]
    assert frames > sum(len(strided(len(ix), 2)) for ix in seqs)
