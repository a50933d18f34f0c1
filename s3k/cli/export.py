"""`s3k export`: export a trained detector to ONNX or TorchScript and verify it
(:mod:`s3k.inference.export`)."""

from __future__ import annotations

import argparse
import json
import sys
import zipfile
from pathlib import Path

from s3k.base.errors import UserError
from s3k.base.outputs import check_companion, check_output, staging_folder
from s3k.cli import examples
from s3k.cli.options import number
from s3k.inference.export import (
    DEFAULT_TOLERANCE,
    EXPORTED_TWO_PASS,
    FORMATS,
    META_KEY,
    export_detector,
    written_files,
)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Export a trained detector: images (N, 3, H, W) in [0, 1] -> heatmap logits (and, with "
        "--with-moments, means and confidences), then verify the file against PyTorch."
    )
    parser.epilog = examples("s3k export runs/box --format onnx --out detector.onnx",
                             "s3k export runs/box --format torchscript --out detector.pt --with-moments")
    parser.add_argument("run", help="run folder written by 's3k train'")
    parser.add_argument("--format", required=True, choices=FORMATS, help="onnx or torchscript")
    parser.add_argument("--out", required=True,
                        help="file to write (e.g. detector.onnx, detector.pt; never a file of the run or of "
                             "a dataset); a two-pass run writes OUT.coarse.EXT, OUT.fine.EXT and OUT.json "
                             "(the crop rule)")
    parser.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    parser.add_argument("--with-moments", action="store_true",
                        help="also output means (N, K, 2) in pixels and confidence (N, K)")
    parser.add_argument("--opset", type=number(int, ge=11, le=20), default=17,
                        help="ONNX opset version (default 17)")
    parser.add_argument("--no-fuse", action="store_true", help="keep BatchNorm layers (default: folded)")
    parser.add_argument("--tolerance", type=number(gt=0), default=DEFAULT_TOLERANCE,
                        help="largest allowed difference from PyTorch (default 1e-4)")
    parser.add_argument("--verify-data", default=None,
                        help="dataset folder whose frames are used to verify (default: the run's dataset)")
    parser.add_argument("--checkpoint", default=None,
                        help="file in the run folder to export instead of the final model (default: "
                             "model.pt, else the last checkpoint.pt)")


def run(args: argparse.Namespace) -> int:
    checkpoint = Path(args.run) / args.checkpoint if args.checkpoint else None
    out = check_output(args.out, args.overwrite, inputs={"--checkpoint": checkpoint})
    for path in written_files(args.run, out):  # a two-pass run writes a file per pass and the rule beside it
        if path != out:
            check_output(path, True, inputs={"--checkpoint": checkpoint})
            check_companion(path, args.overwrite, str(out), lambda p: _exported(p, args.format))
    with staging_folder(out) as tmp:  # written and checked beside --out; moved into place only if it passes
        try:
            report = export_detector(args.run, args.format, tmp / out.name, with_moments=args.with_moments,
                                     fuse=not args.no_fuse, opset=args.opset, tolerance=args.tolerance,
                                     verify_data=args.verify_data, checkpoint=args.checkpoint)
        except ImportError as exc:  # onnx / onnxruntime are optional
            raise UserError(f"--format {args.format} needs a package that is not installed ({exc})") from exc
        if report.ok:
            report.files = [p.replace(out.parent / p.name) for p in report.files]
        report.path = out.parent / report.path.name
    diffs = ", ".join(f"{k} {v:.3g}" for k, v in report.max_diff.items())
    print(f"wrote {', '.join(str(f) for f in report.files)} ({report.format}; outputs: "
          f"{', '.join(report.outputs)})")
    print(f"max |difference| from PyTorch on {report.inputs}: {diffs} (tolerance {report.tolerance:g})")
    if report.max_diff_mm is None:
        print("3D points not compared: no dataset frames (give --verify-data)")
    else:
        print(f"max 3D difference from PyTorch's detector on {report.frames_3d} frames: "
              f"{report.max_diff_mm:.3g} mm (tolerance {report.tolerance_mm:g} mm)")
    if not report.ok:
        print(f"s3k export: error: {report.path} does not reproduce the PyTorch model: "
              f"{'; '.join(report.failures())}; nothing was written", file=sys.stderr)
        return 1
    return 0


def _exported(path, fmt: str) -> bool:
    """True when ``path`` is a file ``s3k export`` wrote (a two-pass export's description, or a pass's
    network carrying s3k's metadata); read without running anything in it."""
    try:
        if path.suffix == ".json":
            return json.loads(path.read_text()).get("format") == EXPORTED_TWO_PASS
        if fmt == "onnx":
            import onnx

            model = onnx.load(str(path), load_external_data=False)
            return any(p.key == META_KEY for p in model.metadata_props)
        with zipfile.ZipFile(path) as z:
            return any(n.endswith(f"/extra/{META_KEY}.json") for n in z.namelist())
    except Exception:  # noqa: BLE001 - anything unreadable is not ours
        return False
