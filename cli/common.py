"""What every command shares: turning user mistakes into one line and exit code 2."""

from __future__ import annotations

import functools
import re
from collections.abc import Callable
from typing import TypeVar

import typer

from relocdepth.errors import UserError

F = TypeVar("F", bound=Callable)


def user_errors(fn: F) -> F:
    """Decorate a command so that a :class:`UserError` prints ``error: ...`` and exits 2.

    Put it *under* ``@app.command()``; ``functools.wraps`` keeps the signature typer reads.
    """

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except UserError as e:
            typer.echo(f"error: {e}", err=True)
            raise typer.Exit(2) from None

    return wrapper  # type: ignore[return-value]


def parse_size(text: str, option: str = "--size") -> tuple[int, int]:
    """``"640x480"`` -> (640, 480); anything else is a UserError naming ``option``."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m or int(m.group(1)) < 1 or int(m.group(2)) < 1:
        raise UserError(f"{option} must look like 640x480 (WIDTHxHEIGHT, positive), got {text!r}")
    return int(m.group(1)), int(m.group(2))
