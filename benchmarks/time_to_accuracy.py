"""Time to accuracy: a box preset (``--preset``, default box-headline) on N seeds end to end, stage by stage.

For every seed: render the box scene (100 labelled + 2000 unlabelled + 200 test frames at 384 px), choose 10
of the 100 labelled frames as the labelling app's *poses in proportion* ranking would, train S3K and labels
only with ``s3k train --preset PRESET`` (``--parallel`` trainings at once, one thread each on a CPU,
sharing the GPU on a GPU machine), evaluate both on the test frames. This is ``benchmarks/accuracy.py`` with
the headline's options (its stages, records and resumption); this script adds the per-stage table.

Printed: the device, then per stage its wall and CPU minutes (mean per seed; the trainings' stages are CPU
time per model: ``coarse`` the coarse pass, ``crops`` its estimates and the crops cut around them, ``fine``
the refining pass), the accuracy per model and the whole call's wall time; the last line is the summary as
JSON (also written to ``--results``/summary.json, with ``stages``, ``device`` and the accuracy checks).

Example::

    python benchmarks/time_to_accuracy.py --seeds 3        # 2-core CPU: 35 min end to end (render 5,
                                                           # train and evaluate 30)
    python benchmarks/time_to_accuracy.py --seeds 3 --device cuda --parallel 6  # a GPU: all models at once
    python benchmarks/time_to_accuracy.py --seeds 3 --preset box-fast  # -> results/accuracy/fast/box-fast
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

ROOT = Path(__file__).resolve().parents[1]

from s3k.cli import showing_library_messages  # noqa: E402
from s3k.train.presets import PRESETS  # noqa: E402


def device_name(device: str) -> str:
    """The device the trainings run on, in words."""
    import torch

    if device.startswith("cuda") or (device == "auto" and torch.cuda.is_available()):
        if not torch.cuda.is_available():
            raise SystemExit("--device cuda: this machine has no CUDA GPU")
        return f"cuda: {torch.cuda.get_device_name(0)}"
    from benchmarks.common import machine_info

    info = machine_info()
    return f"cpu: {info['cpu']}, {info['cpu_count']} cores"


def stage_table(summary: dict) -> list[str]:
    """Lines of the per-stage table of a summary written by ``benchmarks/accuracy.py``."""
    lines = [f"{'stage':28s} {'wall min':>9s} {'CPU min':>9s}"]
    for name, stage in summary.get("stages", {}).items():
        if "cpu_min" in stage:
            wall = f"{stage['wall_min']:9.2f}" if "wall_min" in stage else " " * 9
            lines.append(f"{name + ' (per seed)':28s} {wall} {stage['cpu_min']:9.2f}")
            continue
        for part, spent in stage.items():
            lines.append(f"{name + ' ' + part:28s} {' ' * 9} {spent['cpu_min']:9.2f}")
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seeds", type=int, default=3, help="seeds 0..N-1 (default 3)")
    p.add_argument("--preset", default="box-headline", choices=[n for n in PRESETS if n.startswith("box-")],
                   help="the configuration both models train with (default box-headline)")
    p.add_argument("--device", default="cpu", help="where the models train: cpu (default), cuda, auto")
    p.add_argument("--parallel", type=int, default=2,
                   help="trainings at once (default 2: one per core of a 2-core CPU)")
    p.add_argument("--work", default=None, help="working folder (default runs/time-to-accuracy)")
    p.add_argument("--results", default=None,
                   help="folder of summary.json (default docs/results/accuracy/fast; fast/PRESET for "
                        "another preset)")
    p.add_argument("--coarse-from", metavar="WORK", default=None,
                   help="start from the coarse passes and estimates of an earlier working folder's runs with "
                        "the same coarse options (their CPU minutes counted; benchmarks/accuracy.py)")
    p.add_argument("--notes", default=None,
                   help="text kept in summary.json, e.g. the revision the runs were trained at when the "
                        "summary is written again from finished runs")
    args = p.parse_args(argv)
    device = device_name(args.device)
    if device.startswith("cuda"):
        os.environ.setdefault("MUJOCO_GL", "egl")  # rendering on the GPU
    from benchmarks import accuracy

    work = args.work or str(ROOT / "runs" / "time-to-accuracy")
    fast = ROOT / "docs" / "results" / "accuracy" / "fast"
    results = Path(args.results or (fast if args.preset == "box-headline" else fast / args.preset))
    forwarded = ["--seeds", str(args.seeds), "--preset", args.preset, "--label-pool", "100",
                 "--label-choice", "representative", "--parallel", str(args.parallel), "--work", work,
                 "--results", str(results)]
    if args.device != "cpu":
        forwarded += ["--train-options", f"--device {args.device}"]
    if args.coarse_from:
        forwarded += ["--coarse-from", args.coarse_from]
    if args.notes:
        forwarded += ["--notes", args.notes]
    accuracy.main(forwarded)
    path = results / "summary.json"
    summary = json.loads(path.read_text())
    summary["device"] = device
    worst = max(summary["s3k"]["train_cpu_minutes"]["per_seed"])
    summary["checks"]["s3k_train_cpu_minutes_at_most_12_every_seed"] = worst <= 12.0
    from s3k.experiments.accuracy import without_notes

    given = without_notes(sys.argv[1:] if argv is None else argv)
    summary["time_to_accuracy_command"] = " ".join(["python", "benchmarks/time_to_accuracy.py", *given])
    path.write_text(json.dumps(summary, indent=2) + "\n")
    print(f"device: {device}", file=sys.stderr)
    for line in stage_table(summary):
        print(line, file=sys.stderr)
    for model in ("s3k", "labels_only"):
        m = summary[model]
        print(f"{model:12s} median {m['median_mm']['mean']:.2f} mm, RMS {m['rms_mm']['mean']:.2f} mm, "
              f"within 10 mm {100 * m['pck_10mm']['mean']:.1f}%; training "
              f"{m['train_cpu_minutes']['mean']:.1f} CPU-min per model", file=sys.stderr)
    print(f"whole call: {summary['minutes_this_call']:.1f} min wall", file=sys.stderr)
    print(json.dumps({k: summary[k] for k in ("device", "seeds", "checks", "stages", "minutes_this_call")}))
    return 0


if __name__ == "__main__":
    with showing_library_messages():  # the library's notes and warnings, as under s3k
        raise SystemExit(main())
