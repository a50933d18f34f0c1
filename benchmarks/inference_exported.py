"""Inference speed of the exported detector: 4-view 3D keypoints per frame with ONNX Runtime and TorchScript.

The same end-to-end pipeline as ``benchmarks/inference.py`` (C uint8 camera images -> float [0, 1] -> U-Net
heatmaps of the C views in one batch -> softmax means and variances -> confidence weights -> weighted
triangulation), with the network run from the file ``s3k export`` writes (BatchNorm folded, batch dimension
dynamic): in onnxruntime (CPU execution provider, as many intra-op threads as torch uses) and as TorchScript.
The PyTorch pipeline of ``benchmarks/inference.py`` is timed in the same run for comparison. With
``--with-moments`` the exported graph also computes the heatmap means and confidences (``s3k export
--with-moments``), so only the triangulation stays in PyTorch.

Before timing, each exported file is checked against the PyTorch model (largest absolute difference of the
logits on the benchmark frames, reported as ``max_diff``).

Example::

    python benchmarks/inference_exported.py --size 128

The last line printed is one JSON object: ``frames_per_s`` (ONNX Runtime), ``torchscript_frames_per_s``,
``pytorch_frames_per_s``, the FLOP fractions, machine info, ...
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import (  # noqa: E402
    add_network_options,
    build_network,
    emit,
    interleaved_rounds,
    machine_info,
    network_fields,
    network_summary,
    random_frames,
)
from benchmarks.inference import look_at_rig, make_pipeline  # noqa: E402
from s3k.cli import showing_library_messages  # noqa: E402
from s3k.inference.export import export_module, output_names  # noqa: E402
from s3k.model import count_conv_flops  # noqa: E402
from s3k.readout import read_out, select_views, triangulate  # noqa: E402


def points_of_outputs(outs, cams, stride: int, sigma: float, with_moments: bool):
    """The exported file's outputs for one frame's C images -> ``(X (K, 3), valid (K,))`` (s3k.readout)."""
    if not with_moments:
        result = read_out(torch.as_tensor(outs[0])[None], cams, stride, sigma)
        return result.X[0], result.valid[0]
    means, weights = torch.as_tensor(outs[1])[None], torch.as_tensor(outs[2])[None]
    X, valid = triangulate(cams, means, weights, select_views(means, weights))
    return X[0], valid[0]


def onnx_pipeline(path: Path, cams, stride: int, sigma: float, with_moments: bool, threads: int):
    """Per-frame function with the network in onnxruntime: uint8 ``(C, H, W, 3)`` -> ``(X (K, 3), valid)``."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])

    def run(frames_u8: torch.Tensor):
        # ORT wants dense NCHW float32.
        images = frames_u8.permute(0, 3, 1, 2).float().mul_(1.0 / 255.0).contiguous().numpy()
        return points_of_outputs(session.run(None, {"images": images}), cams, stride, sigma, with_moments)

    return run


def torchscript_pipeline(path: Path, cams, stride: int, sigma: float, with_moments: bool,
                         channels_last: bool):
    """Per-frame function with the network loaded by ``torch.jit.load`` (frozen for inference)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        module = torch.jit.optimize_for_inference(torch.jit.freeze(torch.jit.load(str(path)).eval()))

    def run(frames_u8: torch.Tensor):
        images = frames_u8.permute(0, 3, 1, 2).float().mul_(1.0 / 255.0)
        if not channels_last:
            images = images.contiguous()
        outs = module(images)
        return points_of_outputs(outs if with_moments else (outs,), cams, stride, sigma, with_moments)

    return run


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_network_options(p, threads_help="torch and onnxruntime threads (default: torch's)")
    p.add_argument("--with-moments", action="store_true",
                   help="export means and confidences too (read-out inside the exported graph)")
    p.add_argument("--keep", default=None, help="folder to keep the exported files in (default: temporary)")
    args = p.parse_args(argv)

    config, model, num_params = build_network(args)
    threads = torch.get_num_threads()
    fused = model.fused()

    C, S = args.cameras, args.size
    cams = look_at_rig(C, S)
    frames = random_frames(args)
    images = frames.permute(0, 3, 1, 2).float().div(255.0).contiguous()
    flops_per_frame = count_conv_flops(fused, images)

    from s3k.inference.export import DetectorWithMoments, run_exported

    module = DetectorWithMoments(fused, config.stride, args.sigma) if args.with_moments else fused
    names = output_names(args.with_moments)
    meta = json.dumps({"benchmark": True, "image_size": [S, S], "stride": config.stride, "sigma": args.sigma})
    tmp = None
    if args.keep:
        folder = Path(args.keep)
        folder.mkdir(parents=True, exist_ok=True)
    else:
        tmp = tempfile.TemporaryDirectory()
        folder = Path(tmp.name)
    paths = {
        "onnx": export_module(module, "onnx", folder / "detector.onnx", (S, S), names, meta),
        "torchscript": export_module(module, "torchscript", folder / "detector.pt", (S, S), names, meta),
    }
    with torch.no_grad():
        ref = model(images).numpy()
    max_diff = {fmt: float(np.abs(run_exported(path, fmt, images.numpy())[0] - ref).max())
                for fmt, path in paths.items()}

    pipelines = {
        "pytorch": make_pipeline(fused.to(memory_format=torch.channels_last), cams, config.stride, args.sigma,
                                 True),
        "onnx": onnx_pipeline(paths["onnx"], cams, config.stride, args.sigma, args.with_moments, threads),
        "torchscript": torchscript_pipeline(paths["torchscript"], cams, config.stride, args.sigma,
                                            args.with_moments, channels_last=False),
    }
    peaks, rounds = interleaved_rounds(pipelines, frames, args, matmul_seconds=2.0)
    times = {name: [x for t in per_round for x in t] for name, per_round in rounds.items()}
    matmul = statistics.median(peaks)
    fps = {name: 1 / statistics.median(t) for name, t in times.items()}
    print(f"{network_summary(args, config, num_params, flops_per_frame)}, "
          f"read-out in {'the exported graph' if args.with_moments else 'PyTorch'}")
    for name, t in times.items():
        med = statistics.median(t)
        q = statistics.quantiles(t, n=10)
        diff = f", max |logits - PyTorch| {max_diff[name]:.2g}" if name in max_diff else ""
        print(f"{name:>12}: median {med * 1e3:.2f} ms/frame (p10 {q[0] * 1e3:.2f}, p90 {q[-1] * 1e3:.2f}) -> "
              f"{1 / med:.1f} frames/s, conv {100 * flops_per_frame / med / matmul:.1f}% of matmul "
              f"{matmul / 1e9:.1f} GFLOP/s{diff}")
    result = {
        "benchmark": "inference_exported",
        "frames_per_s": fps["onnx"],
        "torchscript_frames_per_s": fps["torchscript"],
        "pytorch_frames_per_s": fps["pytorch"],
        "flop_fraction": flops_per_frame * fps["onnx"] / matmul,
        "torchscript_flop_fraction": flops_per_frame * fps["torchscript"] / matmul,
        "pytorch_flop_fraction": flops_per_frame * fps["pytorch"] / matmul,
        "ms_per_frame_median": {name: 1e3 * statistics.median(t) for name, t in times.items()},
        "max_diff": max_diff,
        **network_fields(args, config, num_params, flops_per_frame, matmul),
        "with_moments": args.with_moments,
        "threads": threads,
        "repeats": args.repeats,
        "rounds": args.rounds,
        "onnxruntime": __import__("onnxruntime").__version__,
        "machine": machine_info(),
    }
    if tmp is not None:
        tmp.cleanup()
    emit(result)
    return 0


if __name__ == "__main__":
    with showing_library_messages():  # the library's notes and warnings, as under s3k
        sys.exit(main())
