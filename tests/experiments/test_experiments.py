"""``s3k experiment``: sweep plans, frame selection, dataset views, locks, toy sweeps, resumption, findings
and summaries."""

from __future__ import annotations

import json
import os
import shlex
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers.experiment_results import MM_PER_PX, fake_result, old_summary
from helpers.paths import REPO
from helpers.synthetic_rig import make_dataset

import s3k
import s3k.experiments as ex
from s3k.base.errors import UserError
from s3k.base.fileio import file_lock
from s3k.cli import main as cli_main
from s3k.config import TrainConfig
from s3k.data import Dataset
from s3k.experiments.findings import lower
from s3k.experiments.report import readme
from s3k.experiments.runner import LOCK_FILE, run_one
from s3k.experiments.views import make_view, select_frames
from s3k.sim.generate import scene_mm_per_px

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
        assert r.pool.size <= 48 and r.cfg.schedule.steps == 2
        assert r.cfg.self_supervision.unsup == (r.unlabelled > 0)
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
    assert {r.cfg.schedule.steps for r in full} == {TrainConfig().schedule.steps}
    assert {r.pool.size for r in full} == {96}
    cat = ex.plan(ex.Options("category", tmp_path, scale="full"))
    assert sorted({r.params["instances"] for r in cat}) == sorted(ex.PAPER_CATEGORY_TEST_PX)
    assert all(r.eval_train and r.pool.train_instances == r.params["instances"] for r in cat)
    shift = ex.plan(ex.Options("domain-shift", tmp_path, scale="small"))
    assert {r.params["mode"] for r in shift} == {"start", "full"}
    assert {r.pool.mode for r in shift} == {"start", "full"}
    alpha = ex.plan(ex.Options("alpha", tmp_path, scale="small"))
    assert sorted({r.params["alpha"] for r in alpha}) == [0.1, 0.25, 0.5, 1.0]
    assert all(r.cfg.self_supervision.alpha == r.params["alpha"] for r in alpha)
    assert all(r.cfg.self_supervision.unsup for r in alpha)
    # the alpha sweep reuses the label-efficiency dataset of the same scale
    small = ex.plan(ex.Options("label-efficiency", tmp_path, scale="small"))
    assert {r.pool.name for r in alpha} == {r.pool.name for r in small}
    # warm-up and ramp keep the default proportions of the schedule
    cfg = small[0].cfg
    default = TrainConfig()
    assert cfg.self_supervision.warmup_steps / cfg.schedule.steps == \
        pytest.approx(default.self_supervision.warmup_steps / default.schedule.steps)


def test_plan_overrides_and_errors(tmp_path):
    runs = ex.plan(ex.Options("label-efficiency", tmp_path, scale="small", labelled=[5], unlabelled=[0, 7],
                              steps=11, size=40, seeds=2, seeds_other=2))
    assert {(r.labelled, r.unlabelled) for r in runs} == {(5, 0), (5, 7)}
    assert {r.cfg.schedule.steps for r in runs} == {11} and {r.pool.size for r in runs} == {40}
    assert len(runs) == 4
    with pytest.raises(ValueError, match="--alphas"):
        ex.plan(ex.Options("label-efficiency", tmp_path, alphas=[0.5]))
    with pytest.raises(ValueError, match="instances"):
        ex.plan(ex.Options("category", tmp_path, instances=[13]))
    with pytest.raises(ValueError, match="unknown"):
        ex.plan(ex.Options("nope", tmp_path))


def test_cli_rejects_bad_train_field_in_one_line(tmp_path, capsys):
    code = cli_main(["experiment", "alpha", "--out", str(tmp_path), "--scale", "toy", "--set", "nope=1"])
    assert code == 1
    err = capsys.readouterr().err
    assert err.startswith("s3k experiment: error: --set: unknown field 'nope'") and err.count("\n") == 1
    assert cli_main(["experiment", "alpha", "--out", str(tmp_path), "--set", "lr=-1"]) == 1
    assert "'lr' must be in (0, 1]" in capsys.readouterr().err
    assert not (tmp_path / "data").exists()


def test_summarize_only_without_runs_is_one_line(tmp_path, capsys):
    assert cli_main(["experiment", "alpha", "--out", str(tmp_path), "--summarize-only"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "nothing to summarize" in err and "--out" in err


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


# ----------------------------------------------------------------------------------------------------- views
def test_view_holds_the_chosen_frames_of_the_pool_with_linked_images(tmp_path):
    pool = Dataset.open(make_dataset(tmp_path / "pool", labelled=6, unlabelled=5, test=3), cache="none")
    frames = select_frames(pool, 4, 2, seed=1)
    assert set(frames["labelled"]) <= set(pool.frames("labelled")) and len(frames["labelled"]) == 4
    assert frames["unlabelled"].tolist() == select_frames(pool, 1, 2, seed=5)["unlabelled"].tolist()
    spare = sorted(set(pool.frames("unlabelled")) - set(frames["unlabelled"]))[:1]
    frames["test"] = np.concatenate([frames["test"], spare])  # a frame that changes split
    view = make_view(pool, tmp_path / "views" / "v", frames, {"seed": 1})
    assert (view / "images").is_symlink()
    ds = Dataset.open(view, cache="none")
    assert ds.source == {"view_of": "../../pool", "pool_source": None, "seed": 1}
    for split, ids in frames.items():
        assert sorted(ds.frames(split).tolist()) == sorted(ids.tolist())
    ids = ds.frames()
    np.testing.assert_array_equal(ds.images(ids), pool.images(ids))
    for a, b in zip(ds.labels(ids), pool.labels(ids)):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(ds.points3d(ids), pool.points3d(ids)):
        np.testing.assert_array_equal(a, b)
    cal, cal_pool = ds.calibration(ids, np.float64).numpy(), pool.calibration(ids, np.float64).numpy()
    for name in ("K", "dist", "R", "t"):
        np.testing.assert_array_equal(cal[name], cal_pool[name])
    assert ds.static_calibration and len(ds) == 4 + 2 + 3 + 1
    assert [p.name for p in (tmp_path / "views").iterdir()] == ["v"]  # no temporary left


# ------------------------------------------------------------------------------------------------------ locks
def test_run_held_by_a_live_process_is_skipped_and_a_killed_holder_leaves_no_claim(tmp_path):
    spec = ex.plan(toy_options("label-efficiency", tmp_path))[0]
    run_dir = tmp_path / "label-efficiency" / "runs" / spec.name
    run_dir.mkdir(parents=True)
    messages: list[str] = []

    def attempt():
        return run_one(spec, tmp_path / "label-efficiency", tmp_path / "data",
                       toy_options("label-efficiency", tmp_path), messages.append)

    with file_lock(run_dir / LOCK_FILE) as mine:  # another holder of the claim, in this process
        assert mine
        assert attempt() is None
    assert messages == [f"{spec.name}: being trained by another process; skipped"]
    assert not (tmp_path / "data").exists()  # skipped before touching any data
    code = ("import sys, time\nfrom s3k.base.fileio import file_lock\nwith file_lock(sys.argv[1]):\n"
            "    print('held', flush=True)\n    time.sleep(600)\n")
    env = {**os.environ, "PYTHONPATH": str(Path(s3k.__file__).parents[1])}
    holder = subprocess.Popen([sys.executable, "-c", code, str(run_dir / LOCK_FILE)], stdout=subprocess.PIPE,
                              text=True, env=env)
    assert holder.stdout.readline() == "held\n"
    with file_lock(run_dir / LOCK_FILE, blocking=False) as mine:
        assert not mine
    holder.send_signal(signal.SIGKILL)
    holder.wait()
    with file_lock(run_dir / LOCK_FILE, blocking=False) as mine:
        assert mine  # the kernel freed the dead holder's claim


# ------------------------------------------------------------------------------------------------ summaries
def test_aggregate_gives_millimetres_and_averages_seeds():
    results = [fake_result({"labelled": 3, "unlabelled": 0, "seed": s, "method": "no_unsup"}, v)
               for s, v in enumerate([2.0, 4.0, 6.0])]
    (point,) = ex.aggregate(results, MM_PER_PX)
    assert point["seeds"] == [0, 1, 2]
    s = point["test"]["rms_px"]
    assert s["mean"] == pytest.approx(4.0) and s["std"] == pytest.approx(np.std([2, 4, 6], ddof=1))
    mm = point["test"]["rms_mm_2d"]
    assert mm["values"] == pytest.approx([12.0, 24.0, 36.0]) and mm["std"] == pytest.approx(6.0 * s["std"])
    assert point["test"]["rms_mm_2d_reproj"]["mean"] == pytest.approx(2.0 * 6.0)
    assert point["test"]["median_mm"]["values"] == [6.0, 12.0, 18.0]
    assert "rms_px_400" not in point["test"]
    # an image size without a pixel size gets no millimetres, not a wrong number
    (point,) = ex.aggregate(results, {})
    assert point["test"]["rms_mm_2d"]["mean"] is None and point["test"]["rms_px"]["mean"] == 4.0


def test_findings_verdicts_do_not_depend_on_the_unit():
    values = {(L, U): v for (L, U), v in zip([(3, 0), (3, 300), (3, 3000), (10, 0), (10, 3000)],
                                            [[10, 11, 12], [9, 11, 12], [2, 3, 4], [5, 6, 9], [9, 10, 11]])}
    results = [fake_result({"labelled": L, "unlabelled": U, "seed": s}, v)
               for (L, U), vs in values.items() for s, v in enumerate(vs)]
    points = ex.aggregate(results, MM_PER_PX)
    by_unit = {m: [f["reproduced"] for f in ex.findings("label-efficiency", points, metric=m)]
               for m in ("rms_px", "rms_mm_2d")}
    assert by_unit["rms_px"] == by_unit["rms_mm_2d"] == [True, False, "within noise"]
    f = ex.findings("label-efficiency", points)[0]
    assert f["measured"] == "18.00 +- 6.00 vs 66.00 +- 6.00 mm (per-view RMS)"


def test_findings_follow_the_numbers():
    def le(L, U, values):
        return [fake_result({"labelled": L, "unlabelled": U, "seed": s, "method": "x"}, v)
                for s, v in enumerate(values)]

    better = ex.aggregate(le(3, 0, [10, 11, 12]) + le(3, 300, [5, 6, 7]) + le(3, 3000, [2, 3, 4]), MM_PER_PX)
    f = ex.findings("label-efficiency", better)
    assert [x["reproduced"] for x in f] == [True, True]
    worse = ex.aggregate(le(3, 0, [2, 3, 4]) + le(3, 300, [5, 6, 7]), MM_PER_PX)
    assert ex.findings("label-efficiency", worse)[0]["reproduced"] is False
    noisy = ex.aggregate(le(3, 0, [2, 9, 4]) + le(3, 300, [5, 1, 7]), MM_PER_PX)
    assert ex.findings("label-efficiency", noisy)[0]["reproduced"] == "within noise"
    alpha = ex.aggregate([fake_result({"labelled": L, "unlabelled": 9, "alpha": a, "seed": 0}, v)
                          for L, a, v in [(3, 0.1, 1), (3, 1.0, 2), (30, 0.1, 2), (30, 1.0, 1)]], MM_PER_PX)
    assert ex.findings("alpha", alpha)[0]["reproduced"] is True


def test_domain_shift_gap_verdict_compares_sizes():
    def ds(values):  # (mode, unlabelled) -> error
        return ex.aggregate([fake_result({"mode": m, "labelled": 10, "unlabelled": U, "seed": 0}, v)
                             for (m, U), v in values.items()], MM_PER_PX)

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


def test_category_findings_follow_the_numbers():
    def cat(errors):  # instances -> (held-out error, training-instance error)
        results = []
        for n, (test, train) in errors.items():
            r = fake_result({"instances": n, "labelled": 30, "unlabelled": 9, "seed": 0}, test)
            r["metrics"]["train"] = dict(r["metrics"]["test"], rms_px=train)
            results.append(r)
        return [f["reproduced"] for f in ex.findings("category", ex.aggregate(results, MM_PER_PX))]

    # more instances: held-out error 30 -> 15, gap to training instances 20 -> 3
    assert cat({1: (30, 10), 6: (20, 12), 12: (15, 12)}) == [True, True]
    # held-out error rises and the gap widens
    assert cat({1: (15, 12), 12: (30, 10)}) == [False, False]
    # a single instance count measures nothing
    assert cat({12: (15, 12)}) == []


def test_lower_margin_is_two_standard_errors_or_two_percent():
    def s(mean, std=None, n=1):
        return {"mean": mean, "std": std, "n": n}

    # three seeds of std 2: two standard errors of the difference are 2 sqrt(8/3) = 3.27
    assert lower(s(10, 2, 3), s(13, 2, 3)) == "within noise"
    assert lower(s(10, 2, 3), s(13.5, 2, 3)) is True
    assert lower(s(13.5, 2, 3), s(10, 2, 3)) is False
    # single seeds: 2 % of the larger mean
    assert lower(s(10), s(10.2)) == "within noise"
    assert lower(s(10), s(10.3)) is True
    assert lower(None, s(10)) is None
    assert [ex.verdict(v) for v in (True, False, "within noise", None)] == ["yes", "no", "within noise",
                                                                          "not measured"]


# the experiments' summaries (docs/results holds benchmarks' summaries too, in other layouts)
PUBLISHED = sorted(p for p in (REPO / "docs" / "results").glob("*/summary.json")
                   if "points" in json.loads(p.read_text()))


@pytest.mark.parametrize("path", PUBLISHED, ids=lambda p: p.parent.name)
def test_published_summaries_give_their_findings_again(path):
    summary = json.loads(path.read_text())
    assert ex.findings(summary["experiment"], summary["points"]) == summary["findings"]
    page = readme(summary)
    for f in summary["findings"]:
        assert f"| {f['finding']} | {f['measured']} | {ex.verdict(f['reproduced'])} |" in page


@pytest.mark.parametrize("path", PUBLISHED, ids=lambda p: p.parent.name)
def test_published_verdicts_are_those_of_the_pixel_errors(path):
    # The claims compare errors at one image size, so millimetres (pixels x one pixel size) must give the
    # verdicts the pixel errors give (and so the ones the pixels scaled to 400 px gave before).
    summary = json.loads(path.read_text())
    in_px = ex.findings(summary["experiment"], summary["points"], metric="rms_px")
    assert [f["reproduced"] for f in in_px] == [f["reproduced"] for f in summary["findings"]]
    for p in summary["points"]:
        factor = summary["mm_per_px"][str(p["image_size"][0])]
        for split in ("test", "train"):
            if split in p:
                assert p[split]["rms_mm_2d"]["values"] == pytest.approx(
                    [v * factor for v in p[split]["rms_px"]["values"]])


def test_summarize_only_from_an_old_summary_without_runs(tmp_path):
    results = [fake_result({"labelled": L, "unlabelled": U, "seed": s}, v)
               for (L, U), vs in {(3, 0): [10, 11, 12], (3, 9): [2, 3, 4], (10, 0): [5, 6, 7],
                                  (10, 9): [5, 6, 8]}.items() for s, v in enumerate(vs)]
    old = old_summary(ex.aggregate(results, {}))
    exp = tmp_path / "label-efficiency"
    exp.mkdir()
    (exp / "summary.json").write_text(json.dumps(old))
    (exp / "README.md").write_text("# old\n\n## Findings\n\nold table\n\n## Reading\n\nWritten by hand.\n")
    assert cli_main(["experiment", "label-efficiency", "--out", str(tmp_path), "--summarize-only"]) == 0
    new = json.loads((exp / "summary.json").read_text())
    factor = new["mm_per_px"]["64"]
    assert factor == pytest.approx(scene_mm_per_px("box", 64))
    test = new["points"][0]["test"]
    assert test["rms_mm_2d"]["values"] == pytest.approx([factor * v for v in test["rms_px"]["values"]])
    assert "rms_px_400" not in test and new["paper"]["mm_per_px"] == ex.PAPER_MM_PER_PX
    assert [f["reproduced"] for f in new["findings"]] == [f["reproduced"] for f in old["findings"]]
    assert [f["reproduced"] for f in new["findings"]] == [True, "within noise"]
    # what the summary said about the runs is kept, and where this came from is said
    for key in ("runs", "scales", "image_sizes", "steps", "commands", "code_revisions"):
        assert new[key] == old[key]
    assert new["resummarized_from"]["generated_at"] == old["generated_at"]
    page = (exp / "README.md").read_text()
    assert "Re-summarized by `s3k experiment label-efficiency --summarize-only`" in page
    assert "Command: `s3k experiment label-efficiency --out W`" in page and "`728e85c`" in page
    assert page.endswith("\n## Reading\n\nWritten by hand.\n") and "old table" not in page
    assert all((exp / f).stat().st_size > 1000 for f in new["figures"])
    # again: the same summary (the source stays the summary of the runs)
    assert ex.resummarize(exp)["resummarized_from"] == new["resummarized_from"]
    assert json.loads((exp / "summary.json").read_text())["points"] == new["points"]
    with pytest.raises(UserError, match="a summary of experiment 'label-efficiency', not 'alpha'"):
        ex.resummarize(exp, "alpha")


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
    assert cli_main([*argv, "--steps", "3"]) == 1
    assert "finished with other settings (steps: 2 there, 3 now" in capsys.readouterr().err


def test_alpha_sweep_resumes_after_a_kill_during_evaluation(workspace, monkeypatch):
    import s3k.experiments.runner as runner

    real = runner.evaluate_run

    def killed(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(runner, "evaluate_run", killed)
    with pytest.raises(KeyboardInterrupt):
        ex.run_experiment(toy_options("alpha", workspace), log=lambda m: None)
    first = ex.plan(toy_options("alpha", workspace))[0]
    run_dir = workspace / "alpha" / "runs" / first.name
    assert (run_dir / "model.pt").is_file() and not (run_dir / "result.json").exists()
    with file_lock(run_dir / LOCK_FILE, blocking=False) as free:
        assert free  # the interrupted process left no claim behind
    trained_at = (run_dir / "model.pt").stat().st_mtime_ns
    monkeypatch.setattr(runner, "evaluate_run", real)
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
    pool = next((workspace / "data").glob("category-i2-*"))
    view = next((workspace / "data" / "views" / pool.name).glob("L*"))
    assert (view / "images").is_symlink()
    ds, full = Dataset.open(view, cache="none"), Dataset.open(pool, cache="none")
    for split in ("labelled", "unlabelled", "test"):
        assert set(ds.frames(split)) <= set(full.frames(split))
    ids = ds.frames("test")
    np.testing.assert_array_equal(ds.images(ids), full.images(ids))


# ------------------------------------------------------------------------------------------------- two passes
def test_two_pass_plan_renders_larger_pools_and_refuses_stray_options(tmp_path):
    runs = ex.plan(ex.Options("label-efficiency", tmp_path, scale="full", labelled=[10], unlabelled=[0, 3000],
                              two_pass=True, coarse_steps=500, coarse_rotation=180.0))
    assert {r.pool.size for r in runs} == {4 * 96}  # crops are cut from renders of about the paper's size
    assert all(r.two_pass == {"coarse_size": 96, "coarse_steps": 500, "coarse_rotation": 180.0,
                              "crop_size": 128} for r in runs)
    one = ex.plan(ex.Options("label-efficiency", tmp_path, scale="full", labelled=[10], unlabelled=[0, 3000]))
    assert all(r.two_pass is None for r in one)
    # the estimate counts both passes: a short coarse pass costs less than a whole one
    whole = ex.plan(ex.Options("label-efficiency", tmp_path, scale="full", labelled=[10], unlabelled=[3000],
                               two_pass=True, render=200))
    assert {r.pool.size for r in whole} == {200}
    assert runs[-1].estimated_cpu_s() < whole[-1].estimated_cpu_s()
    with pytest.raises(UserError, match="--render.*apply only to two-pass"):
        ex.plan(ex.Options("label-efficiency", tmp_path, render=384))
    with pytest.raises(UserError, match="image_size does not apply to two-pass"):
        ex.plan(ex.Options("label-efficiency", tmp_path, two_pass=True, train_overrides={"image_size": "64"}))


def test_two_pass_sweep_records_its_passes_and_crop_pixels(tmp_path, capsys):
    argv = ["experiment", "label-efficiency", "--out", str(tmp_path), "--scale", "toy", "--no-progress",
            "--threads", "1", "--workers", "1", "--two-pass", "--render", "64", "--coarse-rotation", "90"]
    assert cli_main(argv) == 0
    runs = ex.plan(toy_options("label-efficiency", tmp_path, two_pass=True, render=64, coarse_rotation=90.0))
    sizes = []
    for r in runs:
        run_dir = tmp_path / "label-efficiency" / "runs" / r.name
        result = json.loads((run_dir / "result.json").read_text())
        assert result["two_pass"] == {"coarse_size": 32, "coarse_steps": 2, "coarse_rotation": 90.0,
                                      "crop_size": 32}
        coarse = json.loads((run_dir / "coarse" / "config.json").read_text())["config"]
        assert coarse["rotation_deg"] == 90.0 and coarse["image_size"] == 32
        assert (run_dir / "fine" / "model.pt").is_file() and result["image_size"] == [32, 32]
        assert result["metrics"]["test"]["two_pass"]["size"] == 32
        sizes.append(result["metrics"]["test"]["mm_per_px"])
    summary = json.loads((tmp_path / "label-efficiency" / "summary.json").read_text())
    # pixel errors are crop pixels: they become millimetres with the crops' pixel size, not the scene's
    assert summary["mm_per_px"] == {"32": pytest.approx(float(np.mean(sizes)))}
    assert summary["mm_per_px"]["32"] != pytest.approx(scene_mm_per_px("box", 32))
    assert summary["two_pass"] == [json.loads(json.dumps(runs[0].two_pass))]
    assert "Two passes" in (tmp_path / "label-efficiency" / "README.md").read_text()
    capsys.readouterr()
    # the same folder does not take one-pass runs
    assert cli_main(argv[:9]) == 1
    assert "finished with two passes" in capsys.readouterr().err


# ------------------------------------------------------------------------------------ labelled frames by pose
def test_coverage_choice_picks_each_next_frame_farthest_from_the_picked_poses(tmp_path):
    from s3k.experiments.views import pose_pick
    from s3k.label.suggest import UP, pose_distances

    pool = Dataset.open(make_dataset(tmp_path / "pool", labelled=12, unlabelled=5, test=2), cache="none")
    ids = pool.frames("labelled")
    X, ok = pool.points3d(ids)
    poses = {int(f): np.where(m[:, None], x, np.nan) for f, x, m in zip(ids, X, ok, strict=True)}
    frames = select_frames(pool, 4, 2, seed=3, choice="coverage")
    picked = frames["labelled"]
    assert len(picked) == 4 and set(picked) <= set(ids.tolist())
    assert frames["unlabelled"].tolist() == select_frames(pool, 4, 2, seed=3)["unlabelled"].tolist()
    # the picks of a smaller count are among those of a larger one (same seed): labelled sets nest
    small = pose_pick(pool, ids, 2, np.random.default_rng([0, 3, 1]))
    assert set(small) <= set(picked)
    # greedy farthest-first: every pick is at least as far from the earlier picks as any frame left over
    # ends up from all picks, so no two picked poses are closer than the farthest frame left out
    chosen = picked.tolist()
    left = [min(pose_distances(poses[f][None], poses[g], UP)[0] for g in chosen) for f in ids.tolist()
            if f not in chosen]
    apart = [pose_distances(poses[f][None], poses[g], UP)[0] for f in chosen for g in chosen if f < g]
    assert min(apart) >= max(left) - 1e-12
    with pytest.raises(ValueError, match="label choice"):
        select_frames(pool, 4, 2, seed=3, choice="nope")
    with pytest.raises(ValueError, match="not a pose order"):
        pose_pick(pool, ids, 2, np.random.default_rng(0), "random")


def test_representative_choice_nests_and_starts_from_the_seeds_frame(tmp_path):
    from s3k.experiments.views import pose_pick

    pool = Dataset.open(make_dataset(tmp_path / "pool", labelled=12, unlabelled=5, test=2), cache="none")
    ids = pool.frames("labelled")
    picked = select_frames(pool, 4, 2, seed=3, choice="representative")["labelled"]
    assert len(picked) == 4 and set(picked) <= set(ids.tolist())
    small = pose_pick(pool, ids, 2, np.random.default_rng([0, 3, 1]), "representative")
    first = ids[np.random.default_rng([0, 3, 1]).integers(len(ids))]
    assert first in small and set(small) <= set(picked)


def test_plan_and_runs_keep_the_label_choice(tmp_path):
    runs = ex.plan(toy_options("label-efficiency", tmp_path, label_choice="coverage"))
    assert all(r.label_choice == "coverage" and r.params["labels"] == "coverage" for r in runs)
    assert "labels" not in ex.plan(toy_options("label-efficiency", tmp_path))[0].params
    with pytest.raises(UserError, match="--label-choice"):
        ex.plan(toy_options("label-efficiency", tmp_path, label_choice="nope"))
    # a finished run whose frames were chosen otherwise is refused, not mixed in
    spec = ex.plan(toy_options("label-efficiency", tmp_path))[0]
    run_dir = tmp_path / "label-efficiency" / "runs" / spec.name
    run_dir.mkdir(parents=True)
    (run_dir / "result.json").write_text(json.dumps({"config": spec.cfg.to_dict(), "two_pass": None,
                                                     "data": {"label_choice": "random"}}))
    coverage = ex.plan(toy_options("label-efficiency", tmp_path, label_choice="coverage"))[0]
    with pytest.raises(UserError, match="chosen by random, one pass and labelled frames chosen by coverage"):
        run_one(coverage, tmp_path / "label-efficiency", tmp_path / "data", toy_options("label-efficiency",
                                                                                          tmp_path))
