"""`reloc synth`: write the generated demo scene in the 7-Scenes layout."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from relocdepth.cli.common import parse_size, user_errors
from relocdepth.cli.main import app


@app.command()
@user_errors
def synth(
    out: Annotated[Path, typer.Argument(help="Output folder (7-Scenes layout).")],
    seed: Annotated[int, typer.Option(help="Random seed: same seed, same files.")] = 0,
    frames: Annotated[int, typer.Option(help="Frames per sequence (30 fps).")] = 300,
    size: Annotated[str, typer.Option(help="Image size WIDTHxHEIGHT (even numbers).")] = "640x480",
    train_sequences: Annotated[
        int, typer.Option(help="Training sequences (>= 2); one test sequence follows.")] = 2,
    force: Annotated[bool, typer.Option("--force", help="Replace OUT if it is not empty.")] = False,
) -> None:
    """Generate a textured kitchen (counters, table, shelves, clutter near the camera), rendered
    along handheld-like camera paths, with
    exact depth and poses: seq-XX/frame-XXXXXX.{color.png,depth.png,pose.txt}, split files,
    intrinsics.yaml and videos/seq-XX.mp4."""
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeRemainingColumn,
    )

    from relocdepth.synth import SynthConfig, generate_scene

    width, height = parse_size(size)
    cfg = SynthConfig(seed=seed, frames=frames, width=width, height=height,
                      train_sequences=train_sequences)
    columns = (TextColumn("rendering"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    with Progress(*columns, transient=True) as bar:
        task = bar.add_task("render", total=max(frames, 0) * (train_sequences + 1))
        summary = generate_scene(out, cfg, force=force,
                                 progress=lambda n: bar.update(task, completed=n))
    for seq in summary["sequences"]:
        typer.echo(f"{seq['name']} ({seq['split']}): {seq['frames']} frames, median step "
                   f"{seq['median_step_cm']:.2f} cm {seq['median_step_deg']:.2f} deg")
    typer.echo(f"wrote {out} in {summary['seconds']:.1f} s")
