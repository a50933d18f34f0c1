"""The read-out: heatmap logits -> 2D detections, confidences and 3D keypoints (everything after the network).

Every caller uses these functions: ``s3k predict``, ``s3k evaluate``, ``s3k track``, ``s3k export
--with-moments``, :func:`s3k.model.detect`, the self-supervised loss (:mod:`s3k.train.losses`) and the
inference benchmarks, so what is trained, scored and shipped is the same maths (docs/method.md, "Heatmaps",
"Confidence", "Triangulation"). Per view ``c`` and keypoint ``k``:

1. :func:`moments`: the spatial softmax ``P_ck`` of the logits, its mean ``m_ck`` within a window around
   its most probable cell (the 2D detection, in the network-input pixels, pixel (0, 0) the centre of the
   top-left pixel) and its variance ``var_ck`` over the whole heatmap.
2. :func:`s3k.readout.heatmaps.confidence_weight`: the confidence weight ``w_ck`` from the spread, and the
   run's calibration of it (:class:`ConfidenceMap`), the confidence ``c_ck``.
3. :func:`select_views`: which views enter the triangulation.
4. :func:`triangulate`: the confidence-weighted triangulation of the selected views (lens distortion
   included), valid where at least two views are used and the rays are not near-parallel.
5. :func:`read_out` also maps the detections into the cameras' own pixels (``pixel_maps``), reprojects the
   3D point into every camera and measures the reprojection residuals.

Window: the whole heatmap's mean is pulled towards the heatmap's centre by whatever probability is spread over
the rest of it (a second bright spot, a diffuse tail), so every read-out takes the mean within
:func:`window_cells` of the peak: ``WINDOW_SIGMAS`` target widths, which holds all of a well-formed peak
(a narrower window cut into it would pull the mean towards the peak's cell). Training's pseudo-labels do
the same (``--pseudo-window``). The variance, and so the confidence, stays the whole heatmap's: spread mass
is what makes a view uncertain.

Precision: float64 from the softmax on, whatever the logits' dtype. The mean is a sum over ``h * w`` cells
and the triangulation solves normal equations whose conditioning degrades with near-parallel rays; float64
makes both independent of summation order and of the runtime (PyTorch, ONNX Runtime, TorchScript give the
same points up to their logits), and its cost is negligible next to the network. Results are float64.

View selection: a view is used when its mean and weight are finite and its calibrated confidence
(:mod:`s3k.readout.confidence`: the run's map of the weight to the share of views within two target widths of
the truth, fitted on its validation frames; the weight itself for a run without one) is above
``min_weight``; used views are weighted by their confidence weight ``w``. The default ``min_weight = 0`` uses
every view, weighted: the paper's rule and the one training's self-supervised target uses, so that ``s3k
evaluate`` scores exactly the points ``s3k predict`` and ``s3k track`` write. A higher threshold (``s3k track
--min-weight``) drops uncertain views outright instead of down-weighting them: 0.5 keeps the views of which
at least half are right, whatever the run's weights.
:func:`reject_outliers` (``max_residual_px``) also drops views that miss the other views' consensus;
:func:`reject_layout` drops 3D keypoints whose distances to the others break a rigid object's layout;
:func:`coarse_stands_in` gives a two-pass detector's coarse read-out to a frame whose refining points still
break it.
"""

from s3k.readout.confidence import CALIBRATION_SIGMAS, ConfidenceMap, fit_confidence, reliability
from s3k.readout.config import LAYOUT_FITS, ReadoutConfig
from s3k.readout.pipeline import ReadOut, breaks_layout, coarse_stands_in, read_out
from s3k.readout.rigid import (
    LAYOUT_SAMPLES,
    LayoutPrior,
    fit_layout,
    layout_locus,
    layout_shape,
    reject_layout,
    search_layout,
    settle_ties,
)
from s3k.readout.views import (
    DEFAULT_MIN_WEIGHT,
    DTYPE,
    WINDOW_SIGMAS,
    moments,
    reject_outliers,
    select_views,
    triangulate,
    window_cells,
)

__all__ = [
    "CALIBRATION_SIGMAS", "ConfidenceMap", "fit_confidence", "reliability",
    "DEFAULT_MIN_WEIGHT", "DTYPE", "LAYOUT_FITS", "LAYOUT_SAMPLES", "WINDOW_SIGMAS", "LayoutPrior", "ReadOut",
    "ReadoutConfig", "breaks_layout", "coarse_stands_in", "fit_layout", "layout_locus", "layout_shape",
    "moments", "read_out", "reject_layout",
    "reject_outliers",
    "search_layout", "select_views", "settle_ties", "triangulate", "window_cells",
]
