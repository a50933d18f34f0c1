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
import logging
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor, nn

from s3k import readout
from s3k.base.errors import UserError
from s3k.base.metrics import mm_per_unit
from s3k.data import Dataset
from s3k.detector import (
    CropRule,
    Detector,
    DetectorMeta,
    OnePassDetector,
    TwoPassDetector,
    load_network,
)
from s3k.detector.crop_rule import is_two_pass, read_two_pass
from s3k.inference.exported_files import EXPORTED_TWO_PASS, FORMATS, runtime_of, two_pass_doc
from s3k.readout.heatmaps import confidence_weight
from s3k.run_folder import RunFolder

log = logging.getLogger(__name__)

__all__ = [
    "FORMATS",
    "META_KEY",
    "DetectorWithMoments",
    "ExportReport",
    "export_detector",
    "export_module",
    "written_files",
    "exported_moments",
    "reference_outputs",
    "load_exported",
    "open_exported",
    "read_exported_meta",
    "run_exported",
    "verification_images",
]

META_KEY = "s3k_meta"
DEFAULT_TOLERANCE = 1e-4
DEFAULT_TOLERANCE_MM = 0.1
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
        path: the written file (a two-pass run's ``.json``).
        format: ``"onnx"`` or ``"torchscript"``.
        outputs: output names, in order.
        max_diff: largest absolute difference from PyTorch per output (``PASS/output`` for two passes).
        max_diff_mm: largest 3D difference between the exported detector and PyTorch's, mm (None: no
            dataset frames to compare on), over ``frames_3d`` frames; ``tolerance_mm`` its bound.
        files: every file written.
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
    tolerance_mm: float = DEFAULT_TOLERANCE_MM
    max_diff_mm: float | None = None
    frames_3d: int = 0
    files: list[Path] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.failures()

    def failures(self) -> list[str]:
        """The checks that failed, each in words with its figure and bound (empty when all passed)."""
        out = [f"output {key} differs from PyTorch's by {value:.3g} (--tolerance {self.tolerance:g})"
               for key, value in self.max_diff.items()
               if not (np.isfinite(value) and value <= self.tolerance)]
        if self.max_diff_mm is not None and not self.max_diff_mm <= self.tolerance_mm:
            what = (f"by {self.max_diff_mm:.3g} mm" if np.isfinite(self.max_diff_mm)
                    else "in which keypoints are triangulated")
            out.append(f"the exported detector's 3D points differ from PyTorch's detector's {what} on "
                       f"{self.frames_3d} frames (3D tolerance {self.tolerance_mm:g} mm)")
        return out


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


def open_exported(path: str | Path, fmt: str, threads: int | None = None):
    """Load an exported file the way a consumer would: a callable ``images (N, 3, H, W) float32 -> [outputs]``
    (numpy) running in ONNX Runtime or TorchScript."""
    if fmt == "onnx":
        import onnxruntime as ort

        opts = ort.SessionOptions()
        if threads:
            opts.intra_op_num_threads = threads
        session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        return lambda images: [np.asarray(o) for o in session.run(None, {"images": images})]
    if fmt == "torchscript":
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)  # torch.jit is deprecated, still supported
            module = torch.jit.load(str(path), map_location="cpu")

        def run(images: np.ndarray) -> list[np.ndarray]:
            with torch.no_grad():
                result = module(torch.from_numpy(images))
            return [o.numpy() for o in (result if isinstance(result, (tuple, list)) else (result,))]

        return run
    raise ValueError(f"unknown format {fmt!r}")


def run_exported(path: str | Path, fmt: str, images: np.ndarray,
                 threads: int | None = None) -> list[np.ndarray]:
    """Load an exported file (:func:`open_exported`) and run it on ``images (N, 3, H, W)`` float32."""
    return open_exported(path, fmt, threads)(np.ascontiguousarray(images, dtype=np.float32))


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
            from s3k.data.frames import open_dataset

            ds = open_dataset(dataset, (W, H), cache="none")
            n_frames = max(1, -(-count // len(ds.cameras)))
            ids = ds.frames(("test", "unlabelled", "labelled"))[:n_frames]
            if len(ids):
                imgs = np.asarray(ds.images(ids))  # (B, C, H, W, 3) uint8
                imgs = imgs.reshape(-1, H, W, 3)[:count].transpose(0, 3, 1, 2).astype(np.float32) / 255.0
                return np.ascontiguousarray(imgs), f"{len(imgs)} images of dataset {dataset}"
        except (ValueError, FileNotFoundError, KeyError, OSError) as exc:
            log.warning(f"cannot read verification frames from {dataset} ({exc}); using synthetic images")

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


def _pass_files(run_dir: Path, out: Path) -> dict[str, tuple[Path, Path]]:
    """``{pass: (run folder, file to write)}``: one pass, or a two-pass run's ``OUT.coarse.EXT`` and
    ``OUT.fine.EXT`` (the crop rule that joins them goes to ``OUT.json``)."""
    if not is_two_pass(run_dir):
        return {"": (run_dir, out)}
    _, coarse, fine = read_two_pass(run_dir)
    return {name: (folder, out.with_name(f"{out.stem}.{name}{out.suffix}"))
            for name, folder in (("coarse", coarse), ("fine", fine))}


def written_files(run_dir: str | Path, out: str | Path) -> list[Path]:
    """The files :func:`export_detector` writes for ``run_dir`` at ``out``."""
    files = [path for _, path in _pass_files(Path(run_dir), Path(out)).values()]
    return files + ([Path(out).with_suffix(".json")] if is_two_pass(run_dir) else [])


def export_detector(run_dir: str | Path, fmt: str, out: str | Path, with_moments: bool = False,
                    fuse: bool = True, opset: int = 17, tolerance: float = DEFAULT_TOLERANCE,
                    verify_data: str | Path | None = None, checkpoint: str | None = None,
                    tolerance_mm: float = DEFAULT_TOLERANCE_MM) -> ExportReport:
    """Export the detector of a run folder (one pass, or both passes of a two-pass run) and verify the
    files against PyTorch: each network's outputs, then the whole detector's 3D points on frames of the
    dataset (:func:`load_exported` against :class:`s3k.detector.Detector`).

    Args:
        run_dir: run folder of ``s3k train``.
        fmt: ``"onnx"`` or ``"torchscript"``.
        out: file to write; a two-pass run writes ``OUT.coarse.EXT``, ``OUT.fine.EXT`` and ``OUT.json``.
        with_moments: also output the heatmap means and confidence weights.
        fuse: fold BatchNorm into the convolutions first.
        opset: ONNX opset version.
        tolerance: largest allowed absolute difference from PyTorch, per output element.
        verify_data: dataset folder with frames to verify on; default: the run's training dataset.
        checkpoint: file inside a one-pass ``run_dir`` to load instead of the final model.
        tolerance_mm: largest allowed 3D difference from PyTorch's detector, millimetres.

    Returns:
        An :class:`ExportReport`; ``report.ok`` says whether the verification passed.
    """
    if fmt not in FORMATS:
        raise UserError(f"--format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    run_dir, out = Path(run_dir), Path(out)
    if verify_data is None:
        try:
            verify_data = RunFolder(run_dir).dataset()
        except FileNotFoundError:
            verify_data = None
    names = output_names(with_moments)
    report = ExportReport(out, fmt, names, tolerance=tolerance, tolerance_mm=tolerance_mm)
    for name, (folder, path) in _pass_files(run_dir, out).items():
        model, meta = load_network(folder, "cpu", checkpoint if not name else None)
        net = model.fused() if fuse else model
        module: nn.Module = DetectorWithMoments(net, meta.stride, meta.sigma) if with_moments else net
        meta_doc = {**meta.to_dict(), "outputs": names, "input": "images (N, 3, H, W) float32 RGB in [0, 1]"}
        export_module(module, fmt, path, meta.image_size, names, json.dumps(meta_doc), opset)
        images, report.inputs = verification_images(meta, verify_data)
        got = run_exported(path, fmt, images)
        ref = reference_outputs(model, images, meta.stride, meta.sigma, with_moments)
        report.num_images += len(images)
        report.files.append(path)
        for output, g, r in zip(names, got, ref):
            if g.shape != r.shape:
                raise ValueError(f"{path}: output {output} has shape {g.shape}, PyTorch gives {r.shape}")
            key = f"{name}/{output}" if name else output
            report.max_diff[key] = float(np.max(np.abs(g.astype(np.float64) - r))) if g.size else 0.0
    if is_two_pass(run_dir):
        rule, _, _ = read_two_pass(run_dir)
        files = _pass_files(run_dir, out)
        doc = {"format": EXPORTED_TWO_PASS, **asdict(rule), "runtime": fmt,
               "coarse": files["coarse"][1].name, "fine": files["fine"][1].name}
        report.path = out.with_suffix(".json")
        report.path.write_text(json.dumps(doc, indent=1) + "\n")
        report.files.append(report.path)
    report.max_diff_mm, report.frames_3d = _verify_points(run_dir, report.path, fmt, verify_data,
                                                          None if is_two_pass(run_dir) else checkpoint)
    return report


def _verify_points(run_dir: Path, path: Path, fmt: str, data: str | Path | None,
                   checkpoint: str | None = None) -> tuple[float | None, int]:
    """The largest 3D difference (mm) between the exported detector and PyTorch's on up to 8 frames of
    ``data`` at its own resolution; ``(None, 0)`` when no dataset frame can be read."""
    if data is None or not Path(data).is_dir():
        return None, 0
    try:
        ds = Dataset.open(data, cache="none")
        ids = ds.frames(("test", "unlabelled", "labelled"))[:8]
        images, cams = ds.images(ids), ds.calibration(ids, dtype=np.float64)
    except (ValueError, FileNotFoundError, KeyError, OSError) as exc:
        log.warning(f"cannot read frames from {data} to compare 3D points ({exc})")
        return None, 0
    ref = Detector.load(run_dir, "cpu", checkpoint=checkpoint)(images, cams)  # the network exported
    got = load_exported(path, fmt)(images, cams)
    both = ref.valid & got.valid
    if bool((ref.valid != got.valid).any()):
        return float("inf"), len(ids)
    diff = torch.linalg.vector_norm(ref.X - got.X, dim=-1)[both]
    scale = mm_per_unit(ds.units)
    return (float(diff.max()) * scale if diff.numel() else 0.0), len(ids)


class _ExportedNetwork:
    """An exported network as a :class:`s3k.detector.Detector` pass: images ``(N, 3, H, W)`` -> logits."""

    def __init__(self, path: Path, fmt: str) -> None:
        self.run = open_exported(path, fmt)

    def __call__(self, images: Tensor) -> Tensor:
        x = np.ascontiguousarray(images.float().cpu().numpy())
        return torch.from_numpy(self.run(x)[0]).to(images.device)


def read_exported_meta(path: str | Path, fmt: str):
    """The :class:`s3k.detector.DetectorMeta` an exported file carries."""
    if fmt == "onnx":
        import onnx
        from google.protobuf.message import DecodeError

        try:
            model = onnx.load(str(path), load_external_data=False)
        except DecodeError:
            raise UserError(f"{path}: not an ONNX file (it does not decode as one)") from None
        props = {p.key: p.value for p in model.metadata_props}
        text = props.get(META_KEY)
    else:
        extra = {f"{META_KEY}.json": ""}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            torch.jit.load(str(path), map_location="cpu", _extra_files=extra)
        text = extra[f"{META_KEY}.json"] or None
    if not text:
        raise UserError(f"{path}: no {META_KEY} in the file; not exported by s3k export")
    try:
        meta = DetectorMeta.from_dict(json.loads(text))
        if len(meta.image_size) != 2 or not meta.keypoints or int(meta.stride) < 1:
            raise ValueError("image_size, keypoints or stride")
    except (TypeError, ValueError, KeyError) as exc:
        raise UserError(f"{path}: its {META_KEY} is not an s3k detector's metadata ({exc})") from None
    return meta


def load_exported(path: str | Path, fmt: str | None = None):
    """An exported detector as a :class:`s3k.detector.Detector` whose networks run in ONNX Runtime: a
    one-pass file, or the ``.json`` a two-pass export writes beside its two files (checked: its fields, its
    crop rule's finite extent, its files inside its own folder). TorchScript files run only with
    ``fmt="torchscript"``: they hold code.

    Raises:
        UserError: one line naming the file and the field, or a TorchScript file not asked for.
    """
    path = Path(path)
    if path.suffix == ".json":
        doc = two_pass_doc(path)
        runtime = runtime_of(path, fmt, str(doc.get("runtime", "onnx")))
        folder = path.resolve().parent
        passes = [load_exported(folder / str(doc[name]), runtime) for name in ("coarse", "fine")]
        rule = CropRule(float(doc["extent"]), int(doc["size"]), float(doc.get("margin", 0.0)))
        return TwoPassDetector(passes[0], passes[1], rule)  # type: ignore[arg-type]
    runtime = runtime_of(path, fmt, None)
    if not path.is_file():
        raise FileNotFoundError(2, "exported detector not found", str(path))
    meta = read_exported_meta(path, runtime)  # first: it refuses a file that is not an export in one line
    return OnePassDetector(_ExportedNetwork(path, runtime), meta, "cpu")
