"""The label curve (s3k.experiments.label_curve, behind benchmarks/label_curve.py): each seed's pool rendered
once and nested views of it, one resumable job per (labels, model, seed), and a summary and figure made from
the jobs' result files only."""

from __future__ import annotations

import json

import pytest

from s3k.cli import showing_library_messages
from s3k.experiments.label_curve import (
    CurveOptions,
    Job,
    curve_summary,
    jobs,
    pending_trainings,
    prepare_data,
    read_results,
    run_curve,
    unfinished,
    view_name,
)

TINY_TRAIN = "--channels 8,8 --res_blocks 1 --val_every 0 --warmup_steps 1 --ramp_steps 1"
MACHINE = {"cpu": "test", "cpu_flags": ["avx2", "fma", "avx512_bf16"]}


def tiny_options(**over) -> CurveOptions:
    given = dict(labels=(2, 4), seeds=1, render=64, unlabelled=4, test=3, label_pool=4, steps=2,
                 coarse_steps=2, coarse_size=32, crop_size=32, train_options=TINY_TRAIN, parallel=1,
                 reference=2)
    given.update(over)
    return CurveOptions.from_preset("box-headline", **given)


def test_the_curve_end_to_end_on_a_tiny_box(tmp_path, capsys):
    from s3k.data import Dataset
    from s3k.experiments.views import select_frames

    opts = tiny_options()
    assert opts.preset == "box-headline" and opts.passes == 2
    work, results = tmp_path / "work", tmp_path / "results"
    with showing_library_messages():  # its progress notes, as the command line shows them
        summary = run_curve(opts, work, results, "python benchmarks/label_curve.py ...", "abc", MACHINE)
    err = capsys.readouterr().err
    assert err.count("training ") == 4 and err.count("result ") == 4

    # the pool rendered once; each count's labelled frames chosen from it the headline's way, nested
    assert sorted(p.name for p in work.iterdir() if p.name.startswith("box64-L4-seed")) == ["box64-L4-seed0"]
    pool = Dataset.open(work / "box64-L4-seed0", cache="none")
    picked = {}
    for n in (2, 4):
        view = Dataset.open(work / view_name(opts, n, 0), cache="none")
        picked[n] = set(view.frames("labelled").tolist())
        chosen = select_frames(pool, n, 4, seed=0, choice="representative")["labelled"]
        assert sorted(picked[n]) == chosen.tolist()
        assert view.frames("test").tolist() == pool.frames("test").tolist()
    assert picked[2] < picked[4]

    # one result per job, and the summary holds exactly their figures
    found, missing = read_results(opts, work)
    assert missing == [] and set(found) == set(jobs(opts)) and len(found) == 4
    for job, r in found.items():
        entry = summary["curve"][job.model][str(job.labels)]
        assert entry["median_mm"]["per_seed"] == [r["median_mm"]]
        assert entry["rms_mm"]["per_seed"] == [r["rms_mm"]]
        assert entry["pck_10mm"]["per_seed"] == [r["pck_10mm"]] and r["train_cpu_minutes"] > 0
        assert r["trained_at_revisions"] == ["abc"]
    on_disk = json.loads((results / "summary.json").read_text())
    assert on_disk["command"].startswith("python benchmarks/label_curve.py")
    assert on_disk["git_revision"] == "abc"
    assert on_disk["trained_at_revisions"] == ["abc"] and on_disk["avx512_bf16"] is True
    assert on_disk["machine"]["cpu_flags"] == MACHINE["cpu_flags"]
    figure = results / "label-curve.png"
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    # the same call again trains and evaluates nothing
    stamps = {p: p.stat().st_mtime_ns for p in work.rglob("*") if p.is_file() and p.suffix in (".pt", ".json")
              and "L" in p.parent.name}
    run_curve(opts, work, results, "again", "abc", MACHINE)
    err = capsys.readouterr().err
    assert "training " not in err and "result " not in err
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps

    # the summary and figure come from the result files: changed results, a changed summary and answer
    s3k_at_2 = found[Job(2, "s3k", 0)]["median_mm"]
    for n, median in ((2, s3k_at_2 + 1.0), (4, s3k_at_2 - 1.0)):
        path = Job(n, "labels_only", 0).result(work)
        path.write_text(json.dumps({**json.loads(path.read_text()), "median_mm": median}))
    figure.unlink()
    summary = run_curve(opts, work, results, "again", "abc", MACHINE, summary_only=True)
    assert summary["curve"]["labels_only"]["4"]["median_mm"]["per_seed"] == [s3k_at_2 - 1.0]
    assert summary["labels_only_to_match_s3k"]["median_mm"]["labels_only_labels"] == 4
    assert "labels only reaches it with 4 labels" in summary["answer"] and figure.is_file()

    # a finished run without a result (its seed still training on): the summary evaluates it, trains nothing
    done = Job(2, "s3k", 0)
    done.result(work).unlink()
    summary = run_curve(opts, work, results, "again", "abc", MACHINE, summary_only=True)
    assert json.loads(done.result(work).read_text())["median_mm"] == s3k_at_2
    assert summary["curve"]["s3k"]["2"]["median_mm"]["per_seed"] == [s3k_at_2]
    assert "training " not in capsys.readouterr().err

    # a job killed in training resumes: it alone is planned again, with --resume
    killed = Job(4, "s3k", 0)
    killed.result(work).unlink()
    (killed.run(work) / "two_pass.json").unlink()
    planned = pending_trainings(opts, work, prepare_data(opts, work), "def")
    assert [name for name, _, _ in planned] == [killed.name] and killed.trained_at(work) == ["abc", "def"]
    assert planned[0][1][-1] == "--resume" and str(killed.run(work)) in planned[0][1]


def test_a_curve_goes_seed_by_seed(tmp_path):
    opts = tiny_options(seeds=2, labels=(2,))
    work = tmp_path / "work"
    data = prepare_data(opts, work, [1])  # the second seed alone: its pool, none of the first's
    assert set(data) == {(2, 1)}
    assert sorted(p.name for p in work.iterdir() if p.name.startswith("box64-L")) == sorted([
        "box64-L4-seed1", view_name(opts, 2, 1)])
    planned = pending_trainings(opts, work, data, "abc")
    assert [name for name, _, _ in planned] == [Job(2, m, 1).name for m in ("s3k", "labels_only")]


def _result(job: Job, median: float, rms: float, pck: float) -> dict:
    return {"median_mm": median, "rms_mm": rms, "pck_10mm": pck, "train_cpu_minutes": 1.0}


def test_the_summary_finds_the_labels_labels_only_needs():
    opts = CurveOptions(labels=(5, 10, 20, 50), seeds=2, label_pool=50)
    s3k = {5: (3.0, 6.0), 10: (2.8, 4.0), 20: (2.6, 3.8), 50: (2.5, 3.5)}
    lo = {5: (4.0, 60.0), 10: (3.4, 40.0), 20: (2.9, 20.0), 50: (2.7, 9.0)}
    results = {}
    for s, shift in ((0, -0.1), (1, 0.1)):
        for n in opts.labels:
            results[Job(n, "s3k", s)] = _result(Job(n, "s3k", s), s3k[n][0] + shift, s3k[n][1], 0.98)
            results[Job(n, "labels_only", s)] = _result(Job(n, "labels_only", s), lo[n][0] + shift, lo[n][1],
                                                        0.97 if n < 50 else 0.99)
    out = curve_summary(opts, results)
    median = out["curve"]["s3k"]["10"]["median_mm"]
    assert median["mean"] == pytest.approx(2.8) and median["per_seed"] == pytest.approx([2.7, 2.9])
    assert median["min"] == pytest.approx(2.7) and median["sd"] == pytest.approx(0.1414, abs=1e-3)
    assert out["curve"]["labels_only"]["5"]["seeds"] == [0, 1]
    match = out["labels_only_to_match_s3k"]
    assert match["median_mm"]["labels_only_labels"] == 50  # 2.7 <= 2.8; 2.9 at 20 is not
    assert match["rms_mm"]["labels_only_labels"] is None  # 9 mm at 50 labels against 4
    assert match["pck_10mm"]["labels_only_labels"] == 50  # higher is better
    # a job without a result leaves its seed out, not the count
    del results[Job(20, "labels_only", 1)]
    assert curve_summary(opts, results)["curve"]["labels_only"]["20"]["seeds"] == [0]


def test_label_counts_beyond_the_pool_are_refused():
    with pytest.raises(ValueError, match="pool of 50"):
        CurveOptions(labels=(5, 100), label_pool=50)
    opts = CurveOptions(labels=(10, 5, 10))
    assert opts.labels == (5, 10) and view_name(opts, 5, 2) == "box384-L100-representative-n5-seed2"


def test_the_summary_names_the_steps_and_minutes_of_a_training_begun(tmp_path):
    opts = CurveOptions(labels=(10,), seeds=1)
    begun, waiting = Job(10, "s3k", 0), Job(10, "labels_only", 0)
    (begun.run(tmp_path) / "coarse").mkdir(parents=True)
    (begun.run(tmp_path) / "coarse" / "progress.json").write_text('{"step": 975, "steps": 4000}')
    begun.record(tmp_path).write_text(json.dumps({"cpu_minutes": 1.0, "wall_minutes": 2.0,
                                                  "unfinished_cpu_minutes": 2.5,
                                                  "unfinished_wall_minutes": 4.0}))
    assert unfinished(opts, tmp_path, [begun, waiting]) == [
        {"job": "s3k 10 labels seed 0", "steps": {"coarse": [975, 4000]}, "cpu_minutes": 3.5,
         "wall_minutes": 6.0}]


def test_another_configurations_curve_goes_beside_and_stays(tmp_path):
    from s3k.base.errors import UserError
    from s3k.experiments.label_curve import add_curve, plotted_counts

    def point(median):
        stats = {"mean": median, "sd": 0.0, "min": median, "max": median, "per_seed": [median]}
        return {"seeds": [0], "median_mm": stats, "rms_mm": stats, "pck_10mm": stats}

    opts = tiny_options(labels=(2,))
    work, results = tmp_path / "work", tmp_path / "results"
    with pytest.raises(UserError, match="no label-curve summary"):
        add_curve(results, "other", [tmp_path / "x.json"], "cmd")
    own = run_curve(opts, work, results, "python benchmarks/label_curve.py ...", "abc", MACHINE)
    assert own["train_options"] == opts.train_options == TINY_TRAIN
    figure = results / "label-curve.png"
    alone = figure.read_bytes()
    not_a_summary = tmp_path / "not.json"
    not_a_summary.write_text('{"median_mm": 1}')
    with pytest.raises(UserError, match="not a label-curve summary"):
        add_curve(results, "other", [not_a_summary], "cmd")

    other, more = tmp_path / "other.json", tmp_path / "more.json"
    theirs = {"command": "their command", "git_revision": "def", "scale": "their scale", "seeds": [0],
              "curve": {"s3k": {"2": point(7.5)}, "labels_only": {}}}
    other.write_text(json.dumps(theirs))
    more.write_text(json.dumps({**theirs, "git_revision": "fed", "train_options": "--encoder-lr 0.1",
                                "curve": {"s3k": {"1": point(9.0)}, "labels_only": {"1": point(20.0)}}}))
    summary = add_curve(results, "encoder", [other, more], "the adding command")
    added = summary["added_curves"]["encoder"]
    assert added["curve"] == {"s3k": {"1": point(9.0), "2": point(7.5)}, "labels_only": {"1": point(20.0)}}
    assert [(s["from"], s["git_revision"], s["counts"]) for s in added["sources"]] == [
        (str(other), "def", [2]), (str(more), "fed", [1])]
    assert [s["train_options"] for s in added["sources"]] == ["", "--encoder-lr 0.1"]
    assert added["added_by"] == "the adding command"
    assert json.loads((results / "summary.json").read_text())["added_curves"] == summary["added_curves"]
    with pytest.raises(UserError, match=r"S3K at 2 labels is in .*other.json too"):
        add_curve(results, "encoder", [other, other], "cmd")
    assert figure.read_bytes() != alone  # drawn in the same figure
    assert plotted_counts(summary) == [1, 2]  # its count 1 marked on the axis beside this curve's 2

    # this curve's own summary written again keeps the added one, and its own figures are its own
    again = run_curve(opts, work, results, "again", "abc", MACHINE, summary_only=True)
    assert again["added_curves"]["encoder"]["curve"]["s3k"]["2"]["median_mm"]["mean"] == 7.5
    assert again["curve"]["s3k"]["2"]["median_mm"]["mean"] != 7.5


def test_a_curves_train_options_come_from_its_field_or_an_older_summarys_scale():
    from s3k.experiments.label_curve import train_options_of

    options = "--encoder efficientnet-lite0 --encoder-lr 0.1"
    scale = "box rendered at 384 px; two passes"
    assert train_options_of({"scale": scale, "train_options": options}) == options
    # a summary written before the field names its options at the end of its scale
    assert train_options_of({"scale": f"{scale}; train options {options!r}"}) == options
    assert train_options_of({"scale": scale}) == ""
    assert train_options_of({"scale": f"{scale}; train options {options!r}", "train_options": ""}) == ""
