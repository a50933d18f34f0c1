"""predict, track and stream refuse a run from another rig or object (with ``--other-rig``), warn of a
calibration with copied cameras as ``s3k import`` does, and say how a calibration differs from the run's."""

from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import torch
from helpers.real_recording import REAL, needs_real
from helpers.tiny_detector import save_run
from helpers.track_rig import CAMERAS, KEYPOINTS

from s3k import cli
from s3k.data.formats.anipose import read_anipose_calibration, write_anipose_calibration
from s3k.data.rig import Rig
from s3k.detector import DetectorMeta
from s3k.geometry import Cameras
from s3k.model import UNetConfig


def _track(recording, run, calibration, out, *extra, cameras=CAMERAS):
    return cli.main(["track", str(run), "--calibration", str(calibration), "--out", str(out), "--no-progress",
                     "--stop", "2", "--videos", *[f"{c}={recording['videos'][c]}" for c in cameras], *extra])


def test_track_and_stream_refuse_a_run_of_another_rig(track_recording, tmp_path, capsys):
    """A run trained on cameras a, b, c used on cameras left, top, right: refused, naming --other-rig."""
    run = tmp_path / "other-rig"
    meta = DetectorMeta(keypoints=list(KEYPOINTS), cameras=["a", "b", "c"], image_size=(32, 24), stride=2,
                        sigma=2.0, model=UNetConfig(channels=(8, 8), res_blocks=1, stride=2).to_dict(),
                        units="mm")
    save_run(run, meta, seed=0)
    out = tmp_path / "p.csv"
    assert _track(track_recording, run, track_recording["calibration"], out) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "camera(s) 'left', 'top', 'right' are not among the cameras a, b, c the run" in err
    assert "--other-rig" in err and not out.exists()
    assert _track(track_recording, run, track_recording["calibration"], out, "--other-rig") == 0
    capsys.readouterr()
    assert cli.main(["stream", str(run), "--calibration", str(track_recording["calibration"]),
                     "--max-frames", "1",
                     "--sources", *[f"{c}={track_recording['videos'][c]}" for c in CAMERAS]]) == 1
    err = capsys.readouterr().err
    assert "--sources: camera(s) 'left', 'top', 'right' are not among" in err and "--other-rig" in err


def test_track_warns_of_a_copied_camera_and_of_a_calibration_not_the_runs(track_recording, tmp_path, capsys):
    """A camera that carries another's parameters is named, as s3k import names it; a calibration that
    differs from the one the run recorded is described camera by camera (mm, degrees, px of focal)."""
    rig = track_recording["rig"]
    run = tmp_path / "run"
    meta = DetectorMeta(keypoints=list(KEYPOINTS), cameras=list(CAMERAS), image_size=(32, 24), stride=2,
                        sigma=2.0, model=UNetConfig(channels=(8, 8), res_blocks=1, stride=2).to_dict(),
                        units="mm")
    a = rig.cameras.numpy()
    record = {"units": rig.units, "cameras": {
        n: {"K": a["K"][c].tolist(), "dist": a["dist"][c].tolist(), "R": a["R"][c].tolist(),
            "t": a["t"][c].tolist(), "frame_size": [int(v) for v in rig.size[c]]}
        for c, n in enumerate(rig.names)}}
    whole = {n: {"box": [0, 0, int(w), int(h)], "frame_size": [int(w), int(h)]} for n, (w, h) in
             zip(rig.names, rig.size)}
    geometry = {"cameras": whole, "image_size": [int(v) for v in rig.size[0]], "calibration": record}
    save_run(run, dataclasses.replace(meta, geometry=geometry), seed=0)
    out = tmp_path / "p.csv"
    assert _track(track_recording, run, track_recording["calibration"], out) == 0
    assert "warning" not in capsys.readouterr().err  # the run's own calibration: nothing to say

    # "right" carries "top"'s parameters
    copied = {k: v.copy() for k, v in a.items()}
    top, right = rig.names.index("top"), rig.names.index("right")
    for k in copied:
        copied[k][right] = copied[k][top]
    path = tmp_path / "copied.toml"
    write_anipose_calibration(path, Rig(rig.names, Cameras.from_numpy(
        copied["K"], copied["dist"], copied["R"], copied["t"], dtype=torch.float64), rig.size, rig.units))
    assert _track(track_recording, run, path, out, "--overwrite") == 0
    err = capsys.readouterr().err
    assert "top and right have identical calibration parameters (usually a copy error" in err
    assert "calibration differs from the one the run" in err and "right (centre" in err

    # "left" moved by 5 mm along x and its focal length 10% longer
    moved = {k: v.copy() for k, v in a.items()}
    left = rig.names.index("left")
    moved["t"][left] -= moved["R"][left] @ np.array([5.0, 0.0, 0.0])  # centre + 5 mm (units mm)
    moved["K"][left][:2, :2] *= 1.1
    path = tmp_path / "moved.toml"
    write_anipose_calibration(path, Rig(rig.names, Cameras.from_numpy(
        moved["K"], moved["dist"], moved["R"], moved["t"], dtype=torch.float64), rig.size, rig.units))
    assert _track(track_recording, run, path, out, "--overwrite") == 0
    err = capsys.readouterr().err
    f = a["K"][left][0, 0]
    assert f"left (centre 5 mm away, focal {1.1 * f:.1f} px vs {f:.1f} px)" in err, err
    assert "top (" not in err and "right (" not in err


def test_predict_refuses_another_object_and_describes_the_calibration(tmp_path, capsys):
    """s3k predict refuses a run whose keypoints are not the dataset's (evaluate refuses it too), with
    --other-rig to write it anyway; and says how the dataset's calibration differs from the run's."""
    from helpers.synthetic_rig import make_dataset

    from s3k.data import Dataset
    from s3k.detector.geometry_record import training_geometry

    data = make_dataset(tmp_path / "data", size=32, labelled=1, unlabelled=0, test=2)
    ds = Dataset.open(data, cache="none")
    meta = DetectorMeta(keypoints=["x", "y", "z"], cameras=list(ds.cameras), image_size=(32, 32), stride=2,
                        sigma=2.0, model=UNetConfig(channels=(8, 8), res_blocks=1, stride=2).to_dict(),
                        units="m")
    other = save_run(tmp_path / "mouse", meta, seed=0)
    out = tmp_path / "p.csv"
    assert cli.main(["predict", str(other), "--data", str(data), "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "are not the run's x, y, z" in err and "--other-rig" in err
    assert not out.exists()
    assert cli.main(["predict", str(other), "--data", str(data), "--out", str(out), "--other-rig"]) == 0
    capsys.readouterr()
    # a run that recorded this dataset's calibration, used on a copy whose camera 1 is turned by 2 degrees
    meta = dataclasses.replace(meta, keypoints=list(ds.keypoints), geometry=training_geometry(ds))
    run = save_run(tmp_path / "run", meta, seed=0)
    assert cli.main(["predict", str(run), "--data", str(data), "--out", str(out), "--overwrite"]) == 0
    assert "warning" not in capsys.readouterr().err
    turned = tmp_path / "turned"
    shutil.copytree(data, turned)
    import json

    doc = json.loads((turned / "calibration.json").read_text())
    cam = ds.cameras[1]
    R = np.asarray(doc["cameras"][cam]["R"])
    a = np.radians(2.0)
    doc["cameras"][cam]["R"] = (np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
                                @ R).tolist()
    (turned / "calibration.json").write_text(json.dumps(doc))
    assert cli.main(["predict", str(run), "--data", str(turned), "--out", str(out), "--overwrite",
                     "--other-rig"]) == 0
    err = capsys.readouterr().err
    assert f"calibration differs from the one the run {run} was trained with: {cam} (" in err
    assert "turned 2 deg" in err


@needs_real
def test_track_warns_of_the_real_recordings_copied_camera(tmp_path, capsys):
    """The real recording's shipped calibration.toml gives side top's parameters: s3k track says so, as s3k
    import does."""
    rig = read_anipose_calibration(REAL / "calibration.toml")
    meta = DetectorMeta(keypoints=["nose"], cameras=list(rig.names), image_size=(64, 48), stride=2, sigma=2.0,
                        model=UNetConfig(channels=(8, 8), res_blocks=1, stride=2).to_dict(), units="mm")
    run = save_run(tmp_path / "run", meta, seed=0)
    videos = [f"{c}={REAL / c / f'minimal_{c}.mp4'}" for c in rig.names]
    assert cli.main(["track", str(run), "--calibration", str(REAL / "calibration.toml"), "--videos", *videos,
                     "--out", str(tmp_path / "p.csv"), "--stop", "1", "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert "side and top have identical calibration parameters (usually a copy error" in err
