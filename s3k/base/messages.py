"""How the library speaks to the person running it: through :mod:`logging`, never ``print``.

Every module logs to ``logging.getLogger(__name__)``: results and progress at INFO, remarks that belong
beside a command's output at :data:`NOTE`, what may be wrong at WARNING. The command line shows them while
a command runs (``s3k.cli.showing_library_messages``): INFO on standard output as written, NOTE on standard
error as written, WARNING and above on standard error as ``warning: ...``. A program that imports s3k
configures logging as it likes.
"""

from __future__ import annotations

import logging

NOTE = 25
"""A remark for the user's terminal, not the command's output (between INFO and WARNING)."""
logging.addLevelName(NOTE, "NOTE")

log = logging.getLogger(__name__)


def say(text: str) -> None:
    """A line of a command's output, from a library function that takes a ``log`` callback (its default)."""
    log.info(text)


def note(text: str) -> None:
    """A remark for the terminal, from a library function that takes a callback for them (its default)."""
    log.log(NOTE, text)
