"""What every command shares: exit codes for user mistakes and divergence, size and device options."""

from __future__ import annotations

import functools
import re
from collections.abc import Callable
from enum import Enum
from typing import TypeVar

import typer

from relocdepth.errors import EXIT_DIVERGED, EXIT_USER_ERROR, TrainingDiverged, UserError

F = TypeVar("F", bound=Callable)

# The one --device grammar of train, localize and evaluate (same default everywhere).
DEVICE_METAVAR = "auto|cpu|cuda|cuda:N"
DEVICE_DEFAULT = "auto"
DEVICE_HELP = "auto (a CUDA GPU when there is one, else the CPU), cpu, cuda or cuda:N (GPU N)."


class RefineMatcher(str, Enum):
    """How ``--refine`` matches a pair (``relocdepth.refine.MATCHERS``)."""

    klt = "klt"
    sift = "sift"
    klt_sift = "klt+sift"


REFINE_MATCHER_HELP = ("With --refine: how a pair is matched: klt (the bootstrap's tracks: precise, short "
                       "baselines), sift (descriptors: wider baselines, less precise), klt+sift (SIFT where "
                       "KLT fails).")
class RefineMap(str, Enum):
    """Where ``--refine``'s map poses come from (``relocdepth.refine.MAPS``)."""

    auto = "auto"
    anchors = "anchors"
    network = "network"


REFINE_MAP_HELP = ("With --refine: the training frames' poses the pose is refined against. auto: the run's "
                   "anchors when its checkpoint has them (--anchor vo: the training video's odometry and bundle "
                   "adjustment, in the network's world), else the network's own poses of the frames; anchors: "
                   "those only (an error if the run has none); network: the network's poses. On a generated scene "
                   "of 2000 training frames the anchors were 4 cm from the truth and the network's poses 18 cm, "
                   "and the test poses refined against them 7 and 20 cm (README, Localize, evaluate, demo).")
REFINE_ALIGN_HELP = ("With --refine: after the pairs, align the pose to the nearest training frames pixel by "
                     "pixel (their images and the network's depth), from the pairs' pose and from the "
                     "network's; the aligned pose is used when it explains those frames clearly better than "
                     "their mean brightness does.")


def user_errors(fn: F) -> F:
    """Decorate a command: a :class:`UserError` prints ``error: ...`` and exits 2, a
    :class:`TrainingDiverged` prints ``error: ...`` and exits 3.

    Put it *under* ``@app.command()``; ``functools.wraps`` keeps the signature typer reads.
    """

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except UserError as e:
            typer.echo(f"error: {e}", err=True)
            raise typer.Exit(EXIT_USER_ERROR) from None
        except TrainingDiverged as e:
            typer.echo(f"error: {e}", err=True)
            raise typer.Exit(EXIT_DIVERGED) from None

    return wrapper  # type: ignore[return-value]


def parse_size(text: str, option: str = "--size") -> tuple[int, int]:
    """``"640x480"`` -> (640, 480); anything else is a UserError naming ``option``."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m or int(m.group(1)) < 1 or int(m.group(2)) < 1:
        raise UserError(f"{option} must look like 640x480 (WIDTHxHEIGHT, positive), got {text!r}")
    return int(m.group(1)), int(m.group(2))


def parse_device(text: str) -> str:
    """``--device`` in the one grammar (``auto|cpu|cuda|cuda:N``), normalised; else a UserError."""
    from relocdepth.distributed import check_device

    return check_device(text)
