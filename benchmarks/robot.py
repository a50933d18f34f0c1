"""The robot experiments end to end: the plush grasp (S3K, labels only, ground truth) and the cable-insertion
agents (keypoints from a trained detector, and the beta-VAE baseline) over seeds, into
``docs/results/robot/summary.json`` and ``docs/results/robot/rl-success.png``.

Stages, each skipped when its output exists (a killed training or agent resumes), so the same command
continues an interrupted benchmark:

1. ``s3k simulate plush`` (``--plush-size`` px; 7 labelled frames, one per training arrangement, the first
   of its stretch; ``--plush-unlabelled`` more frames over the training arrangements; ``--plush-test`` over
   the 3 held-out ones).
2. ``s3k label propagate``: each training arrangement's labelled frame copied to the first ``--propagate``
   frames of its stretch. The toys and cameras are still there while the gripper and the light move, so the
   image check is lifted (``--max-changed 100``): the gripper changes 2-50% of a view's pixels.
3. Two plush detectors, S3K and labels only (``--no-unsup``), same labels, steps and seed, side by side.
4. ``s3k robot grasp`` with each and with the ground truth, ``--trials`` each.
5. ``s3k robot simulate-insertion`` and one S3K detector of the insertion keypoints.
6. ``s3k robot train-agent`` for each of ``--seeds``: the keypoint agent reading the detector
   (``--run``), and the beta-VAE agent; two at a time, one thread each.
7. ``s3k robot summarize``, then the success-rate curves' plot.

``--plush-work WORK`` replaces stages 1-4: the grasp runs with the two-pass detectors of
``benchmarks/accuracy.py --scene plush --work WORK`` over their seeds and 6 held-out arrangements, through
``benchmarks/grasp.py``, once the summary is written.

``--insertion-work WORK`` replaces stage 5: seed k's keypoint agent reads the two-pass S3K detector of seed k
of ``benchmarks/accuracy.py --scene insertion --work WORK``, on views of the size it was trained on.

``--agent-ablation`` instead trains the keypoint agent on ground-truth keypoints, one seed, in five
variants (plain TD3 with demonstrations in its buffer only; imitating the demonstrations only, without the
expert's labels of the visited states; the Q-term off: behaviour cloning of the demonstrations and the
relabelled states; the Q-term at full weight; the defaults) and writes their success-rate curves to
``agent-ablation.json``.

Example::

    python benchmarks/robot.py                       # about 2 hours on 2 cores
    python benchmarks/robot.py --seeds 1 --agent-steps 2000 --work runs/robot-small
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import emit, git_revision, machine_info  # noqa: E402
from s3k.cli import showing_library_messages  # noqa: E402
from s3k.config import TrainConfig  # noqa: E402
from s3k.experiments.accuracy import evaluate, run_jobs  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
S3K = [sys.executable, "-m", "s3k.cli"]
ABLATION = {  # agent variants on ground-truth keypoints: name -> train-agent options
    "td3_demos_in_buffer_only": ["--bc-weight", "0", "--bc-pretrain", "0", "--q-weight", "1",
                                 "--expert-relabel", "0", "--learning-starts", "100"],
    "demonstrations_only_imitated": ["--expert-relabel", "0", "--learning-starts", "100"],
    "behaviour_cloning_only": ["--q-weight", "0"],
    "q_term_full_weight": ["--q-weight", "1"],
    "default": [],
}


def note_revision(work: Path) -> None:
    """Records the revision a stage ran at (a resumed benchmark may span several)."""
    with open(work / "revisions.txt", "a", encoding="utf-8") as f:
        f.write(git_revision() + "\n")


def sh(cmd: list[str]) -> None:
    print("$ " + " ".join(str(c) for c in cmd[2:]), file=sys.stderr, flush=True)
    subprocess.run(cmd, check=True, env=dict(os.environ, OMP_NUM_THREADS="1"))


def plush_data(args, work: Path) -> Path:
    data = work / "plush"
    done = work / "plush.propagated"
    if not (data / "s3k.json").is_file():
        sh(S3K + ["simulate", "plush", "--out", str(data), "--size", str(args.plush_size), "--unlabelled",
                  str(args.plush_unlabelled), "--test", str(args.plush_test), "--no-progress", "--overwrite"])
    if not done.is_file():
        from s3k.data import Dataset

        ds = Dataset.open(data, cache="none")
        for first in ds.frames("labelled"):  # one per training arrangement, the first frame of its stretch
            sh(S3K + ["label", "propagate", str(data), "--frames", f"{first}:{first + args.propagate - 1}",
                      "--from", str(first), "--max-changed", "100"])
        done.write_text("")
    return data


def agent_command(args, out: Path, agent: str, seed: int, detector: Path | None) -> list[str]:
    cmd = S3K + ["robot", "train-agent", "--out", str(out), "--agent", agent, "--seed", str(seed),
                 "--steps", str(args.agent_steps), "--checkpoint-every", str(args.eval_every),
                 "--eval-episodes", str(args.eval_episodes), "--threads", "1", *args.agent_options.split()]
    if detector is not None:
        from s3k.robot.detect import RunDetector

        size = RunDetector(detector, ["plug_tip"]).image_size[0]  # the views it was trained on
        cmd += ["--run", str(detector), "--image-size", str(size)]
    if (out / "config.json").is_file():
        cmd.append("--resume")
    return cmd


def plot(summary: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.6))
    for name, label, colour in (("keypoints", "keypoints (S3K detector)", "C0"),
                                ("beta_vae", "beta-VAE latent", "C1")):
        c = summary["rl_success_curve"].get(name)
        if not c:
            continue
        ax.plot(c["env_steps"], c["mean"], color=colour, label=f"{label}, mean of {c['seeds']} seeds")
        ax.fill_between(c["env_steps"], c["min"], c["max"], color=colour, alpha=0.2)
    ax.set_xlabel("environment steps (4 Hz)")
    ax.set_ylabel("plug in: success rate")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(loc="center right", fontsize=8)
    ax.set_title("Cable insertion, deterministic policy; band: min-max over seeds", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def agent_ablation(args, work: Path, results: Path, argv, revision: str) -> int:
    jobs, runs = [], {}
    for name, options in ABLATION.items():
        out = work / "rl-ablation" / name
        runs[name] = out
        progress = out / "progress.json"
        if progress.is_file() and json.loads(progress.read_text()).get("final", {}).get("env_steps") \
                == args.ablation_steps:
            continue
        out.parent.mkdir(parents=True, exist_ok=True)
        cmd = S3K + ["robot", "train-agent", "--out", str(out), "--seed", "0", "--steps",
                     str(args.ablation_steps), "--checkpoint-every", "1000", "--eval-episodes",
                     str(args.eval_episodes), "--threads", "1", *options]
        jobs.append((f"ablation {name}", cmd + (["--resume"] if (out / "config.json").is_file() else []),
                     work / "rl-ablation" / f"{name}.cpu.json"))
    run_jobs(jobs, args.parallel)
    curves = {}
    for name, out in runs.items():
        evals = json.loads((out / "progress.json").read_text())["evaluations"]
        curves[name] = {"options": " ".join(ABLATION[name]) or "(defaults)",
                        "env_steps": [e["env_steps"] for e in evals],
                        "success_rate": [e["true_success_rate"] for e in evals]}
    result = {"command": "python benchmarks/robot.py " + " ".join(argv if argv is not None else sys.argv[1:]),
              "git_revision": revision, "machine": machine_info(),
              "scale": f"keypoint agent on ground-truth keypoints, seed 0, {args.ablation_steps} environment "
                       f"steps, evaluation every 1000 steps over {args.eval_episodes} episodes",
              "curves": curves}
    (results / "agent-ablation.json").write_text(json.dumps(result, indent=2) + "\n")
    emit(result)
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--work", default="runs/robot", help="where datasets and runs go (default runs/robot)")
    p.add_argument("--results", default=str(ROOT / "docs/results/robot"),
                   help="folder of summary.json and the plot (default docs/results/robot)")
    p.add_argument("--plush-size", type=int, default=96)
    p.add_argument("--plush-unlabelled", type=int, default=700)
    p.add_argument("--plush-test", type=int, default=60)
    p.add_argument("--propagate", type=int, default=20,
                   help="frames of each training arrangement that get its labelled frame's labels (20)")
    p.add_argument("--detector-steps", type=int, default=4000, help="training steps of every detector (4000)")
    p.add_argument("--trials", type=int, default=None,
                   help="grasp trials per detector (30; per detector and seed with --plush-work: 60)")
    p.add_argument("--plush-work", default=None, metavar="WORK",
                   help="grasp with the two-pass detectors of benchmarks/accuracy.py --scene plush "
                        "--work WORK over their seeds and 6 held-out arrangements (benchmarks/grasp.py, "
                        "--trials 60 unless given) instead of training one-pass plush detectors here")
    p.add_argument("--insertion-size", type=int, default=64)
    p.add_argument("--insertion-work", default=None, metavar="WORK",
                   help="the keypoint agents read the two-pass S3K detectors of benchmarks/accuracy.py "
                        "--scene insertion --work WORK (agent seed k: detector seed k, on views of the size "
                        "it was trained on) instead of a one-pass detector trained here")
    p.add_argument("--agent-options", default="", help="more s3k robot train-agent options for every agent")
    p.add_argument("--seeds", type=int, default=3, help="agent seeds per agent (3)")
    p.add_argument("--agent-steps", type=int, default=10000, help="environment steps per agent (10000)")
    p.add_argument("--eval-every", type=int, default=2000,
                   help="environment steps between the agents' checkpoints and evaluations (2000)")
    p.add_argument("--eval-episodes", type=int, default=20, help="episodes per evaluation (20)")
    p.add_argument("--parallel", type=int, default=2, help="jobs at a time, one thread each (2)")
    p.add_argument("--agent-ablation", action="store_true",
                   help="run the agent variants on ground-truth keypoints instead (seed 0)")
    p.add_argument("--ablation-steps", type=int, default=4000)
    args = p.parse_args(argv)
    if args.trials is None:
        args.trials = 60 if args.plush_work else 30
    work = Path(args.work).resolve()
    work.mkdir(parents=True, exist_ok=True)
    results = Path(args.results)
    results.mkdir(parents=True, exist_ok=True)
    started = time.time()
    revision = git_revision()  # before anything here writes into the repository's docs
    if args.agent_ablation:
        return agent_ablation(args, work, results, argv, revision)

    # --- the grasp (with --plush-work: benchmarks/grasp.py with those two-pass detectors, after the summary)
    plush = work / "plush" if args.plush_work else plush_data(args, work)
    runs = {} if args.plush_work else {"s3k": work / "plush-s3k", "labels_only": work / "plush-labels-only"}
    jobs = []
    for name, run in runs.items():
        if not (run / "model.pt").is_file():
            cfg = TrainConfig.from_flat(steps=args.detector_steps, threads=1, progress=False,
                                        unsup=name != "labels_only")
            cmd = S3K + ["train", str(plush), "--out", str(run), *cfg.to_argv()]
            jobs.append((f"plush {name}", cmd + (["--resume"] if run.exists() else []),
                         work / f"plush-{name}.cpu.json"))
    if jobs:
        note_revision(work)
    run_jobs(jobs, args.parallel)
    grasps = {}
    for name in () if args.plush_work else ("s3k", "labels_only", "ground_truth"):
        out = work / f"grasp-{name}.json"
        if not out.is_file():
            note_revision(work)
            what = ["--ground-truth", "--size", str(args.plush_size)] if name == "ground_truth" \
                else [str(runs[name])]
            sh(S3K + ["robot", "grasp", *what, "--trials", str(args.trials), "--out", str(out)])
        grasps[name] = out

    # --- the insertion agents (with --insertion-work: seed k's keypoint agent reads that work's S3K seed k)
    insertion = work / "insertion"
    if args.insertion_work:
        detectors_of = [Path(args.insertion_work).resolve() / f"s3k-seed{k}" for k in range(args.seeds)]
    elif not (insertion / "s3k.json").is_file():
        sh(S3K + ["robot", "simulate-insertion", "--out", str(insertion), "--size", str(args.insertion_size),
                  "--no-progress", "--overwrite"])
    detector = work / "insertion-s3k"
    if not args.insertion_work and not (detector / "model.pt").is_file():
        cfg = TrainConfig.from_flat(steps=args.detector_steps, threads=1, progress=False)
        cmd = S3K + ["train", str(insertion), "--out", str(detector), *cfg.to_argv()]
        run_jobs([("insertion detector", cmd + (["--resume"] if detector.exists() else []),
                   work / "insertion-s3k.cpu.json")], 1)
    agents: dict[str, list[Path]] = {"keypoints": [], "beta_vae": []}
    jobs = []
    for seed in range(args.seeds):
        for agent in agents:
            out = work / "rl" / f"{agent}-{seed}"
            agents[agent].append(out)
            progress = out / "progress.json"
            if progress.is_file() and json.loads(progress.read_text()).get("final", {}).get("env_steps") \
                    == args.agent_steps:
                continue
            out.parent.mkdir(parents=True, exist_ok=True)
            jobs.append((f"{agent} agent, seed {seed}",
                         agent_command(args, out, agent, seed, None if agent != "keypoints" else
                                       detectors_of[seed] if args.insertion_work else detector),
                         work / "rl" / f"{agent}-{seed}.cpu.json"))
    if jobs:
        note_revision(work)
    run_jobs(jobs, args.parallel)

    # --- the summary
    machine = machine_info()
    sh(S3K + ["robot", "summarize", "--out", str(results / "summary.json"),
              *[a for name, path in grasps.items()
                for a in (f"--grasp-{name.replace('_', '-')}", str(path))],
              "--rl-keypoints", *map(str, agents["keypoints"]),
              "--rl-beta-vae", *map(str, agents["beta_vae"]),
              "--machine", f"{machine['cpu']}, {machine['cpu_count']} cores"])
    summary = json.loads((results / "summary.json").read_text())
    detectors = {}
    for name, run in {**runs, **({} if args.insertion_work else {"insertion": detector})}.items():
        m = evaluate(run, insertion if name == "insertion" else plush)  # RUN-test.json, written once
        detectors[name] = {k: m.get(k) for k in ("median_mm", "rms_mm", "pck_10mm", "rms_px")}
    if args.insertion_work:  # benchmarks/accuracy.py's evaluations of the detectors, seed by seed
        tests = [json.loads(Path(f"{run}-test.json").read_text()) for run in detectors_of]
        detectors["insertion"] = {k: [t.get(k) for t in tests] for k in ("median_mm", "rms_mm", "pck_10mm")}
    cpu = {}
    for record in sorted(work.glob("**/*.cpu.json")):
        cpu[str(record.relative_to(work)).removesuffix(".cpu.json")] = round(
            json.loads(record.read_text())["cpu_minutes"], 1)
    agents_scale = ("insertion views " + (f"of the two-pass detectors of {args.insertion_work} (the "
                                          f"beta-VAE's 64 px)" if args.insertion_work else
                                          f"{args.insertion_size} px")
                    + f", {args.seeds} seeds x 2 agents x {args.agent_steps} environment steps, evaluation "
                    f"every {args.eval_every} steps over {args.eval_episodes} episodes"
                    + (f", agent options {args.agent_options!r}" if args.agent_options else ""))
    summary.update({
        "command": "python benchmarks/robot.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "git_revision": revision,
        "runs_git_revisions": sorted(set((work / "revisions.txt").read_text().split()))
        if (work / "revisions.txt").is_file() else [],
        "machine": machine,
        "scale": (f"plush {args.plush_size} px: 7 labelled frames (one per training arrangement) propagated "
                  f"to the first {args.propagate} frames of their arrangement "
                  f"({7 * args.propagate} labelled), "
                  f"the other {args.plush_unlabelled - 7 * (args.propagate - 1)} training frames unlabelled, "
                  f"{args.plush_test} test frames over the 3 held-out arrangements; detectors "
                  f"{args.detector_steps} steps; {args.trials} grasps each; {agents_scale}"),
        "agents_scale": agents_scale,
        "detectors_test": detectors,
        "cpu_minutes": cpu,
        "wall_minutes_this_invocation": round((time.time() - started) / 60, 1),
    })
    (results / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    if args.plush_work:
        from benchmarks import grasp

        grasp.main(["--plush-work", args.plush_work, "--trials", str(args.trials), "--results", str(results)])
        summary = json.loads((results / "summary.json").read_text())
    plot(summary, results / "rl-success.png")
    emit(summary)
    return 0


if __name__ == "__main__":
    with showing_library_messages():  # the library's notes and warnings, as under s3k
        raise SystemExit(main())
