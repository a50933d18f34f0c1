"""The labelling app's API (``s3k.label.server``) through Starlette's test client, on small generated datasets
(``label_data``): saving, loading, history, version conflicts, propagation, suggestions and ranking from a
tiny run, path traversal, the token off the loopback."""

from __future__ import annotations

import csv
import json
import shutil
import warnings

import cv2
import numpy as np
import pytest
import torch
from helpers.label_data import make_label_dataset, save_label_run
from helpers.synthetic_rig import CAMERAS, KEYPOINTS
from helpers.tiny_detector import save_run

pytest.importorskip("fastapi")
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from fastapi.testclient import TestClient

from s3k import cli
from s3k.data import Dataset
from s3k.detector import DetectorMeta
from s3k.label.server import create_app
from s3k.label.store import HISTORY_FILE, Edit, LabelStore
from s3k.model import UNetConfig


def click(client, frame, version, camera, keypoint, uv, **extra):
    edit = {"camera": camera, "keypoint": keypoint, "u": float(uv[0]), "v": float(uv[1]), **extra}
    return client.post(f"/api/frame/{frame}/label", json={"version": version, "edits": [edit]})


def rows(path):
    with open(path / "labels.csv") as f:
        return list(csv.DictReader(f))


def polyline_distance(points, p):
    """Distance from p to a polyline."""
    pts = np.asarray(points)
    a, b = pts[:-1], pts[1:]
    ab = b - a
    t = np.clip(((p - a) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-12), 0, 1)
    return float(np.linalg.norm(a + t[:, None] * ab - p, axis=-1).min())


def test_click_epipolar_triangulate_reproject_and_store(truth):
    client = TestClient(create_app(truth.path, labeller="ann"))
    uv = truth.uv(1)
    first = client.get("/api/frame/1").json()
    assert first["version"] == 0 and first["labels"] == [] and first["split"] == "unlabelled"
    r = click(client, 1, 0, "cam0", "b", uv[0, 1])
    assert r.status_code == 200
    body = r.json()
    assert body["version"] == 1
    geo = body["geometry"]["b"]
    assert geo["point"] is None and geo["epipolar_from"] == "cam0"
    for c in (1, 2, 3):  # the true projection lies on the epipolar line of the click
        assert polyline_distance(geo["epipolar"][CAMERAS[c]], uv[c, 1]) < 0.05
    body = click(client, 1, 1, "cam2", "b", uv[2, 1]).json()
    geo = body["geometry"]["b"]
    assert body["version"] == 2 and geo["epipolar"] == {}
    np.testing.assert_allclose(geo["point"], truth.points[1, 1], atol=1e-6)
    for c, cam in enumerate(CAMERAS):
        np.testing.assert_allclose(geo["views"][cam]["reproj"], uv[c, 1], atol=1e-4)
    assert geo["views"]["cam0"]["residual"] < 1e-4 and geo["views"]["cam1"]["residual"] is None
    # on disk, read back by the dataset loader and by a new app
    ds = Dataset.open(truth.path)
    got, mask = ds.labels([1])
    assert mask[0, :, 1].tolist() == [True, False, True, False]
    np.testing.assert_allclose(got[0, [0, 2], 1], uv[[0, 2], 1], atol=1e-4)
    assert ds.split_of([1])[0] == "labelled"  # a labelled unlabelled frame joins the labelled split
    again = TestClient(create_app(truth.path)).get("/api/frame/1").json()
    assert again["version"] == 2 and len(again["labels"]) == 2
    history = client.get("/api/frame/1/history").json()
    assert [h["version"] for h in history] == [1, 2]
    assert history[0]["labeller"] == "ann" and history[0]["changes"][0]["before"] is None
    assert history[0]["split"] == {"before": "unlabelled", "after": "labelled"}
    # a drag is one more version, its history holds the position before
    moved = uv[2, 1] + [1.5, -0.5]
    body = click(client, 1, 2, "cam2", "b", moved).json()
    assert body["geometry"]["b"]["views"]["cam2"]["residual"] > 0.3
    last = client.get("/api/frame/1/history").json()[-1]
    before = last["changes"][0]["before"]
    np.testing.assert_allclose([before["u"], before["v"]], uv[2, 1])


def test_epipolar_curve_follows_lens_distortion(tmp_path):
    truth = make_label_dataset(tmp_path / "ds", distortion=True)
    client = TestClient(create_app(truth.path))
    uv = truth.uv(4)
    geo = click(client, 4, 0, "cam0", "a", uv[0, 0]).json()["geometry"]["a"]
    curve = np.asarray(geo["epipolar"]["cam2"])  # cam2 has strong radial distortion
    assert polyline_distance(curve, uv[2, 0]) < 0.05
    # where a pinhole model of cam2 would put the point: the distortion matters there
    K, _, R, t = truth.calibration[4]
    x = K[2] @ (R[2] @ truth.points[4, 0] + t[2])
    assert np.linalg.norm(x[:2] / x[2] - uv[2, 0]) > 1.0
    geo = click(client, 4, 1, "cam2", "a", uv[2, 0]).json()["geometry"]["a"]
    np.testing.assert_allclose(geo["point"], truth.points[4, 0], atol=1e-5)


def test_stale_version_is_refused_with_the_newer_labels(truth):
    app = create_app(truth.path)
    tab1, tab2 = TestClient(app), TestClient(app)
    v1 = tab1.get("/api/frame/2").json()["version"]
    v2 = tab2.get("/api/frame/2").json()["version"]
    assert click(tab1, 2, v1, "cam1", "a", (30.0, 40.0)).status_code == 200
    r = click(tab2, 2, v2, "cam1", "a", (50.0, 20.0))
    assert r.status_code == 409
    assert "version 0" in r.json()["detail"]
    current = r.json()["current"]
    assert current["version"] == 1
    assert current["labels"] == [{"camera": "cam1", "keypoint": "a", "u": 30.0, "v": 40.0, "visible": True}]
    assert [(r["u"], r["v"]) for r in rows(truth.path)] == [("30.0", "40.0")]
    # the same store in another process (a second server) is refused too: versions come from the history
    other = LabelStore.open(truth.path)
    from s3k.label.store import Edit, StaleVersion

    with pytest.raises(StaleVersion):
        other.save(2, [Edit("cam2", "a", 10.0, 10.0)], version=0)
    assert other.save(2, [Edit("cam2", "a", 10.0, 10.0)], version=1)["version"] == 2
    # the app sees it at its next request and refuses the first tab's old version
    assert click(tab1, 2, 1, "cam3", "a", (5.0, 5.0)).status_code == 409


def test_not_visible_and_remove(truth):
    client = TestClient(create_app(truth.path))
    body = client.post("/api/frame/3/label", json={"version": 0, "edits": [
        {"camera": "cam3", "keypoint": "c", "visible": False}]}).json()
    assert body["labels"] == [{"camera": "cam3", "keypoint": "c", "u": None, "v": None, "visible": False}]
    assert rows(truth.path) == [{"frame": "3", "camera": "cam3", "keypoint": "c", "u": "", "v": "",
                                 "visible": "0"}]
    uv, mask = Dataset.open(truth.path).labels([3])
    assert not mask.any()
    body = client.post("/api/frame/3/label", json={"version": 1, "edits": [
        {"camera": "cam3", "keypoint": "c", "remove": True}]}).json()
    assert body["labels"] == [] and body["version"] == 2
    assert rows(truth.path) == []


def test_invalid_edits_are_refused_and_change_nothing(truth):
    client = TestClient(create_app(truth.path))
    r = click(client, 0, 0, "cam9", "a", (3, 3))
    assert r.status_code == 400 and "cam9" in r.json()["detail"]
    r = click(client, 0, 0, "cam0", "zz", (3, 3))
    assert r.status_code == 400 and "zz" in r.json()["detail"]
    r = click(client, 0, 0, "cam0", "a", (96.0, 3.0))
    assert r.status_code == 400 and "outside the 96x96 image" in r.json()["detail"]
    r = client.post("/api/frame/0/label", json={"version": 0, "edits": [{"camera": "cam0", "keypoint": "a"}]})
    assert r.status_code == 400 and "needs u and v" in r.json()["detail"]
    assert click(client, 99, 0, "cam0", "a", (3, 3)).status_code == 404
    assert not (truth.path / "labels.csv").exists() and not (truth.path / HISTORY_FILE).exists()
    assert client.get("/api/frame/0").json()["version"] == 0


def test_files_outside_the_app_are_never_served(truth):
    client = TestClient(create_app(truth.path))
    secret = (truth.path / "s3k.json").read_text()
    assert client.get("/static/app.js").status_code == 200
    assert client.get("/").status_code == 200
    for url in ["/static/../s3k.json", "/static/..%2Fs3k.json", "/static/%2e%2e/%2e%2e/%2e%2e/etc/passwd",
                "/static/..%2F..%2F..%2F..%2Fetc%2Fpasswd", "/api/frame/0/image/..%2Fs3k.json",
                "/api/frame/0/image/..%2F..%2Fs3k.json", "/api/frame/0/image/%2Fetc%2Fpasswd",
                "/s3k.json", "/labels.csv", "/api/frame/..%2Fs3k.json"]:
        r = client.get(url)
        assert r.status_code in (404, 422), url
        assert secret not in r.text and "root:" not in r.text, url


def test_images_of_png_and_video_datasets(tmp_path):
    for kind in ("png", "video"):
        truth = make_label_dataset(tmp_path / kind, video=kind == "video")
        client = TestClient(create_app(truth.path))
        r = client.get("/api/frame/5/image/cam2")
        assert r.status_code == 200 and r.headers["content-type"] == "image/png"
        image = cv2.cvtColor(cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_COLOR),
                             cv2.COLOR_BGR2RGB)
        np.testing.assert_array_equal(image, Dataset.open(truth.path).images([5])[0, 2])
        uv = truth.uv(5)
        click(client, 5, 0, "cam0", "a", uv[0, 0])
        geo = click(client, 5, 1, "cam3", "a", uv[3, 0]).json()["geometry"]["a"]
        np.testing.assert_allclose(geo["point"], truth.points[5, 0], atol=1e-5)


def test_per_frame_calibration_is_the_frames_own(tmp_path):
    truth = make_label_dataset(tmp_path / "ds", per_frame=True)
    client = TestClient(create_app(truth.path))
    uv = truth.uv(2)  # camera 1 moved in frame 2
    click(client, 2, 0, "cam1", "c", uv[1, 2])
    geo = click(client, 2, 1, "cam3", "c", uv[3, 2]).json()["geometry"]["c"]
    np.testing.assert_allclose(geo["point"], truth.points[2, 2], atol=1e-6)


def label_frame(client, truth, frame, views=(0, 1)):
    uv = truth.uv(frame)
    version = client.get(f"/api/frame/{frame}").json()["version"]
    edits = [{"camera": CAMERAS[c], "keypoint": kp, "u": float(uv[c, k, 0]), "v": float(uv[c, k, 1])}
             for k, kp in enumerate(KEYPOINTS) for c in views]
    r = client.post(f"/api/frame/{frame}/label", json={"version": version, "edits": edits})
    assert r.status_code == 200
    return r.json()


def test_propagate_over_a_still_stretch(truth):
    client = TestClient(create_app(truth.path))
    label_frame(client, truth, 0)
    client.post("/api/frame/0/label", json={"version": 1, "edits": [
        {"camera": "cam2", "keypoint": "a", "visible": False}]})
    r = client.post("/api/propagate", json={"first": 0, "last": 3})
    assert r.status_code == 200, r.text
    assert r.json() == {"source": 0, "frames": [1, 2, 3], "keypoints": KEYPOINTS, "labels": 3 * 12,
                        "replaced": 0, "dry_run": False,
                        "per_frame": {"1": [12, 0], "2": [12, 0], "3": [12, 0]}}
    ds = Dataset.open(truth.path)
    uv, mask = ds.labels([1, 2, 3])
    expected = np.ones((3, 4, 3), bool)
    expected[:, 2, 0] = False  # occluded in the source frame: marked occluded, not reprojected
    assert (mask == expected).all()
    for i, f in enumerate([1, 2, 3]):
        np.testing.assert_allclose(uv[i][expected[i]], truth.uv(f)[expected[i]], atol=1e-3)
    hist = client.get("/api/frame/2/history").json()
    assert hist[-1]["source"] == "propagate from 0"
    # frame 4 moved: refused, naming it, and nothing written
    before = (truth.path / "labels.csv").read_text()
    r = client.post("/api/propagate", json={"first": 0, "last": 5})
    assert r.status_code == 400
    detail = r.json()["detail"]  # in the words of the page's form, not the command line's
    assert "frame 4 is not still" in detail and "raise 'changed pixels at most'" in detail
    assert "--" not in detail
    assert (truth.path / "labels.csv").read_text() == before
    # with a looser threshold the same stretch is accepted; frames 1-3 already hold the copy: no change there
    r = client.post("/api/propagate", json={"first": 0, "last": 5, "max_changed": 100.0})
    assert r.status_code == 200 and r.json()["frames"] == [4, 5]


@pytest.mark.parametrize("limit", ["NaN", "-5", "Infinity", "101"])
def test_propagate_refuses_a_threshold_out_of_range(truth, limit):
    """nan compares false with every percentage: it would pass every frame as still."""
    client = TestClient(create_app(truth.path))
    label_frame(client, truth, 0)
    before = (truth.path / "labels.csv").read_text()
    r = client.post("/api/propagate", content=f'{{"first": 0, "last": 5, "max_changed": {limit}}}',
                    headers={"content-type": "application/json"})
    assert r.status_code == 400 and "'changed pixels at most'" in r.json()["detail"]
    assert (truth.path / "labels.csv").read_text() == before


def test_propagate_refuses_a_moving_camera_and_from_the_command_line(tmp_path, capsys):
    truth = make_label_dataset(tmp_path / "ds", per_frame=True)
    client = TestClient(create_app(truth.path))
    label_frame(client, truth, 0)
    code = cli.main(["label", "propagate", str(truth.path), "--frames", "0:3"])
    err = capsys.readouterr().err
    assert code == 1
    assert "frame 2 is not still: camera cam1's calibration (t) differs from frame 0's" in err
    assert len(err.strip().splitlines()) == 1
    code = cli.main(["label", "propagate", str(truth.path), "--frames", "3:3", "--from", "0"])
    assert code == 0, capsys.readouterr().err
    assert "to 1 frame(s): 12 labels" in capsys.readouterr().out
    uv, mask = Dataset.open(truth.path).labels([3])
    np.testing.assert_allclose(uv[0][mask[0]], truth.uv(3)[mask[0]], atol=1e-3)
    code = cli.main(["label", "propagate", str(truth.path), "--frames", "4:5"])
    assert code == 1
    assert "no frame there has a keypoint labelled in 2 or more views" in capsys.readouterr().err


def test_suggestions_and_ranking_from_a_run(truth, tmp_path):
    from s3k.data import Dataset
    from s3k.detector import Detector

    run = save_label_run(tmp_path / "run")
    assert TestClient(create_app(truth.path)).get("/api/ranking").status_code == 404
    client = TestClient(create_app(truth.path, run=run))
    assert client.get("/api/meta").json()["run"] is True
    # what the run's detector reads on the dataset's own frames, in the dataset's pixels
    detector = Detector.load(run, "cpu")
    meta = detector.meta
    ds = Dataset.open(truth.path, cache="none")
    ids = ds.frames("unlabelled")
    ro = detector(ds.images(ids), ds.calibration(ids))
    sug = client.get(f"/api/frame/{ids[0]}").json()["suggestions"]
    for k, kp in enumerate(KEYPOINTS):
        for c, cam in enumerate(CAMERAS):
            want = ro.reproj[0, c, k] if ro.valid[0, k] else ro.uv[0, c, k]
            np.testing.assert_allclose([sug[kp][cam]["u"], sug[kp][cam]["v"]], want.numpy(), atol=1e-6)
            assert sug[kp][cam]["weight"] == pytest.approx(float(ro.weights[0, c, k]))
            assert sug[kp][cam]["confidence"] == pytest.approx(float(ro.confidence[0, c, k]))
    # the ranking: every unlabelled frame once, worst first, scored by the documented formula
    ranking = client.get("/api/ranking").json()
    assert sorted(r["frame"] for r in ranking) == sorted(ids.tolist())
    scores = [r["score"] for r in ranking]
    assert scores == sorted(scores, reverse=True)
    sigma = meta.sigma * truth.size / meta.image_size[0]
    w, res = ro.weights.numpy(), np.nan_to_num(ro.residual.numpy())
    doubt = ((w * res).sum(1) / w.sum(1) + res.max(1)) / sigma + (1 - w.mean(1))
    doubt = np.where(ro.valid.numpy(), doubt, 100.0).mean(1)
    by_frame = {r["frame"]: r["score"] for r in ranking}
    np.testing.assert_allclose([by_frame[int(f)] for f in ids], doubt, rtol=1e-9)
    # accepting a suggestion stores it
    f = int(ids[0])
    edits = [{"camera": cam, "keypoint": "a", "u": sug["a"][cam]["u"], "v": sug["a"][cam]["v"]}
             for cam in CAMERAS
             if -0.5 <= sug["a"][cam]["u"] <= 95.5 and -0.5 <= sug["a"][cam]["v"] <= 95.5]
    r = client.post(f"/api/frame/{f}/label", json={"version": 0, "edits": edits, "source": "accept"})
    assert r.status_code == 200 and len(r.json()["labels"]) == len(edits)
    assert client.get(f"/api/frame/{f}/history").json()[-1]["source"] == "accept"


def test_the_queued_frames_come_first_by_rank_and_labelled_ones_drop_out(truth, tmp_path):
    """The frames s3k add-frames queued (label-queue.csv) lead the ranking, by rank with the tracker's doubt,
    before the run's doubt ranking of the other unlabelled frames; a queued frame once labelled leaves the
    queue and the list. Without a run the list is the queue alone."""
    from s3k.label.queue import queue_frames

    # frame 0 is labelled and 6 a test frame: passed over; 4, 2, 5 queued in that order (the dataset's ids)
    queue_frames(truth.path, [(0, 9.0), (4, 7.5), (6, 7.0), (2, 3.25), (5, 1.0)], worst=3)
    plain = TestClient(create_app(truth.path))
    listed = plain.get("/api/ranking").json()
    assert [(r["frame"], r["queue"], r["doubt"]) for r in listed] == [(4, 1, 7.5), (2, 2, 3.25), (5, 3, 1.0)]
    assert plain.get("/api/ranking?limit=2").json() == listed[:2]
    assert plain.get("/api/ranking?split=test").status_code == 404  # no queue there, no run

    client = TestClient(create_app(truth.path, run=save_label_run(tmp_path / "run")))
    ranking = client.get("/api/ranking").json()
    assert [r["frame"] for r in ranking[:3]] == [4, 2, 5] and [r["queue"] for r in ranking[:3]] == [1, 2, 3]
    rest = ranking[3:]  # the run's ranking of the other unlabelled frames, worst first, each once
    assert sorted(r["frame"] for r in rest) == [1, 3] and all("queue" not in r for r in rest)
    assert rest[0]["score"] >= rest[1]["score"]
    for by in ("coverage", "representative"):
        assert [r["frame"] for r in client.get(f"/api/ranking?by={by}").json()][:3] == [4, 2, 5]

    label_frame(client, truth, 4)  # labelled: no longer queued, nor among the unlabelled frames
    ranking = client.get("/api/ranking").json()
    assert [r["frame"] for r in ranking[:2]] == [2, 5] and 4 not in [r["frame"] for r in ranking]
    assert [r["frame"] for r in plain.get("/api/ranking").json()] == [2, 5]

    # a frame added to the dataset while the app runs is listed once the app is started again
    with open(truth.path / "frames.csv", "a") as fh:
        fh.write("7,unlabelled\n")
    for cam in CAMERAS:
        shutil.copy(truth.path / f"images/{cam}/000005.png", truth.path / f"images/{cam}/000007.png")
    queue_frames(truth.path, [(7, 8.0)], worst=1)
    assert [r["frame"] for r in plain.get("/api/ranking").json()] == [2, 5]
    assert [r["frame"] for r in TestClient(create_app(truth.path)).get("/api/ranking").json()] == [7, 2, 5]


def test_a_malformed_queue_is_one_line_naming_the_file(truth):
    (truth.path / "label-queue.csv").write_text("frame,rank,doubt,video_frame,source\nfour,1,2.0,4,t.csv\n")
    r = TestClient(create_app(truth.path)).get("/api/ranking")
    assert r.status_code == 400 and "label-queue.csv" in r.json()["detail"] and "'four'" in r.json()["detail"]


def test_a_run_with_other_keypoints_is_refused(truth, tmp_path):
    meta = DetectorMeta(keypoints=["nose"], cameras=list(CAMERAS), image_size=(32, 32), stride=2, sigma=2.0,
                        model=UNetConfig(channels=(8, 8), res_blocks=1, stride=2).to_dict())
    run = save_run(tmp_path / "run", meta, seed=0)
    with pytest.raises(ValueError, match=r"keypoints \['nose'\] of the run are not in the dataset"):
        create_app(truth.path, run=run)


def test_token_and_host_guards(truth):
    guarded = TestClient(create_app(truth.path, token="s3cret"))
    assert guarded.get("/api/meta").status_code == 403
    assert guarded.get("/api/meta?token=wrong").status_code == 403
    assert guarded.post("/api/frame/0/label", json={"version": 0, "edits": []}).status_code == 403
    assert guarded.get("/").status_code == 403
    r = guarded.get("/?token=s3cret")
    assert r.status_code == 200 and "s3k_token" in r.headers["set-cookie"]
    assert guarded.get("/api/meta").status_code == 200  # the cookie from the first page
    fresh = TestClient(create_app(truth.path, token="s3cret"))
    assert fresh.get("/api/frame/0", headers={"X-S3K-Token": "s3cret"}).status_code == 200
    local = TestClient(create_app(truth.path, allowed_hosts=["127.0.0.1", "localhost"]),
                       base_url="http://127.0.0.1:8765")
    assert local.get("/api/meta").status_code == 200
    assert local.get("/api/meta", headers={"host": "evil.example:8765"}).status_code == 400


def test_history_survives_a_torn_last_line(truth):
    client = TestClient(create_app(truth.path))
    click(client, 0, 0, "cam0", "a", (10.0, 10.0))
    with open(truth.path / HISTORY_FILE, "a") as f:
        f.write('{"frame": 0, "vers')  # a write cut short, never acknowledged
    client = TestClient(create_app(truth.path))
    assert client.get("/api/frame/0").json()["version"] == 1
    assert click(client, 0, 1, "cam1", "a", (11.0, 12.0)).status_code == 200
    lines = (truth.path / HISTORY_FILE).read_text().splitlines()
    assert json.loads(lines[-1])["version"] == 2


def test_cli_refuses_options_of_the_other_form(truth, capsys):
    assert cli.main(["label", str(truth.path), "--frames", "0:3"]) == 1
    assert "--frames belongs to 's3k label propagate DATASET'" in capsys.readouterr().err
    assert cli.main(["label", "propagate", str(truth.path), "--frames", "a:b"]) == 1
    assert "--frames 'a:b'" in capsys.readouterr().err


def test_labels_csv_rewrite_keeps_other_rows_exact(truth):
    store = LabelStore.open(truth.path)
    from s3k.label.store import Edit

    store.save(0, [Edit("cam0", "a", 1.0 / 3.0, 2.5)], version=0)
    store.save(5, [Edit("cam1", "b", 7.25, 8.0)], version=0)
    store.save(0, [Edit("cam2", "c", 3.0, 4.0)], version=1)
    got = rows(truth.path)
    assert [(r["frame"], r["camera"], r["keypoint"]) for r in got] == [
        ("0", "cam0", "a"), ("0", "cam2", "c"), ("5", "cam1", "b")]
    assert float(got[0]["u"]) == 1.0 / 3.0  # full precision
    assert torch.isfinite(torch.tensor([float(r["u"]) for r in got])).all()


def test_a_port_in_use_is_one_line(truth, capsys):
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        assert cli.main(["label", str(truth.path), "--port", str(port)]) == 1
    err = capsys.readouterr().err
    assert f"cannot serve on 127.0.0.1:{port}" in err and "--port" in err


def test_a_save_without_edits_changes_nothing(truth):
    client = TestClient(create_app(truth.path))
    r = client.post("/api/frame/2/label", json={"version": 0, "edits": []})
    assert r.status_code == 200 and r.json()["version"] == 0
    assert not (truth.path / HISTORY_FILE).exists() and not (truth.path / "labels.csv").exists()


def test_pose_distance_ignores_position_and_compares_shared_keypoints():
    from s3k.label.suggest import pose_distances

    ref = np.array([[0.1, 0, 0], [-0.1, 0, 0], [0, 0.05, 0]])
    turned = ref @ np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]]).T  # 90 degrees about z
    X = np.stack([ref + [0.3, -0.2, 0.5], turned, np.where([[True], [True], [False]], ref, np.nan),
                  np.where([[True], [False], [False]], ref, np.nan)])
    d = pose_distances(X, ref)
    assert d[0] == pytest.approx(0, abs=1e-12)  # moved, not turned
    centred = ref - ref.mean(0)
    want = np.sqrt(((centred @ np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]]).T - centred) ** 2).sum(-1).mean())
    assert d[1] == pytest.approx(want)
    assert d[2] == pytest.approx(0, abs=1e-12)  # centred on the two keypoints both have
    assert np.isnan(d[3])  # one shared keypoint: no pose to compare


def test_coverage_order_takes_unlabelled_poses_first_and_each_pose_once():
    from s3k.label.suggest import coverage_order

    up = np.array([[0.1, 0, 0], [-0.1, 0, 0], [0, 0.05, 0]])
    side = up[:, [0, 2, 1]]  # turned onto a side
    other = up[:, [2, 1, 0]]  # another side
    candidates = {1: up + 0.2, 2: side, 3: side + [0, 0.1, 0], 4: other, 5: np.full((3, 3), np.nan)}
    order = coverage_order(candidates, [up])
    frames = [f for f, _ in order]
    # the two poses nobody labelled come first, the second copy of a side only after both (as covered as
    # the labelled pose: ties go by frame), the frame with nothing placed last
    assert set(frames[:2]) == {2, 4} and frames[2:] == [1, 3, 5]
    d = dict(order)
    assert d[3] == pytest.approx(0, abs=1e-12) and d[1] == pytest.approx(0, abs=1e-12) and np.isnan(d[5])
    assert np.isinf(coverage_order(candidates, [])[0][1])  # nothing labelled: all equally far
    # past the greedy part the rest follow by distance, farthest first
    rest = coverage_order(candidates, [up], limit=1)[1:]
    dists = [d for _, d in rest[:-1]]
    assert rest[0][0] == frames[1] and dists == sorted(dists, reverse=True) and rest[-1][0] == 5


def _turn(axis: int, angle: float) -> np.ndarray:
    """The rotation by ``angle`` about the world axis ``axis`` (0, 1, 2: x, y, z)."""
    c, s = np.cos(angle), np.sin(angle)
    i, j = [a for a in range(3) if a != axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def _clusters():
    """Frames of three tight clusters of poses, of 6, 3 and 1 frames (the object flat, tipped 60 degrees one
    way about y, a quarter turn the other way: the odd pose a little farther from the flat one than the
    tipped one is), each frame at its own heading about the vertical, and one frame with one keypoint."""
    up = np.array([[0.1, 0, 0], [-0.1, 0, 0], [0, 0.05, 0]])
    side, other = up @ _turn(1, np.pi / 3).T, up @ _turn(1, -np.pi / 2).T
    rng = np.random.default_rng(0)
    poses = [up] * 6 + [side] * 3 + [other]
    candidates = {f: p @ _turn(2, rng.uniform(0, 2 * np.pi)).T + rng.normal(0, 0.002, (3, 3))
                  for f, p in enumerate(poses)}
    candidates[10] = np.array([[0.1, 0, 0], [np.nan] * 3, [np.nan] * 3])
    return candidates, up, side


def test_pose_distance_about_the_vertical_ignores_the_heading_only():
    from s3k.label.suggest import pose_distances

    rng = np.random.default_rng(1)
    ref = rng.normal(0, 0.1, (5, 3))
    headings = [0.3, 2.0, -2.9]
    X = np.stack([ref @ _turn(2, a).T + rng.normal(0, 1, 3) for a in headings])
    assert np.allclose(pose_distances(X, ref, up=(0, 0, 1)), 0, atol=1e-9)
    assert np.allclose(pose_distances(X, ref, up=(0, 0, -2)), 0, atol=1e-9)  # either sense, any length
    assert (pose_distances(X, ref) > 0.01).all()  # without up, every heading is a pose of its own
    # a tilt is not forgiven: the distance is the least over every heading (here searched densely)
    tilted = ref @ _turn(0, 0.5).T
    a, b = tilted - tilted.mean(0), ref - ref.mean(0)
    best = min(np.sqrt(((a @ _turn(2, t).T - b) ** 2).sum(-1).mean()) for t in np.linspace(0, 6.3, 20001))
    assert pose_distances(tilted[None], ref, up=(0, 0, 1))[0] == pytest.approx(best, rel=1e-6)
    # another vertical: the turn about it is forgiven, the turn about z no longer is
    about_y = ref @ _turn(1, 1.1).T
    assert pose_distances(about_y[None], ref, up=(0, 1, 0))[0] == pytest.approx(0, abs=1e-9)
    assert pose_distances(about_y[None], ref, up=(0, 0, 1))[0] > 0.01


def test_representative_order_takes_poses_in_proportion_where_coverage_takes_the_rarest():
    from s3k.label.suggest import UP, coverage_order, pose_distances, representative_order

    candidates, up, side = _clusters()
    order = representative_order(candidates, [])
    frames = [f for f, _ in order]
    cluster = {f: 0 if f < 6 else 1 if f < 9 else 2 for f in range(10)}
    # the most frequent pose first, then the next most frequent, the single odd pose last of the three
    assert [cluster[f] for f in frames[:3]] == [0, 1, 2]
    assert frames[-1] == 10 and np.isnan(order[-1][1]) and np.isinf(order[0][1])
    # each frame's distance is to the nearest frame before it
    assert order[1][1] == pytest.approx(pose_distances(candidates[frames[1]][None], candidates[frames[0]],
                                                       up=UP)[0])
    # the farthest-first order takes the single odd pose within its first two
    far = [cluster.get(f) for f, _ in coverage_order(candidates, [])[:3]]
    assert 2 in far[:2]
    # with the frequent pose labelled, the next most frequent one leads
    assert cluster[representative_order(candidates, [up])[0][0]] == 1
    assert cluster[representative_order(candidates, [up, side])[0][0]] == 2
    # a smaller sample of the poses to stand for gives the same leaders on poses this distinct; the rest
    # follow the greedy part by what each would still add, no frame lost or repeated
    small = representative_order(candidates, [], limit=2, sample=7)
    assert [cluster[f] for f, _ in small[:2]] == [0, 1] and sorted(f for f, _ in small) == list(range(11))


def test_representative_order_without_a_limit_stops_its_greedy_rounds_once_the_sample_is_covered(monkeypatch):
    import s3k.label.suggest as suggest

    candidates, _, _ = _clusters()
    calls = []
    real = suggest.pose_distances
    monkeypatch.setattr(suggest, "pose_distances", lambda *a, **k: calls.append(1) or real(*a, **k))
    order = suggest.representative_order(candidates, [], limit=None, sample=4)  # two flat, one of each other
    cluster = {f: 0 if f < 6 else 1 if f < 9 else 2 for f in range(10)}
    assert sorted(cluster[f] for f, _ in order[:3]) == [0, 1, 2]
    assert sorted(f for f, _ in order) == list(range(11))
    # one pass over the candidates per sampled pose, then one per greedy round, which end once the sampled
    # poses are covered: not one per candidate frame, which made the whole order quadratic in the frames
    assert len(calls) <= 2 * 4


def test_coverage_ranking_from_a_run_and_the_labels(truth, tmp_path):
    from s3k.label.server import LabelApp
    from s3k.label.suggest import coverage_order, representative_order

    run = save_label_run(tmp_path / "run")
    client = TestClient(create_app(truth.path, run=run))
    assert client.get("/api/ranking?by=nope").status_code == 400
    uv = truth.uv(0)
    edits = [{"camera": cam, "keypoint": kp, "u": float(uv[c, k, 0]), "v": float(uv[c, k, 1])}
             for c, cam in enumerate(CAMERAS) for k, kp in enumerate(KEYPOINTS)]
    assert client.post("/api/frame/0/label", json={"version": 0, "edits": edits}).status_code == 200
    got = client.get("/api/ranking?by=coverage&limit=3").json()
    # what the run places, against the pose of frame 0's labels (in millimetres)
    app = LabelApp(truth.path, run=run)
    poses = app.labelled_poses(list(KEYPOINTS))
    assert len(poses) == 1 and np.allclose(poses[0], truth.points[0], atol=1e-6)
    ids = app.dataset.frames("unlabelled")
    preds = app.suggestions.predict(ids)
    want = coverage_order({f: np.where(p["valid"][:, None], p["X"], np.nan) for f, p in preds.items()},
                          poses, limit=3)
    assert [r["frame"] for r in got] == [f for f, _ in want][:3]
    for r, (_, d) in zip(got, want, strict=False):
        assert r["pose_mm"] == (None if not np.isfinite(d) else pytest.approx(d * 1000))
    got = client.get("/api/ranking?by=representative&limit=3").json()
    want = representative_order({f: np.where(p["valid"][:, None], p["X"], np.nan) for f, p in preds.items()},
                                poses, limit=3)
    assert [r["frame"] for r in got] == [f for f, _ in want][:3]
    # an app told the table has no known normal compares poses at every heading
    candidates = {f: np.where(p["valid"][:, None], p["X"], np.nan) for f, p in preds.items()}
    got = TestClient(create_app(truth.path, run=run, up=None)).get("/api/ranking?by=coverage&limit=3").json()
    want = coverage_order(candidates, poses, limit=3, up=None)
    assert want[:3] != coverage_order(candidates, poses, limit=3)[:3]  # so the check below tells them apart
    assert [r["frame"] for r in got] == [f for f, _ in want][:3]
    for r, (_, d) in zip(got, want, strict=False):
        assert r["pose_mm"] == pytest.approx(d * 1000)
    # against the labelled pose alone (no greedy part), forgiving the heading only ever brings a pose nearer
    at_every_heading = dict(coverage_order(candidates, poses, limit=0, up=None))
    blind = dict(coverage_order(candidates, poses, limit=0))
    assert all(at_every_heading[f] >= blind[f] - 1e-12 for f in blind if np.isfinite(blind[f]))
    # labels changed on disk by another app are triangulated again, not taken from the last request
    other = LabelApp(truth.path)  # keypoint 0 clicked where keypoint 1 is, in every view
    other.store.save(0, [Edit(cam, KEYPOINTS[0], float(uv[c, 1, 0]), float(uv[c, 1, 1]))
                         for c, cam in enumerate(CAMERAS)], version=1)
    again = app.labelled_poses(list(KEYPOINTS))
    assert np.allclose(again[0][0], truth.points[0][1], atol=1e-6)
    assert np.allclose(again[0][1:], truth.points[0][1:], atol=1e-6)
    assert np.allclose(app.labelled_poses(list(KEYPOINTS)[::-1])[0], again[0][::-1], atol=0)


def test_label_up_option_takes_a_direction_or_none():
    from s3k.base.errors import UserError
    from s3k.cli.label import _up

    assert _up("0,0,1") == (0.0, 0.0, 1.0) and _up(" 0, -1 ,0") == (0.0, -1.0, 0.0) and _up("None") is None
    for bad in ("0,1", "a,b,c", "0,0,0", "0,0,nan"):
        with pytest.raises(UserError, match="--up"):
            _up(bad)


def test_request_bodies_are_capped(truth):
    from s3k.label.server import MAX_BODY_BYTES

    client = TestClient(create_app(truth.path))
    before = (truth.path / "labels.csv").read_bytes() if (truth.path / "labels.csv").exists() else None
    big = b'{"version": 0, "edits": [], "source": "' + b"x" * MAX_BODY_BYTES + b'"}'
    r = client.post("/api/frame/0/label", content=big, headers={"content-type": "application/json"})
    assert r.status_code == 413 and str(MAX_BODY_BYTES) in r.json()["detail"]

    def chunks():
        yield b'{"first": 0, '
        yield b'"last": 3}'

    r = client.post("/api/propagate", content=chunks(), headers={"content-type": "application/json"})
    assert r.status_code == 411  # no length announced: not read
    after = (truth.path / "labels.csv").read_bytes() if (truth.path / "labels.csv").exists() else None
    assert after == before
    ok = client.post("/api/frame/0/label", json={"version": 0, "edits": []})
    assert ok.status_code == 200  # an ordinary request still goes through


def test_skeleton_edges_are_added_and_removed_in_s3k_json(truth):
    """The dataset's skeleton is sent with the metadata and edited through the app: each change is written
    to s3k.json at once, every other field kept; bad edges are refused, naming the keypoint or edge."""
    meta_before = json.loads((truth.path / "s3k.json").read_text())
    client = TestClient(create_app(truth.path))
    assert client.get("/api/meta").json()["skeleton"] == []
    r = client.post("/api/skeleton", json={"add": ["a", "b"]})
    assert r.status_code == 200 and r.json()["skeleton"] == [["a", "b"]]
    r = client.post("/api/skeleton", json={"add": ["c", "b"]})
    assert r.json()["skeleton"] == [["a", "b"], ["c", "b"]]
    for body, words in [({"add": ["b", "a"]}, "the edge b - a is already in"),
                        ({"add": ["a", "nose"]}, "unknown keypoint 'nose'"),
                        ({"add": ["a", "a"]}, "two different keypoints"),
                        ({"add": ["a"]}, "an edge is two keypoint names"),
                        ({"remove": ["a", "c"]}, "no edge a - c to remove")]:
        r = client.post("/api/skeleton", json=body)
        assert r.status_code == 400 and words in r.json()["detail"], r.json()
    assert client.post("/api/skeleton", json={"remove": ["b", "a"]}).json()["skeleton"] == [["c", "b"]]
    meta = json.loads((truth.path / "s3k.json").read_text())
    assert meta.pop("skeleton") == [["c", "b"]]
    meta_before.pop("skeleton", None)
    assert meta == meta_before  # nothing else changed
    assert Dataset.open(truth.path).skeleton == [("c", "b")]
    assert TestClient(create_app(truth.path)).get("/api/meta").json()["skeleton"] == [["c", "b"]]
    assert not list(truth.path.glob(".s3k.json.*"))  # no temporary file left
