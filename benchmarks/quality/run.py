"""Quality benchmark: does the method learn within a CPU budget?

On the default demo scene (synth seed 0, 3 sequences x 150 frames, 128x96; ingested once), or on
a real walk-through (``--data PATH``: a folder of images/, depth/, poses.txt, K.txt such as
``shared/data/hololens-office``, laid out as a 7-Scenes scene whose last ``--walk-test`` frames
are the test sequence, or ``--walk-blocks`` blocks of them inside the walk; trained at ``--size``), each configuration (row) is trained from scratch
for a wall-clock budget, then evaluated with the paper's protocol (``reloc evaluate``). Writes
``quality.md`` (a markdown table) and ``quality.json`` (the numbers, the recipes, the rung each
row reaches) to ``--out``.

    python benchmarks/quality/run.py [--budget-min 15] [--rows paper,cpu,no-lcvs,no-dsc,...]
                                     [--threads 1] [--out /tmp/quality] [--redo] [--parallel 2]
    python benchmarks/quality/run.py --data ../shared/data/hololens-office --size 192x128 \
                                     --rows oracle-gt,cpu-bootstrap --out /tmp/quality-holo

Every training and evaluation is a child process (``reloc train`` / ``reloc evaluate``) with
``threads`` torch threads; ``--parallel N`` trains N rows at once (on 2 cores: 2 rows of 1
thread). The budget is the trainer's own ``--max-minutes``: it stops after the step in flight
and writes a checkpoint. The steps a row reaches depend on the machine's speed (and load): the
table reports them.

Rungs (each needs the ones below): 1 = depth AbsRel <= 0.9 x constant depth and the relative
pose between test frames 5 apart <= 0.9 x identity in translation and rotation; 2 = median
translation below the mean-pose reference; 3 = median translation and rotation below thumbnail
retrieval. The rungs judge the network's own pose (the paper's); the table's ``refined`` column is
the same checkpoint's pose refined against its nearest training frames (``reloc evaluate
--refine``), beside it.

A row whose ``rows/<name>/result.json`` already holds the same recipe and budget is reused
(``--redo`` retrains it), so the table can be rebuilt, or rows added, without retraining.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import time
from pathlib import Path

log = logging.getLogger("quality")

# The demo scene (relocdepth.demo.DemoConfig defaults): 2 train + 1 test sequence.
SCENE = {"seed": 0, "frames": 150, "width": 128, "height": 96, "train_sequences": 2}
SIZE = f"{SCENE['width']}x{SCENE['height']}"

# Options every row shares (plus --size). Random init: the development machine is offline (no
# ImageNet weights), and it keeps the rows comparable. The batch is the paper's (6 triplets).
COMMON = ["--pretrained", "none", "--batch-size", "6", "--seed", "0", "--workers", "0",
          "--no-progress", "--log-every", "10", "--checkpoint-every", "1000000", "--keep-last", "1"]

# Row -> `reloc train` options on top of COMMON. `paper`: the paper's recipe at 128x96.
# `demo`: the demo's recipe (window 3, one colour jitter per triplet, lr 1e-4), the starting
# point of `cpu`. `cpu`: the best CPU recipe found (README, section quality: trial log).
PAPER = ["--window", "20", "--jitter-per-image", "--scale-max", "1.1", "--lr", "1e-4"]
DEMO = ["--window", "3", "--scale-max", "1.1", "--lr", "1e-4"]
CPU = ["--window", "3", "--scale-max", "1.1", "--lr", "3e-4"]
# `cpu-all`: `cpu` with L_p over all pixels (trial 2). `cpu-schedule`: `cpu-all` with the window
# growing 3 -> 10 -> 20 frames (trial 4: a +-3 window leaves ~1 px of parallax at 128x96).
CPU_ALL = CPU + ["--photometric-pixels", "all"]
CPU_SCHEDULE = CPU_ALL + ["--window-schedule", "0:3,8:10,16:20"]
# Rows of the named recipes (relocdepth.recipes, the ones `reloc train --recipe` and the demo use).
# `oracle-gt`: ground-truth poses drive the warps throughout (a research ceiling for depth: what
# it learns when the poses are right); `oracle-gt-depth`: ground-truth depth in the poses and
# warps (what the pose half learns when depth is right). `cpu-bootstrap`: the essential-matrix
# bootstrap drives them for the first steps, then the DSC (the paper's loss) with the consistency
# term fading out; `cpu-posenet` the same with the two-frame pose network.
RECIPES: dict[str, list[str]] = {
    "paper": PAPER,
    "cpu": CPU,
    "cpu-all": CPU_ALL,
    "cpu-schedule": CPU_SCHEDULE,
    "no-lcvs": CPU + ["--no-lcvs"],
    "no-dsc": CPU + ["--no-dsc"],
    "demo": DEMO,
    "oracle-gt": ["--recipe", "cpu", "--bootstrap", "oracle-gt", "--bootstrap-steps", "100000000"],
    "oracle-gt-depth": ["--recipe", "cpu", "--oracle-gt-depth"],
    "cpu-bootstrap": ["--recipe", "cpu-bootstrap"],
    "cpu-bootstrap-decoder": ["--recipe", "cpu-bootstrap", "--loss-resolution", "decoder"],
    "cpu-posenet": ["--recipe", "cpu-posenet"],
    "cpu-essential": ["--recipe", "cpu-bootstrap", "--bootstrap", "essential"],
    # `oracle-gt-w10`: the GT-pose oracle at the bootstrap recipes' +-10 frames (their yardstick).
    "oracle-gt-w10": ["--recipe", "cpu", "--window", "10", "--loss-resolution", "decoder",
                      "--bootstrap", "oracle-gt", "--bootstrap-steps", "100000000"],
    # `cpu-bootstrap-w3`: the bootstrap recipe at the `cpu` recipe's +-3 frames.
    "cpu-bootstrap-w3": ["--recipe", "cpu-bootstrap", "--window", "3"],
    "cpu-bootstrap-no-lcvs": ["--recipe", "cpu-bootstrap", "--no-lcvs"],
    "cpu-bootstrap-no-dsc": ["--recipe", "cpu-bootstrap", "--no-dsc"],
    # `cpu-anchored`: the bootstrap recipe with the DSC's absolute anchors from odometry.
    "cpu-anchored": ["--recipe", "cpu-anchored"],
    # `cpu-anchored-views`: the anchors rebuilt within a budget, with the depth's new views.
    "cpu-anchored-views": ["--recipe", "cpu-anchored-views"],
    # `cpu-linked`: the bootstrap recipe with anchors from the DSC's own poses, sequences linked.
    "cpu-linked": ["--recipe", "cpu-linked"],
}
# A walk-through moves ~10 cm per frame (hololens-office), 7-Scenes ~0.7 cm: its window is in
# frames too, so rows on it use +-2 (last option wins).
WALK_WINDOW = ["--window", "2"]
OWN_WINDOW: set[str] = set()  # rows that keep their own window there
DEFAULT_ROWS = "paper,cpu,no-lcvs,no-dsc"

# "Clearly" below a reference (rungs 1 and 2): at most this fraction of it.
CLEARLY = 0.9

# Python run in each child: the thread count is set before any work, then the CLI runs.
CHILD = ("import sys, torch; torch.set_num_threads(int(sys.argv[1])); torch.set_num_interop_threads(1); "
         "from relocdepth.cli.main import main; main(sys.argv[2:])")


def child_env(threads: int) -> dict[str, str]:
    env = dict(os.environ)
    for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        env[k] = str(threads)
    return env


def reloc(args: list[str], threads: int, logfile: Path) -> subprocess.Popen:
    """Start ``reloc ARGS`` as a child with ``threads`` torch threads, output to ``logfile``."""
    logfile.parent.mkdir(parents=True, exist_ok=True)
    with logfile.open("a") as f:
        return subprocess.Popen([sys.executable, "-c", CHILD, str(threads), *args], stdout=f,
                                stderr=subprocess.STDOUT, env=child_env(threads))


def run_to_end(args: list[str], threads: int, logfile: Path) -> None:
    rc = reloc(args, threads, logfile).wait()
    if rc != 0:
        raise RuntimeError(f"reloc {' '.join(args[:1])} failed (exit {rc}); see {logfile}")


def walk_split(test: int, blocks: int, every: int) -> str:
    """Which frames of a walk-through test, in words (the log and quality.md)."""
    if every:
        return f"one frame in {every} a test frame"
    return f"the last {test} frames test" if blocks == 1 else f"{test} test frames in {blocks} blocks inside the walk"


def prepare_data(out: Path, threads: int, walk: Path | None = None, walk_test: int = 30, walk_blocks: int = 1,
                 walk_every: int = 0) -> Path:
    """Render the demo scene (or lay out the walk-through) and ingest it once; returns the shards."""
    from relocdepth.ingest.run import IngestConfig, ingest

    from relocdepth.synth import SynthConfig, generate_scene

    scene, shards = out / "data" / "scene", out / "data" / "shards"
    if (shards / "manifest.json").is_file():
        log.info("reusing %s", shards)
        return shards
    import torch

    torch.set_num_threads(threads)
    if walk is not None:
        sys.path.insert(0, str(Path(__file__).parent))
        from walkthrough import lay_out

        log.info("laying out %s as a 7-Scenes scene in %s (%s)", walk, scene,
                 walk_split(walk_test, walk_blocks, walk_every))
        lay_out(walk, scene, walk_test, walk_blocks, walk_every)
    else:
        log.info("rendering the demo scene into %s", scene)
        generate_scene(scene, SynthConfig(**SCENE))
    log.info("ingesting into %s", shards)
    ingest([scene], shards, IngestConfig())
    return shards


def start_training(shards: Path, run: Path, recipe: list[str], budget_s: float, threads: int) -> subprocess.Popen:
    """Start training from scratch with the trainer's own wall-clock budget."""
    args = ["train", str(shards), "-o", str(run), *recipe, "--max-minutes", f"{budget_s / 60.0:g}"]
    return reloc(args, threads, run.parent / "train.log")


def training_summary(run: Path, proc: subprocess.Popen, seconds: float) -> dict:
    """Steps, stop reason and loss curve of a finished training child."""
    stopped = False
    if not (run / "checkpoints").is_dir() or not any((run / "checkpoints").iterdir()):
        raise RuntimeError(f"training wrote no checkpoint (exit {proc.returncode}); see {run.parent / 'train.log'}")
    steps, losses = 0, []
    for line in (run / "logs" / "train.jsonl").read_text().splitlines():
        rec = json.loads(line)
        if rec.get("kind") == "step":
            steps = max(steps, rec["step"])
            losses.append((rec["step"], rec["loss"]))
        elif rec.get("kind") == "event" and rec.get("event") == "stop":
            steps = max(steps, rec["step"])
            stopped = rec.get("reason") == "max_minutes"
    tail = [v for s, v in losses if s > 0.9 * steps] or [v for _, v in losses[-3:]]
    return {"seconds": round(seconds, 1), "stopped_at_deadline": stopped, "steps": steps,
            "final_loss": round(sum(tail) / len(tail), 4) if tail else None,
            "loss_curve": losses[:: max(len(losses) // 20, 1)]}


def evaluate(shards: Path, run: Path, report: Path, threads: int) -> dict:
    t0 = time.perf_counter()
    run_to_end(["evaluate", str(shards), "--checkpoint", str(run), "-o", str(report), "--refine"], threads,
               report.parent / "evaluate.log")
    log.info("evaluated in %.0f s", time.perf_counter() - t0)
    return json.loads(report.read_text())


def metrics(report: dict) -> dict:
    """The table's columns from a ``reloc evaluate`` report."""
    test, rel = report["pose"]["test"], report["pose"]["relative"]
    depth = (report.get("depth") or {}).get("prediction") or {}
    refined = report["pose"].get("refined")  # evaluate --refine; older reports lack it
    return {
        "median_t_m": test["median_t_m"], "median_r_deg": test["median_r_deg"],
        "refined_t_m": refined["test"]["median_t_m"] if refined else None,
        "refined_r_deg": refined["test"]["median_r_deg"] if refined else None,
        "pct_10cm_10deg": test["pct_10cm_10deg"],
        "rel_k": rel["k"], "rel_t_m": rel["median_t_m"], "rel_r_deg": rel["median_r_deg"],
        "abs_rel": depth.get("abs_rel"), "delta1": depth.get("delta1"),
        "scale_std_over_median": depth.get("scale_std_over_median"),
    }


def references(report: dict) -> dict:
    """Mean-pose, retrieval, identity relative pose and constant-depth rows (same split)."""
    base, rel = report["baselines"], report["pose"]["relative"]
    const = (report.get("depth") or {}).get("constant_reference") or {}
    return {
        "mean_pose": {k: base["mean_pose"][k] for k in ("median_t_m", "median_r_deg", "pct_10cm_10deg")},
        "retrieval": {k: base["retrieval"][k] for k in ("median_t_m", "median_r_deg", "pct_10cm_10deg")},
        "identity_relative": {"rel_k": rel["k"], "rel_t_m": rel["identity_median_t_m"],
                              "rel_r_deg": rel["identity_median_r_deg"]},
        "constant_depth": {k: const.get(k) for k in ("abs_rel", "delta1", "scale_std_over_median")},
        # an oracle (the test frames' ground truth), shown beside the references, not a rung
        "nearest_centre": {k: base[key][k] for k in ("median_t_m", "median_r_deg", "pct_10cm_10deg")}
        if (key := "nearest_training_centre") in base else None,
    }


def rung(m: dict, ref: dict) -> tuple[int, list[str]]:
    """The highest rung reached (0: none; module docstring), each rung needing the ones below it,
    and why the next one is not reached."""
    ident, const = ref["identity_relative"], ref["constant_depth"]
    mean, retr = ref["mean_pose"], ref["retrieval"]
    checks = [
        [("AbsRel", m["abs_rel"], CLEARLY * const["abs_rel"]),
         ("relative t", m["rel_t_m"], CLEARLY * ident["rel_t_m"]),
         ("relative r", m["rel_r_deg"], CLEARLY * ident["rel_r_deg"])],
        [("median t", m["median_t_m"], mean["median_t_m"])],
        [("median t", m["median_t_m"], retr["median_t_m"]), ("median r", m["median_r_deg"], retr["median_r_deg"])],
    ]
    reached = 0
    for level in checks:
        failed = [f"{name} {v:.3g} > {bar:.3g}" for name, v, bar in level if v is None or not v < bar]
        if failed:
            return reached, failed
        reached += 1
    return reached, []


def fmt(v: float | None, spec: str) -> str:
    return "-" if v is None else format(v, spec)


def table(rows: dict, ref: dict, size: str) -> str:
    head = ("| row | input | budget | steps | median t (m) | median r (deg) | 10cm/10deg | "
            "rel. pose, frames 5 apart (m / deg) | AbsRel | d<1.25 | scale std/median | "
            "refined t / r (m / deg) | rung |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for name, r in rows.items():
        m = r["metrics"]
        lines.append(
            f"| {name} | {size} | {r['budget_min']:g} min | {r['train']['steps']} | {m['median_t_m']:.3f} | "
            f"{m['median_r_deg']:.1f} | {m['pct_10cm_10deg']:.1f} % | {m['rel_t_m']:.4f} / {m['rel_r_deg']:.2f} | "
            f"{fmt(m['abs_rel'], '.3f')} | {fmt(m['delta1'], '.3f')} | {fmt(m['scale_std_over_median'], '.3f')} | "
            f"{fmt(m.get('refined_t_m'), '.3f')} / {fmt(m.get('refined_r_deg'), '.1f')} | {r['rung']} |")
    mp, rt, idr, cd = ref["mean_pose"], ref["retrieval"], ref["identity_relative"], ref["constant_depth"]
    refs = [
        ("*mean pose*", {4: f"{mp['median_t_m']:.3f}", 5: f"{mp['median_r_deg']:.1f}",
                         6: f"{mp['pct_10cm_10deg']:.1f} %"}),
        ("*thumbnail retrieval*", {4: f"{rt['median_t_m']:.3f}", 5: f"{rt['median_r_deg']:.1f}",
                                   6: f"{rt['pct_10cm_10deg']:.1f} %"}),
        ("*identity (relative)*", {7: f"{idr['rel_t_m']:.4f} / {idr['rel_r_deg']:.2f}"}),
        ("*constant depth*", {8: fmt(cd["abs_rel"], ".3f"), 9: fmt(cd["delta1"], ".3f"),
                              10: fmt(cd["scale_std_over_median"], ".3f")}),
    ]
    if (nc := ref.get("nearest_centre")) is not None:  # results from before the oracle lack it
        refs.append(("*nearest training centre (oracle)*", {4: f"{nc['median_t_m']:.3f}",
                     5: f"{nc['median_r_deg']:.1f}", 6: f"{nc['pct_10cm_10deg']:.1f} %"}))
    for name, cells in refs:
        lines.append("| " + " | ".join([name] + [cells.get(i, "") for i in range(1, 13)]) + " |")
    return "\n".join(lines)


def recipe_of(name: str, size: str, walk: bool) -> list[str]:
    return ["--size", size, *COMMON, *RECIPES[name], *(WALK_WINDOW if walk and name not in OWN_WINDOW else [])]


def run_rows(names: list[str], shards: Path, out: Path, budget_min: float, threads: int, redo: bool,
             size: str, walk: bool, parallel: int) -> dict:
    """Train (``parallel`` at a time) and evaluate the rows that have no result for this recipe yet."""
    results: dict[str, dict] = {}
    todo = []
    for name in names:
        recipe, done = recipe_of(name, size, walk), out / "rows" / name / "result.json"
        if done.is_file() and not redo:
            prev = json.loads(done.read_text())
            if prev.get("recipe") == recipe and prev.get("budget_min") == budget_min:
                log.info("%s: reusing %s", name, done)
                results[name] = prev
                continue
        todo.append(name)
    for i in range(0, len(todo), parallel):
        group = todo[i:i + parallel]
        procs = {}
        t0 = time.perf_counter()
        for name in group:
            folder = out / "rows" / name
            if folder.exists():
                import shutil

                shutil.rmtree(folder)
            log.info("%s: training %.1f min: reloc train %s", name, budget_min, " ".join(recipe_of(name, size, walk)))
            procs[name] = start_training(shards, folder / "run", recipe_of(name, size, walk), 60.0 * budget_min,
                                         threads)
        for name, proc in procs.items():
            proc.wait()
            folder = out / "rows" / name
            summary = training_summary(folder / "run", proc, time.perf_counter() - t0)
            log.info("%s: %d steps, loss %.4f", name, summary["steps"], summary["final_loss"] or float("nan"))
        for name in group:
            folder = out / "rows" / name
            summary = training_summary(folder / "run", procs[name], time.perf_counter() - t0)
            report = evaluate(shards, folder / "run", folder / "eval" / "report.json", threads)
            results[name] = {"row": name, "recipe": recipe_of(name, size, walk), "budget_min": budget_min,
                             "threads": threads, "train": summary, "metrics": metrics(report),
                             "references": references(report)}
            (folder / "result.json").write_text(json.dumps(results[name], indent=2) + "\n")
    return {name: results[name] for name in names}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--budget-min", type=float, default=15.0, help="training wall clock per row (minutes)")
    ap.add_argument("--rows", default=DEFAULT_ROWS, help=f"comma-separated, of {', '.join(RECIPES)}")
    ap.add_argument("--threads", type=int, default=1, help="torch threads of each child process")
    ap.add_argument("--out", type=Path, default=Path("/tmp/quality"), help="output folder")
    ap.add_argument("--redo", action="store_true", help="retrain rows even when a result exists")
    ap.add_argument("--parallel", type=int, default=1, help="rows trained at once")
    ap.add_argument("--data", type=Path, default=None,
                    help="a walk-through folder (images/, depth/, poses.txt, K.txt) instead of the demo scene")
    ap.add_argument("--walk-test", type=int, default=30,
                    help="with --data: N test frames (the walk's last N, or --walk-blocks blocks of them)")
    ap.add_argument("--walk-blocks", type=int, default=1,
                    help="with --data: the test frames in B blocks spread inside the walk (default 1: its end)")
    ap.add_argument("--walk-every", type=int, default=0,
                    help="with --data: every Nth frame a test frame, one training and one test sequence along "
                         "the whole walk (--walk-test and --walk-blocks unused)")
    ap.add_argument("--size", default=None, help=f"training size WxH (default {SIZE}; 192x128 suits 3:2 walk-throughs)")
    a = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s", datefmt="%H:%M:%S")
    names = [r.strip() for r in a.rows.split(",") if r.strip()]
    unknown = [r for r in names if r not in RECIPES]
    size = a.size or SIZE
    if a.walk_every < 0 or a.walk_every == 1:
        ap.error(f"--walk-every must be 0 (off) or >= 2, not {a.walk_every}")
    if unknown or not names or a.budget_min <= 0 or a.threads < 1 or a.parallel < 1:
        ap.error(f"rows must be among {', '.join(RECIPES)} (got {unknown or names}); budget and threads > 0")
    a.out.mkdir(parents=True, exist_ok=True)
    shards = prepare_data(a.out, a.threads, a.data, a.walk_test, a.walk_blocks, a.walk_every)
    rows = run_rows(names, shards, a.out, a.budget_min, a.threads, a.redo, size, a.data is not None, a.parallel)
    ref = rows[names[0]]["references"]
    for r in rows.values():
        r["rung"], r["next_rung_blocked_by"] = rung(r["metrics"], ref)
    md = table(rows, ref, size)
    cmd = "python benchmarks/quality/run.py " + " ".join(sys.argv[1:])
    data = (f"walk-through {a.data}, {walk_split(a.walk_test, a.walk_blocks, a.walk_every)}" if a.data is not None
            else "demo scene: synth seed 0, 150 frames x 3 sequences")
    (a.out / "quality.md").write_text(
        f"`{cmd.strip()}` ({data}; trained at {size}; {a.threads} torch thread(s), {a.parallel} row(s) at once; "
        f"random init)\n\n{md}\n")
    (a.out / "quality.json").write_text(json.dumps(
        {"scene": SCENE, "budget_min": a.budget_min, "threads": a.threads, "clearly": CLEARLY,
         "references": ref, "rows": rows}, indent=2) + "\n")
    print(md)
    for name, r in rows.items():
        why = "; ".join(r["next_rung_blocked_by"])
        print(f"{name}: rung {r['rung']}" + (f" (next blocked by: {why})" if why else ""))
    print(f"\nwritten: {a.out / 'quality.md'}, {a.out / 'quality.json'}")


if __name__ == "__main__":
    main()
