"""What a CPU without native bfloat16, or without AVX-512, takes: CPU seconds per training step of a preset's
two networks (the coarse pass and the refining pass) in bfloat16 and float32, and on an AVX2-only CPU emulated
on this one.

Each setting runs as its own process (the instruction-set limits are read once, at start), in rounds
(A B C D, A B C D, ...), so that the load of a shared machine falls on all alike; each process trains both
networks of ``--preset`` (their configurations from ``TrainConfig.coarse()`` and ``TrainConfig.refining()``:
the coarse pass on whole frames at ``coarse_size`` px, the refining pass at ``crop_size`` px) for
``--warmup`` + ``--steps`` steps with the self-supervised term on from the first step (as in the schedule's
later steps) and one torch thread, and reports the median of the timed steps' CPU times (the process's
``time.process_time`` from one step to the next; the mean is recorded beside it). The settings:

- ``native``: ``--precision`` of the preset (``auto``: bfloat16 where this process computes it natively);
- ``avx512-bf16``: the same with oneDNN limited to AVX512-BF16 (``ONEDNN_MAX_CPU_ISA=AVX512_CORE_BF16``):
  a CPU with AVX512-BF16 but no AMX, such as the AMD EPYC the headline's CPU-minutes were measured on,
  when this CPU has AMX;
- ``float32``: float32 on this CPU (an AVX-512 CPU without bfloat16 trains so);
- ``avx2-float32``: float32 with PyTorch's kernels at AVX2 (``ATEN_CPU_CAPABILITY=avx2``), oneDNN at AVX2
  (``ONEDNN_MAX_CPU_ISA=AVX2``) and MKL at AVX2 (``MKL_ENABLE_INSTRUCTIONS=AVX2``): an AVX2-only CPU of
  this one's clock and caches, emulated.

Each process records what it ran on: ``torch.backends.cpu.get_cpu_capability()``, oneDNN's instruction set
and the implementation of a convolution in its arithmetic (from oneDNN's verbose output), and what
``--precision auto`` resolves to there. The figures are the medians over rounds of each setting's CPU
seconds per step, and the ratios to ``native`` (and to ``avx512-bf16``) taken within each round, with the
rounds' range. ``estimate_cpu_minutes`` scales the stage minutes of ``--headline`` (a summary.json of
``benchmarks/accuracy.py``) by the ratios to ``native``: the coarse and refining passes by their own,
the crops (float32 inference of the coarse pass in every setting) by the coarse pass's ``avx2-float32`` /
``float32`` ratio on AVX2 and 1 elsewhere; beside it, the refining pass's float32 / bfloat16 ratio measured
on the headline's own machine (``--reference``). An estimate: the emulation has this CPU's clock, caches and
memory, only its instruction sets are limited.

Example::

    python benchmarks/cpu_isa.py --out docs/results/benchmarks/cpu-isa.json   # about 7 minutes

The last line printed is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import ensure_box_render, finish, git_revision, machine_info  # noqa: E402

SETTINGS: dict[str, tuple[str | None, dict[str, str]]] = {  # name: (--precision, None: the preset's; env)
    "native": (None, {}),
    "avx512-bf16": (None, {"ONEDNN_MAX_CPU_ISA": "AVX512_CORE_BF16"}),
    "float32": ("float32", {}),
    "avx2-float32": ("float32", {"ATEN_CPU_CAPABILITY": "avx2", "ONEDNN_MAX_CPU_ISA": "AVX2",
                                 "MKL_ENABLE_INSTRUCTIONS": "AVX2"}),
}
PASSES = ("coarse", "fine")
_ISA_VARS = ("ATEN_CPU_CAPABILITY", "ONEDNN_MAX_CPU_ISA", "DNNL_MAX_CPU_ISA", "MKL_ENABLE_INSTRUCTIONS")


# ------------------------------------------------------------------------------------------ one setting
def _pass_configs(preset_name: str, precision: str | None, steps: int, threads: int) -> dict:
    from s3k.train.presets import preset

    cfg = preset(preset_name)
    if precision is not None:
        cfg = cfg.replace(precision=precision)
    cfg = cfg.replace(steps=steps, coarse_steps=steps, val_every=0, warmup_steps=0, ramp_steps=0,
                      checkpoint_every=10**9, progress=False, threads=threads, seed=0)
    crop = int(cfg.passes.crop_size)
    return {"coarse": cfg.coarse(), "fine": cfg.refining(crop).replace(image_size=crop)}


def _onednn_probe(arithmetic: str) -> None:
    """One convolution forward and backward in ``arithmetic`` with oneDNN's verbose output on (to stdout)."""
    import torch

    x = torch.rand(4, 16, 48, 48, requires_grad=True)
    w = torch.rand(16, 16, 3, 3, requires_grad=True)
    dtype = torch.bfloat16 if arithmetic == "bfloat16" else None
    with torch.backends.mkldnn.verbose(torch.backends.mkldnn.VERBOSE_ON):
        with torch.autocast("cpu", dtype=dtype, enabled=dtype is not None):
            y = torch.nn.functional.conv2d(x, w, padding=1)
        y.float().sum().backward()
    sys.stdout.flush()


def child(args: argparse.Namespace) -> None:
    """Train both passes in this process's setting and write CPU seconds per step to ``args.child_out``."""
    import torch

    from s3k.detector import training_precision
    from s3k.detector.cpu import isa_limits
    from s3k.train import train

    precision, _ = SETTINGS[args.child]
    cfgs = _pass_configs(args.preset, precision, args.warmup + args.steps, args.threads)
    out: dict = {"setting": args.child, "isa_limits": isa_limits(),
                 "auto_resolves_to": training_precision("auto", torch.device("cpu")),
                 "env": {k: os.environ[k] for k in _ISA_VARS if k in os.environ}}
    for name in PASSES:
        marks: dict[int, float] = {}

        def mark(step: int, terms: dict, marks=marks) -> None:
            if step >= args.warmup:
                marks[step] = time.process_time()

        with tempfile.TemporaryDirectory() as tmp:
            train(args.data, Path(tmp) / "run", cfgs[name], progress=mark)
        steps = [marks[s + 1] - marks[s] for s in range(args.warmup, args.warmup + args.steps)]
        # the median step: a step that another process's burst on the shared core slowed is left out
        out[name] = {"cpu_s_per_step": statistics.median(steps),
                     "cpu_s_per_step_mean": statistics.fmean(steps),
                     "arithmetic": training_precision(cfgs[name].precision, torch.device("cpu"))}
    _onednn_probe(out["fine"]["arithmetic"])
    Path(args.child_out).write_text(json.dumps(out))


# ------------------------------------------------------------------------------------------ the rounds
def _onednn_seen(stdout: str) -> dict:
    """oneDNN's instruction set and the convolutions' implementations from its verbose lines."""
    isa, convs = None, set()
    for line in stdout.splitlines():
        fields = line.split(",")
        if not line.startswith("onednn_verbose"):
            continue
        if "info" in fields and any(f.startswith("isa:") for f in fields):
            isa = next(f for f in fields if f.startswith("isa:"))[4:]
        elif "exec" in fields and "convolution" in fields:
            convs.add(fields[fields.index("convolution") + 1])
    return {"onednn_isa": isa, "convolution_impl": sorted(convs)}


def _run_setting(name: str, args: argparse.Namespace, data: Path, work: Path) -> dict:
    _, env_extra = SETTINGS[name]
    env = {k: v for k, v in os.environ.items() if k not in _ISA_VARS}
    env.update(env_extra, OMP_NUM_THREADS=str(args.threads))
    result = work / f"{name}.json"
    cmd = [sys.executable, os.path.abspath(__file__), "--child", name, "--data", str(data), "--preset",
           args.preset, "--steps", str(args.steps), "--warmup", str(args.warmup), "--threads",
           str(args.threads), "--child-out", str(result)]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"setting {name} failed (exit {proc.returncode}):\n{proc.stderr[-3000:]}")
    return {**json.loads(result.read_text()), **_onednn_seen(proc.stdout)}


def _ratios(rounds: list[dict], to: str) -> dict:
    out: dict = {}
    for name in SETTINGS:
        out[name] = {}
        for p in PASSES:
            r = [rd[name][p]["cpu_s_per_step"] / rd[to][p]["cpu_s_per_step"] for rd in rounds]
            out[name][p] = {"median": statistics.median(r), "min": min(r), "max": max(r)}
    return out


def _estimate(headline: Path, reference: Path | None, to_native: dict) -> dict:
    """The headline's stage minutes (S3K, per model) scaled by the ratios to ``native`` (module docstring),
    with the refining pass's float32 / bfloat16 CPU-time ratio measured on the headline's machine itself
    (``reference``), to set beside this machine's."""
    summary = json.loads(headline.read_text())
    stages = {k: summary["stages"]["train_s3k"][k]["cpu_min"] for k in ("coarse", "crops", "fine")}
    out: dict = {"headline": str(headline), "headline_machine": summary.get("machine"),
                 "headline_stage_cpu_min": stages, "basis": "ratio_to_native"}
    for name in ("float32", "avx2-float32"):
        crops = (to_native[name]["coarse"]["median"] / to_native["float32"]["coarse"]["median"]
                 if name == "avx2-float32" else 1.0)
        est = {"coarse": stages["coarse"] * to_native[name]["coarse"]["median"],
               "crops": stages["crops"] * crops,
               "fine": stages["fine"] * to_native[name]["fine"]["median"]}
        total = sum(est.values())
        out[name] = {**est, "total": total, "times_headline": total / sum(stages.values())}
    if reference is not None and reference.is_file():
        seeds = json.loads(reference.read_text())["seeds"]
        out["reference_fine_float32_ratio"] = {
            "file": str(reference),
            "per_seed": {s: v["float32"]["refining_cpu_minutes"] / v["bfloat16"]["refining_cpu_minutes"]
                         for s, v in seeds.items()},
            "this_machine": to_native["float32"]["fine"]["median"]}
    return out


def parent(args: argparse.Namespace) -> None:
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.work or tmp)
        from s3k.train.presets import preset

        crop = int(preset(args.preset).passes.crop_size)
        data = Path(args.data) if args.data else ensure_box_render(work, crop, unlabelled=40, test=0)
        rounds = []
        for r in range(args.rounds):
            rounds.append({name: _run_setting(name, args, data, work) for name in SETTINGS})
            print(f"round {r + 1}: " + ", ".join(
                f"{n} " + "/".join(f"{rounds[-1][n][p]['cpu_s_per_step']:.3f}" for p in PASSES)
                for n in SETTINGS) + " CPU s per step (coarse/fine)", flush=True)
    per_step = {n: {p: statistics.median(rd[n][p]["cpu_s_per_step"] for rd in rounds) for p in PASSES}
                for n in SETTINGS}
    to_native, to_bf16 = _ratios(rounds, "native"), _ratios(rounds, "avx512-bf16")
    result = {
        "benchmark": "cpu_isa",
        "command": "python benchmarks/cpu_isa.py " + " ".join(sys.argv[1:]),
        "git_revision": git_revision(),
        "machine": machine_info(),
        "preset": args.preset, "steps_timed": args.steps, "warmup_steps": args.warmup,
        "threads": args.threads, "rounds": args.rounds,
        "settings": {n: {"precision": p or "preset", "env": e, **{k: rounds[0][n][k] for k in (
            "isa_limits", "auto_resolves_to", "onednn_isa", "convolution_impl")},
            "arithmetic": {p_: rounds[0][n][p_]["arithmetic"] for p_ in PASSES}}
            for n, (p, e) in SETTINGS.items()},
        "cpu_s_per_step": per_step,
        "ratio_to_native": to_native,
        "ratio_to_avx512_bf16": to_bf16,
        "per_round": [{n: {p: rd[n][p]["cpu_s_per_step"] for p in PASSES} for n in SETTINGS}
                      for rd in rounds],
    }
    if args.headline:
        reference = Path(args.reference) if args.reference else None
        result["estimate_cpu_minutes"] = _estimate(Path(args.headline), reference, to_native)
    finish(result, started, args.out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--preset", default="box-headline", help="the preset whose networks are timed")
    p.add_argument("--rounds", type=int, default=5, help="rounds of all settings (default 5)")
    p.add_argument("--steps", type=int, default=10, help="timed steps of each pass (default 10)")
    p.add_argument("--warmup", type=int, default=3, help="untimed first steps of each pass (default 3)")
    p.add_argument("--threads", type=int, default=1, help="torch threads of each process (default 1)")
    p.add_argument("--data", default=None,
                   help="dataset folder (default: the box rendered at the preset's crop size, 10 labelled + "
                        "40 unlabelled frames)")
    p.add_argument("--work", default=None, help="folder for the render (default: a temporary one)")
    p.add_argument("--headline", default="docs/results/accuracy/fast/summary.json",
                   help="summary.json whose stage minutes the ratios scale ('' for none)")
    p.add_argument("--reference", default="docs/results/accuracy/fast/bf16-vs-fp32-4000.json",
                   help="the refining pass's float32 and bfloat16 CPU minutes measured on the headline's "
                        "machine ('' for none)")
    p.add_argument("--out", default=None, help="also write the JSON here")
    p.add_argument("--child", choices=list(SETTINGS), help=argparse.SUPPRESS)
    p.add_argument("--child-out", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        child(args)
    else:
        parent(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
