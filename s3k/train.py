"""``s3k train DATASET --out RUN``: semi-supervised training of the keypoint network (S3K, DESIGN 1).

Each step draws a labelled batch and, once the self-supervised term is on, an unlabelled batch; both are
augmented per image with a random similarity that updates the intrinsics (``s3k.augment``), go through the
network in one forward pass, and give

    L = L_sup + alpha(step) * L_unsup + weight_decay * ||theta_non-bias||^2.

``alpha(step)`` is 0 for ``warmup_steps`` labels-only steps, then rises linearly to ``alpha`` over
``ramp_steps`` (``TrainConfig.alpha_at``): from a random network the self-supervised term would lock in a
collapse (every keypoint at one confident 3D point), so the labels first shape the heatmaps. ``--no-unsup``
trains the labels-only baseline: same network, same labels, no unlabelled batch.

Robustness:

- a step whose loss or gradient is not finite is reported with its step number in the log and skipped
  (parameters, optimizer and normalization statistics unchanged); after ``max_nonfinite`` consecutive ones
  the run stops cleanly with exit status 1; such a state is never checkpointed.
- ``RUN/checkpoint.pt`` (written atomically) holds the model, optimizer, scheduler, every rank's RNG states
  and the step; ``--resume`` continues a killed run exactly where its last checkpoint left it.
- every ``val_every`` steps the validation split is predicted: metrics, images of predicted vs true keypoints
  with heatmaps (TensorBoard), and a collapse check: a warning when the mean pairwise distance between the
  triangulated keypoints falls below ``collapse_fraction`` of the labelled layout's.

Distributed: under ``torchrun --nproc_per_node N`` the same command trains with DistributedDataParallel (gloo
on CPU, NCCL on GPU); each rank draws from its own shard of the frames; only rank 0 writes logs and
checkpoints.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import os
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
from torch import nn

from s3k.augment import Augmentation, NoiseBank, augment_frames
from s3k.config import TrainConfig, add_config_arguments, config_from_args, config_from_dict
from s3k.frames import FrameBatch, FrameStore, images_to_float, model_image_size, open_dataset
from s3k.geometry import Cameras, triangulate_pixels
from s3k.losses import l2_non_bias, self_supervised_loss, supervised_loss
from s3k.model import UNet, UNetConfig
from s3k.run import (
    CHECKPOINT_FILE,
    LOG_FILE,
    MODEL_FILE,
    TENSORBOARD_DIR,
    DetectorMeta,
    atomic_save,
    read_run_config,
    write_run_config,
)

log = logging.getLogger("s3k.train")


@dataclass
class TrainResult:
    """What :func:`train` returns.

    Attributes:
        model: the trained network (unwrapped from DDP), in train mode.
        meta: its :class:`DetectorMeta`.
        step: completed steps.
        status: "done", "nonfinite" (stopped after too many non-finite steps).
        history: per validation, a dict of step and metrics.
        timing: mean seconds per step and the fraction spent loading + augmenting data.
    """

    model: nn.Module
    meta: DetectorMeta
    step: int
    status: str
    history: list[dict[str, Any]] = field(default_factory=list)
    timing: dict[str, float] = field(default_factory=dict)


# ------------------------------------------------------------------------------------------------------------
# Distributed helpers


@dataclass
class DistInfo:
    rank: int = 0
    world: int = 1
    local_rank: int = 0
    created: bool = False

    @property
    def enabled(self) -> bool:
        return self.world > 1

    @property
    def main(self) -> bool:
        return self.rank == 0


def init_distributed(device: str) -> DistInfo:
    """Join the process group when launched by torchrun (WORLD_SIZE > 1)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return DistInfo()
    created = False
    if not dist.is_initialized():
        use_nccl = torch.cuda.is_available() and device != "cpu"
        dist.init_process_group("nccl" if use_nccl else "gloo")
        created = True
    return DistInfo(dist.get_rank(), dist.get_world_size(), int(os.environ.get("LOCAL_RANK", "0")), created)


def shard(ids: np.ndarray, info: DistInfo) -> np.ndarray:
    """Rank's share of the frames (every rank keeps all frames when there are fewer than ranks)."""
    if not info.enabled or len(ids) < info.world:
        return ids
    return ids[info.rank::info.world]


# ------------------------------------------------------------------------------------------------------------
# Logging


class _TqdmHandler(logging.Handler):
    def emit(self, record: logging.LogRecord) -> None:
        from tqdm import tqdm

        with contextlib.suppress(Exception):
            tqdm.write(self.format(record))


def _setup_logging(run_dir: Path, main: bool) -> list[logging.Handler]:
    log.setLevel(logging.INFO)
    log.propagate = False
    for h in list(log.handlers):
        if getattr(h, "_s3k", False):
            log.removeHandler(h)
            h.close()
    handlers: list[logging.Handler] = []
    if main:
        fmt = logging.Formatter("%(asctime)s %(levelname)s %(message)s", "%Y-%m-%d %H:%M:%S")
        fh = logging.FileHandler(run_dir / LOG_FILE)
        fh.setFormatter(fmt)
        th = _TqdmHandler()
        th.setFormatter(logging.Formatter("%(levelname)s %(message)s"))
        handlers = [fh, th]
    else:
        handlers = [logging.NullHandler()]
    for h in handlers:
        h._s3k = True  # type: ignore[attr-defined]
        log.addHandler(h)
    return handlers


# ------------------------------------------------------------------------------------------------------------
# The pieces of a step


def mean_pairwise_distance(X: torch.Tensor, valid: torch.Tensor) -> float:
    """Mean distance over all pairs of valid keypoints of every frame.

    Args:
        X: (B, K, 3) points.
        valid: (B, K) bool.

    Returns:
        The mean (NaN when no frame has two valid keypoints).
    """
    d = torch.cdist(X.double(), X.double())  # (B, K, K)
    K = X.shape[1]
    pair = valid[:, :, None] & valid[:, None, :] & torch.triu(torch.ones(K, K, dtype=torch.bool), 1)
    return float(d[pair].mean()) if pair.any() else float("nan")


def draw_batch(store: FrameStore, n: int, gen: torch.Generator, distinct: bool) -> FrameBatch:
    """``n`` random frames of ``store`` (without repeats when ``distinct`` and there are enough)."""
    if distinct and len(store) >= n:
        pos = torch.randperm(len(store), generator=gen)[:n]
    else:
        pos = torch.randint(len(store), (n,), generator=gen)
    return store.get(pos.numpy())


def prepare(batch: FrameBatch, device: torch.device, aug: Augmentation | None, gen: torch.Generator,
            labels: bool, noise_bank: NoiseBank | None = None
            ) -> tuple[torch.Tensor, Cameras, torch.Tensor | None, torch.Tensor | None]:
    """Images (B, C, 3, H, W) float on ``device``, cameras and labels, augmented when ``aug`` is given."""
    cams = batch.cams.to(device=device)
    uv = batch.labels_uv.to(device) if labels and batch.labels_uv is not None else None
    mask = batch.labels_mask.to(device) if labels and batch.labels_mask is not None else None
    if aug is not None:
        images, K, uv, _ = augment_frames(batch.images, cams.K, aug, gen, uv=uv, device=device,
                                          noise_bank=noise_bank)
        cams = Cameras(K, cams.dist, cams.R, cams.t)
    else:
        images = images_to_float(batch.images, device)
    return images, cams, uv, mask


def compute_losses(model: nn.Module, lab: tuple, unl: tuple | None, cfg: TrainConfig, alpha: float,
                   weight_decay_model: nn.Module) -> tuple[torch.Tensor, dict[str, float]]:
    """The training loss of one step (one forward pass over labelled and unlabelled images).

    Args:
        model: the (possibly DDP-wrapped) network.
        lab: (images (Bl, C, 3, H, W), cams (Bl, C), labels_uv (Bl, C, K, 2), labels_mask (Bl, C, K)).
        unl: (images (Bu, C, 3, H, W), cams (Bu, C)) or None when the self-supervised term is off.
        cfg: configuration (stride, sigma, weight decay).
        alpha: weight of the self-supervised term at this step.
        weight_decay_model: the unwrapped network (for the L2 term).

    Returns:
        ``(loss, terms)``: the scalar loss and a dict of float terms for logging.
    """
    images_l, cams_l, uv_l, mask_l = lab
    Bl, C = images_l.shape[:2]
    images = images_l if unl is None else torch.cat([images_l, unl[0]])
    flat = images.reshape(-1, *images.shape[2:]).contiguous(memory_format=torch.channels_last)
    logits = model(flat)
    logits = logits.float().reshape(images.shape[0], C, *logits.shape[1:])
    sigma = cfg.sigma_px()
    l_sup, info = supervised_loss(logits[:Bl], cams_l, uv_l, mask_l, cfg.stride, sigma)
    loss = l_sup
    terms = {"sup": float(l_sup.detach())}
    if unl is not None:
        l_uns, info_u = self_supervised_loss(logits[Bl:], unl[1], cfg.stride, sigma)
        loss = loss + alpha * l_uns
        terms["unsup"] = float(l_uns.detach())
        terms["unsup_valid"] = float(info_u["points_valid"].float().mean())
        terms["unsup_weight"] = float(info_u["weights"].mean())
    if cfg.weight_decay > 0:
        l2 = l2_non_bias(weight_decay_model)
        loss = loss + cfg.weight_decay * l2
        terms["l2"] = float(l2.detach())
    terms["loss"] = float(loss.detach())
    return loss, terms


def labelled_layout(store: FrameStore) -> float:
    """Mean pairwise distance of the keypoints triangulated from the labels (the reference layout size)."""
    dists, counts = [], []
    for batch in store.batches(64):
        w = batch.labels_mask.float()
        cams = batch.cams.to(dtype=torch.float64)
        X, valid = triangulate_pixels(cams, batch.labels_uv.double(), w.double())
        valid = valid & (batch.labels_mask.sum(dim=1) >= 2)
        d = mean_pairwise_distance(X, valid)
        if math.isfinite(d):
            n = int(valid.sum())
            dists.append(d * n)
            counts.append(n)
    return float(sum(dists) / sum(counts)) if counts else float("nan")


# ------------------------------------------------------------------------------------------------------------
# Training


def _lr_lambda(cfg: TrainConfig):
    def f(step: int) -> float:
        frac = min(max(step / max(cfg.steps, 1), 0.0), 1.0)
        return cfg.lr_final + (1.0 - cfg.lr_final) * 0.5 * (1.0 + math.cos(math.pi * frac))

    return f


def _rng_state(gen: torch.Generator) -> dict[str, Any]:
    state: dict[str, Any] = {"gen": gen.get_state(), "torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def _set_rng_state(gen: torch.Generator, state: dict[str, Any]) -> None:
    gen.set_state(state["gen"])
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def _all_finite(module: nn.Module) -> bool:
    return all(bool(torch.isfinite(t).all()) for t in list(module.parameters()) + list(module.buffers())
               if t.is_floating_point())


def train(data: str | Path, out: str | Path, cfg: TrainConfig, resume: bool = False,
          callback=None) -> TrainResult:
    """Train a detector on the dataset folder ``data`` into the run folder ``out``.

    Args:
        data: dataset folder (``s3k.data``), with labelled and (for S3K) unlabelled frames.
        out: run folder (created); see ``s3k.run``.
        cfg: configuration.
        resume: continue from ``out/checkpoint.pt`` (starts afresh when there is none).
        callback: optional ``f(step, terms)`` called after every completed step (``step`` counts completed
            steps; ``terms`` holds the loss terms, alpha, the gradient norm and the step's timings
            ``time_data_s``, ``time_step_s``); an exception it raises aborts the run like a kill would.

    Returns:
        A :class:`TrainResult`.
    """
    cfg.validate()
    info = init_distributed(cfg.device)
    try:
        return _train(Path(data), Path(out), cfg, resume, callback, info)
    finally:
        if info.created and dist.is_initialized():
            dist.destroy_process_group()


def _train(data: Path, out: Path, cfg: TrainConfig, resume: bool, callback, info: DistInfo) -> TrainResult:
    from s3k.predict import pick_device

    device = pick_device(cfg.device, info.local_rank)
    if device.type == "cuda":
        torch.cuda.set_device(device)
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    out.mkdir(parents=True, exist_ok=True)
    ckpt_path = out / CHECKPOINT_FILE
    if info.main and not resume and (ckpt_path.exists() or (out / MODEL_FILE).exists()):
        raise FileExistsError(f"{out} already holds a run; pass --resume to continue it or choose another "
                              "--out")
    _setup_logging(out, info.main)

    probe = open_dataset(data)
    size = model_image_size(probe.image_size, cfg.image_size, cfg.stride)
    ds = open_dataset(data, size)
    labelled_ids = np.asarray(ds.frames("labelled"))
    if len(labelled_ids) == 0:
        raise ValueError(f"{data}: the 'labelled' split is empty; training needs labelled frames")
    unlabelled_ids = np.asarray(ds.frames("unlabelled"))
    if cfg.unsup and len(unlabelled_ids) == 0:
        raise ValueError(f"{data}: the 'unlabelled' split is empty; add unlabelled frames or pass --no-unsup")
    val_ids = np.asarray(ds.frames(cfg.val_split)) if cfg.val_split in ("labelled", "unlabelled", "test") \
        else np.zeros(0, np.int64)
    if len(val_ids) == 0:
        val_ids = unlabelled_ids if len(unlabelled_ids) else labelled_ids
    val_ids = val_ids[np.linspace(0, len(val_ids) - 1, min(cfg.val_frames, len(val_ids))).astype(int)]

    meta = DetectorMeta(
        keypoints=list(ds.keypoints), cameras=list(ds.cameras), image_size=size, stride=cfg.stride,
        sigma=cfg.sigma_px(),
        model=UNetConfig(channels=cfg.channels, res_blocks=cfg.res_blocks, stride=cfg.stride,
                         norm=cfg.norm).to_dict(),
        units=ds.units, source_image_size=tuple(probe.image_size),
    )
    if info.main:
        write_run_config(out, cfg.to_dict(), meta, str(data))

    torch.manual_seed(cfg.seed)
    net = UNet(len(meta.keypoints), UNetConfig.from_dict(meta.model))
    # NHWC is the faster convolution layout for these small channel counts on CPU (and fine on GPU).
    net = net.to(device=device, memory_format=torch.channels_last)  # type: ignore[call-overload]
    gen = torch.Generator().manual_seed(cfg.seed * 1000 + info.rank)
    model: nn.Module = net
    if info.enabled:
        # 1x1 kernels have ambiguous channels-last strides; DDP then copies their (tiny) gradients and warns.
        warnings.filterwarnings("ignore", message="Grad strides do not match bucket view strides")
        model = nn.parallel.DistributedDataParallel(net, device_ids=[device.index] if device.type == "cuda"
                                                    else None)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, _lr_lambda(cfg))

    step, nonfinite_run = 0, 0
    if resume and ckpt_path.exists():
        state = torch.load(ckpt_path, map_location="cpu", weights_only=False)
        net.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        sched.load_state_dict(state["scheduler"])
        step, nonfinite_run = int(state["step"]), int(state.get("nonfinite_run", 0))
        rng = state["rng"]
        if len(rng) == info.world:
            _set_rng_state(gen, rng[info.rank])
        else:
            log.warning("checkpoint was written by %d ranks, now %d: random streams re-seeded", len(rng),
                        info.world)
            gen.manual_seed(cfg.seed * 1000 + info.rank + 7919 * step)
        log.info("resumed from %s at step %d", ckpt_path, step)
    elif resume:
        log.info("no checkpoint in %s: starting a new run", out)

    t0 = time.perf_counter()
    preload = cfg.preload_mb
    lab_store = FrameStore(ds, shard(labelled_ids, info), preload, labels=True)
    unl_store = FrameStore(ds, shard(unlabelled_ids, info), preload) if cfg.unsup else None
    val_store = FrameStore(ds, val_ids, preload, labels=True, points=True) if info.main else None
    ref_layout = labelled_layout(FrameStore(ds, labelled_ids, preload, labels=True))
    n_params = sum(p.numel() for p in net.parameters())
    log.info("dataset %s: %d labelled, %d unlabelled frames, %d cameras, keypoints %s; images %dx%d "
             "(stored %dx%d), heatmaps stride %d, sigma %.2f px; %s, %d parameters; %s on %s x%d; "
             "frames loaded in %.1f s (preloaded: %s)", data, len(labelled_ids), len(unlabelled_ids),
             len(meta.cameras), meta.keypoints, size[0], size[1], probe.image_size[0], probe.image_size[1],
             cfg.stride, meta.sigma, "S3K" if cfg.unsup else "labels only", n_params,
             "DDP" if info.enabled else "single process", device, info.world, time.perf_counter() - t0,
             lab_store.preloaded)
    log.info("labelled layout: mean pairwise keypoint distance %.4g %s", ref_layout, meta.units)

    writer = None
    if info.main:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(str(out / TENSORBOARD_DIR))
    aug = Augmentation.from_config(cfg) if cfg.augment else None
    noise_bank = NoiseBank(seed=cfg.seed)

    def checkpoint(final: bool = False) -> None:
        rng = _rng_state(gen)
        rngs: list[Any] = [None] * info.world
        if info.enabled:
            dist.all_gather_object(rngs, rng)
        else:
            rngs = [rng]
        if not info.main:
            return
        if not _all_finite(net):
            log.error("step %d: model holds non-finite values; checkpoint not written", step)
            return
        state = {"step": step, "model": net.state_dict(), "optimizer": opt.state_dict(),
                 "scheduler": sched.state_dict(), "rng": rngs, "nonfinite_run": nonfinite_run,
                 "meta": meta.to_dict(), "config": cfg.to_dict()}
        atomic_save(state, ckpt_path)
        if final:
            atomic_save({"model": net.state_dict(), "meta": meta.to_dict(), "step": step}, out / MODEL_FILE)

    history: list[dict[str, Any]] = []
    status = "done"
    bar = None
    if info.main and cfg.progress:
        from tqdm import tqdm

        bar = tqdm(total=cfg.steps, initial=step, desc="S3K" if cfg.unsup else "labels only",
                   dynamic_ncols=True, smoothing=0.05)
    t_data = t_total = 0.0
    n_timed = 0
    net.train()
    while step < cfg.steps:
        ts = time.perf_counter()
        alpha = cfg.alpha_at(step)
        lab_batch = draw_batch(lab_store, cfg.batch_labelled, gen, True)
        lab = prepare(lab_batch, device, aug, gen, True, noise_bank)
        unl = None
        if unl_store is not None and alpha > 0:
            unl = prepare(draw_batch(unl_store, cfg.batch_unlabelled, gen, False), device, aug, gen, False,
                          noise_bank)[:2]
        td = time.perf_counter()
        buffers = [b.detach().clone() for b in net.buffers()]
        loss, terms = compute_losses(model, lab, unl, cfg, alpha, net)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        clip = cfg.grad_clip if cfg.grad_clip > 0 else float("inf")
        gnorm = torch.nn.utils.clip_grad_norm_(net.parameters(), clip)
        ok = torch.tensor([float(torch.isfinite(loss) and torch.isfinite(gnorm))], device=device)
        if info.enabled:
            dist.all_reduce(ok, op=dist.ReduceOp.MIN)
        if bool(ok.item()):
            opt.step()
            nonfinite_run = 0
        else:
            opt.zero_grad(set_to_none=True)
            with torch.no_grad():
                for b, saved in zip(net.buffers(), buffers):
                    b.copy_(saved)
            nonfinite_run += 1
            log.warning("step %d: non-finite loss or gradient (%s); step skipped (%d in a row)", step,
                        ", ".join(f"{k}={v:.4g}" for k, v in terms.items()), nonfinite_run)
        with warnings.catch_warnings():
            # after a skipped step the scheduler still advances, so that the schedule follows the step count
            warnings.filterwarnings("ignore", message="Detected call of `lr_scheduler")
            sched.step()
        step += 1
        te = time.perf_counter()
        t_data += td - ts
        t_total += te - ts
        n_timed += 1
        terms["alpha"] = alpha
        terms["grad_norm"] = float(gnorm)
        terms["time_data_s"], terms["time_step_s"] = td - ts, te - ts
        if writer is not None and (step % cfg.log_every == 0 or step == 1):
            for k, v in terms.items():
                if k.startswith("time_"):
                    continue
                group = "loss" if k in ("loss", "sup", "unsup", "l2") else "train"
                writer.add_scalar(f"{group}/{k}", v, step)
            writer.add_scalar("train/lr", sched.get_last_lr()[0], step)
            writer.add_scalar("time/step_s", t_total / n_timed, step)
            writer.add_scalar("time/data_fraction", t_data / max(t_total, 1e-12), step)
        if bar is not None:
            bar.update(1)
            if step % 5 == 0 or step == cfg.steps:
                shown = ("loss", "sup", "unsup", "alpha")
                bar.set_postfix({k: f"{terms[k]:.3g}" for k in shown if k in terms})
        if nonfinite_run >= cfg.max_nonfinite:
            log.error("stopping at step %d after %d consecutive non-finite steps; the last checkpoint is "
                      "the last good state", step, nonfinite_run)
            status = "nonfinite"
            break
        if info.main and cfg.val_every > 0 and (step % cfg.val_every == 0 or step == cfg.steps):
            record = validate(net, meta, val_store, device, ref_layout, cfg, step, writer)
            history.append(record)
            net.train()
        if step % cfg.checkpoint_every == 0 or step == cfg.steps:
            checkpoint(final=step == cfg.steps)
        if callback is not None:
            callback(step, terms)
    if bar is not None:
        bar.close()
    if info.enabled:
        # DDP keeps parameters identical; normalization statistics are only broadcast at each forward, so
        # give every rank rank 0's final ones (those that were checkpointed).
        for buf in net.buffers():
            dist.broadcast(buf.data, 0)
    timing = {"step_s": t_total / max(n_timed, 1), "loader_fraction": t_data / max(t_total, 1e-12)}
    if n_timed:
        log.info("%s at step %d: %.3f s per step, data loading + augmentation %.1f%% of it", status, step,
                 timing["step_s"], 100 * timing["loader_fraction"])
    if writer is not None:
        writer.close()
    return TrainResult(net, meta, step, status, history, timing)


@torch.no_grad()
def validate(net: nn.Module, meta: DetectorMeta, store: FrameStore | None, device: torch.device,
             ref_layout: float, cfg: TrainConfig, step: int, writer=None) -> dict[str, Any]:
    """Predict the validation frames: metrics, collapse check, overlay image; returns a record."""
    from s3k.evaluate import draw_views, evaluate_store
    from s3k.predict import predict_store

    record: dict[str, Any] = {"step": step}
    if store is None or len(store) == 0:
        return record
    net.eval()
    try:
        metrics, arrays = evaluate_store(net, meta, store, device, 16, meta.units, keep=1)
        X, valid = torch.from_numpy(arrays["X"]), torch.from_numpy(arrays["X_valid"])
        for m in ("rms_px", "rms_px_reproj", "median_mm", "rms_mm"):
            record[m] = metrics[m]
    except ValueError:  # no ground truth on this split: collapse check only
        preds = list(predict_store(net, store, meta.stride, meta.sigma, 16, device, keep_heatmaps=True))
        X = torch.cat([p.X for _, p in preds])
        valid = torch.cat([p.valid for _, p in preds])
        arrays = {"images": preds[0][0].images[:1].numpy(), "probs": preds[0][1].probs[:1].numpy(),
                  "pred_uv": preds[0][1].uv[:1].numpy(), "gt_uv": None, "gt_mask": None}
    layout = mean_pairwise_distance(X, valid)
    ratio = layout / ref_layout if ref_layout and math.isfinite(ref_layout) else float("nan")
    record["layout_ratio"] = ratio
    record["triangulated"] = float(valid.float().mean())
    shown = ", ".join(f"{k} {v:.3g}" for k, v in record.items() if k != "step" and v is not None)
    log.info("step %d validation: %s", step, shown)
    # A network that has not learnt yet also puts every keypoint at the image centre; warn only once the
    # self-supervised term, which can lock such a state in, is on.
    if math.isfinite(ratio) and ratio < cfg.collapse_fraction and cfg.alpha_at(step - 1) > 0:
        log.warning("step %d: possible collapse: triangulated keypoints are %.0f%% as far apart as in the "
                    "labelled layout (threshold %.0f%%)", step, 100 * ratio, 100 * cfg.collapse_fraction)
    if writer is not None:
        for k, v in record.items():
            if k != "step" and v is not None and math.isfinite(v):
                writer.add_scalar(f"val/{k}", v, step)
        gt = arrays["gt_uv"][0] if arrays.get("gt_uv") is not None else None
        gm = arrays["gt_mask"][0] if arrays.get("gt_mask") is not None else None
        img = draw_views(arrays["images"][0], arrays["probs"][0], arrays["pred_uv"][0], gt, gm, scale=2)
        writer.add_image("val/keypoints", img, step, dataformats="HWC")
        writer.flush()
    return record


# ------------------------------------------------------------------------------------------------------------
# Command line


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Train a keypoint detector (S3K: labelled + unlabelled frames; --no-unsup: labels-only baseline). "
        "Run under 'torchrun --nproc_per_node N' for data-parallel training."
    )
    parser.add_argument("dataset", help="dataset folder (see docs/dataset-format.md)")
    parser.add_argument("--out", required=True, metavar="RUN", help="run folder to create (or to --resume)")
    parser.add_argument("--resume", action="store_true",
                        help="continue the run in --out from its last checkpoint (its config.json is used; "
                             "options given here override it)")
    add_config_arguments(parser, TrainConfig)


def run(args: argparse.Namespace) -> int:
    base = None
    if args.resume and (Path(args.out) / "config.json").is_file():
        saved = read_run_config(args.out)["config"]
        base = config_from_dict(TrainConfig, saved, where=f"{args.out}/config.json")
    cfg = config_from_args(args, TrainConfig, base=base)
    result = train(args.dataset, args.out, cfg, resume=args.resume)
    return 0 if result.status == "done" else 1
