"""Labels people made are never changed silently: propagation refuses to replace a label or to touch a test
frame unless told, shows its changes first with a dry run and is undone from the history; the app's saves
and undos respect the test frames' lock."""

from __future__ import annotations

import csv
import warnings

import numpy as np
import pytest
from helpers.synthetic_rig import CAMERAS, KEYPOINTS

pytest.importorskip("fastapi")
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from fastapi.testclient import TestClient

from s3k import cli
from s3k.data import Dataset
from s3k.label.server import create_app
from s3k.label.store import HISTORY_FILE, Edit, LabelStore


def label_views(store, truth, frame, views=(0, 1), shift=(0.0, 0.0)):
    uv = truth.uv(frame)
    store.save(frame, [Edit(CAMERAS[c], kp, float(uv[c, k, 0] + shift[0]), float(uv[c, k, 1] + shift[1]))
                       for k, kp in enumerate(KEYPOINTS) for c in views], None)


def splits(path):
    with open(path / "frames.csv") as f:
        rows = csv.DictReader(line for line in f if not line.startswith("#"))
        return {int(r["frame"]): r["split"] for r in rows}


def test_propagate_refuses_to_replace_labels_and_test_frames_and_dry_runs(truth, capsys):
    store = LabelStore.open(truth.path)
    label_views(store, truth, 0)
    store.save(2, [Edit("cam0", "a", 10.0, 12.0)], None)  # a hand click in frame 2, elsewhere than the copy
    before = (truth.path / "labels.csv").read_text()
    history = (truth.path / HISTORY_FILE).read_text()

    assert cli.main(["label", "propagate", str(truth.path), "--frames", "0:3"]) == 1
    err = capsys.readouterr().err
    assert "would replace 1 existing label(s) in frame(s) 2 (first: frame 2, camera cam0, keypoint a)" in err
    assert "--overwrite" in err and "--dry-run" in err and len(err.strip().splitlines()) == 1

    # the dry run lists the changes per frame and writes nothing
    argv = ["label", "propagate", str(truth.path), "--frames", "0:3", "--overwrite", "--dry-run"]
    assert cli.main(argv) == 0
    out = capsys.readouterr().out
    assert "frame 1: 12 new label(s)\n" in out and "frame 2: 11 new label(s), 1 replaced" in out
    assert "would copy frame 0's 3 keypoint(s) (a, b, c) to 3 frame(s): 36 labels, 1 of them replacing" in out
    assert (truth.path / "labels.csv").read_text() == before
    assert (truth.path / HISTORY_FILE).read_text() == history

    # test frames are neither written nor read without --allow-test
    code = cli.main(["label", "propagate", str(truth.path), "--frames", "5:6", "--from", "0",
                     "--max-changed", "100"])
    err = capsys.readouterr().err
    assert code == 1 and "frame(s) 6 are test frames" in err and "--allow-test" in err
    code = cli.main(["label", "propagate", str(truth.path), "--frames", "4:5", "--from", "6",
                     "--max-changed", "100"])
    err = capsys.readouterr().err
    assert code == 1 and "--from 6: frame 6 is a test frame" in err and "--allow-test" in err
    assert (truth.path / "labels.csv").read_text() == before


def test_propagate_overwrite_then_undo_restores_labels_and_splits(truth, capsys):
    store = LabelStore.open(truth.path)
    label_views(store, truth, 0)
    store.save(2, [Edit("cam0", "a", 10.0, 12.0)], None)
    uv0, mask0 = Dataset.open(truth.path).labels([1, 2, 3])
    split0 = splits(truth.path)
    assert split0[1] == "unlabelled" and split0[2] == "labelled"  # the click moved frame 2

    assert cli.main(["label", "propagate", str(truth.path), "--frames", "0:3", "--overwrite"]) == 0
    out = capsys.readouterr().out
    assert "copied frame 0's 3 keypoint(s)" in out and "--undo" in out
    uv, mask = Dataset.open(truth.path).labels([2])
    np.testing.assert_allclose(uv[0, 0, 0], truth.uv(2)[0, 0], atol=1e-3)  # replaced, as asked
    batches = {e["batch"] for e in LabelStore.open(truth.path).history() if e["source"] == "propagate from 0"}
    assert len(batches) == 1  # one propagation, one batch of the history
    assert splits(truth.path)[1] == "labelled"

    assert cli.main(["label", "propagate", str(truth.path), "--undo"]) == 0
    assert "undid the propagation from frame 0: frame(s) 1, 2, 3" in capsys.readouterr().out
    uv, mask = Dataset.open(truth.path).labels([1, 2, 3])
    assert (mask == mask0).all()
    np.testing.assert_array_equal(uv[mask], uv0[mask0])
    assert splits(truth.path) == split0
    # nothing left to undo
    assert cli.main(["label", "propagate", str(truth.path), "--undo"]) == 1
    assert "no propagation to undo" in capsys.readouterr().err


def test_propagation_undo_refuses_when_a_frame_was_edited_since(truth):
    from s3k.base.errors import UserError
    from s3k.label.propagate import propagate_labels, undo_propagation

    store = LabelStore.open(truth.path)
    label_views(store, truth, 0)
    propagate_labels(truth.path, 0, 3, store=store)
    store.save(3, [Edit("cam1", "b", 5.0, 5.0)], None)
    with pytest.raises(UserError, match="frame 3 was edited after 'propagate from 0'"):
        undo_propagation(truth.path, store=store)
    store.undo(3)  # Ctrl+Z on frame 3 first, then the propagation can go
    assert undo_propagation(truth.path, store=store) == (0, [1, 2, 3])
    assert not Dataset.open(truth.path).labels([1, 2, 3])[1].any()


def test_app_undo_steps_back_through_the_history_and_test_frames_are_locked(truth):
    client = TestClient(create_app(truth.path))
    edit = {"camera": "cam0", "keypoint": "a", "u": 20.0, "v": 30.0}
    assert client.post("/api/frame/4/label", json={"version": 0, "edits": [edit]}).status_code == 200
    moved = dict(edit, u=25.0)
    assert client.post("/api/frame/4/label", json={"version": 1, "edits": [moved]}).status_code == 200
    r = client.post("/api/frame/4/undo", json={"version": 2})
    assert r.status_code == 200 and r.json()["version"] == 3
    assert [(x["u"], x["v"]) for x in r.json()["labels"]] == [(20.0, 30.0)]
    r = client.post("/api/frame/4/undo", json={"version": 3})
    assert r.status_code == 200 and r.json()["labels"] == []
    assert client.post("/api/frame/4/undo", json={"version": 4}).status_code == 400  # nothing left
    assert client.post("/api/frame/4/undo", json={"version": 1}).status_code == 409  # stale
    hist = client.get("/api/frame/4/history").json()
    assert [e.get("undoes") for e in hist] == [None, None, 2, 1]

    # frame 6 is a test frame: read-only unless unlocked
    r = client.post("/api/frame/6/label", json={"version": 0, "edits": [edit]})
    assert r.status_code == 403 and "test frame" in r.json()["detail"]
    assert client.get("/api/frame/6").json()["labels"] == []
    r = client.post("/api/frame/6/label", json={"version": 0, "edits": [edit], "unlock": True})
    assert r.status_code == 200 and r.json()["split"] == "test"
    assert client.post("/api/frame/6/undo", json={"version": 1}).status_code == 403
    assert client.post("/api/frame/6/undo", json={"version": 1, "unlock": True}).status_code == 200


def test_redo_reverts_undos_in_turn_and_a_new_edit_ends_them(truth):
    """Ctrl+Shift+Z / Ctrl+Y: undos stack up and each redo takes the latest off; an edit empties the stack."""
    from s3k.base.errors import UserError

    client = TestClient(create_app(truth.path))

    def state(version, how):
        r = client.post(f"/api/frame/4/{how}", json={"version": version})
        assert r.status_code == 200, r.text
        return [(x["u"], x["v"]) for x in r.json()["labels"]]

    for v, u in enumerate((20.0, 25.0, 30.0)):
        edit = {"camera": "cam0", "keypoint": "a", "u": u, "v": 30.0}
        assert client.post("/api/frame/4/label", json={"version": v, "edits": [edit]}).status_code == 200
    assert state(3, "undo") == [(25.0, 30.0)]
    assert state(4, "undo") == [(20.0, 30.0)]
    assert state(5, "redo") == [(25.0, 30.0)]
    assert state(6, "redo") == [(30.0, 30.0)]
    r = client.post("/api/frame/4/redo", json={"version": 7})
    assert r.status_code == 400 and "no undone edit to redo" in r.json()["detail"]
    assert state(7, "undo") == [(25.0, 30.0)]  # a redo is an edit that undo takes back
    assert state(8, "redo") == [(30.0, 30.0)]
    assert state(9, "undo") == [(25.0, 30.0)]
    edit = {"camera": "cam1", "keypoint": "b", "u": 5.0, "v": 5.0}
    assert client.post("/api/frame/4/label", json={"version": 10, "edits": [edit]}).status_code == 200
    assert client.post("/api/frame/4/redo", json={"version": 11}).status_code == 400  # the edit ended them
    assert client.post("/api/frame/4/redo", json={"version": 3}).status_code == 409  # stale
    hist = client.get("/api/frame/4/history").json()
    assert [e["source"] for e in hist][3:7] == ["undo click", "undo click", "redo click", "redo click"]
    assert [e.get("redoes") for e in hist][5:7] == [5, 4]  # each names the undo it reverts
    # the store's own view, as a new process reads it; test frames stay locked for redo too
    store = LabelStore.open(truth.path)
    assert store.last_undo(4) is None
    with pytest.raises(UserError, match="no undone edit"):
        store.redo(4)
    assert client.post("/api/frame/6/redo", json={"version": 0}).status_code == 403
    # a redo that brings labels back to an unlabelled frame moves it to the labelled split again
    edit = {"camera": "cam0", "keypoint": "a", "u": 20.0, "v": 30.0}
    r = client.post("/api/frame/5/label", json={"version": 0, "edits": [edit]})
    assert r.json()["split"] == "labelled"
    assert client.post("/api/frame/5/undo", json={"version": 1}).json()["split"] == "unlabelled"
    assert client.post("/api/frame/5/redo", json={"version": 2}).json()["split"] == "labelled"
    assert splits(truth.path)[5] == "labelled"


def test_the_apps_propagation_refusals_name_its_form_and_the_command_line_its_flags(truth, capsys):
    client = TestClient(create_app(truth.path))
    store = LabelStore.open(truth.path)
    label_views(store, truth, 0)
    store.save(2, [Edit("cam0", "a", 10.0, 12.0)], None)
    cases = [({"first": 0, "last": 3}, "tick 'replace existing labels' to replace them, or 'preview'"),
             ({"first": 5, "last": 6, "max_changed": 100}, "tick 'include test frames' to write them"),
             ({"first": 3, "last": 1}, "frames 3 to 1: the last frame comes before the first"),
             ({"first": 0, "last": 5, "overwrite": True}, "raise 'changed pixels at most'")]
    for body, words in cases:
        r = client.post("/api/propagate", json={"source": 0, **body})
        assert r.status_code == 400 and words in r.json()["detail"], r.json()
        assert "--" not in r.json()["detail"]
    assert cli.main(["label", "propagate", str(truth.path), "--frames", "3:1"]) == 1
    assert "--frames 3:1: the last frame comes before the first" in capsys.readouterr().err
