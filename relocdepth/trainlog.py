"""Where training reports: a JSONL file, TensorBoard when installed, and progress on stderr.

Progress is a rich bar when stderr is a terminal; otherwise (nohup, tmux logs, a scheduler's
log file, where a bar would be drawn once, at the end) one plain line every ``log_every``
steps: step, epoch, loss, triplets/s, ETA. ``logs/train.jsonl`` gets one JSON object per line: ``{"kind": "step", ...}`` every N steps (loss,
its parts, the collapse diagnostics, throughput) and ``{"kind": "event", ...}`` lines for
skipped steps and samples, checkpoints, resume and stop. A resumed run appends; steps between
the last checkpoint and a kill appear twice (the second time is what the weights saw).
"""

from __future__ import annotations

import json
import logging
import math
import sys
import time
from pathlib import Path
from typing import Any, TextIO

import numpy as np

log = logging.getLogger(__name__)

LOG_DIR = "logs"
LOG_NAME = "train.jsonl"
# Steps between two image summaries (depth map, warped target) in TensorBoard: images are
# large next to scalars, and a few hundred steps still show the depth taking shape.
IMAGES_EVERY = 250


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
                 start_step: int = 0, epochs: int = 0, log_every: int = 10,
                 images_every: int = IMAGES_EVERY, plain: bool | None = None,
                 stream: TextIO | None = None, max_seconds: float | None = None) -> None:
        """``plain``: plain progress lines instead of a bar (default: when stderr is not a
        terminal); ``stream``: where they go (default: stderr); ``max_seconds``: a wall-clock
        budget, which caps the ETA of the plain lines."""
        from relocdepth.progress import stderr_console, stderr_is_terminal

        self.enabled = run_dir is not None
        self._file = None
        self._tb = None
        self._progress = None
        self._task = None
        self.epochs = epochs
        self.total_steps = total_steps
        self.max_seconds = max_seconds
        self.log_every = max(int(log_every), 1)
        self.images_every = max(int(images_every), 1)
        self._plain = False
        self._stream = stream
        self._t0, self._step0 = time.monotonic(), start_step
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
        self._plain = progress and (not stderr_is_terminal() if plain is None else plain)
        if progress and not self._plain:
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
                console=stderr_console(),
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

    def wants_images(self, step: int) -> bool:
        """Whether :meth:`images` would write at this step (TensorBoard there, every N steps)."""
        return self._tb is not None and step % self.images_every == 0

    def images(self, step: int, images: dict[str, Any]) -> None:
        """Image summaries in TensorBoard (nothing without it).

        ``images``: name -> ``(H, W)`` map (a depth map: drawn through the depth colour map,
        near = bright) or ``(3, H, W)`` RGB (float in [0, 1] or uint8); tensors or arrays.
        """
        if self._tb is None:
            return
        for name, img in images.items():
            a = img.detach().float().cpu().numpy() if hasattr(img, "detach") else np.asarray(img)
            if a.ndim == 2:
                from relocdepth.plots import colourise_depth

                rgb = colourise_depth(a)[..., ::-1].copy()  # BGR -> RGB
                self._tb.add_image(name, rgb, step, dataformats="HWC")
            elif a.ndim == 3 and a.shape[0] == 3:
                chw = a.astype(np.float32) / 255.0 if a.dtype == np.uint8 else np.clip(a, 0.0, 1.0)
                self._tb.add_image(name, chw, step, dataformats="CHW")
            else:
                raise ValueError(f"TrainLog.images: {name} has shape {a.shape}; want (H, W) or (3, H, W)")

    def tick(self, step: int, epoch: int, loss: float | None, rate: float | None) -> None:
        if self._plain and self.enabled and (step % self.log_every == 0 or step == self.total_steps):
            self._plain_line(step, epoch, loss, rate)
        if self._progress is not None and self._task is not None:
            self._progress.update(
                self._task, completed=step, epoch=f"{epoch + 1}/{self.epochs}",
                loss="-" if loss is None else f"{loss:.4f}", rate="-" if rate is None else f"{rate:.1f}",
            )

    def _plain_line(self, step: int, epoch: int, loss: float | None, rate: float | None) -> None:
        from relocdepth.progress import format_duration

        elapsed = time.monotonic() - self._t0
        done = step - self._step0
        left = max(self.total_steps - step, 0)
        eta_s = left * elapsed / done if done > 0 else None
        if self.max_seconds is not None:  # the trainer stops itself at its wall-clock budget
            eta_s = max(self.max_seconds - elapsed, 0.0) if eta_s is None else min(eta_s, max(self.max_seconds - elapsed, 0.0))
        eta = format_duration(eta_s) if eta_s is not None else "-"
        parts = [f"step {step}/{self.total_steps}", f"epoch {epoch + 1}/{self.epochs}",
                 "loss -" if loss is None else f"loss {loss:.4f}",
                 "- triplets/s" if rate is None else f"{rate:.1f} triplets/s", f"ETA {eta}"]
        stream = self._stream or sys.stderr
        stream.write("train: " + ", ".join(parts) + "\n")
        stream.flush()

    def close(self) -> None:
        if self._progress is not None:
            self._progress.stop()
        if self._tb is not None:
            self._tb.close()
        if self._file is not None:
            self._file.close()
        self._file = self._tb = self._progress = None
