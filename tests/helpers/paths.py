"""Where the tests find the repository and their data, whatever folder a test module sits in."""

from __future__ import annotations

from pathlib import Path

TESTS = Path(__file__).resolve().parents[1]
"""The ``tests/`` folder."""
REPO = TESTS.parent
"""The repository's root: ``s3k/``, ``docs/``, ``benchmarks/``, ``scripts/``, README.md."""
OLD_RUNS = TESTS / "data" / "old_runs"
"""Run folders written by an older s3k (``make_old_runs.py`` there)."""
