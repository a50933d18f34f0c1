"""Size of the Rerun recordings of ``s3k stream --rerun`` and ``s3k view`` on the real 4-camera recording
(1280x1024 views), per frame, read back with Rerun's own reader.

    python benchmarks/rerun_size.py --out docs/results/benchmarks/rerun-size.json

Measured: ``s3k stream RUN --rerun FILE.rrd`` over the first ``--frames`` frames of the four videos at
``--image-scale`` 0.5 (the default) and 1 (full size), JPEG quality 75, with an untrained tiny detector of
the recording's 15 keypoints and skeleton (the recording's size does not depend on the detector's accuracy);
``s3k view`` of the committed tracks ``docs/results/real/tracked-s3k.csv`` with the videos at both scales;
and, as the baseline, the same views logged as the stream logged them before (raw ``rr.Image`` per view and
the 3D points). The last line is one JSON object with the figures, the commands, the git revision and the
machine.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import finish, git_revision, machine_info  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared/data/real/sleap-anipose-minimal_session/minimal_session"
CAMERAS = ("back", "mid", "side", "top")


def _tiny_run(path: Path, real: Path) -> Path:
    """An untrained tiny detector with the recording's keypoints and its SLEAP skeleton."""
    import sleap_io as sio
    import torch

    from s3k.detector import MODEL_FILE, DetectorMeta, atomic_save, build_model
    from s3k.model import UNetConfig
    from s3k.run_folder import RunFolder

    skeleton = sio.load_slp(str(real / "back" / "minimal_back_proofread.slp"), open_videos=False).skeletons[0]
    meta = DetectorMeta(keypoints=list(skeleton.node_names), cameras=list(CAMERAS), image_size=(64, 52),
                        stride=2, sigma=2.0, units="mm", skeleton=list(skeleton.edge_names),
                        model=UNetConfig(channels=(8, 8), res_blocks=1).to_dict())
    torch.manual_seed(0)
    path.mkdir(parents=True)
    RunFolder(path).write_record({}, meta.to_dict())
    atomic_save({"model": build_model(meta).state_dict(), "meta": meta.to_dict()}, path / MODEL_FILE)
    return path


def _baseline(path: Path, videos: list[str], frames: int) -> None:
    """The views and points as ``s3k stream --rerun`` logged them before: raw images, no cameras."""
    import numpy as np
    import rerun as rr

    from s3k.data.video import synchronized_frames

    rec = rr.RecordingStream("s3k_stream_before")
    rec.save(str(path))
    for i, views in synchronized_frames(videos, 0, frames):
        rec.set_time("frame", sequence=i)
        for cam, view in zip(CAMERAS, views):
            rec.log(f"views/{cam}/image", rr.Image(view))
        rec.log("world/keypoints", rr.Points3D(np.zeros((15, 3))))
    rec.flush()
    rec.disconnect()


def _relative(arg: str, tmp: str) -> str:
    """A command's argument with the repository's root and the work folder left out of its paths."""
    arg = arg.replace(tmp, "TMP")
    if "/" in arg and Path(arg.split("=", 1)[-1]).is_absolute():
        head, sep, path = arg.rpartition("=")
        return head + sep + os.path.relpath(path, ROOT)
    return arg


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--real", default=str(REAL), help="the recording's folder (default: %(default)s)")
    parser.add_argument("--frames", type=int, default=20, help="frames to log (default %(default)s)")
    parser.add_argument("--out", default=None, help="JSON file to write")
    args = parser.parse_args()
    started = time.perf_counter()
    from s3k.cli import main as s3k
    from s3k.inference.rerun_log import recording_summary

    real = Path(args.real)
    videos = [f"{c}={real / c / f'minimal_{c}.mp4'}" for c in CAMERAS]
    figures = {}
    with tempfile.TemporaryDirectory() as tmp:
        run = _tiny_run(Path(tmp) / "run", real)
        commands = {}
        for scale in ("0.5", "1"):
            commands[f"stream_scale_{scale}"] = [
                "stream", str(run), "--calibration", str(real / "calibration.toml"), "--max-frames",
                str(args.frames), "--image-scale", scale, "--rerun", f"{tmp}/stream-{scale}.rrd",
                "--sources", *videos]
            commands[f"view_tracks_scale_{scale}"] = [
                "view", str(ROOT / "docs/results/real/tracked-s3k.csv"), "--calibration",
                str(real / "calibration.toml"), "--videos", *videos, "--skeleton",
                str(real / "back" / "minimal_back_proofread.slp"), "--max-frames", str(args.frames),
                "--image-scale", scale, "--save", f"{tmp}/view-{scale}.rrd"]
        for name, argv in commands.items():
            with contextlib.redirect_stdout(io.StringIO()):
                if s3k(argv) != 0:
                    raise SystemExit(f"s3k {' '.join(argv)} failed")
            target = argv[argv.index("--rerun") + 1] if "--rerun" in argv else argv[argv.index("--save") + 1]
            summary = recording_summary(target)
            figures[name] = {"frames": len(summary["frames"]), "bytes": summary["bytes"],
                             "mb_per_frame": round(summary["bytes_per_frame"] / 1e6, 4)}
        _baseline(Path(tmp) / "before.rrd", [v.split("=", 1)[1] for v in videos], args.frames)
        size = (Path(tmp) / "before.rrd").stat().st_size
        figures["stream_before_raw_images"] = {"frames": args.frames, "bytes": size,
                                               "mb_per_frame": round(size / args.frames / 1e6, 4)}
    result = {"benchmark": "rerun_size", "view_size": [1280, 1024], "views": len(CAMERAS), "jpeg_quality": 75,
              "figures": figures, "commands": {k: "s3k " + " ".join(_relative(a, tmp) for a in v)
                                               for k, v in commands.items()},
              "command": "python benchmarks/rerun_size.py " + " ".join(sys.argv[1:]),
              "git_revision": git_revision(), "machine": machine_info()}
    finish(result, started, args.out)


if __name__ == "__main__":
    main()
