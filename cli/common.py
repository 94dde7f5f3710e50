"""What every command shares: turning user mistakes into one line and exit code 2."""

from __future__ import annotations

import functools
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
