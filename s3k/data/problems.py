"""What the dataset checks find: one :class:`Problem` per finding, collected by :class:`Problems`.

Every check of a dataset folder reports here, naming the file, the field and where in the file (line, frame,
camera, keypoint), so that ``s3k validate`` can print every problem and :class:`DatasetError` can say the
first one in a line.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from s3k.base.errors import UserError


@dataclass(frozen=True)
class Problem:
    """One finding of the checks: ``severity`` is ``"error"`` (dataset unusable) or ``"warning"``."""

    severity: str
    file: str
    field: str | None
    message: str
    line: int | None = None
    frame: int | None = None
    camera: str | None = None
    keypoint: str | None = None

    def __str__(self) -> str:
        where = self.file + (f" line {self.line}" if self.line is not None else "")
        context = [
            f"{name} {value}"
            for name, value in (("frame", self.frame), ("camera", self.camera), ("keypoint", self.keypoint))
            if value is not None
        ]
        if context:
            where += f" ({', '.join(context)})"
        field_text = f" field '{self.field}':" if self.field else ""
        return f"{where}:{field_text} {self.message}"


class DatasetError(UserError):
    """A dataset that cannot be used; ``problems`` lists every error found (file, field, line, ...).

    Its message is one line: the dataset, the first problem and how many more there are
    (``s3k validate DATASET`` prints them all).

    Example:
        >>> str(DatasetError("ds", [Problem("error", "labels.csv", "u", "not a number", line=3)] * 2))
        "dataset ds: labels.csv line 3: field 'u': not a number (and 1 more error)"
    """

    def __init__(self, root: str | Path, problems: Sequence[Problem]):
        self.root = Path(root)
        self.problems = list(problems)
        first = str(self.problems[0]) if self.problems else "unusable"
        more = len(self.problems) - 1
        tail = f" (and {more} more error{'s' if more > 1 else ''})" if more > 0 else ""
        super().__init__(f"dataset {self.root}: {first}{tail}")


class DatasetWarning(UserWarning):
    """A problem that s3k works around (e.g. a label outside its image, which is masked)."""


class Problems:
    """The findings of one round of checks, in the order found."""

    def __init__(self) -> None:
        self.items: list[Problem] = []

    def error(self, file: str, field: str | None, message: str, **where: Any) -> None:
        self.items.append(Problem("error", file, field, message, **where))

    def warning(self, file: str, field: str | None, message: str, **where: Any) -> None:
        self.items.append(Problem("warning", file, field, message, **where))

    @property
    def errors(self) -> list[Problem]:
        return [p for p in self.items if p.severity == "error"]

    @property
    def warnings(self) -> list[Problem]:
        return [p for p in self.items if p.severity == "warning"]
