"""Starting a two-pass run (``s3k train --two-pass``): the options it was started with, so that ``--resume``
needs none repeated; the folder a failed start leaves, which a retry replaces; and the check of a crop
extent too large for the images.

``RUN/two_pass_options.json`` holds the configuration of both passes (before the refining pass scales its
pixel tolerances) and the two-pass options (``coarse_size``, ``coarse_steps``, ``coarse_rotation``,
``coarse_stride``, ``coarse_lr``, ``crop_size``, ``margin``, ``extent``). It is written when the run starts
and again when a resumed run completes. A run folder from before it was kept is read from its passes' own
``config.json`` files and its crops (:func:`read_options`).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

from s3k.data.protocol import DatasetLike
from s3k.errors import UserError
from s3k.fileio import atomic_write_json
from s3k.geometry import triangulate_labels
from s3k.geometry.warp import metric_crop_boxes

OPTIONS_FILE = "two_pass_options.json"
# the defaults of s3k.train.two_pass.train_two_pass (crop_size: s3k.train.two_pass.REFERENCE_CROP)
DEFAULTS: dict[str, Any] = {"coarse_size": 96, "coarse_steps": None, "coarse_rotation": None,
                            "coarse_stride": None, "coarse_lr": None,
                            "crop_size": 128, "margin": 0.3, "extent": None}
STUB_FILES = frozenset({OPTIONS_FILE, "cpu.json"})  # what a start that trained nothing writes


def is_stub(run_dir: str | Path) -> bool:
    """Whether ``run_dir`` is a folder that holds nothing but what a failed start of a two-pass run wrote
    (nothing, the options, the CPU record): no pass trained, nothing to keep."""
    path = Path(run_dir)
    return path.is_dir() and all(p.name in STUB_FILES for p in path.iterdir())


def write_options(run_dir: str | Path, cfg, options: dict[str, Any]) -> None:
    """Record ``cfg`` (:class:`s3k.config.TrainConfig`) and the two-pass ``options`` in ``run_dir``."""
    unknown = set(options) - set(DEFAULTS)
    if unknown:
        raise ValueError(f"unknown two-pass options {sorted(unknown)}")
    atomic_write_json({"config": cfg.to_dict(), **{k: options.get(k, v) for k, v in DEFAULTS.items()}},
                      Path(run_dir) / OPTIONS_FILE)


def read_options(run_dir: str | Path) -> tuple[dict[str, Any], dict[str, Any]] | None:
    """``(configuration fields, two-pass options)`` the run in ``run_dir`` was started with; None when the
    folder records no options and its refining pass has not started (:func:`_from_passes`)."""
    path = Path(run_dir) / OPTIONS_FILE
    if path.is_file():
        try:
            doc = json.loads(path.read_text())
            return dict(doc["config"]), {k: doc.get(k, v) for k, v in DEFAULTS.items()}
        except (ValueError, KeyError, TypeError) as e:
            raise UserError(f"{path}: not a two-pass options record ({type(e).__name__}: {e})") from None
    return _from_passes(Path(run_dir))


def _run_config(path: Path) -> dict[str, Any] | None:
    """A pass's ``config.json`` (its ``config`` and ``meta``), or None where it is missing or unreadable."""
    try:
        doc = json.loads(path.read_text())
        return doc if isinstance(doc, dict) and isinstance(doc.get("config"), dict) else None
    except (OSError, ValueError):
        return None


def _from_passes(run_dir: Path) -> tuple[dict[str, Any], dict[str, Any]] | None:
    """The options of a run started before they were recorded: the coarse pass's configuration with the
    refining pass's own steps, rotation, stride and learning rate, and the crops' size and extent where they
    were cut. None until the refining pass has started: a coarse pass alone does not say what the refining
    pass's options are (its rotation, stride, learning rate and steps may be the coarse pass's own), so they
    are the call's, and the coarse pass is checked against them."""
    coarse_doc = _run_config(run_dir / "coarse" / "config.json")
    fine_doc = _run_config(run_dir / "fine" / "config.json")
    if coarse_doc is None or fine_doc is None:
        return None
    coarse, fine = dict(coarse_doc["config"]), dict(fine_doc["config"])
    options = dict(DEFAULTS, coarse_size=coarse.get("image_size", DEFAULTS["coarse_size"]))
    config = dict(coarse, image_size=0, steps=fine["steps"], rotation_deg=fine["rotation_deg"],
                  stride=fine["stride"], lr=fine["lr"])
    options.update(coarse_steps=coarse["steps"], coarse_rotation=coarse["rotation_deg"],
                   coarse_stride=coarse["stride"], coarse_lr=coarse["lr"])
    try:  # the crops' size is the refining pass's input
        options.update(crop_size=int(fine_doc["meta"]["image_size"][0]))
    except (ValueError, KeyError, TypeError, IndexError):
        pass
    for source in (run_dir / "two_pass.json", run_dir / "crops" / "s3k.json"):
        try:
            doc = json.loads(source.read_text())
        except (OSError, ValueError):
            continue
        rule = doc.get("source", doc) if isinstance(doc, dict) else {}
        if isinstance(rule, dict) and rule.get("extent") is not None and rule.get("size") is not None:
            options.update(extent=float(rule["extent"]), crop_size=int(rule["size"]))
            break
    return config, options


def crop_extent_warning(dataset: DatasetLike, extent: float, crop_size: int, coarse_size: int) -> str | None:
    """A warning when crops of side ``extent`` (world units), centred where the labelled keypoints lie, are at
    least as large as the images in most cameras: the refining pass then sees the whole image, at no finer a
    scale than the coarse pass. None otherwise, or when no labelled keypoint can be triangulated."""

    ids = dataset.frames("labelled")
    if not len(ids):
        return None
    uv, mask = dataset.labels(ids)
    cams = dataset.calibration(ids, dtype=np.float64)
    X, valid = triangulate_labels(cams, torch.from_numpy(uv), torch.from_numpy(mask))
    points = X.numpy()[valid.numpy()]
    if not len(points):
        return None
    centre = torch.as_tensor(np.median(points, axis=0))
    boxes, ok = metric_crop_boxes(cams[0], centre, extent)
    sides = (boxes[:, 2] - boxes[:, 0]).numpy()[ok.numpy()]
    W, H = dataset.image_size
    if not len(sides) or float(np.median(sides)) < max(W, H):
        return None
    side = float(np.median(sides))
    return (f"the crops are {extent:g} {dataset.units} wide, about {side:.0f} px in the {W}x{H} images: "
            f"larger than the whole image, so the {crop_size} px crops see the object at "
            f"{crop_size / side:.2f} of its pixels and the coarse pass at {coarse_size / max(W, H):.2f}; "
            "give a smaller side with --crop-extent (world units) or --crop-margin")
