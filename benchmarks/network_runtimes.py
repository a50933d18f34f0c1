"""The two passes' networks on the CPU under two runtimes: s3k's frozen TorchScript graph (what
``s3k.Detector`` runs today, :mod:`s3k.detector.frozen`) against ONNX Runtime on the same network exported,
one thread each, batch = the 4 views of one frame: the coarse pass on 96 px images, the refining pass on
192 px crops (the box headline's sizes and network, untrained weights).

Rounds are interleaved (each runtime ``--repeats`` calls a round after a matmul peak, ``--rounds`` rounds:
``benchmarks.common.interleaved_rounds``), so a shared machine's load falls on both alike; the figure is the
median over rounds of TorchScript's time over ONNX Runtime's (above 1: ONNX Runtime is faster), with each
runtime's median milliseconds, and the largest difference of their logits (the same network must give the
same heatmaps). The last line is one JSON object with the
machine.

Example::

    python benchmarks/network_runtimes.py --out docs/results/benchmarks/network-runtimes-cpu.json
"""

from __future__ import annotations

import argparse
import os
import shlex
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import (  # noqa: E402
    git_revision,
    interleaved_rounds,
    machine_info,
    write_and_emit,
)
from s3k.detector.frozen import FrozenNetwork  # noqa: E402
from s3k.model import UNet, UNetConfig  # noqa: E402


def onnx_session(net: torch.nn.Module, x: torch.Tensor, folder: Path, name: str):
    """An ONNX Runtime session, one thread, all graph optimisations, of ``net`` exported at ``x``'s shape."""
    import onnxruntime as ort

    path = folder / f"{name}.onnx"
    torch.onnx.export(net, (x,), str(path), input_names=["images"], output_names=["logits"], opset_version=17,
                      dynamo=False)
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


def feeding(session, feed: dict):
    """ONNX Runtime as a pipeline of ``interleaved_rounds``: it runs on its own input (NCHW, numpy), whatever
    tensor it is handed."""
    return lambda _frames: session.run(None, feed)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--views", type=int, default=4, help="views of one frame: the batch (default 4)")
    p.add_argument("--keypoints", type=int, default=3, help="keypoints (default 3, the box's)")
    p.add_argument("--warmup", type=int, default=5, help="untimed calls of each runtime first (default 5)")
    p.add_argument("--repeats", type=int, default=20, help="calls per runtime per round (default 20)")
    p.add_argument("--rounds", type=int, default=7, help="interleaved rounds (default 7)")
    p.add_argument("--out", default=None, help="JSON file to write")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    torch.manual_seed(0)
    given = sys.argv[1:] if argv is None else argv
    result: dict = {"command": "python benchmarks/network_runtimes.py " + shlex.join(given),
                    "revision": git_revision(), "threads": 1, "network": "UNetConfig() defaults, fused, "
                    "untrained; TorchScript in channels-last as the detector runs it", "passes": {}}
    with tempfile.TemporaryDirectory() as tmp, torch.no_grad():
        for name, size in (("coarse", 96), ("refining", 192)):
            net = UNet(args.keypoints, UNetConfig()).eval().fused()
            x = torch.randn(args.views, 3, size, size)
            session = onnx_session(net, x, Path(tmp), name)
            feed = {"images": x.numpy()}
            net = net.to(memory_format=torch.channels_last)  # as s3k.Detector holds and feeds it
            x = x.contiguous(memory_format=torch.channels_last)
            frozen = FrozenNetwork(net, torch.device("cpu"))
            reference = frozen(x)
            difference = float(np.abs(session.run(None, feed)[0] - reference.numpy()).max())
            _, rounds = interleaved_rounds({"torchscript": frozen, "onnxruntime": feeding(session, feed)}, x,
                                           args, matmul_seconds=0.2)
            ts, ort_ = ([statistics.fmean(r) for r in rounds[k]] for k in ("torchscript", "onnxruntime"))
            ratio = statistics.median(a / b for a, b in zip(ts, ort_))
            result["passes"][name] = {
                "input": [args.views, 3, size, size], "torchscript_ms": 1e3 * statistics.median(ts),
                "onnxruntime_ms": 1e3 * statistics.median(ort_), "torchscript_over_onnxruntime": ratio,
                "ratio_per_round": [a / b for a, b in zip(ts, ort_)], "max_logit_difference": difference,
                "logit_scale": float(reference.abs().max())}
            print(f"{name:9s} {size} px x{args.views}: TorchScript {1e3 * statistics.median(ts):.2f} ms, "
                  f"ONNX Runtime {1e3 * statistics.median(ort_):.2f} ms, ratio {ratio:.2f}x (rounds "
                  f"{min(result['passes'][name]['ratio_per_round']):.2f}-"
                  f"{max(result['passes'][name]['ratio_per_round']):.2f}); logits differ by {difference:.1e}",
                  file=sys.stderr)
    result["machine"] = machine_info()
    write_and_emit(result, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
