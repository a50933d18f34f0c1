"""The labelling app's check of labels that disagree (``s3k.label.solve``, ``GET /api/disagreements``): a
label more than 40 px from where the other views put it lists its frame, and each view's residual is coloured
by its camera's median residual over the dataset's labelled frames."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from helpers.label_data import FAR_PX, NEAR_PX, label_true_projections
from helpers.synthetic_rig import CAMERAS, KEYPOINTS

pytest.importorskip("fastapi")
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from fastapi.testclient import TestClient

from s3k.label.server import create_app
from s3k.label.solve import DISAGREE_PX, agreement_level
from s3k.label.store import Edit, LabelStore


def test_a_label_far_from_the_other_views_lists_its_frame_and_turns_its_residual_red(truth):
    label_true_projections(truth, {(5, 2, 1): FAR_PX, (4, 1, 0): NEAR_PX})
    client = TestClient(create_app(truth.path))
    found = client.get("/api/disagreements").json()
    assert found["threshold_px"] == DISAGREE_PX == 40.0
    assert [(f["frame"], f["split"]) for f in found["frames"]] == [(5, "labelled")]
    (label,) = found["frames"][0]["labels"]
    assert (label["camera"], label["keypoint"]) == ("cam2", "b")
    # the other three views are exact: their point is the true one, the wrong label lies FAR_PX from it
    assert label["offset_px"] == pytest.approx(FAR_PX, abs=1e-6) == found["frames"][0]["worst_px"]

    geometry = {f: client.get(f"/api/frame/{f}").json()["geometry"] for f in (0, 4, 5)}
    wrong = geometry[5]["b"]["views"]["cam2"]
    assert wrong["level"] == "disagrees" and wrong["offset"] == pytest.approx(FAR_PX, abs=1e-6)
    assert wrong["residual"] == pytest.approx(label["residual_px"])
    careless = geometry[4]["a"]["views"]["cam1"]
    assert careless["level"] == "high" and careless["offset"] == pytest.approx(NEAR_PX, abs=1e-6)
    for kp in KEYPOINTS:
        for cam in CAMERAS:
            assert geometry[0][kp]["views"][cam]["level"] == "ok"
            assert geometry[5][kp]["views"][cam]["level"] != "disagrees" or (kp, cam) == ("b", "cam2")
    # each camera's median is that of the residuals the frames show
    for cam in CAMERAS:
        shown = [geometry[f][kp]["views"][cam]["residual"] for f in geometry for kp in KEYPOINTS]
        assert found["cameras"][cam] == {"median_px": pytest.approx(float(np.median(shown))), "labels": 9}

    # put right, the frame leaves the list and its residual turns green
    state = client.get("/api/frame/5").json()
    uv = truth.uv(5)[2, 1]
    edit = {"camera": "cam2", "keypoint": "b", "u": float(uv[0]), "v": float(uv[1])}
    r = client.post("/api/frame/5/label", json={"version": state["version"], "edits": [edit]})
    assert r.status_code == 200
    assert client.get("/api/disagreements").json()["frames"] == []
    assert client.get("/api/frame/5").json()["geometry"]["b"]["views"]["cam2"]["level"] == "ok"


def test_two_views_alone_cannot_tell_which_label_is_wrong(truth):
    """The check needs two other views: a keypoint labelled in two views is never listed, however far apart
    its labels are (its residual still shows their disagreement)."""
    label_true_projections(truth, {(4, 1, 0): FAR_PX})
    store = LabelStore.open(truth.path)
    store.save(4, [Edit("cam2", "a", remove=True), Edit("cam3", "a", remove=True)], store.version(4))
    client = TestClient(create_app(truth.path))
    assert client.get("/api/disagreements").json()["frames"] == []
    views = client.get("/api/frame/4").json()["geometry"]["a"]["views"]
    assert views["cam1"]["offset"] is None and views["cam1"]["level"] == "high"


def test_the_colour_rule():
    """Green up to three times the camera's median residual (at least up to 2 px), amber above, red beyond
    40 px from the other views."""
    assert agreement_level(5.9, 6.0, median=2.0) == "ok"
    assert agreement_level(6.1, 6.0, median=2.0) == "high"
    assert agreement_level(1.9, 1.9, median=0.01) == "ok"
    assert agreement_level(2.1, 2.1, median=0.01) == "high"
    assert agreement_level(2.1, None, median=None) == "high"
    assert agreement_level(3.0, 40.5, median=5.0) == "disagrees"
    assert agreement_level(30.0, 39.5, median=20.0) == "ok"
    assert agreement_level(None, None, median=1.0) is None
