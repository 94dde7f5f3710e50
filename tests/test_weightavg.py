"""The weights' moving average: its arithmetic, and the trainer's (raw steps unchanged, saved,
resumed exactly, what localisation and evaluation load)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch

from relocdepth import checkpoint as ckpt_io
from relocdepth.errors import UserError
from relocdepth.weightavg import WeightAverage

torch.set_num_threads(1)

FAST = {"size": (128, 96), "batch_size": 2, "pretrained": None, "workers": 0, "progress": False, "log_every": 1}


def _cfg(**kw):
    from relocdepth.train import TrainConfig

    return TrainConfig.from_dict({**FAST, **kw})


def _ckpt(run: Path) -> dict:
    return torch.load(ckpt_io.latest_checkpoint(run), weights_only=True)


def test_the_average_of_a_ramp_lags_it_by_decay_over_one_minus_decay() -> None:
    """Weights that grow by 1 a step: an exponential average with decay d trails them by d / (1 - d)
    steps once the start is forgotten; BatchNorm's step counter is copied, not averaged."""
    net = torch.nn.Sequential(torch.nn.Linear(2, 1), torch.nn.BatchNorm1d(1))
    with torch.no_grad():
        for p in net.parameters():
            p.fill_(0.0)
    avg = WeightAverage(net, decay=0.9)
    for n in range(1, 401):
        with torch.no_grad():
            for p in net.parameters():
                p.fill_(float(n))
        net[1].num_batches_tracked.fill_(n)
        avg.update(net)
    w = avg.weights["0.weight"]
    torch.testing.assert_close(w, torch.full_like(w, 400.0 - 9.0), rtol=0, atol=1e-3)
    assert avg.weights["1.num_batches_tracked"].item() == 400 and avg.updates == 400


def test_the_first_updates_follow_the_weights_closely() -> None:
    """The decay starts at 2/11 and grows as (1 + n) / (10 + n) up to the one asked for."""
    net = torch.nn.Linear(1, 1, bias=False)
    with torch.no_grad():
        net.weight.fill_(0.0)
    avg = WeightAverage(net, decay=0.999)
    assert avg.decay_now() == pytest.approx(2 / 11)
    with torch.no_grad():
        net.weight.fill_(11.0)
    avg.update(net)
    assert avg.weights["weight"].item() == pytest.approx(9.0)  # 2/11 of 0 and 9/11 of 11
    avg.updates = 10_000
    assert avg.decay_now() == pytest.approx(0.999)
    with pytest.raises(ValueError, match="decay"):
        WeightAverage(net, decay=1.0)


def test_training_with_the_average_takes_the_same_steps_and_saves_it(synth_shards: Path, tmp_path: Path) -> None:
    from relocdepth.train import train

    plain, averaged = tmp_path / "plain", tmp_path / "averaged"
    train(synth_shards, plain, _cfg(max_steps=3))
    train(synth_shards, averaged, _cfg(max_steps=3, ema_decay=0.9))
    a, b = _ckpt(plain), _ckpt(averaged)
    assert a["ema"] is None and b["ema"]["updates"] == 3 and b["ema"]["decay"] == 0.9
    assert all(torch.equal(a["model"][k], b["model"][k]) for k in a["model"])  # the raw steps
    ema = b["ema"]["weights"]
    moved = [k for k in ema if ema[k].is_floating_point() and not torch.equal(ema[k], b["model"][k])]
    assert len(moved) > len(ema) // 2  # an average of three steps is not the last one
    # localisation and evaluation take the average; a checkpoint without one, the raw weights
    nets, meta = ckpt_io.load_for_inference(averaged)
    assert meta["weights"] == "average"
    assert all(torch.equal(v, ema[k]) for k, v in nets.state_dict().items())
    nets, meta = ckpt_io.load_for_inference(averaged, raw=True)  # the trained weights when asked
    assert meta["weights"] == "raw"
    assert all(torch.equal(v, b["model"][k]) for k, v in nets.state_dict().items())
    nets, meta = ckpt_io.load_for_inference(plain)
    assert meta["weights"] == "raw"
    assert all(torch.equal(v, a["model"][k]) for k, v in nets.state_dict().items())
    # and the evaluation's report says which (its schema checked as it is written)
    from relocdepth.evaluate import EvalConfig, evaluate
    from relocdepth.report import format_table

    report = evaluate(synth_shards, averaged, EvalConfig(), tmp_path / "report.json")
    assert report["checkpoint"]["weights"] == "average" and "averaged weights" in format_table(report)


def test_a_resumed_run_continues_its_average_exactly(synth_shards: Path, tmp_path: Path) -> None:
    from relocdepth.train import train

    straight, resumed = tmp_path / "straight", tmp_path / "resumed"
    train(synth_shards, straight, _cfg(max_steps=4, ema_decay=0.9))
    train(synth_shards, resumed, _cfg(max_steps=2, ema_decay=0.9))
    train(synth_shards, resumed, _cfg(max_steps=4, ema_decay=0.9, resume=True))
    a, b = _ckpt(straight)["ema"], _ckpt(resumed)["ema"]
    assert a["updates"] == b["updates"] == 4
    assert all(torch.equal(a["weights"][k], b["weights"][k]) for k in a["weights"])
    # resumed without a decay (the default, none), a run keeps its own average and its decay
    kept = tmp_path / "kept"
    train(synth_shards, kept, _cfg(max_steps=2, ema_decay=0.9))
    train(synth_shards, kept, _cfg(max_steps=4, resume=True))
    c = _ckpt(kept)
    assert c["ema"]["updates"] == 4 and c["ema"]["decay"] == 0.9 and c["meta"]["train"]["ema_decay"] == 0.9
    assert all(torch.equal(a["weights"][k], c["ema"]["weights"][k]) for k in a["weights"])
    # a run trained without one may start one when resumed: from the weights it resumes with
    late = tmp_path / "late"
    train(synth_shards, late, _cfg(max_steps=2))
    shutil.copytree(late, tmp_path / "late-copy")
    train(synth_shards, late, _cfg(max_steps=3, ema_decay=0.9, resume=True))
    ck, before = _ckpt(late), _ckpt(tmp_path / "late-copy")
    assert ck["ema"]["updates"] == 1
    d = 2 / 11  # the first update's decay: 2/11 of the step-2 weights, 9/11 of the step-3 ones
    k = next(k for k, v in ck["model"].items() if v.is_floating_point() and v.dim() == 4)
    torch.testing.assert_close(ck["ema"]["weights"][k], d * before["model"][k] + (1 - d) * ck["model"][k])


def test_the_decay_must_be_below_one() -> None:
    for bad in (1.0, -0.1, float("nan")):
        with pytest.raises(UserError, match="--ema-decay must be in"):
            _cfg(ema_decay=bad)
