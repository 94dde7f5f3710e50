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

ADD_PARALLAX_HELP = (
    "Estimate pair parallax for this dataset (as ingest --pair-parallax does) and list it in the "
    "manifest; shards and index are not rewritten. Replaces an existing table."
)


def _parallax_lines(summary: list[dict] | None, root: str) -> list[str]:
    if summary is None:
        return [f"pair parallax: none (add it with: reloc inspect {root} --add-parallax)"]
    lines = ["pair parallax (px of the stored image; motion rotation cannot explain):"]
    for s in summary:
        lines.append(
            f"  offset {s['offset']:3d}: median {s['median_px']:6.2f}, p90 {s['p90_px']:6.2f} "
            f"({s['pairs']} pairs, {s['failed']} failed)"
        )
    return lines


@app.command()
@user_errors
def inspect(
    shards: Annotated[Path, typer.Argument(help="A dataset folder written by reloc ingest.", show_default=False)],
    verify: Annotated[bool, typer.Option("--verify", help=VERIFY_HELP)] = False,
    add_parallax: Annotated[bool, typer.Option("--add-parallax", help=ADD_PARALLAX_HELP)] = False,
) -> None:
    """Show sequences, frames per split, intrinsics and size on disk of a shard dataset."""
    from relocdepth.dataset import describe, open_dataset, parallax_summary
    from relocdepth.dataset import verify as verify_dataset

    ds = open_dataset(shards)
    if add_parallax:
        from relocdepth.ingest.parallax import add_parallax as run_add_parallax

        entry = run_add_parallax(shards)
        typer.echo(f"{shards}: pair parallax for {entry['pairs']} pairs ({entry['failed']} failed) in {entry['file']}")
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
    lines += _parallax_lines(parallax_summary(ds), str(shards))
    if verify:
        n = verify_dataset(ds)
        lines.append(f"verify: {n} shard(s) match the manifest (sha256, size, samples)")
    typer.echo("\n".join(lines))
