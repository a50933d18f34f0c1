"""Results of ``s3k experiment`` runs made up for the tests of its summaries: one run's result and a summary
as written before the millimetre fields."""

from __future__ import annotations

import json

import s3k.experiments as ex


def fake_result(params: dict, rms_px: float, size: int = 64, split_train: bool = False) -> dict:
    metrics = {"rms_px": rms_px, "rms_px_reproj": rms_px / 2, "median_mm": 3 * rms_px, "rms_mm": 4 * rms_px}
    return {"run": json.dumps(params), "params": params, "status": "done", "image_size": [size, size],
            "config": {"steps": 10}, "wall_time_s": {"total": 1.0},
            "metrics": {"test": dict(metrics), **({"train": dict(metrics)} if split_train else {})}}


#: A pixel size for the fake results (image size -> mm per pixel at the workspace centre).
MM_PER_PX = {64: 6.0}


def old_summary(points: list[dict]) -> dict:
    """A summary as written before the millimetre fields: pixel errors x 400 / size, no mm_per_px."""
    for p in points:
        for m in ("rms_px", "rms_px_reproj"):
            st, k = p["test"][m], 400 / p["image_size"][0]
            p["test"][f"{m}_400"] = dict(st, mean=st["mean"] * k, std=st["std"] * k,
                                         values=[v * k for v in st["values"]])
        for m in ("rms_mm_2d", "rms_mm_2d_reproj"):
            del p["test"][m]
    return {"experiment": "label-efficiency", "description": "", "runs": len(points) * 3, "scales": ["small"],
            "image_sizes": [64], "steps": [10], "paper": {"image_size": 400, "steps": 150000},
            "error_metric": "rms_px_400: rms_px x 400 / image size (pixels at the paper's image scale)",
            "points": points, "findings": ex.findings("label-efficiency", points, metric="rms_px_400"),
            "generated_at": "2026-11-30T03:40:41Z", "commands": ["s3k experiment label-efficiency --out W"],
            "code_revisions": ["728e85c"], "runs_without_provenance": 0, "figures": ["error_vs_labelled.png"]}
