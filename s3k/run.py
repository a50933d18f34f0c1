"""The run folder written by ``s3k train``, and :func:`load_detector` to use a trained model.

Layout of ``RUN/``::

    config.json      the resolved TrainConfig plus "meta" (what inference needs) and the dataset path
    checkpoint.pt    full training state (model, optimizer, scheduler, RNG states, step) for --resume
    model.pt         final weights + meta, written at the end of training
    train.log        the log, including non-finite-loss and collapse warnings
    tensorboard/     TensorBoard event files (loss terms, validation metrics, images)

Every file is written atomically (write ``NAME.tmp`` then ``os.replace``), so a run killed at any moment
leaves the previous complete checkpoint in place.
"""

from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from s3k.model import UNet, UNetConfig

CONFIG_FILE = "config.json"
CHECKPOINT_FILE = "checkpoint.pt"
MODEL_FILE = "model.pt"
LOG_FILE = "train.log"
TENSORBOARD_DIR = "tensorboard"


@dataclass
class DetectorMeta:
    """What a trained detector needs at inference time.

    Attributes:
        keypoints: keypoint names, in heatmap order (K).
        cameras: camera names of the training dataset (C).
        image_size: network input size (W, H) in pixels; images are resized to it (``frames.FrameStore``).
        stride: heatmap stride (image pixels per heatmap cell).
        sigma: target Gaussian width in image pixels (also the confidence weight's sigma).
        model: ``UNetConfig.to_dict()`` of the network.
        units: world units of the training dataset's calibration (e.g. "m").
        source_image_size: (W, H) of the training dataset's images.
    """

    keypoints: list[str]
    cameras: list[str]
    image_size: tuple[int, int]
    stride: int
    sigma: float
    model: dict[str, Any] = field(default_factory=dict)
    units: str = "m"
    source_image_size: tuple[int, int] | None = None

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["image_size"] = list(self.image_size)
        if self.source_image_size is not None:
            d["source_image_size"] = list(self.source_image_size)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> DetectorMeta:
        d = dict(d)
        d["image_size"] = tuple(d["image_size"])
        if d.get("source_image_size") is not None:
            d["source_image_size"] = tuple(d["source_image_size"])
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})


def atomic_save(obj: Any, path: str | Path) -> None:
    """``torch.save`` to ``path.tmp`` then rename over ``path`` (never a half-written file)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def atomic_write_text(text: str, path: str | Path) -> None:
    """Write text to ``path.tmp`` then rename over ``path``."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def write_run_config(run_dir: str | Path, config: dict[str, Any], meta: DetectorMeta,
                     dataset: str | None = None) -> None:
    """Write ``RUN/config.json``: {"config": ..., "meta": ..., "dataset": ...}."""
    doc = {"config": config, "meta": meta.to_dict(), "dataset": dataset}
    atomic_write_text(json.dumps(doc, indent=2) + "\n", Path(run_dir) / CONFIG_FILE)


def read_run_config(run_dir: str | Path) -> dict[str, Any]:
    """Read ``RUN/config.json``; raises FileNotFoundError naming the file when absent."""
    path = Path(run_dir) / CONFIG_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: {run_dir} is not an s3k run folder")
    return json.loads(path.read_text())


def build_model(meta: DetectorMeta) -> UNet:
    """A fresh (untrained) network for ``meta``."""
    return UNet(len(meta.keypoints), UNetConfig.from_dict(meta.model))


def load_detector(run_dir: str | Path, device: str | torch.device = "cpu",
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
        >>> model, meta = load_detector("runs/box")  # doctest: +SKIP
        >>> logits = model(images.reshape(-1, 3, meta.image_size[1], meta.image_size[0]))  # doctest: +SKIP
    """
    run_dir = Path(run_dir)
    names = [checkpoint] if checkpoint else [MODEL_FILE, CHECKPOINT_FILE]
    for name in names:
        path = run_dir / name
        if path.is_file():
            state = torch.load(path, map_location="cpu", weights_only=False)
            break
    else:
        raise FileNotFoundError(f"{run_dir}: no {' or '.join(names)} (train first, or check the path)")
    if "meta" not in state or "model" not in state:
        raise ValueError(f"{path}: not an s3k model file (missing 'meta' or 'model')")
    meta = DetectorMeta.from_dict(state["meta"])
    model = build_model(meta)
    model.load_state_dict(state["model"])
    return model.to(device).eval(), meta
