"""A trained run's help in labelling: its predictions as suggestions, and frames ranked by its doubt.

The run's :class:`s3k.detector.Detector` (one pass or two) reads each frame as ``s3k predict`` does, with
results in the dataset's own pixels. A frame's
suggestion for each view is the reprojection of the confidence-weighted 3D point (the view's own detection
where no point could be triangulated).

Frames are ranked by the model's multi-view disagreement, worst first: for keypoint ``k``, with view
residuals ``r_ck`` (pixels between a view's detection and the reprojection of the weighted point) and
confidence weights ``w_ck``,

    doubt_k = (sum_c w_ck r_ck / sum_c w_ck + max_c r_ck) / sigma + (1 - mean_c w_ck)

(``sigma`` the run's target width in the dataset's pixels, through the frame's map onto the network's
input): the weighted residual of the triangulation, the
view that disagrees most, and low confidence. A keypoint that cannot be triangulated counts as
``DOUBT_INVALID``. A frame's score is the mean over its keypoints.

Doubt cannot see an error all views share (a point detected consistently in the wrong place, a symmetric
object taken the wrong way round): labels of the poses the labelled frames do not show are what correct it.
The coverage order (:func:`coverage_order`) ranks frames by how far the run's 3D keypoints are from every
labelled frame's pose: the RMS distance between the two frames' keypoints once both are centred on the
keypoints they share and turned about the vertical (the table's normal, world z in s3k's scenes) to fit best
(:func:`pose_distances`), so it measures how the object rests, not where it stands or which way it faces: a
box lying lid up is one pose whatever its heading, and each face it can rest on is a pose of its own. It is
greedy: each frame taken counts as labelled for the ones after it, so the first frames are as far from the
labelled poses and from each other as possible. That favours the rarest poses, at the edges of
what the object does; the representative order (:func:`representative_order`) weighs each pose by how many
frames show it instead, so a few labels taken down it spread over the poses in proportion.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import numpy as np

from s3k.base.errors import UserError
from s3k.data import Dataset
from s3k.data.frames import FrameStore
from s3k.detector import detect_store
from s3k.inference.session import RigSession

__all__ = ["DOUBT_INVALID", "POSE_ORDERS", "UP", "Suggestions", "Up", "coverage_order", "pose_distances",
           "representative_order"]

DOUBT_INVALID = 100.0


#: A world direction (the table's normal), or None for none.
Up = tuple[float, float, float] | None

#: The world direction of the table's normal in s3k's own scenes (world z up), about which the pose orders
#: ignore the object's turn by default.
UP: Up = (0.0, 0.0, 1.0)


def pose_distances(X: np.ndarray, ref: np.ndarray, up: Up = None) -> np.ndarray:
    """``(N,)`` RMS distance between the keypoints of each ``X (N, K, 3)`` and ``ref (K, 3)`` after centring
    both on the keypoints finite in both (NaN: fewer than two shared). With ``up`` (a world direction, e.g.
    the table's normal), each ``X`` is first turned about ``up`` to fit ``ref`` best, so the distance ignores
    the object's heading: a box lying lid up is the same pose whichever way it faces.

    The best turn has a closed form: with the centred keypoints' components across ``up`` written as complex
    numbers ``a_k``, ``b_k`` and along it ``a'_k``, ``b'_k``, the turn by ``theta`` leaves the squared
    distance ``sum |a_k|^2 + |b_k|^2 + (a'_k - b'_k)^2 - 2 Re(e^{i theta} sum a_k conj(b_k))``, least where
    the last term is ``2 |sum a_k conj(b_k)|``."""
    X = np.asarray(X, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    both = np.isfinite(X).all(-1) & np.isfinite(ref).all(-1)[None]  # (N, K)
    n = both.sum(-1)
    w = both[..., None].astype(np.float64)
    A, B = np.nan_to_num(X) * w, np.nan_to_num(ref)[None] * w
    a = (A - A.sum(1, keepdims=True) / np.maximum(n, 1)[:, None, None]) * w
    b = (B - B.sum(1, keepdims=True) / np.maximum(n, 1)[:, None, None]) * w
    if up is None:
        d2 = ((a - b) ** 2).sum((1, 2))
    else:
        u = np.asarray(up, dtype=np.float64)
        u = u / np.linalg.norm(u)
        e1 = np.cross(u, np.eye(3)[int(np.argmin(np.abs(u)))])
        e1 /= np.linalg.norm(e1)
        across = np.stack([e1, np.cross(u, e1)], axis=1)  # (3, 2): a basis of the plane across up
        ca, cb = a @ across, b @ across  # (N, K, 2)
        za, zb = a @ u, b @ u  # (N, K)
        dot = (ca * cb).sum((1, 2))
        cross = (ca[..., 0] * cb[..., 1] - ca[..., 1] * cb[..., 0]).sum(1)
        d2 = (ca**2).sum((1, 2)) + (cb**2).sum((1, 2)) + ((za - zb) ** 2).sum(1) - 2 * np.hypot(dot, cross)
    d2 = np.maximum(d2, 0.0) / np.maximum(n, 1)
    return np.where(n >= 2, np.sqrt(d2), np.nan)


def coverage_order(candidates: dict[int, np.ndarray], covered: list[np.ndarray],
                   limit: int | None = None, up: Up = UP) -> list[tuple[int, float]]:
    """Frames of ``candidates`` (``{frame: X (K, 3)}``, NaN where not placed) in the greedy coverage order
    (module docstring), ``[(frame, distance)]``: each frame's :func:`pose_distances` to the nearest of
    ``covered`` (``(K, 3)`` poses: the labelled frames') and of the frames before it. The first ``limit``
    are picked greedily, the rest follow by that distance; frames with fewer than two keypoints placed come
    last, with NaN. The distance is ``inf`` while nothing is covered. Poses are compared blind to the turn
    about ``up`` (None: not blind to it)."""
    ids = np.asarray(sorted(candidates), dtype=np.int64)
    if not len(ids):
        return []
    X = np.stack([np.asarray(candidates[int(f)], dtype=np.float64) for f in ids])
    placed = np.isfinite(X).all(-1).sum(-1) >= 2
    near = np.full(len(ids), np.inf)
    for ref in covered:
        d = pose_distances(X, ref, up)
        near = np.where(np.isfinite(d), np.minimum(near, d), near)
    order: list[tuple[int, float]] = []
    left = placed.copy()
    for _ in range(len(ids) if limit is None else min(limit, len(ids))):
        if not left.any():
            break
        i = int(np.flatnonzero(left)[np.argmax(near[left])])  # the first of the farthest (ids are sorted)
        order.append((int(ids[i]), float(near[i])))
        left[i] = False
        d = pose_distances(X, X[i], up)
        near = np.where(np.isfinite(d), np.minimum(near, d), near)
    rest = np.flatnonzero(left)
    order += [(int(ids[i]), float(near[i])) for i in rest[np.argsort(-near[rest], kind="stable")]]
    order += [(int(f), float("nan")) for f in ids[~placed]]
    return order


#: At most this many frames stand for the poses to be covered in :func:`representative_order` (evenly spaced
#: in frame order), so its cost grows linearly with the candidates.
REPRESENTATIVE_SAMPLE = 500


def representative_order(candidates: dict[int, np.ndarray], covered: list[np.ndarray],
                         limit: int | None = None, up: Up = UP, sample: int = REPRESENTATIVE_SAMPLE
                         ) -> list[tuple[int, float]]:
    """Frames of ``candidates`` (as for :func:`coverage_order`) in the greedy representative order: each next
    frame is the one that most lowers the sum, over the candidates' poses, of the :func:`pose_distances` to
    the nearest labelled (``covered``) or already taken pose. Unlike :func:`coverage_order`, which takes the
    farthest pose first (the rarest, at the edges of what the object does), it weighs each pose by how many
    frames show it: ten frames taken this way spread over the poses in proportion to how often each occurs,
    and each stands for the frames around it. ``[(frame, distance)]`` with ``distance`` the frame's pose
    distance to the nearest covered or earlier frame (``inf`` while nothing is covered); the first ``limit``
    are taken greedily (when ``limit`` is None, until every sampled pose is covered and no frame lowers the
    sum), the rest follow by what they would lower the sum; frames with fewer than two keypoints
    placed come last, with NaN. At most ``sample`` frames, evenly spaced, stand for the poses. Poses are
    compared blind to the turn about ``up`` (None: not blind to it)."""
    ids = np.asarray(sorted(candidates), dtype=np.int64)
    if not len(ids):
        return []
    X = np.stack([np.asarray(candidates[int(f)], dtype=np.float64) for f in ids])
    placed = np.flatnonzero(np.isfinite(X).all(-1).sum(-1) >= 2)
    order: list[tuple[int, float]] = []
    if len(placed):
        demand = np.unique(np.linspace(0, len(placed) - 1, min(sample, len(placed))).round().astype(int))
        D = np.stack([pose_distances(X[placed], X[placed[j]], up) for j in demand], axis=1)  # placed x demand
        finite = np.isfinite(D)
        cap = float(D[finite].max()) if finite.any() else 1.0
        D = np.where(finite, D, cap)  # a pose that cannot be compared counts as the farthest
        need = np.full(len(demand), cap)  # each demand pose's distance to the nearest covered one
        near = np.full(len(placed), np.inf)  # each candidate's distance to the nearest covered one
        for ref in covered:
            d = pose_distances(X[placed], ref, up)
            near = np.where(np.isfinite(d), np.minimum(near, d), near)
            need = np.minimum(need, np.where(np.isfinite(d[demand]), d[demand], cap))
        left = np.ones(len(placed), dtype=bool)
        for _ in range(len(placed) if limit is None else min(limit, len(placed))):
            gain = np.maximum(need[None] - D, 0.0).sum(1)
            if limit is None and not gain[left].any():
                break  # every sampled pose is covered: the rest follow by gain (all zero), in frame order
            i = int(np.flatnonzero(left)[np.argmax(gain[left])])  # the first of the best (ids are sorted)
            order.append((int(ids[placed[i]]), float(near[i])))
            left[i] = False
            need = np.minimum(need, D[i])
            d = pose_distances(X[placed], X[placed[i]], up)
            near = np.where(np.isfinite(d), np.minimum(near, d), near)
        rest = np.flatnonzero(left)
        gain = np.maximum(need[None] - D[rest], 0.0).sum(1)
        order += [(int(ids[placed[i]]), float(near[i])) for i in rest[np.argsort(-gain, kind="stable")]]
    order += [(int(f), float("nan")) for f in np.delete(ids, placed)]
    return order


#: The pose orders by name, as the app's ranking and the experiments' label choice name them.
POSE_ORDERS = {"coverage": coverage_order, "representative": representative_order}


class Suggestions:
    """Predictions of the session's detector (:meth:`s3k.inference.session.RigSession.on_dataset`) on the
    frames of the dataset ``data``, computed when first asked for and kept.

    Raises:
        UserError: the run's keypoints are not all among the dataset's (names listed).
    """

    def __init__(self, session: RigSession, data: str | Path, batch_size: int = 16) -> None:
        self.detector = session.detector
        run_dir = self.detector.run
        self.batch_size = batch_size
        self.dataset = Dataset.open(data, cache="memory")
        missing = [k for k in self.detector.keypoints if k not in self.dataset.keypoints]
        if missing:
            raise UserError(f"--run {run_dir}: keypoints {missing} of the run are not in the dataset's "
                            f"{self.dataset.keypoints}",
                            hint="pass a run trained on this dataset's keypoints")
        self.keypoints = self.detector.keypoints
        self._cache: dict[int, dict[str, Any]] = {}
        self._lock = threading.Lock()

    def predict(self, frame_ids) -> dict[int, dict[str, Any]]:
        """Per frame: ``uv (C, K, 2)`` detections, ``weights (C, K)``, ``X (K, 3)``, ``valid (K,)``,
        ``reproj (C, K, 2)``, ``residual (C, K)`` in the dataset's pixels, keypoints in the run's order, and
        ``sigma_px`` the run's target width in those pixels."""
        with self._lock:
            todo = [int(f) for f in frame_ids if int(f) not in self._cache]
            if todo:
                store = FrameStore(self.dataset, todo, preload_mb=0)
                for batch, ro in detect_store(self.detector, store, self.batch_size):
                    assert ro.pixel_maps is not None
                    scale = ro.pixel_maps[..., :2, :2].det().abs().sqrt().mean(dim=1)  # (B,)
                    for b, f in enumerate(batch.frame_ids.tolist()):
                        self._cache[int(f)] = {
                            "uv": ro.uv[b].numpy(), "weights": ro.weights[b].numpy(), "X": ro.X[b].numpy(),
                            "confidence": ro.confidence[b].numpy(),
                            "valid": ro.valid[b].numpy(), "reproj": ro.reproj[b].numpy(),
                            "residual": ro.residual[b].numpy(),
                            "sigma_px": float(self.detector.meta.sigma) / float(scale[b]),
                        }
            return {int(f): self._cache[int(f)] for f in frame_ids}

    def suggestion(self, frame: int, cameras: list[str]) -> dict[str, Any]:
        """``{keypoint: {camera: {"u", "v", "weight", "confidence", "residual"}}}`` for the app (JSON-ready;
        ``confidence`` the calibrated one its accept compares)."""
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
                              "confidence": float(p["confidence"][c, k]),
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
            per_kp = np.where(p["valid"], (weighted + worst) / p["sigma_px"] + (1 - conf), DOUBT_INVALID)
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
        return _json_ready(rows)

    def coverage(self, frame_ids, labelled: list[np.ndarray], mm_per_unit: float,
                 limit: int | None = None, order: str = "coverage", up: Up = UP) -> list[dict[str, Any]]:
        """``frame_ids`` in a pose order against the ``labelled`` poses (``(K, 3)`` in world units, keypoints
        in the run's order): ``order`` "coverage" (:func:`coverage_order`) or "representative"
        (:func:`representative_order`), blind to the turn about ``up`` (None: not blind to it).
        ``[{"frame", "score", "pose_mm"}]``, the distance in millimetres to the nearest labelled or earlier
        pose as both (None: infinite or not placed)."""
        preds = self.predict(frame_ids)
        candidates = {f: np.where(p["valid"][:, None], p["X"], np.nan) for f, p in preds.items()}
        rows = [{"frame": f, "score": d * mm_per_unit, "pose_mm": d * mm_per_unit}
                for f, d in POSE_ORDERS[order](candidates, labelled, limit, up)]
        return _json_ready(rows)


def _json_ready(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """``rows`` with None for every float that is not a number."""
    for r in rows:
        for key, value in r.items():
            if isinstance(value, float) and not np.isfinite(value):
                r[key] = None
    return rows
