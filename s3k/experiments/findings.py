"""Statistics over seeds and the paper's findings checked against them.

:func:`aggregate` turns run results into grid points (mean, std and values over seeds of every metric, the
per-view pixel errors also in millimetres on the object); :func:`findings` states each of the paper's claims
with the numbers measured here and a verdict: True, False, "within noise" (see :func:`lower`) or None when a
point it needs is missing.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from typing import Any, cast

import numpy as np

from s3k.experiments.grid import PAPER_CATEGORY_TEST_PX, PAPER_MM_PER_PX

METRICS = ("rms_px", "rms_px_reproj", "median_mm", "rms_mm", "pck_5mm", "pck_10mm")

#: Per-view errors in millimetres on the object: the pixel error they derive from (x the scene's mm_per_px).
MM_2D = {"rms_mm_2d": "rms_px", "rms_mm_2d_reproj": "rms_px_reproj"}

#: How a finding names the unit of its metric.
UNITS = {"rms_mm_2d": "mm (per-view RMS)", "rms_mm_2d_reproj": "mm (reprojection RMS)", "rms_px": "px",
         "rms_px_reproj": "px", "median_mm": "mm (median 3D)", "rms_mm": "mm (RMS 3D)"}

Verdict = bool | str | None


def paper_mm(px: float) -> float:
    """A pixel figure of the paper (400 px images) in millimetres at its workspace centre."""
    return px * PAPER_MM_PER_PX


def fmt(v: Any, digits: int = 2) -> str:
    """A number with ``digits`` decimals; "-" for None or a non-finite value."""
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.{digits}f}"


def _stats(values: Sequence[float | None]) -> dict[str, Any]:
    v = np.asarray([x for x in values if x is not None and math.isfinite(x)], dtype=np.float64)
    if not v.size:
        return {"mean": None, "std": None, "n": 0, "values": []}
    return {"mean": float(v.mean()), "std": float(v.std(ddof=1)) if v.size > 1 else None, "n": int(v.size),
            "values": [float(x) for x in v]}


def _scaled(s: dict[str, Any], factor: float | None) -> dict[str, Any]:
    """Statistics from :func:`_stats` of a quantity times ``factor`` (none when ``factor`` is None)."""
    if factor is None or s.get("mean") is None:
        return _stats([])
    return {"mean": s["mean"] * factor, "std": None if s.get("std") is None else s["std"] * factor,
            "n": s["n"], "values": [v * factor for v in s["values"]]}


def add_mm(point: dict[str, Any], mm_per_px: Mapping[int, float | None]) -> dict[str, Any]:
    """Give each split of a grid point the per-view errors in millimetres (:data:`MM_2D`).

    ``rms_mm_2d = rms_px x mm_per_px[image size]``: the per-view error at the workspace centre, in mm on the
    object, which compares across image sizes, cameras and with the paper. The pixel errors scaled to the
    paper's image size that summaries used to hold (``rms_px_400``, ``rms_px_reproj_400``) are dropped: image
    size alone does not make pixels comparable.
    """
    factor = mm_per_px.get(point["image_size"][0])
    for block in point.values():
        if isinstance(block, dict) and "rms_px" in block:
            for name, px in MM_2D.items():
                block[name] = _scaled(block[px], factor)
            for old in ("rms_px_400", "rms_px_reproj_400"):
                block.pop(old, None)
    return point


def aggregate(results: Sequence[dict[str, Any]], mm_per_px: Mapping[int, float | None]
              ) -> list[dict[str, Any]]:
    """One entry per grid point (params without the seed): statistics over seeds of every metric.

    ``mm_per_px`` maps an image size to the size of a pixel of the experiment's scene at its workspace
    centre; each split also gets the per-view errors in millimetres from it (:func:`add_mm`). Runs that did
    not finish normally (status other than "done") are listed, not averaged.
    """
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in results:
        key = json.dumps({k: v for k, v in r["params"].items() if k != "seed"}, sort_keys=True)
        groups.setdefault(key, []).append(r)
    points = []
    for key, rs in groups.items():
        ok = [r for r in rs if r["status"] == "done"]
        point: dict[str, Any] = {"params": json.loads(key), "seeds": sorted(r["params"]["seed"] for r in ok),
                                 "not_done": {r["run"]: r["status"] for r in rs if r["status"] != "done"},
                                 "image_size": rs[0]["image_size"], "steps": rs[0]["config"]["steps"],
                                 "wall_time_s": _stats([r["wall_time_s"]["total"] for r in rs])["mean"]}
        for split in sorted({s for r in ok for s in r["metrics"]}):
            point[split] = {m: _stats([r["metrics"][split].get(m) for r in ok if split in r["metrics"]])
                            for m in METRICS}
        points.append(add_mm(point, mm_per_px))
    order = ("mode", "instances", "labelled", "alpha", "unlabelled")

    def sort_key(p: dict[str, Any]) -> tuple:
        vals = [p["params"].get(k) for k in order]
        return tuple((0, v, "") if isinstance(v, (int, float)) else (1, 0, str(v)) for v in vals)

    points.sort(key=sort_key)
    return points


def param_values(points: Sequence[dict[str, Any]], key: str) -> list:
    """The sorted distinct values of grid coordinate ``key`` over ``points``."""
    return sorted({p["params"][key] for p in points if key in p["params"]})


def _stat(points, split: str, metric: str, **params) -> dict[str, Any] | None:
    """Statistics of ``metric`` on ``split`` at the point with ``params`` (None when absent)."""
    for p in points:
        if all(p["params"].get(k) == v for k, v in params.items()) and split in p:
            return p[split][metric] if p[split][metric]["mean"] is not None else None
    return None


def lower(a: dict[str, Any] | None, b: dict[str, Any] | None, rel: float = 0.02) -> Verdict:
    """Is error ``a`` below error ``b`` by more than the noise?

    The margin is the larger of ``rel`` of the larger mean and two standard errors of the difference (from
    the seeds' spread; a single seed contributes none).

    Returns:
        True (lower), False (higher), "within noise", or None when either is missing.
    """
    if a is None or b is None:
        return None

    def se2(s: dict[str, Any]) -> float:
        return (s["std"] ** 2 / s["n"]) if s.get("std") is not None and s["n"] > 1 else 0.0

    margin = max(rel * max(abs(a["mean"]), abs(b["mean"])), 2.0 * math.sqrt(se2(a) + se2(b)))
    if a["mean"] < b["mean"] - margin:
        return True
    if a["mean"] > b["mean"] + margin:
        return False
    return "within noise"


def _smaller(x: float, y: float, tol: float) -> bool | str:
    """x < y by more than ``tol``: True; x > y by more than ``tol``: False; else "within noise"."""
    return True if x < y - tol else False if x > y + tol else "within noise"


def _all(verdicts: Sequence[Verdict]) -> Verdict:
    """Combine verdicts of a chain: False if any is False, True if all are True, else unclear/None."""
    if not verdicts or any(v is None for v in verdicts):
        return None
    if any(v is False for v in verdicts):
        return False
    return True if all(v is True for v in verdicts) else "within noise"


def mean_std(s: dict[str, Any] | None) -> str:
    """``mean +- std`` of statistics from :func:`aggregate` (``mean`` alone with one seed; "-" if none)."""
    if s is None or s["mean"] is None:
        return "-"
    return fmt(s["mean"]) + (f" +- {fmt(s['std'])}" if s.get("std") is not None else "")


def findings(experiment: str, points: list[dict[str, Any]],
             metric: str = "rms_mm_2d") -> list[dict[str, Any]]:
    """The paper's findings checked against these points, on ``metric`` (default: the per-view error in mm).

    Each claim compares errors of one experiment, measured at one image size and scene, so a verdict does not
    depend on the unit: pixels and the millimetres they convert to at one pixel size give the same verdicts.

    Returns:
        ``[{"finding", "measured", "reproduced"}]``; ``reproduced`` is True, False, "within noise" (see
        :func:`lower`) or None when a point it needs is missing.
    """
    out: list[dict[str, Any]] = []

    def add(text: str, measured: str, holds: Verdict) -> None:
        out.append({"finding": text, "measured": measured, "reproduced": holds})

    unit = UNITS.get(metric, metric)
    if experiment == "label-efficiency":
        Us = param_values(points, "unlabelled")
        u_max = max(Us) if Us else 0
        for L in param_values(points, "labelled"):
            base = _stat(points, "test", metric, labelled=L, unlabelled=0)
            s3k = _stat(points, "test", metric, labelled=L, unlabelled=u_max) if u_max else None
            add(f"S3K with {u_max} unlabelled frames beats labels only at {L} labelled",
                f"{mean_std(s3k)} vs {mean_std(base)} {unit}", lower(s3k, base))
        for L in (3, 10):
            errs = [_stat(points, "test", metric, labelled=L, unlabelled=U) for U in Us]
            if len(Us) >= 3 and all(e is not None for e in errs):
                add(f"more unlabelled frames, lower error ({L} labelled; unlabelled {Us})",
                    " > ".join(mean_std(e) for e in errs) + f" {unit}",
                    _all([lower(b, a) for a, b in zip(errs, errs[1:])]))
    elif experiment == "domain-shift":
        Us = param_values(points, "unlabelled")
        u_max = max(Us) if Us else 0
        for L in param_values(points, "labelled"):
            for mode in ("start", "full"):
                base = _stat(points, "test", metric, mode=mode, labelled=L, unlabelled=0)
                s3k = (_stat(points, "test", metric, mode=mode, labelled=L, unlabelled=u_max) if u_max
                       else None)
                add(f"{mode} mode, {L} labelled: unlabelled frames over the whole timeline lower the error "
                    "on unseen distractors", f"{mean_std(s3k)} vs {mean_std(base)} {unit}", lower(s3k, base))
            st0 = _stat(points, "test", metric, mode="start", labelled=L, unlabelled=0)
            fu0 = _stat(points, "test", metric, mode="full", labelled=L, unlabelled=0)
            add(f"{L} labelled, labels only: labels from the first distractor set only (start) generalize "
                "worse than labels over the whole timeline (full)",
                f"{mean_std(st0)} vs {mean_std(fu0)} {unit}", lower(fu0, st0))
            if u_max:
                st = _stat(points, "test", metric, mode="start", labelled=L, unlabelled=u_max)
                fu = _stat(points, "test", metric, mode="full", labelled=L, unlabelled=u_max)
                if st is not None and fu is not None and st0 is not None and fu0 is not None:
                    # gap = start - full: how much worse the start labels generalize. It can only narrow if
                    # there is one without unlabelled frames; "narrower" compares sizes, so a start model
                    # that overtakes full by more than the gap was does not count as closing it.
                    g1, g0 = st["mean"] - fu["mean"], st0["mean"] - fu0["mean"]
                    tol = 0.02 * max(st["mean"], st0["mean"])
                    add(f"{L} labelled: self-supervision narrows the start-vs-full gap",
                        f"gap (start - full) {fmt(g1)} with vs {fmt(g0)} without {unit}",
                        _smaller(abs(g1), g0, tol) if g0 > tol else "no gap without unlabelled frames")
    elif experiment == "category":
        ns = param_values(points, "instances")
        if len(ns) >= 2:
            lo = _stat(points, "test", metric, instances=ns[0])
            hi = _stat(points, "test", metric, instances=ns[-1])
            add(f"more training instances, lower error on the held-out instances ({ns[0]} vs {ns[-1]})",
                f"{mean_std(lo)} -> {mean_std(hi)} {unit} (paper {_paper(ns[0], metric)} -> "
                f"{_paper(ns[-1], metric)})", lower(hi, lo))
            tr = [_stat(points, "train", metric, instances=n) for n in ns]
            te = [_stat(points, "test", metric, instances=n) for n in ns]
            if all(v is not None for v in tr + te):
                trs, tes = cast(list[dict[str, Any]], tr), cast(list[dict[str, Any]], te)
                g0, g1 = tes[0]["mean"] - trs[0]["mean"], tes[-1]["mean"] - trs[-1]["mean"]
                add("the gap between training and held-out instances shrinks with more instances",
                    f"held-out - training: {fmt(g0)} ({ns[0]}) -> {fmt(g1)} ({ns[-1]}) {unit}",
                    _smaller(g1, g0, 0.02 * tes[0]["mean"]))
    elif experiment == "alpha":
        alphas = param_values(points, "alpha")
        best: dict[Any, Any] = {}  # labelled -> the alpha of the lowest error
        for L in param_values(points, "labelled"):
            by_alpha = {a: _stat(points, "test", metric, labelled=L, alpha=a) for a in alphas}
            found = {a: e for a, e in by_alpha.items() if e is not None}
            if found:
                best[L] = min(found, key=lambda a: found[a]["mean"])
        if len(best) >= 2:
            l_lo, l_hi = min(best), max(best)
            add(f"small alpha is best with few labels, alpha near 1 with more ({l_lo} vs {l_hi} labelled)",
                f"best alpha {best[l_lo]:g} at {l_lo} labelled, {best[l_hi]:g} at {l_hi}",
                best[l_lo] < best[l_hi] if best[l_lo] != best[l_hi] else False)
    return out


def _paper(instances: int, metric: str) -> str:
    """The paper's held-out error at ``instances`` training instances in the unit of ``metric``."""
    px = PAPER_CATEGORY_TEST_PX.get(instances)
    if px is None:
        return "-"
    return f"{fmt(paper_mm(px), 1)} mm" if metric in MM_2D else f"{px} px at 400 px"


def verdict(reproduced: Verdict) -> str:
    """Text of a finding's verdict: yes, no, within noise, not measured."""
    if reproduced is None:
        return "not measured"
    if isinstance(reproduced, str):
        return reproduced
    return "yes" if reproduced else "no"
