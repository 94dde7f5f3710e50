"""``reloc demo``: the whole product on a generated scene, in about ten minutes on a laptop CPU.

Stages (each a library call, each output a folder under ``out``):
``scene/`` (synth, 7-Scenes layout) -> ``shards/`` (ingest) -> ``run/`` (train for a time
budget) -> ``eval/`` (the paper's protocol: report.json, TUM trajectories, plots).

The trainer counts steps, not seconds, so the budget is met in two legs of one run: a few
steps to measure the step time, then a resume with as many steps as the remaining time allows.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

from relocdepth.errors import UserError

log = logging.getLogger(__name__)

MARKER = "demo.json"  # says a folder is a demo output (and may be replaced by the next demo)
OWNED = ("scene", "shards", "run", "eval", MARKER)


@dataclass(frozen=True)
class DemoConfig:
    """What `reloc demo` does; defaults fit ~10 minutes on a 2-core CPU."""

    minutes: float = 8.0  # training budget (synth + ingest + evaluate add about a minute)
    seed: int = 0
    sequences: int = 3  # 2 train + 1 test, like a small 7-Scenes scene
    frames: int = 150  # per sequence: 5 s at 30 fps
    size: tuple[int, int] = (128, 96)  # rendered and trained at this size (W, H)
    batch_size: int = 6  # paper IV-B
    window: int = 3  # nearby frames +-3: at this budget wider windows do not learn (issue 6)
    # L_p over all pixels (monodepth2): at 650 steps it halved the relative rotation error where
    # the in-image mask did nothing (README, Quality)
    photometric_pixels: str = "all"
    lr: float = 3e-4  # the measured CPU recipe's rate (paper: 1e-4)
    pretrained: str | None = "imagenet"  # ImageNet encoder if downloadable, else random init
    calibration_steps: int = 6  # first leg: steps to measure the step time
    workers: int = 1  # DataLoader workers (a 2-core machine)
    eval_batch_size: int = 16


def _prepare(out: Path) -> None:
    """Refuse to touch a folder that is not ours; clear a previous demo's outputs."""
    if out.exists() and not out.is_dir():
        raise UserError(f"{out} exists and is not a folder; choose another -o")
    if out.is_dir() and any(out.iterdir()):
        if not (out / MARKER).is_file():
            raise UserError(f"{out} is not empty and holds no earlier demo ({MARKER}); choose another -o")
        for name in OWNED:
            p = out / name
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()
    out.mkdir(parents=True, exist_ok=True)
    (out / MARKER).write_text(json.dumps({"status": "running"}) + "\n")


def _step_seconds(run: Path) -> tuple[float, float]:
    """(seconds per step, start-up seconds before the first step) from the run's train log."""
    start, steps = None, []
    for line in (run / "logs" / "train.jsonl").read_text().splitlines():
        rec = json.loads(line)
        if rec.get("kind") == "event" and rec.get("event") in ("start", "resume"):
            start, steps = rec["time"], []
        elif rec.get("kind") == "step":
            steps.append((rec["step"], rec["time"]))
    if start is None or len(steps) < 3:
        raise RuntimeError(f"{run}: too few step records to time the training")
    (s0, t0), (s1, t1) = steps[1], steps[-1]  # from the 2nd step: the 1st includes warm-up
    per_step = (t1 - t0) / (s1 - s0)
    return per_step, max(steps[0][1] - start - per_step, 0.0)


def _train(shards: Path, run: Path, cfg: DemoConfig, deadline: float) -> dict:
    """Train until ``deadline`` (a time.perf_counter() value): time a few steps, then resume
    with as many steps as the remaining time allows."""
    from relocdepth.train import TrainConfig, train

    tcfg = TrainConfig(
        size=cfg.size, batch_size=cfg.batch_size, window=cfg.window, pretrained=cfg.pretrained,
        photometric_pixels=cfg.photometric_pixels, lr=cfg.lr,
        seed=cfg.seed, workers=cfg.workers, max_steps=cfg.calibration_steps, log_every=1,
        checkpoint_every=200, progress=False,
    )
    first = train(shards, run, tcfg)
    step_s, startup_s = _step_seconds(run)
    left = deadline - time.perf_counter() - startup_s
    more = int(left / step_s)
    log.info("demo: %.2f s per step; %d more steps fit in the remaining %.0f s", step_s, more, left)
    if more <= 0:
        return first
    return train(shards, run, replace(tcfg, max_steps=first["steps"] + more, resume=True,
                                      log_every=10, progress=True))


def run_demo(out: str | Path, cfg: DemoConfig = DemoConfig()) -> dict:
    """Generate, ingest, train, evaluate; returns {"report", "paths", "timings", "train"}."""
    from relocdepth.evaluate import EvalConfig, evaluate
    from relocdepth.ingest.run import IngestConfig, ingest
    from relocdepth.synth import SynthConfig, generate_scene

    if cfg.minutes <= 0:
        raise UserError("--minutes must be positive")
    if cfg.sequences < 2:
        raise UserError("the demo needs at least 2 sequences (train and test)")
    out = Path(out)
    _prepare(out)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    w, h = cfg.size
    log.info("demo 1/4: rendering %d sequences x %d frames at %dx%d", cfg.sequences, cfg.frames, w, h)
    generate_scene(out / "scene", SynthConfig(seed=cfg.seed, frames=cfg.frames, width=w, height=h,
                                              train_sequences=cfg.sequences - 1))
    timings["synth_s"] = time.perf_counter() - t0
    t = time.perf_counter()
    log.info("demo 2/4: ingesting into shards")
    ingest([out / "scene"], out / "shards", IngestConfig())
    timings["ingest_s"] = time.perf_counter() - t
    t = time.perf_counter()
    log.info("demo 3/4: training for %.1f minutes at %dx%d", cfg.minutes, w, h)
    summary = _train(out / "shards", out / "run", cfg, t + 60.0 * cfg.minutes)
    timings["train_s"] = time.perf_counter() - t
    t = time.perf_counter()
    log.info("demo 4/4: evaluating (the paper's protocol)")
    report = evaluate(out / "shards", out / "run", EvalConfig(batch_size=cfg.eval_batch_size),
                      report_path=out / "eval" / "report.json", plots_dir=out / "eval" / "plots",
                      save_alignment=True)
    timings["evaluate_s"] = time.perf_counter() - t
    timings["total_s"] = time.perf_counter() - t0
    timings = {k: round(v, 1) for k, v in timings.items()}
    result = {"config": _jsonable(asdict(cfg)), "timings": timings, "train": summary,
              "paths": {"scene": str(out / "scene"), "shards": str(out / "shards"),
                        "run": str(out / "run"), **report["outputs"]}}
    (out / MARKER).write_text(json.dumps({"status": "done"} | result, indent=2) + "\n")
    return result | {"report": report}


def _jsonable(d: dict) -> dict:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}
