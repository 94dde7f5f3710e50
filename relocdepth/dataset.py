"""Reading a shard dataset (what ``reloc ingest`` writes): manifest, index, random access by offset.

A dataset directory holds ``shard-*.tar`` (WebDataset tars), ``index.parquet`` (one row per
frame, with the byte offset and size of each member's data inside its tar) and
``manifest.json`` (written last: a directory without it is incomplete and refused here).
Members are read with positional reads (``os.pread``), so one :class:`ShardDataset` can be
shared by forked DataLoader workers without seek races.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from relocdepth import imageio
from relocdepth.camera import Intrinsics
from relocdepth.errors import UserError
from relocdepth.shardformat import DEPTH_SCALE, INDEX, MANIFEST, MemberReader, TruncatedMember

HASH_CHUNK = 1 << 22
# Pair parallax table written at ingest (or added later); listed under "parallax" in the manifest.
PARALLAX_FILE = "parallax.parquet"


@dataclass(frozen=True)
class FrameRecord:
    """One row of ``index.parquet``: a frame and where its members sit (offsets of member data, -1 if absent)."""

    key: str
    shard: str
    sequence: str
    frame: int
    timestamp: float
    split: str
    intrinsics: Intrinsics
    has_depth: bool
    has_pose: bool
    image_ext: str
    image_offset: int
    image_size: int
    json_offset: int
    json_size: int
    depth_offset: int
    depth_size: int
    pose_offset: int
    pose_size: int


def manifest_hash(manifest: dict) -> str:
    """A stable id of the data: sha256 over the shard names and their sha256s, in order."""
    h = hashlib.sha256()
    for s in manifest["shards"]:
        h.update(f"{s['name']}:{s['sha256']}\n".encode())
    return h.hexdigest()


def _records_from_index(path: Path) -> list[FrameRecord]:
    import pyarrow.parquet as pq

    try:
        cols = pq.read_table(path).to_pydict()
    except (OSError, ValueError, KeyError) as e:  # ArrowInvalid is a ValueError
        raise UserError(f"{path}: cannot read the index ({e}); re-run reloc ingest --force") from None
    records = []
    for i in range(len(cols["key"])):
        intr = Intrinsics(
            fx=cols["fx"][i], fy=cols["fy"][i], cx=cols["cx"][i], cy=cols["cy"][i],
            width=int(cols["width"][i]), height=int(cols["height"][i]),
        )
        records.append(FrameRecord(
            key=cols["key"][i], shard=cols["shard"][i], sequence=cols["sequence"][i],
            frame=int(cols["frame"][i]), timestamp=float(cols["timestamp"][i]), split=cols["split"][i],
            intrinsics=intr, has_depth=bool(cols["has_depth"][i]), has_pose=bool(cols["has_pose"][i]),
            image_ext=cols["image_ext"][i],
            image_offset=int(cols["image_offset"][i]), image_size=int(cols["image_size"][i]),
            json_offset=int(cols["json_offset"][i]), json_size=int(cols["json_size"][i]),
            depth_offset=int(cols["depth_offset"][i]), depth_size=int(cols["depth_size"][i]),
            pose_offset=int(cols["pose_offset"][i]), pose_size=int(cols["pose_size"][i]),
        ))
    return records


def parallax_arrow_schema():  # built lazily: pyarrow imports slowly
    """Columns of the pair parallax table (see schemas/parallax.schema.json)."""
    import pyarrow as pa

    return pa.schema([
        ("key", pa.string()), ("sequence", pa.string()), ("frame", pa.int64()),
        ("offset", pa.int32()), ("frame_b", pa.int64()), ("parallax_px", pa.float64()),
    ])


class ShardDataset:
    """A complete shard dataset on local disk, with random access to every frame's members."""

    def __init__(self, root: str | Path) -> None:
        from relocdepth.schemas import validate

        rootp = Path(root)
        if not rootp.is_dir():
            raise UserError(f"dataset not found: {rootp} is not a directory (make one with reloc ingest)")
        mpath = rootp / MANIFEST
        if not mpath.is_file():
            raise UserError(
                f"{rootp} is not a complete dataset (no {MANIFEST}); re-run reloc ingest --force"
            )
        try:
            manifest = json.loads(mpath.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            raise UserError(f"{mpath}: not readable JSON ({e})") from None
        validate("manifest", manifest, what=str(mpath))
        ipath = rootp / INDEX
        if not ipath.is_file():
            raise UserError(f"{rootp}: {INDEX} is missing; re-run reloc ingest --force")
        self.root = str(rootp)
        self.manifest = manifest
        self.manifest_hash = manifest_hash(manifest)
        self.records: list[FrameRecord] = _records_from_index(ipath)
        if len(self.records) != manifest["totals"]["frames"]:
            raise UserError(
                f"{rootp}: the index has {len(self.records)} frames but the manifest says "
                f"{manifest['totals']['frames']}; re-run reloc ingest --force"
            )
        names = {s["name"] for s in manifest["shards"]}
        missing = sorted({r.shard for r in self.records} - names)
        if missing:
            raise UserError(f"{rootp}: the index names shards not in the manifest: {missing[:3]}")
        self._reader = MemberReader()

    def __len__(self) -> int:
        return len(self.records)

    def __repr__(self) -> str:
        return f"ShardDataset({self.root!r}, frames={len(self.records)})"

    def frames(self, split: str | None = None) -> list[FrameRecord]:
        """Records of one split (``"train"``/``"test"``), or all, in index order."""
        if split is None:
            return list(self.records)
        if split not in ("train", "test"):
            raise ValueError(f"split must be 'train', 'test' or None, not {split!r}")
        return [r for r in self.records if r.split == split]

    def sequences(self) -> list[str]:
        """Sequence names in index order."""
        return list(dict.fromkeys(r.sequence for r in self.records))

    def shard_path(self, rec: FrameRecord) -> str:
        return os.path.join(self.root, rec.shard)

    def shard_paths(self) -> list[str]:
        """Every shard's path, in manifest order (e.g. for ``webdataset.WebDataset``)."""
        return [os.path.join(self.root, s["name"]) for s in self.manifest["shards"]]

    # -- raw member access -------------------------------------------------------------------
    def _read(self, rec: FrameRecord, offset: int, size: int, what: str) -> bytes:
        if offset < 0:
            raise ValueError(f"frame {rec.key} has no {what}")
        path = self.shard_path(rec)
        try:
            return self._reader.read(path, offset, size)
        except TruncatedMember:
            raise UserError(f"shard {rec.shard} is truncated (reading {what} of {rec.key})") from None
        except OSError as e:
            raise UserError(f"cannot open shard {path}: {e.strerror}") from None

    def read_image_bytes(self, rec: FrameRecord) -> bytes:
        """The encoded image (``rec.image_ext``), exactly as stored."""
        return self._read(rec, rec.image_offset, rec.image_size, "image")

    def read_meta(self, rec: FrameRecord, validate_schema: bool = True) -> dict:
        """The frame's json member, validated against the ``frame`` schema."""
        meta = json.loads(self._read(rec, rec.json_offset, rec.json_size, "json"))
        if validate_schema:
            from relocdepth.schemas import validate

            validate("frame", meta, what=f"{rec.shard}:{rec.key}.json")
        return meta

    def read_image(self, rec: FrameRecord) -> np.ndarray:
        """RGB uint8 (H, W, 3), exactly ``rec.intrinsics.width x height`` (orientation tags are
        ignored, :mod:`relocdepth.imageio`); a decoded size other than that is a UserError."""
        what = f"{rec.shard}:{rec.key}.{rec.image_ext}"
        try:
            img = imageio.decode_rgb(self.read_image_bytes(rec))
            imageio.check_size(img, rec.intrinsics, what)
        except imageio.SizeMismatch as e:
            raise UserError(f"{e}; re-run reloc ingest --force") from None
        except ValueError:
            raise UserError(f"{what} cannot be decoded") from None
        return img

    def read_depth(self, rec: FrameRecord) -> np.ndarray:
        """Ground-truth depth, float32 metres (H, W), 0 = invalid. For evaluation only."""
        raw = self._read(rec, rec.depth_offset, rec.depth_size, "depth")
        d = imageio.decode_unchanged(raw)
        if d is None or d.dtype != np.uint16 or d.ndim != 2:
            raise UserError(f"{rec.shard}:{rec.key}.depth.png is not a uint16 depth image")
        return d.astype(np.float32) / DEPTH_SCALE

    def read_pose(self, rec: FrameRecord) -> np.ndarray:
        """Ground-truth world-from-camera pose (4, 4) float64. For evaluation only."""
        text = self._read(rec, rec.pose_offset, rec.pose_size, "pose").decode()
        T = np.array(text.split(), dtype=np.float64)
        if T.size != 16:
            raise UserError(f"{rec.shard}:{rec.key}.pose.txt is not a 4x4 matrix")
        return T.reshape(4, 4)

    def close(self) -> None:
        self._reader.close()


def describe(ds: ShardDataset) -> dict:
    """What ``reloc inspect`` shows: sequences, frames per split, intrinsics, size on disk."""
    m = ds.manifest
    intr: dict[str, list[str]] = {}
    for r in ds.records:
        d = r.intrinsics.to_dict()
        label = "fx={fx:g} fy={fy:g} cx={cx:g} cy={cy:g} {width}x{height}".format(**d)
        seqs = intr.setdefault(label, [])
        if r.sequence not in seqs:
            seqs.append(r.sequence)
    files = [Path(p) for p in ds.shard_paths()] + [Path(ds.root) / INDEX, Path(ds.root) / MANIFEST]
    if "parallax" in m:
        files.append(Path(ds.root) / m["parallax"]["file"])
    return {
        "name": m["name"], "root": ds.root, "created": m["created"], "tool_version": m["tool_version"],
        "sources": m["sources"], "sequences": m["sequences"], "totals": m["totals"],
        "intrinsics": intr, "shards": len(m["shards"]),
        "bytes_on_disk": sum(p.stat().st_size for p in files if p.is_file()),
        "has_depth": sum(r.has_depth for r in ds.records), "has_pose": sum(r.has_pose for r in ds.records),
        "manifest_hash": ds.manifest_hash,
    }


def _hash_file(path: Path) -> tuple[str, int]:
    h, n = hashlib.sha256(), 0
    with open(path, "rb") as f:
        while chunk := f.read(HASH_CHUNK):
            h.update(chunk)
            n += len(chunk)
    return h.hexdigest(), n


def _count_samples(path: Path) -> int:
    import tarfile

    with tarfile.open(path, "r:") as tf:
        return len({m.name.split(".", 1)[0] for m in tf if m.isfile()})


def verify(ds: ShardDataset) -> int:
    """Check every shard's size, sha256 and sample count against the manifest (and the index).

    Returns the number of shards checked; any mismatch is a UserError listing the problems.
    """
    import tarfile

    per_shard: dict[str, int] = {}
    for r in ds.records:
        per_shard[r.shard] = per_shard.get(r.shard, 0) + 1
    problems = []
    for s in ds.manifest["shards"]:
        path = Path(ds.root) / s["name"]
        if not path.is_file():
            problems.append(f"{s['name']} is missing")
            continue
        digest, size = _hash_file(path)
        if size != s["bytes"]:
            problems.append(f"{s['name']} has {size} bytes, the manifest says {s['bytes']}")
        if digest != s["sha256"]:
            problems.append(f"{s['name']} sha256 differs from the manifest")
        try:
            n = _count_samples(path)
        except (tarfile.TarError, OSError) as e:
            problems.append(f"{s['name']} is not a readable tar ({e})")
            continue
        if n != s["samples"] or per_shard.get(s["name"], 0) != s["samples"]:
            problems.append(
                f"{s['name']} holds {n} samples (index: {per_shard.get(s['name'], 0)}), "
                f"the manifest says {s['samples']}"
            )
    entry = ds.manifest.get("parallax")
    if entry is not None:
        path = Path(ds.root) / entry["file"]
        if not path.is_file():
            problems.append(f"{entry['file']} (pair parallax) is missing")
        elif _hash_file(path) != (entry["sha256"], entry["bytes"]):
            problems.append(f"{entry['file']} (pair parallax) differs from the manifest")
    if problems:
        more = f" (+{len(problems) - 1} more problems)" if len(problems) > 1 else ""
        raise UserError(f"verify failed: {problems[0]}{more}; re-run reloc ingest --force")
    return len(ds.manifest["shards"])


def read_parallax(ds: ShardDataset) -> dict[str, np.ndarray] | None:
    """The pair parallax table as columns (numpy arrays), or None if the dataset has none.

    Rows are forward pairs (frame ``frame`` of ``sequence``, the ``offset``-th stored frame after
    it, ``frame_b``); ``parallax_px`` is in pixels of the stored image, NaN where tracking failed.
    """
    import pyarrow.parquet as pq

    from relocdepth.schemas import load_schema

    entry = ds.manifest.get("parallax")
    if entry is None:
        return None
    path = Path(ds.root) / entry["file"]
    try:
        table = pq.read_table(path)
    except (OSError, ValueError) as e:
        raise UserError(
            f"{path}: cannot read the pair parallax ({e}); re-create it with "
            f"reloc inspect {ds.root} --add-parallax"
        ) from None
    expected = parallax_arrow_schema()
    missing = [n for n in load_schema("parallax")["required"] if n not in table.column_names]
    if missing or not table.select(expected.names).schema.equals(expected):
        raise UserError(
            f"{path}: not a pair parallax table (columns {table.column_names}); re-create it with "
            f"reloc inspect {ds.root} --add-parallax"
        )
    return {n: table.column(n).to_numpy(zero_copy_only=False) for n in expected.names}


def parallax_for_frames(root: str | Path, frames: list[tuple[str, str, int]],
                        offsets: tuple[int, ...] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pair parallax of a list of frames, e.g. the training frames, for the triplet sampler.

    Args:
        frames: ``(key, sequence, frame)`` per frame, sequence-contiguous in stored order.
    Returns:
        ``offsets (M,)`` and ``px (N, M)``: ``px[i, j]`` is the parallax (stored px) between frame
        i and the frame ``offsets[j]`` places after it in the list, NaN where unknown (tracking
        failed, past the sequence end, or the list's neighbour is not the stored one).
    Raises:
        UserError: the dataset has no pair parallax (saying how to add it).
    """
    ds = open_dataset(root)
    table = read_parallax(ds)
    ds.close()
    if table is None:
        raise UserError(
            f"{root} has no pair parallax data; add it with `reloc inspect {root} --add-parallax` "
            "(or ingest with --pair-parallax)"
        )
    offs = np.array(sorted(set(table["offset"].tolist())) if offsets is None else offsets, np.int64)
    col = {int(k): j for j, k in enumerate(offs)}
    where = {key: i for i, (key, _, _) in enumerate(frames)}
    px = np.full((len(frames), len(offs)), np.nan)
    for key, k, fb, val in zip(table["key"], table["offset"], table["frame_b"], table["parallax_px"]):
        i, j = where.get(key), col.get(int(k))
        if i is None or j is None or i + k >= len(frames):
            continue
        _, seq_b, frame_b = frames[i + k]
        if seq_b == frames[i][1] and frame_b == fb:
            px[i, j] = val
    return offs, px


def parallax_summary(ds: ShardDataset) -> list[dict] | None:
    """Per offset: pairs, failed, median and 90th percentile (stored px); None without a table."""
    table = read_parallax(ds)
    if table is None:
        return None
    out = []
    for k in sorted(set(table["offset"].tolist())):
        vals = table["parallax_px"][table["offset"] == k]
        ok = vals[np.isfinite(vals)]
        out.append({
            "offset": int(k), "pairs": len(vals), "failed": int(len(vals) - len(ok)),
            "median_px": float(np.median(ok)) if len(ok) else float("nan"),
            "p90_px": float(np.percentile(ok, 90)) if len(ok) else float("nan"),
        })
    return out


def open_dataset(path: str | Path) -> ShardDataset:
    """Open a complete shard dataset; :class:`UserError` if missing, incomplete or invalid."""
    return ShardDataset(path)
