"""The `reloc` command: a typer app whose commands parse, validate and call one library function.

Each command lives in its own module of this package (``cli/<command>.py``) and registers
itself on :data:`app`; heavy imports (torch, cv2) happen inside the command so that
``reloc --help`` stays fast. Exit codes (README, "Exit codes"): 0 done, 1 a bug (traceback),
2 bad input (one ``error:`` line), 3 training diverged, 130 interrupted.
"""

from __future__ import annotations

import importlib
import logging
import os
import sys
from typing import Annotated

import typer

from relocdepth.errors import (
    EXIT_DIVERGED,
    EXIT_INTERRUPTED,
    EXIT_USER_ERROR,
    TrainingDiverged,
    UserError,
)

app = typer.Typer(
    name="reloc",
    help="Learn camera re-localization and monocular depth for one place from unlabeled video.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

# Environment variable that sets the log level of every rank (default: INFO on rank 0 only).
LOG_LEVEL_ENV = "RELOCDEPTH_LOG_LEVEL"

# Command modules, in the order a user meets them; each defines its command on `app`.
COMMAND_MODULES = ("synth", "ingest", "inspect", "train", "localize", "evaluate", "demo")


def _version(value: bool) -> None:
    if value:
        from relocdepth import __version__

        typer.echo(f"relocdepth {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                                          help="Print the version and exit.")] = False,
) -> None:
    """Learn camera re-localization and monocular depth for one place from unlabeled video."""


def _register() -> None:
    for name in COMMAND_MODULES:
        try:
            importlib.import_module(f"relocdepth.cli.{name}")
        except ModuleNotFoundError as e:
            # A command whose module is not there yet is simply absent; a missing dependency
            # inside an existing module is a real error.
            if e.name != f"relocdepth.cli.{name}":
                raise


class _StderrHandler(logging.StreamHandler):
    """A stream handler that writes to whatever ``sys.stderr`` is at the time of each record."""

    @property  # type: ignore[override]
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass


def setup_logging() -> None:
    """INFO on rank 0 (or a single process), WARNING on the other torchrun ranks; the
    environment variable ``RELOCDEPTH_LOG_LEVEL`` (e.g. ``INFO``, ``DEBUG``) sets every rank's.

    On a terminal the lines go through rich's handler on the same console as the progress
    bars, so a log line is printed above a bar instead of through it. Without a terminal
    (nohup, a scheduler's log file) there is no bar to protect and rich would wrap lines at 80
    columns, so plain timestamped lines are written instead.
    """
    from relocdepth.progress import stderr_console, stderr_is_terminal

    rank = int(os.environ.get("RANK", "0") or 0)
    level: int | str = logging.INFO if rank == 0 else logging.WARNING
    if os.environ.get(LOG_LEVEL_ENV):
        level = os.environ[LOG_LEVEL_ENV].strip().upper()
        if not isinstance(logging.getLevelName(level), int):
            raise UserError(f"{LOG_LEVEL_ENV}={level} is not a logging level "
                            "(DEBUG, INFO, WARNING, ERROR)")
    who = f"[rank {rank}] " if rank else ""
    handler: logging.Handler
    if stderr_is_terminal():
        from rich.logging import RichHandler

        handler = RichHandler(console=stderr_console(), show_path=False, markup=False)
        fmt = who + "%(name)s: %(message)s"
    else:
        handler = _StderrHandler()
        fmt = "%(asctime)s %(levelname)s " + who + "%(name)s: %(message)s"
    handler.setFormatter(logging.Formatter(fmt))
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(level)


def main(argv: list[str] | None = None) -> None:
    """Console-script entry point: runs the command and maps the outcome to the exit code."""
    try:
        setup_logging()
    except UserError as e:
        typer.echo(f"error: {e}", err=True)
        sys.exit(EXIT_USER_ERROR)
    _register()
    try:
        # standalone_mode=False lets every outcome reach this function (click's standalone mode
        # turns Ctrl-C into "Aborted!" and exit 1 in some versions, 130 in others).
        rc = app(args=argv, standalone_mode=False)
    except UserError as e:
        typer.echo(f"error: {e}", err=True)
        sys.exit(EXIT_USER_ERROR)
    except TrainingDiverged as e:
        typer.echo(f"error: {e}", err=True)
        sys.exit(EXIT_DIVERGED)
    except KeyboardInterrupt:
        sys.exit(EXIT_INTERRUPTED)
    except typer.Abort as e:  # older click: Ctrl-C arrives as Abort from KeyboardInterrupt
        if isinstance(e.__cause__, KeyboardInterrupt):
            sys.exit(EXIT_INTERRUPTED)
        typer.echo("Aborted!", err=True)
        sys.exit(1)
    except typer.Exit as e:
        sys.exit(e.exit_code)
    except Exception as e:
        if hasattr(e, "show") and isinstance(getattr(e, "exit_code", None), int):
            e.show()  # a usage error: click's message, exit 2
            sys.exit(e.exit_code)
        raise
    sys.exit(rc if isinstance(rc, int) else 0)


_register()

if __name__ == "__main__":
    main()
