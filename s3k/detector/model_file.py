"""A run's model files and :func:`load_network` to use a trained model (the run folder's files are named, and
its ``config.json`` read and written, by :class:`s3k.run_folder.RunFolder`).

Every file is written atomically (``s3k.base.fileio``), so a run killed at any moment leaves the previous
complete checkpoint in place. The ``.pt`` files hold only tensors and plain containers (the configuration and
meta as dicts) and are read with ``torch.load(..., weights_only=True)`` (:func:`load_torch_file`), so loading
a run never runs code from the file.
"""

from __future__ import annotations

import logging
import pickle
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from s3k.base.errors import UserError
from s3k.base.fileio import atomic_path
from s3k.base.messages import NOTE
from s3k.detector.meta import DetectorMeta
from s3k.model import UNet, UNetConfig
from s3k.networks import build_network
from s3k.run_folder import RunFolder

# the names RunFolder gives a one-pass run's files, under the names s3k.detector has long exported
CONFIG_FILE = RunFolder.CONFIG
CHECKPOINT_FILE = RunFolder.CHECKPOINT
MODEL_FILE = RunFolder.MODEL
LOG_FILE = RunFolder.LOG
TENSORBOARD_DIR = RunFolder.TENSORBOARD
PROGRESS_FILE = RunFolder.PROGRESS
RUN_FILES = RunFolder.ONE_PASS_FILES
MODEL_FORMAT = "s3k-model/1"

log = logging.getLogger(__name__)

_UNCALIBRATED_NOTED: set[str] = set()
"""The model files this process said once have no confidence calibration."""


def atomic_save(obj: Any, path: str | Path) -> None:
    """``torch.save`` to a temporary file then rename it over ``path`` (never a half-written file).

    ``obj`` must hold only tensors, dicts, lists, tuples, numbers, strings and None, so that
    :func:`load_torch_file` can read it back without running any pickled code.
    """
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


def load_torch_file(path: str | Path, what: str, keys: Sequence[str]) -> dict[str, Any]:
    """Read an s3k ``.pt`` file (a dict holding ``keys``) with ``weights_only=True``: nothing in it runs.

    Args:
        path: the file.
        what: what it should be, for the message ("model", "checkpoint").
        keys: keys the dict must have.

    Raises:
        UserError: naming the file when it is unreadable, truncated, holds anything but tensors and plain
            containers (a foreign or crafted pickle), or lacks ``keys``.
    """
    refusal = f"{path}: not an s3k {what} or written by an older s3k"
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except OSError as exc:
        if exc.filename is not None:
            raise  # missing or unreadable: the CLI names the file and the system's reason
        # torch's reader raises a bare EINVAL for a zip cut short near its end
        raise UserError(f"{path}: not a complete {what} file (truncated or damaged)",
                        hint="copy it again or retrain") from exc
    except pickle.UnpicklingError as exc:  # weights_only refused an object: nothing of it was run
        raise UserError(f"{refusal} (it holds objects other than tensors and plain values)",
                        hint="retrain") from exc
    except Exception as exc:  # noqa: BLE001 - the zip reader and the unpickler raise many kinds
        text = str(exc).strip()
        if "zip archive" in text or "central directory" in text:
            raise UserError(f"{path}: not a complete {what} file (truncated or damaged)",
                            hint="copy it again or retrain") from exc
        reason = text.splitlines()[0] if text else type(exc).__name__
        raise UserError(f"{refusal} (unreadable: {reason[:200]})", hint="retrain") from exc
    if not isinstance(state, dict) or any(k not in state for k in keys):
        raise UserError(f"{refusal} (it lacks {' or '.join(repr(k) for k in keys)})", hint="retrain")
    return state


def save_model_file(path: str | Path, model: dict[str, Any], meta: DetectorMeta, step: int) -> None:
    """Write ``RUN/model.pt``: the final weights (a state dict), :class:`DetectorMeta` as a dict, the step."""
    atomic_save({"format": MODEL_FORMAT, "model": model, "meta": meta.to_dict(), "step": step}, path)


def build_model(meta: DetectorMeta) -> UNet:
    """A fresh (untrained) network for ``meta``."""
    return build_network(len(meta.keypoints), UNetConfig.from_dict(meta.model))


def _older_run_meta(run_dir: Path) -> dict[str, Any]:
    """What a detector trained before its meta kept the read-out's outlier threshold takes from its run's
    ``config.json``: the ``--outlier-px`` it was trained with (nothing when that is missing)."""
    doc = RunFolder(run_dir).record()
    value = doc["config"].get("outlier_px") if doc is not None else None
    return {"outlier_px": float(value)} if isinstance(value, (int, float)) else {}


def load_network(run_dir: str | Path, device: str | torch.device = "cpu",
                  checkpoint: str | None = None) -> tuple[UNet, DetectorMeta]:
    """Load a trained detector from a run folder, in eval mode.

    Uses ``RUN/model.pt`` (final weights) when present, else the last training checkpoint.

    Args:
        run_dir: the ``--out`` folder of ``s3k train``.
        device: where to put the model.
        checkpoint: explicit file name inside ``run_dir`` to load instead.

    Returns:
        ``(model, meta)``: the UNet (eval mode) and its :class:`DetectorMeta` (keypoint names, image size,
        stride, sigma in image pixels).

    Example:
        >>> model, meta = load_network("runs/box")  # doctest: +SKIP
        >>> logits = model(images.reshape(-1, 3, meta.image_size[1], meta.image_size[0]))  # doctest: +SKIP
    """
    run_dir = Path(run_dir)
    names = [checkpoint] if checkpoint else [MODEL_FILE, CHECKPOINT_FILE]
    for name in names:
        path = run_dir / name
        if path.is_file():
            state = load_torch_file(path, "model", ("meta", "model"))
            break
    else:
        run = RunFolder(run_dir)
        if run.is_two_pass():
            raise UserError(f"{run_dir} is a two-pass run; this needs one network: {run.coarse.path} or "
                            f"{run.fine.path}", hint="give one of them, or use s3k.Detector.load for both")
        raise UserError(f"{run_dir}: no {' or '.join(names)}", hint="train first, or check the path")
    try:
        older = {} if "outlier_px" in state["meta"] else _older_run_meta(run_dir)
        meta = DetectorMeta.from_dict({**older, **state["meta"]})
        model = build_model(meta)
        model.load_state_dict(state["model"])
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        reason = str(exc).splitlines()[0][:200] if str(exc) else type(exc).__name__
        raise UserError(f"{path}: not an s3k model or written by an older s3k (its content does not fit: "
                        f"{reason})", hint="retrain") from exc
    return model.to(device).eval(), meta


def note_uncalibrated(path: Path) -> None:
    """Say once per run that its thresholds compare the raw confidence weight (a detector without a
    confidence map, asked for a ``min_weight`` above 0)."""
    key = str(path.resolve())
    if key in _UNCALIBRATED_NOTED:
        return
    _UNCALIBRATED_NOTED.add(key)
    log.log(NOTE, "%s has no confidence calibration (trained before runs were calibrated, without truth on "
            "its validation frames, or not finished): --min-weight and the labelling app's accept compare "
            "the raw confidence weight", path)
