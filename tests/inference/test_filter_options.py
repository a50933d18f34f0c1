"""The filter options of ``s3k track`` and ``s3k stream``: a value whose squares overflow, or underflow to
zero, is refused as the command line is parsed, before a frame is read; ``--filter-rigid on`` with a run that
has no rigid layout is refused in one line rather than left unapplied."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers.tiny_detector import save_run
from helpers.track_rig import CAMERAS, FRAMES, KEYPOINTS, NET_SIZE, moving_points, run_track

from s3k import cli
from s3k.base.errors import UserError
from s3k.detector import DetectorMeta
from s3k.inference.kalman import RANGES, FilterSettings
from s3k.inference.track_filter import StreamFilter
from s3k.model import UNetConfig

BAD = [("--filter-gate", "1e308"), ("--filter-gate", "1e200"), ("--filter-gate", "101"),
       ("--filter-process-noise", "1e308"), ("--filter-process-noise", "1e-300"),
       ("--filter-noise-scale", "1e200"), ("--filter-noise-scale", "1e-300"), ("--filter-noise-px", "1e308"),
       ("--filter-layout-std", "1e308"), ("--filter-layout-std", "1e-200"), ("--filter-limb-std", "1e308"),
       ("--filter-limb-std", "1e-200")]


@pytest.mark.parametrize("option, value", BAD)
def test_track_refuses_a_filter_value_out_of_range_before_any_work(track_recording, tmp_path, capsys,
                                                                   option, value):
    out = tmp_path / "points3d.csv"
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_:
        run_track(track_recording, out, option, value)
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and option in err and "must be in" in err, err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("option, value", BAD[::3])
def test_stream_refuses_the_same_values(tmp_path, capsys, option, value):
    with pytest.raises(SystemExit) as exit_:
        cli.main(["stream", str(tmp_path / "run"), "--calibration", "c.toml", "--sources", "a=0", "b=1",
                  "--filter", "kalman", option, value])
    assert exit_.value.code == 2
    assert option in capsys.readouterr().err


@pytest.mark.parametrize("name", [n for n in RANGES if n != "max_gap"])
def test_the_filter_settings_hold_the_same_ranges(name):
    with pytest.raises(UserError, match=f"--filter-{name.replace('_', '-')}"):
        FilterSettings(**{name: 1e308}).check()
    FilterSettings(**{name: RANGES[name].le}).check()


def test_track_refuses_rigid_on_with_a_run_without_a_layout(track_recording, tmp_path, capsys):
    out = tmp_path / "points3d.csv"
    capsys.readouterr()
    assert run_track(track_recording, out, "--filter-rigid", "on") == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--filter-rigid on" in err, err
    assert str(track_recording["run"]) in err, err
    assert "--layout-tol" in err and "--filter-rigid auto or off" in err
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(UserError, match="--filter-rigid on"):
        StreamFilter(FilterSettings(rigid=True), len(KEYPOINTS), {}, shape=None)


def test_track_holds_the_points_to_a_runs_layout_with_rigid_on(track_recording, tmp_path):
    """The same call with a run that has a rigid layout (the points' own distances) is taken and applied."""
    X = moving_points(FRAMES)[0]
    distances = np.linalg.norm(X[:, None] - X[None], axis=-1)
    meta = DetectorMeta(keypoints=list(KEYPOINTS), cameras=list(CAMERAS), image_size=NET_SIZE, stride=2,
                        sigma=2.0, model=UNetConfig(channels=(8, 8), res_blocks=1, stride=2).to_dict(),
                        units="mm", source_image_size=NET_SIZE, layout=distances.tolist(), layout_tol=0.2)
    run = save_run(tmp_path / "rigid-run", meta, seed=0)
    out = tmp_path / "points3d.csv"
    argv = ["track", str(run), "--calibration", str(track_recording["calibration"]), "--out", str(out),
            "--no-progress", "--min-weight", "0", "--filter-rigid", "on",
            "--videos", *[f"{c}={track_recording['videos'][c]}" for c in CAMERAS]]
    assert cli.main(argv) == 0
    record = json.loads((tmp_path / "points3d.csv.s3k.json").read_text())
    assert record["filter"]["settings"]["rigid"] is True and "layout_std" in record["filter"]
