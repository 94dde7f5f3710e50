"""Shard datasets behind a URL: fetched once into a local cache, then read by offset like any other.

Training reads frames by random access (``os.pread`` at the offsets in ``index.parquet``; see
``relocdepth/data.py`` for why), which needs seekable local files. A dataset given as a URL that
webdataset's ``gopen`` opens (``http(s)://``, ``file://``, ``s3://``/``gs://`` through their command
line tools, ...) is therefore copied first: ``manifest.json``, ``index.parquet`` and every shard the
manifest lists, each shard checked against the manifest's sha256 and size, into
``$RELOCDEPTH_CACHE`` (default ``~/.cache/relocdepth``) ``/shards/<hash of the URL>``. The copy is
built in a temporary folder and renamed, so an interrupted fetch leaves nothing that looks complete;
a complete copy whose manifest matches the remote one is reused without downloading the shards.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import shutil
import tempfile
from pathlib import Path

from rich.progress import BarColumn, DownloadColumn, Progress, TransferSpeedColumn

from relocdepth.errors import UserError
from relocdepth.fileio import write_json_atomic
from relocdepth.shardformat import INDEX, MANIFEST, WIDS_DESCRIPTOR, wids_descriptor

log = logging.getLogger(__name__)

_CHUNK = 1 << 20


def is_url(location: str | os.PathLike) -> bool:
    """True for ``scheme://...`` locations (a local path has no scheme)."""
    text = str(location)
    return "://" in text and not Path(text).exists()


def cache_root() -> Path:
    return Path(os.environ.get("RELOCDEPTH_CACHE", Path.home() / ".cache" / "relocdepth"))


def _join(base: str, name: str) -> str:
    return base.rstrip("/") + "/" + name


def _copy(url: str, dest: Path) -> tuple[int, str]:
    """Copy ``url`` to ``dest``; (bytes, sha256 hex) of what was written."""
    import webdataset

    h, n = hashlib.sha256(), 0
    try:
        with webdataset.gopen(url, "rb") as src, open(dest, "wb") as out:
            while chunk := src.read(_CHUNK):
                h.update(chunk)
                out.write(chunk)
                n += len(chunk)
    except Exception as e:  # noqa: BLE001 - gopen's pipes raise plain Exceptions on a failing command
        status = re.search(r"exit (\d+)", str(e))  # gopen's message holds the whole command line
        why = f"the download command exited with status {status.group(1)}" if status else str(e)
        raise UserError(f"cannot read {url}: {why}") from None
    return n, h.hexdigest()


def _same_manifest(a: Path, b: Path) -> bool:
    return (a / MANIFEST).is_file() and (a / MANIFEST).read_bytes() == (b / MANIFEST).read_bytes()


def fetch_dataset(url: str, root: Path | None = None, progress: bool = True) -> Path:
    """A local copy of the shard dataset at ``url`` (see the module doc); returns its folder."""
    root = Path(root) if root is not None else cache_root()
    dest = root / "shards" / hashlib.sha1(url.rstrip("/").encode()).hexdigest()[:16]
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".fetch-", dir=dest.parent))
    try:
        _copy(_join(url, MANIFEST), tmp / MANIFEST)
        try:
            manifest = json.loads((tmp / MANIFEST).read_text())
            shards = [(s["name"], int(s["bytes"]), s["sha256"]) for s in manifest["shards"]]
        except (ValueError, KeyError, TypeError) as e:
            raise UserError(f"{_join(url, MANIFEST)} is not a shard manifest ({e})") from None
        if _same_manifest(dest, tmp):
            log.info("using the cached copy of %s in %s", url, dest)
            return dest
        _copy(_join(url, INDEX), tmp / INDEX)
        total = sum(b for _, b, _ in shards)
        columns = ("fetch", BarColumn(), DownloadColumn(), TransferSpeedColumn())
        with Progress(*columns, transient=True, disable=not progress) as bar:
            task = bar.add_task(url, total=total)
            for name, size, sha in shards:
                n, got = _copy(_join(url, name), tmp / name)
                if n != size or got != sha:
                    raise UserError(f"{_join(url, name)}: {n} bytes, sha256 {got[:12]}..., but the "
                                    f"manifest says {size} bytes, {sha[:12]}...; the remote dataset is damaged")
                bar.advance(task, n)
        extra = manifest.get("parallax")  # the optional pair parallax table, checked like a shard
        if extra:
            n, got = _copy(_join(url, extra["file"]), tmp / extra["file"])
            if n != int(extra["bytes"]) or got != extra["sha256"]:
                raise UserError(f"{_join(url, extra['file'])}: {n} bytes, sha256 {got[:12]}..., but the manifest "
                                f"says {extra['bytes']} bytes, {extra['sha256'][:12]}...; the remote dataset is damaged")
        write_json_atomic(tmp / WIDS_DESCRIPTOR, wids_descriptor(manifest))  # derived, not fetched
        if dest.exists():
            shutil.rmtree(dest, ignore_errors=True)
        try:
            os.replace(tmp, dest)
        except OSError:  # another process (a DDP rank) finished the same fetch first
            if not _same_manifest(dest, tmp):
                raise
        log.info("fetched %s (%d shards, %.1f MB) to %s", url, len(shards), total / 1e6, dest)
        return dest
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def local_dataset(location: str | os.PathLike, progress: bool = True) -> str | os.PathLike:
    """``location`` itself when local, else the folder of its fetched copy."""
    return fetch_dataset(str(location), progress=progress) if is_url(location) else location
