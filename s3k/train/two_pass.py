"""The coarse-to-fine detector: a coarse pass on the whole image, a refining pass on scale-normalized crops.

A two-pass run folder holds two ordinary runs of ``s3k train`` and the crop rule that joins them::

    RUN/two_pass.json    the crop rule (extent in world units, crop size in pixels) and the passes' folders
    RUN/coarse/          the coarse detector: the whole image, resized to ``coarse_size`` px
    RUN/estimates.csv    the coarse pass's 3D keypoints for the frames the refining pass reads (labelled,
                         unlabelled for S3K, validation; every frame with ``keep_crops``)
    RUN/fine/            the refining detector, trained on crops around those estimates with the same
                         losses (its pixel tolerances scaled to the crop size: :func:`refining_config`)
    RUN/cpu.json         CPU seconds each stage took: ``coarse`` (its training), ``crops`` (the estimates
                         and the crops) and ``fine``, summed over the attempts of a resumed run
    RUN/crops/           the crops as a dataset folder, only with ``keep_crops`` (``--keep-crops``)

The crops are cut in memory (:func:`s3k.data.crops.cut_crops`) and the refining pass trains on them there:
nothing is written between the passes but the estimates, from which a resumed run cuts the same crops
again. A run whose ``RUN/crops/`` was written trains its refining pass on that folder.

The crop of a frame is centred on the middle of its coarse keypoints' extent (the midpoint of the two that
are farthest apart), not on their mean: a mean lies towards where keypoints cluster and can leave an
outlying keypoint at the crop's edge, where a truncated heatmap pulls its estimate inwards. The crop's side,
in world units, is fixed for the run (:func:`crop_rule_from_labels`): twice the largest distance of a
labelled keypoint from that middle, plus a margin for the coarse pass's error. Every view's crop covers that
extent at the centre's depth and is resampled to ``size`` px, so the object has the same size in every crop
whatever the camera's distance or focal length, and each camera becomes ``K' = M K``. The same rule makes
the crops at training (labelled and unlabelled frames) and at inference (``s3k evaluate``, ``s3k predict``,
``s3k track``).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import os
import shutil
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from s3k.base.choices import Device
from s3k.base.errors import UserError
from s3k.base.memory import available_memory
from s3k.base.outputs import check_run_folder
from s3k.config import TrainConfig
from s3k.data import Dataset
from s3k.data.crops import CropCutter, cut_crops
from s3k.data.frames import FrameStore
from s3k.data.protocol import DatasetLike
from s3k.data.tracks_csv import csv_rows, read_csv, rows_points, write_csv
from s3k.detector import (
    Detector,
    detect_store,
    is_two_pass,
    load_network,
    load_torch_file,
    read_two_pass,
    split_frames,
)
from s3k.detector.crop_rule import CropRule, extent_middle, write_two_pass
from s3k.geometry import triangulate_labels
from s3k.run_folder import RunFolder
from s3k.train.loop import TrainResult, train_one_pass
from s3k.train.out_folder import check_config
from s3k.train.run_setup import check_trained_as, frames_used, setup_logging
from s3k.train.two_pass_start import crop_extent_warning

__all__ = ["coarse_estimates", "crop_rule_from_labels", "estimates_and_crops", "train_two_pass",
           "training_crops", "write_crops"]

log = logging.getLogger(__name__)


def crop_rule_from_labels(dataset: DatasetLike, size: int, margin: float = 0.3) -> CropRule:
    """The run's crop rule from the labelled frames' triangulated labels (never from ground truth).

    ``extent = 2 * r * (1 + margin)`` with ``r`` the largest distance of a labelled keypoint from the middle
    of its frame's keypoints' extent: a crop centred on a perfect estimate holds every keypoint with
    ``margin * r`` to spare on each side, the room left for the coarse pass's error.

    Raises:
        UserError: no labelled frame has two triangulated keypoints.
    """
    ids = dataset.frames("labelled")
    radius = 0.0
    if len(ids):
        uv, mask = dataset.labels(ids)
        X, valid = triangulate_labels(dataset.calibration(ids, dtype=np.float64), torch.from_numpy(uv),
                                      torch.from_numpy(mask))
        ok = valid.numpy()
        for points in np.where(ok[..., None], X.numpy(), np.nan):
            if np.isfinite(points).all(axis=-1).sum() < 2:
                continue
            c = extent_middle(points)
            radius = max(radius, float(np.nanmax(np.linalg.norm(points - c, axis=-1))))
    if radius <= 0:
        raise UserError(f"{dataset.path}: no labelled frame has two keypoints triangulated from its labels, "
                        "so the crop's extent cannot be set", hint="label at least two keypoints in two "
                        "cameras of a frame, or give the extent with --crop-extent")
    return CropRule(extent=2 * radius * (1 + margin), size=int(size), margin=float(margin))


def coarse_estimates(run_dir: Path, data: Path, out_csv: Path, device: Device | torch.device = "cpu",
                     batch_size: int = 32) -> dict[int, np.ndarray]:
    """The coarse pass's 3D keypoints of every frame of ``data`` (:class:`s3k.detector.Detector` on the
    frames at the dataset's resolution, on ``device``), written once to ``out_csv`` and read back."""
    if out_csv.is_file():  # written by an earlier attempt: the networks need not be loaded
        return read_csv(out_csv, RunFolder(run_dir).read_record()["meta"]["keypoints"])
    detector = Detector.load(run_dir, device)
    ds = Dataset.open(data, cache="none")
    store = FrameStore(ds, split_frames(ds, "all"), preload_mb=0)
    tmp = out_csv.with_name(out_csv.name + ".part")
    with write_csv(tmp, detector.keypoints) as writer:
        for batch, pred in detect_store(detector, store, batch_size):
            writer.writerows(csv_rows(batch.frame_ids.tolist(), pred))
    tmp.replace(out_csv)
    return read_csv(out_csv, detector.keypoints)


def estimates_and_crops(run_dir: Path, ds, out_csv: Path, rule: CropRule,
                        device: Device | torch.device = "cpu", batch_size: int = 32,
                        frames: np.ndarray | None = None):
    """The coarse pass's estimates of every frame of ``ds``, or of ``frames`` (written to ``out_csv``), and
    the crops around them (:func:`training_crops`), each frame decoded once for both. The crops are cut
    around the estimates as the file holds them, so that a resumed run, which cuts them again from the file,
    gets the same crops of the same frames."""
    description = f"crops of {rule.extent:g} {ds.units} around the coarse pass's estimates"
    if out_csv.is_file():  # written by an earlier attempt: the networks need not be loaded
        estimates = coarse_estimates(run_dir, ds.path, out_csv)
        return training_crops(ds, estimates, rule, description=description, frames=list(estimates))
    detector = Detector.load(run_dir, device)
    ids = split_frames(ds, "all")
    store = FrameStore(ds, ids if frames is None else ids[np.isin(ids, frames)], preload_mb=0)
    cutter = CropCutter(ds, rule.extent, rule.size, fallback=True)
    tmp = out_csv.with_name(out_csv.name + ".part")
    K = len(detector.keypoints)
    placed = 0
    with write_csv(tmp, detector.keypoints) as writer:
        for batch, pred in detect_store(detector, store, batch_size):
            rows = csv_rows(batch.frame_ids.tolist(), pred)
            writer.writerows(rows)
            centres = _centres(rows_points(rows, K))  # around the values as written
            placed += len(centres)
            cutter.add(batch.frame_ids, centres, batch.images)
    if not placed:
        tmp.unlink(missing_ok=True)
        _centres({}, ds.path)
    tmp.replace(out_csv)
    return cutter.result(description)


def training_crops(data, estimates: Mapping[int, np.ndarray], rule: CropRule, splits=None,
                   description: str | None = None, frames=None):
    """The crops of ``data`` (of its ``frames`` when given) around ``estimates`` by ``rule``, in memory (a
    :class:`s3k.data.crops.CropDataset`), each frame cut around the crop centre of its estimates
    (:func:`s3k.detector.crop_centres`, the rule the detector applies at inference)."""
    return cut_crops(data, _centres(estimates, data), rule.extent, rule.size, fallback=True, splits=splits,
                     frames=frames, description=description)


def _centres(estimates: Mapping[int, np.ndarray], refuse_empty: Any = None) -> dict[int, np.ndarray]:
    """The crop centre of each frame's estimates (frames without a placed keypoint left out); with
    ``refuse_empty`` (the dataset, for the message) none at all is an error."""
    centres = {}
    for frame, X in estimates.items():
        middle = extent_middle(X)
        if middle is not None:
            centres[int(frame)] = middle
    if not centres and refuse_empty is not None:
        raise UserError(f"the coarse pass placed no keypoint in any frame of {refuse_empty}",
                        hint="train the coarse pass longer (--coarse-steps) or check the labels")
    return centres


def write_crops(data: Path, out: Path, estimates: Mapping[int, np.ndarray], rule: CropRule,
                splits=None, description: str | None = None) -> Path:
    """:func:`training_crops` written as a dataset folder ``out`` (replaced if it exists)."""
    return training_crops(data, estimates, rule, splits, description).write(out, overwrite=True)


def train_two_pass(data: str | Path, out: str | Path, cfg: TrainConfig, *, resume: bool = False,
                   overwrite: bool = False, command: str | None = None, progress=None,
                   init_from: str | Path | None = None):
    """Train a two-pass detector (module docstring) into ``out`` by ``cfg`` (its two-pass section; each pass
    by :meth:`TrainConfig.coarse` and :meth:`TrainConfig.refining`); each stage is skipped when its output is
    complete, so ``resume`` continues a killed run at the stage where it stopped. Called by
    :func:`s3k.train.train` for a configuration with ``two_pass``; its arguments are that function's.

    Returns:
        The refining pass's :class:`s3k.train.TrainResult` (the model, its meta and step), with ``passes``
        ``{"coarse": ..., "fine": ...}``, each pass's result or None when it was complete before this call,
        and ``rule``, the :class:`CropRule`.

    ``init_from`` is a two-pass run whose passes start this run's (fine-tuning; :func:`s3k.train.train`), its
    crops' extent kept unless ``cfg.passes.crop_extent`` is given.
    """
    data, run = Path(data), RunFolder(out)
    cfg.validate()  # every option of both passes is checked before the coarse pass trains
    inits, cfg = _init_passes(init_from, cfg)
    check_run_folder(run.path, resume, overwrite, whole=True)  # --overwrite deletes the folder: a run's files
    if run.path.exists() and not resume and not run.is_stub():  # a start that trained nothing is not kept
        if not overwrite:
            raise UserError(f"{run.path} exists",
                            hint="pass --resume to continue it or --overwrite to replace it")
        if not run.is_two_pass_run():
            raise UserError(f"{run.path} is not a two-pass run; refusing to delete it",
                            hint="choose another --out")
    if run.path.exists() and not resume:
        shutil.rmtree(run.path)
    if resume and run.is_two_pass() and run.coarse.model.is_file() and run.fine.model.is_file():
        return _finished(data, run, cfg)  # nothing to train: checked, and left as it is
    run.path.mkdir(parents=True, exist_ok=True)
    if not run.options_file.is_file():
        run.write_config(cfg)
    try:
        result = _train_two_pass(data, run, cfg, command, progress, inits)
    except BaseException:
        if run.is_stub():  # nothing trained: leave no folder that a retry would have to get past
            shutil.rmtree(run.path, ignore_errors=True)
        raise
    run.write_config(cfg)  # what --resume takes: the configuration of the last call that completed
    return result


def _train_two_pass(data: Path, run: RunFolder, cfg: TrainConfig, command: str | None, progress,
                    inits: tuple[Path, Path] | None = None):
    console = functools.partial(setup_logging, None, os.environ.get("RANK", "0") == "0")
    console()  # between the passes the log goes to the console alone
    ds = Dataset.open(data, cache="none")
    rule = _crop_rule(ds, cfg)
    passes: dict[str, Any] = {}
    coarse_data: Any = data
    # a coarse pass still to train decodes the frames; the coarse pass reads the same disk cache as from the
    # folder
    if not run.coarse.model.is_file() and _hold_frames(ds, cfg):
        coarse_data = ds.with_cache("disk")
    with _StageClock(run, "coarse", progress) as clock:
        passes["coarse"] = _train_pass(train_one_pass, coarse_data, run.coarse, cfg.coarse(), command,
                                       "coarse pass", clock, inits[0] if inits else None)
    console()
    with _StageClock(run, "crops"):
        if (run.crops / "s3k.json").is_file():  # written by an earlier call: the refining pass trains on them
            _check_crops(run.crops, rule)
            crops: Any = run.crops
        else:
            _check_rule(run, rule)
            # the frames the refining pass reads, or every frame for a crop dataset written to keep
            used = ds.frames() if cfg.passes.keep_crops else frames_used(ds, cfg.refining(rule.size))
            log.info(f"coarse pass: estimating the {len(used)} frames of {data} the refining pass reads and "
                     f"cropping them in memory ({rule.extent:g} {ds.units} -> {rule.size} px)")
            crops = estimates_and_crops(run.coarse.path, ds, run.estimates, rule, cfg.execution.device,
                                        frames=used)
            if cfg.passes.keep_crops:
                crops.write(run.crops, overwrite=True)
                log.info(f"crops written to {run.crops}")
    ds.release_frames()
    with _StageClock(run, "fine", progress) as clock:
        passes["fine"] = _train_pass(train_one_pass, crops, run.fine, cfg.refining(rule.size), command,
                                     "refining pass", clock, inits[1] if inits else None)
    write_two_pass(run.path, rule, cfg.passes.coarse_size, ds.keypoints)
    return _result(run, passes, rule)


def _crop_rule(ds: Dataset, cfg: TrainConfig) -> CropRule:
    """The crops' rule: ``--crop-extent`` when given, else from the labels' spread (with a warning where the
    crops would be too coarse)."""
    p = cfg.passes
    rule = (CropRule(float(p.crop_extent), int(p.crop_size), 0.0) if p.crop_extent is not None
            else crop_rule_from_labels(ds, p.crop_size, p.crop_margin))
    if p.crop_extent is None and (too_large := crop_extent_warning(ds, rule.extent, rule.size,
                                                                   p.coarse_size)):
        log.warning(too_large)
    return rule


def _finished(data: Path, run: RunFolder, cfg: TrainConfig):
    """``--resume`` of a complete run: each pass checked as the call would train it (the refining pass's
    configuration alone: its crops follow from the coarse pass, the dataset and the crop rule, all checked),
    nothing computed again and nothing written."""
    setup_logging(None, os.environ.get("RANK", "0") == "0")
    ds = Dataset.open(data, cache="none")
    rule = _crop_rule(ds, cfg)
    _check_complete("coarse pass", run.coarse.path,  # the dataset as opened for the rule, not read again
                    lambda: check_trained_as(ds, run.coarse.path, cfg.coarse()))
    _check_rule(run, rule)
    _check_complete("refining pass", run.fine.path,
                    lambda: check_config(run.fine.path, cfg.refining(rule.size)))
    return _result(run, {"coarse": None, "fine": None}, rule)


def _init_passes(init_from: str | Path | None, cfg: TrainConfig
                 ) -> tuple[tuple[Path, Path] | None, TrainConfig]:
    """The passes of the two-pass run ``init_from`` that start this run's, and the configuration with the
    crops' extent of that run (unless ``cfg`` sets one)."""
    if init_from is None:
        return None, cfg
    if not is_two_pass(init_from):
        raise UserError(f"--init-from {init_from}: not a two-pass run", hint="fine-tune a --two-pass run "
                        "with --two-pass, a one-pass run without it")
    rule, coarse, fine = read_two_pass(init_from)
    return (coarse, fine), cfg if cfg.passes.crop_extent is not None else cfg.replace(crop_extent=rule.extent)


def _result(run: RunFolder, passes: dict[str, Any], rule: CropRule):
    """The run's :class:`TrainResult`: the refining pass's, loaded from its folder when it was complete."""
    fine = passes["fine"]
    if fine is None:
        model, meta = load_network(run.fine.path)
        fine = TrainResult(model.train(), meta, int(_model_step(run.fine)), "done")
    return dataclasses.replace(fine, passes=passes, rule=rule)


def _model_step(run: RunFolder) -> int:
    return int(load_torch_file(run.model, "model", ("step",))["step"])


def _hold_frames(ds: Dataset, cfg: TrainConfig) -> bool:
    """Keep the frames the coarse pass decodes in memory for the crops (:meth:`s3k.data.Dataset.hold_frames`)
    when they take at most half the memory available now and ``--preload-mb`` is not 0; otherwise the crops
    decode them again."""
    have = available_memory()
    if cfg.execution.preload_mb == 0 or have is None or ds.stored_mib > have / 2**20 / 2:
        log.info(f"the crops will decode the frames again: the {ds.stored_mib:.0f} MiB of full-resolution "
                 f"frames are not kept in memory "
                 f"({'--preload-mb 0' if cfg.execution.preload_mb == 0 else 'too little memory'})")
        return False
    ds.hold_frames()
    log.info(f"keeping the coarse pass's frames at full resolution in memory for the crops (up to "
             f"{ds.stored_mib:.0f} MiB)")
    return True


def _check_rule(run: RunFolder, rule: CropRule) -> None:
    """Refuse a crop rule other than the one a complete run recorded, or a crop size other than the one its
    refining pass was started at (another extent there changes the crops' calibration, which ``--resume``
    refuses)."""
    if run.is_two_pass():
        done, _, _ = read_two_pass(run.path)
        extent, size = done.extent, done.size
    elif run.fine.config_file.is_file():
        extent, size = rule.extent, int(run.fine.read_record()["meta"]["image_size"][0])
    else:
        return
    if int(size) != rule.size or not np.isclose(float(extent), rule.extent, rtol=1e-6, atol=0.0):
        raise UserError(f"{run.path}: the refining pass was trained on crops {float(extent):g} wide at "
                        f"{int(size)} px; this call cuts {rule.extent:g} at {rule.size} px",
                        hint="repeat the --crop-size, --crop-margin and --crop-extent the run was trained "
                             "with, or pass --overwrite to train both passes again")


def _check_crops(crops: Path, rule: CropRule) -> None:
    """Refuse existing crops cut by another rule than this call's (another --crop-size, margin or extent)."""
    source = json.loads((crops / "s3k.json").read_text()).get("source") or {}
    extent, size = source.get("extent"), source.get("size")
    if extent is None or size is None:
        return  # crops written before the rule was recorded with them
    if int(size) != rule.size or not np.isclose(float(extent), rule.extent, rtol=1e-6, atol=0.0):
        raise UserError(f"{crops} were cut {float(extent):g} wide at {int(size)} px; this call cuts "
                        f"{rule.extent:g} at {rule.size} px",
                        hint="repeat the --crop-size, --crop-margin and --crop-extent the run was trained "
                             "with, or pass --overwrite to train both passes again")


class _StageClock:
    """Adds the CPU time this process spends in a stage to ``RUN/cpu.json``: when the stage ends, and every
    ``every`` training steps meanwhile (:meth:`tick`, a training callback that also calls ``progress``), so a
    killed attempt's time up to its last tick is kept. Only the main process of a distributed run writes."""

    def __init__(self, run: RunFolder, stage: str, progress=None, every: int = 50) -> None:
        self.run, self.stage, self.progress, self.every = run, stage, progress, every
        self.writes = os.environ.get("RANK", "0") == "0"

    def __enter__(self) -> _StageClock:
        self.before = self.run.read_cpu().get(self.stage, 0.0)
        self.started = time.process_time()
        return self

    def tick(self, step: int, terms=None) -> None:
        if step % self.every == 0:
            self._write()
        if self.progress is not None:
            self.progress(step, terms)

    def _write(self) -> None:
        if not self.writes:
            return
        spent = self.run.read_cpu()
        spent[self.stage] = self.before + time.process_time() - self.started
        self.run.write_cpu(spent)

    def __exit__(self, *exc) -> None:
        self._write()


def _check_complete(what: str, path: Path, changes) -> None:
    """Refuse a complete pass that ``changes()`` (the resumable fields that differ; it raises on the others)
    says was trained otherwise than this call would train it."""
    try:
        changed = changes()
        if "steps" in changed:  # a finished pass is not continued: it would be kept at its steps
            raise UserError(f"steps is {changed['steps'][1]} now but {changed['steps'][0]} there")
    except UserError as e:
        raise UserError(f"{what} {path} is complete but not what this call would train "
                        f"({e.message.removeprefix('--resume: ')})",
                        hint="repeat the options it was trained with, or pass --overwrite to train both "
                             "passes again") from None
    log.info(f"{what}: {path} is complete")


def _train_pass(train, data, run: RunFolder, cfg: TrainConfig, command, what: str, clock: _StageClock,
                init_from: Path | None = None):
    """Train one pass unless its model exists (then None, after checking it was trained as this call would
    train it); resume a pass whose folder exists."""
    if run.model.is_file():
        _check_complete(what, run.path, lambda: check_trained_as(data, run.path, cfg))
        return None
    log.info(f"{what}: training {run.path}")
    result = train(data, run.path, cfg, resume=run.path.exists(), progress=clock.tick, command=command,
                   init_from=init_from)
    if result.status != "done":
        raise UserError(f"{what} stopped ({result.status}); see {run.log}",
                        hint="fix what the log says and continue with --resume")
    return result
