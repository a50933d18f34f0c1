"""`s3k experiment NAME --out DIR`: a paper experiment as a resumable sweep (:mod:`s3k.experiments`)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from s3k.base.errors import UserError
from s3k.base.outputs import check_folder
from s3k.cli import examples
from s3k.cli.options import device, number
from s3k.experiments import (
    DESCRIPTIONS,
    EXPERIMENTS,
    LABEL_CHOICES,
    SCALES,
    SUMMARY_FILE,
    Options,
    describe_plan,
    plan,
    publish,
    published,
    resummarize,
    run_experiment,
    summarize,
    verdict,
)


def _int_list(text: str) -> list[int]:
    """Comma-separated counts, each >= 0."""
    parse = number(int, ge=0)
    return [parse(v) for v in text.split(",") if v.strip()]


def _float_list(text: str) -> list[float]:
    """Comma-separated finite numbers, each >= 0."""
    parse = number(ge=0)
    return [parse(v) for v in text.split(",") if v.strip()]


def configure_parser(parser: argparse.ArgumentParser) -> None:
    lines = "\n".join(f"  {name:<18} {text}" for name, text in DESCRIPTIONS.items())
    scales = "\n".join(f"  {name:<6} {s.size} px, {s.steps} steps, {s.test} test frames, up to "
                       f"{s.pool_unlabelled} unlabelled, {s.seeds} seed(s) at claim points"
                       for name, s in SCALES.items())
    parser.epilog = (f"experiments:\n{lines}\n\nscales:\n{scales}\n\nA finished run (runs/NAME/result.json) "
                     "is never redone: rerun the same command to continue a killed sweep.\n\n"
                     + examples("s3k experiment label-efficiency --out runs/experiments --dry-run",
                                "s3k experiment alpha --out runs/experiments --scale toy --no-progress"))
    parser.add_argument("name", choices=EXPERIMENTS, metavar="NAME",
                        help="experiment: " + ", ".join(EXPERIMENTS))
    parser.add_argument("--out", required=True, metavar="DIR",
                        help="workspace: data/ (shared by experiments), NAME/runs/, NAME/summary.json, plots")
    parser.add_argument("--scale", choices=list(SCALES), default="small",
                        help="toy (seconds; tests), small (about 1 h per experiment on 2 CPU cores), full "
                             "(whole grid, default training scale; hours). Default: small")
    parser.add_argument("--seeds", type=number(int, ge=1), default=None,
                        help="seeds at the points carrying a claim (default: the scale's)")
    parser.add_argument("--seeds-other", type=number(int, ge=0), default=1,
                        help="seeds at the other points (default 1)")
    parser.add_argument("--steps", type=number(int, ge=1), default=None,
                        help="training steps per run (default: the scale's)")
    parser.add_argument("--size", type=number(int, ge=16), default=None, metavar="PX",
                        help="image size in pixels (default: the scale's)")
    parser.add_argument("--test", type=number(int, ge=1), default=None,
                        help="test frames (default: the scale's)")
    parser.add_argument("--data-seed", type=number(int, ge=0), default=0,
                        help="seed of the rendered datasets (default 0)")
    parser.add_argument("--labelled", type=_int_list, default=None, metavar="N,N,...",
                        help="labelled counts of the grid (default: the experiment's at --scale)")
    parser.add_argument("--unlabelled", type=_int_list, default=None, metavar="N,N,...",
                        help="unlabelled counts of the grid (0: labels-only baseline; default: the "
                             "experiment's at --scale)")
    parser.add_argument("--instances", type=_int_list, default=None, metavar="N,N,...",
                        help="category: training instance counts (default: the experiment's at --scale)")
    parser.add_argument("--alphas", type=_float_list, default=None, metavar="A,A,...",
                        help="alpha: values of alpha (default: the experiment's at --scale)")
    parser.add_argument("--modes", type=lambda s: [m for m in s.split(",") if m], default=None,
                        metavar="start,full", help="domain-shift: labelling modes (default: start,full)")
    two = parser.add_argument_group(
        "two passes (coarse-to-fine, as s3k train --two-pass)",
        "--two-pass trains every run as a coarse pass on the whole image at --size px and a refining pass on "
        "crops around its estimate, cut from pools rendered at --render px; --set applies to both passes")
    two.add_argument("--two-pass", action="store_true", help="train every run coarse-to-fine")
    two.add_argument("--render", type=number(int, ge=16), default=None, metavar="PX",
                     help="the pools' image size (default: 4 x --size, 384 at the full scale)")
    two.add_argument("--coarse-steps", type=number(int, ge=1), default=None, metavar="N",
                     help="the coarse pass's steps (default: --steps)")
    two.add_argument("--coarse-rotation", type=number(ge=0), default=None, metavar="DEG",
                     help="the coarse pass's augmentation rotation range in degrees (default: the runs' "
                          "rotation_deg field, which --set rotation_deg=DEG changes)")
    two.add_argument("--crop-size", type=number(int, ge=16), default=None, metavar="PX",
                     help="the refining pass's crop size in pixels (default: the scale's, 128 at small/full)")
    parser.add_argument("--label-choice", choices=LABEL_CHOICES, default="random",
                        help="how runs choose their labelled frames from the pool: random (stratified; "
                             "default), coverage or representative (the labelling app's 'poses not yet "
                             "labelled, farthest first' or 'poses in proportion' order over the pool's true "
                             "poses, from a first frame drawn by the seed)")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                        help="any TrainConfig field for every run (repeatable), e.g. --set lr=0.002 "
                             "(default: none)")
    parser.add_argument("--device", type=device, default="cpu",
                        help="'cpu', 'cuda', 'cuda:N' or 'auto' (default: cpu)")
    parser.add_argument("--threads", type=number(int, ge=0), default=0,
                        help="torch threads per run (0: torch's default; 1 when running two sweeps at once)")
    parser.add_argument("--workers", type=number(int, ge=1), default=None,
                        help="rendering processes (default: CPUs)")
    parser.add_argument("--dry-run", action="store_true", help="print the runs and the estimate, run nothing")
    parser.add_argument("--summarize-only", action="store_true",
                        help="only (re)write summary.json, plots and README.md from the finished runs "
                             "(without NAME/runs/: from the grid points of NAME/summary.json)")
    parser.add_argument("--publish", default=None, metavar="DIR",
                        help="then copy summary.json, README.md and plots to DIR, e.g. docs/results/NAME: a "
                             "new or empty folder or one published for NAME before (default: not copied)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def options_from_args(args: argparse.Namespace) -> Options:
    """:class:`Options` from parsed arguments (``--set`` values are checked when the plan is made)."""
    overrides: dict[str, Any] = {}
    for item in args.set:
        if "=" not in item:
            raise UserError(f"--set: expected FIELD=VALUE, got {item!r}")
        k, v = item.split("=", 1)
        overrides[k.strip().replace("-", "_")] = v.strip()
    for name in ("seeds", "steps", "size", "test", "render", "coarse_steps", "crop_size"):
        v = getattr(args, name)
        if v is not None and v <= 0:
            raise UserError(f"--{name.replace('_', '-')}: must be > 0, got {v}")
    return Options(experiment=args.name, out=Path(args.out), scale=args.scale, seeds=args.seeds,
                   seeds_other=args.seeds_other, steps=args.steps, size=args.size, test=args.test,
                   data_seed=args.data_seed, labelled=args.labelled, unlabelled=args.unlabelled,
                   instances=args.instances, alphas=args.alphas, modes=args.modes,
                   train_overrides=overrides, two_pass=args.two_pass, render=args.render,
                   coarse_steps=args.coarse_steps, coarse_rotation=args.coarse_rotation,
                   crop_size=args.crop_size, label_choice=args.label_choice, device=args.device,
                   threads=args.threads, workers=args.workers,
                   progress=not args.no_progress, command=getattr(args, "command_line", None))


def run(args: argparse.Namespace) -> int:
    def log(msg: str) -> None:
        print(msg, flush=True)


    exp_dir = Path(args.out) / args.name
    failed: list[str] = []
    check_folder(exp_dir, "experiment folder", owns=lambda folder: (folder / "runs").is_dir()
                 or published(folder, args.name), writes={"runs", "README.md", SUMMARY_FILE})
    if args.publish:  # before any work: never into a dataset, nor over files s3k did not publish

        check_folder(args.publish, "published experiment", inputs={"--out": exp_dir}, option="--publish",
                     owns=lambda folder: published(folder, args.name), writes={"README.md", SUMMARY_FILE})
    if args.summarize_only:
        if (exp_dir / "runs").is_dir():
            summary = summarize(exp_dir, args.name)
        elif (exp_dir / SUMMARY_FILE).is_file():  # the run folders are gone: from the summary's grid points
            summary = resummarize(exp_dir, args.name)
            log(f"re-summarized from {exp_dir / SUMMARY_FILE} (no {exp_dir / 'runs'})")
        else:
            raise UserError(f"{exp_dir / 'runs'} does not exist: nothing to summarize",
                            hint="check --out, or run the sweep first")
    else:
        opts = options_from_args(args)
        runs = plan(opts)
        if args.dry_run:
            log(describe_plan(runs, exp_dir, Path(args.out) / "data", args.scale))
            for r in runs:
                log(f"  {r.name:<28} pool {r.pool.name}, ~{r.estimated_cpu_s() / 60:.1f} CPU-min")
            return 0
        outcome = run_experiment(opts, log)
        summary, failed = outcome["summary"], outcome["failed"]
        log(f"trained {len(outcome['trained'])}, already finished or held elsewhere "
            f"{len(outcome['skipped'])}, failed {len(failed)}")
    log(f"summary: {exp_dir / SUMMARY_FILE} ({summary['runs']} runs, {len(summary['points'])} points); "
        f"figures: {', '.join(summary['figures'])}")
    for f in summary["findings"]:
        log(f"  {verdict(f['reproduced']):<12} {f['finding']}: {f['measured']}")
    if args.publish:
        copied = publish(exp_dir, Path(args.publish))
        log(f"published {len(copied)} files to {args.publish}")
    return 1 if failed else 0
