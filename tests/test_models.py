"""Networks: torchvision-compatible encoder weights, output shapes, parameter counts, init."""

from __future__ import annotations

import logging
import urllib.error
from pathlib import Path

import pytest
import torch

from relocdepth import geometry as geo
from relocdepth.errors import UserError
from relocdepth.models import ModelConfig, build_networks, disp_to_depth
from relocdepth.models.depth import DepthNet
from relocdepth.models.dsc import DSCNet
from relocdepth.models.encoder import ResNet18Encoder
from relocdepth.models.pose import AbsPoseNet

torch.set_num_threads(1)


def torchvision_resnet18_shapes() -> dict[str, tuple[int, ...]]:
    """Parameter/buffer names and shapes of ``torchvision.models.resnet18().state_dict()``,
    written out from torchvision's layout (torchvision is not installed here)."""
    shapes: dict[str, tuple[int, ...]] = {"conv1.weight": (64, 3, 7, 7)}

    def bn(prefix: str, c: int) -> None:
        for k in ("weight", "bias", "running_mean", "running_var"):
            shapes[f"{prefix}.{k}"] = (c,)
        shapes[f"{prefix}.num_batches_tracked"] = ()

    bn("bn1", 64)
    cin = 64
    for layer, cout in zip(range(1, 5), (64, 128, 256, 512)):
        for block in (0, 1):
            p = f"layer{layer}.{block}"
            shapes[f"{p}.conv1.weight"] = (cout, cin if block == 0 else cout, 3, 3)
            bn(f"{p}.bn1", cout)
            shapes[f"{p}.conv2.weight"] = (cout, cout, 3, 3)
            bn(f"{p}.bn2", cout)
            if block == 0 and layer > 1:
                shapes[f"{p}.downsample.0.weight"] = (cout, cin, 1, 1)
                bn(f"{p}.downsample.1", cout)
        cin = cout
    shapes["fc.weight"] = (1000, 512)
    shapes["fc.bias"] = (1000,)
    return shapes


def _write_state_dict(path: Path, seed: int = 0) -> dict[str, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    state = {
        k: (torch.tensor(7) if s == () else torch.rand(s, generator=gen) + 0.5)
        for k, s in torchvision_resnet18_shapes().items()
    }
    torch.save(state, path)
    return state


def test_encoder_keys_match_torchvision() -> None:
    own = {k: tuple(v.shape) for k, v in ResNet18Encoder().state_dict().items()}
    tv = {k: s for k, s in torchvision_resnet18_shapes().items() if not k.startswith("fc.")}
    assert own == tv


def test_encoder_loads_torchvision_state_dict(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "resnet18.pth"
    state = _write_state_dict(path)
    enc = ResNet18Encoder()
    enc.load_imagenet_weights(path)
    assert torch.equal(enc.layer3[0].downsample[0].weight, state["layer3.0.downsample.0.weight"])
    assert torch.equal(enc.bn1.running_var, state["bn1.running_var"])
    with caplog.at_level(logging.INFO, logger="relocdepth.models"):
        nets = build_networks(ModelConfig(pretrained=str(path)))
    assert torch.equal(nets.depth.encoder.conv1.weight, state["conv1.weight"])
    assert torch.equal(nets.dsc.encoder.conv1.weight, state["conv1.weight"])
    assert "ImageNet" in caplog.text


def test_wrong_weight_files_are_clear_user_errors(tmp_path: Path) -> None:
    enc = ResNet18Encoder()
    with pytest.raises(UserError, match="does not exist"):
        enc.load_imagenet_weights(tmp_path / "missing.pth")
    junk = tmp_path / "junk.pth"
    junk.write_bytes(b"not a checkpoint at all")
    with pytest.raises(UserError, match="cannot read"):
        enc.load_imagenet_weights(junk)
    wrong = tmp_path / "resnet50.pth"
    state = {k: torch.zeros(s) for k, s in torchvision_resnet18_shapes().items()}
    state["layer1.0.conv1.weight"] = torch.zeros(64, 64, 1, 1)  # a bottleneck's 1x1, as resnet50
    torch.save(state, wrong)
    with pytest.raises(UserError, match="layer1.0.conv1.weight"):
        enc.load_imagenet_weights(wrong)
    partial = tmp_path / "partial.pth"
    torch.save({"conv1.weight": torch.zeros(64, 3, 7, 7)}, partial)
    with pytest.raises(UserError, match="keys missing"):
        build_networks(ModelConfig(pretrained=str(partial)))
    bad_hash = tmp_path / "resnet18-f37072fd.pth"
    _write_state_dict(bad_hash)
    with pytest.raises(UserError, match="checksum"):
        enc.load_imagenet_weights(bad_hash)


def test_imagenet_offline_falls_back_to_random_init(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    def offline(*args: object, **kwargs: object) -> None:
        raise urllib.error.URLError("no network")

    monkeypatch.setattr(torch.hub, "load_state_dict_from_url", offline)
    with caplog.at_level(logging.WARNING, logger="relocdepth.models"):
        nets = build_networks(ModelConfig(pretrained="imagenet", use_dsc=False))
    assert "RANDOMLY initialised" in caplog.text
    assert hasattr(nets, "pose") and not hasattr(nets, "dsc")


@pytest.fixture(scope="module")
def three_nets() -> tuple[DepthNet, DSCNet, AbsPoseNet]:
    return DepthNet().eval(), DSCNet().eval(), AbsPoseNet().eval()


@pytest.mark.parametrize("size", [(128, 96), (256, 192), (640, 480)])
def test_output_shapes(size: tuple[int, int], three_nets: tuple[DepthNet, DSCNet, AbsPoseNet]) -> None:
    W, H = size
    x = torch.rand(1, 3, H, W)
    depth, dsc, pose = three_nets
    with torch.no_grad():
        disps = depth(x)
        assert [tuple(d.shape) for d in disps] == [(1, 1, H >> s, W >> s) for s in range(4)]
        assert all(float(d.min()) >= 0 and float(d.max()) <= 1 for d in disps)
        assert tuple(dsc(x).shape) == (1, 6, H // 32, W // 32)
        assert tuple(pose(x).shape) == (1, 6)


def test_input_size_must_be_multiple_of_32() -> None:
    with pytest.raises(UserError, match="multiple of 32"):
        ResNet18Encoder()(torch.rand(1, 3, 100, 128))
    with pytest.raises(ValueError, match=r"\(B, 3, H, W\)"):
        ResNet18Encoder()(torch.rand(1, 1, 96, 128))


def _count(m: torch.nn.Module) -> int:
    return sum(p.numel() for p in m.parameters())


def test_parameter_counts(three_nets: tuple[DepthNet, DSCNet, AbsPoseNet]) -> None:
    depth, dsc, pose = three_nets
    assert _count(depth.encoder) == 11_176_512  # torchvision resnet18 (11,689,512) without fc
    assert _count(depth.decoder) == 3_152_724  # monodepth2's depth decoder
    assert _count(dsc.head) == 1_772_038  # 3x3 512->256, 3x3 256->256 (+BN), 1x1 256->6
    assert _count(pose) - _count(pose.encoder) == 1_313_030  # monodepth2 pose decoder, 1 image
    nets = build_networks(ModelConfig())
    assert _count(nets) == _count(depth) + _count(dsc)


def test_disp_to_depth_range() -> None:
    sigma = torch.tensor([0.0, 0.5, 1.0])
    d = disp_to_depth(sigma, 0.1, 100.0)
    assert torch.allclose(d[[0, 2]], torch.tensor([100.0, 0.1]))
    assert 0.1 < float(d[1]) < 100.0


def test_initial_dsc_gives_finite_nondegenerate_poses() -> None:
    torch.manual_seed(0)
    nets = build_networks(ModelConfig()).eval()
    x = torch.rand(2, 3, 96, 128)
    K = torch.tensor([[100.0, 0, 63.5], [0, 100.0, 47.5], [0, 0, 1]]).expand(2, 3, 3)
    with torch.no_grad():
        dsc = nets.dsc(x)
        depth = disp_to_depth(nets.depth(x)[0])
        q, c = geo.cell_poses(dsc, geo.pool_depth(depth), K)
        qm, cm = geo.mean_cell_pose(q, c)
    assert dsc.abs().max() < 0.5  # small initial DSC: G ~ I, tau ~ 0
    assert torch.isfinite(q).all() and torch.isfinite(c).all()
    assert torch.isfinite(geo.pose_matrix(qm, cm)).all()
    # each cell looks along its own ray, so the mean rotation is near identity
    assert float(torch.rad2deg(geo.quat_angle(qm, torch.tensor([1.0, 0, 0, 0])).max())) < 5.0


def test_decoder_batch_norm_option() -> None:
    """Paper Sec. IV-B: BN in every layer but the outputs. Off: monodepth2's decoder, unchanged."""
    from relocdepth.models.depth import NUM_CH_DEC

    plain, bn = DepthNet(), DepthNet(decoder_bn=True)
    norms = [m for m in bn.decoder.modules() if isinstance(m, torch.nn.BatchNorm2d)]
    assert len(norms) == 2 * len(NUM_CH_DEC)  # two conv blocks per decoder level
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in plain.decoder.modules())
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in bn.decoder.dispconv.modules())
    # each block trades its conv bias (cout) for BN's scale and shift (2 cout)
    assert _count(bn.decoder) == _count(plain.decoder) + 2 * sum(NUM_CH_DEC)
    keys = set(plain.decoder.state_dict())
    assert "upconv1.4.conv.bias" in keys and not any("norm" in k for k in keys)
    x = torch.rand(2, 3, 96, 128)
    bn.train()
    disps = [d.detach() for d in bn(x)]
    assert [tuple(d.shape) for d in disps] == [(2, 1, 96 >> s, 128 >> s) for s in range(4)]
    assert all(float(d.min()) >= 0 and float(d.max()) <= 1 for d in disps)
    assert float(bn.decoder.upconv0[0].norm.running_mean.abs().sum()) > 0  # statistics are tracked
    nets = build_networks(ModelConfig(decoder_bn=True))
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in nets.depth.decoder.modules())


def _save_run(run: Path, model_cfg: dict, state: dict[str, torch.Tensor]) -> None:
    import relocdepth
    from relocdepth import checkpoint as ckpt_io

    meta = {
        "format": ckpt_io.FORMAT, "format_version": ckpt_io.FORMAT_VERSION,
        "tool_version": relocdepth.__version__, "created": "2026-01-01T00:00:00+00:00",
        "step": 1, "epoch": 0, "position": 0, "manifest_hash": "test",
        "dataset": {"name": "test", "root": str(run)}, "input_size": [128, 96],
        "intrinsics": {"fx": 100.0, "fy": 100.0, "cx": 63.5, "cy": 47.5, "width": 128, "height": 96},
        "intrinsics_policy": "resize", "model": model_cfg, "method": {}, "train": {}, "world_size": 1,
    }
    ckpt_io.save_checkpoint(run, {"meta": meta, "model": state})


def test_checkpoints_with_and_without_decoder_bn_load(tmp_path: Path) -> None:
    from relocdepth import checkpoint as ckpt_io

    torch.manual_seed(0)
    old = build_networks(ModelConfig())
    # a checkpoint written before the option existed: no decoder_bn in its model config
    _save_run(tmp_path / "old", {"pretrained": None, "use_dsc": True, "min_depth": 0.1, "max_depth": 100.0},
              old.state_dict())
    nets, _ = ckpt_io.load_for_inference(tmp_path / "old")
    assert not nets.cfg.decoder_bn
    assert torch.equal(nets.depth.decoder.upconv1[4].conv.bias, old.depth.decoder.upconv1[4].conv.bias)
    with_bn = build_networks(ModelConfig(decoder_bn=True))
    with_bn.depth(torch.rand(2, 3, 96, 128))  # moves the running statistics off their init
    _save_run(tmp_path / "bn", {"pretrained": None, "use_dsc": True, "decoder_bn": True, "min_depth": 0.1,
                                "max_depth": 100.0}, with_bn.state_dict())
    nets, _ = ckpt_io.load_for_inference(tmp_path / "bn")
    assert nets.cfg.decoder_bn
    stats = nets.depth.decoder.upconv0[2].norm.running_var
    assert torch.equal(stats, with_bn.depth.decoder.upconv0[2].norm.running_var)
