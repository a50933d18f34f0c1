"""A dataset of two sessions whose cameras moved between them: every frame is read with its own session's
cameras, one model trains on both, and validate and evaluate report per session."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers.synthetic_rig import make_sessions_dataset, rig

from s3k.cli import main
from s3k.config import TrainConfig
from s3k.data import Dataset, usable_labels
from s3k.data.frames import FrameStore
from s3k.train import train


@pytest.fixture(scope="module")
def two_days(tmp_path_factory):
    root = tmp_path_factory.mktemp("days")
    data = make_sessions_dataset(root / "ds", {"day1": 0.0, "day2": 0.6}, labelled=3, unlabelled=4, test=3)
    cfg = TrainConfig.from_flat(steps=2, batch_labelled=2, batch_unlabelled=2, channels=(8, 16),
                                res_blocks=1, warmup_steps=0, val_every=0, progress=False, threads=1)
    train(data, root / "run", cfg)
    return data, root / "run"


def test_training_reads_each_frame_with_its_sessions_cameras(two_days):
    data, run = two_days
    ds = Dataset.open(data, cache="none")
    ids = ds.frames("labelled")
    assert usable_labels(ds).all()  # every label triangulates with its own session's rig
    batch = next(FrameStore(ds, ids, labels=True).batches(len(ids)))
    for b, frame in enumerate(batch.frame_ids):
        K, _, R, t = rig(32, 0.0 if ds.session_of([frame])[0] == "day1" else 0.6)
        np.testing.assert_allclose(batch.cams.R[b].double().numpy(), R, atol=1e-6)
        np.testing.assert_allclose(batch.cams.t[b].double().numpy(), t, atol=1e-6)
    log = (run / "train.log").read_text()
    assert "2 sessions, each frame with its own session's cameras: day1 (3 labelled, 4 unlabelled), day2 " \
           "(3 labelled, 4 unlabelled)" in log


def test_evaluate_and_validate_report_per_session(two_days, capsys):
    data, run = two_days
    assert main(["evaluate", str(run), "--data", str(data), "--json", "--device", "cpu"]) == 0
    m = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert set(m["sessions"]) == {"day1", "day2"}
    for name in ("day1", "day2"):
        part = m["sessions"][name]
        assert part["n_frames"] == 3 and part["rms_px"] is not None
        # test frames at times 7, 8, 9; the session's last labelled frame at time 2
        assert part["label_distance"] == {"median": 6.0, "min": 5.0}
    assert m["label_distance"] == {"median": 6.0, "min": 5.0}
    assert main(["evaluate", str(run), "--data", str(data), "--device", "cpu"]) == 0
    out = capsys.readouterr().out
    assert "session day1" in out and "session day2" in out
    assert "test frames lie median 6, min 5 frames from the nearest labelled frame of their session" in out
    assert main(["validate", str(data), "--no-images"]) == 0
    out = capsys.readouterr().out
    assert "2 sessions (frames per split; calibration per_session):" in out
    assert "  day2: labelled 3, unlabelled 4, test 3 (frame rate 30.0, subject dots-1)" in out
