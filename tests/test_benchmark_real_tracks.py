"""benchmarks/real_tracks.py reuses a track of the run's present weights on a rerun, and tracks again when the
run changed since, when the track is of another run, or when --retrack asks."""

from __future__ import annotations

import json
import os
from pathlib import Path

from benchmarks import real_tracks


def made(path: Path, text: str = "x", when: float | None = None) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    if when is not None:
        os.utime(path, (when, when))
    return path


def test_a_track_is_reused_only_while_it_is_of_the_runs_present_weights(tmp_path, monkeypatch):
    run, other = tmp_path / "run", tmp_path / "other"
    made(run / "fine" / "model.pt", when=1000.0)
    made(other / "model.pt", when=1000.0)
    out = tmp_path / "work" / "tracked.csv"
    record = out.with_name("tracked.csv.s3k.json")
    calls: list[list[str]] = []

    def fake_main(args):
        calls.append(args)
        made(out, "frame\n", when=2000.0 + len(calls))
        made(record, json.dumps({"run": str(Path(args[1]))}))
        return 0

    monkeypatch.setattr("s3k.cli.main", fake_main)

    def again(**kw):
        real_tracks.track(run, {"back": Path("b.mp4")}, Path("c.toml"), out, [], **kw)

    assert not real_tracks.tracked_already(run, out)
    again()
    assert len(calls) == 1 and real_tracks.tracked_already(run, out)
    again()  # the same weights: reused
    assert len(calls) == 1
    again(again=True)  # --retrack
    assert len(calls) == 2
    made(run / "fine" / "model.pt", when=5000.0)  # trained on since the track
    assert not real_tracks.tracked_already(run, out)
    again()
    assert len(calls) == 3
    assert not real_tracks.tracked_already(other, out)  # a track of another run is not this run's
    record.write_text("not json")
    assert not real_tracks.tracked_already(run, out)
