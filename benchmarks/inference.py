"""Inference speed: 4-view 3D keypoints from camera images, end to end, one frame at a time.

Targets: docs/method.md#performance-targets.

Per frame: C uint8 camera images (H, W, 3) -> float [0, 1] channels_last -> U-Net heatmaps (shared weights,
the C views in one batch) -> softmax means and variances -> confidence weights -> weighted triangulation.
Timed under ``torch.inference_mode`` after warm-up; the figure is the median over repeated frames.

``flop_fraction`` is the FLOP/s achieved by the network's convolutions (counted by
``s3k.model.count_conv_flops``) over the machine's float32 matmul FLOP/s measured in the same run, with the
same threads.

Example::

    python benchmarks/inference.py --size 128

The last line printed is one JSON object (``frames_per_s``, ``flop_fraction``, machine info, ...).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import (  # noqa: E402
    add_network_options,
    build_network,
    emit,
    interleaved_rounds,
    network_fields,
    network_summary,
    random_frames,
)
from s3k.config import TrainConfig  # noqa: E402
from s3k.geometry import Cameras  # noqa: E402
from s3k.model import count_conv_flops  # noqa: E402
from s3k.readout import read_out  # noqa: E402


def look_at_rig(num_cameras: int, size: int, distance: float = 1.0) -> Cameras:
    """``(1, C)`` pinhole cameras on a ring around the origin looking at it, 60 degree field of view."""
    az = torch.linspace(0, 2 * torch.pi, num_cameras + 1)[:-1]
    el = torch.full_like(az, 0.5)
    pos = distance * torch.stack([az.cos() * el.cos(), az.sin() * el.cos(), el.sin()], dim=-1)
    z = -pos / pos.norm(dim=-1, keepdim=True)
    x = torch.linalg.cross(z, torch.tensor([0.0, 0.0, 1.0]).expand_as(z))
    x = x / x.norm(dim=-1, keepdim=True)
    R = torch.stack([x, torch.linalg.cross(z, x), z], dim=-2)
    t = -(R @ pos[..., None])[..., 0]
    f = (size / 2) / torch.tan(torch.tensor(torch.pi / 6))
    K = torch.tensor([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1]])
    return Cameras(K.expand(1, num_cameras, 3, 3), None, R[None], t[None])


def make_pipeline(model: torch.nn.Module, cams: Cameras, stride: int, sigma: float, channels_last: bool,
                  max_residual_px: float | None = None):
    """The per-frame function: uint8 frames ``(C, H, W, 3)`` -> ``(X (K, 3), valid (K,))``; with
    ``max_residual_px``, the views that miss the others' consensus are dropped (:func:`read_out`)."""

    def run(frames_u8: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        # (C, H, W, 3) -> (1, C, 3, H, W): the permuted view of HWC data is already channels_last.
        images = frames_u8.permute(0, 3, 1, 2).float().mul_(1.0 / 255.0)
        if not channels_last:
            images = images.contiguous()
        logits = model(images)
        result = read_out(logits[None], cams, stride, sigma, max_residual_px=max_residual_px)
        return result.X[0], result.valid[0]

    return run


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_network_options(p, threads_help="torch threads (default: torch's default)")
    p.add_argument("--no-fuse", action="store_true", help="keep BatchNorm separate (not folded into convs)")
    p.add_argument("--contiguous", action="store_true", help="NCHW instead of channels_last")
    p.add_argument("--outlier-px", type=float, default=TrainConfig().outlier_px,
                   help="the read-out's outlier threshold, network pixels (default: a detector trained with "
                        "the defaults; 0: every view)")
    args = p.parse_args(argv)

    config, model, num_params = build_network(args)
    if not args.no_fuse:
        model = model.fused()
    channels_last = not args.contiguous
    if channels_last:
        model = model.to(memory_format=torch.channels_last)

    C, S = args.cameras, args.size
    cams = look_at_rig(C, S)
    frames = random_frames(args)
    flops_per_frame = count_conv_flops(model, torch.rand(C, 3, S, S))
    run = make_pipeline(model, cams, config.stride, args.sigma, channels_last, args.outlier_px or None)

    peaks, rounds = interleaved_rounds({"pytorch": run}, frames, args, matmul_seconds=1.0)
    round_fps = [1 / statistics.median(t) for t in rounds["pytorch"]]
    times = [x for t in rounds["pytorch"] for x in t]
    med = statistics.median(times)
    q = statistics.quantiles(times, n=10)
    achieved = flops_per_frame / med
    matmul = statistics.median(peaks)
    print(network_summary(args, config, num_params, flops_per_frame))
    print(
        f"per frame: median {med * 1e3:.2f} ms (p10 {q[0] * 1e3:.2f}, p90 {q[-1] * 1e3:.2f}) -> "
        f"{1 / med:.1f} frames/s; conv {achieved / 1e9:.1f} GFLOP/s of matmul {matmul / 1e9:.1f} GFLOP/s "
        f"({100 * achieved / matmul:.1f}%)"
    )
    result = {
        "benchmark": "inference",
        "frames_per_s": 1 / med,
        "flop_fraction": achieved / matmul,
        "ms_per_frame_median": med * 1e3,
        "ms_per_frame_p10": q[0] * 1e3,
        "ms_per_frame_p90": q[-1] * 1e3,
        "achieved_flops": achieved,
        **network_fields(args, config, num_params, flops_per_frame, matmul),
        "fused": not args.no_fuse,
        "channels_last": channels_last,
        "outlier_px": args.outlier_px,
        "repeats": args.repeats,
        "rounds": args.rounds,
        "frames_per_s_rounds": round_fps,
        "matmul_flops_rounds": peaks,
    }
    emit(result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
