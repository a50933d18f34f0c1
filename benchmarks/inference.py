"""Inference speed: 4-view 3D keypoints from camera images through ``s3k.Detector``, one frame at a time and
in batches, side by side.

Targets: docs/method.md#performance-targets (two-pass from native-resolution frames >= 60 frames/s on 2 CPU
cores; on a GPU one-pass <= 1 ms, two-pass <= 2 ms per frame, batched one-pass >= 100k frames/s at 96 px).

Pipelines, each timed per frame (or per batch of ``--batch`` frames) after warm-up, interleaved in rounds with
a matmul peak so a shared machine's drift hits all of them alike:

- ``one_pass``: frames of ``--size`` px (the network's input) -> ``OnePassDetector`` (U-Net, BatchNorm
  folded, channels_last; the read-out in float64);
- ``one_pass_native``: frames of ``--native`` px resampled on the device to ``--coarse`` px, then the same;
- ``two_pass``: frames of ``--native`` px -> coarse pass at ``--coarse`` px -> crops of ``--crop`` px around
  its estimate, cut on the device -> refining pass (``TwoPassDetector``, its fast path: on the CPU each
  network a frozen graph, every view's crop cut in one resampling);
- ``two_pass_plain``: the same detector on the plain path (``fast=False``: module by module, crops per
  camera), the pipeline as it ran before the fast path; the JSON's ``two_pass_check`` gives the largest
  distance between the two pipelines' 3D points on the benchmark's frames (and ``two_pass_speedup``, the
  median over rounds of plain time over fast time);
- ``two_pass_compiled`` (with ``--compile``): the plain path with each network through ``torch.compile``
  (inductor, static shapes); its compile seconds (the first frame) and its points against the plain path's
  are in ``compiled``. Not the detector's default: compiling costs tens of seconds per network on 2 cores;
- ``two_pass@ENCODER``, ``one_pass_native@ENCODER`` (with ``--compare-encoder ENCODER``): those two with
  the network of that encoder (``--compare-encoder-stride``) in place of the options', timed in the same
  rounds;
- ``reference``: the earlier hand-written per-frame pipeline at ``--size`` px (network + ``read_out``), the
  baseline the one-pass detector must not be slower than.

The networks are untrained (timing does not depend on the weights); the rig is four cameras on a ring looking
at the origin, the crop 0.3 world units wide. The last line is one JSON object naming the device.

Example::

    python benchmarks/inference.py --size 128 --native 384 --coarse 96 --crop 192 --batch 1
    python benchmarks/inference.py --batch 1 --threads 1 --compare-encoder efficientnet-lite0 \
        --compare-encoder-stride 8
"""

from __future__ import annotations

import argparse
import os
import shlex
import statistics
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import (  # noqa: E402
    add_network_options,
    build_network,
    emit,
    git_revision,
    interleaved_rounds,
    network_fields,
    network_summary,
)
from s3k.cli import showing_library_messages  # noqa: E402
from s3k.config import TrainConfig  # noqa: E402
from s3k.geometry import Cameras  # noqa: E402
from s3k.model import count_conv_flops  # noqa: E402
from s3k.readout import ReadoutConfig, read_out  # noqa: E402


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
        result = read_out(logits[None], cams, stride, sigma,
                          config=ReadoutConfig(max_residual_px=max_residual_px))
        return result.X[0], result.valid[0]

    return run


def _device_name(device: torch.device) -> str:
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    from benchmarks.common import machine_info

    return str(machine_info().get("cpu", "cpu"))


def detectors(args, device: torch.device) -> dict:
    """``{name: (detector, frames (B, C, S, S, 3) uint8, cameras)}`` of the pipelines (module docstring)."""

    from s3k.detector import CropRule, DetectorMeta, OnePassDetector, TwoPassDetector
    def net(size: int, fast: bool = True, options=args):
        config, model, _ = build_network(options)
        meta = DetectorMeta([str(k) for k in range(args.keypoints)], [], (size, size), config.stride,
                            args.sigma, config.to_dict(), outlier_px=args.outlier_px)
        model = model.fused().to(device=device, memory_format=torch.channels_last)
        return OnePassDetector(model, meta, device, args.precision, fast)

    gen = torch.Generator().manual_seed(0)

    def frames(size: int):
        shape = (args.batch, args.cameras, size, size, 3)
        return torch.randint(0, 256, shape, dtype=torch.uint8, generator=gen).to(device)

    coarse, fine = net(args.coarse), net(args.crop)
    rule = CropRule(extent=0.3, size=args.crop)
    two = TwoPassDetector(coarse, fine, rule)
    plain = TwoPassDetector(net(args.coarse, False), net(args.crop, False), rule)
    rig = look_at_rig(args.cameras, args.size)[0].to(device=device)
    native = look_at_rig(args.cameras, args.native)[0].to(device=device)
    pipes = {"one_pass": (net(args.size), frames(args.size), rig),
             "one_pass_native": (coarse, frames(args.native), native),
             "two_pass": (two, frames(args.native), native),
             "two_pass_plain": (plain, frames(args.native), native)}
    if args.compare_encoder:
        other = argparse.Namespace(**{**vars(args), "encoder": args.compare_encoder,
                                      "encoder_stride": args.compare_encoder_stride})
        coarse_other = net(args.coarse, options=other)
        two_other = TwoPassDetector(coarse_other, net(args.crop, options=other), rule)
        pipes[f"one_pass_native@{args.compare_encoder}"] = (coarse_other, frames(args.native), native)
        pipes[f"two_pass@{args.compare_encoder}"] = (two_other, frames(args.native), native)
    if args.compile:
        compiled = TwoPassDetector(net(args.coarse, False), net(args.crop, False), rule)
        for one in (compiled.coarse, compiled.fine):
            one.pass_.net = one.pass_.run.net = torch.compile(one.pass_.net, dynamic=False)
        pipes["two_pass_compiled"] = (compiled, *pipes["two_pass"][1:])
    return pipes


def two_pass_check(pipes: dict, frames: int = 8) -> dict:
    """The fast and the plain two-pass pipelines on ``frames`` frames of noise: the largest distance between
    their 3D points (world units; the rig is in metres, so 1e-4 is 0.1 mm), over the points both find."""
    fast, x, cams = pipes["two_pass"]
    plain = pipes["two_pass_plain"][0]
    gen = torch.Generator().manual_seed(1)
    shape = (frames, *x.shape[1:])
    batch = torch.randint(0, 256, shape, dtype=torch.uint8, generator=gen).to(x.device)
    worst, points, agree = 0.0, 0, True
    for b in range(frames):  # one frame at a time, as timed
        a, p = fast(batch[b], cams), plain(batch[b], cams)
        agree &= bool(torch.equal(a.valid, p.valid))
        ok = a.valid & p.valid
        points += int(ok.sum())
        if bool(ok.any()):
            worst = max(worst, float((a.X[ok] - p.X[ok]).norm(dim=-1).max()))
    return {"frames": frames, "points": points, "max_3d_distance": worst, "same_validity": agree}


def compile_check(pipes: dict) -> dict:
    """The compiled two passes: seconds of the first frame (compiling both networks) and the largest
    distance between their 3D points and the plain path's on that frame."""
    import time

    compiled, x, cams = pipes["two_pass_compiled"]
    plain = pipes["two_pass_plain"][0]
    t0 = time.perf_counter()
    a = compiled(x[0], cams)
    seconds = time.perf_counter() - t0
    p = plain(x[0], cams)
    ok = a.valid & p.valid
    worst = float((a.X[ok] - p.X[ok]).norm(dim=-1).max()) if bool(ok.any()) else float("nan")
    same = bool(torch.equal(a.valid, p.valid))
    return {"compile_s": seconds, "max_3d_distance": worst, "same_validity": same}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_network_options(p, threads_help="torch threads (default: torch's default)")
    p.add_argument("--native", type=int, default=384, help="native frame size of the two-pass pipelines")
    p.add_argument("--coarse", type=int, default=96, help="coarse pass input size (default 96)")
    p.add_argument("--crop", type=int, default=192, help="refining pass crop size (default 192)")
    p.add_argument("--batch", type=int, default=1, help="frames per call (default 1)")
    p.add_argument("--device", default="auto", help="'auto', 'cpu', 'cuda' (default: auto)")
    p.add_argument("--precision", default="float32", choices=("float32", "bfloat16", "float16"))
    p.add_argument("--outlier-px", type=float, default=TrainConfig().self_supervision.outlier_px,
                   help="the read-out's outlier threshold, network pixels (default: a detector trained with "
                        "the defaults; 0: every view)")
    p.add_argument("--no-reference", action="store_true", help="leave out the earlier per-frame pipeline")
    p.add_argument("--compile", action="store_true", help="also time the two passes through torch.compile")
    p.add_argument("--compare-encoder", default=None, choices=["unet", "efficientnet-lite0"],
                   help="also time the one- and two-pass pipelines with this encoder's network")
    p.add_argument("--compare-encoder-stride", type=int, default=16, choices=[8, 16, 32],
                   help="where --compare-encoder's network is cut (default 16)")
    args = p.parse_args(argv)

    from s3k.detector import pick_device

    device = pick_device(args.device)
    config, model, num_params = build_network(args)
    pipes = detectors(args, device)
    check = two_pass_check(pipes)
    compiled = compile_check(pipes) if args.compile else None
    runs = {name: (lambda _f, d=d, x=x, c=c: d(x, c)) for name, (d, x, c) in pipes.items()}
    if not args.no_reference and args.batch == 1:
        reference = model.fused().to(device=device, memory_format=torch.channels_last)
        cams = look_at_rig(args.cameras, args.size).to(device=device)
        x = pipes["one_pass"][1][0]
        runs["reference"] = (lambda _f: make_pipeline(reference, cams, config.stride, args.sigma, True,
                                                      args.outlier_px or None)(x))
    if device.type == "cuda":
        inner = dict(runs)
        runs = {name: (lambda f, r=r: (r(f), torch.cuda.synchronize())) for name, r in inner.items()}
    flops = count_conv_flops(model, torch.rand(args.cameras, 3, args.size, args.size))
    peaks, rounds = interleaved_rounds(runs, torch.zeros(1), args, matmul_seconds=1.0)
    print(network_summary(args, config, num_params, flops))
    result: dict = {"command": shlex.join(["python", "benchmarks/inference.py",
                                            *(sys.argv[1:] if argv is None else argv)]),
                    "git_revision": git_revision(),
                    "benchmark": "inference", "device": _device_name(device), "device_type": device.type,
                    "batch": args.batch, "native": args.native, "coarse": args.coarse, "crop": args.crop,
                    "precision": args.precision, "pipelines": {}}
    for name, per_round in rounds.items():
        times = [t for r in per_round for t in r]
        med = statistics.median(times)
        fps = args.batch / med
        result["pipelines"][name] = {"frames_per_s": fps, "ms_per_call_median": med * 1e3,
                                     "frames_per_s_rounds": [args.batch / statistics.median(r)
                                                             for r in per_round]}
        print(f"{name}: {med * 1e3:.2f} ms per call of {args.batch} frame(s) -> {fps:.1f} frames/s")
    speedups = [statistics.median(a) / statistics.median(b)
                for a, b in zip(rounds["two_pass_plain"], rounds["two_pass"])]
    result["two_pass_speedup"] = statistics.median(speedups)
    result["two_pass_check"] = check
    if compiled is not None:
        result["compiled"] = compiled
        print(f"torch.compile: {compiled['compile_s']:.1f} s to compile both networks; 3D distance to "
              f"the plain path {compiled['max_3d_distance']:.2e} world units")
    print(f"two_pass_plain / two_pass time, median of rounds: {result['two_pass_speedup']:.3f}; largest 3D "
          f"distance between them {check['max_3d_distance']:.2e} world units over {check['points']} points")
    if "reference" in rounds:
        ratios = [statistics.median(a) / statistics.median(b)
                  for a, b in zip(rounds["one_pass"], rounds["reference"])]
        result["one_pass_over_reference_time"] = statistics.median(ratios)
        print(f"one_pass / reference time, median of rounds: {statistics.median(ratios):.3f}")
    if args.compare_encoder:
        other = argparse.Namespace(**{**vars(args), "encoder": args.compare_encoder,
                                      "encoder_stride": args.compare_encoder_stride})
        other_config, other_model, other_params = build_network(other)
        images = torch.rand(args.cameras, 3, args.size, args.size)
        result["compared"] = {"config": other_config.to_dict(), "params": other_params,
                              "flops_per_frame": count_conv_flops(other_model, images)}
    result.update({**network_fields(args, config, num_params, flops, statistics.median(peaks)),
                   "repeats": args.repeats, "rounds": args.rounds, "matmul_flops_rounds": peaks})
    emit(result)
    return 0


if __name__ == "__main__":
    with showing_library_messages():  # the library's notes and warnings, as under s3k
        sys.exit(main())
