"""A run folder holding an untrained tiny detector, for the tests of the commands that load one: ``save_run``
of any meta, and ``make_run`` (the export tests' run, ``RUN_SIZE``)."""

from __future__ import annotations

from pathlib import Path

import torch

from s3k.detector import MODEL_FILE, DetectorMeta, atomic_save, build_model
from s3k.model import UNetConfig
from s3k.run_folder import RunFolder


def trained_like_batch_norm(net: torch.nn.Module, var: tuple[float, float] = (0.3, 3.0)) -> torch.nn.Module:
    """Give ``net``'s BatchNorm layers statistics and affine weights far from the identity (as after
    training), so that folding them into the convolutions and eval-mode inference are exercised."""
    for m in net.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.3, 0.3)
            m.running_var.uniform_(*var)
            m.weight.data.uniform_(0.5, 1.5)
            m.bias.data.uniform_(-0.2, 0.2)
    return net


def save_run(path: Path, meta: DetectorMeta, seed: int, dataset: str | None = None,
             head_std: float | None = None) -> Path:
    """Write ``path/config.json`` and ``path/model.pt`` with the network of ``meta`` drawn from ``seed``.

    Its BatchNorm layers get statistics far from the identity, so that folding them into the convolutions
    (export) and eval-mode inference are exercised. ``head_std`` redraws the head's weights with that spread,
    for heatmaps peaked like a trained model's.
    """
    torch.manual_seed(seed)
    net = trained_like_batch_norm(build_model(meta))
    if head_std is not None:
        net.head.weight.data.normal_(0, head_std)
    path.mkdir(parents=True)
    RunFolder(path).write_record({}, meta.to_dict(), dataset)
    atomic_save({"model": net.state_dict(), "meta": meta.to_dict()}, path / MODEL_FILE)
    return path


RUN_SIZE = (40, 32)  # (W, H): not square, heatmap grid not a multiple of 2^depth (padding path of the UNet)


def make_run(path: Path, dataset: str | None = None, norm: str = "batch") -> Path:
    """A run folder with a tiny detector whose BatchNorm statistics are far from the identity."""
    meta = DetectorMeta(keypoints=["a", "b", "c"], cameras=["cam0", "cam1", "cam2", "cam3"],
                        image_size=RUN_SIZE, stride=2, sigma=2.0,
                        model=UNetConfig(channels=(8, 16, 16), res_blocks=1, norm=norm).to_dict())
    # Larger head weights than at initialization, so that heatmaps are peaked like a trained model's.
    return save_run(path, meta, seed=1, dataset=dataset, head_std=0.5)
