"""Shared fixtures: a small generated scene and its shards, built once per test session."""

from __future__ import annotations

from pathlib import Path

import pytest

# A small scene: 3 sequences x SCENE_FRAMES frames at 128x96 (a multiple of 32, the training size
# of the fast tests), rendered in about a second.
SCENE_FRAMES = 24
SCENE_SIZE = (128, 96)


@pytest.fixture(scope="session")
def synth_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A `reloc synth` scene in the 7-Scenes layout (read-only: copy it before changing it)."""
    from relocdepth.synth import SynthConfig, generate_scene

    out = tmp_path_factory.mktemp("scene") / "scene"
    generate_scene(out, SynthConfig(seed=0, frames=SCENE_FRAMES, width=SCENE_SIZE[0], height=SCENE_SIZE[1]))
    return out


@pytest.fixture(scope="session")
def synth_shards(synth_scene: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The synth scene ingested into shards (read-only)."""
    from relocdepth.ingest.run import IngestConfig, ingest

    out = tmp_path_factory.mktemp("shards") / "shards"
    ingest([synth_scene], out, IngestConfig(shard_size=16))
    return out


@pytest.fixture(scope="session")
def synth_shards_320(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The demo scene (3 sequences x 24 frames) stored at 320x240, ingested (read-only): for what
    needs more pixels than the 128x96 test scene has (links, tracking on the stored images)."""
    from relocdepth.ingest.run import IngestConfig, ingest

    from relocdepth.synth import SynthConfig, generate_scene

    root = tmp_path_factory.mktemp("scene320")
    generate_scene(root / "scene", SynthConfig(seed=0, frames=24, width=320, height=240))
    ingest([root / "scene"], root / "shards", IngestConfig())
    return root / "shards"
