"""Training speed: seconds per S3K step, FLOP/s as a fraction of matmul FLOP/s, data-loading share.

Targets: docs/method.md#performance-targets.

One step = a labelled batch and an unlabelled batch (default 4 + 4 frames of 4 cameras), each image augmented
(random similarity + photometric, in torch), one forward pass over all images, supervised + self-supervised
losses, backward, Adam. The run goes through ``s3k.train.train`` itself, on a small simulated box dataset
rendered at ``--size`` (or on ``--data``), with the self-supervised term on from the first step.

``flop_fraction`` = (3 x forward convolution FLOPs of one step, the usual forward + backward estimate) /
(median step time) / (this machine's float32 matmul FLOP/s, measured in the same run with the same threads).
``loader_fraction`` = median share of the step spent drawing, converting and augmenting the batches.
``conv_only_fraction`` = the same numerator over the time of the network's convolutions alone, each timed
forward + backward on its own (``benchmarks.common.conv_ceiling``): the ceiling of ``flop_fraction`` for this
network on this machine, reached only if nothing but the convolutions took time. ``gemm_fraction`` = the
convolutions' forward FLOPs over the time of plain matrix products of their im2col shapes. Per-layer figures
are printed above the JSON line (``--no-layers`` skips them).

``--train-options`` sets more of ``s3k train``'s options (``'--encoder efficientnet-lite0 --encoder-stride 8
--precision auto'``); ``cpu_s_per_step`` is the process's CPU seconds over the timed steps, ``peak_rss_mb``
its peak resident memory (the data, the network and a step's activations).

Example::

    python benchmarks/train_step.py --size 128
    python benchmarks/train_step.py --size 192 --threads 1 --data DATA --no-layers \
        --train-options '--encoder efficientnet-lite0 --encoder-stride 8 --precision auto'

The last line printed is one JSON object.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import conv_ceiling, emit, matmul_flops  # noqa: E402
from s3k.cli import showing_library_messages  # noqa: E402
from s3k.config import TrainConfig, default_of  # noqa: E402
from s3k.model import UNetConfig, count_conv_flops  # noqa: E402
from s3k.networks import build_network  # noqa: E402
from s3k.train import train  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", type=int, default=128, help="image size in pixels (default 128)")
    parser.add_argument("--steps", type=int, default=30, help="timed steps (default 30)")
    parser.add_argument("--warmup", type=int, default=5, help="untimed first steps (default 5)")
    batch = default_of("batch_labelled")
    parser.add_argument("--batch", type=int, default=batch,
                        help=f"labelled and unlabelled frames per step (default {batch})")
    parser.add_argument("--data", default=None, help="dataset folder (default: render a small box dataset)")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (default: torch's choice)")
    parser.add_argument("--train-options", default="",
                        help="more `s3k train` options, e.g. '--encoder efficientnet-lite0 --precision auto'")
    parser.add_argument("--no-layers", action="store_true",
                        help="skip timing the convolutions one by one (conv_only_fraction, gemm_fraction)")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)

    with tempfile.TemporaryDirectory() as tmp:
        data = args.data
        if data is None:
            os.environ.setdefault("MUJOCO_GL", "osmesa")
            from s3k.sim.generate import SimulateConfig, simulate

            data = Path(tmp) / "box"
            simulate(SimulateConfig(scene="box", size=args.size, labelled=10, unlabelled=40, test=0, seed=0),
                     data, progress=False)
        cfg = TrainConfig.from_flat(steps=args.warmup + args.steps, batch_labelled=args.batch,
                                    batch_unlabelled=args.batch, warmup_steps=0, ramp_steps=0, val_every=0,
                                    checkpoint_every=10**9, progress=False, threads=args.threads, seed=0,
                                    image_size=args.size).with_options(args.train_options.split(),
                                                                       where="--train-options")
        times: list[tuple[float, float]] = []
        cpu: dict[int, float] = {}

        def record(step: int, terms: dict) -> None:
            if step > args.warmup:
                times.append((terms["time_step_s"], terms["time_data_s"]))
            if step in (args.warmup, args.warmup + args.steps):
                cpu[step] = time.process_time()

        peak_before = matmul_flops(seconds=1.0)
        result = train(data, Path(tmp) / "run", cfg, progress=record)
        peak_after = matmul_flops(seconds=1.0)

    step_s = statistics.median(t for t, _ in times)
    loader_fraction = statistics.median(d / t for t, d in times)
    meta = result.meta
    W, H = meta.image_size
    C = len(meta.cameras)
    n_images = 2 * args.batch * C
    net = build_network(len(meta.keypoints), UNetConfig.from_dict(meta.model))
    fwd = count_conv_flops(net, torch.rand(n_images, 3, H, W))
    peak = max(peak_before, peak_after)
    flops_per_step = 3 * fwd
    ceiling: dict = {}
    if not args.no_layers:
        images = torch.rand(n_images, 3, H, W).contiguous(memory_format=torch.channels_last)
        layers = conv_ceiling(net.to(memory_format=torch.channels_last), images, peak)
        for layer in layers.pop("layers"):
            print(f"{layer['layer']:28s} train {1e3 * layer['train_s']:7.2f} ms  fraction "
                  f"{layer['train_fraction']:.2f}   im2col GEMM fraction {layer['gemm_fraction']:.2f}")
        ceiling = {**layers, "conv_share_of_step": layers["conv_train_s"] / step_s}
    emit({
        "benchmark": "train_step",
        "size": args.size,
        "image_size": [W, H],
        "images_per_step": n_images,
        "parameters": sum(p.numel() for p in net.parameters()),
        "steps_timed": len(times),
        "step_s": step_s,
        "step_s_mean": statistics.fmean(t for t, _ in times),
        "train_options": args.train_options,
        "cpu_s_per_step": (cpu[args.warmup + args.steps] - cpu[args.warmup]) / args.steps
        if len(cpu) == 2 else None,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "loader_fraction": loader_fraction,
        "train_flops_per_step": flops_per_step,
        "achieved_flops": flops_per_step / step_s,
        "matmul_flops": peak,
        "flop_fraction": flops_per_step / step_s / peak,
        **ceiling,
    })
    return 0


if __name__ == "__main__":
    with showing_library_messages():  # the library's notes and warnings, as under s3k
        sys.exit(main())
