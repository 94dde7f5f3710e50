"""The ingest pipeline (decode thread, encoding pool, writer) changes speed, never bytes.

Shards are compared with what Python's ``tarfile`` writes for the same members, and the stored
JPEGs with an independent decode + encode of the same video; the same video ingested with 1 or
3 workers, with or without the decode thread, gives byte-identical shards and index.
"""

from __future__ import annotations

import hashlib
import io
import json
import tarfile
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from ingest_fixtures import write_K, write_video
from relocdepth.ingest import run as ingest_run
from relocdepth.ingest.run import IngestConfig, ingest
from relocdepth.ingest.writer import MEMBER_MODE, MEMBER_MTIME, SMALL_MEMBER, Sample, ShardWriter

# The stored JPEG: quality 95, no chroma subsampling (the documented video frame encoding).
JPEG_PARAMS = [cv2.IMWRITE_JPEG_QUALITY, 95,
               cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444]


def _tarfile_bytes(samples: list[Sample]) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w", format=tarfile.USTAR_FORMAT) as tar:
        for s in samples:
            for suffix, data in s.members.items():
                info = tarfile.TarInfo(f"{s.key}.{suffix}")
                info.size, info.mtime, info.mode = len(data), MEMBER_MTIME, MEMBER_MODE
                tar.addfile(info, io.BytesIO(data))
    return buf.getvalue()


def test_shards_are_what_tarfile_writes(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)

    def blob(n: int) -> bytes:
        return rng.integers(0, 256, n, dtype=np.uint8).tobytes()

    # members below and above the small-member size, block-aligned or not, empty
    sizes = [(700, 3), (SMALL_MEMBER + 1, 40), (512, 0), (3 * SMALL_MEMBER, 1024), (SMALL_MEMBER - 1, 5)]
    samples = [Sample(f"seq-{i:06d}", {"jpg": blob(a), "json": blob(b), "pose.txt": blob(7)})
               for i, (a, b) in enumerate(sizes)]
    writer = ShardWriter(tmp_path, shard_size=2)
    where = [writer.add(s) for s in samples]
    shards = writer.close()
    assert [s["samples"] for s in shards] == [2, 2, 1]
    for k, shard in enumerate(shards):
        data = (tmp_path / shard["name"]).read_bytes()
        assert shard["bytes"] == len(data)
        assert shard["sha256"] == hashlib.sha256(data).hexdigest()
        # tarfile pads the archive to whole 10 kB records: the same bytes, then zeros
        ref = _tarfile_bytes(samples[2 * k: 2 * k + 2])
        assert len(ref) >= len(data) and data == ref[: len(data)] and not any(ref[len(data):])
    first = (tmp_path / shards[0]["name"]).read_bytes()
    for s, w in zip(samples[:2], where[:2]):
        for suffix, data in s.members.items():
            offset, size = w[suffix]
            assert size == len(data) and first[offset: offset + size] == data


def _digests(out: Path) -> dict[str, str]:
    files = sorted(out.glob("*.tar")) + [out / "index.parquet"]
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in files}


@pytest.fixture(scope="module")
def video(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, list[np.ndarray]]:
    root = tmp_path_factory.mktemp("video")
    size = (160, 120)
    decoded = write_video(root / "walk.mp4", frames=23, size=size)
    return root / "walk.mp4", write_K(root / "K.yaml", size=size), decoded


def test_video_shards_hold_the_decoded_frames_encoded(video, tmp_path: Path) -> None:
    path, K, decoded = video
    out = tmp_path / "shards"
    ingest([path], out, IngestConfig(intrinsics=str(K), shard_size=5), progress=False)
    names = [s["name"] for s in json.loads((out / "manifest.json").read_text())["shards"]]
    assert len(names) == 5
    jpgs = {}
    for name in names:
        with tarfile.open(out / name) as tar:
            for m in tar.getmembers():
                if m.name.endswith(".jpg"):
                    jpgs[m.name] = tar.extractfile(m).read()
    assert sorted(jpgs) == [f"walk-{i:06d}.jpg" for i in range(len(decoded))]
    for i, img in enumerate(decoded):
        ok, ref = cv2.imencode(".jpg", img, JPEG_PARAMS)
        assert ok and jpgs[f"walk-{i:06d}.jpg"] == ref.tobytes()


@pytest.mark.parametrize("video_format", ["jpg", "png"])
def test_workers_and_decode_thread_do_not_change_bytes(
    video, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, video_format: str,
) -> None:
    path, K, _ = video
    cfg = IngestConfig(intrinsics=str(K), shard_size=7, video_format=video_format)
    runs = {}
    for workers in (1, 3):
        ingest([path], tmp_path / f"w{workers}", replace(cfg, workers=workers), progress=False)
        runs[f"{workers} workers"] = _digests(tmp_path / f"w{workers}")
    with monkeypatch.context() as m:  # frames decoded on the thread that writes
        m.setattr(ingest_run, "background", lambda items, depth: items)
        ingest([path], tmp_path / "main", cfg, progress=False)
    runs["no decode thread"] = _digests(tmp_path / "main")
    assert len(runs["1 workers"]) == 5  # 4 shards + the index
    assert runs["3 workers"] == runs["1 workers"] and runs["no decode thread"] == runs["1 workers"]
