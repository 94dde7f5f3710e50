"""The shard dataset format, defined once: file names, format tag, and positional member reads.

Writers (``relocdepth.ingest``) and readers (:mod:`relocdepth.dataset`, :mod:`relocdepth.data`,
:mod:`relocdepth.remote`) take every name from here, so the two sides cannot drift apart.
"""

from __future__ import annotations

import os

FORMAT = "relocdepth-shards"
SCHEMA_VERSION = 1
MANIFEST = "manifest.json"  # written last: a folder without it is incomplete
INDEX = "index.parquet"
WIDS_DESCRIPTOR = "wids.json"  # shard list for webdataset's ``wids.ShardListDataset``
WIDS_KIND = "wids-shard-index-v1"
SHARD_PATTERN = "shard-{:06d}.tar"
# 7-Scenes convention: depth PNGs hold uint16 millimetres, 0 = invalid.
DEPTH_SCALE = 1000.0


def wids_descriptor(manifest: dict) -> dict:
    """The shard list ``wids.ShardListDataset`` reads, from a manifest (URLs relative to the
    descriptor's folder, so the dataset folder can move)."""
    return {
        "__kind__": WIDS_KIND,
        "wids_version": 1,
        "name": manifest["name"],
        "shardlist": [
            {"url": s["name"], "nsamples": s["samples"], "filesize": s["bytes"]} for s in manifest["shards"]
        ],
    }


class TruncatedMember(OSError):
    """A positional read returned fewer bytes than the index promised."""


class MemberReader:
    """Reads byte ranges of shard files with ``os.pread``, one descriptor per file per process.

    Positional reads have no shared file position, so one reader can serve several threads; a
    forked DataLoader worker notices the new process id and opens its own descriptors, and a
    pickled reader (spawned workers) carries none.
    """

    def __init__(self) -> None:
        self._fds: dict[str, int] = {}
        self._pid = os.getpid()

    def _fd(self, path: str) -> int:
        if os.getpid() != self._pid:  # forked: the parent's descriptors are shared, open our own
            self._fds, self._pid = {}, os.getpid()
        fd = self._fds.get(path)
        if fd is None:
            fd = self._fds[path] = os.open(path, os.O_RDONLY)
        return fd

    def read(self, path: str, offset: int, size: int) -> bytes:
        """``size`` bytes of ``path`` at ``offset``; :class:`TruncatedMember` if the file is shorter."""
        data = os.pread(self._fd(path), size, offset)
        if len(data) != size:
            raise TruncatedMember(f"{path} is truncated ({len(data)} of {size} bytes at offset {offset})")
        return data

    def close(self) -> None:
        if os.getpid() == self._pid:
            for fd in self._fds.values():
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._fds = {}

    def __getstate__(self) -> dict:
        return {"_fds": {}, "_pid": self._pid}

    def __setstate__(self, state: dict) -> None:
        self._fds, self._pid = {}, os.getpid()

    def __del__(self) -> None:
        self.close()
