"""Writes the run folders in this folder with the code of revision e7e42b1 (before the two-pass options
joined TrainConfig): a one-pass run ``one`` and a two-pass run ``two`` trained on
``synthetic_rig.make_dataset(DIR / "ds", size=48, labelled=4, unlabelled=4, test=2)``.

    git worktree add --detach /tmp/old e7e42b1 && cd /tmp/old
    PYTHONPATH=$PWD python /path/to/make_old_runs.py /tmp/old-runs
    (cd /tmp/old-runs && tar --exclude=tensorboard -cf - one two) | (cd tests/data/old_runs && tar xf -)

``tests/detector/test_old_runs.py`` loads, evaluates and resumes them with the code of today.
"""
import shutil
import sys
from pathlib import Path

sys.path.insert(0, "tests")
from synthetic_rig import make_dataset  # noqa: E402

from s3k import cli  # noqa: E402

root = Path(sys.argv[1])
if root.exists():
    shutil.rmtree(root)
root.mkdir(parents=True)
data = make_dataset(root / "ds", size=48, labelled=4, unlabelled=4, test=2)
common = ["--steps", "4", "--channels", "4,4", "--res_blocks", "0", "--val_every", "2", "--val_frames",
          "2", "--warmup_steps", "1", "--ramp_steps", "1", "--no-progress", "--threads", "1",
          "--batch-labelled", "2", "--batch-unlabelled", "2", "--checkpoint-every", "2"]
assert cli.main(["train", str(data), "--out", str(root / "one"), *common]) == 0
assert cli.main(["train", str(data), "--out", str(root / "two"), "--two-pass", "--coarse-size", "32",
                 "--crop-size", "32", "--coarse-steps", "3", "--coarse-rotation", "90", "--crop-margin",
                 "0.2", "--lr", "0.002", "--coarse-lr", "0.001", *common]) == 0
