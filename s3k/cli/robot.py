"""``s3k robot``: the keypoints-in-the-loop experiments (docs/robot.md).

- ``s3k robot grasp RUN --trials 30 --out FILE``: grasp the plush toy's paw at the detected keypoint on the
  held-out arrangements (``--ground-truth``: at the true keypoint, the upper bound; RUN not needed);
- ``s3k robot train-agent --out DIR --agent keypoints|beta_vae --steps N --seed S [--resume]``: TD3 with
  demonstrations on the cable-insertion environment, checkpointed;
- ``s3k robot simulate-insertion --out D``: a keypoint dataset of the insertion environment, to train the
  detector an agent can read its keypoints with (``train-agent --run RUN``);
- ``s3k robot summarize --out docs/results/robot/summary.json ...``: the summary of what was measured.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from s3k.base.errors import UserError
from s3k.base.fileio import atomic_write_json
from s3k.base.outputs import check_output, check_output_folder, check_replaceable
from s3k.cli import examples
from s3k.cli.options import device, number
from s3k.robot.detect import RunDetector
from s3k.robot.results import write_summary
from s3k.run_folder import RunFolder


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.epilog = examples("s3k robot grasp runs/plush-s3k --trials 30 --out grasp-s3k.json",
                             "s3k robot train-agent --out runs/rl/kp-0 --run runs/insertion-s3k "
                             "--steps 10000")
    sub = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    g = sub.add_parser("grasp", help="grasp trials on the plush scene's held-out arrangements",
                       epilog=examples("s3k robot grasp runs/plush-s3k --trials 30 --out grasp-s3k.json",
                                       "s3k robot grasp --ground-truth --trials 30 "
                                       "--out grasp-ground-truth.json"))
    g.add_argument("run", nargs="?", default=None,
                   help="trained s3k run (plush keypoints) that detects the paw")
    g.add_argument("--ground-truth", action="store_true", help="grasp at the true keypoints instead (no RUN)")
    g.add_argument("--trials", type=number(int, ge=1), default=60,
                   help="grasp trials, over the held-out arrangements in turn (default 60)")
    g.add_argument("--arrangements", type=number(int, ge=1, le=6), default=6,
                   help="held-out arrangements 7, 8, ..., up to 12: 7-9 are the datasets' test arrangements, "
                        "10-12 in no dataset (default 6)")
    g.add_argument("--out", required=True, help="JSON file to write (successes, trials, per-trial results)")
    g.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    g.add_argument("--seed", type=number(int, ge=0), default=0,
                   help="draws each trial's lighting and gripper start (default 0)")
    g.add_argument("--object-seed", type=number(int, ge=0), default=None,
                   help="the plush scene's look and arrangements (default: that of the run's dataset when "
                        "its s3k.json can be read, else 0)")
    g.add_argument("--size", type=number(int, ge=16), default=None,
                   help="rendered image size (default: the run's network input; 96 with --ground-truth)")
    g.add_argument("--paw", default="front_left_paw", choices=["front_left_paw", "front_right_paw"],
                   help="which front paw to grasp (default front_left_paw)")
    g.add_argument("--device", type=device, default="cpu", help="torch device of the detector (default cpu)")

    t = sub.add_parser("train-agent", help="train a TD3 agent on cable insertion (resumable)",
                       epilog=examples("s3k robot train-agent --out runs/rl/kp-0 --agent keypoints "
                                       "--run runs/insertion-s3k --steps 10000 --seed 0",
                                       "s3k robot train-agent --out runs/rl/kp-0 --resume"))
    t.add_argument("--out", required=True, help="agent run folder to create (or to --resume)")
    t.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    from s3k.robot.agents import AgentConfig

    for f in dataclasses.fields(AgentConfig):
        flag = "--" + f.name.replace("_", "-")
        default = f.default
        kind = {int: number(int, ge=0), float: number(ge=0)}.get(type(default), str)
        t.add_argument(flag, type=kind, default=None, metavar=f.name.upper(),
                       help=f"{f.metadata['help']} (default {default})")

    d = sub.add_parser("simulate-insertion",
                       help="a keypoint dataset of the insertion environment (to train its detector)",
                       epilog=examples("s3k robot simulate-insertion --out data/insertion",
                                       "s3k robot simulate-insertion --out data/insertion --size 64 "
                                       "--labelled 10 --unlabelled 2000 --test 200"))
    d.add_argument("--out", required=True, help="dataset folder to create")
    d.add_argument("--size", type=number(int, ge=16), default=64, help="image width and height (default 64)")
    d.add_argument("--labelled", type=number(int, ge=0), default=10, help="labelled frames (default 10)")
    d.add_argument("--unlabelled", type=number(int, ge=0), default=2000,
                   help="unlabelled frames (default 2000)")
    d.add_argument("--test", type=number(int, ge=0), default=200,
                   help="test frames, from episodes of their own (default 200)")
    d.add_argument("--seed", type=number(int, ge=0), default=0, help="draws the episodes (default 0)")
    d.add_argument("--overwrite", action="store_true", help="replace --out if it exists and is not empty")
    d.add_argument("--no-progress", action="store_true", help="no progress bar")

    s = sub.add_parser("summarize", help="write docs/results/robot/summary.json from measured runs",
                       epilog=examples("s3k robot summarize --out summary.json --grasp-s3k grasp-s3k.json "
                                       "--rl-keypoints runs/rl/kp-0 runs/rl/kp-1"))
    s.add_argument("--out", required=True, help="summary JSON to write")
    s.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    s.add_argument("--grasp-s3k", default=None, help="s3k robot grasp result with the S3K run")
    s.add_argument("--grasp-labels-only", default=None, help="... with the labels-only run")
    s.add_argument("--grasp-ground-truth", default=None, help="... with --ground-truth")
    s.add_argument("--rl-keypoints", nargs="*", default=[], metavar="DIR", help="keypoint agent runs (seeds)")
    s.add_argument("--rl-beta-vae", nargs="*", default=[], metavar="DIR", help="beta-VAE agent runs (seeds)")
    s.add_argument("--machine", default=None, help="a description of the machine the runs took place on")


def _dataset_object_seed(run: str) -> int | None:
    """The ``object_seed`` of the plush dataset run ``run`` was trained on, when its metadata says so."""

    dataset = RunFolder(run).dataset()
    try:
        source = json.loads((Path(str(dataset)) / "s3k.json").read_text()).get("source") or {}
    except (OSError, ValueError, AttributeError):
        return None
    if source.get("scene") != "plush" or not isinstance(source.get("object_seed"), int):
        return None
    print(f"s3k robot grasp: the plush scene of --object-seed {source['object_seed']}, as in {dataset}",
          file=sys.stderr)
    return int(source["object_seed"])


def _grasp(args: argparse.Namespace) -> int:
    from s3k.robot.grasp import KeypointSource, detector_keypoints, ground_truth_keypoints, run_trials
    from s3k.sim.plush import PlushScene

    if args.trials < 1:
        raise UserError(f"--trials: must be >= 1, got {args.trials}")
    source: KeypointSource
    if args.ground_truth:
        source, size, label = ground_truth_keypoints, args.size or 96, "ground_truth"
    else:
        if args.run is None:
            raise UserError("RUN: give a trained run, or --ground-truth for the upper bound")

        detector = RunDetector(args.run, PlushScene.keypoints, device=args.device)
        W, H = detector.image_size
        size = args.size or W
        if args.size is None and W != H:
            raise UserError(f"run {args.run}: its network input is {W}x{H}; the plush scene renders square "
                            "images", hint="give --size")
        source, label = detector_keypoints(detector), str(args.run)
        if args.object_seed is None:
            args.object_seed = _dataset_object_seed(args.run)
    if args.object_seed is None:
        args.object_seed = 0
    check_output(args.out, args.overwrite, inputs={"RUN": args.run})  # before the trials: never a lost hour

    def progress(i: int, r) -> None:
        print(f"trial {i + 1}/{args.trials}: {'success' if r.success else 'failure'} (paw lifted "
              f"{100 * r.lift:.1f} cm, {r.held_mm:.0f} mm from the gripper; aim error "
              f"{r.aim_error_mm:.1f} mm)", file=sys.stderr)

    result = run_trials(source, args.trials, size=size, seed=args.seed, object_seed=args.object_seed,
                        paw=args.paw, arrangements=args.arrangements, progress=progress)
    result["detector"] = label
    atomic_write_json(result, args.out)
    print(f"wrote {args.out}: {result['successes']}/{result['trials']} grasps lifted the paw 10 cm, "
          "held by it")
    return 0


def _train_agent(args: argparse.Namespace) -> int:
    try:
        import gymnasium  # noqa: F401
        import stable_baselines3  # noqa: F401
    except ImportError as exc:
        raise UserError(f"s3k robot train-agent needs {exc.name}", hint="pip install 's3k[robot]'") from exc
    from s3k.robot.agents import AgentConfig, saved_config, train_agent

    check_output_folder(args.out)  # never inside a dataset, nor a run's own files
    given = {f.name: getattr(args, f.name) for f in dataclasses.fields(AgentConfig)
             if getattr(args, f.name) is not None}
    base = {}
    config_file = Path(args.out) / "config.json"
    if args.resume and config_file.is_file():
        base = saved_config(config_file)
    cfg = AgentConfig(**{**base, **given})
    result = train_agent(args.out, cfg, resume=args.resume)
    print(json.dumps(result))
    return 0


def _simulate_insertion(args: argparse.Namespace) -> int:
    from s3k.robot.insertion_data import write_insertion_dataset

    check_replaceable(args.out, args.overwrite)  # as simulate: never inside a dataset, nor someone's files
    summary = write_insertion_dataset(args.out, args.labelled, args.unlabelled, args.test, size=args.size,
                                      seed=args.seed, overwrite=args.overwrite, progress=not args.no_progress)
    print(f"wrote {summary['path']}: {summary['frames']} frames ({args.labelled} labelled, {args.unlabelled} "
          f"unlabelled, {args.test} test), 4 cameras, {args.size}x{args.size} px")
    return 0


def _summarize(args: argparse.Namespace) -> int:
    check_output(args.out, args.overwrite, inputs={"--grasp-s3k": args.grasp_s3k,
                                                   "--grasp-labels-only": args.grasp_labels_only,
                                                   "--grasp-ground-truth": args.grasp_ground_truth})
    summary = write_summary(args.out, grasp_s3k=args.grasp_s3k, grasp_labels_only=args.grasp_labels_only,
                            grasp_ground_truth=args.grasp_ground_truth, rl_keypoints=args.rl_keypoints,
                            rl_beta_vae=args.rl_beta_vae, machine=args.machine)
    print(json.dumps(summary, indent=2))
    return 0


def run(args: argparse.Namespace) -> int:
    actions = {"grasp": _grasp, "train-agent": _train_agent, "simulate-insertion": _simulate_insertion,
               "summarize": _summarize}
    return actions[args.action](args)
