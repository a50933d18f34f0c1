"""``s3k experiment``: sweep plans, frame selection, dataset views, toy sweeps, resumption and summaries."""

from __future__ import annotations

import json
import shlex
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import s3k.experiments as ex
from s3k.cli import main as cli_main

pytest.importorskip("mujoco")


def toy_options(name: str, out: Path, **over) -> ex.Options:
    base = dict(experiment=name, out=out, scale="toy", threads=1, workers=1, progress=False)
    base.update(over)
    return ex.Options(**base)


@pytest.fixture(scope="module")
def workspace(tmp_path_factory) -> Path:
    """One workspace for every toy sweep of this module, so that they share rendered datasets as users do."""
    return tmp_path_factory.mktemp("experiments")


def result_files(out: Path, name: str) -> dict[str, float]:
    return {p.parent.name: p.stat().st_mtime_ns for p in (out / name / "runs").glob("*/result.json")}


# ------------------------------------------------------------------------------------------------------ plans
@pytest.mark.parametrize("name", ex.EXPERIMENTS)
def test_toy_plan_has_two_runs_on_tiny_data(name, tmp_path):
    runs = ex.plan(toy_options(name, tmp_path))
    assert len(runs) == 2
    assert len({r.name for r in runs}) == 2
    for r in runs:
        assert r.pool.size <= 48 and r.cfg.steps == 2
        assert r.cfg.unsup == (r.unlabelled > 0)
        assert r.params["method"] == ("s3k" if r.unlabelled > 0 else "no_unsup")


def test_small_and_full_grids_follow_the_paper(tmp_path):
    full = ex.plan(ex.Options("label-efficiency", tmp_path, scale="full"))
    points = {(r.labelled, r.unlabelled) for r in full}
    assert points == {(L, U) for L in (3, 10, 30, 100) for U in (0, 300, 3000)}
    seeds = {}
    for r in full:
        seeds.setdefault((r.labelled, r.unlabelled), set()).add(r.seed)
    for (L, _), s in seeds.items():
        assert len(s) == (3 if L in (3, 10) else 1)  # seeds where the claims are made
    assert {r.cfg.steps for r in full} == {ex.TrainConfig().steps}
    assert {r.pool.size for r in full} == {96}
    cat = ex.plan(ex.Options("category", tmp_path, scale="full"))
    assert sorted({r.params["instances"] for r in cat}) == sorted(ex.PAPER_CATEGORY_TEST_PX)
    assert all(r.eval_train and r.pool.train_instances == r.params["instances"] for r in cat)
    shift = ex.plan(ex.Options("domain-shift", tmp_path, scale="small"))
    assert {r.params["mode"] for r in shift} == {"start", "full"}
    assert {r.pool.mode for r in shift} == {"start", "full"}
    alpha = ex.plan(ex.Options("alpha", tmp_path, scale="small"))
    assert sorted({r.params["alpha"] for r in alpha}) == [0.1, 0.25, 0.5, 1.0]
    assert all(r.cfg.alpha == r.params["alpha"] and r.cfg.unsup for r in alpha)
    # the alpha sweep reuses the label-efficiency dataset of the same scale
    small = ex.plan(ex.Options("label-efficiency", tmp_path, scale="small"))
    assert {r.pool.name for r in alpha} == {r.pool.name for r in small}
    # warm-up and ramp keep the default proportions of the schedule
    cfg = small[0].cfg
    default = ex.TrainConfig()
    assert cfg.warmup_steps / cfg.steps == pytest.approx(default.warmup_steps / default.steps)


def test_plan_overrides_and_errors(tmp_path):
    runs = ex.plan(ex.Options("label-efficiency", tmp_path, scale="small", labelled=[5], unlabelled=[0, 7],
                              steps=11, size=40, seeds=2, seeds_other=2))
    assert {(r.labelled, r.unlabelled) for r in runs} == {(5, 0), (5, 7)}
    assert {r.cfg.steps for r in runs} == {11} and {r.pool.size for r in runs} == {40}
    assert len(runs) == 4
    with pytest.raises(ValueError, match="--alphas"):
        ex.plan(ex.Options("label-efficiency", tmp_path, alphas=[0.5]))
    with pytest.raises(ValueError, match="instances"):
        ex.plan(ex.Options("category", tmp_path, instances=[13]))
    with pytest.raises(ValueError, match="unknown"):
        ex.plan(ex.Options("nope", tmp_path))


def test_cli_rejects_bad_train_field(tmp_path, capsys):
    code = cli_main(["experiment", "alpha", "--out", str(tmp_path), "--scale", "toy", "--set", "nope=1"])
    assert code == 2
    assert "nope" in capsys.readouterr().err


def test_dry_run_prints_the_estimate_and_runs_nothing(tmp_path, capsys):
    code = cli_main(["experiment", "label-efficiency", "--out", str(tmp_path), "--scale", "small",
                     "--dry-run"])
    assert code == 0
    text = capsys.readouterr().out
    n = len(ex.plan(ex.Options("label-efficiency", tmp_path, scale="small")))
    assert f"{n} runs" in text and "CPU-hours" in text
    assert not (tmp_path / "data").exists()


# ----------------------------------------------------------------------------------------- frame selection
def test_stratified_pick_nests_balances_and_sorts():
    ids = np.arange(100, 160)
    groups = np.repeat(np.arange(6), 10)
    small = ex.stratified_pick(ids, groups, 4, np.random.default_rng(7))
    large = ex.stratified_pick(ids, groups, 13, np.random.default_rng(7))
    assert set(small) <= set(large)
    assert np.all(np.diff(large) > 0)
    counts = np.bincount(groups[np.searchsorted(ids, large)], minlength=6)
    assert counts.max() - counts.min() <= 1
    other = ex.stratified_pick(ids, groups, 13, np.random.default_rng(8))
    assert set(other) != set(large)
    with pytest.raises(ValueError, match="cannot pick"):
        ex.stratified_pick(ids, None, 61, np.random.default_rng(0))


# ------------------------------------------------------------------------------------------------------ locks
def test_lock_refuses_while_held_and_takes_over_a_dead_holder(tmp_path):
    lock = tmp_path / "run.lock"
    with ex._claim(lock) as first:
        assert first and lock.is_file()
        with ex._claim(lock) as second:
            assert not second
    assert not lock.exists()
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True, check=True)
    lock.write_text(f"{int(dead.stdout)} {socket.gethostname()}")
    with ex._claim(lock) as mine:
        assert mine


# ------------------------------------------------------------------------------------------------ summaries
def fake_result(params: dict, rms_px: float, size: int = 64, split_train: bool = False) -> dict:
    metrics = {"rms_px": rms_px, "rms_px_reproj": rms_px / 2, "median_mm": 3 * rms_px, "rms_mm": 4 * rms_px}
    return {"run": json.dumps(params), "params": params, "status": "done", "image_size": [size, size],
            "config": {"steps": 10}, "wall_time_s": {"total": 1.0},
            "metrics": {"test": dict(metrics), **({"train": dict(metrics)} if split_train else {})}}


def test_aggregate_scales_to_paper_pixels_and_averages_seeds():
    results = [fake_result({"labelled": 3, "unlabelled": 0, "seed": s, "method": "no_unsup"}, v)
               for s, v in enumerate([2.0, 4.0, 6.0])]
    (point,) = ex.aggregate(results)
    assert point["seeds"] == [0, 1, 2]
    s = point["test"]["rms_px"]
    assert s["mean"] == pytest.approx(4.0) and s["std"] == pytest.approx(np.std([2, 4, 6], ddof=1))
    assert point["test"]["rms_px_400"]["mean"] == pytest.approx(4.0 * 400 / 64)
    assert point["test"]["median_mm"]["values"] == [6.0, 12.0, 18.0]


def test_findings_follow_the_numbers():
    def le(L, U, values):
        return [fake_result({"labelled": L, "unlabelled": U, "seed": s, "method": "x"}, v)
                for s, v in enumerate(values)]

    better = ex.aggregate(le(3, 0, [10, 11, 12]) + le(3, 300, [5, 6, 7]) + le(3, 3000, [2, 3, 4]))
    f = ex.findings("label-efficiency", better)
    assert [x["reproduced"] for x in f] == [True, True]
    worse = ex.aggregate(le(3, 0, [2, 3, 4]) + le(3, 300, [5, 6, 7]))
    assert ex.findings("label-efficiency", worse)[0]["reproduced"] is False
    noisy = ex.aggregate(le(3, 0, [2, 9, 4]) + le(3, 300, [5, 1, 7]))
    assert ex.findings("label-efficiency", noisy)[0]["reproduced"] == "within noise"
    alpha = ex.aggregate([fake_result({"labelled": L, "unlabelled": 9, "alpha": a, "seed": 0}, v)
                          for L, a, v in [(3, 0.1, 1), (3, 1.0, 2), (30, 0.1, 2), (30, 1.0, 1)]])
    assert ex.findings("alpha", alpha)[0]["reproduced"] is True


def test_domain_shift_gap_verdict_compares_sizes():
    def ds(values):  # (mode, unlabelled) -> error
        return ex.aggregate([fake_result({"mode": m, "labelled": 10, "unlabelled": U, "seed": 0}, v)
                             for (m, U), v in values.items()])

    def gap_verdict(values):
        (f,) = [x for x in ex.findings("domain-shift", ds(values)) if "gap" in x["finding"]]
        return f["reproduced"]

    # start 10 px worse without unlabelled frames, 1 px with: the gap closes
    assert gap_verdict({("start", 0): 30, ("full", 0): 20, ("start", 100): 16, ("full", 100): 15}) is True
    # it widens
    assert gap_verdict({("start", 0): 30, ("full", 0): 25, ("start", 100): 30, ("full", 100): 15}) is False
    # start overtakes full by more than the gap was: not a narrower gap
    assert gap_verdict({("start", 0): 30, ("full", 0): 25, ("start", 100): 10, ("full", 100): 20}) is False
    # start is not worse to begin with: nothing to close
    assert gap_verdict({("start", 0): 20, ("full", 0): 25, ("start", 100): 15, ("full", 100): 15}) == (
        "no gap without unlabelled frames")


def test_plots_and_readme_without_runs(tmp_path):
    (tmp_path / "category" / "runs").mkdir(parents=True)
    summary = ex.summarize(tmp_path / "category")
    assert summary["runs"] == 0 and summary["points"] == []
    assert all((tmp_path / "category" / f).stat().st_size > 0 for f in summary["figures"])
    assert "paper finding" in (tmp_path / "category" / "README.md").read_text()


# ------------------------------------------------------------------------------------------- toy sweeps
def check_sweep(out: Path, name: str, outcome: dict) -> None:
    runs = ex.plan(toy_options(name, out))
    files = result_files(out, name)
    assert sorted(files) == sorted(r.name for r in runs)  # one JSON per run
    for r in runs:
        result = json.loads((out / name / "runs" / r.name / "result.json").read_text())
        assert result["status"] == "done" and result["steps"] == 2
        assert result["params"] == r.params
        assert result["config"]["unsup"] == (r.unlabelled > 0)
        assert result["metrics"]["test"]["rms_px"] is not None
        assert result["wall_time_s"]["total"] > 0
        assert result["data"]["frames"]["labelled"] == r.labelled
        assert result["data"]["frames"]["unlabelled"] == r.unlabelled
    summary = json.loads((out / name / "summary.json").read_text())
    assert summary["runs"] == 2 and len(summary["points"]) == 2
    assert summary["figures"] and all((out / name / f).stat().st_size > 1000 for f in summary["figures"])
    assert outcome["failed"] == []


def test_label_efficiency_sweep_cli_resumes_and_summarizes(workspace, capsys):
    argv = ["experiment", "label-efficiency", "--out", str(workspace), "--scale", "toy", "--no-progress",
            "--threads", "1", "--workers", "1"]
    assert cli_main(argv) == 0
    assert "2 runs" in capsys.readouterr().out  # the plan is printed first
    check_sweep(workspace, "label-efficiency", {"failed": []})
    before = result_files(workspace, "label-efficiency")
    models = {p: p.stat().st_mtime_ns for p in (workspace / "label-efficiency").glob("runs/*/model.pt")}
    outcome = ex.run_experiment(toy_options("label-efficiency", workspace), log=lambda m: None)
    assert outcome["trained"] == [] and len(outcome["skipped"]) == 2  # nothing trained again
    assert result_files(workspace, "label-efficiency") == before
    assert {p: p.stat().st_mtime_ns for p in models} == models
    # the summary path on its own, and publishing to a results folder
    exp = workspace / "label-efficiency"
    for f in ["summary.json", "README.md", *outcome["summary"]["figures"]]:
        (exp / f).unlink()
    pub = workspace / "published"
    assert cli_main(["experiment", "label-efficiency", "--out", str(workspace), "--summarize-only",
                     "--publish", str(pub)]) == 0
    assert (exp / "summary.json").is_file() and (exp / "error_vs_labelled.png").is_file()
    assert {p.name for p in pub.iterdir()} == {"summary.json", "README.md", "error_vs_labelled.png",
                                               "error_vs_total_frames.png"}
    # each run recorded the command that made it; the summary and its page say it
    summary = json.loads((pub / "summary.json").read_text())
    assert summary["commands"] == [shlex.join(["s3k", *argv])] and summary["runs_without_provenance"] == 0
    assert f"Command: `{shlex.join(['s3k', *argv])}`" in (pub / "README.md").read_text()
    # different settings in the same folder are refused, not mixed
    assert cli_main([*argv, "--steps", "3"]) == 2


def test_alpha_sweep_resumes_after_a_kill_during_evaluation(workspace, monkeypatch):
    import s3k.evaluate

    real = s3k.evaluate.evaluate_run

    def killed(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(s3k.evaluate, "evaluate_run", killed)
    with pytest.raises(KeyboardInterrupt):
        ex.run_experiment(toy_options("alpha", workspace), log=lambda m: None)
    first = ex.plan(toy_options("alpha", workspace))[0]
    run_dir = workspace / "alpha" / "runs" / first.name
    assert (run_dir / "model.pt").is_file() and not (run_dir / "result.json").exists()
    assert not (run_dir / "run.lock").exists()
    trained_at = (run_dir / "model.pt").stat().st_mtime_ns
    monkeypatch.setattr(s3k.evaluate, "evaluate_run", real)
    outcome = ex.run_experiment(toy_options("alpha", workspace), log=lambda m: None)
    check_sweep(workspace, "alpha", outcome)
    assert (run_dir / "model.pt").stat().st_mtime_ns == trained_at  # finished run not trained again
    assert json.loads((run_dir / "result.json").read_text())["resumed_from_step"] == 2
    # the box dataset rendered for label-efficiency was reused
    assert len(list((workspace / "data").glob("box-*"))) == 1


def test_domain_shift_sweep(workspace):
    outcome = ex.run_experiment(toy_options("domain-shift", workspace), log=lambda m: None)
    check_sweep(workspace, "domain-shift", outcome)
    assert sorted(p.name.split("-")[1] for p in (workspace / "data").glob("distractors-*")) == ["full",
                                                                                                "start"]
    again = ex.run_experiment(toy_options("domain-shift", workspace), log=lambda m: None)
    assert again["trained"] == []


def test_category_sweep_evaluates_training_and_held_out_instances(workspace):
    outcome = ex.run_experiment(toy_options("category", workspace), log=lambda m: None)
    check_sweep(workspace, "category", outcome)
    for p in (workspace / "category" / "runs").glob("*/result.json"):
        metrics = json.loads(p.read_text())["metrics"]
        assert set(metrics) == {"test", "train"}
    summary = json.loads((workspace / "category" / "summary.json").read_text())
    assert summary["paper"]["category_test_px"]["12"] == ex.PAPER_CATEGORY_TEST_PX[12]
    # views are small: tables filtered, images linked to the rendered dataset
    from s3k.data.format import Dataset

    pool = next((workspace / "data").glob("category-i2-*"))
    view = next((workspace / "data" / "views" / pool.name).glob("L*"))
    assert (view / "images").is_symlink()
    ds, full = Dataset.open(view, cache="none"), Dataset.open(pool, cache="none")
    for split in ("labelled", "unlabelled", "test"):
        assert set(ds.frames(split)) <= set(full.frames(split))
    ids = ds.frames("test")
    np.testing.assert_array_equal(ds.images(ids), full.images(ids))
