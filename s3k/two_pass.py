"""The coarse-to-fine detector: a coarse pass on the whole image, a refining pass on scale-normalized crops.

A two-pass run folder holds two ordinary runs of ``s3k train`` and the crop rule that joins them::

    RUN/two_pass.json    the crop rule (extent in world units, crop size in pixels) and the passes' folders
    RUN/coarse/          the coarse detector: the whole image, resized to ``coarse_size`` px
    RUN/estimates.csv    the coarse pass's 3D keypoints for every frame of the training dataset
    RUN/crops/           a dataset of crops around those estimates (:func:`s3k.refine.write_crop_dataset`)
    RUN/fine/            the refining detector, trained on the crops with the same losses (its pixel
                         tolerances scaled to the crop size: :func:`refining_config`)
    RUN/cpu.json         CPU seconds each stage took: ``coarse`` (its training, the estimates and the
                         crops) and ``fine``, summed over the attempts of a resumed run

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

import contextlib
import json
import tempfile
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from s3k.errors import UserError

__all__ = ["CPU_FILE", "ESTIMATES_FILE", "REFERENCE_CROP", "TWO_PASS_FILE", "CropRule", "TwoPassDetector",
           "crop_centres", "crop_rule_from_labels", "evaluate_two_pass", "extent_middle", "is_two_pass",
           "predict_two_pass", "read_cpu", "read_two_pass", "refining_config", "train_two_pass"]

TWO_PASS_FILE = "two_pass.json"
ESTIMATES_FILE = "estimates.csv"  # the coarse pass's 3D keypoints of every training frame
CPU_FILE = "cpu.json"  # CPU seconds per stage ("coarse", "fine"), summed over a resumed run's attempts


@dataclass(frozen=True)
class CropRule:
    """How a frame's crops are cut around its coarse 3D keypoints.

    Attributes:
        extent: side of every crop at the centre's depth, in the dataset's world units.
        size: crop width and height in pixels (the refining network's input).
        margin: the relative margin that went into ``extent`` (recorded for the reader).
    """

    extent: float
    size: int
    margin: float = 0.0


def extent_middle(points: np.ndarray) -> np.ndarray | None:
    """The middle of the keypoints' extent: the midpoint of the two finite rows of ``points (K, 3)`` farthest
    apart (the point itself when only one is finite; None when none is).

    Unlike a bounding box in world axes it does not depend on the object's orientation; for three corners of
    a rectangle it is the rectangle's centre, equally far from all of them."""
    X = np.asarray(points, dtype=np.float64)
    X = X[np.isfinite(X).all(axis=-1)]
    if not len(X):
        return None
    d = np.linalg.norm(X[:, None] - X[None], axis=-1)
    i, j = np.unravel_index(np.argmax(d), d.shape)
    return 0.5 * (X[i] + X[j])


def crop_centres(points: Mapping[int, np.ndarray]) -> dict[int, np.ndarray]:
    """``{frame: (3,)}`` crop centres from ``{frame: (K, 3)}`` keypoints (frames with none finite are left
    out)."""
    out = {}
    for frame, X in points.items():
        c = extent_middle(X)
        if c is not None:
            out[int(frame)] = c
    return out


def crop_rule_from_labels(dataset, size: int, margin: float = 0.3) -> CropRule:
    """The run's crop rule from the labelled frames' triangulated labels (never from ground truth).

    ``extent = 2 * r * (1 + margin)`` with ``r`` the largest distance of a labelled keypoint from the middle
    of its frame's keypoints' extent: a crop centred on a perfect estimate holds every keypoint with
    ``margin * r`` to spare on each side, the room left for the coarse pass's error.

    Raises:
        UserError: no labelled frame has two triangulated keypoints.
    """
    from s3k.geometry import triangulate_pixels

    ids = dataset.frames("labelled")
    radius = 0.0
    if len(ids):
        uv, mask = dataset.labels(ids)
        cams = dataset.calibration(ids, dtype=np.float64)
        m = torch.from_numpy(mask)
        X, valid = triangulate_pixels(cams, torch.from_numpy(uv).to(torch.float64), m.to(torch.float64))
        ok = (valid & (m.sum(dim=1) >= 2)).numpy()
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


def is_two_pass(run_dir: str | Path) -> bool:
    """Whether ``run_dir`` is a two-pass run folder."""
    return (Path(run_dir) / TWO_PASS_FILE).is_file()


def read_two_pass(run_dir: str | Path) -> tuple[CropRule, Path, Path]:
    """``(rule, coarse run folder, fine run folder)`` of a two-pass run.

    Raises:
        UserError: the file is missing or a field is absent or of the wrong type.
    """
    path = Path(run_dir) / TWO_PASS_FILE
    try:
        info = json.loads(path.read_text())
        rule = CropRule(float(info["extent"]), int(info["size"]), float(info.get("margin", 0.0)))
        coarse, fine = Path(run_dir) / str(info["coarse"]), Path(run_dir) / str(info["fine"])
    except FileNotFoundError:
        raise UserError(f"{path}: not found (is {run_dir} a run of 's3k train --two-pass'?)") from None
    except (ValueError, KeyError, TypeError) as e:
        raise UserError(f"{path}: not a two-pass run description ({type(e).__name__}: {e})") from None
    return rule, coarse, fine


def _write_two_pass(run_dir: Path, rule: CropRule, coarse_size: int, keypoints) -> None:
    from s3k.fileio import atomic_write_json

    info = {**asdict(rule), "coarse": "coarse", "fine": "fine", "coarse_size": coarse_size,
            "keypoints": list(keypoints)}
    atomic_write_json(info, run_dir / TWO_PASS_FILE)


def coarse_estimates(run_dir: Path, data: Path, out_csv: Path, split: str,
                     keypoints) -> dict[int, np.ndarray]:
    """The coarse pass's 3D keypoints of ``split``, written once to ``out_csv`` and read back."""
    from s3k.predict import predict_dataset
    from s3k.tracks_csv import read_csv

    if not out_csv.is_file():
        tmp = out_csv.with_name(out_csv.name + ".part")
        predict_dataset(run_dir, data, tmp, split=split, device="cpu", overwrite=True)
        tmp.replace(out_csv)
    return read_csv(out_csv, keypoints)


def write_crops(data: Path, out: Path, estimates: Mapping[int, np.ndarray], rule: CropRule,
                splits=None, description: str | None = None) -> Path:
    """The crop dataset of ``data`` around ``estimates`` by ``rule``; a frame the coarse pass could not place
    is cropped around the median of the other frames' centres (the workspace)."""
    from s3k.refine import write_crop_dataset

    centres = crop_centres(estimates)
    if not centres:
        raise UserError(f"the coarse pass placed no keypoint in any frame of {data}",
                        hint="train the coarse pass longer (--coarse-steps) or check the labels")
    middle = np.median(np.stack(list(centres.values())), axis=0)
    return write_crop_dataset(data, out, centres, rule.extent, rule.size, fallback=lambda frame: middle,
                              overwrite=True, splits=splits, description=description)


REFERENCE_CROP = 128
"""The default crop size (px), at which the refining pass takes its pixel-valued options as given."""


def refining_config(cfg, crop_size: int):
    """The refining pass's configuration: ``cfg`` with its pixel-valued tolerances scaled by
    ``crop_size / REFERENCE_CROP``.

    The crop covers a fixed extent of the scene, so a crop pixel is ``extent / crop_size`` world units: the
    same ``--outlier_px`` would leave out of the pseudo-labels views half as far off at twice the crop size,
    and ``--shift_px`` and ``--pseudo_window`` would shrink in the scene alike. Scaled, they keep their size
    in the scene and ``--crop-size`` changes the resolution alone. ``--sigma`` is not scaled: a finer
    target is what a finer crop is for.
    """
    k = crop_size / REFERENCE_CROP
    return cfg.replace(image_size=0, outlier_px=cfg.outlier_px * k, shift_px=cfg.shift_px * k,
                       pseudo_window=max(1, round(cfg.pseudo_window * k)) if cfg.pseudo_window else 0)


def train_two_pass(data: str | Path, out: str | Path, cfg, *, coarse_size: int = 96,
                   coarse_steps: int | None = None, coarse_rotation: float | None = None,
                   crop_size: int = REFERENCE_CROP, margin: float = 0.3, extent: float | None = None,
                   resume: bool = False, overwrite: bool = False, command: str | None = None,
                   log=print) -> dict[str, Any]:
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
        crop_size: crop size in pixels (the refining pass's input).
        margin: relative margin of the crop's extent (:func:`crop_rule_from_labels`).
        extent: the crop's side in world units (default: from the labels).
        resume, overwrite, command: as for :func:`s3k.train.train`.

    Returns:
        ``{"coarse": ..., "fine": ..., "rule": CropRule}``, a pass's :class:`s3k.train.TrainResult` or None
        when it was complete before this call.
    """
    import shutil

    from s3k.data import Dataset
    from s3k.ranges import Range
    from s3k.train import train

    data, out = Path(data), Path(out)
    # every option of both passes is checked before the coarse pass trains
    for value, bounds, option in ((coarse_size, Range(ge=16), "--coarse-size"), (crop_size, Range(ge=16),
                                  "--crop-size"), (margin, Range(ge=0), "--crop-margin"),
                                  (extent, Range(gt=0), "--crop-extent")):
        if value is not None:
            bounds.check(value, option)
    refining_config(cfg, crop_size).validate()
    if out.exists() and not resume:
        if not overwrite:
            raise UserError(f"{out} exists", hint="pass --resume to continue it or --overwrite to replace it")
        if not is_two_pass(out) and not (out / "coarse").is_dir():
            raise UserError(f"{out} is not a two-pass run; refusing to delete it",
                            hint="choose another --out")
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
    ds = Dataset.open(data, cache="none")
    rule = (CropRule(float(extent), int(crop_size), 0.0) if extent is not None
            else crop_rule_from_labels(ds, crop_size, margin))
    results: dict[str, Any] = {"rule": rule}
    coarse_cfg = cfg.replace(image_size=coarse_size, steps=coarse_steps or cfg.steps,
                             rotation_deg=cfg.rotation_deg if coarse_rotation is None else coarse_rotation)
    with _StageClock(out, "coarse") as clock:
        results["coarse"] = _train_pass(train, data, out / "coarse", coarse_cfg, command, log, "coarse pass",
                                        clock)
        log(f"coarse pass: estimating every frame of {data}")
        estimates = coarse_estimates(out / "coarse", data, out / ESTIMATES_FILE, "all", ds.keypoints)
        crops = out / "crops"
        if (crops / "s3k.json").is_file():
            _check_crops(crops, rule)
        else:
            log(f"cropping every frame: {rule.extent:g} {ds.units} -> {rule.size} px")
            write_crops(data, crops, estimates, rule,
                        description=f"crops of {rule.extent:g} {ds.units} around the coarse pass's estimates")
    with _StageClock(out, "fine") as clock:
        results["fine"] = _train_pass(train, crops, out / "fine", refining_config(cfg, rule.size), command,
                                      log, "refining pass", clock)
    _write_two_pass(out, rule, coarse_size, ds.keypoints)
    return results


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
        import os

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
        from s3k.fileio import atomic_write_json

        spent = read_cpu(self.path.parent)
        spent[self.stage] = self.before + time.process_time() - self.started
        atomic_write_json(spent, self.path)

    def __exit__(self, *exc) -> None:
        self._write()


def _train_pass(train, data: Path, run: Path, cfg, command, log, what: str, clock: _StageClock):
    """Train one pass unless its model exists (then None, after checking it was trained as this call would
    train it); resume a pass whose folder exists."""
    if (run / "model.pt").is_file():
        from s3k.train import check_trained_as

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
    result = train(data, run, cfg, resume=run.exists(), callback=clock.tick, command=command)
    if result.status != "done":
        raise UserError(f"{what} stopped ({result.status}); see {run / 'train.log'}",
                        hint="fix what the log says and continue with --resume")
    return result


def evaluate_two_pass(run_dir: str | Path, data: str | Path, split: str = "test", device: str = "auto",
                      batch_size: int = 16, report: str | Path | None = None, overlays: int = 6
                      ) -> dict[str, Any]:
    """Metrics of a two-pass run on ``data``'s ``split``: the coarse pass places every frame, the refining
    pass detects in the crops around it (cut from ``data``'s own images) and its triangulated points are the
    run's 3D keypoints. Pixel metrics are in crop pixels; 3D metrics in millimetres."""
    from s3k.evaluate import evaluate_run

    rule, _, fine = read_two_pass(run_dir)
    with _split_crops(run_dir, data, split) as (crops, placed):
        metrics = evaluate_run(fine, crops, split=split, device=device, batch_size=batch_size, report=report,
                               overlays=overlays)
    metrics["two_pass"] = {**asdict(rule), "coarse_frames_placed": placed}
    return metrics


def predict_two_pass(run_dir: str | Path, data: str | Path, out: Path, split: str = "test",
                     batch_size: int = 16, device: str = "auto"):
    """:func:`s3k.predict.predict_dataset` through both passes; the CSV's ``error`` is in crop pixels."""
    from s3k.predict import predict_dataset

    _, _, fine = read_two_pass(run_dir)
    with _split_crops(run_dir, data, split) as (crops, _placed):
        return predict_dataset(fine, crops, out, split, batch_size, device, overwrite=True)


@contextlib.contextmanager
def _split_crops(run_dir: str | Path, data: str | Path, split: str):
    """``(crop dataset, frames the coarse pass placed)`` of ``data``'s ``split`` (``all``: every split) by the
    run's rule, in a temporary folder removed on exit: what evaluating and predicting a two-pass run share."""
    from s3k.data import Dataset

    rule, coarse, _ = read_two_pass(run_dir)
    keypoints = Dataset.open(data, cache="none").keypoints
    with tempfile.TemporaryDirectory(prefix="s3k-two-pass-") as tmp:
        estimates = coarse_estimates(coarse, Path(data), Path(tmp) / "coarse.csv", split, keypoints)
        crops = write_crops(Path(data), Path(tmp) / "crops", estimates, rule,
                            splits=None if split == "all" else (split,))
        yield crops, len(crop_centres(estimates))


class TwoPassDetector:
    """Both passes of a two-pass run, for frames at their native resolution (``s3k track``).

    :meth:`refine` takes the coarse pass's read-out of a batch of frames and the original images, cuts each
    view around the middle of the coarse keypoints by the run's crop rule (the rule its refining pass was
    trained with), and returns the refining pass's read-out in the original images' pixels and world frame.
    """

    def __init__(self, run_dir: str | Path, device: str | torch.device = "cpu"):
        from s3k.run import load_detector

        self.rule, coarse, fine = read_two_pass(run_dir)
        self.coarse, self.coarse_meta = load_detector(coarse, device)
        self.fine, self.fine_meta = load_detector(fine, device)
        self.device = torch.device(device)
        self._last_centre: np.ndarray | None = None

    @torch.inference_mode()
    def refine(self, originals, coarse, cams, min_weight: float = 0.0):
        """The refining pass's :class:`s3k.readout.ReadOut` of a batch of frames.

        Args:
            originals: ``B`` frames, each ``C`` images ``(H_c, W_c, 3)`` uint8 (cameras may differ in size).
            coarse: the coarse pass's read-out of those frames (its ``X (B, K, 3)``, NaN where invalid).
            cams: the cameras ``(C,)`` of the original images.
            min_weight: as for :func:`s3k.readout.read_out`.
        """
        from s3k.crops import crop_images, crop_maps, metric_crop_boxes
        B, C = len(originals), len(originals[0])
        centres = []
        for X in coarse.X.cpu().numpy():
            middle = extent_middle(X)
            if middle is None:  # the coarse pass lost the object: look where it was last seen
                middle = self._last_centre if self._last_centre is not None else np.zeros(3)
            self._last_centre = middle
            centres.append(middle)
        cams = cams.to(dtype=torch.float64)
        centre = torch.as_tensor(np.stack(centres))[:, None, :]  # (B, 1, 3)
        boxes, _ = metric_crop_boxes(cams, centre, self.rule.extent)  # (B, C, 4)
        size = (self.rule.size, self.rule.size)
        crops = torch.empty(B, C, 3, *size)
        for c in range(C):
            images = torch.from_numpy(np.stack([frame[c] for frame in originals])).permute(0, 3, 1, 2)
            crops[:, c] = crop_images(images.float(), boxes[:, c].float(), size)
        # the refining pass was trained on crops stored as 8-bit images: quantize them the same way
        x = crops.round_().clamp_(0, 255).div_(255.0).to(self.device)
        logits = self.fine(x.reshape(B * C, 3, *size))
        logits = logits.reshape(B, C, *logits.shape[1:])
        maps = crop_maps(boxes, size)  # (B, C, 3, 3): original pixels -> crop pixels
        return self.fine_meta.read_out(logits, cams.to(self.device), maps, min_weight)
