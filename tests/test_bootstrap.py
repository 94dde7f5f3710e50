"""The relative-pose bootstrap: the two-frame network, the triplet's poses, the consistency term,
the schedule, and the hand-over from bootstrap warps to the DSC's (the paper's loss)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from reloc_fixtures import FixedDSC
from typer.testing import CliRunner

from relocdepth import geometry as geo
from relocdepth.losses import relative_pose_consistency
from relocdepth.method import Bootstrap, MethodConfig, bootstrap_poses, triplet_loss
from relocdepth.models import ModelConfig, Networks, RelPoseNet

torch.set_num_threads(1)
H, W = 64, 96


def _random_poses(n: int, seed: int, rot_deg: float = 20.0, trans: float = 0.3) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    T = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    axis = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    angle = torch.rand(n, 1, generator=gen, dtype=torch.float64) * math.radians(rot_deg)
    T[:, :3, :3] = geo.so3_exp(axis / axis.norm(dim=-1, keepdim=True) * angle)
    T[:, :3, 3] = (torch.rand(n, 3, generator=gen, dtype=torch.float64) - 0.5) * 2 * trans
    return T


def _K(B: int) -> torch.Tensor:
    K = torch.tensor([[60.0, 0, (W - 1) / 2], [0, 60.0, (H - 1) / 2], [0, 0, 1]])
    return K.expand(B, 3, 3, 3).clone()


def test_relpose_net_starts_near_identity() -> None:
    torch.manual_seed(0)
    net = RelPoseNet()
    x = torch.rand(4, 3, H, W)
    T = net(x, x.flip(0))
    t_err, r_err = geo.pose_errors(T, torch.eye(4).expand(4, 4, 4))
    assert float(t_err.detach().max()) < 0.02 and float(r_err.detach().max()) < 1.0  # 0.01-scaled outputs
    assert torch.allclose(T[:, :3, :3] @ T[:, :3, :3].transpose(1, 2), torch.eye(3).expand(4, 3, 3), atol=1e-5)
    with pytest.raises(ValueError):
        net(x, x[:, :2])


def test_bootstrap_poses_are_the_middle_camera_frame_and_keep_relative_poses() -> None:
    T = _random_poses(6, seed=1).reshape(2, 3, 4, 4)
    boot = bootstrap_poses(None, torch.zeros(2, 3, 3, H, W, dtype=torch.float64), T)  # type: ignore[arg-type]
    assert torch.allclose(boot[:, 1], torch.eye(4, dtype=torch.float64).expand(2, 4, 4), atol=1e-12)
    for t in range(3):
        for s in range(3):
            assert torch.allclose(geo.relative_pose(boot[:, t], boot[:, s]),
                                  geo.relative_pose(T[:, t], T[:, s]), atol=1e-10)


def test_posenet_path_uses_the_same_convention_as_the_oracle(monkeypatch: pytest.MonkeyPatch) -> None:
    """If the two-frame network returned the true T_{1->i} (points of camera 1 into camera i, the
    warp's T_t2s), the triplet's poses must equal the ground truth's in the middle camera's frame."""
    torch.manual_seed(0)
    nets = Networks(ModelConfig(relpose=True))
    T = _random_poses(6, seed=2).float().reshape(2, 3, 4, 4)
    true_1i = torch.cat((geo.relative_pose(T[:, 1], T[:, 0]), geo.relative_pose(T[:, 1], T[:, 2])))
    monkeypatch.setattr(nets.relpose, "forward", lambda a, b: true_1i)
    got = bootstrap_poses(nets, torch.rand(2, 3, 3, H, W))
    want = bootstrap_poses(nets, torch.rand(2, 3, 3, H, W), T)
    assert torch.allclose(got, want, atol=1e-5)


def test_relative_pose_consistency_measures_angle_and_translation() -> None:
    Ta = _random_poses(5, seed=3)
    assert torch.allclose(relative_pose_consistency(Ta, Ta), torch.zeros(5, dtype=torch.float64), atol=1e-7)
    # A known rotation offset about any axis and a known translation offset: sqrt(angle^2 + |dt|^2).
    Tb = Ta.clone()
    Tb[:, :3, :3] = Ta[:, :3, :3] @ geo.so3_exp(torch.tensor([0.0, 0.0, 0.1], dtype=torch.float64)).expand(5, 3, 3)
    Tb[:, :3, 3] += torch.tensor([0.03, 0.0, -0.04], dtype=torch.float64)
    assert torch.allclose(relative_pose_consistency(Ta, Tb), torch.full((5,), math.hypot(0.1, 0.05),
                                                                          dtype=torch.float64), atol=1e-9)
    # A zero translation weight compares the rotations only (pairs whose translation is unknown).
    w = torch.tensor([1.0, 0.0, 1.0, 0.0, 0.5], dtype=torch.float64)
    want = torch.tensor([math.hypot(0.1, 0.05), 0.1, math.hypot(0.1, 0.05), 0.1, math.hypot(0.1, 0.025)],
                        dtype=torch.float64)
    assert torch.allclose(relative_pose_consistency(Ta, Tb, w), want, atol=1e-9)
    # Finite gradients where the two agree (the hand-over starts there).
    Tc = Ta.clone().requires_grad_(True)
    relative_pose_consistency(Tc, Ta).sum().backward()
    assert torch.isfinite(Tc.grad).all()


def test_consistency_weighs_translation_relative_to_scene_depth() -> None:
    """L_boot counts a translation error as t / D (D = the scene's depth): a DSC whose third camera
    is off by |d| from the bootstrap's costs |d| / D on the 4 of 6 pairs that involve it, and the
    same in any depth units (poses and depth scaled together)."""
    torch.manual_seed(0)
    nets = Networks(ModelConfig())
    imgs = torch.rand(1, 3, 3, H, W)
    K = _K(1)
    T_dsc = _random_poses(3, seed=8, rot_deg=5.0, trans=0.1).float().reshape(1, 3, 4, 4)
    T_boot = T_dsc.clone()
    T_boot[0, 2, :3, 3] += torch.tensor([0.03, -0.04, 0.0])  # |d| = 0.05
    got = []
    for k in (1.0, 4.0):  # depth units: the same scene at two scales
        D = 1.5 * k
        depth = torch.full((1, 3, 1, H, W), D)
        T_k, Tb_k = T_dsc.clone(), T_boot.clone()
        T_k[..., :3, 3] *= k
        Tb_k[..., :3, 3] *= k
        cells = geo.pool_depth(depth.reshape(3, 1, H, W))
        nets.dsc = FixedDSC(geo.dsc_from_pose(T_k.reshape(3, 4, 4), cells, K.reshape(3, 3, 3)))
        _, parts, _ = triplet_loss(nets, imgs, imgs, K, MethodConfig(), Bootstrap(True, 1.0, Tb_k),
                                   depth_override=depth)
        got.append(float(parts["L_boot"]))
    assert got[0] == pytest.approx(4 / 6 * 0.05 / 1.5, rel=1e-3)
    assert got[1] == pytest.approx(got[0], rel=1e-3)


def test_warps_switch_between_bootstrap_and_dsc_poses() -> None:
    """A deliberately wrong bootstrap source changes L_p only while it drives the warps."""
    torch.manual_seed(0)
    nets = Networks(ModelConfig(relpose=True))
    imgs = torch.rand(2, 3, 3, H, W)
    K = _K(2)
    cfg = MethodConfig(photometric_pixels="all")
    wrong = _random_poses(6, seed=4, rot_deg=30.0, trans=0.5).float().reshape(2, 3, 4, 4)
    paper, p_parts, _ = triplet_loss(nets, imgs, imgs, K, cfg)
    _driven, d_parts, d_diag = triplet_loss(nets, imgs, imgs, K, cfg, Bootstrap(True, 1.0, wrong))
    fading, f_parts, f_diag = triplet_loss(nets, imgs, imgs, K, cfg, Bootstrap(False, 0.5, wrong))
    assert d_diag["boot_warps"] == 1.0 and f_diag["boot_warps"] == 0.0
    assert float(d_parts["L_p"].detach()) != pytest.approx(float(p_parts["L_p"].detach()), rel=1e-3)  # other warps
    assert float(f_parts["L_p"].detach()) == pytest.approx(float(p_parts["L_p"].detach()), rel=1e-6)  # DSC warps again
    # The consistency term is added with its weight.
    assert float(fading.detach()) == pytest.approx(float(paper.detach()) + 0.5 * float(f_parts["L_boot"].detach()), rel=1e-5)
    assert float(f_parts["L_boot"].detach()) > 0.1  # 30 deg / 0.5 units from the DSC's near-identity poses


def test_bootstrap_schedule() -> None:
    from relocdepth.train import TrainConfig, bootstrap_at

    cfg = TrainConfig.from_dict({"bootstrap": "posenet", "bootstrap_steps": 10,
                                 "bootstrap_fade_steps": 4, "w_bootstrap": 2.0})
    got = [bootstrap_at(cfg, s) for s in (0, 9, 10, 11, 13, 14, 100)]
    assert got == [(True, 2.0), (True, 2.0), (False, 2.0), (False, 1.5), (False, 0.5), (False, 0.0), (False, 0.0)]
    assert bootstrap_at(TrainConfig(), 0) == (False, 0.0)


def _log_steps(run: Path) -> list[dict]:
    return [d for d in map(json.loads, (run / "logs" / "train.jsonl").read_text().splitlines()) if "loss" in d]


def test_trainer_hands_over_from_a_wrong_bootstrap(synth_shards: Path, tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """The research oracle fed deliberately wrong poses: the warps are bad for the bootstrap's
    steps, and back at the DSC's (near identity at init) level once it hands over."""
    import relocdepth.train as train_mod

    real = train_mod.research_gt_poses

    def wrong_poses(shards, frames):
        T = real(shards, frames)  # refuses data without poses; the values are then replaced
        return _random_poses(len(T), seed=5, rot_deg=25.0, trans=0.6).numpy().astype(np.float32)

    monkeypatch.setattr(train_mod, "research_gt_poses", wrong_poses)
    cfg = train_mod.TrainConfig.from_dict({"size": (128, 96), "batch_size": 2, "pretrained": None,
                                           "workers": 0, "progress": False, "log_every": 1,
                                           "max_steps": 4, "bootstrap": "oracle-gt",
                                           "bootstrap_steps": 2, "bootstrap_fade_steps": 1,
                                           "photometric_pixels": "all"})
    train_mod.train(synth_shards, tmp_path / "run", cfg)
    steps = _log_steps(tmp_path / "run")
    assert [d["step"] for d in steps] == [1, 2, 3, 4]
    for d in steps[:2]:  # the wrong poses drive the warps: large motion, mostly off-image
        diag = d["diagnostics"]
        assert diag["boot_warps"] == 1.0 and diag["rel_trans"] == pytest.approx(diag["boot_rel_trans"])
        assert diag["rel_trans"] > 0.2 and diag["valid_frac"] < 0.8
    assert steps[2]["diagnostics"]["boot_warps"] == 0.0 and "L_boot" in steps[2]["parts"]  # fading
    assert "L_boot" not in steps[3]["parts"]  # the paper's loss alone
    for d in steps[2:]:  # the DSC's poses (near identity at init) drive them again
        assert d["diagnostics"]["rel_trans"] < 0.05 and d["diagnostics"]["valid_frac"] > 0.9


def test_posenet_bootstrap_trains_and_checkpoint_localizes(synth_shards: Path, tmp_path: Path) -> None:
    from relocdepth.checkpoint import load_for_inference
    from relocdepth.train import TrainConfig, train

    cfg = TrainConfig.from_dict({"size": (128, 96), "batch_size": 2, "pretrained": None,
                                 "workers": 0, "progress": False, "log_every": 1, "max_steps": 3,
                                 "bootstrap": "posenet", "bootstrap_steps": 2,
                                 "bootstrap_fade_steps": 1})
    summary = train(synth_shards, tmp_path / "run", cfg)
    assert summary["steps"] == 3
    steps = _log_steps(tmp_path / "run")
    assert [d["diagnostics"].get("boot_warps") for d in steps] == [1.0, 1.0, 0.0]
    nets, _ = load_for_inference(tmp_path / "run")
    assert hasattr(nets, "relpose")


def test_max_minutes_stops_on_wall_clock(synth_shards: Path, tmp_path: Path) -> None:
    from relocdepth.train import TrainConfig, train

    cfg = TrainConfig.from_dict({"size": (128, 96), "batch_size": 1, "pretrained": None,
                                 "workers": 0, "progress": False, "max_minutes": 1e-4,
                                 "checkpoint_every": 1000})
    summary = train(synth_shards, tmp_path / "run", cfg)
    assert summary["stop"] == "max_minutes" and summary["steps"] == 1
    assert summary["checkpoint"] is not None  # the final checkpoint


def test_cli_refuses_oracle_without_ground_truth_and_bad_values(synth_scene: Path, tmp_path: Path) -> None:
    from relocdepth.cli.main import app

    runner = CliRunner()
    frames = tmp_path / "frames"
    frames.mkdir()
    for p in sorted((synth_scene / "seq-01").glob("*.color.png"))[:8]:
        (frames / p.name).write_bytes(p.read_bytes())
    (tmp_path / "k.yaml").write_text((synth_scene / "intrinsics.yaml").read_text())
    r = runner.invoke(app, ["ingest", str(frames), "--K", str(tmp_path / "k.yaml"), "-o", str(tmp_path / "shards")])
    assert r.exit_code == 0, r.output
    common = ["--size", "128x96", "--pretrained", "none", "--workers", "0", "--no-progress", "--max-steps", "1"]
    r = runner.invoke(app, ["train", str(tmp_path / "shards"), "-o", str(tmp_path / "run"), *common,
                            "--bootstrap", "oracle-gt", "--bootstrap-steps", "5"])
    assert r.exit_code == 2 and "ground-truth poses" in r.output
    assert not (tmp_path / "run").exists()
    for bad in (["--bootstrap", "magic", "--bootstrap-steps", "5"], ["--bootstrap", "posenet"],
                ["--max-minutes", "0"]):
        r = runner.invoke(app, ["train", str(tmp_path / "shards"), "-o", str(tmp_path / "run2"), *common, *bad])
        assert r.exit_code == 2 and "error" in r.output.lower(), (bad, r.output)


def test_recipes_config_files_and_explicit_options_layer(synth_shards: Path, tmp_path: Path) -> None:
    """defaults < --recipe < --config < options given on the command line; a run's config.json
    repeats that run."""
    from relocdepth.cli.main import app

    from relocdepth.recipes import RECIPES
    from relocdepth.train import TrainConfig

    runner = CliRunner()
    common = ["--pretrained", "none", "--workers", "0", "--no-progress", "--max-steps", "1", "--batch-size", "1"]

    def trained(run: str) -> dict:
        train = json.loads((tmp_path / run / "config.json").read_text())["train"]
        return TrainConfig.from_dict(train).values()

    r = runner.invoke(app, ["train", str(synth_shards), "-o", str(tmp_path / "a"), "--recipe", "cpu-bootstrap",
                            "--window", "5", *common])
    assert r.exit_code == 0, r.output
    a = trained("a")
    assert a["lr"] == 3e-4 and a["method.photometric_pixels"] == "all"
    assert a["bootstrap"] == RECIPES["cpu-bootstrap"]["bootstrap"]
    assert (a["augment.width"], a["augment.height"]) == (128, 96)
    assert a["bootstrap_steps"] == RECIPES["cpu-bootstrap"]["bootstrap_steps"]
    assert a["sampler.window"] == 5  # given here: overrides the recipe's 3
    # The run's own config.json repeats it (same training fields), with options still on top.
    r = runner.invoke(app, ["train", str(synth_shards), "-o", str(tmp_path / "b"), "--config",
                            str(tmp_path / "a" / "config.json"), "--seed", "3"])
    assert r.exit_code == 0, r.output
    b = trained("b")
    assert {k: v for k, v in b.items() if k != "sampler.seed"} == {k: v for k, v in a.items() if k != "sampler.seed"}
    assert b["sampler.seed"] == 3
    # A YAML file over a recipe.
    (tmp_path / "c.yaml").write_text("lr: 0.002\nwindow: 7\n")
    r = runner.invoke(app, ["train", str(synth_shards), "-o", str(tmp_path / "c"), "--recipe", "cpu",
                            "--config", str(tmp_path / "c.yaml"), *common])
    assert r.exit_code == 0, r.output
    c = trained("c")
    assert (c["lr"], c["sampler.window"], c["method.photometric_pixels"], c["bootstrap"]) == (0.002, 7, "all", "off")
    # Bad input: one line, exit 2, nothing written.
    (tmp_path / "bad.yaml").write_text("learning_rate: 1\n")
    for bad in (["--recipe", "fast"], ["--config", str(tmp_path / "bad.yaml")],
                ["--config", str(tmp_path / "missing.yaml")]):
        r = runner.invoke(app, ["train", str(synth_shards), "-o", str(tmp_path / "d"), *common, *bad])
        assert r.exit_code == 2 and "error" in r.output, (bad, r.output)
        assert not (tmp_path / "d").exists()


def test_two_view_poses_scale_translation_by_depth_and_fall_back() -> None:
    """Essential-matrix pairs carry unit translations: the depth network's depth at the tracked
    points over their triangulated depths (in baselines) gives the translation's length."""
    from relocdepth.method import two_view_poses

    B, n = 2, 8
    T_true = _random_poses(6, seed=6).float().reshape(B, 3, 4, 4)
    rel = torch.stack((geo.relative_pose(T_true[:, 1], T_true[:, 0]), geo.relative_pose(T_true[:, 1], T_true[:, 2])), 1)
    unit = rel.clone()
    length = unit[..., :3, 3].norm(dim=-1, keepdim=True)
    unit[..., :3, 3] = unit[..., :3, 3] / length
    depth = torch.full((B, 1, H, W), 2.0)  # the network's depth units
    points = torch.full((B, 2, n, 3), float("nan"))
    points[:, :, :5, 0] = torch.linspace(3, W - 4, 5)
    points[:, :, :5, 1] = torch.linspace(3, H - 4, 5)
    points[:, :, :5, 2] = 2.0 / length.squeeze(-1).unsqueeze(-1)  # depth 2 = this many baselines
    ok = torch.tensor([[True, True], [True, False]])
    points[1, 0] = float("nan")  # a rotation-only pair: no triangulated points
    unit[1, 0, :3, 3] = 0.0
    dsc = _random_poses(6, seed=7).float().reshape(B, 3, 4, 4)
    got, t_known = two_view_poses((unit, points, ok), depth, dsc)
    assert torch.allclose(got[:, 1], torch.eye(4).expand(B, 4, 4))
    assert torch.allclose(geo.relative_pose(got[0, 1:2], got[0, 0:1]), rel[0, 0:1], atol=1e-5)
    assert torch.allclose(geo.relative_pose(got[0, 1:2], got[0, 2:3]), rel[0, 1:2], atol=1e-5)
    # The rotation-only pair keeps its rotation, with no translation.
    rot_only = geo.relative_pose(got[1, 1:2], got[1, 0:1])[0]
    assert torch.allclose(rot_only[:3, :3], rel[1, 0, :3, :3], atol=1e-5)
    assert torch.allclose(rot_only[:3, 3], torch.zeros(3), atol=1e-6)
    # The failed pair takes the DSC's relative pose.
    assert torch.allclose(geo.relative_pose(got[1, 1:2], got[1, 2:3]),
                          geo.relative_pose(dsc[1, 1:2], dsc[1, 2:3]), atol=1e-5)
    # Only measured translations count as known (the middle frame's own is).
    assert t_known.tolist() == [[True, True, True], [False, True, False]]


def test_preview_warps_the_target_from_a_source() -> None:
    """The TensorBoard preview: with the DSC near identity at init, the warped source stays close
    to the source itself, and every output has the documented shape."""
    from relocdepth.method import preview

    torch.manual_seed(0)
    nets = Networks(ModelConfig())
    smooth = torch.nn.functional.interpolate(torch.rand(6, 3, H // 8, W // 8), (H, W), mode="bilinear")
    imgs = smooth.reshape(2, 3, 3, H, W)
    view = preview(nets, imgs, imgs, _K(2), MethodConfig())
    assert view["target"].shape == (3, H, W) and torch.equal(view["target"], imgs[0, 1])
    assert view["depth"].shape == (H, W) and bool((view["depth"] > 0).all())
    assert view["warped"].shape == (3, H, W)
    # near-identity relative pose: the warp resamples the source, which differs from the target
    gap = float((imgs[0, 1] - imgs[0, 0]).abs().mean())
    assert float((view["warped"] - imgs[0, 0]).abs().mean()) < 0.5 * gap
