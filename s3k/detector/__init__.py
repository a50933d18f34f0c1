"""A trained detector: the run folder it lives in, what it needs at inference, and :class:`Detector`, the one
object every part of s3k (and a user's program) goes through to use it.

- :mod:`s3k.detector.model_file`: a run's model files and the one safe reader of s3k's ``.pt`` files;
- :mod:`s3k.detector.meta`: :class:`DetectorMeta`, the settings it was trained with;
- :mod:`s3k.detector.crop_rule`: the crop rule of a two-pass run and the one crop-centre rule;
- :mod:`s3k.detector.detector`: :class:`Detector` (one pass or two) on frames of any size, on any device.
"""

from s3k.detector.crop_rule import (
    TWO_PASS_FILE,
    CropRule,
    crop_centres,
    extent_middle,
    is_two_pass,
    read_two_pass,
    write_two_pass,
)
from s3k.detector.detector import (
    PRECISIONS,
    Detection,
    Detector,
    OnePassDetector,
    TwoPassDetector,
    autocast,
    native_bfloat16,
    pick_device,
    training_precision,
)
from s3k.detector.meta import DetectorMeta
from s3k.detector.model_file import (
    CHECKPOINT_FILE,
    CONFIG_FILE,
    LOG_FILE,
    MODEL_FILE,
    MODEL_FORMAT,
    PROGRESS_FILE,
    RUN_FILES,
    TENSORBOARD_DIR,
    atomic_save,
    build_model,
    load_network,
    load_torch_file,
    save_model_file,
)
from s3k.detector.over_frames import detect_store, evaluate_store, scored_views, split_frames

__all__ = [
    "CHECKPOINT_FILE", "CONFIG_FILE", "LOG_FILE", "MODEL_FILE", "MODEL_FORMAT", "PRECISIONS",
    "PROGRESS_FILE", "RUN_FILES", "TENSORBOARD_DIR", "TWO_PASS_FILE", "CropRule", "Detection", "Detector",
    "DetectorMeta", "OnePassDetector", "TwoPassDetector", "atomic_save", "autocast", "build_model",
    "crop_centres", "detect_store", "evaluate_store", "extent_middle", "is_two_pass", "load_network",
    "load_torch_file", "native_bfloat16", "pick_device", "read_two_pass",
    "save_model_file", "scored_views", "split_frames", "training_precision", "write_two_pass",
]
