"""Numeric ranges: the one description of what values a setting takes, checked wherever it is given.

A :class:`Range` is declared once beside the setting (a :mod:`s3k.config` field's metadata, a command-line
option's ``type=``, ``s3k.cli.options.number``) and checked by :meth:`Range.problem`: every float must be
finite (``nan`` and ``inf`` compare false with everything, so a threshold of ``nan`` would switch a check
off), and the value must lie within the bounds.

Example:
    >>> Range(gt=0).problem(0.0)
    'must be > 0'
    >>> Range(ge=0, lt=1).problem(float("nan"))
    'must be a finite number'
    >>> Range(ge=0, lt=1).describe()
    'in [0, 1)'
    >>> Range(one_of=(1, 2, 4)).problem(3)
    'must be one of 1, 2, 4'
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from s3k.base.errors import UserError


@dataclass(frozen=True)
class Range:
    """Bounds of a number: ``ge`` / ``gt`` (at least / above), ``le`` / ``lt`` (at most / below); or the
    values it may take, ``one_of``."""

    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    one_of: tuple[float, ...] | None = None

    def describe(self) -> str:
        """The bounds in words, e.g. ``'>= 1'``, ``'in [0, 1)'``, ``'one of 1, 2, 4'``; ``''`` when
        unbounded."""
        if self.one_of is not None:
            return "one of " + ", ".join(f"{v:g}" for v in self.one_of)
        low = (f"[{self.ge:g}" if self.ge is not None else f"({self.gt:g}" if self.gt is not None else None)
        high = (f"{self.le:g}]" if self.le is not None else f"{self.lt:g})" if self.lt is not None else None)
        if low and high:
            return f"in {low}, {high}"
        if low:
            return (">= " if low[0] == "[" else "> ") + low[1:]
        if high:
            return ("<= " if high[-1] == "]" else "< ") + high[:-1]
        return ""

    def problem(self, value: Any) -> str | None:
        """What is wrong with ``value`` (``'must be > 0'``), or None when it is in range."""
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return "must be a number"
        if isinstance(value, float) and not math.isfinite(value):
            return "must be a finite number"
        if self.one_of is not None and value not in self.one_of:
            return f"must be {self.describe()}"
        out = ((self.ge is not None and value < self.ge) or (self.gt is not None and value <= self.gt)
               or (self.le is not None and value > self.le) or (self.lt is not None and value >= self.lt))
        return f"must be {self.describe()}" if out else None

    def check(self, value: Any, what: str, hint: str | None = None) -> Any:
        """``value`` when in range; else :class:`UserError` ``'<what> must be ..., got <value>'``."""
        problem = self.problem(value)
        if problem is not None:
            raise UserError(f"{what} {problem}, got {value!r}", hint=hint)
        return value


FINITE = Range()
"""Any finite number."""
