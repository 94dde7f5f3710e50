"""A run trained for one step on the shared synth shards, built once per session and shared by
the localize and evaluate tests (a module-level cache: both test modules import this one); a DSC
network of given output for the loss tests."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

_CACHE: dict[str, Path] = {}


def trained_run(shards: Path, factory: pytest.TempPathFactory) -> Path:
    """A run folder with one checkpoint (1 step, batch 1, 128x96, random init). Read-only:
    copy it (:func:`copy_run`) before saving an alignment into it."""
    key = str(shards)
    if key not in _CACHE:
        from relocdepth.train import TrainConfig, train

        run = factory.mktemp("run") / "run"
        cfg = TrainConfig.from_dict({"size": (128, 96), "batch_size": 1, "max_steps": 1,
                                     "pretrained": None, "workers": 0, "progress": False,
                                     "window": 3})
        train(shards, run, cfg)
        _CACHE[key] = run
    return _CACHE[key]


def copy_run(run: Path, dest: Path) -> Path:
    shutil.copytree(run, dest)
    return dest


def with_anchors(run: Path, shards: Path, dest: Path, sim3: tuple) -> tuple[Path, np.ndarray]:
    """A copy of ``run`` whose checkpoint holds anchors: the training frames' true poses moved by
    the similarity ``sim3`` (scale, R, t), in the order of the shards' training frames (as the
    trainer stores them). Returns the copy and those anchors."""
    from relocdepth.checkpoint import resolve_checkpoint
    from relocdepth.dataset import open_dataset
    from relocdepth.eval_geometry import apply_sim3

    run = copy_run(run, dest)
    ds = open_dataset(shards)
    anchors = apply_sim3(*sim3, np.stack([ds.read_pose(r) for r in ds.frames("train")]).astype(np.float64))
    path = resolve_checkpoint(run)
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    ckpt["anchors"] = {"T_wc": torch.as_tensor(anchors, dtype=torch.float32), "step": 1}
    torch.save(ckpt, path)
    return run, anchors


class FixedDSC(torch.nn.Module):
    """A DSC network whose output is given (the DSC of known poses)."""

    def __init__(self, out: torch.Tensor) -> None:
        super().__init__()
        self.out = out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.out
