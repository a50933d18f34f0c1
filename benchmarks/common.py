"""Shared helpers of the benchmarks: what machine a figure was measured on, its matmul peak, JSON output, and
the network, frames and interleaved timing rounds of the two inference benchmarks.

Every benchmark ends with `emit(result)`, which prints the result and the machine description as one JSON
line, the last line of its output, so that scripts can collect figures with ``tail -n 1``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shlex
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from s3k.experiments.accuracy import without_notes


def _cpu_model() -> str:
    """The CPU's marketing name (from /proc/cpuinfo on Linux, else what `platform` knows)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _cpu_flags() -> list[str]:
    """The vector extensions that matter for float32 throughput (AVX2/AVX-512/AMX), if known."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.lower().startswith("flags"):
                    flags = line.split(":", 1)[1].split()
                    keep = ("avx2", "fma", "avx512f", "avx512_bf16", "avx512_fp16", "amx_tile", "amx_bf16")
                    return [x for x in keep if x in flags]
    except OSError:
        pass
    return []


def _memory_gb() -> float | None:
    try:
        with open("/proc/meminfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("MemTotal:"):
                    return round(int(line.split()[1]) / 2**20, 1)
    except OSError:
        pass
    return None


def machine_info() -> dict[str, Any]:
    """A description of this machine and software stack, without the hostname or any user name.

    Returns:
        dict with the CPU model and vector flags, logical cores (and those this process may use), memory,
        torch/numpy/python versions, torch's intra-op thread count, the OS, and the 1-minute load average at
        call time (a busy shared machine explains a low figure).
    """
    info: dict[str, Any] = {
        "cpu": _cpu_model(),
        "cpu_flags": _cpu_flags(),
        "cpu_count": os.cpu_count(),
        "cpu_affinity": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "memory_gb": _memory_gb(),
        "torch": torch.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
        "torch_threads": torch.get_num_threads(),
        "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
        "os": f"{platform.system()} {platform.release()} {platform.machine()}",
    }
    if hasattr(os, "getloadavg"):
        info["load_avg_1min"] = round(os.getloadavg()[0], 2)
    cv2 = sys.modules.get("cv2")
    if cv2 is not None:
        info["opencv"] = cv2.__version__
    return info


_ROOT = Path(__file__).resolve().parents[1]


def t_interval(x: list[float]) -> list[float] | None:
    """95% t-interval of the mean of ``x`` (None for fewer than 2 values)."""
    if len(x) < 2:
        return None
    from scipy import stats

    m, se = float(np.mean(x)), float(np.std(x, ddof=1) / math.sqrt(len(x)))
    h = float(stats.t.ppf(0.975, len(x) - 1)) * se
    return [m - h, m + h]


def paired(a: np.ndarray, b: np.ndarray) -> dict[str, Any]:
    """``a - b`` (two ``(frames, points)`` error arrays, NaN where none) over the points both have: the mean,
    its 95% bootstrap interval over frames, the two medians and the count (None figures without one)."""
    from s3k.base.label_reference import bootstrap_ci

    both = np.isfinite(a) & np.isfinite(b)
    if not both.any():
        return {"mean_diff_mm": None, "ci95_mm": None, "median_mm": None, "points": 0}
    diff = np.where(both, a - b, np.nan)
    return {"mean_diff_mm": float(np.nanmean(diff)), "ci95_mm": bootstrap_ci(diff),
            "median_mm": [float(np.median(a[both])), float(np.median(b[both]))], "points": int(both.sum())}


def git_revision() -> str:
    """HEAD of the repository these benchmarks are in, ``+modified`` when tracked files differ from it; run
    from a ``git archive`` of a commit (no repository), the environment's ``S3K_GIT_REVISION``, else
    ``unknown``."""
    if not (_ROOT / ".git").exists() and os.environ.get("S3K_GIT_REVISION"):
        return os.environ["S3K_GIT_REVISION"]
    try:
        rev = subprocess.run(["git", "rev-parse", "HEAD"], cwd=_ROOT, capture_output=True, text=True,
                             check=True)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=_ROOT,
                               capture_output=True, text=True).stdout.strip()
        return rev.stdout.strip() + ("+modified" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return os.environ.get("S3K_GIT_REVISION", "unknown")


def matmul_flops(seconds: float = 2.0, sizes: tuple[int, ...] = (256, 512, 1024, 2048)) -> float:
    """This machine's float32 matmul throughput with torch and its current thread count, in FLOP/s.

    Square matmuls of each size are timed repeatedly within a share of ``seconds``; the best rate over sizes
    and repeats is returned (``2 n^3`` FLOPs per product), the figure other benchmarks compare against.

    Args:
        seconds: total time budget (at least one timed product per size is always run).
        sizes: square matrix sizes to try.

    Returns:
        FLOP/s, a float.
    """
    gen = torch.Generator().manual_seed(0)
    best = 0.0
    share = seconds / max(1, len(sizes))
    for n in sizes:
        a = torch.randn(n, n, generator=gen)
        b = torch.randn(n, n, generator=gen)
        out = torch.empty(n, n)
        torch.mm(a, b, out=out)  # warm-up: thread pool, packing buffers
        flops = 2.0 * n**3
        start = time.perf_counter()
        while True:
            t0 = time.perf_counter()
            torch.mm(a, b, out=out)
            dt = time.perf_counter() - t0
            if dt > 0:
                best = max(best, flops / dt)
            if time.perf_counter() - start >= share:
                break
    return best


def _median_time(fn, repeats: int) -> float:
    fn()  # warm-up: oneDNN primitive creation, packing buffers
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def conv_ceiling(net: torch.nn.Module, images: torch.Tensor, peak: float, repeats: int = 7) -> dict[str, Any]:
    """How fast the network's convolutions alone run for training, layer by layer, against ``peak``.

    Each ``nn.Conv2d`` of ``net`` (a copy, same weights and memory format) is timed on its own, forward and
    backward on an input of the shape it sees in ``net(images)`` (no input gradient for the first layer, as in
    training). ``conv_only_fraction`` is ``3 x`` the forward FLOPs of all layers (the numerator of a training
    step's ``flop_fraction``) over the summed layer times over ``peak``: the ``flop_fraction`` a step would
    reach if everything but the convolutions took no time. ``gemm_fraction`` times each layer's forward as the
    plain matrix product of its im2col form, ``(N h w, C_in k k) @ (C_in k k, C_out)``, the shape a GEMM
    library sees for these channel counts, without the im2col copy.

    Returns:
        ``{"layers": [...], "conv_only_fraction", "gemm_fraction", "conv_train_s"}``.
    """
    import copy

    from s3k.model import conv_layers

    seen = conv_layers(net, images)
    gen = torch.Generator().manual_seed(0)
    layers = []
    for i, (mod, in_shape, out_shape) in enumerate(seen):
        conv = copy.deepcopy(mod).train()
        x = torch.rand(in_shape, generator=gen).contiguous(memory_format=torch.channels_last)
        x.requires_grad_(i > 0)
        grad = torch.rand(out_shape, generator=gen).contiguous(memory_format=torch.channels_last)
        kh, kw = mod.kernel_size
        k = mod.in_channels // mod.groups * kh * kw
        m = out_shape[0] * out_shape[2] * out_shape[3]
        fwd = 2 * k * out_shape[1] * m

        def train_pass(conv=conv, x=x, grad=grad) -> None:
            conv.zero_grad(set_to_none=True)
            x.grad = None
            conv(x).backward(grad)

        a = torch.rand(m, k, generator=gen)
        b = torch.rand(k, out_shape[1], generator=gen)
        t_train = _median_time(train_pass, repeats)
        t_gemm = _median_time(lambda a=a, b=b: torch.mm(a, b), repeats)
        layers.append({
            "layer": f"{mod.in_channels}->{mod.out_channels} k{kh} s{mod.stride[0]} "
                     f"out {out_shape[2]}x{out_shape[3]}",
            "forward_flops": fwd, "train_s": t_train, "train_fraction": 3 * fwd / t_train / peak,
            "gemm_s": t_gemm, "gemm_fraction": fwd / t_gemm / peak,
        })
    fwd_total = sum(layer["forward_flops"] for layer in layers)
    train_s = sum(layer["train_s"] for layer in layers)
    gemm_s = sum(layer["gemm_s"] for layer in layers)
    return {"layers": layers, "conv_train_s": train_s, "conv_only_fraction": 3 * fwd_total / train_s / peak,
            "gemm_fraction": fwd_total / gemm_s / peak}


def add_network_options(p: argparse.ArgumentParser, threads_help: str) -> None:
    """The options of the inference benchmarks: the frames (size, cameras, keypoints), the network
    (``UNetConfig`` overrides, see :func:`build_network`), the confidence scale and the timing."""
    from s3k.config import TrainConfig

    p.add_argument("--size", type=int, default=128, help="square image size in pixels (default 128)")
    p.add_argument("--cameras", type=int, default=4, help="cameras per frame (default 4)")
    p.add_argument("--keypoints", type=int, default=3, help="keypoints K (default 3)")
    p.add_argument("--stride", type=int, default=None, help="heatmap stride (default: UNetConfig's)")
    p.add_argument("--channels", type=str, default=None, help="comma-separated channels per level")
    p.add_argument("--res-blocks", type=int, default=None, help="residual blocks at the bottom")
    p.add_argument("--encoder-convs", type=int, default=None, help="extra convs per encoder level")
    p.add_argument("--norm", type=str, default=None, choices=["batch", "group", "none"])
    p.add_argument("--encoder", default=None, choices=["unet", "efficientnet-lite0"],
                   help="the encoder (default: UNetConfig's, the U-Net)")
    p.add_argument("--encoder-stride", type=int, default=None, choices=[8, 16, 32],
                   help="where a pretrained encoder is cut (default: UNetConfig's)")
    sigma = TrainConfig().sigma_px()
    p.add_argument("--sigma", type=float, default=sigma,
                   help=f"target width in image pixels (confidence scale; default {sigma:g}, training's)")
    p.add_argument("--threads", type=int, default=None, help=threads_help)
    p.add_argument("--warmup", type=int, default=20, help="untimed frames first (default 20)")
    p.add_argument("--repeats", type=int, default=100, help="timed frames per round (default 100)")
    p.add_argument("--rounds", type=int, default=3,
                   help="rounds of matmul peak + timed frames, interleaved (default 3)")


def build_network(args: argparse.Namespace) -> tuple[Any, torch.nn.Module, int]:
    """Set ``--threads``, seed torch with 0 and build the untrained network of the options, in eval mode.

    Returns:
        ``(config, model, parameter count)``; ``config`` is the ``UNetConfig`` with the options' overrides.
    """
    from s3k.model import UNetConfig
    from s3k.networks import build_network as network

    if args.threads is not None:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    overrides = {
        k: v
        for k, v in {
            "stride": args.stride,
            "channels": tuple(int(c) for c in args.channels.split(",")) if args.channels else None,
            "res_blocks": args.res_blocks,
            "encoder_convs": args.encoder_convs,
            "norm": args.norm,
            "encoder": getattr(args, "encoder", None),
            "encoder_stride": getattr(args, "encoder_stride", None),
        }.items()
        if v is not None
    }
    config = UNetConfig(**overrides)
    model = network(args.keypoints, config).eval()
    return config, model, sum(q.numel() for q in model.parameters())


def random_frames(args: argparse.Namespace) -> torch.Tensor:
    """The benchmark's frame: ``uint8 (C, S, S, 3)`` noise, the same on every run."""
    gen = torch.Generator().manual_seed(0)
    return torch.randint(0, 256, (args.cameras, args.size, args.size, 3), dtype=torch.uint8, generator=gen)


def time_frames(run: Callable[[torch.Tensor], Any], frames: torch.Tensor, warmup: int,
                repeats: int) -> list[float]:
    """Seconds per frame of ``run(frames)`` for ``repeats`` frames after ``warmup`` frames."""
    times = []
    with torch.inference_mode():
        for _ in range(warmup):
            run(frames)
        for _ in range(repeats):
            t0 = time.perf_counter()
            run(frames)
            times.append(time.perf_counter() - t0)
    return times


def interleaved_rounds(pipelines: dict[str, Callable[[torch.Tensor], Any]], frames: torch.Tensor,
                       args: argparse.Namespace, matmul_seconds: float,
                       ) -> tuple[list[float], dict[str, list[list[float]]]]:
    """Time each pipeline ``args.repeats`` frames per round, ``args.rounds`` rounds (at least one), each
    after a matmul peak: the machine may be shared, so the peaks and the frames are measured side by side
    and compared by their medians. Every pipeline first runs ``args.warmup`` untimed frames.

    Returns:
        ``(peaks, times)``: the matmul FLOP/s of each round, and per pipeline the seconds per frame of
        each round.
    """
    peaks: list[float] = []
    times: dict[str, list[list[float]]] = {name: [] for name in pipelines}
    for run in pipelines.values():
        time_frames(run, frames, args.warmup, 0)
    for _ in range(max(1, args.rounds)):
        peaks.append(matmul_flops(seconds=matmul_seconds))
        for name, run in pipelines.items():
            times[name].append(time_frames(run, frames, 2, args.repeats))
    return peaks, times


def network_summary(args: argparse.Namespace, config: Any, params: int, flops_per_frame: float) -> str:
    """The first printed line of an inference benchmark: frames, heatmap, network and threads."""
    S, h = args.size, args.size // config.stride
    return (f"{S}x{S} px, {args.cameras} cameras, K={args.keypoints}, heatmap {h}x{h}, {params} params, "
            f"{flops_per_frame / 1e6:.1f} MFLOP/frame, threads {torch.get_num_threads()}")


def network_fields(args: argparse.Namespace, config: Any, params: int, flops_per_frame: float,
                   matmul: float) -> dict[str, Any]:
    """The result fields the inference benchmarks share: the matmul peak, the network and its frames."""
    return {"matmul_flops": matmul, "flops_per_frame": flops_per_frame, "size": args.size,
            "cameras": args.cameras, "keypoints": args.keypoints, "params": params,
            "config": config.to_dict()}


def _jsonable(x: Any) -> Any:
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    if isinstance(x, torch.Tensor) and x.numel() == 1:
        return x.item()
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    return x


def emit(result: dict[str, Any]) -> None:
    """Print ``result`` plus ``machine`` (`machine_info`, unless given) as one JSON line, flushed.

    Call it last: the JSON line is meant to be the final line of a benchmark's output.
    """
    out = dict(result)
    out.setdefault("machine", machine_info())
    sys.stdout.flush()
    print(json.dumps(_jsonable(out), default=str, separators=(",", ":")), flush=True)


def write_and_emit(result: dict[str, Any], out: str | Path | None) -> None:
    """Write ``result`` with ``machine`` to the JSON file ``out`` (when given, folders made), then
    :func:`emit` it."""
    result = {**result, "machine": result.get("machine") or machine_info()}
    if out:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        Path(out).write_text(json.dumps(_jsonable(result), indent=2, default=str) + "\n")
    emit(result)



def add_run_data_arguments(p) -> None:
    """The arguments of a benchmark that reads run folders on their datasets: ``RUN DATA`` pairs,
    ``--split``, ``--out`` and ``--notes``."""
    p.add_argument("pairs", nargs="+", metavar="RUN DATA", help="run folders, each followed by its dataset")
    p.add_argument("--split", default="test", help="split to read (default test)")
    p.add_argument("--out", default=None, help="JSON file to write")
    p.add_argument("--notes", default=None, help="text kept in the JSON, e.g. how the runs were trained")


def run_data_pairs(p, args) -> list[tuple[str, str]]:
    """``[(run, data), ...]`` of :func:`add_run_data_arguments`' pairs (an odd count is a usage error)."""
    if len(args.pairs) % 2:
        p.error("give each RUN followed by its DATA")
    return list(zip(args.pairs[::2], args.pairs[1::2]))


def split_store(data: str | Path, split: str) -> tuple[Any, Any]:
    """``(dataset, frame store)`` of ``data``'s ``split`` with its 3D points, nothing preloaded: what a
    run-reading benchmark evaluates a detector on (``s3k.inference.evaluate.evaluate_store``)."""
    from s3k.data import Dataset
    from s3k.data.frames import FrameStore
    from s3k.inference.predict import split_frames

    ds = Dataset.open(data, cache="none")
    return ds, FrameStore(ds, split_frames(ds, split), preload_mb=0, points=True)


def write_runs(script: str, argv: list[str] | None, args, runs: dict[str, Any],
               extra: dict[str, Any] | None = None) -> None:
    """Write and print the result of a run-reading benchmark: its command (notes kept apart), revision,
    split, ``runs``, ``extra`` (e.g. figures over the runs) and notes (:func:`write_and_emit` to
    ``args.out``)."""
    given = sys.argv[1:] if argv is None else argv
    result = {"command": shlex.join(["python", script, *without_notes(given)]),
              "git_revision": git_revision(), "split": args.split, "runs": runs, **(extra or {}),
              **({"notes": args.notes} if args.notes else {})}
    write_and_emit(result, args.out)

# ---------------------------------------------------------------------------------------------- crop studies
#: The figures the crop benchmarks (oracle_crops.py, two_pass.py) report per model and split.
CROP_FIGURES = ("rms_px", "median_mm", "rms_mm", "pck_5mm", "pck_10mm", "mm_per_px")


def ensure_box_render(work: Path, size: int, unlabelled: int, test: int) -> Path:
    """``work/box{size}``: the box scene (10 labelled frames) rendered once, reused when it exists."""
    render = work / f"box{size}"
    if not (render / "s3k.json").is_file():
        from s3k.sim.generate import SimulateConfig, simulate

        simulate(SimulateConfig("box", size=size, labelled=10, unlabelled=unlabelled, test=test), render,
                 workers=1, progress=False, overwrite=True)
    return render


def train_side_by_side(jobs: dict[str, tuple[Path, Path, Any]]) -> None:
    """Train every job ``(dataset, run folder, TrainConfig)`` at once, each an ``s3k train`` process of one
    thread with the options of its configuration; a job whose run is complete is skipped, one with a folder
    is resumed."""
    from s3k.run_folder import RunFolder

    procs = {}
    for name, (data, out, cfg) in jobs.items():
        if RunFolder(out).is_complete():
            continue
        cmd = [sys.executable, "-m", "s3k.cli", "train", str(data), "--out", str(out),
               *cfg.replace(threads=1, progress=False).to_argv()]
        if out.exists():
            cmd.append("--resume")
        env = dict(os.environ, OMP_NUM_THREADS="1")
        procs[name] = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, env=env)
    for name, proc in procs.items():
        if proc.wait() != 0:
            raise SystemExit(f"training {name} failed (exit {proc.returncode})")


def crop_figures(metrics: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(CROP_FIGURES of an evaluate metrics dict, {keypoint: median_mm})``."""
    return ({k: metrics[k] for k in CROP_FIGURES},
            {kp: d["median_mm"] for kp, d in metrics["per_keypoint"].items()})


def finish(result: dict[str, Any], started: float, out: str | None) -> None:
    """Add the call's minutes, write ``result`` to ``out`` (atomically, if given) and print it last."""
    result["minutes_this_call"] = (time.perf_counter() - started) / 60
    if out:
        from s3k.base.fileio import atomic_write_json

        atomic_write_json(result, out)
    emit(result)


def fine_tune_args(data, base, out, steps: int, threads: int = 1, lr: float | None = None,
                   seed: int | None = None, validate: bool = True) -> list[str]:
    """``train DATA --out OUT --init-from BASE --steps STEPS --resume``: BASE's configuration at its final
    learning rates, each pass STEPS (at ``lr`` and ``seed`` instead where given), validated on labelled frames
    (not at all without ``validate``). ``--resume`` makes the same command start OUT, continue it from its
    own checkpoint once begun (the checkpoint, not BASE's network: tests/train/test_finetune.py) or keep it
    once finished."""
    args = ["train", str(data), "--out", str(out), "--init-from", str(base), "--steps", str(steps),
            "--threads", str(threads), "--no-progress", "--resume"]
    args += ["--val-split", "labelled"] if validate else ["--val-every", "0"]
    if lr is not None:
        args += ["--lr", str(lr)]
    if seed is not None:
        args += ["--seed", str(seed)]
    return args


def fine_tune_argv(data, base, out, steps: int, threads: int = 1) -> list[str]:
    """:func:`fine_tune_args` as a command line of this Python."""
    import sys

    return [sys.executable, "-m", "s3k.cli", *fine_tune_args(data, base, out, steps, threads)]
