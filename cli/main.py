"""The `reloc` command: a typer app whose commands parse, validate and call one library function.

Each command lives in its own module of this package (``cli/<command>.py``) and registers
itself on :data:`app`; heavy imports (torch, cv2) happen inside the command so that
``reloc --help`` stays fast. User mistakes (:class:`relocdepth.errors.UserError`) become one
line on stderr and exit code 2.
"""

from __future__ import annotations

import importlib
import logging
import sys

import typer

from relocdepth.errors import UserError

app = typer.Typer(
    name="reloc",
    help="Learn camera re-localization and monocular depth for one place from unlabeled video.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

# Command modules, in the order a user meets them; each defines its command on `app`.
COMMAND_MODULES = ("synth", "ingest", "inspect", "train", "localize", "evaluate", "demo")


def _register() -> None:
    for name in COMMAND_MODULES:
        try:
            importlib.import_module(f"relocdepth.cli.{name}")
        except ModuleNotFoundError as e:
            # A command whose module is not there yet is simply absent; a missing dependency
            # inside an existing module is a real error.
            if e.name != f"relocdepth.cli.{name}":
                raise


def main(argv: list[str] | None = None) -> None:
    """Console-script entry point."""
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    _register()
    try:
        app(args=argv, standalone_mode=True)
    except UserError as e:
        typer.echo(f"error: {e}", err=True)
        sys.exit(2)


_register()

if __name__ == "__main__":
    main()
