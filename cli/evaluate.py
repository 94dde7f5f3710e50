"""``reloc evaluate``: the paper's protocol on shards with ground truth."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from relocdepth.cli.common import (
    DEVICE_DEFAULT,
    DEVICE_HELP,
    DEVICE_METAVAR,
    REFINE_ALIGN_HELP,
    REFINE_MAP_HELP,
    REFINE_MATCHER_HELP,
    RefineMap,
    RefineMatcher,
    parse_device,
    user_errors,
)
from relocdepth.cli.main import app


@app.command()
@user_errors
def evaluate(
    shards: Annotated[Path, typer.Argument(help="Shard dataset with ground-truth poses (and depth).", show_default=False)],
    checkpoint: Annotated[str | None, typer.Option("--checkpoint", metavar="RUN", help="Run folder or checkpoint file. Default: the newest run under ./runs.")] = None,
    out: Annotated[Path | None, typer.Option("-o", "--output", metavar="FILE", help="Report JSON. Default: RUN/eval/report.json; the per-frame errors (REPORT.frames.csv) and TUM files (trajectories/) go beside it.")] = None,
    plots: Annotated[Path | None, typer.Option("--plots", metavar="DIR", help="Folder for the PNG plots. Default: plots/ beside the report.")] = None,
    save_alignment: Annotated[bool, typer.Option("--save-alignment", help="Store the fitted Sim(3) with the run: localize then reports metric poses in the ground-truth frame.")] = False,
    batch_size: Annotated[int, typer.Option("--batch-size", min=1, help="Images per forward pass.")] = 16,
    device: Annotated[str, typer.Option(metavar=DEVICE_METAVAR, help=DEVICE_HELP)] = DEVICE_DEFAULT,
    test_sequences: Annotated[str | None, typer.Option("--test-sequences", metavar="NAMES", help="Comma-separated sequences to test on instead of the test split (the training split's other sequences fit the Sim(3)); e.g. a training sequence, to see whether the networks fit the frames they trained on.")] = None,
    refine: Annotated[bool, typer.Option("--refine", help="Also refine each test pose against the training frames nearest it (two-view geometry and direct alignment with the network's depth; the map: --refine-map) and report both. Not part of the paper's protocol.")] = False,
    refine_neighbours: Annotated[int, typer.Option("--refine-neighbours", min=1, metavar="N", help="With --refine: training frames paired with each test frame.")] = 3,
    refine_min_pairs: Annotated[int, typer.Option("--refine-min-pairs", min=1, metavar="N", help="With --refine: agreeing pairs needed to replace the network's pose.")] = 2,
    refine_matcher: Annotated[RefineMatcher, typer.Option("--refine-matcher", help=REFINE_MATCHER_HELP)] = RefineMatcher.klt_sift,
    refine_align: Annotated[bool, typer.Option("--refine-align/--no-refine-align", help=REFINE_ALIGN_HELP)] = True,
    refine_map: Annotated[RefineMap, typer.Option("--refine-map", help=REFINE_MAP_HELP)] = RefineMap.auto,
) -> None:
    """Sim(3)-aligned pose errors, depth metrics and baselines (JSON report, TUM files, plots)."""
    from relocdepth.evaluate import EvalConfig
    from relocdepth.evaluate import evaluate as run_evaluate
    from relocdepth.report import format_table

    report = run_evaluate(shards, checkpoint, EvalConfig(
        batch_size=batch_size, device=parse_device(device),
        test_sequences=tuple(n.strip() for n in (test_sequences or "").split(",") if n.strip()),
        refine=refine, refine_neighbours=refine_neighbours, refine_min_pairs=refine_min_pairs,
        refine_matcher=refine_matcher.value, refine_align=refine_align, refine_map=refine_map.value),
                          report_path=out, plots_dir=plots, save_alignment=save_alignment)
    typer.echo(format_table(report))
    if save_alignment:
        typer.echo("alignment saved with the run: `reloc localize` now reports metres in the ground-truth frame")
