"""Training options the README lists, each checked on what it promises: --keep-last,
--jitter-per-image, --amp on CPU (bf16), and `reloc demo` end to end at a tiny size."""

from __future__ import annotations

import functools
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from relocdepth.cli.main import app
from typer.testing import CliRunner

from relocdepth import checkpoint as ckpt_io

torch.set_num_threads(1)

FAST = ["--size", "64x64", "--batch-size", "1", "--pretrained", "none", "--workers", "0",
        "--no-progress", "--log-every", "1"]


def _cli(*args: str) -> str:
    res = CliRunner().invoke(app, list(args))
    assert res.exit_code == 0, res.output[-3000:]
    return res.output


# -- --keep-last ---------------------------------------------------------------------------------------
@pytest.mark.slow
def test_keep_last_keeps_the_newest_and_a_valid_pointer(synth_shards: Path, tmp_path: Path) -> None:
    from relocdepth.schemas import validate

    run = tmp_path / "run"
    _cli("train", str(synth_shards), "-o", str(run), *FAST, "--checkpoint-every", "1", "--max-steps", "3",
         "--keep-last", "2")
    log = [json.loads(x) for x in (run / "logs" / "train.jsonl").read_text().splitlines()]
    written = [r["path"] for r in log if r.get("event") == "checkpoint"]
    assert written == [ckpt_io.checkpoint_name(s) for s in (1, 2, 3)]  # three were written ...
    d = run / "checkpoints"
    assert sorted(p.name for p in d.iterdir()) == [*written[1:], "latest"]  # ... the 2 newest remain
    for name in written[1:]:  # each complete and holding the step its name says
        assert ckpt_io.load_checkpoint(d / name)["meta"]["step"] == int(name[5:13])
    pointer = json.loads((d / "latest").read_text())
    validate("checkpoint_pointer", pointer)
    assert pointer["checkpoint"] == written[-1] and pointer["step"] == 3
    assert ckpt_io.resolve_checkpoint(run) == d / written[-1]
    assert ckpt_io.load_for_inference(run)[1]["step"] == 3


# -- --jitter-per-image --------------------------------------------------------------------------------
def _same_frame_thrice(seed: int) -> object:
    from relocdepth.sampler import Triplet

    # One frame as all three images: any difference between the network inputs is the jitter's.
    return Triplet(source_a=5, target=5, source_b=5, aug_seed=seed, is_global=False, epoch=0, position=0)


def test_jitter_per_triplet_is_one_draw_per_image_is_three(synth_shards: Path) -> None:
    from relocdepth.data import AugmentConfig, ImageFrames, TripletData

    frames = ImageFrames.open(synth_shards)
    shared = TripletData(frames, AugmentConfig(64, 64, scale_max=1.0))
    per_image = TripletData(frames, AugmentConfig(64, 64, scale_max=1.0, jitter_per_image=True))
    for seed in range(4):
        a, b = shared[_same_frame_thrice(seed)], per_image[_same_frame_thrice(seed)]
        assert all(np.array_equal(a["images"][0], x) for x in a["images"])  # the same pixels thrice
        assert np.array_equal(a["images"], b["images"]) and np.array_equal(a["K"], b["K"])  # inputs only
        # Per triplet: one draw, identical network inputs, but jittered.
        assert all(np.array_equal(a["inputs"][0], x) for x in a["inputs"])
        assert not np.array_equal(a["inputs"][0], a["images"][0])
        # Per image: three draws, three different network inputs.
        x = b["inputs"].astype(np.int16)
        for i, j in ((0, 1), (0, 2), (1, 2)):
            assert np.abs(x[i] - x[j]).mean() > 1.0, (seed, i, j)
    # Brightness only: each image's own factor lies in the configured +-0.2 and they differ.
    bright = TripletData(frames, AugmentConfig(64, 64, scale_max=1.0, contrast=0.0, saturation=0.0, hue=0.0,
                                               jitter_per_image=True))[_same_frame_thrice(7)]
    img = bright["images"][0].astype(float)
    keep = img < 200  # pixels that a factor up to 1.2 does not clip
    ratios = [bright["inputs"][i].astype(float)[keep].mean() / img[keep].mean() for i in range(3)]
    assert all(0.79 < r < 1.21 for r in ratios) and max(ratios) - min(ratios) > 0.01


def test_jitter_per_image_option_reaches_the_run(synth_shards: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    _cli("train", str(synth_shards), "-o", str(run), *FAST, "--max-steps", "0", "--jitter-per-image")
    assert json.loads((run / "config.json").read_text())["train"]["augment"]["jitter_per_image"] is True
    meta = ckpt_io.load_checkpoint(ckpt_io.latest_checkpoint(run))["meta"]
    assert meta["train"]["augment"]["jitter_per_image"] is True
    from relocdepth.train import TrainConfig

    assert TrainConfig.from_dict(meta["train"]).augment.jitter_per_image is True


# -- --amp on CPU -------------------------------------------------------------------------------------
def test_amp_on_cpu_trains_a_step_in_bf16(synth_shards: Path, tmp_path: Path) -> None:
    from relocdepth.data import collate
    from relocdepth.train import TrainConfig, forward_losses, optimizer_step, sample, setup

    cfg = TrainConfig.from_dict({"size": (64, 64), "batch_size": 1, "pretrained": None,
                                 "workers": 0, "progress": False, "device": "cpu", "amp": True,
                                 "amp_dtype": "bf16"})
    tr, state = setup(synth_shards, tmp_path / "run", cfg)
    try:
        convs = [m for m in tr.nets.modules() if isinstance(m, torch.nn.Conv2d)]
        dtypes: set[torch.dtype] = set()
        hooks = [m.register_forward_hook(lambda _m, _i, out: dtypes.add(out.dtype)) for m in convs]
        before = {k: v.detach().clone() for k, v in tr.nets.named_parameters()}
        b = sample(tr, state, collate([tr.data[t] for t in list(tr.sampler.iter_epoch(0))[:1]]))
        assert b is not None
        loss, parts, _ = forward_losses(tr, b)
        for h in hooks:
            h.remove()
        assert dtypes == {torch.bfloat16}  # every convolution of both networks ran in bf16 ...
        assert loss.dtype == torch.float32 and torch.isfinite(loss)  # ... the loss stays float32
        assert all(torch.isfinite(torch.as_tensor(v)).all() for v in parts.values())
        assert optimizer_step(tr, state, loss) and state.nonfinite_skipped == 0
        after = dict(tr.nets.named_parameters())
        assert all(p.dtype == torch.float32 and torch.isfinite(p).all() for p in after.values())
        assert sum(not torch.equal(before[k], after[k]) for k in before) > len(before) // 2
    finally:
        tr.log.close()


# -- reloc demo -----------------------------------------------------------------------------------------
@pytest.mark.slow
def test_demo_runs_end_to_end_at_a_tiny_size(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import relocdepth.demo as demo_mod

    # The command as users run it, on a smaller scene than its default (3 x 150 frames at 128x96,
    # batch 6, about 4 minutes at the least on a busy 2-core machine): 3 x 12 frames at 64x64.
    tiny = functools.partial(demo_mod.DemoConfig, frames=12, size=(64, 64), batch_size=1, workers=0,
                             eval_batch_size=8)
    monkeypatch.setattr(demo_mod, "DemoConfig", tiny)
    out = tmp_path / "demo"
    text = _cli("demo", "-o", str(out), "--minutes", "0.75", "--pretrained", "none")
    assert "pose, test frames" in text and "depth, test frames" in text and "demo done in" in text
    assert "\nbeats: " in text  # which references the model beats (or "none ... yet")
    done = json.loads((out / "demo.json").read_text())
    assert done["status"] == "done" and done["config"]["size"] == [64, 64]
    # One run that the trainer stops itself on wall-clock time, with the demo recipe's bootstrap.
    log = [json.loads(x) for x in (out / "run" / "logs" / "train.jsonl").read_text().splitlines()]
    assert [r["event"] for r in log if r.get("event") in ("start", "resume")] == ["start"]
    assert done["train"]["stop"] == "max_minutes" and done["train"]["steps"] >= 1
    assert done["timings"]["train_s"] >= 0.75 * 60
    steps = [r for r in log if r.get("kind") == "step"]
    assert steps and steps[0]["diagnostics"]["boot_warps"] == 1.0
    report = json.loads((out / "eval" / "report.json").read_text())
    assert report["checkpoint"]["step"] == done["train"]["steps"]  # it evaluated the final weights
    # ... and refined the test poses against the nearest training frames, beside the network's
    assert report["pose"]["refined"]["test"]["median_t_m"] >= 0 and "refined, nearest train" in text
    assert report["dataset"]["test_frames"] == 12 and report["checkpoint"]["input_size"] == [64, 64]
    for p in (out / "eval" / "plots" / "trajectory.png", out / "eval" / "plots" / "depth_strips.png",
              out / "run" / "checkpoints" / "alignment.json"):
        assert p.is_file() and p.stat().st_size > 0, p
    # A second demo into the same folder replaces the first; a foreign folder is refused.
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("keep me")
    res = CliRunner().invoke(app, ["demo", "-o", str(foreign), "--minutes", "0.1", "--pretrained", "none"])
    assert res.exit_code == 2 and "holds no earlier demo" in res.output
    assert (foreign / "notes.txt").read_text() == "keep me"


def test_the_demo_says_which_references_it_beats() -> None:
    """Each reference is beaten only where both figures are lower; the refined pose is judged
    against retrieval apart from the network's own, and only where the report has it."""
    from relocdepth.demo import beaten_references

    report = {
        "pose": {"test": {"median_t_m": 0.25, "median_r_deg": 4.7},
                 "relative": {"k": 5, "median_t_m": 0.035, "median_r_deg": 1.6,
                              "identity_median_t_m": 0.039, "identity_median_r_deg": 2.6}},
        "baselines": {"mean_pose": {"median_t_m": 0.34, "median_r_deg": 14.9},
                      "retrieval": {"median_t_m": 0.21, "median_r_deg": 5.4}},
        "depth": {"prediction": {"abs_rel": 0.08}, "constant_reference": {"abs_rel": 0.21}},
    }
    beats, misses = beaten_references(report)
    assert [b.split(" (")[0] for b in beats] == ["constant depth", "identity relative pose, frames 5 apart",
                                                  "mean training pose"]
    assert [m.split(" (")[0] for m in misses] == ["thumbnail retrieval"]
    report["pose"]["refined"] = {"test": {"median_t_m": 0.045, "median_r_deg": 2.2}}
    beats, misses = beaten_references(report)
    assert beats[-1].startswith("thumbnail retrieval by the refined pose") and "0.045 m / 2.2 deg" in beats[-1]
    assert [m.split(" (")[0] for m in misses] == ["thumbnail retrieval"]
    report["pose"]["refined"]["test"]["median_r_deg"] = 6.0  # rotation above retrieval's: not beaten
    assert beaten_references(report)[1][-1].startswith("thumbnail retrieval by the refined pose")
