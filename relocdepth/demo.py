"""``reloc demo``: the whole product on a generated scene, in about ten minutes on a laptop CPU.

Stages (each a library call, each output a folder under ``out``):
``scene/`` (synth, 7-Scenes layout) -> ``shards/`` (ingest) -> ``run/`` (train for a time
budget) -> ``eval/`` (the paper's protocol: report.json, TUM trajectories, plots).

The training budget is wall-clock time, kept by the trainer itself (``TrainConfig.max_minutes``),
so a machine that gets faster or slower while it trains still uses the whole budget.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from dataclasses import asdict, dataclass
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
    # The training recipe (relocdepth.recipes): the CPU recipe with the relative-pose bootstrap and,
    # from step 100, absolute anchors from the training frames' own odometry.
    recipe: str = "demo"
    batch_size: int = 6  # paper IV-B
    pretrained: str | None = "imagenet"  # ImageNet encoder if downloadable, else random init
    workers: int = 1  # DataLoader workers (a 2-core machine)
    eval_batch_size: int = 16
    # Also evaluate each test pose refined against its nearest training frames (relocdepth.refine,
    # not the paper's: what `reloc localize --refine` gives), beside the network's own (~20 s).
    refine: bool = True


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


def _train(shards: Path, run: Path, cfg: DemoConfig) -> dict:
    """Train for ``cfg.minutes`` of wall-clock time (the trainer stops itself and checkpoints)."""
    from relocdepth.recipes import recipe
    from relocdepth.train import TrainConfig, train

    tcfg = TrainConfig.from_dict({
        **recipe(cfg.recipe), "size": cfg.size, "batch_size": cfg.batch_size, "pretrained": cfg.pretrained,
        "seed": cfg.seed, "workers": cfg.workers, "max_minutes": cfg.minutes, "log_every": 10,
        "checkpoint_every": 200, "progress": True,
    })
    return train(shards, run, tcfg)


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
    summary = _train(out / "shards", out / "run", cfg)
    timings["train_s"] = time.perf_counter() - t
    t = time.perf_counter()
    log.info("demo 4/4: evaluating (the paper's protocol%s)", "; and the poses refined" if cfg.refine else "")
    report = evaluate(out / "shards", out / "run", EvalConfig(batch_size=cfg.eval_batch_size, refine=cfg.refine),
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


def beaten_references(report: dict) -> tuple[list[str], list[str]]:
    """Which of the evaluation's references the model beats, and which it does not: constant depth
    (AbsRel), identity relative pose (translation and rotation between test frames k apart), the
    mean training pose and thumbnail retrieval (median translation and rotation); where the report
    has refined poses (``evaluate --refine``), thumbnail retrieval by the refined pose too."""
    test, rel, base = report["pose"]["test"], report["pose"]["relative"], report["baselines"]
    depth = report.get("depth") or {}
    pred, const = depth.get("prediction") or {}, depth.get("constant_reference") or {}
    checks = []
    if pred.get("abs_rel") is not None and const.get("abs_rel") is not None:
        checks.append((f"constant depth (AbsRel {pred['abs_rel']:.3f} vs {const['abs_rel']:.3f})",
                       pred["abs_rel"] < const["abs_rel"]))
    if rel.get("median_t_m") is not None:
        checks.append(((f"identity relative pose, frames {rel['k']} apart ({rel['median_t_m']:.4f} m / "
                       f"{rel['median_r_deg']:.2f} deg vs {rel['identity_median_t_m']:.4f} m / "
                       f"{rel['identity_median_r_deg']:.2f} deg)"),
                       rel["median_t_m"] < rel["identity_median_t_m"]
                       and rel["median_r_deg"] < rel["identity_median_r_deg"]))
    for key, name in (("mean_pose", "mean training pose"), ("retrieval", "thumbnail retrieval")):
        b = base[key]
        checks.append(((f"{name} ({test['median_t_m']:.3f} m / {test['median_r_deg']:.1f} deg vs "
                       f"{b['median_t_m']:.3f} m / {b['median_r_deg']:.1f} deg)"),
                       test["median_t_m"] < b["median_t_m"] and test["median_r_deg"] < b["median_r_deg"]))
    refined = report["pose"].get("refined")
    if refined:
        r, b = refined["test"], base["retrieval"]
        checks.append(((f"thumbnail retrieval by the refined pose, not the paper's ({r['median_t_m']:.3f} m / "
                       f"{r['median_r_deg']:.1f} deg)"),
                       r["median_t_m"] < b["median_t_m"] and r["median_r_deg"] < b["median_r_deg"]))
    return [n for n, ok in checks if ok], [n for n, ok in checks if not ok]


def _jsonable(d: dict) -> dict:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}
