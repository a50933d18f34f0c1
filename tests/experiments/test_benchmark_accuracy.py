"""The accuracy benchmark's stages (s3k.experiments.accuracy, behind benchmarks/accuracy.py)
--labels-only-from: the renders and labels-only runs of an earlier working folder are linked, not made
again, and an unfinished run is refused; --coarse-from: a run starts from an earlier run's coarse stage,
its CPU time counted, and refuses one its options would not make."""

from __future__ import annotations

import json
import os
import sys
from types import SimpleNamespace

import pytest

from s3k.experiments.accuracy import reuse_coarse, reuse_labels_only


def test_labels_only_runs_are_linked_from_an_earlier_working_folder(tmp_path):
    args = SimpleNamespace(scene="box", render=384, passes=2, label_pool=10, label_choice="random")
    old, new = tmp_path / "old", tmp_path / "new"
    for s in (0, 1):
        (old / f"box384-seed{s}").mkdir(parents=True)
        (old / f"labels_only-seed{s}").mkdir()
        (old / f"labels_only-seed{s}" / "two_pass.json").write_text("{}")
        (old / f"labels_only-seed{s}-cpu.json").write_text('{"cpu_minutes": 1.0}')
        (old / f"s3k-seed{s}").mkdir()
    new.mkdir()
    reuse_labels_only(old, new, [0, 1], args)
    linked = sorted(p.name for p in new.iterdir())
    assert linked == ["box384-seed0", "box384-seed1", "labels_only-seed0", "labels_only-seed0-cpu.json",
                      "labels_only-seed1", "labels_only-seed1-cpu.json"]  # no S3K run, no missing record
    assert (new / "labels_only-seed1").resolve() == (old / "labels_only-seed1").resolve()
    (old / "labels_only-seed2").mkdir()
    with pytest.raises(SystemExit, match="labels_only-seed2"):
        reuse_labels_only(old, new, [2], args)


def test_cpu_record_counts_the_minutes_of_an_interrupted_run(tmp_path):
    """A record left with the unfinished minutes of a run whose benchmark process died is folded into the
    total when the run resumes; a finished job leaves no unfinished entry."""
    import json

    from s3k.experiments.accuracy import _cpu_minutes_so_far, read_record, run_jobs

    record = tmp_path / "s3k-seed0-cpu.json"
    record.write_text(json.dumps({"cpu_minutes": 2.0, "wall_minutes": 3.0, "unfinished_cpu_minutes": 1.5,
                                  "unfinished_wall_minutes": 2.5}))
    burn = [sys.executable, "-c",
            "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.2: pass"]
    run_jobs([("s3k seed 0", burn, record)], parallel=1, poll_s=0.05)
    spent = json.loads(record.read_text())
    assert set(spent) == {"cpu_minutes", "wall_minutes"}
    assert spent["cpu_minutes"] > 3.5 and spent["wall_minutes"] > 5.5  # 2 + 1.5 before, plus this run
    assert _cpu_minutes_so_far(os.getpid()) > 0  # what is written while a job runs
    # a run that finished as its benchmark died is not trained again; its record still counts what it spent
    record.write_text(json.dumps({"cpu_minutes": 0.0, "wall_minutes": 0.0, "unfinished_cpu_minutes": 31.5,
                                  "unfinished_wall_minutes": 35.0}))
    assert read_record(record) == {"cpu_minutes": 31.5, "wall_minutes": 35.0}
    with pytest.raises(SystemExit, match="s3k seed 1 failed"):
        fail = [sys.executable, "-c", "raise SystemExit(3)"]
        run_jobs([("s3k seed 1", fail, tmp_path / "r.json")], parallel=1, poll_s=0.05)


def test_every_job_is_recorded_when_two_end_before_the_next_starts(tmp_path):
    """Jobs that end together are each seen to end and recorded; the Popen of a job started earlier must not
    reap one behind the scheduler's back (it then waited for a job that had long finished)."""
    import json

    from s3k.experiments.accuracy import run_jobs

    quick = [sys.executable, "-c", "pass"]
    jobs = [(f"job {i}", quick, tmp_path / f"r{i}.json") for i in range(4)]
    run_jobs(jobs, parallel=2, poll_s=0.3)
    for _, _, record in jobs:
        spent = json.loads(record.read_text())
        assert set(spent) == {"cpu_minutes", "wall_minutes"} and spent["cpu_minutes"] > 0


def test_notes_stay_out_of_the_recorded_command():
    from s3k.experiments.accuracy import without_notes

    argv = ["--seeds", "3", "--notes", "trained at abc1234", "--work", "runs/w", "--notes=again"]
    assert without_notes(argv) == ["--seeds", "3", "--work", "runs/w"]
    assert without_notes(["--seeds", "3"]) == ["--seeds", "3"]


def test_an_evaluation_cached_by_an_older_read_out_is_made_again(tmp_path, monkeypatch):
    from s3k.experiments import accuracy

    calls = []
    monkeypatch.setattr(accuracy, "evaluate_run",
                        lambda run, data, split, device: calls.append(run) or {"median_mm": 2.0})
    run = tmp_path / "s3k-seed0"
    cache = tmp_path / "s3k-seed0-test.json"
    cache.write_text('{"median_mm": 5.0}\n')  # no read-out mark: every view entered
    assert accuracy.evaluate(run, tmp_path / "data")["median_mm"] == 2.0 and calls == [run]
    assert accuracy.evaluate(run, tmp_path / "data") == {"median_mm": 2.0, "readout": accuracy.READOUT}
    assert calls == [run]  # the new evaluation is the cache now


def test_ten_labelled_frames_chosen_from_a_larger_pool(tmp_path):
    from helpers.synthetic_rig import make_dataset

    from s3k.data import Dataset
    from s3k.experiments.accuracy import data_names, labelled_view
    from s3k.experiments.views import select_frames

    args = SimpleNamespace(scene="box", render=384, label_pool=30, label_choice="coverage")
    assert data_names(args, 2) == ["box384-L30-seed2", "box384-L30-coverage-seed2"]
    assert data_names(SimpleNamespace(scene="box", render=384, label_pool=10), 2) == ["box384-seed2"]
    pool_dir = make_dataset(tmp_path / "pool", size=16, labelled=14, unlabelled=5, test=3)
    pool = Dataset.open(pool_dir, cache="none")
    views = {}
    for choice in ("random", "coverage", "representative"):
        view = Dataset.open(labelled_view(pool_dir, tmp_path / choice, choice, seed=1), cache="none")
        views[choice] = view.frames("labelled").tolist()
        assert views[choice] == select_frames(pool, 10, 5, seed=1, choice=choice)["labelled"].tolist()
        assert view.frames("unlabelled").tolist() == pool.frames("unlabelled").tolist()
        assert view.frames("test").tolist() == pool.frames("test").tolist()
    assert views["random"] != views["coverage"]


def test_a_run_starts_from_an_earlier_runs_coarse_stage(tmp_path, capsys):
    from helpers.synthetic_rig import make_dataset

    from s3k import cli
    from s3k.run_folder import RunFolder
    from s3k.train.presets import PRESETS

    CPU_FILE = RunFolder.CPU

    def read_cpu(run):
        return RunFolder(run).read_cpu()

    data = make_dataset(tmp_path / "d", size=64, labelled=4, unlabelled=6, test=3)
    old, new = tmp_path / "old", tmp_path / "new"
    # as the benchmark trains: a preset whose refining pass has its own rotation and learning rate
    args = ["--preset", "box-headline", "--steps", "2", "--coarse-steps", "2", "--coarse-size", "32",
            "--crop-size", "32", "--channels", "8,8", "--res_blocks", "1", "--val_every", "0",
            "--warmup_steps", "1", "--ramp_steps", "1", "--no-progress", "--threads", "1"]
    assert cli.main(["train", str(data), "--out", str(old / "s3k-seed0"), *args]) == 0
    source_cpu = read_cpu(old / "s3k-seed0")
    reuse_coarse(old, [new / "s3k-seed0"])
    record = json.loads((new / "s3k-seed0-cpu.json").read_text())
    assert record["cpu_minutes"] == pytest.approx(source_cpu["coarse"] / 60)
    assert read_cpu(new / "s3k-seed0") == {"coarse": source_cpu["coarse"]}
    coarse_model = new / "s3k-seed0" / "coarse" / "model.pt"
    before = coarse_model.stat().st_mtime_ns
    # the benchmark's training command resumes it: only the refining pass is trained
    assert cli.main(["train", str(data), "--out", str(new / "s3k-seed0"), *args, "--resume"]) == 0
    assert coarse_model.stat().st_mtime_ns == before and (new / "s3k-seed0" / "fine" / "model.pt").is_file()
    fine = [json.loads((run / "s3k-seed0" / "fine" / "config.json").read_text())["config"]
            for run in (old, new)]
    preset = PRESETS["box-headline"].config
    assert preset.augmentation.rotation_deg != PRESETS["box-headline"].config.passes.coarse_rotation
    # the preset's refining pass, not the coarse pass's rotation and learning rate
    own = (preset.augmentation.rotation_deg, preset.schedule.lr)
    assert [(c["rotation_deg"], c["lr"]) for c in fine] == [own] * 2
    spent = read_cpu(new / "s3k-seed0")
    assert spent["coarse"] >= source_cpu["coarse"] and spent["crops"] > 0 and spent["fine"] > 0
    # options that would make another coarse pass are refused; a run already begun is left alone
    (old / "other").symlink_to(old / "s3k-seed0")
    reuse_coarse(old, [new / "other"])
    capsys.readouterr()
    assert cli.main(["train", str(data), "--out", str(new / "other"), *args, "--coarse-steps", "3",
                     "--resume"]) == 1
    assert "steps is 3" in capsys.readouterr().err
    # a source without its coarse stage's CPU record is refused
    (old / "s3k-seed0" / CPU_FILE).unlink()
    with pytest.raises(SystemExit, match=CPU_FILE):
        reuse_coarse(old, [new / "s3k-seed2"])


def test_the_insertion_scene_renders_its_own_rig_with_the_seed_drawing_the_episodes(tmp_path):
    """``--scene insertion`` renders the cable-insertion environment's dataset (plug tip, plug base, socket)
    once per seed; another seed draws other episodes from the same rig."""
    from s3k.data import Dataset
    from s3k.experiments.accuracy import render

    args = SimpleNamespace(scene="insertion", render=32, label_pool=10, label_choice="random", unlabelled=4,
                           test=2, parallel=1)
    out = render(args, 0, tmp_path)
    assert out == tmp_path / "insertion32-seed0"
    ds = Dataset.open(out, cache="none")
    assert ds.keypoints == ["plug_tip", "plug_base", "socket"]
    assert [len(ds.frames(s)) for s in ("labelled", "unlabelled", "test")] == [10, 4, 2]
    assert render(args, 0, tmp_path) == out  # rendered once: the stage is skipped
    other = Dataset.open(render(args, 1, tmp_path), cache="none")
    assert json.loads((out / "s3k.json").read_text())["source"]["seed"] == 0
    assert json.loads((tmp_path / "insertion32-seed1" / "s3k.json").read_text())["source"]["seed"] == 1
    X0, X1 = ds.points3d(ds.frames("test")), other.points3d(other.frames("test"))
    assert X0 is not None and X1 is not None and X0[1].all() and X1[1].all()
    assert abs(X0[0] - X1[0]).max() > 0.001  # metres: other episodes
