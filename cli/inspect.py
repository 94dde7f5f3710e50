"""``reloc inspect``: what a shard dataset holds; ``--verify`` checks it against its manifest."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from relocdepth.cli.common import user_errors
from relocdepth.cli.main import app

VERIFY_HELP = (
    "Also re-hash every shard and count its samples; exit 2 with one line on any mismatch with "
    "the manifest."
)


@app.command()
@user_errors
def inspect(
    shards: Annotated[Path, typer.Argument(help="A dataset folder written by reloc ingest.", show_default=False)],
    verify: Annotated[bool, typer.Option("--verify", help=VERIFY_HELP)] = False,
) -> None:
    """Show sequences, frames per split, intrinsics and size on disk of a shard dataset."""
    from relocdepth.dataset import describe, open_dataset
    from relocdepth.dataset import verify as verify_dataset

    ds = open_dataset(shards)
    info = describe(ds)
    t = info["totals"]
    lines = [
        f"dataset {info['name']} at {info['root']} (created {info['created']}, relocdepth {info['tool_version']})",
        (
            f"frames: {t['frames']} ({t['train']} train, {t['test']} test), {t['skipped']} skipped; "
            f"with depth: {info['has_depth']}, with pose: {info['has_pose']}"
        ),
        f"shards: {info['shards']}, size on disk: {info['bytes_on_disk'] / 1e6:.1f} MB",
        "sources: " + ", ".join(f"{s['path']} ({s['kind']})" for s in info["sources"]),
        "sequences:",
        *(f"  {s['name']}: {s['frames']} frames, {s['split']}" for s in info["sequences"]),
        "intrinsics:",
        *(f"  {k}: {', '.join(v)}" for k, v in info["intrinsics"].items()),
    ]
    if verify:
        n = verify_dataset(ds)
        lines.append(f"verify: {n} shard(s) match the manifest (sha256, size, samples)")
    typer.echo("\n".join(lines))
