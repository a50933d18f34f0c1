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

import json
import os
import shutil
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from s3k.data import Dataset
from s3k.data.cache import available_memory
from s3k.data.crops import CropCutter, cut_crops
from s3k.data.frames import FrameStore
from s3k.data.protocol import DatasetLike
from s3k.data.tracks_csv import csv_rows, read_csv, rows_points, write_csv
from s3k.detector import Detector, read_run_config, read_two_pass
from s3k.detector.crop_rule import CropRule, extent_middle, is_two_pass, write_two_pass
from s3k.errors import UserError
from s3k.fileio import atomic_write_json
from s3k.geometry import triangulate_labels
from s3k.inference.predict import detect_store, split_frames
from s3k.messages import say
from s3k.outputs import check_run_folder
from s3k.ranges import Range
from s3k.train.loop import train
from s3k.train.run_setup import check_trained_as, frames_used
from s3k.train.two_pass_start import OPTIONS_FILE, crop_extent_warning, is_stub, write_options

__all__ = ["CPU_FILE", "ESTIMATES_FILE", "REFERENCE_CROP", "coarse_estimates", "crop_rule_from_labels",
           "estimates_and_crops", "read_cpu", "refining_config", "train_two_pass", "training_crops",
           "write_crops"]

ESTIMATES_FILE = "estimates.csv"  # the coarse pass's 3D keypoints of the frames the refining pass reads
CPU_FILE = "cpu.json"  # CPU seconds per stage ("coarse", "crops", "fine"), summed over a run's attempts


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


def coarse_estimates(run_dir: Path, data: Path, out_csv: Path, device: str | torch.device = "cpu",
                     batch_size: int = 32) -> dict[int, np.ndarray]:
    """The coarse pass's 3D keypoints of every frame of ``data`` (:class:`s3k.detector.Detector` on the
    frames at the dataset's resolution, on ``device``), written once to ``out_csv`` and read back."""
    if out_csv.is_file():  # written by an earlier attempt: the networks need not be loaded
        return read_csv(out_csv, read_run_config(run_dir)["meta"]["keypoints"])
    detector = Detector.load(run_dir, device)
    ds = Dataset.open(data, cache="none")
    store = FrameStore(ds, split_frames(ds, "all"), preload_mb=0)
    tmp = out_csv.with_name(out_csv.name + ".part")
    with write_csv(tmp, detector.keypoints) as writer:
        for batch, pred in detect_store(detector, store, batch_size):
            writer.writerows(csv_rows(batch.frame_ids.tolist(), pred))
    tmp.replace(out_csv)
    return read_csv(out_csv, detector.keypoints)


def estimates_and_crops(run_dir: Path, ds: DatasetLike, out_csv: Path, rule: CropRule,
                        device: str | torch.device = "cpu",
                        batch_size: int = 32, frames: np.ndarray | None = None):
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


REFERENCE_CROP = 128
"""The default crop size (px), at which the refining pass takes its pixel-valued options as given."""


def refining_config(cfg, crop_size: int):
    """The refining pass's configuration: ``cfg`` with its pixel-valued tolerances scaled by
    ``crop_size / REFERENCE_CROP``.

    The crop covers a fixed extent of the scene, so a crop pixel is ``extent / crop_size`` world units: the
    same ``--outlier-px`` would leave out of the pseudo-labels views half as far off at twice the crop size,
    and ``--shift-px`` and ``--pseudo-window`` would shrink in the scene alike. Scaled, they keep their size
    in the scene and ``--crop-size`` changes the resolution alone. ``--sigma`` is not scaled: a finer
    target is what a finer crop is for.
    """
    k = crop_size / REFERENCE_CROP
    return cfg.replace(image_size=0, outlier_px=cfg.outlier_px * k, shift_px=cfg.shift_px * k,
                       pseudo_window=max(1, round(cfg.pseudo_window * k)) if cfg.pseudo_window else 0)


def train_two_pass(data: str | Path, out: str | Path, cfg, *, coarse_size: int = 96,
                   coarse_steps: int | None = None, coarse_rotation: float | None = None,
                   coarse_stride: int | None = None, coarse_lr: float | None = None,
                   crop_size: int = REFERENCE_CROP, margin: float = 0.3, extent: float | None = None,
                   resume: bool = False, overwrite: bool = False, command: str | None = None,
                   keep_crops: bool = False, log: Callable[[str], None] | None = None,
                   init_from: str | Path | None = None) -> dict[str, Any]:
    """Train a two-pass detector (module docstring) into ``out``; each stage is skipped when its output is
    complete, so ``resume`` continues a killed run at the stage where it stopped.

    Args:
        data: dataset folder at full resolution.
        out: two-pass run folder.
        cfg: :class:`s3k.config.TrainConfig` of both passes (``image_size`` is set per pass; the refining
            pass scales the pixel-valued options with the crop size, :func:`refining_config`).
        coarse_size: the coarse pass's image size (longer side, px).
        coarse_steps: the coarse pass's steps (default: ``cfg.steps``).
        coarse_rotation: the coarse pass's augmentation rotation range, degrees (default:
            ``cfg.rotation_deg``): wide for a coarse pass that must find the object in any pose, while the
            refining pass keeps a narrow one for precision.
        coarse_stride: the coarse pass's heatmap stride (default: ``cfg.stride``), e.g. 2 under a refining
            pass at 4: the coarse pass places the crops, and a coarser one places some astray.
        coarse_lr: the coarse pass's learning rate (default: ``cfg.lr``), so that the refining pass's can
            change under a coarse pass that is kept.
        crop_size: crop size in pixels (the refining pass's input).
        margin: relative margin of the crop's extent (:func:`crop_rule_from_labels`).
        extent: the crop's side in world units (default: from the labels).
        resume, overwrite, command: as for :func:`s3k.train.train`.
        keep_crops: also write the crops as a dataset folder, ``RUN/crops``.
        init_from: a two-pass run whose passes start this run's (fine-tuning; :func:`s3k.train.train`), its
            crops' extent kept unless ``extent`` is given.

    Returns:
        ``{"coarse": ..., "fine": ..., "rule": CropRule}``, a pass's :class:`s3k.train.TrainResult` or None
        when it was complete before this call.
    """
    data, out, log = Path(data), Path(out), log or say
    inits, extent = _init_passes(init_from, extent)
    # every option of both passes is checked before the coarse pass trains
    for value, bounds, option in ((coarse_size, Range(ge=16), "--coarse-size"), (crop_size, Range(ge=16),
                                  "--crop-size"), (margin, Range(ge=0), "--crop-margin"),
                                  (extent, Range(gt=0), "--crop-extent")):
        if value is not None:
            bounds.check(value, option)
    refining_config(cfg, crop_size).validate()
    if coarse_stride is not None and coarse_stride not in (1, 2, 4):
        raise UserError(f"--coarse-stride: the coarse pass's heatmap stride must be 1, 2 or 4, "
                        f"got {coarse_stride}")
    if coarse_lr is not None:
        Range(gt=0, le=1).check(coarse_lr, "--coarse-lr")
    check_run_folder(out, resume, overwrite, whole=True)  # --overwrite deletes the folder: only a run's files
    if out.exists() and not resume and not is_stub(out):  # a start that trained nothing is not kept
        if not overwrite:
            raise UserError(f"{out} exists", hint="pass --resume to continue it or --overwrite to replace it")
        if not is_two_pass(out) and not (out / "coarse").is_dir() and not (out / OPTIONS_FILE).is_file():
            raise UserError(f"{out} is not a two-pass run; refusing to delete it",
                            hint="choose another --out")
    if out.exists() and not resume:
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
    options = dict(coarse_size=coarse_size, coarse_steps=coarse_steps, coarse_rotation=coarse_rotation,
                   coarse_stride=coarse_stride, coarse_lr=coarse_lr, crop_size=crop_size, margin=margin,
                   extent=extent)
    if not (out / OPTIONS_FILE).is_file():
        write_options(out, cfg, options)
    try:
        results = _train_two_pass(data, out, cfg, coarse_size, coarse_steps, coarse_rotation, crop_size,
                                  margin, extent, command, log, keep_crops, coarse_stride, coarse_lr, inits)
    except BaseException:
        if is_stub(out):  # nothing trained: leave no folder that a retry would have to get past
            shutil.rmtree(out, ignore_errors=True)
        raise
    write_options(out, cfg, options)  # what --resume takes: the options of the last call that completed
    return results


def _train_two_pass(data: Path, out: Path, cfg, coarse_size: int, coarse_steps: int | None,
                    coarse_rotation: float | None, crop_size: int, margin: float, extent: float | None,
                    command: str | None, log, keep_crops: bool = False,
                    coarse_stride: int | None = None, coarse_lr: float | None = None,
                    inits: tuple[Path, Path] | None = None) -> dict[str, Any]:
    ds = Dataset.open(data, cache="none")
    rule = (CropRule(float(extent), int(crop_size), 0.0) if extent is not None
            else crop_rule_from_labels(ds, crop_size, margin))
    if extent is None and (too_large := crop_extent_warning(ds, rule.extent, rule.size, coarse_size)):
        log(f"warning: {too_large}")
    results: dict[str, Any] = {"rule": rule}
    coarse_cfg = cfg.replace(image_size=coarse_size, steps=coarse_steps or cfg.steps,
                             rotation_deg=cfg.rotation_deg if coarse_rotation is None else coarse_rotation,
                             stride=cfg.stride if coarse_stride is None else coarse_stride,
                             lr=cfg.lr if coarse_lr is None else coarse_lr)
    coarse_data: Any = data
    # a coarse pass still to train decodes the frames; the coarse pass reads the same disk cache as from the
    # folder
    if not (out / "coarse" / "model.pt").is_file() and _hold_frames(ds, cfg, log):
        coarse_data = ds.with_cache("disk")
    with _StageClock(out, "coarse") as clock:
        results["coarse"] = _train_pass(train, coarse_data, out / "coarse", coarse_cfg, command, log,
                                        "coarse pass", clock, inits[0] if inits else None)
    written = out / "crops"
    with _StageClock(out, "crops"):
        if (written / "s3k.json").is_file():  # written by an earlier call: the refining pass trains on them
            _check_crops(written, rule)
            crops: Any = written
        else:
            _check_rule(out, rule)
            # the frames the refining pass reads, or every frame for a crop dataset written to keep
            used = ds.frames() if keep_crops else frames_used(ds, refining_config(cfg, rule.size))
            log(f"coarse pass: estimating the {len(used)} frames of {data} the refining pass reads and "
                f"cropping them in memory ({rule.extent:g} {ds.units} -> {rule.size} px)")
            crops = estimates_and_crops(out / "coarse", ds, out / ESTIMATES_FILE, rule, cfg.device,
                                        frames=used)
            if keep_crops:
                crops.write(written, overwrite=True)
                log(f"crops written to {written}")
    ds.release_frames()
    with _StageClock(out, "fine") as clock:
        results["fine"] = _train_pass(train, crops, out / "fine", refining_config(cfg, rule.size), command,
                                      log, "refining pass", clock, inits[1] if inits else None)
    write_two_pass(out, rule, coarse_size, ds.keypoints)
    return results


def _init_passes(init_from: str | Path | None, extent: float | None
                 ) -> tuple[tuple[Path, Path] | None, float | None]:
    """The passes of the two-pass run ``init_from`` that start this run's, and the crops' extent (its own
    unless ``extent`` is given)."""
    if init_from is None:
        return None, extent
    if not is_two_pass(init_from):
        raise UserError(f"--init-from {init_from}: not a two-pass run", hint="fine-tune a --two-pass run "
                        "with --two-pass, a one-pass run without it")
    rule, coarse, fine = read_two_pass(init_from)
    return (coarse, fine), rule.extent if extent is None else extent


def _hold_frames(ds: Dataset, cfg, log) -> bool:
    """Keep the frames the coarse pass decodes in memory for the crops (:meth:`s3k.data.Dataset.hold_frames`)
    when they take at most half the memory available now and ``--preload-mb`` is not 0; otherwise the crops
    decode them again."""
    have = available_memory()
    if cfg.preload_mb == 0 or have is None or ds.stored_mib > have / 2**20 / 2:
        log(f"the crops will decode the frames again: the {ds.stored_mib:.0f} MiB of full-resolution frames "
            f"are not kept in memory ({'--preload-mb 0' if cfg.preload_mb == 0 else 'too little memory'})")
        return False
    ds.hold_frames()
    log(f"keeping the coarse pass's frames at full resolution in memory for the crops (up to "
        f"{ds.stored_mib:.0f} MiB)")
    return True


def _check_rule(out: Path, rule: CropRule) -> None:
    """Refuse a crop rule other than the one a complete run recorded, or a crop size other than the one its
    refining pass was started at (another extent there changes the crops' calibration, which ``--resume``
    refuses)."""
    if is_two_pass(out):
        done, _, _ = read_two_pass(out)
        extent, size = done.extent, done.size
    elif (out / "fine" / "config.json").is_file():
        extent, size = rule.extent, int(read_run_config(out / "fine")["meta"]["image_size"][0])
    else:
        return
    if int(size) != rule.size or not np.isclose(float(extent), rule.extent, rtol=1e-6, atol=0.0):
        raise UserError(f"{out}: the refining pass was trained on crops {float(extent):g} wide at "
                        f"{int(size)} "
                        f"px; this call cuts {rule.extent:g} at {rule.size} px",
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


def read_cpu(run_dir: str | Path) -> dict[str, float]:
    """CPU seconds per stage of a two-pass run (``RUN/cpu.json``); empty for a run trained without it."""
    path = Path(run_dir) / CPU_FILE
    if not path.is_file():
        return {}
    try:
        return {str(k): float(v) for k, v in json.loads(path.read_text()).items()}
    except (ValueError, AttributeError, TypeError) as e:
        raise UserError(f"{path}: not a CPU record ({type(e).__name__}: {e})") from None


class _StageClock:
    """Adds the CPU time this process spends in a stage to ``RUN/cpu.json``: when the stage ends, and every
    ``every`` training steps meanwhile (:meth:`tick`, a training callback), so a killed attempt's time up to
    its last tick is kept. Only the main process of a distributed run writes."""

    def __init__(self, run_dir: Path, stage: str, every: int = 50) -> None:
        self.path, self.stage, self.every = run_dir / CPU_FILE, stage, every
        self.writes = os.environ.get("RANK", "0") == "0"

    def __enter__(self) -> _StageClock:
        self.before = read_cpu(self.path.parent).get(self.stage, 0.0)
        self.started = time.process_time()
        return self

    def tick(self, step: int, terms=None) -> None:
        if step % self.every == 0:
            self._write()

    def _write(self) -> None:
        if not self.writes:
            return

        spent = read_cpu(self.path.parent)
        spent[self.stage] = self.before + time.process_time() - self.started
        atomic_write_json(spent, self.path)

    def __exit__(self, *exc) -> None:
        self._write()


def _train_pass(train, data, run: Path, cfg, command, log, what: str, clock: _StageClock, init_from=None):
    """Train one pass unless its model exists (then None, after checking it was trained as this call would
    train it); resume a pass whose folder exists."""
    if (run / "model.pt").is_file():
        try:
            changed = check_trained_as(data, run, cfg)
            if "steps" in changed:  # a finished pass is not continued: it would be kept at its steps
                raise UserError(f"steps is {changed['steps'][1]} now but {changed['steps'][0]} there")
        except UserError as e:
            raise UserError(f"{what} {run} is complete but not what this call would train "
                            f"({e.message.removeprefix('--resume: ')})",
                            hint="repeat the options it was trained with, or pass --overwrite to train both "
                                 "passes again") from None
        log(f"{what}: {run} is complete")
        return None
    log(f"{what}: training {run}")
    result = train(data, run, cfg, resume=run.exists(), callback=clock.tick, command=command,
                   init_from=init_from)
    if result.status != "done":
        raise UserError(f"{what} stopped ({result.status}); see {run / 'train.log'}",
                        hint="fix what the log says and continue with --resume")
    return result
