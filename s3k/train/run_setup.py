"""The set-up of a training run: the dataset opened at the network's size and the frames each role uses, the
checks that refuse a run before anything is written, the detector's meta, the run folder and its log."""

from __future__ import annotations

import contextlib
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from s3k.base.errors import UserError
from s3k.budget import check_fits
from s3k.config import TrainConfig
from s3k.data import Dataset, usable_label_count
from s3k.data.frames import open_dataset
from s3k.data.protocol import DatasetLike
from s3k.detector import CHECKPOINT_FILE, DetectorMeta
from s3k.detector.geometry_record import dataset_identity, training_geometry
from s3k.geometry.warp import model_image_size
from s3k.model import UNetConfig
from s3k.run_folder import RunFolder
from s3k.train import checkpoint as ckpt
from s3k.train import out_folder
from s3k.train.distributed import DistInfo

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------------------------------------
# Logging


class _TqdmHandler(logging.Handler):
    def emit(self, record: logging.LogRecord) -> None:
        with contextlib.suppress(Exception):
            tqdm.write(self.format(record))


def setup_logging(run_dir: Path | None, main: bool) -> None:
    """The training room's logger (``s3k.train``, the parent of its modules' loggers) writes to the run's
    log file and the console while the run goes, and nowhere else (to the console alone without
    ``run_dir``: a two-pass run between its passes)."""
    room = logging.getLogger("s3k.train")
    room.setLevel(logging.INFO)
    room.propagate = False
    for h in list(room.handlers):
        if getattr(h, "_s3k", False):
            room.removeHandler(h)
            h.close()
    handlers: list[logging.Handler] = [logging.NullHandler()]
    if main:
        th = _TqdmHandler()
        th.setFormatter(logging.Formatter("%(levelname)s %(message)s"))
        handlers = [th]
        if run_dir is not None:
            fh = logging.FileHandler(RunFolder(run_dir).log)
            fh.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s", "%Y-%m-%d %H:%M:%S"))
            handlers.insert(0, fh)
    for h in handlers:
        h._s3k = True  # type: ignore[attr-defined]
        room.addHandler(h)


# ------------------------------------------------------------------------------------------------------------
# Set-up


@dataclass
class _Data:
    """The dataset opened once at the network's input size, and the frames each role uses."""

    ds: DatasetLike
    source_size: tuple[int, int]
    labelled: np.ndarray
    unlabelled: np.ndarray
    val: np.ndarray


def data_path(data: str | os.PathLike | DatasetLike) -> Path:
    """The folder of ``data``: a dataset folder, or the source folder of a dataset held in memory."""
    return Path(data) if isinstance(data, (str, os.PathLike)) else Path(data.path)


def _open_at_network_size(data: str | os.PathLike | DatasetLike,
                          cfg: TrainConfig) -> tuple[DatasetLike, tuple[int, int]]:
    """``data`` opened at the network's input size, and its own image size."""
    ds = open_dataset(data)
    source_size = (int(ds.image_size[0]), int(ds.image_size[1]))
    check_fits(cfg, cameras=len(ds.cameras), keypoints=len(ds.keypoints), source_size=source_size,
               frames=[len(ds.frames(split)) for split in ("labelled", "unlabelled", "test")],
               where=str(data_path(data)))  # before any frame is decoded or file written
    return ds.resized(model_image_size(source_size, cfg.model.image_size, cfg.model.stride)), source_size


def check_trained_as(data: str | os.PathLike | DatasetLike, out: str | Path,
                     cfg: TrainConfig) -> dict[str, list[Any]]:
    """Check that the run in ``out`` was trained on ``data`` (a folder, or a dataset already open) with
    ``cfg``, as ``--resume`` checks a run it continues (every field but ``s3k.config.resumable_fields``, and
    the dataset's identity); returns the resumable fields that differ, ``{field: [there, here]}``.

    Raises:
        UserError: naming the first field or dataset property that differs where it must not.
    """
    ds, _ = _open_at_network_size(data, cfg)
    return out_folder.check_resume(Path(out), cfg, dataset_identity(ds), data_path(data))


def open_data(data: str | os.PathLike | DatasetLike, cfg: TrainConfig) -> _Data:
    """Open ``data`` at the network's size; refuse a dataset this configuration cannot train on."""
    ds, source_size = _open_at_network_size(data, cfg)
    labelled = np.asarray(ds.frames("labelled"))
    if len(labelled) == 0:
        raise UserError(f"{data}: the 'labelled' split is empty; training needs labelled frames")
    if usable_label_count(ds, "labelled") == 0:
        raise UserError(f"{data}: none of the {len(labelled)} labelled frames gives a training target (a "
                        "keypoint labelled in >= 2 cameras, triangulated, projecting inside an image)",
                        hint="check the labels and the calibration with 's3k validate'")
    unlabelled = np.asarray(ds.frames("unlabelled"))
    if cfg.self_supervision.unsup and len(unlabelled) == 0:
        raise UserError(f"{data}: the 'unlabelled' split is empty, S3K needs unlabelled frames",
                        hint="add unlabelled frames or pass --no-unsup for the labels-only baseline")
    return _Data(ds, source_size, labelled, unlabelled, _validation_frames(ds, cfg, labelled, unlabelled))


def _validation_frames(ds: DatasetLike, cfg: TrainConfig, labelled: np.ndarray,
                       unlabelled: np.ndarray) -> np.ndarray:
    """``--val-frames`` frames spread evenly over ``--val-split`` (over the unlabelled frames, else the
    labelled ones, when that split is empty). Never a frame of a held-out session (one with no labelled or
    unlabelled frame, ``s3k import --test-sessions``): the run's confidence is calibrated on its validation
    frames, and a held-out session stays unseen by everything a training does."""
    split, count = cfg.monitoring.val_split, cfg.monitoring.val_frames
    known = split in ("labelled", "unlabelled", "test")
    val = np.asarray(ds.frames(split)) if known else np.zeros(0, np.int64)
    if len(val) and isinstance(ds, Dataset) and len(ds.sessions) > 1:
        trained = np.unique(ds.session_of(np.concatenate([labelled, unlabelled])))
        val = val[np.isin(ds.session_of(val), trained)]
    if len(val) == 0:
        val = unlabelled if len(unlabelled) else labelled
    return val[np.linspace(0, len(val) - 1, min(count, len(val))).astype(int)]


def frames_used(ds: DatasetLike, cfg: TrainConfig) -> np.ndarray:
    """The frames a training of ``cfg`` on ``ds`` reads, in ``ds``'s order: the labelled ones, the unlabelled
    ones when the self-supervised term is on, and the validation frames."""
    labelled, unlabelled = np.asarray(ds.frames("labelled")), np.asarray(ds.frames("unlabelled"))
    used = [labelled, _validation_frames(ds, cfg, labelled, unlabelled)]
    used += [unlabelled] if cfg.self_supervision.unsup else []
    everything = ds.frames()
    return everything[np.isin(everything, np.concatenate(used))]


def reference_layout(data: Path, layout: torch.Tensor, cfg: TrainConfig) -> torch.Tensor | None:
    """The labelled keypoints' distances ``layout`` (:func:`labelled_distances`) when ``--layout-tol``
    holds pseudo-labels to them (None when off)."""
    if not (cfg.self_supervision.unsup and cfg.self_supervision.layout_tol > 0):
        return None
    if not bool(torch.isfinite(layout).any()):
        raise UserError(f"{data}: no labelled frame has two keypoints triangulated from its labels, so "
                        "--layout-tol has no layout to hold the pseudo-labels to",
                        hint="label two keypoints in two cameras of a frame, or leave --layout-tol at 0")
    return layout


def detector_meta(d: _Data, cfg: TrainConfig, distances: torch.Tensor) -> DetectorMeta:
    """What inference needs; a rigid object's labelled layout (``--layout-tol``) goes into the read-out."""
    m, s = cfg.model, cfg.self_supervision
    rigid = s.layout_tol > 0 and bool(torch.isfinite(distances).any())
    return DetectorMeta(
        keypoints=list(d.ds.keypoints), cameras=list(d.ds.cameras), image_size=d.ds.image_size,
        stride=m.stride, sigma=cfg.sigma_px(),
        model=UNetConfig(channels=m.channels, res_blocks=m.res_blocks, stride=m.stride, norm=m.norm,
                         encoder=cfg.backbone.encoder, encoder_stride=cfg.backbone.encoder_stride).to_dict(),
        units=d.ds.units, source_image_size=d.source_size, outlier_px=s.outlier_px,
        layout=distances.tolist() if rigid else None, layout_tol=s.layout_tol if rigid else 0.0,
        geometry=training_geometry(d.ds), skeleton=list(getattr(d.ds, "skeleton", [])),
    )


def start_run(data: Path, out: Path, cfg: TrainConfig, d: _Data, meta: DetectorMeta, resume: bool,
               overwrite: bool, command: str | None, info: DistInfo) -> dict[str, Any] | None:
    """Check the run folder (and the run being resumed) then write its configuration; returns the
    checkpoint to resume from, or None. Nothing is written unless every check passes."""
    ckpt_path = out / CHECKPOINT_FILE
    state = ckpt.load_checkpoint(ckpt_path) if resume and ckpt_path.is_file() else None
    if not info.main:
        return state
    identity = dataset_identity(d.ds)
    changed = out_folder.check_resume(out, cfg, identity, data) if state is not None else {}
    if overwrite:
        out_folder.clear_run(out)
    out.mkdir(parents=True, exist_ok=True)
    setup_logging(out, info.main)
    out_folder.write_start(out, cfg, meta, data, identity, state is not None, changed, command)
    if changed:
        log.info("resumed with changed settings: %s",
                 ", ".join(f"{k} {a!r} -> {b!r}" for k, (a, b) in changed.items()))
    return state


def log_sessions(ds: DatasetLike, labelled: np.ndarray, unlabelled: np.ndarray) -> None:
    """Log what each session of a dataset of several gives the training (its labelled and unlabelled frames;
    each frame is triangulated with its own session's cameras)."""
    if not isinstance(ds, Dataset) or len(ds.sessions) < 2:
        return
    lab, unl = ds.session_of(labelled), ds.session_of(unlabelled)
    log.info(f"{len(ds.sessions)} sessions, each frame with its own session's cameras: " + ", ".join(
        f"{name} ({int((lab == name).sum())} labelled, {int((unl == name).sum())} unlabelled)"
        for name in ds.sessions))
