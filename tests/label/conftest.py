"""Fixtures of the labelling app's tests."""

from __future__ import annotations

import pytest
from helpers.label_data import make_label_dataset


@pytest.fixture
def truth(tmp_path):
    """A labelling dataset of the synthetic rig written to ``tmp_path/ds`` (:func:`make_label_dataset`)."""
    return make_label_dataset(tmp_path / "ds")
