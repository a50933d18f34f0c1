"""s3k: semantic 3D keypoints from a calibrated multi-camera rig (after S3K, Vecerik et al. 2020).

The public objects, imported when first used: :class:`s3k.Detector` (a trained detector on frames of any
size, on any device), :class:`s3k.Cameras`, :class:`s3k.Dataset`, :class:`s3k.TrainConfig` and
:func:`s3k.train`; :class:`s3k.TrackConfig`, :class:`s3k.RigOptions` and :func:`s3k.track` (what ``s3k track``
does, the same files written).
"""

import importlib
from typing import Any

__version__ = "0.1.0"
__all__ = ["Cameras", "Dataset", "Detector", "RigOptions", "TrackConfig", "TrainConfig", "track", "train"]

_PUBLIC = {"Detector": "s3k.detector", "Cameras": "s3k.geometry", "Dataset": "s3k.data",
           "TrainConfig": "s3k.config", "train": "s3k.train", "track": "s3k.inference.track",
           "TrackConfig": "s3k.inference.track_config", "RigOptions": "s3k.inference.session"}


def __getattr__(name: str) -> Any:
    if name == "train":  # the package, callable as its train(): importing it binds it here anyway
        return importlib.import_module("s3k.train")
    if name in _PUBLIC:
        return getattr(importlib.import_module(_PUBLIC[name]), name)
    raise AttributeError(f"module 's3k' has no attribute {name!r}")
