"""``reloc localize``: the pose (+ confidence, + depth) of single images, folders or videos."""

from __future__ import annotations

from enum import Enum
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


class PoseFormat(str, Enum):
    json = "json"
    tum = "tum"


INPUTS_HELP = (
    "Image files, folders of images (natural order; in a 7-Scenes sequence folder only the "
    ".color.png frames) or videos."
)
K_HELP = (
    "Intrinsics of the query images (project YAML or OpenCV calibration file; scaled to the image "
    "size when the aspect matches, distortion removed). Default: the training camera stored in the "
    "checkpoint, scaled to the image size (a different aspect ratio is an error)."
)


@app.command()
@user_errors
def localize(
    inputs: Annotated[list[Path], typer.Argument(help=INPUTS_HELP, show_default=False)],
    checkpoint: Annotated[str | None, typer.Option("--checkpoint", metavar="RUN", help="Run folder or checkpoint file. Default: the newest run under ./runs.")] = None,
    K: Annotated[str | None, typer.Option("--K", metavar="FILE", help=K_HELP)] = None,
    depth_out: Annotated[Path | None, typer.Option("--depth-out", metavar="DIR", help="Write <name>.depth.png (uint16, depth x 1000: millimetres once aligned) and <name>.depth_preview.png here.")] = None,
    fmt: Annotated[PoseFormat, typer.Option("--format", help="JSON lines (one object per image) or a TUM trajectory (timestamp tx ty tz qx qy qz qw).")] = PoseFormat.json,
    output: Annotated[Path | None, typer.Option("--output", "-o", metavar="FILE", help="Write the poses to FILE instead of stdout.")] = None,
    batch_size: Annotated[int, typer.Option("--batch-size", min=1, help="Images per forward pass.")] = 8,
    device: Annotated[str, typer.Option(metavar=DEVICE_METAVAR, help=DEVICE_HELP)] = DEVICE_DEFAULT,
    refine: Annotated[Path | None, typer.Option("--refine", metavar="SHARDS", help="Refine each pose against the training frames of these shards (the run's own) nearest it: two-view geometry and direct alignment with the network's depth, against the frames' poses of --refine-map. Not part of the paper's method; each line gains refined_pairs and refined_by (aligned, pairs or none).")] = None,
    refine_neighbours: Annotated[int, typer.Option("--refine-neighbours", min=1, metavar="N", help="With --refine: training frames paired with each image.")] = 3,
    refine_min_pairs: Annotated[int, typer.Option("--refine-min-pairs", min=1, metavar="N", help="With --refine: agreeing pairs needed to replace the network's pose.")] = 2,
    refine_matcher: Annotated[RefineMatcher, typer.Option("--refine-matcher", help=REFINE_MATCHER_HELP)] = RefineMatcher.klt_sift,
    refine_align: Annotated[bool, typer.Option("--refine-align/--no-refine-align", help=REFINE_ALIGN_HELP)] = True,
    refine_map: Annotated[RefineMap, typer.Option("--refine-map", help=REFINE_MAP_HELP)] = RefineMap.auto,
) -> None:
    """World-from-camera pose, confidence and depth of each image from a trained run."""
    from relocdepth.localize import LocalizeConfig
    from relocdepth.localize import localize as run_localize

    cfg = LocalizeConfig(
        checkpoint=checkpoint, K_file=K, depth_out=str(depth_out) if depth_out else None,
        format=fmt.value, output=str(output) if output else None, batch_size=batch_size,
        device=parse_device(device), refine=str(refine) if refine else None,
        refine_neighbours=refine_neighbours, refine_min_pairs=refine_min_pairs,
        refine_matcher=refine_matcher.value, refine_align=refine_align, refine_map=refine_map.value,
    )
    # Printing to stdout: each batch's lines go out as soon as the batch is done.
    echo = (lambda text: typer.echo(text, nl=False)) if output is None else None
    records, _ = run_localize(inputs, cfg, on_text=echo)
    if output is not None:
        aligned = "metres, ground-truth frame" if records and records[0]["aligned"] else "network frame"
        typer.echo(f"{output}: {len(records)} pose(s) ({aligned})")
