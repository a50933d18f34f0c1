"""Cameras outside the training rig (s3k.sim.rigs; s3k.experiments.outside_rig, behind
benchmarks/outside_rig.py): each named rig's ranges lie outside the scene's training rig, the rendered test
sets' cameras measured back from their calibration do too, with the same object poses, and a run is
evaluated on each against in-range."""

from __future__ import annotations

import json

import numpy as np
import pytest

from s3k.sim.rigs import RIGS, rig_sampler
from s3k.sim.scenes import SCENES


@pytest.mark.parametrize("scene", ["box", "category", "plush"])
def test_each_rig_lies_outside_the_training_ranges(scene):
    train = SCENES[scene].cameras_sampler
    assert rig_sampler(train, "train") == train
    low, high = rig_sampler(train, "low"), rig_sampler(train, "high")
    assert low.elevation_deg[1] < train.elevation_deg[0] and high.elevation_deg[0] > train.elevation_deg[1]
    assert 0 < low.elevation_deg[0] < low.elevation_deg[1] and high.elevation_deg[1] < 90
    assert rig_sampler(train, "far").distance[0] > train.distance[1]
    assert rig_sampler(train, "wide").fovy_deg > train.fovy_deg
    for rig in ("low", "high", "far", "wide"):  # one range changed, the rest as in training
        changed = {k for k in ("distance", "elevation_deg", "fovy_deg", "target", "roll_deg")
                   if getattr(rig_sampler(train, rig), k) != getattr(train, k)}
        assert len(changed) == 1
    with pytest.raises(ValueError, match="unknown 'side'"):
        rig_sampler(train, "side")


def test_test_sets_outside_the_rig_and_the_table(tmp_path):
    from helpers.tiny_detector import save_run

    from s3k.data import Dataset
    from s3k.detector import DetectorMeta
    from s3k.experiments.outside_rig import evaluate_rigs, measured_cameras, outside, render_test_sets, table
    from s3k.model import UNetConfig
    from s3k.sim.rigs import describe_rig

    sets = render_test_sets("box", 32, 4, 7, tmp_path / "sets", workers=1)
    assert list(sets) == list(RIGS)
    train = SCENES["box"].cameras_sampler
    ranges = describe_rig(train)
    measured = {rig: measured_cameras(path, train.target) for rig, path in sets.items()}
    # the training rig's cameras within its ranges (the aim point's jitter moves the angles a little)
    assert ranges["elevation_deg"][0] - 3 <= measured["train"]["elevation_deg"][0]
    assert measured["train"]["elevation_deg"][1] <= ranges["elevation_deg"][1] + 3
    assert measured["train"]["fovy_deg"] == pytest.approx([train.fovy_deg] * 2, abs=1e-3)
    assert not any(outside(measured["train"], ranges).values())
    # each other rig outside in the quantity it changes, and in that one only
    varied = {"low": "elevation_deg", "high": "elevation_deg", "far": "distance_m", "wide": "fovy_deg"}
    for rig, quantity in varied.items():
        assert [k for k, v in outside(measured[rig], ranges).items() if v] == [quantity], rig
    assert measured["low"]["elevation_deg"][1] < ranges["elevation_deg"][0]
    assert measured["high"]["elevation_deg"][0] > ranges["elevation_deg"][1]
    assert measured["far"]["distance_m"][0] > ranges["distance_m"][1]
    assert measured["wide"]["fovy_deg"][0] > 1.4 * train.fovy_deg
    # the same object poses in every set: only the cameras differ
    points = {rig: Dataset.open(path, cache="none").points3d(np.arange(4))[0] for rig, path in sets.items()}
    assert all(np.allclose(points[rig], points["train"]) for rig in RIGS)
    assert Dataset.open(sets["low"], cache="none").frames("labelled").size == 0
    source = json.loads((sets["low"] / "s3k.json").read_text())["source"]
    assert source["rig"] == "low" and source["cameras"]["elevation_deg"] == [10.0, 20.0]
    assert "rig" not in json.loads((sets["train"] / "s3k.json").read_text())["source"]
    again = render_test_sets("box", 32, 4, 7, tmp_path / "sets", rigs=("low",), workers=1)
    assert again == {"low": sets["low"]}

    meta = DetectorMeta(keypoints=list(SCENES["box"].keypoints), cameras=[f"cam{i}" for i in range(4)],
                        image_size=(32, 32), stride=2, sigma=2.0,
                        model=UNetConfig(channels=(8, 16), res_blocks=1).to_dict())
    run = save_run(tmp_path / "run", meta, seed=0, head_std=0.5)
    result = evaluate_rigs(run, sets, "box")
    rows = result["rigs"]
    assert list(rows) == list(RIGS) and all(row["frames"] == 4 for row in rows.values())
    for rig in varied:
        assert rows[rig]["median_ratio_to_in_range"] == pytest.approx(rows[rig]["median_mm"]
                                                                     / rows["train"]["median_mm"])
        assert rows[rig]["meets_target"] == (rows[rig]["median_ratio_to_in_range"] <= 1.3)
    assert "median_ratio_to_in_range" not in rows["train"]
    lines = table(result)
    assert len(lines) == 1 + len(RIGS) and lines[2].startswith("low ") and lines[2].split()[4].endswith("x")

    # a run trained on a wider rig, read on the scene rig's sets: they are no longer outside its range
    from s3k.sim.rigs import ranged_sampler

    wider = ranged_sampler(train, elevation=(5.0, 88.0))
    read = evaluate_rigs(run, {r: sets[r] for r in ("train", "low")}, "box", trained_on=wider,
                         drawn_from=train)
    assert read["training_rig"]["elevation_deg"] == [5.0, 88.0]
    assert read["rigs_drawn_relative_to"]["elevation_deg"] == list(train.elevation_deg)
    assert read["rigs"]["low"]["sampled"]["elevation_deg"] == [10.0, 20.0]
    assert not any(read["rigs"]["low"]["outside_training_range"].values())
    assert read["rigs"]["low"]["median_mm"] == pytest.approx(rows["low"]["median_mm"])


def test_an_unknown_rig_is_a_one_line_error():
    from s3k.base.errors import UserError
    from s3k.sim.generate import SimulateConfig

    with pytest.raises(UserError, match=r"rig \(--rig\): unknown camera rig 'side'"):
        SimulateConfig("box", rig="side")


@pytest.mark.parametrize("option, value, message", [
    ("elevation", (30.0, 20.0),
     r"elevation \(--elevation\): expected LO <= HI, both from 5 to 88 degrees, got 30,20"),
    ("elevation", (2.0, 40.0), r"elevation \(--elevation\): .* got 2,40"),
    ("elevation", (40.0, 90.0), r"elevation \(--elevation\): .* got 40,90"),
    ("distance", (0.0, 1.0), r"distance \(--distance\): expected LO <= HI, both from 0.2 to 10 m, got 0,1"),
    ("distance", (1.2, float("nan")), r"distance \(--distance\): expected two numbers"),
])
def test_a_bad_camera_range_is_a_one_line_error(option, value, message):
    from s3k.base.errors import UserError
    from s3k.sim.generate import SimulateConfig

    with pytest.raises(UserError, match=message) as e:
        SimulateConfig("box", **{option: value})
    assert "\n" not in str(e.value)


def test_simulate_refuses_a_range_that_is_not_two_numbers(capsys):
    from s3k.cli import main

    with pytest.raises(SystemExit) as e:
        main(["simulate", "box", "--out", "unused", "--elevation", "10,a"])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip()
    assert "--elevation: expected two numbers LO,HI" in err and "'10,a'" in err and "\n" not in err


def test_the_cameras_lie_in_the_given_ranges_and_the_rigs_outside_them(tmp_path):
    from s3k.experiments.outside_rig import measured_cameras, render_test_sets

    train = SCENES["box"].cameras_sampler
    sets = render_test_sets("box", 32, 6, 3, tmp_path, rigs=("train", "high"), workers=1,
                            elevation=(40.0, 50.0), distance=(1.5, 1.6))
    assert sets["train"].name == "box32-train-el40-50-d1.5-1.6-test6-seed3"
    measured = {rig: measured_cameras(path, train.target) for rig, path in sets.items()}
    # within the ranges, give or take the aim point's jitter (15 mm at 1.5 m: about 0.6 degree, 15 mm)
    assert 39 <= measured["train"]["elevation_deg"][0] and measured["train"]["elevation_deg"][1] <= 51
    assert 1.48 <= measured["train"]["distance_m"][0] and measured["train"]["distance_m"][1] <= 1.62
    # a named rig is drawn relative to the given ranges: high is 5 to 15 degrees above 50
    assert 54 <= measured["high"]["elevation_deg"][0] and measured["high"]["elevation_deg"][1] <= 66
    assert 1.48 <= measured["high"]["distance_m"][0] and measured["high"]["distance_m"][1] <= 1.62
    source = json.loads((sets["train"] / "s3k.json").read_text())["source"]
    assert source["cameras"]["elevation_deg"] == [40.0, 50.0]
    assert source["cameras"]["distance_m"] == [1.5, 1.6]
    assert "rig" not in source


def test_the_triangulation_floor_grows_with_the_noise_and_overhead_cameras(tmp_path):
    from s3k.experiments.outside_rig import render_test_sets, triangulation_floor

    sets = render_test_sets("box", 32, 8, 5, tmp_path, rigs=("train",), workers=1)
    overhead = render_test_sets("box", 32, 8, 5, tmp_path, rigs=("train",), workers=1, elevation=(84.0, 88.0))
    assert triangulation_floor(sets["train"], 0.0) < 1e-6
    one, two = triangulation_floor(sets["train"], 1.0), triangulation_floor(sets["train"], 2.0)
    assert 0 < one < two
    # cameras all nearly overhead meet at narrow angles: the same 2D error, a larger 3D one
    assert triangulation_floor(overhead["train"], 1.0) > 2 * one


def test_the_diagnosis_of_a_two_pass_run(tmp_path):
    from helpers.tiny_detector import save_run

    from s3k.detector import DetectorMeta
    from s3k.detector.crop_rule import CropRule, write_two_pass
    from s3k.experiments.outside_rig import diagnose, render_test_sets
    from s3k.model import UNetConfig
    from s3k.run_folder import RunFolder

    data = render_test_sets("box", 32, 4, 7, tmp_path / "sets", rigs=("train",), workers=1)["train"]
    keypoints, cameras = list(SCENES["box"].keypoints), [f"cam{i}" for i in range(4)]
    run = tmp_path / "run"
    for folder, size in ((RunFolder.COARSE, 32), (RunFolder.FINE, 16)):
        meta = DetectorMeta(keypoints=keypoints, cameras=cameras, image_size=(size, size), stride=2,
                            sigma=2.0, model=UNetConfig(channels=(8, 16), res_blocks=1).to_dict())
        save_run(run / folder, meta, seed=0, head_std=0.5)
    write_two_pass(run, CropRule(extent=0.3, size=16), 32, keypoints)
    d = diagnose(run, data, gross_px=2.0)
    for key in ("coarse_3d_median_mm", "fine_3d_median_mm", "coarse_2d_median_px", "fine_2d_median_px"):
        assert np.isfinite(d[key]) and d[key] > 0, key
    for key in ("coarse_2d_gross", "fine_2d_gross", "truth_outside_crop", "fine_2d_gross_on_another_keypoint",
                "frames_swapped"):
        assert 0 <= d[key] <= 1, key
    assert d["fine_2d_gross_on_another_keypoint"] <= d["fine_2d_gross"]
    # an untrained network is off by more than 2 px almost everywhere
    assert d["fine_2d_gross"] > 0.5
