"""Where training reports: a JSONL file, TensorBoard when installed, and a rich progress bar.

``logs/train.jsonl`` gets one JSON object per line: ``{"kind": "step", ...}`` every N steps (loss,
its parts, the collapse diagnostics, throughput) and ``{"kind": "event", ...}`` lines for
skipped steps and samples, checkpoints, resume and stop. A resumed run appends; steps between
the last checkpoint and a kill appear twice (the second time is what the weights saw).
"""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

LOG_DIR = "logs"
LOG_NAME = "train.jsonl"


def _clean(v: Any) -> Any:
    """JSON-able value; non-finite floats become strings ("nan", "inf")."""
    if isinstance(v, dict):
        return {str(k): _clean(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_clean(x) for x in v]
    if hasattr(v, "item"):  # tensors, numpy scalars
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return str(v)
    return v


class TrainLog:
    """Rank 0's reporter; other ranks get ``TrainLog(None)`` which drops everything."""

    def __init__(self, run_dir: Path | None, progress: bool = False, total_steps: int = 0,
                 start_step: int = 0, epochs: int = 0) -> None:
        self.enabled = run_dir is not None
        self._file = None
        self._tb = None
        self._progress = None
        self._task = None
        self.epochs = epochs
        if not self.enabled:
            return
        assert run_dir is not None
        (run_dir / LOG_DIR).mkdir(parents=True, exist_ok=True)
        self._file = open(run_dir / LOG_DIR / LOG_NAME, "a", buffering=1)  # noqa: SIM115 - closed in close()
        try:
            from torch.utils.tensorboard import SummaryWriter

            self._tb = SummaryWriter(str(run_dir / LOG_DIR / "tensorboard"))
        except ImportError:
            log.info("tensorboard is not installed; logging to %s only", run_dir / LOG_DIR / LOG_NAME)
        if progress:
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                TextColumn,
                TimeElapsedColumn,
                TimeRemainingColumn,
            )

            self._progress = Progress(
                TextColumn("epoch {task.fields[epoch]}"), BarColumn(), MofNCompleteColumn(),
                TextColumn("loss {task.fields[loss]}"), TextColumn("{task.fields[rate]} triplets/s"),
                TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(),
            )
            self._progress.start()
            self._task = self._progress.add_task(
                "train", total=total_steps, completed=start_step, epoch=f"-/{epochs}", loss="-", rate="-"
            )

    def write(self, obj: dict[str, Any]) -> None:
        if self._file is not None:
            obj = {"time": round(time.time(), 3), **obj}
            self._file.write(json.dumps(_clean(obj), sort_keys=False) + "\n")

    def event(self, name: str, step: int, **fields: Any) -> None:
        self.write({"kind": "event", "event": name, "step": step, **fields})

    def step(self, record: dict[str, Any]) -> None:
        self.write({"kind": "step", **record})
        if self._tb is not None:
            s = record["step"]
            self._tb.add_scalar("loss/total", record["loss"], s)
            for k, v in record.get("parts", {}).items():
                self._tb.add_scalar(f"loss/{k}", v, s)
            for k, v in record.get("diagnostics", {}).items():
                self._tb.add_scalar(f"diag/{k}", v, s)
            self._tb.add_scalar("speed/triplets_per_s", record["triplets_per_s"], s)

    def tick(self, step: int, epoch: int, loss: float | None, rate: float | None) -> None:
        if self._progress is not None and self._task is not None:
            self._progress.update(
                self._task, completed=step, epoch=f"{epoch + 1}/{self.epochs}",
                loss="-" if loss is None else f"{loss:.4f}", rate="-" if rate is None else f"{rate:.1f}",
            )

    def close(self) -> None:
        if self._progress is not None:
            self._progress.stop()
        if self._tb is not None:
            self._tb.close()
        if self._file is not None:
            self._file.close()
        self._file = self._tb = self._progress = None
