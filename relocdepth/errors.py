"""The exception types the CLI maps to exit codes.

Library code raises :class:`UserError` with a message that says what is wrong and what to
do; the CLI turns it into one line on stderr and exit code 2. :class:`TrainingDiverged` is
not the user's input being wrong but a run that went numerically bad: one line, exit code 3.
Anything else is a bug and keeps its traceback (exit code 1).
"""

# Exit codes of `reloc` (README, "Exit codes").
EXIT_USER_ERROR = 2
EXIT_DIVERGED = 3
EXIT_INTERRUPTED = 130  # 128 + SIGINT, what shells report for a process stopped by Ctrl-C


class UserError(Exception):
    """A mistake in the user's input (a path, a file, an option), not a bug."""


class TrainingDiverged(Exception):
    """Training stopped because the loss stayed non-finite (the last good checkpoint is kept)."""
