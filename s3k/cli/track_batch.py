"""``s3k track RUN --manifest FILE --out FOLDER``: every session of a manifest tracked on a Ray cluster
(:func:`s3k.inference.batch.track_batch`); the manifest is ``s3k import``'s (``docs/scale.md``)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from s3k.base.errors import UserError
from s3k.cli import import_
from s3k.cli.options import add_frame_offsets_option, add_rig_options, camera_pairs, number, rig_options
from s3k.data.add_session import manifest_sessions
from s3k.inference.batch import BatchSession, table, track_batch
from s3k.inference.track_config import TrackConfig

TRACK_KEYS = ("session", "calibration", "videos", "video_region", "units", "crop", "frame_offsets", "out")
"""A manifest session's entries that tracking reads; ``s3k import``'s other options are left to it."""


def add_batch_options(parser: argparse.ArgumentParser) -> None:
    """The options of ``s3k track --manifest``."""
    parser.add_argument("--manifest", default=None, metavar="FILE",
                        help="track every session of this manifest (s3k import's TOML or JSON: session, "
                        "calibration, videos, and out, the CSV inside --out, default <session>.csv), on a "
                        "Ray cluster; --out is then the folder of the tracks")
    parser.add_argument("--workers", type=number(int, ge=1), default=None,
                        help="with --manifest: sessions (or chunks) tracked at once, one thread each "
                        "(default: the cluster's CPUs)")
    parser.add_argument("--address", default=None,
                        help="with --manifest: the Ray cluster to join, e.g. HEAD:6379 (default: the "
                        "RAY_ADDRESS environment variable, else a cluster of this machine, started and "
                        "stopped by the command)")
    parser.add_argument("--chunk-frames", type=number(int, ge=1), default=None,
                        help="with --manifest: detect each session in parts of this many frames on several "
                        "workers (rounded up to a multiple of --batch), filtered as one track (default: "
                        "whole sessions)")


def check_no_batch_options(args: argparse.Namespace) -> None:
    """Refuse the options of a batch given without ``--manifest``."""
    for option in ("workers", "address", "chunk_frames"):
        if getattr(args, option) is not None:
            raise UserError(f"--{option.replace('_', '-')} applies to --manifest only",
                            hint="give --manifest FILE, or leave it out")


def _import_options() -> set[str]:
    """The options of ``s3k import`` (a manifest's entries for it, which tracking leaves alone)."""
    parser = argparse.ArgumentParser()
    import_.configure_parser(parser)
    return {a.dest for a in parser._actions}


def _session_parser(args: argparse.Namespace) -> argparse.ArgumentParser:
    parser = import_._ManifestParser(prog=f"s3k track --manifest {args.manifest}")
    parser.add_argument("--session", required=True)
    parser.add_argument("--videos", nargs="+", required=True)
    parser.add_argument("--out", default=None)
    add_rig_options(parser, calibration_required=True)
    add_frame_offsets_option(parser)
    shared = ("units", "crop", "fit", "device", "other_rig", "video_region", "frame_offsets")
    parser.set_defaults(**{name: getattr(args, name) for name in shared})
    return parser


def manifest_track_sessions(args: argparse.Namespace) -> list[BatchSession]:
    """The sessions of ``--manifest`` with their rigs (the command line's rig options, each session's own
    entries over them) and CSVs inside ``--out``."""
    entries = manifest_sessions(args.manifest)
    folder, out = Path(args.manifest).parent, Path(args.out)
    known = _import_options()
    parser = _session_parser(args)
    sessions = []
    for entry in entries:
        if "dataset" in entry:
            raise UserError(f"--manifest {args.manifest}: session {entry['session']} names a dataset; "
                            "tracking needs its videos and calibration")
        unknown = [k for k in entry if k not in TRACK_KEYS and k.replace("-", "_") not in known]
        if unknown:
            raise UserError(f"--manifest {args.manifest}: session {entry['session']}: unknown field "
                            f"{unknown[0]!r} (tracking reads {', '.join(TRACK_KEYS)})")
        mine: dict[str, Any] = {k: v for k, v in entry.items() if k.replace("-", "_") in TRACK_KEYS}
        try:
            options = parser.parse_args(import_._argv(mine, folder))
        except UserError as exc:
            raise UserError(f"--manifest {args.manifest}: session {entry['session']}: {exc}") from None
        videos = camera_pairs(options.videos, f"--manifest session {options.session}: videos")
        sessions.append(BatchSession(options.session, {c: Path(p) for c, p in videos.items()},
                                     rig_options(options, list(videos)),
                                     out / (options.out or f"{options.session}.csv")))
    return sessions


def run_batch(args: argparse.Namespace, config: TrackConfig) -> int:
    """``s3k track RUN --manifest FILE --out FOLDER``: the per-session table; exit 1 when one failed."""
    if args.videos or args.calibration:
        raise UserError(f"--manifest {args.manifest}: each session names its videos and calibration",
                        hint="give no --videos or --calibration with --manifest")
    results = track_batch(args.run, manifest_track_sessions(args), args.out, config, workers=args.workers,
                          address=args.address, chunk_frames=args.chunk_frames, overwrite=args.overwrite,
                          progress=config.outputs.progress)
    print("\n".join(table(results)))
    failed = [r.session for r in results if r.status == "failed"]
    if failed:
        print(f"{len(failed)} of {len(results)} sessions failed ({', '.join(failed)}); run the same command "
              "again to retry them (finished sessions are skipped)")
    return 1 if failed else 0
