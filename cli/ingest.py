"""``reloc ingest``: 7-Scenes folders, videos and image folders -> WebDataset shards."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from relocdepth.cli.common import parse_size, user_errors
from relocdepth.cli.main import app

SOURCES_HELP = (
    "One or more sources: a 7-Scenes scene folder (seq-XX/ + TrainSplit.txt/TestSplit.txt) or a "
    "root of several scenes (with --scene), video files (one sequence each), or image folders "
    "(one sequence each, natural sort order, optional times.txt)."
)
K_HELP = (
    "Intrinsics file: the project YAML (fx, fy, cx, cy, width, height and optional distortion: "
    "k1, k2, p1, p2, k3) or an OpenCV calibration file (camera_matrix, distortion_coefficients, "
    "image_width, image_height). Required for videos and image folders; for 7-Scenes it "
    "overrides the scene's intrinsics.yaml or the default fx=fy=525, cx=320, cy=240 at 640x480. "
    "Scaled to the frame size when the aspect ratio matches; distortion is removed at ingest."
)


@app.command()
@user_errors
def ingest(
    sources: Annotated[list[Path], typer.Argument(help=SOURCES_HELP, show_default=False)],
    out: Annotated[Path, typer.Option("-o", "--out", help="Output dataset folder (shards, index.parquet, manifest.json).")] = Path("shards"),
    K: Annotated[str | None, typer.Option("--K", metavar="FILE", help=K_HELP)] = None,
    stride: Annotated[int, typer.Option(min=1, help="Keep every Nth frame of each sequence (frame indices keep their gaps).")] = 1,
    resize: Annotated[str | None, typer.Option(metavar="WxH", help="Re-encode frames at this size (intrinsics and depth follow). Default: keep the source size and copy images byte-for-byte.")] = None,
    split: Annotated[str | None, typer.Option(metavar="train|test", help="Put every sequence into this split. Default: the 7-Scenes split files; videos and image folders go to train.")] = None,
    name: Annotated[str | None, typer.Option(help="Dataset name stored in the manifest. Default: the first source's name.")] = None,
    scene: Annotated[str | None, typer.Option(metavar="NAME", help="Which scene of a 7-Scenes root holding several scenes.")] = None,
    shard_size: Annotated[int, typer.Option(min=1, help="Samples (frames) per shard; a shard never mixes sequences.")] = 1000,
    video_format: Annotated[str, typer.Option(metavar="jpg|png", help="How decoded video frames are stored: jpg (quality 95, fast) or png (lossless, slow to write, ~4x larger).")] = "jpg",
    pair_parallax: Annotated[bool, typer.Option("--pair-parallax/--no-pair-parallax", help="Estimate, for frame pairs 1, 2, 4, ... 32 apart, the image motion rotation cannot explain (KLT tracks + homography residual on 160 px grey copies), stored as a parquet table for `reloc train --min-parallax`. Off by default: it multiplies the ingest time of PNG sources (see README, Performance).")] = False,
    force: Annotated[bool, typer.Option("--force", help="Replace the output folder if it exists.")] = False,
    strict: Annotated[bool, typer.Option("--strict", help="Fail on a corrupt frame instead of skipping it (skipped frames are listed in the manifest and counted in a warning).")] = False,
) -> None:
    """Convert sources into a shard dataset (WebDataset tars + index.parquet + manifest.json)."""
    from relocdepth.ingest.run import IngestConfig
    from relocdepth.ingest.run import ingest as run_ingest

    cfg = IngestConfig(
        intrinsics=K, stride=stride, resize=parse_size(resize, "--resize") if resize else None, split=split,
        name=name, scene=scene, shard_size=shard_size, force=force, strict=strict,
        video_format=video_format, pair_parallax=pair_parallax,
    )
    manifest = run_ingest(sources, out, cfg)
    t = manifest["totals"]
    typer.echo(
        f"{out}: {t['frames']} frames ({t['train']} train, {t['test']} test) in {t['sequences']} "
        f"sequence(s), {len(manifest['shards'])} shard(s), {t['skipped']} skipped"
        + (f", {manifest['parallax']['pairs']} parallax pairs" if "parallax" in manifest else "")
    )
