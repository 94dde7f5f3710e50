"""The one exception type for user mistakes.

Library code raises :class:`UserError` with a message that says what is wrong and what to
do; the CLI turns it into one line on stderr and exit code 2. Anything else is a bug and
keeps its traceback.
"""


class UserError(Exception):
    """A mistake in the user's input (a path, a file, an option), not a bug."""
