"""Clicks needed to label a frame in ``s3k label``, counted by driving the app's API with a simulated labeller
(``benchmarks/label_clicks.py``; the ways of working: docs/labelling.md).

The labeller knows where each keypoint truly is (:func:`ground_truth`: the projection of the dataset's 3D
points, visible where the scene says so) and clicks it with Gaussian noise; :func:`run_way` labels frames one
way (``every_view``, ``reprojection`` or ``suggestions``) on a fresh copy of the labels and scores it by the
clicks per frame and the 3D error of the triangulated labels.
"""

from __future__ import annotations

import shutil
import tempfile
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch

from s3k.data import Dataset
from s3k.geometry import project


def ground_truth(data: Path) -> dict[str, Any]:
    """``uv (N, C, K, 2)`` true projections, ``visible (N, C, K)`` (the dataset's labels), ``points (N, K,
    3)``, ``frames (N,)`` of a simulated dataset."""

    ds = Dataset.open(data, cache="none")
    ids = ds.frames()
    got = ds.points3d(ids)
    if got is None:
        raise SystemExit(f"{data}: no points3d.csv; use a simulated dataset")
    X, X_mask = got
    cams = ds.calibration(ids, np.float64)
    C = len(ds.cameras)
    uv, _ = project(cams, torch.as_tensor(X, dtype=torch.float64)[:, None].expand(-1, C, -1, -1))
    _, visible = ds.labels(ids)
    return {"frames": ids, "uv": uv.numpy(), "visible": visible & X_mask[:, None], "points": X.astype(float),
            "cameras": ds.cameras, "keypoints": ds.keypoints, "size": ds.source_image_size, "units": ds.units}


class Labeller:
    """Counts the clicks (requests that a person's click or drag would make) of one way of working."""

    def __init__(self, client, truth: dict[str, Any], noise: float, tol: float, seed: int) -> None:
        self.client, self.t, self.noise, self.tol = client, truth, noise, tol
        self.rng = np.random.default_rng(seed)
        self.clicks = 0
        self.accepted = 0  # keypoints whose suggestion was accepted as it was
        self.suggestion_px: list[float] = []  # suggestion errors in views where the keypoint is visible

    def state(self, frame: int) -> dict[str, Any]:
        return self.client.get(f"/api/frame/{frame}").json()

    def post(self, frame: int, edits: list[dict[str, Any]], source: str) -> dict[str, Any]:
        version = self.state(frame)["version"]
        # the simulated labeller may label test frames too: it unlocks them, as a person would in the page
        r = self.client.post(f"/api/frame/{frame}/label", json={"version": version, "edits": edits,
                                                                 "source": source, "unlock": True})
        if r.status_code != 200:
            raise RuntimeError(r.text)
        self.clicks += 1
        return r.json()

    def aim(self, i: int, c: int, k: int) -> dict[str, Any]:
        W, H = self.t["size"]
        u, v = self.t["uv"][i, c, k] + self.rng.normal(0.0, self.noise, 2)
        return {"camera": self.t["cameras"][c], "keypoint": self.t["keypoints"][k],
                "u": float(np.clip(u, -0.5, W - 0.5)), "v": float(np.clip(v, -0.5, H - 0.5))}

    def off(self, i: int, c: int, k: int, at) -> bool:
        return at is None or float(np.linalg.norm(np.asarray(at) - self.t["uv"][i, c, k])) > self.tol

    def every_view(self, i: int, frame: int) -> None:
        C, K = self.t["visible"].shape[1:]
        for k in range(K):
            for c in range(C):
                if self.t["visible"][i, c, k]:
                    self.post(frame, [self.aim(i, c, k)], "click")

    def reprojection(self, i: int, frame: int) -> None:
        for k in range(self.t["visible"].shape[2]):
            self.reprojection_keypoint(i, frame, k)

    def reprojection_keypoint(self, i: int, frame: int, k: int) -> None:
        C = self.t["visible"].shape[1]
        seen = [c for c in range(C) if self.t["visible"][i, c, k]]
        clicked = seen[:2]
        for c in clicked:
            state = self.post(frame, [self.aim(i, c, k)], "click")
        while len(seen) >= 2:
            views = state["geometry"][self.t["keypoints"][k]]["views"]
            wrong = [c for c in seen if c not in clicked
                     and self.off(i, c, k, views[self.t["cameras"][c]]["reproj"])]
            if not wrong:
                break
            clicked.append(wrong[0])
            state = self.post(frame, [self.aim(i, wrong[0], k)], "drag")

    def suggestions(self, i: int, frame: int) -> None:
        W, H = self.t["size"]
        sug = self.state(frame)["suggestions"]
        for k, kp in enumerate(self.t["keypoints"]):
            views = sug.get(kp, {})
            inside = {cam: s for cam, s in views.items()
                      if -0.5 <= s["u"] <= W - 0.5 and -0.5 <= s["v"] <= H - 0.5}
            seen = [c for c in range(len(self.t["cameras"])) if self.t["visible"][i, c, k]]
            for c in seen:
                s = inside.get(self.t["cameras"][c])
                if s is not None:
                    self.suggestion_px.append(float(np.linalg.norm([s["u"], s["v"]] - self.t["uv"][i, c, k])))
            at = {c: (inside[cam]["u"], inside[cam]["v"]) if cam in inside else None
                  for c, cam in enumerate(self.t["cameras"])}
            good = len(seen) >= 2 and not any(self.off(i, c, k, at[c]) for c in seen)
            if good:
                self.accepted += 1
                self.post(frame, [{"camera": cam, "keypoint": kp, "u": s["u"], "v": s["v"]}
                                  for cam, s in inside.items()], "accept")
            else:
                self.reprojection_keypoint(i, frame, k)


def run_way(way: str, data: Path, truth: dict[str, Any], frames: list[int], run: Path | None, noise: float,
            tol: float, seed: int) -> dict[str, Any]:
    """Label ``frames`` of a copy of ``data`` (labels removed) one way; clicks and 3D errors."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from fastapi.testclient import TestClient

    from s3k.label.server import create_app

    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / "data"
        skip = shutil.ignore_patterns(".cache", "labels.csv", "labels-history.jsonl", ".labels.lock")
        shutil.copytree(data, copy, ignore=skip)
        client = TestClient(create_app(copy, run if way == "suggestions" else None, labeller="simulated"))
        person = Labeller(client, truth, noise, tol, seed)
        per_frame, errors, missing = [], [], 0
        index = {int(f): i for i, f in enumerate(truth["frames"])}
        scale = {"m": 1000.0, "mm": 1.0, "cm": 10.0}.get(truth["units"], 1.0)
        for f in frames:
            i = index[f]
            before = person.clicks
            getattr(person, way)(i, f)
            per_frame.append(person.clicks - before)
            geometry = person.state(f)["geometry"]
            for k, kp in enumerate(truth["keypoints"]):
                if truth["visible"][i, :, k].sum() < 2:
                    continue  # no way triangulates it
                point = geometry[kp]["point"]
                if point is None:
                    missing += 1
                else:
                    errors.append(float(np.linalg.norm(np.asarray(point) - truth["points"][i, k])) * scale)
    extra = {}
    if way == "suggestions":
        px = np.asarray(person.suggestion_px)
        extra = {"keypoints_accepted": person.accepted,
                 "suggestion_median_px": float(np.median(px)) if len(px) else None,
                 "suggestion_within_tol": float(np.mean(px <= tol)) if len(px) else None}
    return {**extra, "clicks_per_frame": float(np.mean(per_frame)), "clicks_min": int(min(per_frame)),
            "clicks_max": int(max(per_frame)), "clicks_total": int(sum(per_frame)),
            "median_3d_error_mm": float(np.median(errors)) if errors else None,
            "max_3d_error_mm": float(np.max(errors)) if errors else None, "untriangulated": missing}
