"""``s3k train DATASET --out RUN``: semi-supervised training of the keypoint network (S3K).

The losses: docs/method.md#losses.

Each step draws a labelled batch and, once the self-supervised term is on, an unlabelled batch; both are
augmented per image with a random similarity that updates the intrinsics (``s3k.train.augment``), go through
the network in one forward pass, and give

    L = L_sup + alpha(step) * L_unsup + weight_decay * ||theta_non-bias||^2.

``alpha(step)`` is 0 for ``warmup_steps`` labels-only steps, then rises linearly to ``alpha`` over
``ramp_steps`` (``TrainConfig.alpha_at``): from a random network the self-supervised term would lock in a
collapse (every keypoint at one confident 3D point), so the labels first shape the heatmaps. When warm-up and
ramp together outlast ``steps`` both shrink in proportion to end at the last step
(``TrainConfig.unsup_schedule``); the log names the step where the term switches on. ``--no-unsup``
trains the labels-only baseline: same network, same labels, no unlabelled batch.

Robustness:

- a step whose loss or gradient is not finite is reported with its step number in the log and skipped
  (parameters, optimizer and normalization statistics unchanged); after ``max_nonfinite`` consecutive ones
  the run stops cleanly with exit status 1; such a state is never checkpointed.
- ``RUN/checkpoint.pt`` (written atomically, read with ``weights_only=True``) holds the model, optimizer,
  scheduler, every rank's RNG states and the step; ``--resume`` continues a killed run exactly where its last
  checkpoint left it, after checking that the configuration and the dataset are the run's.

The rooms:

- :mod:`s3k.train.entry`: :func:`train`, one pass or two.
- :mod:`s3k.train.loop`: :func:`train_one_pass` and the loop (steps, logging, checkpoints, stops).
- :mod:`s3k.train.two_pass`: the coarse-to-fine detector's training.
- :mod:`s3k.train.fine_tune`: a fine-tune's configuration (``--init-from RUN``): RUN's, continued where it
  ended.
- :mod:`s3k.train.step`: the loss of one step (:func:`compute_losses`) and the learning-rate schedule.
- :mod:`s3k.train.run_setup`: the set-up of a run (the dataset and its frames, the refusals, the run's meta,
  folder and log; :func:`check_trained_as`).
- :mod:`s3k.train.checkpoint`: the checkpoint format, its one writer and one reader.
- :mod:`s3k.train.out_folder`: the checks of ``--out`` before anything is written, ``--resume`` compatibility,
  history.
- :mod:`s3k.train.sampling`: random batches, augmented, on the device.
- :mod:`s3k.train.validation`: periodic validation and the labelled layout it compares with.
- :mod:`s3k.train.distributed`: DDP helpers (under ``torchrun --nproc-per-node N`` the ranks train what one
  process trains: each draws the whole global batch and passes its own part; only rank 0 writes logs and
  checkpoints).
"""

import sys
import types
from typing import Any

from s3k.train.checkpoint import load_checkpoint, read_checkpoint_step
from s3k.train.distributed import DistInfo, init_distributed
from s3k.train.entry import train
from s3k.train.loop import TrainResult, train_one_pass
from s3k.train.run_setup import check_trained_as
from s3k.train.sampling import draw_batch, prepare
from s3k.train.step import compute_losses
from s3k.train.validation import labelled_distances, labelled_layout, mean_pairwise_distance, validate

__all__ = [
    "DistInfo", "TrainResult", "check_trained_as", "compute_losses", "draw_batch", "init_distributed",
    "labelled_distances", "labelled_layout", "load_checkpoint", "mean_pairwise_distance", "prepare",
    "read_checkpoint_step", "train", "train_one_pass", "validate",
]


class _CallablePackage(types.ModuleType):
    """``s3k.train`` is both this package and :func:`train`: importing any of its modules binds the package to
    ``s3k.train``, so the package calls :func:`train` and ``s3k.train(...)`` trains whichever it is."""

    def __call__(self, *args: Any, **kwargs: Any) -> TrainResult:
        return train(*args, **kwargs)


sys.modules[__name__].__class__ = _CallablePackage
