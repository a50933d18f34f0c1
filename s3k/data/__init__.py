"""The dataset layer: the folder format, its loader and writer, importers, image and video sources.

Import the public names from here (``from s3k.data import Dataset``); the modules behind them may move.

Modules, one job each:

- :mod:`~s3k.data.problems`: what the checks find (``Problem``, ``DatasetError``, ``DatasetWarning``).
- :mod:`~s3k.data.tables`: readers of ``s3k.json``, ``frames.csv``, ``labels.csv``, ``points3d.csv``.
- :mod:`~s3k.data.cameras`: readers and checks of ``calibration.json`` / ``calibration.csv``.
- :mod:`~s3k.data.images`: decoding one image file (``decode_image``, ``ImageReadError``).
- :mod:`~s3k.data.sources`: image sources (PNG files, videos; ``register_image_source`` for more).
- :mod:`~s3k.data.cache`: the decoded-image cache.
- :mod:`~s3k.data.dataset`: ``Dataset`` (open, validate, serve frames).
- :mod:`~s3k.data.checks`: ``check_dataset`` (every check, problems collected instead of raised).
- :mod:`~s3k.data.usable`: which labels give the supervised loss a target (``usable_labels``).
- :mod:`~s3k.data.writer`: ``DatasetWriter``.
- :mod:`~s3k.data.validate`: the report of ``s3k validate``.
- :mod:`~s3k.data.rig`: ``Rig``, a calibration file's content (names, sizes, units, ``Cameras``).
- :mod:`~s3k.data.formats`: other tools' files, one module per format (calibrations, 2D labels, 3D tracks;
  ``label_export`` writes labels back out); :mod:`~s3k.data.recording` (``import_recording``: a recording to a
  dataset) and :mod:`~s3k.data.import_choices` (its choices of image size and splits);
  :mod:`~s3k.data.splits` (test frames held out in time, or whole sessions), :mod:`~s3k.data.sessions` (a
  dataset's recordings: each frame's session, each session's rig and metadata) and
  :mod:`~s3k.data.add_session` (``s3k import --into``: a recording or dataset added as a session).
- :mod:`~s3k.geometry.warp` (crop/resize maps), :mod:`~s3k.data.video` (video I/O) and
  :mod:`~s3k.data.imageseq` (image sequences read in place of videos).
"""

from s3k.data.checks import check_dataset
from s3k.data.dataset import Dataset
from s3k.data.images import ImageReadError
from s3k.data.problems import DatasetError, DatasetWarning, Problem
from s3k.data.rig import Rig
from s3k.data.sources import register_image_source
from s3k.data.tables import SPLITS
from s3k.data.usable import usable_label_count, usable_labels
from s3k.data.writer import DatasetWriter

__all__ = [
    "SPLITS",
    "Dataset",
    "DatasetError",
    "DatasetWarning",
    "DatasetWriter",
    "ImageReadError",
    "Problem",
    "Rig",
    "check_dataset",
    "register_image_source",
    "usable_label_count",
    "usable_labels",
]
