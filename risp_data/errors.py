"""The one exception type users see.

Every command-line entry point catches :class:`RispError` and prints its message as a single line
(``error: ...``) before exiting with status 1.  Raise it for anything the *user* can fix: unknown names,
wrong shapes, corrupt files, missing libraries.  Programming errors stay ordinary exceptions.
"""


class RispError(Exception):
    """A user-facing error whose message fits on one line and names the offending input."""
