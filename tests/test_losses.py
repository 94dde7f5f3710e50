"""Losses and the triplet loss: ground-truth warps on the synth scene, pairs, symmetry, gradients."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from relocdepth import geometry as geo
from relocdepth.losses import (
    photometric_loss,
    pose_coordinate_loss,
    smoothness_loss,
    ssim_distance,
)
from relocdepth.method import LOSS_RESOLUTIONS, MethodConfig, pairs_for, predict, triplet_loss
from relocdepth.models import ModelConfig, build_networks

torch.set_num_threads(1)
H, W = 64, 96


def _K(B: int, n: int | None = None) -> torch.Tensor:
    K = torch.tensor([[80.0, 0, (W - 1) / 2], [0, 80.0, (H - 1) / 2], [0, 0, 1]])
    return K.expand(B, 3, 3).clone() if n is None else K.expand(B, n, 3, 3).clone()


# --------------------------------------------------------------------------------- the loss terms


def test_photometric_terms() -> None:
    gen = torch.Generator().manual_seed(0)
    a = torch.rand(2, 3, 16, 16, generator=gen)
    ones = torch.ones(2, 1, 16, 16)
    assert float(ssim_distance(a, a).max()) < 1e-6
    assert torch.allclose(photometric_loss(a, a, ones), torch.zeros(2), atol=1e-6)
    b = (a + 0.1).clamp(0, 1)
    lp = photometric_loss(a, b, ones)
    assert (lp > 0).all()
    # only valid pixels count: corrupting invalid pixels changes nothing
    half = ones.clone()
    half[..., 8:] = 0
    c = b.clone()
    c[..., 10:] = 0.0
    assert torch.allclose(photometric_loss(a, b, half), photometric_loss(a, c, half), atol=0.02)
    assert torch.allclose(photometric_loss(a, a, torch.zeros_like(ones)), torch.zeros(2))


def _ssim_at(x: np.ndarray, y: np.ndarray, i: int, j: int) -> float:
    """(1 - SSIM) / 2 of one channel at pixel (i, j), its 3x3 window mirrored at the borders
    (reflection without repeating the edge), from the definition (Wang et al. 2004)."""
    h, w = x.shape
    rows = [abs(r) if r < 0 else (2 * (h - 1) - r if r >= h else r) for r in (i - 1, i, i + 1)]
    cols = [abs(c) if c < 0 else (2 * (w - 1) - c if c >= w else c) for c in (j - 1, j, j + 1)]
    a, b = x[np.ix_(rows, cols)], y[np.ix_(rows, cols)]
    mx, my = a.mean(), b.mean()
    vx, vy, cxy = (a * a).mean() - mx * mx, (b * b).mean() - my * my, (a * b).mean() - mx * my
    c1, c2 = 0.01**2, 0.03**2
    ssim = (2 * mx * my + c1) * (2 * cxy + c2) / ((mx * mx + my * my + c1) * (vx + vy + c2))
    return float(np.clip((1 - ssim) / 2, 0, 1))


def test_ssim_matches_its_definition_at_every_pixel_and_has_true_gradients() -> None:
    gen = torch.Generator().manual_seed(3)
    x = torch.rand(2, 3, 7, 9, generator=gen, dtype=torch.float64)
    y = (x + 0.3 * torch.rand(2, 3, 7, 9, generator=gen, dtype=torch.float64)).clamp(0, 1)
    got = ssim_distance(x, y)
    assert got.shape == x.shape
    xs, ys = x.numpy(), y.numpy()
    want = np.array([[[[_ssim_at(xs[b, c], ys[b, c], i, j) for j in range(9)] for i in range(7)]
                      for c in range(3)] for b in range(2)])
    np.testing.assert_allclose(got.numpy(), want, atol=1e-12)  # corners and edges included
    xg, yg = x[:1, :1].clone().requires_grad_(), y[:1, :1].clone().requires_grad_()
    assert torch.autograd.gradcheck(ssim_distance, (xg, yg))


def test_smoothness_is_scale_invariant_and_edge_aware() -> None:
    gen = torch.Generator().manual_seed(1)
    disp = torch.rand(1, 1, 16, 16, generator=gen)
    flat_img = torch.zeros(1, 3, 16, 16)
    assert float(smoothness_loss(torch.ones(1, 1, 16, 16), flat_img)) == 0.0
    assert torch.allclose(smoothness_loss(disp, flat_img), smoothness_loss(5 * disp, flat_img))
    edgy = torch.rand(1, 3, 16, 16, generator=gen) * 4
    assert float(smoothness_loss(disp, edgy)) < float(smoothness_loss(disp, flat_img))
    # the paper's squared form: doubling the disparity gradient around its mean quadruples it
    d1 = 1 + 0.1 * disp
    d2 = 1 + 0.2 * disp
    ratio = float(smoothness_loss(d2, flat_img) / smoothness_loss(d1, flat_img))
    assert 3.3 < ratio < 4.2


def test_pose_coordinate_loss() -> None:
    q = torch.tensor([1.0, 0, 0, 0]).expand(2, 5, 4).clone().requires_grad_()
    c = torch.zeros(2, 5, 3, requires_grad=True)
    qm, cm = geo.mean_cell_pose(q, c)
    lc = pose_coordinate_loss(q, c, qm, cm)
    assert torch.allclose(lc, torch.zeros(2))
    lc.sum().backward()
    assert torch.isfinite(q.grad).all() and torch.isfinite(c.grad).all()
    c2 = torch.zeros(1, 2, 3)
    c2[0, 1, 0] = 2.0
    q2 = torch.tensor([1.0, 0, 0, 0]).expand(1, 2, 4)
    assert torch.allclose(pose_coordinate_loss(q2, c2, *geo.mean_cell_pose(q2, c2)), torch.tensor([1.0]))


# ------------------------------------------------------------------------ warp with ground truth


@pytest.fixture(scope="module")
def synth_pair() -> dict[str, torch.Tensor]:
    """Two frames of the synth scene with exact depth and poses (rendered, not read from disk)."""
    from relocdepth.camera import Intrinsics
    from relocdepth.synth import SynthConfig, build_scene, render, rotation_from_angles

    intr = Intrinsics(fx=80.0, fy=80.0, cx=(W - 1) / 2, cy=(H - 1) / 2, width=W, height=H)
    scene = build_scene(0, SynthConfig(width=W, height=H))
    Ts = []
    for yaw, x in ((0.3, 0.0), (0.33, 0.03)):  # 3 cm and ~1.7 deg apart
        T = np.eye(4)
        T[:3, :3] = rotation_from_angles(np.array([[yaw, -0.15, 0.02]]))[0]
        T[:3, 3] = [x, 0.0, 1.4]
        Ts.append(T)
    imgs, depths = zip(*(render(scene, T, intr) for T in Ts))
    return {
        "images": torch.from_numpy(np.stack(imgs)).permute(0, 3, 1, 2).float() / 255.0,
        "depth": torch.from_numpy(np.stack(depths))[:, None].float(),
        "T": torch.from_numpy(np.stack(Ts)).float(),
        "K": torch.from_numpy(intr.K()).float()[None],
    }


def _synth_lp(pair: dict[str, torch.Tensor], T_s: torch.Tensor) -> tuple[float, float]:
    I, D, T, K = pair["images"], pair["depth"], pair["T"], pair["K"]
    warped, valid = geo.warp(I[1:2], D[0:1], geo.relative_pose(T[0:1], T_s[None]), K, K)
    return float(photometric_loss(I[0:1], warped, valid)), float(valid.mean())


def test_gt_warp_on_synth_frames(synth_pair: dict[str, torch.Tensor]) -> None:
    I, D, T, K = synth_pair["images"], synth_pair["depth"], synth_pair["T"], synth_pair["K"]
    lp_gt, valid_frac = _synth_lp(synth_pair, T[1])
    lp_id, _ = _synth_lp(synth_pair, T[0])  # no motion
    assert valid_frac > 0.8
    assert lp_gt < 0.03 and lp_gt < 0.2 * lp_id  # measured: 0.008 vs 0.19
    warped, valid = geo.warp(I[1:2], D[0:1], geo.relative_pose(T[0:1], T[1:2]), K, K)
    diff = (warped - I[0:1]).abs().mean(1, keepdim=True)
    assert float(diff[valid > 0].median()) < 0.03  # matches the target on valid pixels
    for offset in ([0.05, 0, 0], [0, 0.05, 0], [0, 0, 0.05]):  # 5 cm
        Tp = T[1].clone()
        Tp[:3, 3] += torch.tensor(offset)
        assert _synth_lp(synth_pair, Tp)[0] > 4 * lp_gt, offset  # measured >= 10x
    for axis in ([1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]):  # 2 deg
        Tp = T[1].clone()
        Tp[:3, :3] = Tp[:3, :3] @ geo.so3_exp(torch.tensor(axis) * math.radians(2.0))
        assert _synth_lp(synth_pair, Tp)[0] > 4 * lp_gt, axis


# ------------------------------------------------------------------------------ the triplet loss


@pytest.fixture(scope="module")
def nets() -> torch.nn.Module:
    torch.manual_seed(0)
    return build_networks(ModelConfig())


def _triplet(seed: int = 0, B: int = 1) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    base = torch.rand(B, 1, 3, H // 8, W // 8, generator=gen)
    imgs = torch.nn.functional.interpolate(base.flatten(0, 1), (H, W), mode="bilinear").unflatten(0, (B, 1))
    return (imgs + 0.05 * torch.rand(B, 3, 3, H, W, generator=gen)).clamp(0, 1)


def test_lcvs_pairs() -> None:
    full, middle = pairs_for(MethodConfig()), pairs_for(MethodConfig(lcvs=False))
    assert len(full) == 6 and len(set(full)) == 6 and all(t != s for t, s in full)
    assert middle == ((1, 0), (1, 2))


def test_triplet_loss_parts_and_diagnostics(nets: torch.nn.Module) -> None:
    imgs = _triplet(0, B=2)
    K = _K(2, 3)
    total, parts, diag = triplet_loss(nets, imgs, imgs, K, MethodConfig())
    pair_keys = sorted(k for k in parts if k.startswith("L_p/pair_"))
    assert pair_keys == ["L_p/pair_01", "L_p/pair_02", "L_p/pair_10", "L_p/pair_12", "L_p/pair_20", "L_p/pair_21"]
    assert {f"L_p/scale{k}" for k in range(4)} | {f"L_s/scale{k}" for k in range(4)} <= set(parts)
    cfg = MethodConfig()
    assert torch.allclose(total, parts["L_p"] + cfg.w_s * parts["L_s"] + cfg.w_c * parts["L_c"])
    assert torch.allclose(parts["L_p"], torch.stack([parts[k] for k in pair_keys]).mean(), atol=1e-6)
    for k in ("centre_spread", "rot_spread_deg", "rel_trans", "rel_rot_deg", "cell_spread",
              "valid_frac", "median_depth", "lp_identity"):
        assert isinstance(diag[k], float) and math.isfinite(diag[k]), k
    _, parts2, _ = triplet_loss(nets, imgs, imgs, K, MethodConfig(lcvs=False))
    assert sorted(k for k in parts2 if k.startswith("L_p/pair_")) == ["L_p/pair_10", "L_p/pair_12"]


def test_pair_losses_symmetric_under_frame_swap(nets: torch.nn.Module) -> None:
    """Swapping frames 0 and 2 relabels the pairs; with frame 0 == frame 2, mirrored pairs agree."""
    nets.eval()
    try:
        imgs = _triplet(1)
        K = _K(1, 3)
        K[:, 2, 0, 0] = 85.0  # distinct intrinsics per frame catch K_t / K_s mix-ups
        with torch.no_grad():
            _, p, _ = triplet_loss(nets, imgs, imgs, K, MethodConfig())
            sw = [2, 1, 0]
            _, q, _ = triplet_loss(nets, imgs[:, sw], imgs[:, sw], K[:, sw], MethodConfig())
            relabel = {"0": "2", "1": "1", "2": "0"}
            for key, val in p.items():
                if key.startswith("L_p/pair_"):
                    t, s = key[-2], key[-1]
                    assert torch.allclose(val, q[f"L_p/pair_{relabel[t]}{relabel[s]}"], atol=1e-5), key
            same = imgs.clone()
            same[:, 2] = same[:, 0]
            K2 = _K(1, 3)
            _, r, _ = triplet_loss(nets, same, same, K2, MethodConfig())
            assert torch.allclose(r["L_p/pair_10"], r["L_p/pair_12"], atol=1e-6)
            assert torch.allclose(r["L_p/pair_01"], r["L_p/pair_21"], atol=1e-6)
            assert float(r["L_p/pair_02"]) < 1e-3  # a frame synthesised from itself
    finally:
        nets.train()


def test_gradients_reach_both_networks(nets: torch.nn.Module) -> None:
    imgs = _triplet(2)
    _, parts, _ = triplet_loss(nets, imgs, imgs, _K(1, 3), MethodConfig())
    depth_params = list(nets.depth.parameters())
    dsc_params = list(nets.dsc.parameters())
    for name in ("L_p", "L_c"):
        grads = torch.autograd.grad(parts[name], depth_params + dsc_params, retain_graph=True, allow_unused=True)
        g_depth = sum(float(g.abs().sum()) for g in grads[: len(depth_params)] if g is not None)
        g_dsc = sum(float(g.abs().sum()) for g in grads[len(depth_params):] if g is not None)
        assert g_depth > 0 and g_dsc > 0, name
        assert all(torch.isfinite(g).all() for g in grads if g is not None)


def test_without_dsc_uses_pose_head() -> None:
    torch.manual_seed(0)
    nets = build_networks(ModelConfig(use_dsc=False))
    imgs = _triplet(3)
    cfg = MethodConfig(use_dsc=False, lcvs=False)
    total, parts, diag = triplet_loss(nets, imgs, imgs, _K(1, 3), cfg)
    assert float(parts["L_c"]) == 0.0 and diag["cell_spread"] == 0.0
    grads = torch.autograd.grad(total, list(nets.pose.parameters()), allow_unused=True)
    assert any(g is not None and float(g.abs().sum()) > 0 for g in grads)
    out = predict(nets, imgs[:, 1], _K(1))
    assert torch.equal(out["confidence"], torch.ones(1))


def test_predict(nets: torch.nn.Module) -> None:
    imgs = _triplet(4, B=2)
    nets.train()
    out = predict(nets, imgs[:, 0], _K(2))
    assert nets.training  # mode restored
    assert out["T_wc"].shape == (2, 4, 4) and out["depth"].shape == (2, 1, H, W)
    assert torch.allclose(out["T_wc"][:, 3], torch.tensor([0.0, 0, 0, 1]).expand(2, 4))
    assert ((out["confidence"] > 0) & (out["confidence"] <= 1)).all()
    assert out["cell_spread_t"].shape == (2,) and out["cell_spread_r_deg"].shape == (2,)
    with pytest.raises(ValueError):
        predict(nets, imgs[:, 0], _K(1))


def test_photometric_pixels_option_is_wired() -> None:
    """"all" averages L_p over every pixel (monodepth2), "valid" over in-image ones (the default)."""
    torch.manual_seed(0)
    nets = build_networks(ModelConfig())
    imgs, Kb = _triplet(3, B=1), _K(1, 3)
    _, p_valid, d = triplet_loss(nets, imgs, imgs, Kb, MethodConfig())
    _, p_all, d_all = triplet_loss(nets, imgs, imgs, Kb, MethodConfig(photometric_pixels="all"))
    assert math.isfinite(float(p_all["L_p"].detach())) and d["valid_frac"] == d_all["valid_frac"]
    if d["valid_frac"] < 0.999:
        assert not torch.allclose(p_valid["L_p"], p_all["L_p"])
    else:
        assert torch.allclose(p_valid["L_p"], p_all["L_p"], atol=1e-5)
    with pytest.raises(ValueError, match="photometric_pixels"):
        MethodConfig(photometric_pixels="some")


def test_depth_consistency_weight_is_wired() -> None:
    """L_g is computed and added to the total only with its weight set; its gradient reaches the
    depth network."""
    torch.manual_seed(0)
    nets = build_networks(ModelConfig())
    imgs, Kb = _triplet(4, B=2), _K(2, 3)
    total0, parts0, _ = triplet_loss(nets, imgs, imgs, Kb, MethodConfig())
    assert "L_g" not in parts0
    cfg = MethodConfig(w_depth_consistency=0.5)
    total, parts, _ = triplet_loss(nets, imgs, imgs, Kb, cfg)
    assert 0 < float(parts["L_g"].detach()) < 1
    assert torch.allclose(total, total0 + 0.5 * parts["L_g"], atol=1e-6)
    nets.zero_grad()
    parts["L_g"].backward()
    grads = [p.grad for p in nets.depth.parameters() if p.grad is not None]
    assert grads and sum(float(g.abs().sum()) for g in grads) > 0
    with pytest.raises(ValueError, match="w_depth_consistency"):
        MethodConfig(w_depth_consistency=-0.1)


@pytest.mark.parametrize("loss_resolution", LOSS_RESOLUTIONS)
def test_recompute_warps_gives_the_same_loss_and_gradients(loss_resolution: str) -> None:
    """Checkpointing the warps/SSIM trades memory for time; values and gradients must not change."""
    imgs, K = _triplet(5, B=2), _K(2, 3)
    grads = []
    for recompute in (False, True):
        torch.manual_seed(0)
        nets = build_networks(ModelConfig())
        cfg = MethodConfig(recompute_warps=recompute, loss_resolution=loss_resolution)
        total, _, diag = triplet_loss(nets, imgs, imgs, K, cfg)
        total.backward()
        grads.append((float(total.detach()), diag["valid_frac"],
                      [p.grad.clone() for p in nets.parameters() if p.grad is not None]))
    (l0, v0, g0), (l1, v1, g1) = grads
    assert l0 == pytest.approx(l1, rel=1e-6) and v0 == v1
    assert len(g0) == len(g1) > 0
    for a, b in zip(g0, g1):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-7)


# ------------------------------------------------------------------- loss resolution (per scale)


@pytest.fixture(scope="module")
def synth_triplet() -> dict:
    """Three frames of the synth scene, rendered at the input size and at each decoder scale's size
    (intrinsics scaled with the half-pixel convention), with exact depths and poses."""
    from relocdepth.camera import Intrinsics
    from relocdepth.synth import SynthConfig, build_scene, render, rotation_from_angles

    h, w = 2 * H, 2 * W  # scale 3 is then 16x24 pixels
    intr = Intrinsics(fx=160.0, fy=160.0, cx=(w - 1) / 2, cy=(h - 1) / 2, width=w, height=h)
    scene = build_scene(0, SynthConfig(width=w, height=h))
    Ts = []
    for yaw, x, z in ((0.3, 0.0, 1.4), (0.33, 0.06, 1.4), (0.36, 0.12, 1.3)):  # ~6-10 cm, ~2-3 deg apart
        T = np.eye(4)
        T[:3, :3] = rotation_from_angles(np.array([[yaw, -0.15, 0.02]]))[0]
        T[:3, 3] = [x, 0.0, z]
        Ts.append(T)
    depths = []
    for k in range(4):
        cam = intr.scaled(w >> k, h >> k)
        depths.append(torch.from_numpy(np.stack([render(scene, T, cam)[1] for T in Ts]))[:, None].float())
    imgs = np.stack([render(scene, T, intr)[0] for T in Ts])
    return {
        "images": (torch.from_numpy(imgs).permute(0, 3, 1, 2).float() / 255.0)[None],  # (1, 3, 3, h, w)
        "depths": depths,  # per scale (3, 1, h >> k, w >> k)
        "T": torch.from_numpy(np.stack(Ts)).float(),
        "K": torch.from_numpy(intr.K()).float().expand(1, 3, 3, 3).clone(),
    }


class _ExactNets(torch.nn.Module):
    """Stands in for the networks with the rendered geometry: each scale's disparity (sigmoid units)
    is the exact depth at that scale's size, and the DSC is the one the true poses give."""

    def __init__(self, depths: list[torch.Tensor], T_wc: torch.Tensor, K: torch.Tensor) -> None:
        super().__init__()
        lo, hi = 0.1, 100.0
        b, a = 1.0 / hi, 1.0 / lo - 1.0 / hi
        self.disps = [(1.0 / d - b) / a for d in depths]
        self.dsc_out = geo.dsc_from_pose(T_wc, geo.pool_depth(depths[0]), K)

    def depth(self, x: torch.Tensor) -> list[torch.Tensor]:
        return self.disps

    def dsc(self, x: torch.Tensor) -> torch.Tensor:
        return self.dsc_out


def test_decoder_resolution_warps_reconstruct_each_scale(synth_triplet: dict) -> None:
    """Exact depth + exact poses at each decoder layer's own size (images area-downsampled, K scaled
    with the half-pixel offset) synthesise every scale's targets; a wrong pose does not."""
    imgs, K, depths, T = synth_triplet["images"], synth_triplet["K"], synth_triplet["depths"], synth_triplet["T"]
    cfg = MethodConfig(loss_resolution="decoder")
    with torch.no_grad():
        exact = _ExactNets(depths, T, K[0])
        _, parts, diag = triplet_loss(exact, imgs, imgs, K, cfg)
        T_still = T[:1].expand(3, 4, 4)  # every frame at the first pose: the no-motion reference
        _, still, _ = triplet_loss(_ExactNets(depths, T_still, K[0]), imgs, imgs, K, cfg)
    assert diag["rel_trans"] > 0.05 and diag["valid_frac"] > 0.8  # the frames really move
    for k in range(4):
        lp, lp_still = float(parts[f"L_p/scale{k}"]), float(still[f"L_p/scale{k}"])
        # measured: 0.009 / 0.018 / 0.037 / 0.038 vs 0.27 / 0.32 / 0.28 / 0.20 without motion (a
        # warp resamples the area-averaged source bilinearly, so coarse scales match less closely)
        assert lp < 0.05 and lp < 0.25 * lp_still, (k, lp, lp_still)


def test_loss_resolutions_agree_at_full_scale_and_differ_below(nets: torch.nn.Module) -> None:
    imgs, K = _triplet(6, B=2), _K(2, 3)
    out = {}
    for res in ("input", "decoder"):
        total, parts, diag = triplet_loss(nets, imgs, imgs, K, MethodConfig(loss_resolution=res))
        out[res] = (total, parts, diag)
    (_, p_in, d_in), (total, p_dec, d_dec) = out["input"], out["decoder"]
    for key in ("L_p/scale0", "L_s/scale0", "L_c"):
        assert torch.equal(p_in[key], p_dec[key]), key
    assert d_in == d_dec  # poses, valid fraction and depth all come from the full-res scale
    for key in ("L_p/scale1", "L_p/scale2", "L_p/scale3"):
        assert not torch.allclose(p_in[key], p_dec[key]), key
    for key in ("L_s/scale1", "L_s/scale3"):  # L_s was at decoder size in both modes already
        assert torch.equal(p_in[key], p_dec[key]), key
    # gradients flow from the coarsest scale's L_p to its own disparity output and to the DSC
    params = [nets.depth.decoder.dispconv[3].weight, nets.dsc.head.out.weight]
    grads = torch.autograd.grad(p_dec["L_p/scale3"], params, retain_graph=True)
    assert all(torch.isfinite(g).all() and float(g.abs().sum()) > 0 for g in grads)
    grads = torch.autograd.grad(total, list(nets.parameters()), allow_unused=True)
    assert all(torch.isfinite(g).all() for g in grads if g is not None)
    with pytest.raises(ValueError, match="loss_resolution"):
        MethodConfig(loss_resolution="output")


def test_train_options_reach_the_method_and_networks(tmp_path: Path) -> None:
    from relocdepth.cli.main import app
    from typer.testing import CliRunner

    from relocdepth.train import TrainConfig

    cfg = TrainConfig.from_dict({"loss_resolution": "input", "decoder_bn": True, "w_depth_consistency": 0.5})
    assert cfg.method.loss_resolution == "input" and cfg.model.decoder_bn and cfg.method.w_depth_consistency == 0.5
    cfg = TrainConfig()  # the paper's: each layer's size
    assert cfg.method.loss_resolution == "decoder" and not cfg.model.decoder_bn
    run = tmp_path / "run"
    res = CliRunner().invoke(app, ["train", str(tmp_path), "-o", str(run), "--loss-resolution", "output"])
    assert res.exit_code == 2 and "--loss-resolution must be one of input, decoder" in res.output
    assert len(res.output.strip().splitlines()) == 1 and not run.exists()
    res = CliRunner().invoke(app, ["train", str(tmp_path), "-o", str(run), "--w-depth-consistency", "-1"])
    assert res.exit_code == 2 and "w_depth_consistency must be >= 0" in res.output
    assert len(res.output.strip().splitlines()) == 1 and not run.exists()
