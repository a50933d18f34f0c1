"""Every setting of the read-out in one carrier, :class:`ReadoutConfig`: a detector's (from its meta, the
settings it was trained with) and the pseudo-labels' (:meth:`ReadoutConfig.for_pseudo_labels`) go through the
same :func:`s3k.readout.read_out`.

The two differ where a test showed a reason, each an explicit field: at inference a keypoint that breaks a
rigid object's layout is looked for again where the layout puts it and the fitted layout places every
keypoint (``layout_search``, ``layout_fit="all"``); a pseudo-label keypoint that breaks the layout gives no
term instead (``layout_drop``) and the layout moves only the kept keypoints (``layout_fit="kept"`` with
``--layout-fit``, else ``"off"``), so that training never learns from a place no view showed
(docs/training.md). The pseudo-labels' window is the training's ``--pseudo-window``.
"""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

from s3k.base.choices import LAYOUT_FITS, LayoutFit
from s3k.config import SelfSupervisionConfig
from s3k.readout.confidence import ConfidenceMap
from s3k.readout.views import DEFAULT_MIN_WEIGHT

__all__ = ["LAYOUT_FITS", "ReadoutConfig"]



@dataclass(frozen=True, eq=False)
class ReadoutConfig:
    """How heatmap logits become detections and 3D points (:func:`s3k.readout.read_out`).

    Attributes:
        window: each detection is its heatmap's mean within this many cells of the peak; None:
            :func:`s3k.readout.window_cells` of the target width; 0: the whole heatmap's mean (the paper's).
        min_weight: views whose calibrated confidence is at or below this are not used (0: every view,
            weighted by its raw weight).
        confidence: the run's calibration, raw weight -> calibrated confidence
            (:class:`s3k.readout.confidence.ConfidenceMap`); None: the raw weight is the confidence (a run
            trained before runs were calibrated, and the pseudo-labels).
        max_residual_px: views whose reprojection residual exceeds this many network-input pixels are left
            out one at a time (:func:`s3k.readout.reject_outliers`); None: every view.
        layout, layout_tol: a rigid object's ``(K, K)`` reference distances and the relative tolerance
            keypoints are held to (:func:`s3k.readout.reject_layout`); None or 0: no rigid read-out.
        layout_search: look again for a keypoint that breaks the layout where the layout puts it
            (:func:`s3k.readout.search_layout`; needs a window).
        layout_ties: with the search, settle the check's ties by the heatmaps
            (:func:`s3k.readout.settle_ties`); False: the check's own choice, the first keypoint of the pair.
        layout_prior: with the search, a two-pass detector's refining read-out scores the places with the
            coarse pass's heatmaps too (:class:`s3k.readout.LayoutPrior`).
        layout_drop: a keypoint that breaks the layout is not valid.
        layout_fit: ``"all"``: the layout fitted onto the kept keypoints (:func:`s3k.readout.fit_layout`)
            places every keypoint; ``"kept"``: it moves only the kept ones; ``"off"``: no fit.
    """

    window: int | None = None
    min_weight: float = DEFAULT_MIN_WEIGHT
    confidence: ConfidenceMap | None = None
    max_residual_px: float | None = None
    layout: Tensor | None = None
    layout_tol: float = 0.0
    layout_search: bool = True
    layout_ties: bool = True
    layout_prior: bool = True
    layout_drop: bool = False
    layout_fit: LayoutFit = "all"

    @property
    def rigid(self) -> bool:
        """Whether the rigid read-out is on."""
        return self.layout is not None and self.layout_tol > 0

    @classmethod
    def for_pseudo_labels(cls, max_residual_px: float | None = None, window: int | None = None,
                          layout: Tensor | None = None, layout_tol: float = 0.0,
                          layout_fit: bool = False) -> ReadoutConfig:
        """The pseudo-labels' read-out (module docstring): every view, no search, layout-breaking
        keypoints dropped, the layout fitted onto the kept ones with ``layout_fit``."""
        return cls(window=window, max_residual_px=max_residual_px, layout=layout, layout_tol=layout_tol,
                   layout_search=False, layout_drop=True, layout_fit="kept" if layout_fit else "off")

    @classmethod
    def of_training(cls, s: SelfSupervisionConfig, layout: Tensor | None = None) -> ReadoutConfig:
        """The pseudo-labels' read-out of a training configuration's self-supervision section
        (``--outlier-px``, ``--pseudo-window``, ``--layout-tol``, ``--layout-fit``) with the labelled layout
        ``layout``."""
        return cls.for_pseudo_labels(max_residual_px=s.outlier_px or None, window=s.pseudo_window,
                                     layout=layout if s.layout_tol > 0 else None, layout_tol=s.layout_tol,
                                     layout_fit=s.layout_fit)
