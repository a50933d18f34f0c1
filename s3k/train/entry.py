""":func:`train`, the one way to train a detector, one pass or two, from Python as from ``s3k train``."""

from __future__ import annotations

import os
from pathlib import Path

from s3k.base.errors import UserError
from s3k.config import TrainConfig
from s3k.data.protocol import DatasetLike
from s3k.detector import is_two_pass
from s3k.train.distributed import check_batches, world_size
from s3k.train.loop import TrainResult, train_one_pass
from s3k.train.two_pass import train_two_pass

__all__ = ["train"]


def train(data: str | Path | DatasetLike, out: str | Path, cfg: TrainConfig, *, resume: bool = False,
          progress=None, overwrite: bool = False, command: str | None = None,
          init_from: str | Path | None = None) -> TrainResult:
    """Train a detector on the dataset ``data`` into the run folder ``out`` by ``cfg``: the coarse-to-fine
    detector when ``cfg.passes.two_pass`` (:mod:`s3k.train.two_pass`), else one network on the whole image
    (:mod:`s3k.train.loop`). The run folder's files: :class:`s3k.run_folder.RunFolder`.

    Args:
        data: dataset folder (``s3k.data``), with labelled and (for S3K) unlabelled frames; or, for one pass,
            a dataset held in memory (:class:`s3k.data.crops.CropDataset`).
        out: run folder (created).
        cfg: the configuration, e.g. ``preset("box-fast").replace(seed=1)`` (:mod:`s3k.train.presets`).
        resume: continue the run in ``out`` where it stopped; the configuration and the dataset must match
            the run's except for ``s3k.config.resumable_fields``.
        progress: optional ``f(step, terms)`` called after every completed step of each pass (``terms``: the
            loss terms, alpha, the gradient norm and the step's timings); an exception it raises aborts the
            run like a kill would.
        overwrite: replace the run in ``out`` (only the files a run holds are deleted).
        command: the command line, recorded in the run's history.
        init_from: fine-tuning: a run whose network (same keypoints and architecture) starts this run's
            instead of a random one, with this run's own steps, learning rate and schedule (``--init-from``):
            a one-pass run for one pass; a two-pass run for two, each pass from its pass, the crops' extent
            kept unless ``--crop-extent`` is given. A run resumed from its checkpoint ignores it.

    Returns:
        A :class:`TrainResult` (of a two-pass run: the refining pass's, with both passes' in ``passes``).

    Raises:
        UserError: before anything is written, naming what is wrong.

    Example:
        >>> result = train("data/box", "runs/box", TrainConfig.from_flat(steps=100))  # doctest: +SKIP
        >>> result.status, result.step  # doctest: +SKIP
        ('done', 100)
    """
    # before anything is written
    check_batches(cfg.schedule.batch_labelled, cfg.schedule.batch_unlabelled, cfg.self_supervision.unsup,
                  world_size())
    if cfg.passes.two_pass:
        if resume and overwrite:
            raise UserError("--resume and --overwrite exclude each other", hint="pass one of them")
        if not isinstance(data, (str, os.PathLike)):
            raise UserError("two passes train from a dataset folder, not a dataset held in memory",
                            hint="pass the dataset's folder")
        return train_two_pass(data, out, cfg, resume=resume, overwrite=overwrite, command=command,
                              progress=progress, init_from=init_from)
    if init_from is not None and is_two_pass(init_from):
        raise UserError(f"--init-from {init_from}: a two-pass run", hint="add --two-pass to fine-tune it")
    return train_one_pass(data, out, cfg, resume=resume, progress=progress, overwrite=overwrite,
                          command=command, init_from=init_from)
