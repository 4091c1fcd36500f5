"""The one exception type users see.

Every command-line entry point catches :class:`RispError` and prints its message as a single line
(``error: ...``) before exiting with status 1.  Raise it for anything the *user* can fix: unknown names,
wrong shapes, corrupt files, missing libraries.  Programming errors stay ordinary exceptions.
"""


class RispError(Exception):
    """A user-facing error whose message fits on one line and names the offending input."""


def message_line(error: BaseException, default: str = "") -> str:
    """The first non-empty line of ``error``'s message (``default`` when it has none): a library's multi-line
    message quoted inside one error line."""
    return next((line for line in str(error).splitlines() if line.strip()), default)
