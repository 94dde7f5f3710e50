"""``reloc demo``: generate a scene, ingest, train, evaluate: the whole product in ~9 minutes."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from relocdepth.cli.common import user_errors
from relocdepth.cli.main import app


@app.command()
@user_errors
def demo(
    out: Annotated[Path, typer.Option("-o", "--out", help="Output folder (scene/, shards/, run/, eval/); an earlier demo there is replaced.")] = Path("demo"),
    minutes: Annotated[float, typer.Option("--minutes", help="Training budget in minutes, wall clock (rendering, ingest and evaluation add about half a minute). 8 minutes on 2 CPU cores (~250-350 steps): depth beats the constant-depth reference, the relative pose the identity, the absolute pose the mean training pose, and the refined pose thumbnail retrieval; the network's own position reaches retrieval's only after far longer on a CPU (README, Quality).")] = 8.0,
    seed: Annotated[int, typer.Option(help="Seed of the generated scene and of training.")] = 0,
    pretrained: Annotated[str | None, typer.Option("--pretrained", metavar="imagenet|FILE|none", help="Encoder initialisation: ImageNet weights (downloaded if possible), a torchvision resnet18 .pth, or none.")] = "imagenet",
    refine: Annotated[bool, typer.Option("--refine/--no-refine", help="Also evaluate the test poses refined against their nearest training frames (what `reloc localize --refine` gives; not the paper's method; about 20 s more at the default size).")] = True,
) -> None:
    """Run the whole pipeline on a generated scene and print the evaluation table."""
    from relocdepth.demo import DemoConfig, beaten_references, run_demo
    from relocdepth.report import format_table

    init = None if pretrained in (None, "", "none") else pretrained
    result = run_demo(out, DemoConfig(minutes=minutes, seed=seed, pretrained=init, refine=refine))
    t = result["timings"]
    typer.echo(format_table(result["report"]))
    beats, misses = beaten_references(result["report"])
    typer.echo("\nbeats: " + ("; ".join(beats) if beats else "none of the references yet"))
    if misses:
        typer.echo("not yet: " + "; ".join(misses))
    typer.echo(
        f"\ndemo done in {t['total_s'] / 60:.1f} min (train {t['train_s'] / 60:.1f} min, "
        f"{result['train']['steps']} steps). Localize with:\n"
        f"  reloc localize {result['paths']['scene']}/{result['report']['dataset']['test_sequences'][0]} "
        f"--checkpoint {result['paths']['run']}"
    )
