"""Where the tests find the real 4-camera recording: ``shared/data/real`` beside the repository.

Tests that read it are marked ``@needs_real`` and skip when it is absent (e.g. a clone on its own).
"""

from __future__ import annotations

from pathlib import Path

import pytest

REAL = Path(__file__).resolve().parents[3] / "shared/data/real/sleap-anipose-minimal_session/minimal_session"

needs_real = pytest.mark.skipif(not REAL.is_dir(), reason=f"real recording not available at {REAL}")
