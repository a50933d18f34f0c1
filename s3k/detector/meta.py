"""What a trained detector needs at inference time, saved with its weights (``RUN/model.pt``) and in
``RUN/config.json``."""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from s3k.readout import DEFAULT_MIN_WEIGHT, ConfidenceMap, ReadoutConfig

__all__ = ["DetectorMeta"]


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
        outlier_px: at read-out, a view whose detection misses the others' consensus by more than this many
            network-input pixels does not enter the triangulation (the threshold the training's
            ``--outlier-px`` held its pseudo-labels to); 0: every view enters.
        layout: a rigid object's ``(K, K)`` distances between the keypoints, triangulated from the labels
            (NaN where unknown, None: not a rigid object), and ``layout_tol`` the relative tolerance
            ``--layout-tol`` held them to: at read-out a keypoint that breaks them is looked for again where
            the layout puts it (:func:`s3k.readout.search_layout`).
        geometry: the part of each camera's full frame the training images showed, the training images' size
            and the training dataset's path and identity
            (:func:`s3k.detector.geometry_record.training_geometry`), so that inputs are cropped the same way
            or refused; None for a run trained before it was recorded.
        skeleton: the training dataset's skeleton, edges as keypoint name pairs (drawn by ``s3k track
            --overlay``, ``s3k view`` and ``s3k stream --rerun``; empty for none, or a run trained before it
            was recorded).
        calibration: the map of the confidence weight to the calibrated confidence, fitted on the
            validation frames at the end of training (:meth:`s3k.readout.ConfidenceMap.to_dict`); None: the
            raw weight is the confidence (a run trained before runs were calibrated, one whose validation
            frames had no truth, or a checkpoint of an unfinished run).
    """

    keypoints: list[str]
    cameras: list[str]
    image_size: tuple[int, int]
    stride: int
    sigma: float
    model: dict[str, Any] = field(default_factory=dict)
    units: str = "m"
    source_image_size: tuple[int, int] | None = None
    outlier_px: float = 0.0
    layout: list[list[float]] | None = None
    layout_tol: float = 0.0
    geometry: dict[str, Any] | None = None
    skeleton: list[tuple[str, str]] = field(default_factory=list)
    calibration: dict[str, Any] | None = None

    @property
    def max_residual_px(self) -> float | None:
        """``outlier_px`` as :func:`s3k.readout.read_out` takes it (None: off)."""
        return self.outlier_px if self.outlier_px > 0 else None

    def readout_config(self, min_weight: float = DEFAULT_MIN_WEIGHT) -> ReadoutConfig:
        """The read-out settings this detector was trained with (:class:`s3k.readout.ReadoutConfig`: its
        confidence calibration, outlier threshold and rigid layout; the window of its target width)."""
        return ReadoutConfig(min_weight=min_weight, confidence=self.confidence_map,
                             max_residual_px=self.max_residual_px, layout=self.layout_distances,
                             layout_tol=self.layout_tol)

    @property
    def confidence_map(self) -> ConfidenceMap | None:
        """``calibration`` as :class:`s3k.readout.ConfidenceMap` (None: none recorded)."""
        return None if self.calibration is None else ConfidenceMap.from_dict(self.calibration)

    def recorded_skeleton(self) -> list[tuple[str, str]]:
        """``skeleton``; for a run trained before it was recorded, the skeleton of the training dataset's
        ``s3k.json`` where that is still readable (else none)."""
        if self.skeleton or not self.geometry:
            return list(self.skeleton)
        path = (self.geometry.get("dataset") or {}).get("path")
        try:
            doc = json.loads((Path(path) / "s3k.json").read_text()) if path else {}
        except (OSError, ValueError):
            return []
        edges = doc.get("skeleton") if isinstance(doc, dict) else None
        return [(a, b) for a, b in edges or [] if isinstance(a, str) and isinstance(b, str)
                and a in self.keypoints and b in self.keypoints]

    @property
    def layout_distances(self) -> torch.Tensor | None:
        """``layout`` as the ``(K, K)`` float64 tensor :func:`s3k.readout.read_out` takes (None: off)."""
        if self.layout is None or not self.layout_tol > 0:
            return None
        return torch.tensor(self.layout, dtype=torch.float64)

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["image_size"] = list(self.image_size)
        if self.source_image_size is not None:
            d["source_image_size"] = list(self.source_image_size)
        if self.layout is not None:  # JSON has no NaN: an unknown distance is null
            d["layout"] = [[v if math.isfinite(v) else None for v in row] for row in self.layout]
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> DetectorMeta:
        d = dict(d)
        d["image_size"] = tuple(d["image_size"])
        if d.get("source_image_size") is not None:
            d["source_image_size"] = tuple(d["source_image_size"])
        if d.get("layout") is not None:
            d["layout"] = [[math.nan if v is None else float(v) for v in row] for row in d["layout"]]
        d["skeleton"] = [(str(a), str(b)) for a, b in d.get("skeleton") or []
                         if a in d.get("keypoints", ()) and b in d.get("keypoints", ())]
        if d.get("calibration") is not None:
            ConfidenceMap.from_dict(d["calibration"])  # a damaged one is refused when read, not at first use
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})
