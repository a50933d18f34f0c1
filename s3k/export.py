"""``s3k export``: a trained detector as an ONNX or TorchScript file, verified against PyTorch.

The exported network takes ``images (N, 3, H, W)`` float32 in [0, 1] (RGB, ``(W, H)`` the detector's
``image_size``; ``N`` is dynamic) and returns ``logits (N, K, h, w)``. With ``--with-moments`` it also
returns ``means (N, K, 2)`` (the heatmap softmax means within the read-out's window of each peak,
docs/method.md#heatmaps, in input-image pixels, pixel (0, 0) the centre of the top-left pixel) and
``confidence (N, K)`` (docs/method.md#confidence), computed in float64 inside the graph and returned as
float32.

BatchNorm is folded into the convolutions before export (``UNet.fused``). After writing, the file is loaded
back (onnxruntime for ONNX, ``torch.jit.load`` for TorchScript) and run on real images (frames of the run's
dataset when it is available, else seeded synthetic images); the command fails when any output differs from
the PyTorch model's by more than ``--tolerance`` (default 1e-4) and prints the largest difference.

The detector's metadata (keypoints, image size, stride, sigma, ...) travels with the file: as the ONNX model
property ``s3k_meta`` and as the TorchScript extra file ``s3k_meta.json`` (both ``DetectorMeta.to_dict()`` as
JSON), so a consumer needs no other file.
"""

from __future__ import annotations

import json
import sys
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from s3k import readout
from s3k.errors import UserError
from s3k.heatmaps import confidence_weight

__all__ = [
    "FORMATS",
    "META_KEY",
    "DetectorWithMoments",
    "ExportReport",
    "export_detector",
    "export_module",
    "exported_moments",
    "reference_outputs",
    "run_exported",
    "verification_images",
]

FORMATS = ("onnx", "torchscript")
META_KEY = "s3k_meta"
DEFAULT_TOLERANCE = 1e-4
TRACE_BATCH = 2


class DetectorWithMoments(nn.Module):
    """The network plus its heatmap read-out: ``images -> (logits, means, confidence)``.

    Args:
        net: maps ``(N, 3, H, W)`` to ``(N, K, h, w)`` logits.
        stride: heatmap stride.
        sigma: target width in image pixels (the confidence weight's scale).
    """

    def __init__(self, net: nn.Module, stride: int, sigma: float) -> None:
        super().__init__()
        self.net = net
        self.stride = int(stride)
        self.sigma = float(sigma)

    def forward(self, images: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(N, 3, H, W)`` -> ``logits (N, K, h, w)``, ``means (N, K, 2)`` pixels, ``confidence (N, K)``."""
        logits = self.net(images)
        means, confidence = exported_moments(logits, self.stride, self.sigma)
        return logits, means, confidence


def exported_moments(logits: Tensor, stride: int, sigma: float) -> tuple[Tensor, Tensor]:
    """Softmax means (within the read-out's window of the peak) and confidence weights of logits
    ``(*, h, w)``: :mod:`s3k.readout`'s, returned float32.

    The read-out's float64 keeps the sums over ``h * w`` cells independent of the summation order of a
    runtime, so exported and PyTorch read-outs differ only through their logits.
    """
    _probs, means, var = readout.moments(logits, stride, readout.window_cells(sigma, stride))
    return means.to(torch.float32), confidence_weight(var, sigma).to(torch.float32)


@dataclass
class ExportReport:
    """Result of :func:`export_detector`.

    Attributes:
        path: the written file.
        format: ``"onnx"`` or ``"torchscript"``.
        outputs: output names, in order.
        max_diff: largest absolute difference from PyTorch per output.
        inputs: where the verification images came from.
        num_images: how many images were compared.
        tolerance: the largest difference allowed.
    """

    path: Path
    format: str
    outputs: list[str]
    max_diff: dict[str, float] = field(default_factory=dict)
    inputs: str = ""
    num_images: int = 0
    tolerance: float = DEFAULT_TOLERANCE

    @property
    def ok(self) -> bool:
        return all(np.isfinite(v) and v <= self.tolerance for v in self.max_diff.values())


def output_names(with_moments: bool) -> list[str]:
    return ["logits", "means", "confidence"] if with_moments else ["logits"]


def export_module(module: nn.Module, fmt: str, out: str | Path, image_size: tuple[int, int],
                  names: list[str], meta_json: str, opset: int = 17) -> Path:
    """Trace ``module`` on ``(TRACE_BATCH, 3, H, W)`` images and write it as ``fmt`` with a dynamic batch.

    Args:
        module: eval-mode module mapping images to one tensor or a tuple (``names`` in order).
        fmt: ``"onnx"`` or ``"torchscript"``.
        out: file to write.
        image_size: ``(W, H)`` of the input.
        names: output names.
        meta_json: metadata stored in the file.
        opset: ONNX opset.

    Returns:
        The path written.
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    W, H = int(image_size[0]), int(image_size[1])
    example = torch.rand(TRACE_BATCH, 3, H, W, generator=torch.Generator().manual_seed(0))
    module = module.eval()
    with warnings.catch_warnings():
        # The tracer warns about Python branches on shapes; H and W are fixed by the export, N stays dynamic.
        warnings.simplefilter("ignore")
        if fmt == "onnx":
            import onnx

            axes = {"images": {0: "N"}, **{n: {0: "N"} for n in names}}
            torch.onnx.export(module, (example,), str(out), dynamo=False, input_names=["images"],
                              output_names=names, dynamic_axes=axes, opset_version=opset)
            model = onnx.load(str(out))
            onnx.helper.set_model_props(model, {META_KEY: meta_json})
            onnx.checker.check_model(model)
            onnx.save(model, str(out))
        elif fmt == "torchscript":
            with torch.no_grad():
                traced = torch.jit.trace(module, (example,), check_trace=False)
            torch.jit.save(traced, str(out), _extra_files={f"{META_KEY}.json": meta_json})
        else:
            raise UserError(f"--format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    return out


def run_exported(path: str | Path, fmt: str, images: np.ndarray,
                 threads: int | None = None) -> list[np.ndarray]:
    """Load an exported file the way a consumer would and run it on ``images (N, 3, H, W)`` float32."""
    images = np.ascontiguousarray(images, dtype=np.float32)
    if fmt == "onnx":
        import onnxruntime as ort

        opts = ort.SessionOptions()
        if threads:
            opts.intra_op_num_threads = threads
        session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        return [np.asarray(o) for o in session.run(None, {"images": images})]
    if fmt == "torchscript":
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)  # torch.jit is deprecated, still supported
            module = torch.jit.load(str(path), map_location="cpu")
        with torch.no_grad():
            result = module(torch.from_numpy(images))
        outs = result if isinstance(result, (tuple, list)) else (result,)
        return [o.numpy() for o in outs]
    raise ValueError(f"unknown format {fmt!r}")


def reference_outputs(model: nn.Module, images: np.ndarray, stride: int, sigma: float,
                      with_moments: bool) -> list[np.ndarray]:
    """The PyTorch outputs the exported file must reproduce (``model`` as loaded, eval mode)."""
    with torch.no_grad():
        logits = model(torch.from_numpy(np.ascontiguousarray(images, dtype=np.float32))).float()
        outs = [logits]
        if with_moments:
            outs += list(exported_moments(logits, stride, sigma))
    return [o.numpy() for o in outs]


def verification_images(meta, dataset: str | Path | None, count: int = 6,
                        seed: int = 0) -> tuple[np.ndarray, str]:
    """Images ``(N, 3, H, W)`` float32 to compare exported and PyTorch outputs on.

    Frames of ``dataset`` (resized to the detector's input like training did) when it opens, else seeded
    synthetic images: smooth colour gradients with noise and a few bright discs, which give peaked heatmaps
    and a range of activations closer to real frames than uniform noise.

    Returns:
        ``(images, description)``.
    """
    W, H = int(meta.image_size[0]), int(meta.image_size[1])
    if dataset is not None and Path(dataset).is_dir():
        try:
            from s3k.frames import open_dataset

            ds = open_dataset(dataset, (W, H), cache="none")
            n_frames = max(1, -(-count // len(ds.cameras)))
            ids = ds.frames(("test", "unlabelled", "labelled"))[:n_frames]
            if len(ids):
                imgs = np.asarray(ds.images(ids))  # (B, C, H, W, 3) uint8
                imgs = imgs.reshape(-1, H, W, 3)[:count].transpose(0, 3, 1, 2).astype(np.float32) / 255.0
                return np.ascontiguousarray(imgs), f"{len(imgs)} images of dataset {dataset}"
        except (ValueError, FileNotFoundError, KeyError, OSError) as exc:
            print(f"warning: cannot read verification frames from {dataset} ({exc}); using synthetic images",
                  file=sys.stderr)
    import cv2

    rng = np.random.default_rng(seed)
    out = np.empty((count, 3, H, W), np.float32)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    for i in range(count):
        img = np.empty((H, W, 3), np.float32)
        for ch in range(3):
            a, b, c = rng.uniform(-1, 1, 3)
            img[..., ch] = 0.5 + 0.3 * np.tanh(a * xx / W + b * yy / H + c)
        img += rng.normal(0, 0.05, img.shape).astype(np.float32)
        for _ in range(3):
            centre = (int(rng.integers(0, W)), int(rng.integers(0, H)))
            colour = tuple(float(v) for v in rng.uniform(0, 1, 3))
            cv2.circle(img, centre, max(2, min(W, H) // 16), colour, -1)
        out[i] = np.clip(img, 0, 1).transpose(2, 0, 1)
    return out, f"{count} synthetic images (seed {seed})"


def export_detector(run_dir: str | Path, fmt: str, out: str | Path, with_moments: bool = False,
                    fuse: bool = True, opset: int = 17, tolerance: float = DEFAULT_TOLERANCE,
                    verify_data: str | Path | None = None, checkpoint: str | None = None) -> ExportReport:
    """Export the detector of a run folder and verify the file against PyTorch.

    Args:
        run_dir: run folder of ``s3k train``.
        fmt: ``"onnx"`` or ``"torchscript"``.
        out: file to write.
        with_moments: also output the heatmap means and confidence weights.
        fuse: fold BatchNorm into the convolutions first.
        opset: ONNX opset version.
        tolerance: largest allowed absolute difference from PyTorch, per output element.
        verify_data: dataset folder with frames to verify on; default: the run's training dataset.
        checkpoint: file inside ``run_dir`` to load instead of the final model.

    Returns:
        An :class:`ExportReport`; ``report.ok`` says whether the verification passed.
    """
    from s3k.run import load_detector, read_run_config

    if fmt not in FORMATS:
        raise UserError(f"--format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    model, meta = load_detector(run_dir, "cpu", checkpoint)
    net = model.fused() if fuse else model
    module: nn.Module = DetectorWithMoments(net, meta.stride, meta.sigma) if with_moments else net
    names = output_names(with_moments)
    meta_doc = {**meta.to_dict(), "outputs": names, "input": "images (N, 3, H, W) float32 RGB in [0, 1]"}
    path = export_module(module, fmt, out, meta.image_size, names, json.dumps(meta_doc), opset)

    if verify_data is None:
        try:
            verify_data = read_run_config(run_dir).get("dataset")
        except FileNotFoundError:
            verify_data = None
    images, source = verification_images(meta, verify_data)
    got = run_exported(path, fmt, images)
    ref = reference_outputs(model, images, meta.stride, meta.sigma, with_moments)
    report = ExportReport(path, fmt, names, inputs=source, num_images=len(images), tolerance=tolerance)
    if len(got) != len(ref):
        raise ValueError(f"{path}: {len(got)} outputs, expected {len(ref)} ({', '.join(names)})")
    for name, g, r in zip(names, got, ref):
        if g.shape != r.shape:
            raise ValueError(f"{path}: output {name} has shape {g.shape}, PyTorch gives {r.shape}")
        report.max_diff[name] = float(np.max(np.abs(g.astype(np.float64) - r))) if g.size else 0.0
    return report
