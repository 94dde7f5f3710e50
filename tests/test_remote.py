"""Shard datasets given as URLs: fetched into the cache, verified, reused, and trainable."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from relocdepth.data import ImageFrames
from relocdepth.dataset import open_dataset
from relocdepth.errors import UserError
from relocdepth.remote import fetch_dataset, is_url


def test_fetch_by_url_verifies_and_reuses(synth_shards: Path, tmp_path: Path, monkeypatch) -> None:
    url = synth_shards.resolve().as_uri()  # file:///..., opened by webdataset's gopen
    assert is_url(url) and not is_url(synth_shards)
    local = fetch_dataset(url, tmp_path / "cache", progress=False)
    for f in sorted(synth_shards.iterdir()):
        assert (local / f.name).read_bytes() == f.read_bytes(), f.name
    assert len(open_dataset(local)) == len(open_dataset(synth_shards))
    stamp = (local / "shard-000000.tar").stat().st_mtime_ns
    assert fetch_dataset(url, tmp_path / "cache", progress=False) == local  # cached: not copied again
    assert (local / "shard-000000.tar").stat().st_mtime_ns == stamp

    monkeypatch.setenv("RELOCDEPTH_CACHE", str(tmp_path / "cache"))
    view = ImageFrames.open(url)  # the trainer's entry point
    assert len(view) == len(ImageFrames.open(synth_shards)) and Path(view.root) == local


def test_damaged_or_missing_remote_is_a_user_error(synth_shards: Path, tmp_path: Path) -> None:
    remote = tmp_path / "remote"
    shutil.copytree(synth_shards, remote)
    with open(remote / "shard-000001.tar", "r+b") as f:  # flip bytes inside a member
        f.seek(2000)
        f.write(b"\x00\xff\x00\xff")
    with pytest.raises(UserError, match="damaged"):
        fetch_dataset(remote.as_uri(), tmp_path / "cache", progress=False)
    assert not list((tmp_path / "cache" / "shards").iterdir())  # nothing half-written left
    with pytest.raises(UserError, match="cannot read"):
        fetch_dataset((tmp_path / "nowhere").as_uri(), tmp_path / "cache", progress=False)
