"""s3k track --frame-offsets: a camera whose clock runs behind is paired with the others' frames it shows."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers.track_rig import CAMERAS, read_track_csv

from s3k import cli
from s3k.data.video import synchronized_frames


def _sequences(track_recording, root: Path, late: dict[str, int]) -> dict[str, Path]:
    """Each camera's video as a PNG folder (lossless), ``late[camera]`` first frames left out: that camera's
    frame i then shows the others' frame i + N."""
    frames = list(synchronized_frames([track_recording["videos"][c] for c in CAMERAS]))
    out = {}
    for c, name in enumerate(CAMERAS):
        folder = root / name
        folder.mkdir(parents=True)
        for j, (_, views) in enumerate(frames[late.get(name, 0):]):
            cv2.imwrite(str(folder / f"{j:04d}.png"), cv2.cvtColor(views[c], cv2.COLOR_RGB2BGR))
        out[name] = folder
    return out


def _track(recording, videos: dict[str, Path], out: Path, *extra: str) -> int:
    return cli.main(["track", str(recording["run"]), "--calibration", str(recording["calibration"]),
                     "--out", str(out), "--no-progress", "--filter", "none", "--min-weight", "0",
                     "--videos", *[f"{c}={p}" for c, p in videos.items()], *extra])


def test_a_late_camera_is_paired_with_the_instants_it_shows(track_recording, tmp_path):
    synced = _sequences(track_recording, tmp_path / "synced", {})
    late = _sequences(track_recording, tmp_path / "late", {"top": 2})
    assert _track(track_recording, synced, tmp_path / "synced.csv") == 0
    assert _track(track_recording, late, tmp_path / "late.csv", "--frame-offsets", "top=2") == 0
    header, ref = read_track_csv(tmp_path / "synced.csv")
    _, got = read_track_csv(tmp_path / "late.csv")
    fnum = header.index("fnum")
    assert got[:, fnum].tolist() == ref[2:, fnum].tolist() == [2, 3, 4, 5]  # the instants every camera filmed
    np.testing.assert_array_equal(got, ref[2:])
    record = json.loads((tmp_path / "late.csv.s3k.json").read_text())
    assert record["frame_offsets"] == {"left": 0, "top": 2, "right": 0}
    # without the offset the same videos pair top's frames with the wrong instants
    assert _track(track_recording, late, tmp_path / "unpaired.csv") == 0
    _, wrong = read_track_csv(tmp_path / "unpaired.csv")
    assert not np.array_equal(wrong[:4, :fnum], ref[2:, :fnum])


def test_add_frames_refuses_a_track_made_with_offsets(track_recording, tmp_path, capsys):
    late = _sequences(track_recording, tmp_path / "late", {"top": 1})
    assert _track(track_recording, late, tmp_path / "late.csv", "--frame-offsets", "top=1") == 0
    capsys.readouterr()
    assert cli.main(["add-frames", str(tmp_path / "late.csv"), "--data", str(tmp_path / "none"),
                     "--worst", "1"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--frame-offsets" in err


@pytest.mark.parametrize("given, why", [(["cam9=1"], "unknown camera 'cam9'"),
                                        (["top=x"], "expected CAMERA=N"),
                                        (["top=4", "left=-4"], "no instant is filmed by every camera")])
def test_offsets_that_cannot_apply_are_refused_in_one_line(track_recording, tmp_path, capsys, given, why):
    videos = track_recording["videos"]
    assert _track(track_recording, videos, tmp_path / "x.csv", "--frame-offsets", *given) != 0
    errors = [line for line in capsys.readouterr().err.splitlines() if "error:" in line]
    assert len(errors) == 1 and why in errors[0]
    assert not (tmp_path / "x.csv").exists()
