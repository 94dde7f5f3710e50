"""The training config: composed of the sampler, augmentation, method and model configs; flat
option names (the command line's, recipes, runs written before the sections) map onto it; nested
configs round-trip; layering defaults < recipe < config file < options given."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from relocdepth import checkpoint as ckpt_io
from relocdepth.errors import UserError
from relocdepth.recipes import read_config_file, recipe
from relocdepth.train import TrainConfig

torch.set_num_threads(1)

# A run's config.json `train` entry as runs wrote it before the sections (one flat mapping of
# every option), with values away from the defaults so that each must arrive in its place.
FLAT_RUN = {
    "size": [128, 96], "epochs": 40, "batch_size": 2, "lr": 0.0003, "beta1": 0.8, "beta2": 0.99,
    "window": 3, "window_seconds": None, "global_epochs": 10, "global_prob": 0.25,
    "window_schedule": [[0, 2], [5, 3]], "min_parallax": 1.5, "scale_min": 1.0, "scale_max": 1.05,
    "brightness": 0.1, "contrast": 0.15, "saturation": 0.05, "hue": 0.02, "jitter_per_image": True,
    "lcvs": False, "use_dsc": False, "pretrained": None, "alpha": 0.8, "w_s": 0.002, "w_c": 0.05,
    "photometric_pixels": "all", "recompute_warps": True, "loss_resolution": "input",
    "decoder_bn": True, "bootstrap": "essential", "oracle_gt_depth": False, "bootstrap_steps": 7,
    "bootstrap_fade_steps": 3, "w_bootstrap": 0.5, "seed": 11, "workers": 0, "device": "cpu",
    "amp": False, "amp_dtype": "bf16", "channels_last": False, "max_steps": 9, "max_minutes": 2.5,
    "log_every": 4, "checkpoint_every": 6, "keep_last": 2, "max_nonfinite": 5, "progress": False,
    "resume": False,
}
# Where each flat option lives now.
FLAT_PLACES = {
    "epochs": "sampler.epochs", "window": "sampler.window", "window_seconds": "sampler.window_seconds",
    "global_epochs": "sampler.global_epochs", "global_prob": "sampler.global_prob",
    "window_schedule": "sampler.window_schedule", "min_parallax": "sampler.min_parallax",
    "seed": "sampler.seed", "scale_min": "augment.scale_min", "scale_max": "augment.scale_max",
    "brightness": "augment.brightness", "contrast": "augment.contrast",
    "saturation": "augment.saturation", "hue": "augment.hue",
    "jitter_per_image": "augment.jitter_per_image", "lcvs": "method.lcvs", "alpha": "method.alpha",
    "w_s": "method.w_s", "w_c": "method.w_c", "photometric_pixels": "method.photometric_pixels",
    "recompute_warps": "method.recompute_warps", "loss_resolution": "method.loss_resolution",
    "pretrained": "model.pretrained", "decoder_bn": "model.decoder_bn",
}


def _as_json(value):
    return json.loads(json.dumps(value))


def test_flat_config_json_loads_with_the_same_values(tmp_path: Path) -> None:
    path = tmp_path / "config.json"
    path.write_text(json.dumps({"tool_version": "0.1.0", "shards": "x", "world_size": 1, "train": FLAT_RUN}))
    cfg = TrainConfig.from_values(read_config_file(path))
    values = cfg.values()
    for name, value in FLAT_RUN.items():
        if name == "size":
            assert (values["augment.width"], values["augment.height"]) == tuple(value) == cfg.size
        elif name == "use_dsc":  # one option of the method and the networks
            assert values["method.use_dsc"] is values["model.use_dsc"] is False
        elif name == "resume":  # a repeated run starts afresh
            assert values["resume"] is False
        else:
            assert _as_json(values[FLAT_PLACES.get(name, name)]) == value, name
    assert cfg.sampler.window_schedule == ((0, 2), (5, 3)) and cfg.epochs == 40 and cfg.seed == 11
    # The sections get exactly these values: what the sampler, loader, losses and networks see.
    assert cfg.sampler.window_at(6) == 3 and cfg.augment.jitter_per_image and not cfg.method.lcvs
    assert cfg.model.pretrained is None and not cfg.model.use_dsc and not cfg.model.relpose
    assert TrainConfig.from_dict(FLAT_RUN) == cfg


def test_nested_config_round_trips_through_json(tmp_path: Path) -> None:
    cfg = TrainConfig.from_dict({**FLAT_RUN, "bootstrap": "posenet"})
    assert cfg.model.relpose  # the bootstrap's two-frame network
    nested = _as_json(cfg.to_dict())
    assert set(nested) >= {"sampler", "augment", "method", "model"} and "window" not in nested
    assert nested["sampler"]["window"] == 3 and nested["augment"]["width"] == 128
    assert TrainConfig.from_dict(nested) == cfg
    path = tmp_path / "config.json"
    path.write_text(json.dumps({"train": nested}))
    assert TrainConfig.from_values(read_config_file(path)) == cfg
    assert TrainConfig.from_dict({}) == TrainConfig()


def test_recipe_config_file_and_flags_layer_across_flat_and_nested(tmp_path: Path) -> None:
    # defaults < recipe (flat) < config file (nested) < options given (flat)
    (tmp_path / "c.yaml").write_text("sampler:\n  window: 7\n  seed: 4\nmethod:\n  w_s: 0.01\n"
                                     "augment:\n  width: 160\n  height: 128\n")
    values = TrainConfig.values_of(recipe("cpu"))
    values.update(read_config_file(tmp_path / "c.yaml"))
    values.update(TrainConfig.values_of({"window": 9, "use_dsc": False}))
    cfg = TrainConfig.from_values(values)
    assert cfg.sampler.window == 9  # the flag's
    assert cfg.sampler.seed == 4 and cfg.method.w_s == 0.01 and cfg.size == (160, 128)  # the file's
    assert cfg.lr == 3e-4 and cfg.method.photometric_pixels == "all"  # the recipe's
    assert cfg.sampler.global_prob == 0.5 and cfg.batch_size == 6  # the defaults
    assert not cfg.method.use_dsc and not cfg.model.use_dsc


def test_an_option_of_two_sections_is_one_option_and_unknown_ones_are_refused(tmp_path: Path) -> None:
    with pytest.raises(UserError, match="use_dsc must be the same"):
        TrainConfig.from_dict({"method": {"use_dsc": False}})
    with pytest.raises(UserError, match="unknown option.*method.learning_rate.*windw"):
        TrainConfig.from_dict({"windw": 3, "method": {"learning_rate": 1}})
    with pytest.raises(UserError, match="size must be"):
        TrainConfig.from_dict({"size": 128})
    with pytest.raises(UserError, match="loss_resolution"):  # the method's own check, as a user error
        TrainConfig.from_dict({"method": {"loss_resolution": "output"}})
    (tmp_path / "bad.json").write_text(json.dumps({"train": {"sampler": {"windw": 3}}}))
    with pytest.raises(UserError, match=r"--config .*bad.json: unknown option\(s\) sampler.windw"):
        read_config_file(tmp_path / "bad.json")


def test_checkpoint_with_a_flat_config_resumes_with_its_values(synth_shards: Path, tmp_path: Path) -> None:
    """A run whose checkpoint stores the flat layout (written before the sections) resumes with
    its own values, and its networks load for inference."""
    from relocdepth.cli.main import app

    run = tmp_path / "run"
    common = ["--size", "64x64", "--batch-size", "1", "--pretrained", "none", "--workers", "0", "--no-progress"]
    r = CliRunner().invoke(app, ["train", str(synth_shards), "-o", str(run), *common, "--max-steps", "1",
                                 "--window", "4", "--seed", "5"])
    assert r.exit_code == 0, r.output
    path = ckpt_io.latest_checkpoint(run)
    ck = torch.load(path, weights_only=False)
    flat = {**FLAT_RUN, "size": [64, 64], "batch_size": 1, "window": 4, "seed": 5, "bootstrap": "off",
            "bootstrap_steps": 0, "min_parallax": None, "use_dsc": True, "decoder_bn": False,
            "max_steps": 1}
    ck["meta"]["train"] = flat
    torch.save(ck, path)
    r = CliRunner().invoke(app, ["train", str(synth_shards), "-o", str(run), *common, "--max-steps", "2",
                                 "--resume"])
    assert r.exit_code == 0, r.output
    saved = TrainConfig.from_dict(ckpt_io.load_checkpoint(ckpt_io.latest_checkpoint(run))["meta"]["train"])
    assert saved.max_steps == 2  # given now (how the run runs)
    assert (saved.sampler.window, saved.seed, saved.lr, saved.method.w_c) == (4, 5, 0.0003, 0.05)  # the run's
    nets, meta = ckpt_io.load_for_inference(run)
    assert meta["step"] == 2 and hasattr(nets, "dsc")


def test_resume_keeps_what_the_command_line_did_not_give(synth_shards: Path, tmp_path: Path,
                                                        caplog: pytest.LogCaptureFixture) -> None:
    """``--resume`` alone keeps the run's options, its weights' average and checkpoint interval
    included, without warning; a training option given again is kept at the run's value and named;
    a run control given again (``--checkpoint-every``) is taken; ``--ema-decay 0`` given when
    resuming ends the average; training options given are not checked against each other, run
    controls are."""
    from relocdepth.cli.main import app

    run = tmp_path / "run"
    common = ["--size", "64x64", "--batch-size", "1", "--pretrained", "none", "--workers", "0", "--no-progress"]

    def reloc(*args: str) -> dict:
        r = CliRunner().invoke(app, ["train", str(synth_shards), "-o", str(run), *common, *args])
        assert r.exit_code == 0, r.output
        return ckpt_io.load_checkpoint(ckpt_io.latest_checkpoint(run))

    reloc("--max-steps", "1", "--lr", "0.0002", "--window", "4", "--ema-decay", "0.9", "--checkpoint-every", "7")
    caplog.clear()
    ck = reloc("--max-steps", "2", "--resume")
    assert "given values ignored" not in caplog.text
    saved = TrainConfig.from_dict(ck["meta"]["train"])
    assert (saved.lr, saved.sampler.window, saved.ema_decay, saved.checkpoint_every) == (0.0002, 4, 0.9, 7)
    assert saved.max_steps == 2
    assert ck["ema"]["updates"] == 2
    caplog.clear()
    ck = reloc("--max-steps", "3", "--resume", "--lr", "0.001")
    assert "keeping the run's lr = 0.0002 (given values ignored)" in caplog.text
    assert TrainConfig.from_dict(ck["meta"]["train"]).lr == 0.0002 and ck["ema"]["updates"] == 3
    ck = reloc("--max-steps", "4", "--resume", "--ema-decay", "0", "--checkpoint-every", "9")
    saved = TrainConfig.from_dict(ck["meta"]["train"])
    assert ck["ema"] is None and saved.ema_decay == 0.0 and saved.checkpoint_every == 9
    # A training option that needs another (here --anchor-bundle) is no error when resuming: the
    # run keeps its own value of both; only the run controls given must make sense.
    caplog.clear()
    ck = reloc("--max-steps", "5", "--resume", "--anchor-bundle-scale-degree", "2")
    assert "keeping the run's anchor_bundle_scale_degree = None (given values ignored)" in caplog.text
    assert TrainConfig.from_dict(ck["meta"]["train"]).anchor_bundle_scale_degree is None
    r = CliRunner().invoke(app, ["train", str(synth_shards), "-o", str(run), *common, "--resume",
                                 "--max-minutes", "-1"])
    assert r.exit_code == 2 and "--max-minutes must be > 0" in r.output


def test_resume_with_the_runs_own_config_file_warns_of_nothing(synth_shards: Path, tmp_path: Path,
                                                               caplog: pytest.LogCaptureFixture) -> None:
    """A config file given again when resuming, with the run's own values (lists, as YAML has
    them, where the config holds tuples), is no value the run keeps over: no warning."""
    from relocdepth.cli.main import app

    run, conf = tmp_path / "run", tmp_path / "run.yaml"
    conf.write_text("window_schedule: [[0, 2], [5, 3]]\nlr: 0.0002\n")
    common = ["--size", "64x64", "--batch-size", "1", "--pretrained", "none", "--workers", "0", "--no-progress",
              "--config", str(conf)]
    for args in (["--max-steps", "1"], ["--max-steps", "2", "--resume"]):
        caplog.clear()
        r = CliRunner().invoke(app, ["train", str(synth_shards), "-o", str(run), *common, *args])
        assert r.exit_code == 0, r.output
    assert "given values ignored" not in caplog.text
    saved = TrainConfig.from_dict(ckpt_io.load_checkpoint(ckpt_io.latest_checkpoint(run))["meta"]["train"])
    assert saved.sampler.window_schedule == ((0, 2), (5, 3)) and saved.lr == 0.0002 and saved.max_steps == 2


def test_every_recipe_is_a_valid_config_that_says_what_it_sets() -> None:
    from relocdepth.recipes import RECIPES

    for name, options in RECIPES.items():
        cfg = TrainConfig.from_values(TrainConfig.values_of(recipe(name)))
        values = cfg.values()
        for key, value in TrainConfig.values_of(options).items():
            assert values[key] == value, (name, key)
    assert TrainConfig.from_values(TrainConfig.values_of(recipe("cpu-linked"))).anchor == "linked"


def test_a_recipes_scale_line_is_turned_off_from_the_command_line(synth_shards: Path, tmp_path: Path) -> None:
    """``--anchor-bundle-scale-degree none`` over ``--recipe cpu-anchored`` trains without the
    recipe's line and keeps the rest of the recipe; a degree given is taken; text that is neither
    is a one-line usage error."""
    from relocdepth.cli.main import app

    common = ["--size", "64x64", "--batch-size", "1", "--pretrained", "none", "--workers", "0", "--no-progress",
              "--recipe", "cpu-anchored", "--max-steps", "1"]
    for given, degree in (("none", None), ("None", None), ("2", 2)):
        run = tmp_path / f"run-{given}"
        r = CliRunner().invoke(app, ["train", str(synth_shards), "-o", str(run), *common,
                                     "--anchor-bundle-scale-degree", given])
        assert r.exit_code == 0, r.output
        saved = TrainConfig.from_dict(ckpt_io.load_checkpoint(ckpt_io.latest_checkpoint(run))["meta"]["train"])
        assert saved.anchor_bundle_scale_degree == degree
        assert (saved.anchor, saved.anchor_bundle, saved.anchor_combine) == ("vo", True, 3)  # the recipe's
    assert TrainConfig.from_values(TrainConfig.values_of(recipe("cpu-anchored"))).anchor_bundle_scale_degree == 1
    r = CliRunner().invoke(app, ["train", str(synth_shards), "-o", str(tmp_path / "bad"), *common,
                                 "--anchor-bundle-scale-degree", "one"])
    assert r.exit_code == 2 and "--anchor-bundle-scale-degree must be a whole number or none, not 'one'" in r.output
    assert not (tmp_path / "bad").exists() or ckpt_io.latest_checkpoint(tmp_path / "bad") is None
