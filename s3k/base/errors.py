"""The one exception type for mistakes a user can fix.

Library code raises :class:`UserError` (or a subclass, such as the data layer's ``DatasetError``) when the
input is wrong: a missing or corrupt file, a field out of range, a run folder that already exists. The message
is one line that names the file, field or value, and, where an option fixes it, the option (``hint``). The
command line prints it as ``s3k COMMAND: error: ...`` without a traceback; library callers get an ordinary
``ValueError`` subclass they can catch.
"""

from __future__ import annotations


class UserError(ValueError):
    """A mistake in the user's input or environment, reported in one line.

    Args:
        message: what is wrong, naming the file, field or value.
        hint: what fixes it, e.g. ``"pass --overwrite to replace it"``; appended after ``"; "``.

    Example:
        >>> str(UserError("runs/a exists", hint="pass --resume to continue it"))
        'runs/a exists; pass --resume to continue it'
    """

    def __init__(self, message: str, hint: str | None = None) -> None:
        self.message = message
        self.hint = hint
        super().__init__(f"{message}; {hint}" if hint else message)
