"""A trained run's help in labelling: its predictions as suggestions, and frames ranked by its doubt.

The detector of a run (:func:`s3k.run.load_detector`) reads each frame as ``s3k predict`` does
(:func:`s3k.predict.predict_store`, the one read-out), with results in the dataset's own pixels. A frame's
suggestion for each view is the reprojection of the confidence-weighted 3D point (the view's own detection
where no point could be triangulated).

Frames are ranked by the model's multi-view disagreement, worst first: for keypoint ``k``, with view
residuals ``r_ck`` (pixels between a view's detection and the reprojection of the weighted point) and
confidence weights ``w_ck``,

    doubt_k = (sum_c w_ck r_ck / sum_c w_ck + max_c r_ck) / sigma + (1 - mean_c w_ck)

(``sigma`` the run's target width in the dataset's pixels): the weighted residual of the triangulation, the
view that disagrees most, and low confidence. A keypoint that cannot be triangulated counts as
``DOUBT_INVALID``. A frame's score is the mean over its keypoints.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import numpy as np

from s3k.errors import UserError

__all__ = ["DOUBT_INVALID", "Suggestions"]

DOUBT_INVALID = 100.0


class Suggestions:
    """Predictions of the run ``run_dir`` on the frames of the dataset ``data``, computed when first asked
    for and kept.

    Raises:
        UserError: the run's keypoints are not all among the dataset's (names listed).
    """

    def __init__(self, run_dir: str | Path, data: str | Path, device: str = "cpu",
                 batch_size: int = 16) -> None:
        from s3k.data import Dataset
        from s3k.run import load_detector

        self.model, self.meta = load_detector(run_dir, device)
        self.device = device
        self.batch_size = batch_size
        full = Dataset.open(data, cache="memory")
        missing = [k for k in self.meta.keypoints if k not in full.keypoints]
        if missing:
            raise UserError(f"--run {run_dir}: keypoints {missing} of the run are not in the dataset's "
                            f"{full.keypoints}", hint="pass a run trained on this dataset's keypoints")
        self.keypoints = list(self.meta.keypoints)
        self.dataset = full.resized(self.meta.image_size)
        # sigma in the dataset's pixels: the network's pixels are the dataset's scaled by the pixel map
        scale = float(np.sqrt(abs(np.linalg.det(self.dataset.pixel_map[:2, :2]))))
        self.sigma_px = float(self.meta.sigma) / scale
        self._cache: dict[int, dict[str, np.ndarray]] = {}
        self._lock = threading.Lock()

    def predict(self, frame_ids) -> dict[int, dict[str, np.ndarray]]:
        """Per frame: ``uv (C, K, 2)`` detections, ``weights (C, K)``, ``X (K, 3)``, ``valid (K,)``,
        ``reproj (C, K, 2)``, ``residual (C, K)``, in the dataset's pixels, keypoints in the run's order."""
        from s3k.frames import FrameStore
        from s3k.predict import predict_store

        with self._lock:
            todo = [int(f) for f in frame_ids if int(f) not in self._cache]
            if todo:
                store = FrameStore(self.dataset, todo, preload_mb=0)
                pixel_map = self.dataset.pixel_map
                for batch, ro in predict_store(self.model, self.meta, store, self.batch_size, self.device,
                                               pixel_map=pixel_map):
                    for b, f in enumerate(batch.frame_ids.tolist()):
                        self._cache[int(f)] = {
                            "uv": ro.uv[b].numpy(), "weights": ro.weights[b].numpy(), "X": ro.X[b].numpy(),
                            "valid": ro.valid[b].numpy(), "reproj": ro.reproj[b].numpy(),
                            "residual": ro.residual[b].numpy(),
                        }
            return {int(f): self._cache[int(f)] for f in frame_ids}

    def suggestion(self, frame: int, cameras: list[str]) -> dict[str, Any]:
        """``{keypoint: {camera: {"u", "v", "weight", "residual"}}}`` for the app (JSON-ready)."""
        p = self.predict([frame])[frame]
        out: dict[str, Any] = {}
        for k, kp in enumerate(self.keypoints):
            views = {}
            for c, cam in enumerate(cameras):
                at = p["reproj"][c, k] if p["valid"][k] else p["uv"][c, k]
                if not np.isfinite(at).all():
                    continue
                res = p["residual"][c, k]
                views[cam] = {"u": float(at[0]), "v": float(at[1]), "weight": float(p["weights"][c, k]),
                              "residual": float(res) if np.isfinite(res) else None}
            out[kp] = views
        return out

    def doubt(self, frame_ids) -> dict[int, dict[str, float]]:
        """The ranking score of each frame (module docstring) with its parts."""
        preds = self.predict(frame_ids)
        out = {}
        for f, p in preds.items():
            w, r = p["weights"], np.nan_to_num(p["residual"], nan=0.0)
            wsum = np.maximum(w.sum(axis=0), 1e-12)
            weighted = (w * r).sum(axis=0) / wsum
            worst = r.max(axis=0)
            conf = w.mean(axis=0)
            per_kp = np.where(p["valid"], (weighted + worst) / self.sigma_px + (1 - conf), DOUBT_INVALID)
            valid = p["valid"]
            out[f] = {"score": float(per_kp.mean()),
                      "residual_px": float(weighted[valid].mean()) if valid.any() else float("nan"),
                      "worst_view_px": float(worst[valid].max()) if valid.any() else float("nan"),
                      "confidence": float(conf.mean()), "invalid": int((~valid).sum())}
        return out

    def ranking(self, frame_ids) -> list[dict[str, Any]]:  # JSON-ready: None where not a number
        """``frame_ids`` ordered by doubt, worst first: ``[{"frame", "score", ...}]``."""
        scores = self.doubt(frame_ids)
        rows: list[dict[str, Any]] = [{"frame": f, **s} for f, s in scores.items()]
        rows.sort(key=lambda r: (-r["score"], r["frame"]))
        for r in rows:
            for key, value in r.items():
                if isinstance(value, float) and not np.isfinite(value):
                    r[key] = None
        return rows
