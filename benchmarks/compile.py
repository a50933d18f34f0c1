"""torch.compile on the training step's network: eager against compiled, side by side in one run.

One step here is what the trainer's optimizer step costs in the network: a forward pass of the U-Net over the
step's images (``--frames`` labelled + ``--frames`` unlabelled frames x 4 cameras at ``--size`` px, the
default network of ``s3k train``), a loss on the heatmaps, backward, and Adam. Data loading, augmentation and
the pseudo-labels are left out: they are the same either way. The two variants alternate step by step
(eager, compiled, eager, ...) after each has been warmed up (the compiled one's first steps include its
compilation, reported as ``compile_s``), so load on the machine falls on both alike; the figure is the ratio
of their median step times.

Example::

    python benchmarks/compile.py --size 96 --threads 1
    python benchmarks/compile.py --size 128 --device cuda --precision bfloat16

The last line printed is one JSON object.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import emit  # noqa: E402
from s3k.cli import showing_library_messages  # noqa: E402
from s3k.model import UNet, UNetConfig  # noqa: E402

KEYPOINTS = 3


def make_step(net: torch.nn.Module, device: torch.device, dtype: torch.dtype | None):
    """One optimizer step of ``net`` (Adam) on a batch: heatmap log-softmax against fixed targets."""
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)

    def loss_of(images: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        with torch.autocast(device.type, dtype=dtype, enabled=dtype is not None):
            logits = net(images)
        logp = torch.log_softmax(logits.float().flatten(2), dim=-1)
        return -(target.flatten(2) * logp).sum(-1).mean()

    return opt, loss_of


def timed_step(opt, loss_fn, images, target, device) -> float:
    t0 = time.perf_counter()
    opt.zero_grad(set_to_none=True)
    loss = loss_fn(images, target)
    loss.backward()
    opt.step()
    if device.type == "cuda":
        torch.cuda.synchronize()
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--size", type=int, default=96, help="image size in pixels (default 96)")
    p.add_argument("--frames", type=int, default=4, help="labelled and unlabelled frames a step (default 4)")
    p.add_argument("--steps", type=int, default=20, help="timed steps of each variant (default 20)")
    p.add_argument("--warmup", type=int, default=3, help="untimed steps of each after compiling (default 3)")
    p.add_argument("--threads", type=int, default=0, help="torch threads (default: torch's choice)")
    p.add_argument("--device", default="cpu", help="torch device (default cpu)")
    p.add_argument("--precision", choices=("float32", "bfloat16"), default="float32",
                   help="autocast precision of the network (default float32)")
    p.add_argument("--mode", default="default", help="torch.compile mode (default, reduce-overhead, ...)")
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    dtype = torch.bfloat16 if args.precision == "bfloat16" else None
    torch.manual_seed(0)
    cfg = UNetConfig()
    eager = UNet(KEYPOINTS, cfg).to(device).to(memory_format=torch.channels_last)
    compiled_net = UNet(KEYPOINTS, cfg).to(device).to(memory_format=torch.channels_last)
    compiled_net.load_state_dict(eager.state_dict())
    n = 2 * args.frames * 4
    images = torch.rand(n, 3, args.size, args.size, device=device)
    images = images.contiguous(memory_format=torch.channels_last)
    with torch.no_grad():
        shape = eager(images[:1]).shape
    target = torch.softmax(torch.randn(n, *shape[1:], device=device).flatten(2), -1).view(n, *shape[1:])

    opt_e, loss_e = make_step(eager, device, dtype)
    opt_c, loss_c = make_step(compiled_net, device, dtype)
    loss_c = torch.compile(loss_c, mode=args.mode)
    t0 = time.perf_counter()
    timed_step(opt_c, loss_c, images, target, device)  # compiles forward and backward
    compile_s = time.perf_counter() - t0
    for _ in range(args.warmup):
        timed_step(opt_e, loss_e, images, target, device)
        timed_step(opt_c, loss_c, images, target, device)
    eager_s, compiled_s = [], []
    for _ in range(args.steps):
        eager_s.append(timed_step(opt_e, loss_e, images, target, device))
        compiled_s.append(timed_step(opt_c, loss_c, images, target, device))
    e, c = statistics.median(eager_s), statistics.median(compiled_s)
    print(f"eager {e * 1e3:.1f} ms a step, compiled {c * 1e3:.1f} ms ({e / c:.2f}x); compiling took "
          f"{compile_s:.0f} s", file=sys.stderr)
    emit({"benchmark": "compile", "size": args.size, "images_per_step": n, "device": str(device),
          "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
          "precision": args.precision, "mode": args.mode, "threads": torch.get_num_threads(),
          "steps_timed": args.steps, "eager_step_s": e, "compiled_step_s": c, "speedup": e / c,
          "compile_s": compile_s,
          "steps_to_repay_compiling": compile_s / (e - c) if e > c else None})
    return 0


if __name__ == "__main__":
    with showing_library_messages():  # the library's notes and warnings, as under s3k
        sys.exit(main())
