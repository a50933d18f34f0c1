"""Training memory: ``s3k.budget``'s estimate against what a real training step takes.

For each image size, a fresh process trains one S3K step (4 + 4 frames of 4 cameras, the default U-Net) on a
small synthetic dataset through ``s3k.train.train`` and records two measurements: the bytes autograd saves
for the backward pass (each storage once, ``torch.autograd.graph.saved_tensors_hooks``) and the rise of the
process's peak resident memory during the step (its peak reset as training starts, Linux's
``/proc/self/clear_refs``). The estimate must bound both from above, within a factor of 2 of the peak
(``tests/train/test_budget.py`` holds one size of it).

Example::

    python benchmarks/train_memory.py --sizes 96 192 --out docs/results/benchmarks/train-memory-cpu.json

The last line printed is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import git_revision, write_and_emit  # noqa: E402
from s3k.cli import showing_library_messages  # noqa: E402

STEP = """
import json, sys
import torch
from s3k.budget import footprint
from s3k.config import TrainConfig
from s3k.train import train

def status(name):
    for line in open("/proc/self/status"):
        if line.startswith(name + ":"):
            return int(line.split()[1]) * 1024

saved = {}
def pack(t):
    storage = t.untyped_storage()
    saved[storage.data_ptr()] = storage.nbytes()
    return t

torch.set_num_threads(1)
size = int(sys.argv[3])
cfg = TrainConfig.from_flat(steps=1, batch_labelled=4, batch_unlabelled=4, warmup_steps=0, ramp_steps=0,
                            val_every=0, progress=False, threads=1, augment=False, preload_mb=0,
                            image_size=size)
with open("/proc/self/clear_refs", "w") as f:
    f.write("5")
before = status("VmRSS")
with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
    train(sys.argv[1], sys.argv[2], cfg)
peak = status("VmHWM") - before
need = footprint(cfg, cameras=4, keypoints=3, source_size=(32, 32))
print(json.dumps({"image_size": size, "saved_bytes": sum(saved.values()), "peak_rss_rise_bytes": peak,
                  "estimate_activations_bytes": need.activations, "estimate_total_bytes": need.total}))
"""


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[96, 192], help="image sizes (default 96 192)")
    p.add_argument("--out", default=None, help="also write the JSON here")
    args = p.parse_args(argv)
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from helpers.synthetic_rig import make_dataset

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        data = make_dataset(Path(tmp) / "ds", size=32, labelled=3, unlabelled=3, test=2)
        env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1]), "OMP_NUM_THREADS": "1"}
        for size in args.sizes:
            done = subprocess.run([sys.executable, "-c", STEP, str(data), str(Path(tmp) / f"run{size}"),
                                   str(size)], env=env, capture_output=True, text=True, check=True)
            row = json.loads(done.stdout.strip().splitlines()[-1])
            row["estimate_over_peak"] = round(row["estimate_total_bytes"] / row["peak_rss_rise_bytes"], 3)
            row["estimate_over_saved"] = round(row["estimate_activations_bytes"] / row["saved_bytes"], 3)
            rows.append(row)
    command = "python benchmarks/train_memory.py " + " ".join(sys.argv[1:] if argv is None else argv)
    write_and_emit({"benchmark": "train_memory", "command": command, "git_revision": git_revision(),
                    "frames_per_step": "4 labelled + 4 unlabelled, 4 cameras", "rows": rows}, args.out)
    return 0


if __name__ == "__main__":
    with showing_library_messages():  # the library's notes and warnings, as under s3k
        raise SystemExit(main())
