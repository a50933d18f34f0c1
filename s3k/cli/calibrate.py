"""``s3k calibrate CAM=SOURCE ... --board board.toml --out calibration.toml``: a whole rig from synchronized
board videos or image folders (:mod:`s3k.rigcal`)."""

from __future__ import annotations

import argparse
import time

import numpy as np

from s3k.base.errors import UserError
from s3k.base.outputs import check_output
from s3k.cli import examples
from s3k.cli.options import camera_pairs, number
from s3k.data import imageseq
from s3k.data.formats.anipose import write_anipose_calibration
from s3k.data.formats.sleap import read_sleap_analysis
from s3k.rigcal.boards import Faces, board_from_fields, read_board_toml
from s3k.rigcal.figure import draw_calibration
from s3k.rigcal.report import calibration_report, report_path
from s3k.rigcal.rig import calibrate_sources, refine_with_points


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Calibrate a whole rig from synchronized videos or image folders of a ChArUco board or checkerboard, "
        "one per camera: each camera's intrinsics and distortion, extrinsics chained over the cameras that "
        "share board views, then one bundle adjustment over every camera and board pose (Huber loss). "
        "Prints per camera the reprojection error, views used and image coverage; writes an anipose "
        "calibration.toml that s3k import reads. The world is the first camera (or --origin-view), the unit "
        "the board's."
    )
    parser.epilog = examples(
        "s3k calibrate back=calib/back.mp4 mid=calib/mid.mp4 top=calib/top/ --board board.toml "
        "--out calibration.toml --figure calibration.png",
        "s3k calibrate cam1=c1/ cam2=c2/ --squares 10x7 --square-length 25 --out calibration.toml",
    )
    parser.add_argument(
        "sources",
        nargs="+",
        metavar="CAM=SOURCE",
        help="per camera a video, an image folder or a glob; frames pair by index (videos) or "
        "by the last number in the file names (images)",
    )
    parser.add_argument("--out", required=True, help="anipose calibration.toml to write")
    parser.add_argument("--overwrite", action="store_true", help="replace --out (and --figure) if they exist")
    board = parser.add_argument_group("board (anipose's board.toml, or these options)")
    board.add_argument(
        "--board",
        default=None,
        help="anipose board.toml (board_x, board_y, square_length, "
        "marker_length, marker_bits, dict_size; no marker_length: a checkerboard)",
    )
    board.add_argument("--squares", default=None, metavar="XxY", help="squares along x and y, e.g. 8x11")
    board.add_argument(
        "--square-length",
        type=number(gt=0),
        default=None,
        help="side of a square, in the unit the calibration is to use (e.g. 24 for mm)",
    )
    board.add_argument(
        "--marker-length",
        type=number(ge=0),
        default=0.0,
        help="ArUco marker side for a ChArUco board (default 0: a plain checkerboard)",
    )
    board.add_argument(
        "--dict",
        default="4x4_50",
        metavar="BITSxBITS_SIZE",
        help="ArUco dictionary of a ChArUco board (default 4x4_50)",
    )
    board.add_argument(
        "--inverted",
        action="store_true",
        help="the board is printed inverted (white squares and markers on black); tried anyway when the "
        "board as printed is not found in an image",
    )
    board.add_argument(
        "--one-sided",
        action="store_true",
        help="do not look for a two-sided board's back face (by default an image where the board is not "
        "found is flipped left-right and searched again: a camera behind the board sees its front mirrored)",
    )
    solve = parser.add_argument_group("solver")
    solve.add_argument("--every", type=number(int, ge=1), default=1, help="use every N-th frame (default 1)")
    solve.add_argument(
        "--free-principal-point",
        action="store_true",
        help="refine each camera's principal point (default: the image centre, anipose's model)",
    )
    solve.add_argument(
        "--radial",
        type=number(int, ge=1, le=2),
        default=2,
        help="radial distortion terms: 1 (k1, anipose's model) or 2 (k1, k2; default)",
    )
    solve.add_argument(
        "--labels",
        nargs="+",
        default=None,
        metavar="CAM=FILE",
        help="SLEAP analysis files (.h5) of the recording per camera: their keypoints seen by >= 2 "
        "cameras in a frame join the adjustment as extra correspondences (after the board-only "
        "solution)",
    )
    solve.add_argument(
        "--allow-identical-views",
        action="store_true",
        help="calibrate cameras whose sources show the same board views (the same images given twice; "
        "refused by default)",
    )
    solve.add_argument(
        "--origin-view",
        type=number(int, ge=0),
        default=None,
        metavar="FRAME",
        help="the board's pose in this frame is the world frame (default: the first camera's)",
    )
    solve.add_argument(
        "--loss-scale",
        type=number(gt=0),
        default=1.0,
        metavar="PX",
        help="Huber loss scale: residuals beyond it weigh linearly (default 1 px)",
    )
    parser.add_argument(
        "--report",
        default=None,
        metavar="JSON",
        help="write the calibration report here (default: beside --out, calibration.report.json)",
    )
    parser.add_argument(
        "--bootstrap",
        type=number(int, ge=0),
        default=8,
        metavar="N",
        help="bootstrap resamples of the board frames for the cameras' centre and orientation spread "
        "(default 8, seed 0; 0 skips them)",
    )
    parser.add_argument(
        "--figure",
        default=None,
        metavar="PNG",
        help="write the picture: detected vs reprojected corners per camera, cameras from above",
    )


def _parsed(text: str) -> object:
    """An option's part as a number when it is one (the board's check names what it is not)."""
    try:
        return int(text)
    except ValueError:
        return text


def _board(args):
    """The board of ``--board`` (anipose's board.toml) or of ``--squares``, ``--square-length``,
    ``--marker-length`` and ``--dict``, checked by the one check of a board (:func:`board_from_fields`)."""
    if args.board:
        return read_board_toml(args.board)
    if not args.squares or not args.square_length:
        raise UserError(
            "no board given", hint="pass --board board.toml, or --squares XxY and --square-length"
        )
    squares = args.squares.lower().split("x")
    bits_text, _, size_text = args.dict.lower().partition("_")
    bits = bits_text.split("x")
    if len(squares) != 2 or len(bits) != 2 or bits[0] != bits[1] or not size_text:
        raise UserError(
            f"--squares {args.squares!r} / --dict {args.dict!r}: expected e.g. 8x11 and 4x4_50"
        )
    fields = {"board_x": _parsed(squares[0]), "board_y": _parsed(squares[1]),
              "square_length": args.square_length, "marker_length": args.marker_length,
              "marker_bits": _parsed(bits[0]), "dict_size": _parsed(size_text)}
    names = {"board_x": f"--squares {args.squares}: squares along x",
             "board_y": f"--squares {args.squares}: squares along y", "square_length": "--square-length",
             "marker_length": "--marker-length", "marker_bits": f"--dict {args.dict}: marker bits",
             "dict_size": f"--dict {args.dict}: dictionary size"}
    return board_from_fields(fields, names=names)


def _label_tables(args, cameras: list[str]) -> dict:
    """``--labels``' SLEAP analysis tables per camera, read and matched to the cameras before any work."""
    files = camera_pairs(args.labels, "--labels")
    unknown = [c for c in files if c not in cameras]
    if unknown:
        raise UserError(
            f"--labels: camera {unknown[0]!r} is not calibrated here (cameras: {', '.join(cameras)})",
            hint="name the cameras of CAM=SOURCE",
        )
    return {c: read_sleap_analysis(f) for c, f in files.items()}


def _with_labels(cal, args, tables: dict):
    """The calibration refined with ``--labels``' SLEAP analysis tables as further correspondences."""
    T = max(t.uv.shape[0] for t in tables.values())
    K = max(t.uv.shape[1] for t in tables.values())
    uv = np.full((T, len(cal.names), K, 2), np.nan)
    for c, t in tables.items():
        uv[: t.uv.shape[0], cal.names.index(c), : t.uv.shape[1]] = t.uv
    return refine_with_points(
        cal,
        uv,
        radial=args.radial,
        free_principal_point=args.free_principal_point,
        loss_scale_px=args.loss_scale,
    )


def _source_files(source: str) -> list[str]:
    """The files a camera's source names: its video, or every image of its folder or pattern."""
    if imageseq.is_sequence(source):
        return [str(f) for f in imageseq.sequence_files(source)]
    return [source]


def run(args: argparse.Namespace) -> int:
    """``s3k calibrate``: the rig from the board views, printed per camera, written as anipose TOML."""
    sources = camera_pairs(args.sources, "CAM=SOURCE")
    labels = camera_pairs(args.labels, "--labels") if args.labels else {}
    inputs = {"--board": args.board, "--labels": list(labels.values()),
              "CAM=SOURCE": [f for source in sources.values() for f in _source_files(source)]}
    check_output(args.out, args.overwrite, inputs=inputs, option="--out")
    report_file = args.report or report_path(args.out)
    check_output(report_file, args.overwrite, inputs={**inputs, "--out": args.out}, option="--report")
    if args.figure:
        check_output(args.figure, args.overwrite, inputs={**inputs, "--out": args.out}, option="--figure")
    board = _board(args)
    tables = _label_tables(args, list(sources)) if args.labels else {}
    start = time.perf_counter()
    cal = calibrate_sources(
        sources,
        board,
        every=args.every,
        free_principal_point=args.free_principal_point,
        radial=args.radial,
        origin_view=args.origin_view,
        loss_scale_px=args.loss_scale,
        identical=args.allow_identical_views,
        faces=Faces(normal=not args.inverted, back=not args.one_sided),
    )
    if tables:
        cal = _with_labels(cal, args, tables)
    seconds = time.perf_counter() - start
    print(
        f"calibrated {len(cal.names)} cameras from {len(cal.view_keys)} board views ({board.describe()}) in "
        f"{seconds:.1f} s; world: {cal.origin}, unit {cal.rig().units}"
    )
    print(cal.format())
    report = calibration_report(cal, resamples=args.bootstrap)
    print(report.format())
    write_anipose_calibration(args.out, cal.rig())
    print(f"wrote {args.out}")
    report.write(report_file)
    print(f"wrote {report_file}")
    if args.figure:

        draw_calibration(cal, args.figure)
        print(f"wrote {args.figure}")
    return 0
