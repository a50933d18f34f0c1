"""Each camera's map onto a detector's input, as ``s3k track`` computes it, for the tests that build an oracle
detector's answers in the network's pixels."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

from s3k.data import video
from s3k.geometry.warp import crop_resize_matrix
from s3k.inference.session import fit_box


def rig_inputs(videos: dict[str, Path], rig, net_size: tuple[int, int], fit: str = "pad"):
    """``([SimpleNamespace(name, video_size, fps, box, M)], cameras (C,))`` of ``videos`` on ``rig``."""
    inputs = []
    for name, path in videos.items():
        size = video.frame_size(path)
        box = fit_box(size, net_size, fit)  # type: ignore[arg-type]
        inputs.append(SimpleNamespace(name=name, video_size=size, fps=video.frame_rate(path), box=box,
                                      M=crop_resize_matrix(box, net_size)))
    return inputs, rig.select(list(videos)).cameras
