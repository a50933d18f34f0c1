"""benchmarks/sessions.py on a tiny box: the rendered sessions, dataset A (three sessions) and B (one, as many
labels and frames) each with the fourth held out, a few training steps, and a summary per session written
again from the runs' results; then the held-out sessions on new rigs added to those datasets in place
(nothing retrained), the paired A - B differences, and B adapted to the moved session beside a control."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
from helpers.paths import REPO as ROOT

from s3k.data import Dataset


def bench(args: list[str]) -> int:
    """``python benchmarks/sessions.py ARGS`` from the repository root (tests do not import benchmarks/)."""
    proc = subprocess.run([sys.executable, "benchmarks/sessions.py", *args], cwd=ROOT, capture_output=True,
                          text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.returncode

TINY = ["--size", "64", "--fixed-rigs", "--labelled", "2,1,1", "--unlabelled", "3", "--test", "2",
        "--steps", "2", "--coarse-steps", "2", "--train-options",
        "--coarse-size 32 --crop-size 32 --channels 8,8 --res-blocks 1 --val-every 0 --warmup-steps 1 "
        "--ramp-steps 1"]


def split_counts(ds: Dataset) -> dict[tuple[str, str], int]:
    ids = ds.frames()
    pairs = zip(ds.session_of(ids).tolist(), ds.split_of(ids).tolist())
    out: dict[tuple[str, str], int] = {}
    for pair in pairs:
        out[pair] = out.get(pair, 0) + 1
    return out


def test_the_benchmark_end_to_end_on_a_tiny_box(tmp_path, capsys):
    work, results = tmp_path / "work", tmp_path / "results"
    args = [*TINY, "--work", str(work), "--results", str(results)]
    old = [*args, "--new-rigs", ""]  # as the benchmark was before the new-rig sessions: s4 held out alone
    assert bench(["--summary-only", *old]) == 0  # nothing trained yet: every run missing
    assert json.loads((results / "summary.json").read_text())["missing_runs"] == ["A-seed0", "B-seed0"]

    assert bench(old) == 0
    a, b = Dataset.open(work / "A"), Dataset.open(work / "B")
    assert a.sessions == ["s1", "s2", "s3", "s4"] and b.sessions == ["s1", "s4"]
    assert split_counts(a) == {("s1", "labelled"): 2, ("s2", "labelled"): 1, ("s3", "labelled"): 1,
                               ("s1", "unlabelled"): 3, ("s2", "unlabelled"): 3, ("s3", "unlabelled"): 3,
                               ("s1", "test"): 2, ("s2", "test"): 2, ("s3", "test"): 2, ("s4", "test"): 2}
    # B: s1 alone with A's labels and frames in all; the held-out session's test frames, as in A
    assert split_counts(b) == {("s1", "labelled"): 4, ("s1", "unlabelled"): 9, ("s1", "test"): 2,
                               ("s4", "test"): 2}
    # A's labels of s1 are among B's (the same frames of the same render, the labelling app's order)
    assert set(a.frames("labelled", session="s1")) < set(b.frames("labelled", session="s1"))
    held = a.frames("test", session="s4")
    assert np.array_equal(a.images(held[:1]), b.images(b.frames("test", session="s4")[:1]))
    # --fixed-rigs: every session's frames share its cameras, and the sessions' rigs differ
    centres = {s: np.asarray(a.calibration(a.frames(session=s)).centres()) for s in a.sessions}
    assert all(np.allclose(c, c[:1]) for c in centres.values())
    assert not np.allclose(centres["s1"][0], centres["s2"][0])

    summary = json.loads((results / "summary.json").read_text())
    assert summary["missing_runs"] == [] and set(summary["held_out"]) == {"A", "B"}
    for model in ("A", "B"):
        per_session = summary["per_seed"][model]["0"]["sessions"]
        assert set(per_session) == {"s1", "s2", "s3", "s4"}
        assert all(per_session[s]["n_frames"] == 2 for s in per_session)
        assert summary["held_out"][model] == {k: per_session["s4"][k] for k in ("median_mm", "rms_mm",
                                                                                  "pck_10mm")}
    assert summary["setup"]["sessions"] == {"A": {"s1": 2, "s2": 1, "s3": 1}, "B": {"s1": 4}}
    assert summary["setup"]["fixed_rigs"] is True
    assert summary["command"].startswith("python benchmarks/sessions.py --size 64")
    assert "cpu_flags" in summary["machine"]
    assert summary["held_out_new_rigs"] == {} and set(summary["paired"]["over_seeds"]) == {"s4"}

    # the same command again trains nothing and evaluates nothing: the runs' results are read back
    stamp = {p: p.stat().st_mtime_ns for p in (work / "runs").iterdir()}
    assert bench(["--summary-only", *old]) == 0
    assert {p: p.stat().st_mtime_ns for p in (work / "runs").iterdir()} == stamp
    assert json.loads((results / "summary.json").read_text())["held_out"] == summary["held_out"]

    # the default command: s5..s7 (rigs high, far, wide) rendered and added to A and B in place, the runs
    # evaluated again on them but not trained again; B fine-tuned on B+s3 and on B
    weights = {p: p.stat().st_mtime_ns for p in (work / "runs").rglob("*.pt")}
    assert weights
    assert bench([*args, "--adapt-steps", "2"]) == 0
    assert {p: p.stat().st_mtime_ns for p in weights} == weights
    a, b, adapt = Dataset.open(work / "A"), Dataset.open(work / "B"), Dataset.open(work / "B+s3")
    new = {"s5": "high", "s6": "far", "s7": "wide"}
    assert a.sessions == ["s1", "s2", "s3", "s4", *new] and b.sessions == ["s1", "s4", *new]
    for ds in (a, b):
        assert all(split_counts(ds)[(s, "test")] == 2 for s in new)
        assert {s for s, _ in split_counts(ds)} - {"s1", "s2", "s3"} == {"s4", *new}
        assert not any(s in new and split != "test" for s, split in split_counts(ds))
    # B+s3: B's s1 and s3's unlabelled frames (A's), no label and no test frame of s3
    assert split_counts(adapt) == {("s1", "labelled"): 4, ("s1", "unlabelled"): 9, ("s1", "test"): 2,
                                   ("s3", "unlabelled"): 3}
    # the cameras stand where the rigs say: s3 (low) lower, s5 (high) higher than the training rig's
    heights = {s: float(np.mean(np.asarray(a.calibration(a.frames(session=s)).centres())[..., 2]))
               for s in a.sessions}
    assert heights["s3"] < min(heights["s1"], heights["s2"], heights["s4"]) < heights["s5"]
    assert max(heights["s1"], heights["s2"], heights["s4"]) < heights["s5"]

    summary = json.loads((results / "summary.json").read_text())
    assert summary["missing_runs"] == []
    assert set(summary["per_seed"]["A"]["0"]["sessions"]) == {"s1", "s2", "s3", "s4", *new}
    assert {s: d["rig"] for s, d in summary["held_out_new_rigs"].items()} == new
    assert all(set(d) == {"rig", "A", "B"} for d in summary["held_out_new_rigs"].values())
    paired = summary["paired"]
    assert set(paired["per_seed"]["0"]) == {"s4", *new, "new_rigs"} and paired["pooled"]["new_rigs"] == [*new]
    for d in paired["per_seed"]["0"].values():
        assert np.isfinite(d["mean_diff_mm"]) and d["points"] > 0 and len(d["ci95_mm"]) == 2
    pooled = paired["per_seed"]["0"]["new_rigs"]["points"]
    assert pooled == sum(paired["per_seed"]["0"][s]["points"] for s in new)
    adaptation = summary["adaptation"]
    assert adaptation["steps"] == 2 and adaptation["adapted_to"] == "s3" and adaptation["seeds"] == [0]
    sessions = adaptation["per_seed"]["0"]
    assert list(sessions)[:2] == ["s3", "s1"] and {"s4", *new, "new_rigs"} <= set(sessions)
    for s in ("s3", "s1", "s5"):
        assert set(sessions[s]) == {"B", "adapted", "control", "adapted_minus_B", "adapted_minus_control"}
        assert sessions[s]["B"] == summary["mean_over_seeds"]["B"][s]
        assert np.isfinite(sessions[s]["adapted_minus_control"]["mean_diff_mm"])
    assert adaptation["over_seeds"]["s3"]["adapted_minus_B"]["mean_mm"] == \
        sessions["s3"]["adapted_minus_B"]["mean_diff_mm"]
    for kind in ("adapted2", "control2"):
        assert (work / "runs" / f"B-seed0-{kind}-test.npz").is_file()

    # and once more: nothing trained, nothing evaluated, nothing added
    stamp = {p: p.stat().st_mtime_ns for p in (work / "runs").iterdir()}
    assert bench(["--summary-only", *args, "--adapt-steps", "2"]) == 0
    assert {p: p.stat().st_mtime_ns for p in (work / "runs").iterdir()} == stamp
    again = json.loads((results / "summary.json").read_text())
    assert again["paired"] == summary["paired"] and again["adaptation"] == summary["adaptation"]


def test_draws_of_the_sessions_pool_each_draws_difference(tmp_path):
    """benchmarks/sessions_draws.py: per held-out session (by role: s4, or a new rig by its name) each draw's
    A - B, the mean of its training seeds; the mean over draws with a t-interval; how many draws A wins, the
    sign test's two-sided p, and how many draws (of one seed, with an interval over frames) A wins clearly."""

    def summary(name: str, seeds: list[int], per_seed: dict[str, dict[str, float]], rig_session: str) -> str:
        def entry(diff: float) -> dict:
            return {"mean_diff_mm": diff, "ci95_mm": [diff - 1, diff + 1], "median_mm": [2.0 + diff, 2.0],
                    "points": 30}
        path = tmp_path / name / "summary.json"
        path.parent.mkdir()
        path.write_text(json.dumps({
            "git_revision": "abc",
            "setup": {"session_seeds": dict(zip(["s1", "s2", "s3", "s4"], seeds)),
                      "new_rigs": {rig_session: {"rig": "low", "seed": seeds[0] + 4}}},
            "paired": {"per_seed": {seed: {s: entry(d) for s, d in diffs.items()}
                                    for seed, diffs in per_seed.items()}},
        }))
        return str(path)

    one = summary("d1", [10, 11, 12, 13], {"0": {"s4": 1.0, "s5": -3.0}, "1": {"s4": 0.0, "s5": -1.0}}, "s5")
    two = summary("d2", [20, 21, 22, 23], {"0": {"s4": -2.0, "s8": -4.0}}, "s8")  # the low rig named s8 here
    out = tmp_path / "pooled.json"
    proc = subprocess.run([sys.executable, "benchmarks/sessions_draws.py", one, two, "--out", str(out)],
                          cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    pooled = json.loads(out.read_text())["pooled"]
    assert set(pooled) == {"training rig (s4)", "rig low"}
    s4, low = pooled["training rig (s4)"], pooled["rig low"]
    assert s4["per_draw_mm"] == [0.5, -2.0] and s4["mean_diff_mm"] == -0.75 and s4["draws_A_lower"] == 1
    assert s4["ci95_mm_over_draws"][0] < -0.75 < s4["ci95_mm_over_draws"][1]
    assert low["per_draw_mm"] == [-2.0, -4.0] and low["draws_A_lower"] == 2
    assert s4["sign_test_p"] == 1.0 and low["sign_test_p"] == 0.5  # 1 of 2: no lean; 2 of 2: 2 in 4
    # d1 has two seeds (no interval over frames); d2's one seed is clear of zero on both sessions
    assert s4["draws_A_lower_clear_of_zero"] == 1 and low["draws_A_lower_clear_of_zero"] == 1
    assert s4["draws_B_lower_clear_of_zero"] == 0 and low["draws_B_lower_clear_of_zero"] == 0

    # the same draw twice is refused, in one line naming the option
    proc = subprocess.run([sys.executable, "benchmarks/sessions_draws.py", one, one], cwd=ROOT,
                          capture_output=True, text=True)
    assert proc.returncode == 2 and "--session-seeds" in proc.stderr
