"""Tests of keypoints in the loop: the plush scene, the grasp primitive, the detector read-out of a run, the
summary writer (s3k/sim/plush.py, s3k/robot/grasp.py, s3k/robot/detect.py, s3k/robot/results.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from s3k.base.errors import UserError
from s3k.sim.generate import SimulateConfig, frame_plan, frame_rng
from s3k.sim.plush import NUM_ARRANGEMENTS, TRAIN_ARRANGEMENTS, PlushScene
from s3k.sim.scene import FrameSpec

mujoco = pytest.importorskip("mujoco")


# ------------------------------------------------------------------------------------------ plush scene
def test_plush_labelled_frames_project_onto_the_toy():
    """Every visible keypoint of each training arrangement's labelled frame lands on the toy in a
    segmentation render (the keypoints lie inside the toy, so their projections are on its silhouette)."""
    with PlushScene(size=64, seed=0) as scene:
        own = set(scene.own_geoms().tolist())
        checked = 0
        for a in range(TRAIN_ARRANGEMENTS):
            frame = scene.frame(FrameSpec(a, "labelled", segment=a), frame_rng(0, a))
            assert frame.images.shape == (4, 64, 64, 3)
            assert frame.images.std() > 10  # something is drawn
            seg = scene.renderer.render(scene.data, scene.camera_ids, segmentation=True)["segmentation"]
            for c, k in zip(*np.nonzero(frame.visible)):
                u, v = np.rint(frame.uv[c, k]).astype(int)
                assert seg[c, v, u] in own, (a, c, scene.keypoints[k])
                checked += 1
        assert checked >= 0.8 * TRAIN_ARRANGEMENTS * 4 * len(scene.keypoints)


def test_plush_arrangement_is_still_while_gripper_and_light_move():
    with PlushScene(size=32, seed=0) as scene:
        f0 = scene.frame(FrameSpec(0, "labelled", segment=2), frame_rng(0, 0))
        f1 = scene.frame(FrameSpec(1, "unlabelled", segment=2), frame_rng(0, 1))
        other = scene.frame(FrameSpec(2, "unlabelled", segment=3), frame_rng(0, 2))
    # Same arrangement: same cameras and keypoints (what label propagation needs); the gripper moved.
    for a, b in ((f0.K, f1.K), (f0.R, f1.R), (f0.t, f1.t), (f0.points3d, f1.points3d)):
        np.testing.assert_array_equal(a, b)
    assert f0.extra["gripper_tcp"] != f1.extra["gripper_tcp"]
    assert np.abs(f0.images.astype(int) - f1.images.astype(int)).max() > 0
    assert np.abs(f0.points3d - other.points3d).max() > 0.01
    assert not np.allclose(f0.R, other.R)


def test_plush_frame_plan_one_labelled_frame_per_training_arrangement():
    specs = frame_plan(SimulateConfig("plush", labelled=7, unlabelled=21, test=6))
    labelled = [s.segment for s in specs if s.split == "labelled"]
    assert labelled == list(range(TRAIN_ARRANGEMENTS))
    assert {s.segment for s in specs if s.split == "unlabelled"} == set(range(TRAIN_ARRANGEMENTS))
    assert {s.segment for s in specs if s.split == "test"} == set(range(TRAIN_ARRANGEMENTS, NUM_ARRANGEMENTS))
    assert [s.frame_id for s in specs] == list(range(len(specs)))
    with PlushScene(size=16, seed=0) as scene, pytest.raises(ValueError, match="arrangement"):
        scene.sample(FrameSpec(0, "labelled"), frame_rng(0, 0))
    # unlabelled frames over 4 further arrangements too: numbered from 13, after every held-out one
    more = frame_plan(SimulateConfig("plush", labelled=7, unlabelled=22, test=6, unlabelled_arrangements=4))
    assert [s.segment for s in more if s.split == "labelled"] == labelled
    unlabelled = {s.segment for s in more if s.split == "unlabelled"}
    assert unlabelled == {*range(TRAIN_ARRANGEMENTS), 13, 14, 15, 16}
    assert {s.segment for s in more if s.split == "test"} == set(range(TRAIN_ARRANGEMENTS, NUM_ARRANGEMENTS))
    assert [s.frame_id for s in more] == list(range(len(more)))
    with pytest.raises(UserError, match="--unlabelled-arrangements"):
        SimulateConfig("plush", unlabelled_arrangements=-1)


def test_simulate_plush_writes_a_dataset_with_arrangements(tmp_path):
    from s3k.cli import main
    from s3k.data import Dataset, usable_labels

    out = tmp_path / "plush"
    assert main(["simulate", "plush", "--out", str(out), "--size", "32", "--unlabelled", "7", "--test", "3",
                 "--workers", "1", "--no-progress"]) == 0
    ds = Dataset.open(out)
    assert ds.keypoints == PlushScene.keypoints
    lab, unl = ds.frames("labelled"), ds.frames("unlabelled")
    assert len(lab) == TRAIN_ARRANGEMENTS and len(unl) == 7
    seg_lab = ds.column("segment", lab).astype(int)
    seg_unl = ds.column("segment", unl).astype(int)
    assert sorted(seg_lab) == list(range(TRAIN_ARRANGEMENTS))
    # The labelled frame's 3D label holds for the arrangement's unlabelled frames: same calibration, same
    # ground truth; every keypoint of the labelled frame triangulates from its labels.
    for f, s in zip(unl, seg_unl):
        g = lab[list(seg_lab).index(s)]
        np.testing.assert_allclose(ds.calibration([f]).numpy()["R"], ds.calibration([g]).numpy()["R"])
        np.testing.assert_allclose(ds.points3d([f])[0], ds.points3d([g])[0])
    assert usable_labels(ds, "labelled").mean() > 0.9


def test_plush_label_propagated_over_an_arrangement_lands_on_the_true_pixel(tmp_path, capsys):
    """The plush workflow: one labelled frame per arrangement, copied with ``s3k label propagate`` to the
    arrangement's other frames (the gripper moves there, hence --max-changed), lands on the projection of the
    true keypoint in every view of every frame of the stretch."""
    from s3k.cli import main
    from s3k.data import Dataset
    from s3k.sim.camera import project_points

    out = tmp_path / "plush"
    assert main(["simulate", "plush", "--out", str(out), "--size", "48", "--unlabelled", "21", "--test", "3",
                 "--workers", "1", "--no-progress"]) == 0
    ds = Dataset.open(out, cache="none")
    first = int(ds.frames("labelled")[1])  # arrangement 1: frames first..first+3
    stretch = [f for f in ds.frame_ids if first < f <= first + 3]
    assert (ds.column("segment", stretch).astype(int) == 1).all()
    # The gripper moved: the default still check refuses, naming the option.
    assert main(["label", "propagate", str(out), "--frames", f"{first}:{first + 3}"]) == 1
    assert "--max-changed" in capsys.readouterr().err
    stretch_arg = ["--frames", f"{first}:{first + 3}"]
    assert main(["label", "propagate", str(out), *stretch_arg, "--max-changed", "100"]) == 0
    ds = Dataset.open(out, cache="none")
    assert set(ds.split_of(stretch)) == {"labelled"}  # the stretch's frames now count as labelled
    _, src_mask = ds.labels([first])
    uv, mask = ds.labels(stretch)
    X, _ = ds.points3d(stretch)
    cams = ds.calibration(stretch, np.float64).numpy()
    checked = 0
    for i in range(len(stretch)):
        truth, _ = project_points(cams["K"][i], cams["R"][i], cams["t"][i], X[i].astype(np.float64))
        for c in range(len(ds.cameras)):
            for k in range(len(ds.keypoints)):
                if src_mask[0, c, k]:
                    assert mask[i, c, k]
                    np.testing.assert_allclose(uv[i, c, k], truth[c, k], atol=1e-3)
                    checked += 1
    assert checked >= 0.8 * len(stretch) * len(ds.cameras) * len(ds.keypoints)


# ------------------------------------------------------------------------------------------ grasp
def test_grasp_on_ground_truth_lifts_the_paw_and_a_bad_aim_does_not():
    from s3k.robot.grasp import SUCCESS_LIFT, ground_truth_keypoints, run_trials

    result = run_trials(ground_truth_keypoints, trials=6, size=32)
    assert result["successes"] == 6 and result["trials"] == 6
    assert all(t["lift"] >= SUCCESS_LIFT and t["held_mm"] < 40 for t in result["per_trial"])
    # the datasets' three test arrangements, then three that no dataset has
    assert [t["arrangement"] for t in result["per_trial"]] == [7, 8, 9, 10, 11, 12]
    assert result["per_arrangement"] == {str(a): 1.0 for a in range(7, 13)}
    two = run_trials(ground_truth_keypoints, trials=3, size=32, arrangements=2)
    assert [t["arrangement"] for t in two["per_trial"]] == [7, 8, 7] and two["arrangements"] == [7, 8]
    with pytest.raises(ValueError, match="arrangements"):  # 13 on may be a dataset's unlabelled arrangements
        run_trials(ground_truth_keypoints, trials=1, size=32, arrangements=7)

    def off_by_6cm(scene, spec):
        X = scene.keypoints_world().copy()
        X[:, 0] += 0.06
        return X

    missed = run_trials(off_by_6cm, trials=2, size=32)
    assert missed["successes"] == 0
    assert all(abs(t["lift"]) < 0.02 for t in missed["per_trial"])

    def other_paw(scene, spec):  # a detector that swaps the paws: the toy is lifted by the wrong leg
        X = scene.keypoints_world().copy()
        X[[2, 3]] = X[[3, 2]]
        return X

    swapped = run_trials(other_paw, trials=3, size=32)
    assert swapped["successes"] == 0
    assert all(t["held_mm"] > 40 for t in swapped["per_trial"])


def _oracle_logits(uv: np.ndarray, h: int, w: int, stride: int, sigma: float) -> torch.Tensor:
    """Logits ``(C, K, h, w)`` of a Gaussian of width ``sigma`` image pixels at ``uv (C, K, 2)``."""
    from s3k.readout.heatmaps import cell_centres

    u, v = cell_centres(h, w, stride)
    uv_t = torch.as_tensor(uv, dtype=torch.float32)
    du = (u[None, None, None, :] - uv_t[..., 0, None, None]) ** 2
    dv = (v[None, None, :, None] - uv_t[..., 1, None, None]) ** 2
    return -(du + dv) / (2 * sigma**2)


class _Oracle(torch.nn.Module):
    def __init__(self, logits: torch.Tensor):
        super().__init__()
        self.logits = logits

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.logits.to(images.dtype)


def test_run_detector_reads_the_true_points_and_grasps(monkeypatch, tmp_path):
    """Through RunDetector (rendered views -> network -> s3k's read-out), an oracle network whose heatmaps
    peak at the true projections gives the true 3D points, and the grasp at them succeeds."""
    import s3k.detector.detector
    from s3k.detector import DetectorMeta
    from s3k.model import UNetConfig
    from s3k.robot.detect import RunDetector
    from s3k.robot.grasp import detector_keypoints, run_trials

    size, stride, sigma = 64, 2, 2.0
    # The network's keypoint order differs from the scene's: the detector must reorder by name.
    names = PlushScene.keypoints[::-1]
    meta = DetectorMeta(keypoints=names, cameras=[f"cam{i}" for i in range(4)], image_size=(size, size),
                        stride=stride, sigma=sigma,
                        model=UNetConfig(channels=(8, 8), stride=stride).to_dict())
    oracle = _Oracle(torch.zeros(0))
    monkeypatch.setattr(s3k.detector.detector, "load_network", lambda *a, **k: (oracle, meta))
    detector = RunDetector(tmp_path, PlushScene.keypoints)
    inner = detector_keypoints(detector)
    errors = []

    def source(scene, spec):
        from s3k.sim.camera import project_points

        scene.forward()
        K, R, t = scene.calibration()
        truth = scene.keypoints_world()
        uv, _ = project_points(K, R, t, truth[::-1])  # in the network's order
        oracle.logits = _oracle_logits(uv, size // stride, size // stride, stride, sigma)
        X = inner(scene, spec)
        errors.append(np.linalg.norm(X - truth, axis=1))
        return X

    result = run_trials(source, trials=3, size=size)
    err = np.concatenate(errors)
    assert np.nanmax(err) < 0.004, err  # millimetres: the read-out of exact heatmaps
    assert result["successes"] == 3

    with pytest.raises(UserError, match="no keypoint 'nose'"):
        RunDetector(tmp_path, ["head", "nose"])


def test_grasp_command_ground_truth_and_refusal(tmp_path, capsys):
    from s3k.cli import main

    out = tmp_path / "grasp.json"
    assert main(["robot", "grasp", "--ground-truth", "--trials", "1", "--size", "32", "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["successes"] == 1 and doc["trials"] == 1 and doc["detector"] == "ground_truth"
    assert main(["robot", "grasp", "--trials", "1", "--out", str(out)]) == 1
    assert "RUN" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------ summary
def test_summary_holds_only_what_was_measured(tmp_path):
    from s3k.robot.results import write_summary

    g = tmp_path / "gt.json"
    g.write_text(json.dumps({"successes": 27, "trials": 30}))
    runs = []
    for seed, curve in enumerate(([0.0, 0.2, 0.5], [0.1, 0.6, 0.9])):  # two seeds' evaluations
        run = tmp_path / f"kp{seed}"
        run.mkdir()
        # the detected success (by the agent's own keypoints) lags the true one by 0.1
        evals = [{"env_steps": 50 * (i + 1), "success_rate": r - 0.1 * (r > 0), "true_success_rate": r}
                 for i, r in enumerate(curve)]
        final = {**evals[-1], "seed": seed, "env_steps": 150, "cpu_seconds": 1800.0}
        (run / "progress.json").write_text(json.dumps({"evaluations": evals, "final": final}))
        runs.append(run)
    out = tmp_path / "summary.json"
    s = write_summary(out, grasp_ground_truth=g, rl_keypoints=runs)
    assert s["grasp_success"] == {"s3k": None, "labels_only": None, "ground_truth": 0.9, "trials": 30}
    kp = s["rl_final_success"]["keypoints"]
    assert [(p["seed"], p["success_rate"]) for p in kp["per_seed"]] == [(0, 0.5), (1, 0.9)]
    assert [p["detected_success_rate"] for p in kp["per_seed"]] == pytest.approx([0.4, 0.8])
    assert kp["mean"] == pytest.approx(0.7) and (kp["min"], kp["max"]) == (0.5, 0.9)
    assert kp["cpu_hours"] == pytest.approx(1.0)
    assert s["rl_final_success"]["beta_vae"] is None and s["rl_final_success"]["env_steps"] == 150
    curve = s["rl_success_curve"]["keypoints"]
    assert curve["env_steps"] == [50, 100, 150] and curve["seeds"] == 2
    assert curve["mean"] == pytest.approx([0.05, 0.4, 0.7])
    assert curve["min"] == [0.0, 0.2, 0.5] and curve["max"] == [0.1, 0.6, 0.9]
    assert s["rl_success_curve"]["beta_vae"] is None
    assert json.loads(out.read_text()) == s
    bad = tmp_path / "bad.json"
    bad.write_text("{")
    with pytest.raises(UserError, match="bad.json"):
        write_summary(out, grasp_s3k=bad)
    (run / "progress.json").write_text(json.dumps({"evaluations": []}))
    with pytest.raises(UserError, match="no final evaluation"):
        write_summary(out, rl_keypoints=[run])


def test_grasp_command_with_a_run_reads_its_detector_and_dataset_seed(tmp_path):
    from helpers.tiny_detector import save_run

    from s3k.cli import main
    from s3k.detector import DetectorMeta
    from s3k.model import UNetConfig

    dataset = tmp_path / "plush-data"
    dataset.mkdir()
    (dataset / "s3k.json").write_text(json.dumps({"source": {"scene": "plush", "object_seed": 3}}))
    meta = DetectorMeta(keypoints=list(PlushScene.keypoints), cameras=[f"cam{i}" for i in range(4)],
                        image_size=(32, 32), stride=2, sigma=2.0,
                        model=UNetConfig(channels=(8, 8), res_blocks=1, stride=2).to_dict())
    run = save_run(tmp_path / "run", meta, seed=0, dataset=str(dataset))
    out = tmp_path / "grasp.json"
    assert main(["robot", "grasp", str(run), "--trials", "1", "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["trials"] == 1 and doc["detector"] == str(run)
    assert doc["object_seed"] == 3 and doc["size"] == 32
    assert len(doc["per_trial"]) == 1 and np.isfinite(doc["per_trial"][0]["aim_error_mm"])


def test_grasps_over_seeds_and_the_summary_keep_the_agents_figures():
    """The grasp results of several detector seeds are combined per source (success rate over the seeds,
    per arrangement, aim error), and the robot summary takes them in place of its grasp alone: its agents'
    figures are kept, its scale and plush detector figures become those of the detectors grasped with."""
    from s3k.robot.results import grasps_over_seeds, with_grasp

    rates = {"s3k": [1.0, 0.5], "labels_only": [0.5, 0.5], "ground_truth": [1.0, 1.0]}
    docs = {}
    for src, per_seed in rates.items():
        for seed, rate in enumerate(per_seed):
            trials = [{"arrangement": 7 + i, "success": i < 2 * rate, "aim_error_mm": 1.0 + i + seed}
                      for i in range(2)]
            per_arrangement = {str(t["arrangement"]): float(t["success"]) for t in trials}
            docs[src, seed] = {"trials": 2, "success_rate": rate, "per_arrangement": per_arrangement,
                               "per_trial": trials}
    record = grasps_over_seeds(docs, [0, 1])
    assert record["s3k"]["success_rate"]["mean"] == 0.75 and record["s3k"]["per_arrangement"] == {"7": 1.0,
                                                                                                  "8": 0.5}
    assert record["s3k"]["trials"] == 4 and record["s3k"]["aim_error_mm_median"] == 2.0
    record.update(scale="plush grasp ...", seeds=[0, 1], arrangements=[7, 8], git_revision="abc")
    summary = {"grasp_success": {"s3k": 0.1}, "rl_final_success": {"keypoints": {"mean": 0.5}},
               "scale": "plush 96 px ...; 30 grasps each; insertion views 64 px, 3 seeds",
               "detectors_test": {"s3k": {"median_mm": 9.0}, "labels_only": {"median_mm": 8.0},
                                  "insertion": {"median_mm": 5.0}}}
    tests = {"s3k": [{"median_mm": m, "rms_mm": 6.0, "pck_10mm": 0.9} for m in (4.0, 5.0)],
             "labels_only": None}
    out = with_grasp(summary, record, 2, tests)
    assert out["rl_final_success"] == {"keypoints": {"mean": 0.5}}
    g = out["grasp_success"]
    assert (g["s3k"], g["labels_only"], g["ground_truth"]) == (0.75, 0.5, 1.0)
    assert g["trials"] == 2 and g["trials_in_all"] == 4 and g["arrangements"] == 2
    assert g["per_seed"]["s3k"] == [1.0, 0.5] and g["git_revision"] == "abc"
    assert out["scale"] == "grasp: plush grasp ...; agents: insertion views 64 px, 3 seeds"
    assert out["detectors_test"]["s3k"]["median_mm"]["per_seed"] == [4.0, 5.0]
    assert "labels_only" not in out["detectors_test"]  # its detectors' figures unknown here: none given
    assert out["detectors_test"]["insertion"] == {"median_mm": 5.0}
    assert summary["grasp_success"] == {"s3k": 0.1}  # the summary given is not changed
    # The agents' part of the scale is taken from its own field where the summary has one.
    summary.update(scale="plush ...; 30 grasps each; agents at 384 px", agents_scale="agents at 384 px")
    assert with_grasp(summary, record, 2, tests)["scale"] == \
        "grasp: plush grasp ...; agents: agents at 384 px"
