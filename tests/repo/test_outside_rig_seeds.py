"""benchmarks/outside_rig_seeds.py: two models' outside_rig.py results over seeds, side by side."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from helpers.paths import REPO as ROOT


def result(tmp_path, name: str, mm: dict[str, float], px: dict[str, float],
           scale: str = "box, seed 1000") -> str:
    path = tmp_path / f"{name}.json"
    path.write_text(json.dumps({"run": f"runs/{name}", "scale": scale, "rigs": {
        rig: {"median_mm": mm[rig], "rms_mm": 2 * mm[rig], "diagnosis": {"fine_2d_median_px": px[rig]}}
        for rig in mm}}))
    return str(path)


def run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "benchmarks/outside_rig_seeds.py", *args], cwd=ROOT,
                          capture_output=True, text=True)


def test_two_models_over_seeds_give_ratios_and_differences_seed_by_seed(tmp_path):
    a0 = result(tmp_path, "a0", {"train": 2.0, "low": 4.0}, {"train": 1.0, "low": 3.0})
    a1 = result(tmp_path, "a1", {"train": 4.0, "low": 4.0}, {"train": 2.0, "low": 2.0})
    b0 = result(tmp_path, "b0", {"train": 1.0, "low": 5.0}, {"train": 1.0, "low": 4.0})
    b1 = result(tmp_path, "b1", {"train": 3.0, "low": 3.0}, {"train": 1.0, "low": 1.0})
    out = tmp_path / "out.json"
    proc = run(f"enc={a0},{a1}", f"scr={b0},{b1}", "--out", str(out), "--notes", "here")
    assert proc.returncode == 0, proc.stderr[-2000:]
    got = json.loads(out.read_text())
    low = got["models"]["enc"]["rigs"]["low"]
    assert low["median_ratio"]["per_seed"] == [2.0, 1.0] and low["median_ratio"]["mean"] == 1.5
    assert low["fine_2d_ratio"]["per_seed"] == [3.0, 1.0]
    assert "median_ratio" not in got["models"]["scr"]["rigs"]["train"]
    diff = got["first_minus_second"]
    assert (diff["first"], diff["second"]) == ("enc", "scr")
    assert diff["rigs"]["low"]["median_mm_diff"]["per_seed"] == [-1.0, 1.0]
    assert diff["rigs"]["low"]["seeds_first_lower_3d"] == 1
    assert diff["rigs"]["train"]["seeds_first_lower_3d"] == 0
    assert diff["rigs"]["low"]["fine_2d_px_diff"]["per_seed"] == [-1.0, 1.0]
    assert got["seeds"] == 2 and got["notes"] == "here" and "cpu_flags" in got["machine"]


@pytest.mark.parametrize("second, says", [
    ("scr={b0}", "enc has 2 seeds and scr 1"),
    ("scr={b0},{other}", "read other test sets"),
    ("scr={b0},{missing}", "not an outside_rig.py --diagnose result"),
    ("{b0}", "expected NAME=FILE"),
])
def test_files_that_do_not_pair_up_are_refused_in_one_line(tmp_path, second, says):
    rigs = {"train": 2.0, "low": 4.0}
    a0, a1, b0 = (result(tmp_path, n, rigs, rigs) for n in ("a0", "a1", "b0"))
    other = result(tmp_path, "other", rigs, rigs, scale="box, seed 7")
    proc = run(f"enc={a0},{a1}", second.format(b0=b0, other=other, missing=tmp_path / "none.json"))
    assert proc.returncode == 2 and says in proc.stderr
    assert proc.stderr.strip().splitlines()[-1].startswith("outside_rig_seeds.py: error:")
