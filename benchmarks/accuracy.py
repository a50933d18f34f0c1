"""Accuracy over seeds: S3K against the labels-only baseline, same network, crops and training budget.

Targets (docs/method.md#performance-targets), box scene, 10 labelled + 2000 unlabelled frames, 3 seeds: S3K
median 3D error <= 3 mm and RMS <= 6 mm, at most labels only's in every seed, RMS <= 0.6 x labels only's
mean, >= 95% of keypoints within 10 mm, <= 60 CPU-minutes of training per model.

For every seed ``s`` the scene is rendered once at ``--render`` px with sampling seed ``s`` (poses, cameras,
lighting; the object's look is the scene's own), and two detectors are trained from it with training seed
``s``: S3K and labels only (``--no-unsup``), each with ``s3k train --two-pass`` (a coarse pass at
``--coarse-size`` px, a refining pass on ``--crop-size`` px crops; ``--passes 1`` trains one pass on the
whole image at ``--coarse-size`` px instead). The trainings run two at a time, one thread each; each one's
CPU time (user + system, from the operating system, so unaffected by other load on the machine) is its
``train_cpu_minutes``. Both are evaluated on the seed's test frames with ``s3k evaluate``.

``--label-pool N`` renders ``N`` labelled frames instead of 10 and trains on 10 of them, chosen by
``--label-choice``: ``random`` (drawn by the seed), ``coverage`` or ``representative`` (as a labeller
following the labelling app's *poses not yet labelled, farthest first* or *poses in proportion* ranking
would choose them, judged on the true poses: :func:`s3k.experiments.views.pose_pick`); all see the same
rendered frames, so the choices compare side by side.

``--scene distractors`` renders the distractors scene in start mode (labels from the first distractor set
only; test frames with distractor sets never seen in training). ``--scene plush`` renders the deformable
plush toy among distractor toys (docs/scenes.md); its layout is not rigid, so its runs leave
``--layout-tol`` off; ``--unlabelled-arrangements N`` spreads its unlabelled frames over N further
arrangements too (``s3k simulate plush --unlabelled-arrangements``). ``--scene category`` renders mugs:
labelled and unlabelled frames of the 12 training instances, test frames of the 4 held out (one layout per
instance, so no ``--layout-tol`` either).
``--scene insertion`` renders the cable-insertion environment's fixed rig
(:func:`s3k.robot.insertion_data.write_insertion_dataset`: frames from noisy scripted episodes, the seed
drawing the episodes, test frames from episodes of their own): plug tip, plug base and socket.

To compare options that change one model or one pass, ``--labels-only-from WORK`` links an earlier working
folder's renders and finished labels-only runs, and ``--coarse-from WORK`` starts each training from the
coarse pass, estimates and crops of the same-named run there, adding that stage's CPU time
(``RUN/cpu.json``) to the run's; the training refuses a coarse pass or crops its options would not make.

Everything is kept in ``--work``; a stage whose output exists is skipped and a killed training resumes, so
the same command continues an interrupted benchmark. Writes ``--results``/summary.json (command, revision,
machine, scale, per-seed figures, means) and prints it as the last line.

Example::

    python benchmarks/accuracy.py --seeds 3                          # box, about 2.5 hours on 2 cores
    python benchmarks/accuracy.py --seeds 3 --scene distractors \\
        --results docs/results/accuracy/distractors
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import emit, git_revision, machine_info  # noqa: E402
from s3k.cli import showing_library_messages  # noqa: E402
from s3k.config import default_of  # noqa: E402
from s3k.experiments.accuracy import (  # noqa: E402
    FIGURES,
    LABELLED,
    MODELS,
    TARGETS,
    evaluate,
    finished,
    read_record,
    render,
    reuse_coarse,
    reuse_labels_only,
    run_jobs,
    seed_stats,
    stage_summary,
    train_command,
    without_notes,
)
from s3k.experiments.grid import LABEL_CHOICES  # noqa: E402
from s3k.train.presets import PRESETS  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seeds", type=int, default=3, help="seeds 0..N-1 (default 3)")
    p.add_argument("--scene", choices=("box", "distractors", "plush", "category", "insertion"), default="box")
    p.add_argument("--work", default=None, help="working folder (default runs/accuracy-SCENE)")
    p.add_argument("--results", default=None,
                   help="folder of summary.json (default docs/results/accuracy; .../SCENE for another scene)")
    p.add_argument("--render", type=int, default=384, help="rendered image size (default 384)")
    p.add_argument("--unlabelled", type=int, default=2000, help="unlabelled frames (default 2000)")
    p.add_argument("--test", type=int, default=200, help="test frames (default 200)")
    p.add_argument("--unlabelled-arrangements", type=int, default=0, metavar="N",
                   help="plush: unlabelled frames over N further arrangements too (new toy placements and "
                        "camera rigs; default 0: the 7 training arrangements only)")
    p.add_argument("--label-pool", type=int, default=LABELLED, metavar="N",
                   help=f"labelled frames rendered, of which {LABELLED} are trained on (default {LABELLED})")
    p.add_argument("--label-choice", choices=LABEL_CHOICES, default="random",
                   help="how the 10 are chosen from a larger --label-pool: random (default), coverage or "
                        "representative")
    p.add_argument("--passes", type=int, choices=(1, 2), default=2, help="two passes (default) or one")
    p.add_argument("--coarse-size", type=int, default=default_of("coarse_size"),
                   help=f"coarse (or only) pass size (default {default_of('coarse_size')})")
    p.add_argument("--crop-size", type=int, default=default_of("crop_size"),
                   help=f"refining pass crop size (default {default_of('crop_size')})")
    p.add_argument("--steps", type=int, default=4000, help="steps of each pass (default 4000)")
    p.add_argument("--coarse-steps", type=int, default=None, help="coarse pass steps (default --steps)")
    p.add_argument("--train-options", default="", help="more `s3k train` options for both models")
    p.add_argument("--preset", choices=list(PRESETS), default=None,
                   help="train both models with `s3k train --preset NAME`; its two-pass sizes and steps "
                        "become the defaults of the options above (box-headline: the headline's "
                        "configuration)")
    p.add_argument("--parallel", type=int, default=2, help="trainings at once, one thread each (default 2)")
    p.add_argument("--labels-only-from", metavar="WORK", default=None,
                   help="take the renders and the finished labels-only runs of an earlier working folder "
                        "instead of making them again (labels only reads none of the self-supervision "
                        "options, so a comparison of those trains S3K alone)")
    p.add_argument("--coarse-from", metavar="WORK", default=None,
                   help="start the trainings from the coarse passes, estimates and crops of an earlier "
                        "working folder's runs (their CPU minutes counted), to compare refining-pass "
                        "options; the trainings refuse a coarse pass or crops the options here would not "
                        "make")
    p.add_argument("--notes", default=None,
                   help="text kept in summary.json, e.g. the revision the runs were trained at when the "
                        "summary is written again from finished runs (left out of the recorded command)")
    args = p.parse_args(argv)
    if args.preset:  # the preset's sizes and steps, unless given here
        chosen = PRESETS[args.preset].config
        two = chosen.passes
        p.set_defaults(passes=2 if two.two_pass else 1, steps=chosen.schedule.steps,
                       coarse_size=two.coarse_size, coarse_steps=two.coarse_steps, crop_size=two.crop_size)
        args = p.parse_args(argv)
    if args.unlabelled_arrangements and args.scene != "plush":
        p.error("--unlabelled-arrangements: the plush scene only")
    if args.label_pool < LABELLED:
        p.error(f"--label-pool: at least {LABELLED}, got {args.label_pool}")
    os.environ.setdefault("MUJOCO_GL", "osmesa")
    work = Path(args.work or ROOT / "runs" / f"accuracy-{args.scene}")
    results = Path(args.results or ROOT / "docs" / "results" / "accuracy"
                   / ("" if args.scene == "box" else args.scene))
    work.mkdir(parents=True, exist_ok=True)
    revision = git_revision()
    t0 = time.perf_counter()
    seeds = list(range(args.seeds))
    if args.labels_only_from:
        reuse_labels_only(Path(args.labels_only_from), work, seeds, args)
    data = {s: render(args, s, work) for s in seeds}
    runs = {(s, m): work / f"{m}-seed{s}" for s in seeds for m in MODELS}
    if args.coarse_from:
        if args.passes != 2:
            p.error("--coarse-from: only with two passes")
        reuse_coarse(Path(args.coarse_from), [r for r in runs.values() if not finished(r, args.passes)])
    # model by model, S3K's (the longer trainings) first, so the labels-only ones fill in around them
    jobs = [(f"{m} seed {s}", train_command(args, data[s], runs[s, m], s, m),
             runs[s, m].with_name(runs[s, m].name + "-cpu.json"))
            for m in MODELS for s in seeds if not finished(runs[s, m], args.passes)]
    run_jobs(jobs, args.parallel)
    metrics = {key: evaluate(run, data[key[0]]) for key, run in runs.items()}
    cpu = {key: read_record(run.with_name(run.name + "-cpu.json")) for key, run in runs.items()}
    chosen = "" if args.label_pool == LABELLED else \
        f" ({args.label_choice} choice of {args.label_pool} rendered)"
    spread = (f" (over the 7 training and {args.unlabelled_arrangements} further arrangements)"
              if args.unlabelled_arrangements else "")
    scale = (f"{args.scene} rendered at {args.render} px, {LABELLED} labelled{chosen} + {args.unlabelled} "
             f"unlabelled{spread} + {args.test} test frames; " + (
                 f"two passes: coarse {args.coarse_size} px, {args.coarse_steps or args.steps} steps; crops "
                 f"{args.crop_size} px, {args.steps} steps" if args.passes == 2
                 else f"one pass at {args.coarse_size} px, {args.steps} steps")
             + (f"; preset {args.preset}" if args.preset else "")
             + (f"; train options {args.train_options!r}" if args.train_options else ""))
    summary = {
        "command": shlex.join(["python", "benchmarks/accuracy.py", *without_notes(
            sys.argv[1:] if argv is None else argv)]),
        "git_revision": revision,
        "machine": machine_info(),
        "scale": scale,
        "seeds": seeds,
        **({"labels_only_from": args.labels_only_from} if args.labels_only_from else {}),
        **({"coarse_from": args.coarse_from} if args.coarse_from else {}),
        "train_cpu_minutes_per_model": max(c["cpu_minutes"] for c in cpu.values()),
        "train_wall_minutes_per_model": max(c["wall_minutes"] for c in cpu.values()),
    }
    for m in MODELS:
        summary[m] = {k: seed_stats([float(metrics[s, m][k]) for s in seeds]) for k in FIGURES}
        for figure in ("median_mm", "rms_mm"):  # a keypoint the others hide (the mugs' rim) read on its own
            summary[m][f"{figure}_per_keypoint"] = {
                kp: seed_stats([float(metrics[s, m]["per_keypoint"][kp][figure]) for s in seeds])
                for kp in metrics[seeds[0], m]["per_keypoint"]}
        summary[m]["train_cpu_minutes"] = seed_stats([cpu[s, m]["cpu_minutes"] for s in seeds])
    s3k, lo = summary["s3k"], summary["labels_only"]
    summary["checks"] = {
        "s3k_median_mm_mean_at_most_3": s3k["median_mm"]["mean"] <= 3.0,
        "s3k_rms_mm_mean_at_most_6": s3k["rms_mm"]["mean"] <= 6.0,
        "s3k_at_most_labels_only_every_seed_median_mm": all(
            a <= b for a, b in zip(s3k["median_mm"]["per_seed"], lo["median_mm"]["per_seed"])),
        "s3k_at_most_labels_only_every_seed_rms_mm": all(
            a <= b for a, b in zip(s3k["rms_mm"]["per_seed"], lo["rms_mm"]["per_seed"])),
        "s3k_rms_mm_ratio": s3k["rms_mm"]["mean"] / lo["rms_mm"]["mean"],
        "s3k_pck_10mm_at_least_0.95": s3k["pck_10mm"]["mean"] >= 0.95,
        "train_cpu_minutes_at_most_60": summary["train_cpu_minutes_per_model"] <= 60.0,
    }
    summary["stages"] = stage_summary(work, seeds, runs)
    summary["targets"] = TARGETS
    if args.notes:
        summary["notes"] = args.notes
    summary["minutes_this_call"] = (time.perf_counter() - t0) / 60
    results.mkdir(parents=True, exist_ok=True)
    (results / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    for m in MODELS:
        print(f"{m:12s} " + "  ".join(f"{k} {summary[m][k]['mean']:.3g} +- {summary[m][k]['sd']:.2g}"
                                      for k in ("median_mm", "rms_mm", "pck_10mm")), file=sys.stderr)
    emit({k: v for k, v in summary.items() if k not in ("s3k", "labels_only")})
    return 0


if __name__ == "__main__":
    with showing_library_messages():  # the library's notes and warnings, as under s3k
        raise SystemExit(main())
