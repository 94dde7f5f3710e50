"""The bootstrap's translation-direction term (``--w-direction``): the angle between two
translations, and ``L_dir`` in the training loss against the geometry of known poses."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from reloc_fixtures import FixedDSC

from relocdepth import geometry as geo
from relocdepth.errors import UserError
from relocdepth.losses import translation_direction_angle
from relocdepth.method import Bootstrap, MethodConfig, triplet_loss
from relocdepth.models import ModelConfig, Networks

torch.set_num_threads(1)
H, W = 64, 96


def test_angle_between_translations_of_any_length() -> None:
    """A vector turned by a known angle about an axis perpendicular to it, and scaled, is that angle
    away; a zero translation has no direction (0, no gradient); the gradient matches finite
    differences, also near agreement and near opposition."""
    gen = torch.Generator().manual_seed(0)
    a = torch.randn(200, 3, generator=gen, dtype=torch.float64)
    perp = torch.linalg.cross(a, torch.randn(200, 3, generator=gen, dtype=torch.float64), dim=-1)
    theta = torch.rand(200, generator=gen, dtype=torch.float64) * math.pi
    R = geo.so3_exp(perp / perp.norm(dim=-1, keepdim=True) * theta[:, None])
    b = (R @ a[..., None])[..., 0] * torch.rand(200, 1, generator=gen, dtype=torch.float64).add(0.1) * 7
    assert torch.allclose(translation_direction_angle(a, b), theta, atol=1e-6)
    assert torch.allclose(translation_direction_angle(b, a), theta, atol=1e-6)

    z = torch.zeros(2, 3, dtype=torch.float64, requires_grad=True)
    out = translation_direction_angle(z, torch.tensor([[1.0, 0, 0], [0, 0, 2.0]], dtype=torch.float64))
    out.sum().backward()
    assert out.tolist() == [0.0, 0.0] and z.grad is not None and torch.all(z.grad == 0)

    x = torch.tensor([[0.3, -0.2, 1.0], [1.0, 0.001, 0.0], [-1.0, 0.01, 0.02]], dtype=torch.float64,
                     requires_grad=True)
    y = torch.tensor([[0.1, 0.4, 0.9], [2.0, 0.0, 0.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda v: translation_direction_angle(v, y), (x,))


def _poses(seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    T = torch.eye(4).repeat(3, 1, 1)
    T[:, :3, :3] = geo.so3_exp((torch.rand(3, 3, generator=gen) - 0.5) * 0.2)
    T[:, :3, 3] = (torch.rand(3, 3, generator=gen) - 0.5) * 0.4
    return T.reshape(1, 3, 4, 4)


def _expected_term(T_a: np.ndarray, T_b: np.ndarray, depth: float) -> float:
    """Mean over the 6 ordered pairs (t, s) of the angle between the translations of T_s^-1 T_t
    under the two pose sets (camera-to-world 4x4 each), times the shorter baseline over ``depth``."""
    angles = []
    for t in range(3):
        for s in range(3):
            if s == t:
                continue
            ua = (np.linalg.inv(T_a[s]) @ T_a[t])[:3, 3]
            ub = (np.linalg.inv(T_b[s]) @ T_b[t])[:3, 3]
            c = ua @ ub / np.linalg.norm(ua) / np.linalg.norm(ub)
            angles.append(math.acos(max(-1.0, min(1.0, c))) * min(np.linalg.norm(ua), np.linalg.norm(ub)) / depth)
    return float(np.mean(angles))


def test_direction_term_is_the_mean_angle_of_the_pairs_translations() -> None:
    """A DSC whose cells give the bootstrap's poses has L_dir 0; with the third camera moved, L_dir
    is the mean over the pairs of the angle between their translation directions, computed from the
    matrices, times the shorter of the two baselines over the scene's depth: the same in any depth units;
    it enters the total with w_consistency x w_direction, and teaches the DSC network only."""
    torch.manual_seed(0)
    nets = Networks(ModelConfig())
    imgs = torch.rand(1, 3, 3, H, W)
    K = torch.tensor([[60.0, 0, (W - 1) / 2], [0, 60.0, (H - 1) / 2], [0, 0, 1]]).expand(1, 3, 3, 3).clone()
    cfg = MethodConfig(photometric_pixels="all")
    T_dsc = _poses(seed=3)
    got = []
    for k in (1.0, 3.0):
        depth = torch.full((1, 3, 1, H, W), 1.5 * k)
        T_k = T_dsc.clone()
        T_k[..., :3, 3] *= k
        nets.dsc = FixedDSC(geo.dsc_from_pose(T_k.reshape(3, 4, 4), geo.pool_depth(depth.reshape(3, 1, H, W)),
                                               K.reshape(3, 3, 3)))
        _, parts, diag = triplet_loss(nets, imgs, imgs, K, cfg, Bootstrap(False, 1.0, T_k, w_direction=1.0),
                                      depth_override=depth)
        assert float(parts["L_dir"]) < 2e-3 and diag["dsc_boot_dir_deg"] < 0.2
        moved = T_k.clone()
        moved[0, 2, :3, 3] += torch.tensor([0.08, -0.05, 0.03]) * k
        total, parts, diag = triplet_loss(nets, imgs, imgs, K, cfg, Bootstrap(False, 0.5, moved, w_direction=2.0),
                                          depth_override=depth)
        expected = _expected_term(T_k[0].double().numpy(), moved[0].double().numpy(), 1.5 * k)
        assert expected > 0.01
        assert float(parts["L_dir"]) == pytest.approx(expected, rel=2e-2)
        got.append(float(parts["L_dir"]))
        plain, p_parts, _ = triplet_loss(nets, imgs, imgs, K, cfg, Bootstrap(False, 0.5, moved),
                                         depth_override=depth)
        assert "L_dir" not in p_parts
        assert float(total.detach()) == pytest.approx(float(plain.detach()) + 0.5 * 2.0 * got[-1], rel=1e-5)
    assert got[1] == pytest.approx(got[0], rel=1e-2)

    nets = Networks(ModelConfig())
    _, parts, _ = triplet_loss(nets, imgs, imgs, K, MethodConfig(),
                               Bootstrap(False, 1.0, _poses(seed=5), w_direction=1.0))
    parts["L_dir"].backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in nets.dsc.parameters())
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in nets.depth.parameters())


def test_direction_term_moves_the_centres_only_and_its_gradient_stays_bounded() -> None:
    """L_dir's gradient reaches the DSC's scene points (tau), never its ray rotations (theta: the
    orientations, which the centres also depend on); and it stays below ~1 / D however short the
    DSC's own baseline between two frames gets (the angle's own gradient grows as 1 / baseline)."""
    nets = Networks(ModelConfig())
    imgs = torch.rand(1, 3, 3, H, W)
    K = torch.tensor([[60.0, 0, (W - 1) / 2], [0, 60.0, (H - 1) / 2], [0, 0, 1]]).expand(1, 3, 3, 3).clone()
    D = 1.5
    depth = torch.full((1, 3, 1, H, W), D)
    T_boot = _poses(seed=21)
    norms = []
    for gap in (1e-1, 1e-3, 1e-5):
        T_dsc = T_boot.clone()
        T_dsc[0, 2, :3, 3] = T_dsc[0, 1, :3, 3] + torch.tensor([0.6, -0.8, 0.0]) * gap  # frame 2 ~ on frame 1
        out = geo.dsc_from_pose(T_dsc.reshape(3, 4, 4), geo.pool_depth(depth.reshape(3, 1, H, W)),
                                K.reshape(3, 3, 3)).clone().requires_grad_(True)
        nets.dsc = FixedDSC(out)
        _, parts, _ = triplet_loss(nets, imgs, imgs, K, MethodConfig(),
                                   Bootstrap(False, 1.0, T_boot, w_direction=1.0), depth_override=depth)
        parts["L_dir"].backward()
        assert out.grad is not None
        assert torch.all(out.grad[:, :3] == 0)  # theta
        assert out.grad[:, 3:].abs().sum() > 0  # tau
        norms.append(float(out.grad.norm()))
    assert max(norms) < 10 / D, norms


def test_direction_term_counts_only_the_pairs_whose_translation_was_measured() -> None:
    """Essential bootstrap, one pair measured (middle -> frame 0, its direction off the DSC's) and
    one rotation-only (middle -> frame 2: no translation to compare): L_dir is the mean over the
    two pairs between frames 0 and 1 of their angle, computed from the matrices, times the shorter
    baseline over the scene's depth; the pairs with frame 2 do not count. With both pairs rotation-only there
    is nothing to compare: L_dir is 0."""

    nets = Networks(ModelConfig())
    imgs = torch.rand(1, 3, 3, H, W)
    K = torch.tensor([[60.0, 0, (W - 1) / 2], [0, 60.0, (H - 1) / 2], [0, 0, 1]]).expand(1, 3, 3, 3).clone()
    depth = torch.full((1, 3, 1, H, W), 1.5)
    T_dsc = _poses(seed=11)
    nets.dsc = FixedDSC(geo.dsc_from_pose(T_dsc.reshape(3, 4, 4), geo.pool_depth(depth.reshape(3, 1, H, W)),
                                           K.reshape(3, 3, 3)))
    T_b = T_dsc.clone()
    T_b[0, 0, :3, 3] += torch.tensor([0.1, 0.06, -0.05])  # the bootstrap sees frame 0 elsewhere
    T_1i = torch.stack((geo.relative_pose(T_b[:, 1], T_b[:, 0]), geo.relative_pose(T_b[:, 1], T_b[:, 2])), 1)
    length = T_1i[0, 0, :3, 3].norm()
    T_1i[0, 0, :3, 3] /= length  # essential matrix: a unit translation
    T_1i[0, 1, :3, 3] = 0.0  # rotation only
    points = torch.full((1, 2, 8, 3), float("nan"))
    points[0, 0, :5, 0] = torch.linspace(3, W - 4, 5)
    points[0, 0, :5, 1] = torch.linspace(3, H - 4, 5)
    points[0, 0, :5, 2] = 1.5 / length
    ok = torch.ones(1, 2, dtype=torch.bool)
    _, parts, diag = triplet_loss(nets, imgs, imgs, K, MethodConfig(),
                                  Bootstrap(True, 1.0, two_view=(T_1i, points, ok), w_direction=1.0),
                                  depth_override=depth)
    a, b = T_dsc[0].double().numpy(), T_b[0].double().numpy()
    angles, weights = [], []
    for t, s_ in ((0, 1), (1, 0)):
        ua = (np.linalg.inv(a[s_]) @ a[t])[:3, 3]
        ub = (np.linalg.inv(b[s_]) @ b[t])[:3, 3]
        angles.append(math.acos(ua @ ub / np.linalg.norm(ua) / np.linalg.norm(ub)))
        weights.append(min(np.linalg.norm(ua), np.linalg.norm(ub)) / 1.5)
    assert min(angles) > 0.05
    assert float(parts["L_dir"]) == pytest.approx(float(np.mean(np.multiply(angles, weights))), rel=2e-2)
    assert diag["dsc_boot_dir_deg"] == pytest.approx(math.degrees(float(np.median(angles))), rel=2e-2)

    points[0, 0] = float("nan")
    T_1i[0, 0, :3, 3] = 0.0
    _, parts, diag = triplet_loss(nets, imgs, imgs, K, MethodConfig(),
                                  Bootstrap(True, 1.0, two_view=(T_1i, points, ok), w_direction=1.0),
                                  depth_override=depth)
    assert float(parts["L_dir"]) == 0.0 and "dsc_boot_dir_deg" not in diag


def test_direction_weight_needs_a_bootstrap_and_a_sane_value() -> None:
    from relocdepth.train import TrainConfig

    assert TrainConfig.from_dict({"bootstrap": "essential", "bootstrap_steps": 10,
                                  "w_direction": 0.3}).w_direction == 0.3
    with pytest.raises(UserError, match="--w-direction needs a --bootstrap"):
        TrainConfig.from_dict({"w_direction": 0.3})
    with pytest.raises(UserError, match="--w-bootstrap > 0"):
        TrainConfig.from_dict({"bootstrap": "essential", "bootstrap_steps": 10, "w_bootstrap": 0.0,
                               "w_direction": 0.3})
    for bad in (-1.0, float("nan")):
        with pytest.raises(UserError, match="--w-direction"):
            TrainConfig.from_dict({"bootstrap": "essential", "bootstrap_steps": 10, "w_direction": bad})


def test_w_direction_reaches_the_run_and_its_log(synth_shards, tmp_path) -> None:
    """`reloc train --bootstrap essential --w-direction 2` trains, keeps the weight in the run's
    config and logs a finite L_dir every step, positive where the bootstrap measured a pair;
    without a bootstrap it is one error line and no run folder."""
    import json

    from relocdepth.cli.main import app
    from typer.testing import CliRunner

    run = tmp_path / "run"
    res = CliRunner().invoke(app, [
        "train", str(synth_shards), "-o", str(run), "--size", "64x64", "--batch-size", "2", "--pretrained",
        "none", "--workers", "0", "--no-progress", "--log-every", "1", "--max-steps", "2",
        "--bootstrap", "essential", "--bootstrap-steps", "10", "--w-direction", "2"])
    assert res.exit_code == 0, res.output[-3000:]
    assert json.loads((run / "config.json").read_text())["train"]["w_direction"] == 2.0
    steps = [json.loads(x) for x in (run / "logs" / "train.jsonl").read_text().splitlines()]
    steps = [r for r in steps if r.get("kind") == "step"]
    assert len(steps) == 2 and all(math.isfinite(r["parts"]["L_dir"]) for r in steps)
    measured = [r for r in steps if "dsc_boot_dir_deg" in r["diagnostics"]]  # pairs with a baseline
    assert measured and all(r["parts"]["L_dir"] > 0 for r in measured)

    bad = tmp_path / "bad"
    res = CliRunner().invoke(app, ["train", str(synth_shards), "-o", str(bad), "--w-direction", "2"])
    assert res.exit_code == 2 and "--w-direction needs a --bootstrap" in res.output and not bad.exists()
