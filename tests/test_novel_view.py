"""The moved view (a frame seen from a camera moved back or aside, synthesised from its image and
depth) against the renderer, and L_nv against known geometry."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from relocdepth import geometry as geo
from relocdepth.method import MethodConfig, novel_view_loss, triplet_loss
from relocdepth.models import ModelConfig, build_networks

torch.set_num_threads(1)
H, W = 64, 96


def _K(B: int = 1) -> torch.Tensor:
    K = torch.tensor([[80.0, 0, (W - 1) / 2], [0, 80.0, (H - 1) / 2], [0, 0, 1]])
    return K.expand(B, 3, 3).clone()


@pytest.fixture(scope="module")
def scene() -> dict:
    from relocdepth.camera import Intrinsics
    from relocdepth.synth import SynthConfig, build_scene, camera_paths

    intr = Intrinsics(fx=80.0, fy=80.0, cx=(W - 1) / 2, cy=(H - 1) / 2, width=W, height=H)
    return {"scene": build_scene(0, SynthConfig(width=W, height=H)), "intr": intr,
            "poses": camera_paths(SynthConfig(frames=120))["seq-01"][::40]}


def _image(rgb: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(rgb).permute(2, 0, 1)[None].float()


@pytest.mark.parametrize("move", [(0.0, 0.0, -0.2), (0.1, -0.05, -0.1), (0.0, 0.0, 0.1)])
def test_moved_view_is_the_rendered_view(scene: dict, move: tuple) -> None:
    """A frame moved back, aside or forward by a fraction of its median depth, synthesised from its
    rendered image and depth, is what the renderer draws from the moved camera: colours within a few
    grey levels (as the exactness check of the renderer's warps; moved forward, the frame's pixels
    are magnified), depth exact, over most of the image; the unmoved frame is far from it there."""
    from relocdepth.synth import render

    for T in scene["poses"]:
        rgb, depth = render(scene["scene"], T, scene["intr"])
        t = np.asarray(move) * float(np.median(depth))
        T2 = T.copy()
        T2[:3, 3] = T[:3, :3] @ t + T[:3, 3]
        rgb2, depth2 = render(scene["scene"], T2, scene["intr"])
        image, z, valid, _ = geo.moved_view(_image(rgb), torch.from_numpy(depth)[None, None],
                                         torch.tensor(t, dtype=torch.float32)[None], _K())
        v = valid[0, 0].numpy()
        assert v.mean() > 0.55  # moved back 20 %: ~0.65 (the rest beyond the frame's edges)
        diff = np.abs(image[0].permute(1, 2, 0).numpy() - rgb2).mean(-1)[v]
        unmoved = np.abs(rgb.astype(np.float64) - rgb2).mean(-1)[v]
        assert np.median(diff) < 3 and np.median(unmoved) > 5 * np.median(diff), (np.median(diff), np.median(unmoved))
        rel = np.abs(z[0, 0].numpy() / depth2 - 1)[v]
        assert np.median(rel) < 1e-3 and np.percentile(rel, 90) < 0.02


def test_moved_view_unmoved_is_the_frame() -> None:
    gen = torch.Generator().manual_seed(0)
    image = torch.rand(2, 3, H, W, generator=gen)
    depth = 1.0 + torch.rand(2, 1, H, W, generator=gen)
    out, z, valid, _ = geo.moved_view(image, depth, torch.zeros(2, 3), _K(2))
    assert torch.allclose(out, image, atol=1e-4) and torch.allclose(z, depth, atol=1e-4) and bool(valid.all())


def _disp_of(depth: torch.Tensor, cfg: MethodConfig) -> torch.Tensor:
    """The sigmoid output that ``disp_to_depth`` turns into ``depth``."""
    b = 1.0 / cfg.max_depth
    return (1.0 / depth - b) / (1.0 / cfg.min_depth - b)


def _plane_case(back: float, d: float = 2.0) -> dict:
    """A frame looking at a wall d away, its pose, and the networks' outputs for it."""
    cfg = MethodConfig(w_novel_view=1.0, novel_view_back=0.25)
    K = _K()
    T = torch.eye(4)[None]
    T[0, :3, :3] = geo.so3_exp(torch.tensor([0.1, -0.4, 0.05]))
    T[0, :3, 3] = torch.tensor([0.3, -0.2, 1.0])
    depth = torch.full((1, 1, H, W), d)
    cells = geo.pool_depth(depth)
    T_back = T.clone()
    T_back[0, :3, 3] = T[0, :3, 3] - back * d * T[0, :3, 2]  # moved back along its optical axis
    return {"cfg": cfg, "K": K, "disp": _disp_of(depth, cfg), "dsc": geo.dsc_from_pose(T, cells, K),
            "T": T, "T_back": T_back, "cells": cells, "d": d}


def _nets(depth_out: torch.Tensor, dsc_out: torch.Tensor) -> SimpleNamespace:
    return SimpleNamespace(depth=lambda x: [depth_out], dsc=lambda x: dsc_out)


@pytest.mark.parametrize("back", [0.2, -0.2])
def test_novel_view_loss_is_zero_for_networks_that_see_the_move(back: float) -> None:
    """A wall 2 m away, seen from 0.4 m further back (or nearer): networks that place the new view
    there (depth 2.4 or 1.6, pose moved) give L_nv = 0; networks that keep to the frame's distance
    (depth 2.0, the frame's pose: what the networks do on views farther than their training frames)
    give the log ratio and the move over the depth."""
    c = _plane_case(back)
    cfg, d = c["cfg"], c["d"]
    inputs = torch.rand(1, 3, H, W)
    right = _nets(_disp_of(torch.full((1, 1, H, W), d * (1 + back)), cfg),
                  geo.dsc_from_pose(c["T_back"], c["cells"] * (1 + back), c["K"]))
    parts, diag = novel_view_loss(right, inputs, c["disp"], c["dsc"], c["K"], cfg, back=torch.tensor([back]))
    assert float(parts["L_nv_depth"]) < 1e-4 and float(parts["L_nv_pose"]) < 1e-4
    assert abs(diag["nv_depth_ratio"] - 1) < 1e-4 and diag["nv_trans"] < 1e-4
    assert abs(diag["nv_back"] - back) < 1e-6 and 0.5 < diag["nv_valid"] < 1
    # every cell placing the new view where the frame was
    stay = _nets(c["disp"], geo.dsc_from_pose(c["T"], c["cells"] * (1 + back), c["K"]))
    parts, diag = novel_view_loss(stay, inputs, c["disp"], c["dsc"], c["K"], cfg, back=torch.tensor([back]))
    assert float(parts["L_nv_depth"]) == pytest.approx(abs(math.log(1 + back)), rel=1e-3)
    assert diag["nv_depth_ratio"] == pytest.approx(1 / (1 + back), rel=1e-3)
    # the centres 0.4 m off, over the frame's 2 m; the rotations right
    assert diag["nv_trans"] == pytest.approx(abs(back), rel=1e-3)
    assert float(parts["L_nv_pose"]) == pytest.approx(abs(back), rel=1e-3)
    # a scale of all depths changes nothing (so the term cannot push one), and its gradient reaches
    # the frame's depth as well as the new view's
    disp3 = _disp_of(torch.full((1, 1, H, W), 3 * d), cfg).requires_grad_()
    stay3 = _nets(disp3, geo.dsc_from_pose(c["T"], c["cells"] * (1 + back), c["K"]))
    src3 = _disp_of(torch.full((1, 1, H, W), 3 * d), cfg).requires_grad_()
    parts3, _ = novel_view_loss(stay3, inputs, src3, c["dsc"], c["K"], cfg, back=torch.tensor([back]))
    assert float(parts3["L_nv_depth"].detach()) == pytest.approx(abs(math.log(1 + back)), rel=1e-3)
    parts3["L_nv_depth"].backward()
    assert float(src3.grad.abs().sum()) > 0 and float(disp3.grad.abs().sum()) > 0


def test_novel_view_depth_only_is_the_depth_term_alone() -> None:
    """With ``novel_view_pose`` False the depth term is the same number as with both, the pose term
    is 0 and the DSC network is neither run on the new view nor needed at all."""
    back = 0.2
    c = _plane_case(back)
    inputs = torch.rand(1, 3, H, W)
    stay = _nets(c["disp"], geo.dsc_from_pose(c["T"], c["cells"] * (1 + back), c["K"]))
    both, _ = novel_view_loss(stay, inputs, c["disp"], c["dsc"], c["K"], c["cfg"], back=torch.tensor([back]))
    cfg = MethodConfig(w_novel_view=1.0, novel_view_back=0.25, novel_view_pose=False, use_dsc=False)

    def no_dsc(x):
        raise AssertionError("the DSC network ran")

    alone = SimpleNamespace(depth=stay.depth, dsc=no_dsc)
    for dsc in (c["dsc"], None):
        parts, diag = novel_view_loss(alone, inputs, c["disp"], dsc, c["K"], cfg, back=torch.tensor([back]))
        assert float(parts["L_nv_depth"]) == pytest.approx(math.log(1 + back), rel=1e-3)
        assert float(parts["L_nv_depth"]) == pytest.approx(float(both["L_nv_depth"]), rel=1e-6)
        assert float(parts["L_nv_pose"]) == 0 and "nv_trans" not in diag
    assert float(both["L_nv_pose"]) == pytest.approx(back, rel=1e-3)


def test_novel_view_leaves_the_running_statistics() -> None:
    """The networks' passes on the new views (training mode) leave the BatchNorm running statistics
    that localize and evaluate use as they were, and the layers' momentum as it was; a pass on the
    same views outside the term moves them."""
    torch.manual_seed(0)
    nets = build_networks(ModelConfig())
    nets.train()
    gen = torch.Generator().manual_seed(5)
    x = torch.rand(2, 3, H, W, generator=gen)
    disp = nets.depth(x)[0].detach()
    dsc = nets.dsc(x).detach()
    before = {k: v.clone() for k, v in nets.state_dict().items() if "running" in k or "tracked" in k}
    parts, _ = novel_view_loss(nets, x, disp, dsc, _K(2), MethodConfig(w_novel_view=1.0))
    (parts["L_nv_depth"] + parts["L_nv_pose"]).backward()
    after = nets.state_dict()
    assert before and all(torch.equal(v, after[k]) for k, v in before.items())
    norms = [m for m in nets.modules() if isinstance(m, torch.nn.BatchNorm2d)]
    assert norms and all(m.momentum == 0.1 for m in norms)
    nets.depth(x)
    nets.dsc(x)
    moved = nets.state_dict()
    assert any(not torch.equal(v, moved[k]) for k, v in before.items() if "running_mean" in k)


def test_novel_view_window_hides_how_far_back() -> None:
    """The new view's pixels outside the central window are grey whatever the move, so the border
    says nothing of it; inside, the frame's content."""
    c = _plane_case(0.1)
    seen = []
    net = SimpleNamespace(depth=lambda x: (seen.append(x.clone()), [c["disp"]])[1], dsc=lambda x: c["dsc"])
    inputs = torch.rand(1, 3, H, W)
    for back in (0.0, 0.05, 0.25, -0.1):
        novel_view_loss(net, inputs, c["disp"], c["dsc"], c["K"], c["cfg"], back=torch.tensor([back]))
    keep = 1 / (1 + c["cfg"].novel_view_back)
    u = (torch.arange(W) - (W - 1) / 2).abs() <= keep * W / 2
    v = (torch.arange(H) - (H - 1) / 2).abs() <= keep * H / 2
    window = v[:, None] & u[None, :]
    for x in seen:
        assert bool((x[0][:, ~window] == 0.5).all()) and not bool((x[0][:, window] == 0.5).all())
    assert torch.allclose(seen[0][0][:, window], inputs[0][:, window], atol=1e-4)  # unmoved: the frame


def test_novel_view_weight_is_wired() -> None:
    """With its weight set L_nv's two terms are in the parts and the total, their gradient reaches
    both networks; without it nothing is computed."""
    torch.manual_seed(0)
    nets = build_networks(ModelConfig())
    gen = torch.Generator().manual_seed(3)
    imgs = torch.rand(2, 3, 3, H, W, generator=gen)
    K = _K(2)[:, None].expand(2, 3, 3, 3).clone()
    _, parts0, diag0 = triplet_loss(nets, imgs, imgs, K, MethodConfig())
    assert "L_nv_depth" not in parts0 and "nv_depth_ratio" not in diag0
    torch.manual_seed(1)
    total, parts, diag = triplet_loss(nets, imgs, imgs, K, MethodConfig(w_novel_view=0.5))
    assert {"L_nv_depth", "L_nv_pose"} <= set(parts) and 0 <= diag["nv_back"] <= 0.2
    rest = parts["L_p"] + 0.001 * parts["L_s"] + 0.03 * parts["L_c"]
    assert torch.allclose(total, rest + 0.5 * (parts["L_nv_depth"] + parts["L_nv_pose"]), atol=1e-6)
    nets.zero_grad()
    (parts["L_nv_depth"] + parts["L_nv_pose"]).backward()
    for net in (nets.depth, nets.dsc):
        assert sum(float(p.grad.abs().sum()) for p in net.parameters() if p.grad is not None) > 0
    # the depth term alone, with the two-frame pose network instead of the DSC
    torch.manual_seed(0)
    nets_p = build_networks(ModelConfig(use_dsc=False))
    cfg_p = MethodConfig(w_novel_view=0.5, novel_view_pose=False, use_dsc=False)
    total, parts, _ = triplet_loss(nets_p, imgs, imgs, K, cfg_p)
    assert float(parts["L_nv_pose"]) == 0 and float(parts["L_nv_depth"].detach()) > 0
    nets_p.zero_grad()
    parts["L_nv_depth"].backward()
    assert sum(float(p.grad.abs().sum()) for p in nets_p.depth.parameters() if p.grad is not None) > 0
    for bad in ({"w_novel_view": -1.0}, {"novel_view_back": 0.0}, {"novel_view_back": 1.5},
                {"novel_view_forward": -0.1}, {"novel_view_forward": 0.6},
                {"w_novel_view": 0.5, "use_dsc": False}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            MethodConfig(**bad)


def test_novel_view_forward_draws_moves_both_ways() -> None:
    """With ``novel_view_forward`` the drawn moves span [-forward, back] (the window stays the back
    move's), without it [0, back]; each move gives the depth ratio of a wall seen from there."""
    c = _plane_case(0.0)
    inputs = torch.rand(1, 3, H, W)
    net = _nets(c["disp"], c["dsc"])
    for forward, lo, hi in ((0.0, 0.0, 0.25), (0.25, -0.25, 0.25), (0.1, -0.1, 0.25)):
        cfg = MethodConfig(w_novel_view=1.0, novel_view_back=0.25, novel_view_forward=forward)
        torch.manual_seed(0)
        moves = []
        for _ in range(200):
            _, diag = novel_view_loss(net, inputs, c["disp"], c["dsc"], c["K"], cfg)
            moves.append(diag["nv_back"])
            # a network that keeps the frame's depth is off by the move's ratio
            assert diag["nv_depth_ratio"] == pytest.approx(1 / (1 + diag["nv_back"]), rel=1e-3)
        moves = np.array(moves)
        assert lo <= moves.min() < lo + 0.03 and hi - 0.03 < moves.max() <= hi, (forward, moves.min(), moves.max())
        assert abs(moves.mean() - (lo + hi) / 2) < 0.03


def test_novel_view_one_way_moves_the_frame_only_by_its_scale() -> None:
    """``novel_view_one_way``: the same value of L_nv_depth, the same derivative along a scale of the
    frame's depth, and a gradient on the frame's depth that is one signed field (its mean log moves,
    not its shape) where both ways it pulls the frame's pixels opposite ways where the network
    places parts of the new view too near and others too far; the new view's gradient is unchanged."""
    back = 0.2
    gen = torch.Generator().manual_seed(4)
    inputs = torch.rand(1, 3, H, W, generator=gen)
    # a wall 2 m away with a bump: a frame depth that is not flat
    u = torch.linspace(-1, 1, W)[None, None, None, :]
    frame = 2.0 * torch.exp(0.2 * torch.cos(3 * u) * torch.ones(1, 1, H, 1))
    med = frame.reshape(-1).median()
    _, z, valid, _ = geo.moved_view(inputs, frame, torch.tensor([[0.0, 0.0, -back * float(med)]]), _K())
    # the network places the new view's left third 30 % too far and the rest 10 % too near
    bump = torch.where(u < -0.3, torch.tensor(0.3), torch.tensor(-0.1))
    results = {}
    for one_way in (False, True):
        cfg = MethodConfig(w_novel_view=1.0, novel_view_back=0.25, novel_view_pose=False, use_dsc=False,
                           novel_view_one_way=one_way)
        log_frame = torch.log(frame).clone().requires_grad_()
        new = _disp_of(z * torch.exp(bump), cfg).clone().requires_grad_()
        net = SimpleNamespace(depth=lambda x, new=new: [new], dsc=None)
        disp = _disp_of(torch.exp(log_frame), cfg)
        parts, _ = novel_view_loss(net, inputs, disp, None, _K(), cfg, back=torch.tensor([back]))
        parts["L_nv_depth"].backward()
        results[one_way] = (float(parts["L_nv_depth"].detach()), log_frame.grad[0, 0].clone(), new.grad.clone())
    (v_both, g_both, n_both), (v_one, g_one, n_one) = results[False], results[True]
    assert v_one == pytest.approx(v_both, rel=1e-6) and v_both > 0.1
    assert torch.allclose(n_one, n_both, atol=1e-7) and float(n_both.abs().sum()) > 0
    # along a scale of the frame's depth both move the loss alike
    assert float(g_one.sum()) == pytest.approx(float(g_both.sum()), rel=1e-4) and abs(float(g_both.sum())) > 1e-3
    # both ways the frame is pulled opposite ways in the two parts; one way, all one sign
    assert float(g_both.max()) > 1e-6 and float(g_both.min()) < -1e-6
    assert float(g_one.max()) <= 1e-9 or float(g_one.min()) >= -1e-9
    assert float(g_one.abs().sum()) > 0


def test_novel_view_decoder_only_keeps_the_encoder_out_of_the_new_views() -> None:
    """``novel_view_decoder_only``: the same value of L_nv_depth; the new views' gradient reaches
    the depth network's decoder, with the same values as over the whole network, and not its
    encoder, which the whole network's does reach."""
    x = torch.rand(2, 3, H, W, generator=torch.Generator().manual_seed(6))
    grads = {}
    for decoder_only in (False, True):
        torch.manual_seed(0)
        nets = build_networks(ModelConfig())
        nets.train()
        disp = nets.depth(x)[0].detach()  # the frame's own depth out of it: the new views' path alone
        cfg = MethodConfig(w_novel_view=1.0, novel_view_pose=False, novel_view_decoder_only=decoder_only)
        parts, _ = novel_view_loss(nets, x, disp, None, _K(2), cfg, back=torch.tensor([0.2, 0.1]))
        parts["L_nv_depth"].backward()
        grads[decoder_only] = (float(parts["L_nv_depth"].detach()),
                               [p.grad for p in nets.depth.encoder.parameters()],
                               [p.grad for p in nets.depth.decoder.parameters()])
    (v_all, enc_all, dec_all), (v_dec, enc_dec, dec_dec) = grads[False], grads[True]
    assert v_dec == pytest.approx(v_all, rel=1e-6) and v_all > 0
    assert all(g is None for g in enc_dec)
    assert sum(float(g.abs().sum()) for g in enc_all if g is not None) > 0
    # (the coarser scales' output layers take no part: no gradient either way)
    assert all((a is None and b is None) or torch.allclose(a, b, rtol=1e-4, atol=1e-7)
               for a, b in zip(dec_all, dec_dec))
    assert sum(float(g.abs().sum()) for g in dec_dec if g is not None) > 0


def test_novel_view_options_reach_the_config_and_bad_values_are_one_line(tmp_path) -> None:
    from relocdepth.cli.main import app
    from relocdepth.train import TrainConfig
    from typer.testing import CliRunner

    cfg = TrainConfig.from_dict({"w_novel_view": 0.5, "novel_view_back": 0.3, "novel_view_forward": 0.2})
    assert cfg.method.w_novel_view == 0.5 and cfg.method.novel_view_back == 0.3
    assert cfg.method.novel_view_forward == 0.2
    assert cfg.method.novel_view_pose and not TrainConfig.from_dict({"novel_view_pose": False}).method.novel_view_pose
    assert not cfg.method.novel_view_one_way and TrainConfig.from_dict({"novel_view_one_way": True}).method.novel_view_one_way
    assert not cfg.method.novel_view_decoder_only
    assert TrainConfig.from_dict({"novel_view_decoder_only": True}).method.novel_view_decoder_only
    run = tmp_path / "run"
    for args, message in ((["--w-novel-view", "0.5", "--no-dsc"], "w_novel_view needs the DSC network"),
                          (["--novel-view-back", "2"], "novel_view_back must be in (0, 1]"),
                          (["--novel-view-forward", "0.9"], "novel_view_forward must be in [0, 0.5]")):
        res = CliRunner().invoke(app, ["train", str(tmp_path), "-o", str(run), *args])
        assert res.exit_code == 2 and message in res.output, res.output
        assert len(res.output.strip().splitlines()) == 1 and not run.exists()


def test_novel_view_steps_leave_the_term_out_after_them(synth_shards, tmp_path) -> None:
    """`--novel-view-steps 2`: the logged steps 1 and 2 hold L_nv's terms and a positive total of
    them, steps 3 and 4 neither; the option reaches the run's config, and a negative count is one
    error line with no run folder."""
    import json

    from relocdepth.cli.main import app
    from relocdepth.train import TrainConfig, novel_view_at
    from typer.testing import CliRunner

    cfg = TrainConfig.from_dict({"w_novel_view": 0.1, "novel_view_steps": 2})
    assert [novel_view_at(cfg, s) for s in range(4)] == [True, True, False, False]
    assert all(novel_view_at(TrainConfig.from_dict({"w_novel_view": 0.1}), s) for s in (0, 10 ** 6))
    assert not novel_view_at(TrainConfig.from_dict({"novel_view_steps": 2}), 0)
    run = tmp_path / "run"
    common = ["train", str(synth_shards), "-o", str(run), "--size", "64x64", "--batch-size", "2", "--pretrained",
              "none", "--workers", "0", "--no-progress", "--log-every", "1", "--max-steps", "4", "--w-novel-view", "0.5"]
    res = CliRunner().invoke(app, [*common, "--novel-view-steps", "2"])
    assert res.exit_code == 0, res.output[-3000:]
    assert json.loads((run / "config.json").read_text())["train"]["method"]["novel_view_steps"] == 2
    steps = [e for e in map(json.loads, (run / "logs" / "train.jsonl").read_text().splitlines())
             if e["kind"] == "step"]
    assert [e["step"] for e in steps] == [1, 2, 3, 4]
    for e in steps[:2]:
        assert e["parts"]["L_nv_depth"] + e["parts"]["L_nv_pose"] > 0
    for e in steps[2:]:
        assert "L_nv_depth" not in e["parts"] and "L_nv_pose" not in e["parts"]
    bad = tmp_path / "bad"
    res = CliRunner().invoke(app, ["train", str(synth_shards), "-o", str(bad), "--novel-view-steps", "-1"])
    assert res.exit_code == 2 and "novel_view_steps must be >= 0" in res.output, res.output
    assert len(res.output.strip().splitlines()) == 1 and not bad.exists()
