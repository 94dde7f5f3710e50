"""Progress of long jobs: a rich bar on a terminal, a plain line every few seconds otherwise.

Under ``nohup``, tmux logs or a cluster scheduler stderr is a file: a rich bar there is drawn
once, at the end. :func:`progress_bar` returns a rich ``Progress`` when stderr is a terminal
and a :class:`PlainProgress` (same calls: ``add_task``, ``update``, ``advance``, ``start``,
``stop``, context manager) when it is not. Both write to stderr, so stdout stays clean for
results (``reloc localize`` prints poses there).
"""

from __future__ import annotations

import sys
import time
from typing import Any, TextIO

# Seconds between two plain progress lines when stderr is not a terminal.
PLAIN_EVERY_S = 5.0

_console: Any = None


def stderr_console() -> Any:
    """The one rich Console on stderr shared by the log handler and the progress bars.

    One console for both is what lets rich print log lines above a live bar instead of
    through it. Its file is looked up at each write, so a swapped ``sys.stderr`` is honoured.
    """
    global _console
    if _console is None:
        from rich.console import Console

        _console = Console(stderr=True)
    return _console


def stderr_is_terminal() -> bool:
    """True when stderr is an interactive terminal (rich's view, so FORCE_TERMINAL counts)."""
    return bool(stderr_console().is_terminal)


def format_duration(seconds: float) -> str:
    """``3725.2`` -> ``"1:02:05"``."""
    s = max(round(seconds), 0)
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"


class PlainProgress:
    """A progress report as plain lines: at most one per ``every_s`` seconds, and one at the end.

    A line reads ``<label> <description>: 120/500 frames (24%), 31.2 frames/s, ETA 0:00:12``.
    It implements the part of rich's ``Progress`` API the commands use, for one or more tasks.
    """

    def __init__(self, label: str, unit: str = "frames", every_s: float | None = None,
                 stream: TextIO | None = None) -> None:
        self.label = label
        self.unit = unit
        self.every_s = PLAIN_EVERY_S if every_s is None else every_s
        self._stream = stream
        self._tasks: list[dict[str, Any]] = []

    # rich.progress.Progress's API --------------------------------------------------------
    def __enter__(self) -> PlainProgress:  # noqa: PYI034 - not subclassed
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def start(self) -> None:
        pass

    def stop(self) -> None:
        for task in self._tasks:
            if task["completed"] > task["printed"]:
                self._line(task, final=True)

    def add_task(self, description: str = "", total: float | None = None, completed: int = 0,
                 **fields: Any) -> int:
        now = time.monotonic()
        self._tasks.append({"description": description, "total": total, "completed": completed,
                            "start": completed, "t0": now, "last": now, "printed": completed})
        return len(self._tasks) - 1

    def update(self, task_id: int, *, advance: float = 0, completed: float | None = None,
               description: str | None = None, total: float | None = None, **fields: Any) -> None:
        task = self._tasks[task_id]
        if description is not None:
            task["description"] = description
        if total is not None:
            task["total"] = total
        task["completed"] = completed if completed is not None else task["completed"] + advance
        now = time.monotonic()
        if now - task["last"] >= self.every_s:
            task["last"] = now
            self._line(task)

    def advance(self, task_id: int, advance: float = 1) -> None:
        self.update(task_id, advance=advance)

    # -------------------------------------------------------------------------------------
    def _line(self, task: dict[str, Any], final: bool = False) -> None:
        done, total = task["completed"], task["total"]
        elapsed = max(time.monotonic() - task["t0"], 1e-9)
        rate = (done - task["start"]) / elapsed
        head = f"{self.label} {task['description']}".strip()
        parts = [f"{int(done)}/{int(total)} {self.unit} ({100.0 * done / total:.0f}%)"
                 if total else f"{int(done)} {self.unit}"]
        parts.append(f"{rate:.1f} {self.unit}/s")
        if final:
            parts.append(f"done in {format_duration(elapsed)}")
        elif total and rate > 0:
            parts.append(f"ETA {format_duration((total - done) / rate)}")
        stream = self._stream or sys.stderr
        stream.write(f"{head}: {', '.join(parts)}\n")
        stream.flush()
        task["printed"] = done


def progress_bar(label: str, unit: str = "frames", *columns: Any, transient: bool = True) -> Any:
    """A rich ``Progress`` on stderr when it is a terminal, else a :class:`PlainProgress`.

    ``columns``: rich columns for the terminal bar (default: description, bar, M/N, ETA).
    """
    if not stderr_is_terminal():
        return PlainProgress(label, unit)
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeRemainingColumn,
    )

    if not columns:
        columns = (TextColumn(f"{label} {{task.description}}"), BarColumn(), MofNCompleteColumn(),
                   TextColumn("ETA"), TimeRemainingColumn())
    return Progress(*columns, console=stderr_console(), transient=transient)
