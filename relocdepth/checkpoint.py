"""Versioned, atomic training checkpoints and the inference API on top of them.

Layout of a run folder::

    runs/NAME/config.json
    runs/NAME/logs/train.jsonl
    runs/NAME/checkpoints/ckpt-00012000.pt     # one per save, keep-last-K
    runs/NAME/checkpoints/latest               # JSON pointer (schema checkpoint_pointer)
    runs/NAME/checkpoints/alignment.json       # optional Sim(3), written by evaluate

Every ``.pt`` is written to a temporary file in the same folder and renamed into place, so a
``kill -9`` at any moment leaves only complete checkpoints under their final names. The pointer
is written the same way *after* the checkpoint; a reader that finds the pointer stale (killed
between the two renames) takes the newest complete file instead. Each checkpoint is a plain
``torch.save`` dict loadable with ``weights_only=True`` (tensors, numbers, strings, lists):
``meta`` (JSON-able, schema ``checkpoint``), ``model``, ``optimizer``, ``scaler``, ``sampler``, ``rng``.
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path
from typing import Any

import numpy as np

from relocdepth.errors import UserError
from relocdepth.fileio import atomic_write, write_json_atomic

log = logging.getLogger(__name__)

FORMAT = "relocdepth-checkpoint"
POINTER_FORMAT = "relocdepth-checkpoint-pointer"
ALIGNMENT_FORMAT = "relocdepth-alignment"
FORMAT_VERSION = 1  # bump when the checkpoint dict changes incompatibly
CHECKPOINT_DIR = "checkpoints"
POINTER_NAME = "latest"
ALIGNMENT_NAME = "alignment.json"
DEFAULT_RUNS_DIR = "runs"
_NAME_RE = re.compile(r"^ckpt-(\d{8,})\.pt$")


def checkpoint_name(step: int) -> str:
    """File name of the checkpoint taken after ``step`` optimizer steps."""
    return f"ckpt-{step:08d}.pt"


def checkpoint_dir(run_dir: str | Path) -> Path:
    return Path(run_dir) / CHECKPOINT_DIR


def list_checkpoints(run_or_dir: str | Path) -> list[Path]:
    """Complete checkpoints of a run (or of its checkpoints folder), oldest first."""
    d = Path(run_or_dir)
    if (d / CHECKPOINT_DIR).is_dir():
        d = d / CHECKPOINT_DIR
    if not d.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in d.iterdir() if (m := _NAME_RE.match(p.name))]
    return [p for _, p in sorted(found)]


def save_checkpoint(run_dir: str | Path, state: dict[str, Any], keep_last: int = 3) -> Path:
    """Write ``state`` (with ``state["meta"]["step"]``) as the next checkpoint of ``run_dir``.

    Atomic (temp file + rename), then the ``latest`` pointer, then older checkpoints beyond
    ``keep_last`` are removed. Returns the checkpoint path.
    """
    import torch

    from relocdepth.schemas import validate

    meta = state["meta"]
    validate("checkpoint", meta, "checkpoint metadata")
    d = checkpoint_dir(run_dir)
    path = d / checkpoint_name(int(meta["step"]))
    # temp files (checkpoint or pointer) left by a killed writer: one writer per run
    for stale in d.glob(".*.tmp") if d.is_dir() else ():
        stale.unlink(missing_ok=True)
    atomic_write(path, lambda f: torch.save(state, f))
    pointer = {
        "format": POINTER_FORMAT, "format_version": FORMAT_VERSION,
        "checkpoint": path.name, "step": int(meta["step"]), "epoch": int(meta["epoch"]),
    }
    write_json_atomic(d / POINTER_NAME, pointer, sort_keys=True)
    if keep_last > 0:
        for old in list_checkpoints(d)[:-keep_last]:
            old.unlink(missing_ok=True)
    return path


def _read_pointer(d: Path) -> Path | None:
    p = d / POINTER_NAME
    if not p.is_file():
        return None
    try:
        obj = json.loads(p.read_text())
        from relocdepth.schemas import validate

        validate("checkpoint_pointer", obj, str(p))
    except (ValueError, UserError) as e:
        log.warning("ignoring unreadable checkpoint pointer %s (%s)", p, e)
        return None
    target = d / obj["checkpoint"]
    return target if target.is_file() else None


def latest_checkpoint(run_dir: str | Path) -> Path | None:
    """The newest complete checkpoint of a run, or None.

    The pointer names it; the newest ``ckpt-*.pt`` wins when the pointer is older (a kill
    between the checkpoint's rename and the pointer's) or missing.
    """
    d = Path(run_dir)
    if (d / CHECKPOINT_DIR).is_dir():
        d = d / CHECKPOINT_DIR
    files = list_checkpoints(d)
    pointed = _read_pointer(d)
    if not files:
        return pointed
    newest = files[-1]
    if pointed is not None and _NAME_RE.match(pointed.name) and pointed.name >= newest.name:
        return pointed
    return newest


def resolve_checkpoint(path_or_run: str | Path | None) -> Path:
    """A checkpoint file from a file, a run folder (its latest), a checkpoints folder, or None.

    None means the newest run under ``./runs`` (by its latest checkpoint's modification time).
    Raises :class:`UserError` when nothing is found.
    """
    if path_or_run is None:
        runs = Path(DEFAULT_RUNS_DIR)
        cands = [c for r in sorted(runs.iterdir()) if r.is_dir() and (c := latest_checkpoint(r))] \
            if runs.is_dir() else []
        if not cands:
            raise UserError(
                f"no checkpoint given and no trained run under ./{DEFAULT_RUNS_DIR}; "
                "pass --checkpoint runs/NAME (train one with `reloc train SHARDS -o runs/NAME`)"
            )
        return max(cands, key=lambda p: p.stat().st_mtime)
    p = Path(path_or_run)
    if p.is_file():
        return p
    if not p.exists():
        raise UserError(f"checkpoint or run folder {p} does not exist")
    found = latest_checkpoint(p)
    if found is None:
        raise UserError(
            f"{p} holds no checkpoint (expected {p}/{CHECKPOINT_DIR}/ckpt-*.pt); "
            "pass a run folder written by `reloc train` or a .pt file"
        )
    return found


def load_checkpoint(path: str | Path, map_location: Any = "cpu") -> dict[str, Any]:
    """Load and check a checkpoint dict: readable, ours, this format version, valid metadata."""
    import torch

    from relocdepth.schemas import validate

    path = Path(path)
    try:
        ckpt = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:  # noqa: BLE001 - truncated / foreign / not a torch file: all say the same
        raise UserError(f"{path} is not a readable relocdepth checkpoint ({type(e).__name__}: {e})") from None
    meta = ckpt.get("meta") if isinstance(ckpt, dict) else None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise UserError(f"{path} is not a relocdepth checkpoint (no '{FORMAT}' metadata)")
    version = meta.get("format_version")
    if version != FORMAT_VERSION:
        raise UserError(
            f"{path} has checkpoint format version {version}, this relocdepth reads version "
            f"{FORMAT_VERSION}; use the relocdepth version that wrote it (tool_version "
            f"{meta.get('tool_version', '?')}) or train again"
        )
    validate("checkpoint", meta, f"checkpoint metadata of {path}")
    return ckpt


def check_same_dataset(meta: dict, manifest_hash: str, path: str | Path) -> None:
    """Refuse to resume a checkpoint trained on other shards (manifest hash differs)."""
    if meta["manifest_hash"] != manifest_hash:
        raise UserError(
            f"checkpoint {path} was trained on another dataset ({meta['dataset']['name']}, manifest "
            f"{meta['manifest_hash'][:12]}) than these shards (manifest {manifest_hash[:12]}); "
            "resume with the same shards, or train into a new run folder (-o)"
        )


def _alignment_path(ckpt_path: Path) -> Path:
    return ckpt_path.parent / ALIGNMENT_NAME


def read_alignment(ckpt_path: Path) -> dict | None:
    """The stored Sim(3) alignment for exactly this checkpoint, or None."""
    p = _alignment_path(ckpt_path)
    if not p.is_file():
        return None
    try:
        obj = json.loads(p.read_text())
    except ValueError:
        log.warning("ignoring unreadable alignment file %s", p)
        return None
    if obj.get("checkpoint") != ckpt_path.name:
        log.info("alignment %s belongs to %s, not %s; ignoring it", p, obj.get("checkpoint"), ckpt_path.name)
        return None
    return obj.get("alignment")


def save_alignment(path_or_run: str | Path | None, alignment: dict) -> None:
    """Store a Sim(3) alignment (JSON-able dict) with the run, tied to the resolved checkpoint."""
    ckpt = resolve_checkpoint(path_or_run)
    obj = {"format": ALIGNMENT_FORMAT, "checkpoint": ckpt.name, "alignment": alignment}
    write_json_atomic(_alignment_path(ckpt), obj, sort_keys=True)


def load_for_inference(path_or_run: str | Path | None, device: str = "cpu",
                       raw: bool = False) -> tuple[Any, dict]:
    """Networks in eval mode plus metadata, from a checkpoint file or run folder.

    Returns ``(nets, meta)``; ``meta`` is the checkpoint metadata with ``input_size`` (W, H),
    ``intrinsics`` (training camera at input size), ``alignment`` (Sim(3) dict or None),
    ``config`` (the training config dict), ``manifest_hash``, ``step``, ``path`` and ``weights``:
    "average" where the checkpoint holds a moving average of the weights (whose networks these
    then are, unless ``raw``: the trained weights, as training itself uses them), else "raw";
    ``anchors``: the run's anchors ``(N, 4, 4)`` float64 in its training frames' order (``--anchor``;
    None without), the map of :func:`relocdepth.refine.map_anchors`.
    """
    from relocdepth.models import ModelConfig, Networks

    path = resolve_checkpoint(path_or_run)
    ckpt = load_checkpoint(path, map_location="cpu")
    meta = dict(ckpt["meta"])
    model_cfg = dict(meta["model"])
    model_cfg["pretrained"] = None  # the weights come from the checkpoint
    nets = Networks(ModelConfig(**model_cfg))  # not build_networks: no initialisation to log
    # the weights' moving average, where training kept one (TrainConfig.ema_decay) and it is wanted
    ema = None if raw else ckpt.get("ema")
    nets.load_state_dict(ema["weights"] if ema else ckpt["model"])
    meta["weights"] = "average" if ema else "raw"
    log.info("networks loaded from %s (step %s, %s weights)", path, meta.get("step"), meta["weights"])
    nets.to(device).eval()
    meta["input_size"] = tuple(meta["input_size"])
    meta["config"] = meta.get("train", {})
    meta["alignment"] = read_alignment(path) or meta.get("alignment")
    meta["path"] = str(path)
    anchors = ckpt.get("anchors") or {}
    meta["anchors"] = None if anchors.get("T_wc") is None else np.asarray(anchors["T_wc"], np.float64)
    return nets, meta
