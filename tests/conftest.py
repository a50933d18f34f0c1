"""Fixtures shared by the tests: a tiny dataset and a tiny run folder, the recordings ``s3k track`` and
``s3k import`` read (each built once per session, read only), and the devices and float types a tensor
function is checked on. The helpers they are built from are in ``tests/helpers`` (``from helpers.synthetic_rig
import make_dataset``; ``helpers.paths`` for the repository's root and the tests' data, whatever folder a test
sits in).

The test modules sit in folders that mirror s3k's rooms (``tests/cli``, ``tests/data``, ``tests/detector``,
..., ``tests/model`` for ``s3k/model.py`` and ``s3k/networks.py``) and ``tests/repo`` for the repository-wide
checks (layout, docs, README figures, setup script, benchmark scripts); ``tests/data/old_runs`` holds run
folders of an older s3k. The folders have no ``__init__.py``: pytest's default import mode imports each test
module by its file name alone, so every ``test_*.py`` name is unique across ``tests/`` (pytest stops at
collection on a second one). A test module imports no other test module: what several share is a helper
(``tests/helpers``) or a fixture here."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from helpers.recordings import write_import_recording
from helpers.synthetic_rig import CAMERAS, KEYPOINTS, make_dataset
from helpers.tiny_detector import save_run
from helpers.track_rig import write_track_recording

from s3k.detector import DetectorMeta
from s3k.model import UNetConfig

DEVICES = ["cpu", pytest.param("cuda", marks=[pytest.mark.cuda, pytest.mark.skipif(
    not torch.cuda.is_available(), reason="no CUDA GPU on this machine")])]


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory) -> Path:
    """A dataset folder of the synthetic rig: 32 px images, 3 labelled, 3 unlabelled and 2 test frames of 4
    cameras. Shared by the session: a test must not change it (a training may add its image cache)."""
    return make_dataset(tmp_path_factory.mktemp("tiny") / "ds", size=32, labelled=3, unlabelled=3, test=2)


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory) -> Path:
    """A run folder holding an untrained detector of the synthetic rig's keypoints and cameras (32 px, a
    two-level U-Net); shared by the session, read only."""
    meta = DetectorMeta(keypoints=list(KEYPOINTS), cameras=list(CAMERAS), image_size=(32, 32), stride=2,
                        sigma=2.0, model=UNetConfig(channels=(8, 8), res_blocks=1).to_dict())
    return save_run(tmp_path_factory.mktemp("tiny") / "run", meta, seed=0)


@pytest.fixture(scope="session")
def track_recording(tmp_path_factory) -> dict:
    """The tiny rig of ``s3k track``'s tests (:mod:`helpers.track_rig`): mp4 videos of the three moving dots,
    its ``calibration.toml`` and a run folder of an untrained detector; shared by the session, read only (a
    test that needs another run passes ``dict(track_recording, run=...)``)."""
    return write_track_recording(tmp_path_factory.mktemp("track"))


@pytest.fixture(scope="session")
def import_recording(tmp_path_factory) -> dict:
    """What ``s3k import`` reads (:func:`helpers.recordings.write_import_recording`): a 3-camera rig in mm,
    ffv1 videos, SLEAP files and DLC CSVs of the same projected 3D points; shared by the session, read
    only."""
    return write_import_recording(tmp_path_factory.mktemp("recording"))


@pytest.fixture(params=DEVICES)
def device(request) -> torch.device:
    """Each device a tensor function runs on: the CPU, and a CUDA GPU where there is one."""
    return torch.device(request.param)


@pytest.fixture(params=[torch.float32, torch.float64], ids=["float32", "float64"])
def dtype(request) -> torch.dtype:
    """Each float type a tensor function works in."""
    return request.param
