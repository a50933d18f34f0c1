"""The training loop: steps, logging, checkpoints, the stop conditions (the set-up of a run:
:mod:`s3k.train.run_setup`; the loss of one step: :mod:`s3k.train.step`).

:func:`train` opens the dataset once, makes every check that can refuse the run before anything is written
(``out_folder``; no labelled frame with a usable target; S3K without unlabelled frames), builds or restores
the network, optimizer and schedule, then runs :class:`_Loop` until ``cfg.schedule.steps``.
"""

from __future__ import annotations

import copy
import logging
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import nn
from tqdm import tqdm

from s3k.base.errors import UserError
from s3k.base.fileio import atomic_write_json
from s3k.config import TrainConfig
from s3k.data.frames import FrameStore
from s3k.data.protocol import DatasetLike
from s3k.detector import (
    CHECKPOINT_FILE,
    MODEL_FILE,
    PROGRESS_FILE,
    TENSORBOARD_DIR,
    DetectorMeta,
    load_network,
    pick_device,
    save_model_file,
    training_precision,
)
from s3k.model import UNetConfig
from s3k.networks import EncoderUNet, build_network, load_imagenet_weights
from s3k.readout import ReadoutConfig
from s3k.train import checkpoint as ckpt
from s3k.train import out_folder
from s3k.train.augment import NoiseBank
from s3k.train.distributed import (
    DistInfo,
    all_ranks,
    broadcast_buffers,
    check_batches,
    finish_distributed,
    gather,
    init_distributed,
    mean_terms,
    part,
    world_size,
    wrap_model,
)
from s3k.train.run_setup import (
    check_trained_as,
    data_path,
    detector_meta,
    log_sessions,
    open_data,
    reference_layout,
    setup_logging,
    start_run,
)
from s3k.train.sampling import draw_batch, prepare
from s3k.train.step import all_finite, compute_losses, optimizer
from s3k.train.validation import calibrate, labelled_distances, layout_size, validate

log = logging.getLogger(__name__)  # under "s3k.train", which a run logs to (run_setup)


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
        passes: of a two-pass run, ``{"coarse": ..., "fine": ...}``: each pass's result, None for a pass that
            was complete before the call (the other fields are the refining pass's); None for one pass.
        rule: of a two-pass run, its :class:`s3k.detector.CropRule`.
    """

    model: nn.Module
    meta: DetectorMeta
    step: int
    status: str
    history: list[dict[str, Any]] = field(default_factory=list)
    timing: dict[str, float] = field(default_factory=dict)
    passes: dict[str, TrainResult | None] | None = None
    rule: Any = None


# ------------------------------------------------------------------------------------------------------------
# The loop


class _Loop:
    """The network, optimizer, schedule and random stream of one rank, and the step counter."""

    def __init__(self, cfg: TrainConfig, meta: DetectorMeta, device: torch.device, info: DistInfo,
                 out: Path, layout: torch.Tensor | None = None) -> None:
        self.cfg, self.meta, self.device, self.info, self.out = cfg, meta, device, info, out
        torch.manual_seed(cfg.execution.seed)
        net = build_network(len(meta.keypoints), UNetConfig.from_dict(meta.model))
        if isinstance(net, EncoderUNet) and cfg.backbone.pretrained:
            load_imagenet_weights(net)
        # NHWC is the faster convolution layout for these small channel counts on CPU (and fine on GPU).
        self.net = net.to(device=device, memory_format=torch.channels_last)  # type: ignore[call-overload]
        self.model = wrap_model(self.net, device, info)
        # one stream for every rank: each draws and augments the whole batch as one process does
        self.gen = torch.Generator().manual_seed(cfg.execution.seed * 1000)
        self.opt, self.sched = optimizer(self.net, cfg)
        self.step, self.nonfinite_run = 0, 0
        self.teacher: nn.Module | None = None
        # the pseudo-label rule, with the rigid layout that --layout-tol holds the pseudo-labels to
        self.rule = ReadoutConfig.of_training(cfg.self_supervision, layout)
        self.precision = training_precision(cfg.execution.precision, device)
        if cfg.self_supervision.unsup and cfg.self_supervision.teacher_ema > 0:
            # in eval mode (running normalization statistics, copied from the network at every update)
            self.teacher = copy.deepcopy(self.net).eval().requires_grad_(False)

    def update_teacher(self) -> None:
        """teacher <- decay * teacher + (1 - decay) * network for the weights; the network's normalization
        statistics are copied (they are already running averages)."""
        if self.teacher is None:
            return
        with torch.no_grad():
            for tp, p in zip(self.teacher.parameters(), self.net.parameters()):
                tp.lerp_(p, 1.0 - self.cfg.self_supervision.teacher_ema)
            for tb, b in zip(self.teacher.buffers(), self.net.buffers()):
                tb.copy_(b)

    def restore(self, state: dict[str, Any], path: Path) -> None:
        """Continue from a checkpoint (``checkpoint.load_checkpoint``)."""
        try:
            self.net.load_state_dict(state["model"])
            self.opt.load_state_dict(state["optimizer"])
            self.sched.load_state_dict(state["scheduler"])
            if self.teacher is not None:
                self.teacher.load_state_dict(state.get("teacher") or state["model"])
        except (KeyError, RuntimeError, ValueError) as exc:
            raise UserError(f"{path}: does not fit this network ({str(exc).splitlines()[0][:200]})",
                            hint="resume with the run's settings, or choose another --out") from exc
        self.step, self.nonfinite_run = int(state["step"]), int(state.get("nonfinite_run", 0))
        # every rank continues the one stream (the first rank's, of a checkpoint written with one per rank),
        # whatever number of ranks wrote it
        ckpt.set_rng_state(self.gen, state["rng"][0])
        log.info("resumed from %s at step %d", path, self.step)

    def start_from(self, weights: dict[str, Any], run: Any) -> None:
        """Start from another run's network (``train(init_from=...)``), the teacher too."""
        self.net.load_state_dict(weights)
        if self.teacher is not None:
            self.teacher.load_state_dict(weights)
        log.info("fine-tuning: the network starts from %s", run)

    def save(self, final: bool = False, val_store: FrameStore | None = None) -> None:
        """Write the checkpoint (and at the end ``model.pt``) from rank 0, unless the model is not finite; at
        the end the confidence is calibrated on ``val_store`` first (:func:`calibrate`), and the model's meta
        holds the map."""
        rngs = gather(ckpt.rng_state(self.gen), self.info)
        if not self.info.main:
            return
        if not all_finite(self.net):
            log.error("step %d: model holds non-finite values; checkpoint not written", self.step)
            return
        if final:
            self.meta.calibration = calibrate(self.net, self.meta, val_store, self.device)
            self.net.train()
        ckpt.save_checkpoint(self.out / CHECKPOINT_FILE, step=self.step, model=self.net.state_dict(),
                             optimizer=self.opt.state_dict(), scheduler=self.sched.state_dict(), rng=rngs,
                             nonfinite_run=self.nonfinite_run, meta=self.meta.to_dict(),
                             config=self.cfg.to_dict(),
                             teacher=None if self.teacher is None else self.teacher.state_dict())
        if final:
            save_model_file(self.out / MODEL_FILE, self.net.state_dict(), self.meta, self.step)

    def train_step(self, lab_store: FrameStore, unl_store: FrameStore | None, aug, noise_bank
                   ) -> dict[str, float]:
        """One optimizer step (skipped, with the state unchanged, when the loss or gradient is not finite)."""
        cfg, net = self.cfg, self.net
        ts = time.perf_counter()
        alpha = cfg.alpha_at(self.step)
        # the whole global batch is drawn and augmented on every rank; each passes its own part forward
        batches = cfg.schedule
        lab = part(prepare(draw_batch(lab_store, batches.batch_labelled, self.gen, True), self.device, aug,
                           self.gen, True, noise_bank), self.info)
        unl = None
        if unl_store is not None and alpha > 0:
            unl = part(prepare(draw_batch(unl_store, batches.batch_unlabelled, self.gen, False), self.device,
                               aug, self.gen, False, noise_bank)[:2], self.info)
        td = time.perf_counter()
        buffers = [b.detach().clone() for b in net.buffers()]
        loss, terms = compute_losses(self.model, lab, unl, cfg, alpha, net, self.rule, self.teacher,
                                     self.precision)
        terms = mean_terms(terms, self.device, self.info)  # the whole batch's, as one process logs them
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        clip = cfg.schedule.grad_clip if cfg.schedule.grad_clip > 0 else float("inf")
        gnorm = torch.nn.utils.clip_grad_norm_(net.parameters(), clip)
        if all_ranks(bool(torch.isfinite(loss) and torch.isfinite(gnorm)), self.device, self.info):
            self.opt.step()
            self.update_teacher()
            self.nonfinite_run = 0
        else:
            self.opt.zero_grad(set_to_none=True)
            with torch.no_grad():
                for b, saved in zip(net.buffers(), buffers):
                    b.copy_(saved)
            self.nonfinite_run += 1
            log.warning("step %d: non-finite loss or gradient (%s); step skipped (%d in a row)", self.step,
                        ", ".join(f"{k}={v:.4g}" for k, v in terms.items()), self.nonfinite_run)
        with warnings.catch_warnings():
            # after a skipped step the scheduler still advances, so that the schedule follows the step count
            warnings.filterwarnings("ignore", message="Detected call of `lr_scheduler")
            self.sched.step()
        self.step += 1
        terms["alpha"] = alpha
        terms["grad_norm"] = float(gnorm)
        terms["time_data_s"], terms["time_step_s"] = td - ts, time.perf_counter() - ts
        return terms


class _Monitor:
    """TensorBoard scalars, the progress bar, ``RUN/progress.json`` and the step timings (rank 0 only writes).

    ``progress.json`` (``{"step", "steps", "seconds"}``, rewritten atomically every ``log_every`` steps) lets
    another process follow a training without parsing its log (``s3k demo`` draws its bars from it).
    """

    def __init__(self, cfg: TrainConfig, out: Path, info: DistInfo, step: int) -> None:
        self.cfg = cfg
        self.writer = None
        self.bar = None
        self.progress_file = out / PROGRESS_FILE if info.main else None
        self.started = time.perf_counter()
        if info.main:
            from torch.utils.tensorboard import SummaryWriter

            self.writer = SummaryWriter(str(out / TENSORBOARD_DIR))
            if cfg.monitoring.progress:
                self.bar = tqdm(total=cfg.schedule.steps, initial=step,
                                desc="S3K" if cfg.self_supervision.unsup else "labels only",
                                dynamic_ncols=True, smoothing=0.05)
        self.t_data = self.t_total = 0.0
        self.n_timed = 0

    def record(self, step: int, terms: dict[str, float], lr: float) -> None:
        self.t_data += terms["time_data_s"]
        self.t_total += terms["time_step_s"]
        self.n_timed += 1
        if self.writer is not None and (step % self.cfg.monitoring.log_every == 0 or step == 1):
            for k, v in terms.items():
                if not k.startswith("time_"):
                    group = "loss" if k in ("loss", "sup", "unsup", "l2") else "train"
                    self.writer.add_scalar(f"{group}/{k}", v, step)
            self.writer.add_scalar("train/lr", lr, step)
            self.writer.add_scalar("time/step_s", self.t_total / self.n_timed, step)
            self.writer.add_scalar("time/data_fraction", self.t_data / max(self.t_total, 1e-12), step)
        steps = self.cfg.schedule.steps
        if self.progress_file is not None and (step % self.cfg.monitoring.log_every == 0 or step == steps):
            atomic_write_json({"step": step, "steps": steps,
                               "seconds": time.perf_counter() - self.started}, self.progress_file)
        if self.bar is not None:
            self.bar.update(1)
            if step % 5 == 0 or step == steps:
                shown = ("loss", "sup", "unsup", "alpha")
                self.bar.set_postfix({k: f"{terms[k]:.3g}" for k in shown if k in terms})

    def close(self, status: str, step: int) -> dict[str, float]:
        """Close the bar and writer; returns the mean step time and the data-loading fraction."""
        if self.bar is not None:
            self.bar.close()
        timing = {"step_s": self.t_total / max(self.n_timed, 1),
                  "loader_fraction": self.t_data / max(self.t_total, 1e-12)}
        if self.n_timed:
            log.info("%s at step %d: %.3f s per step, data loading + augmentation %.1f%% of it", status, step,
                     timing["step_s"], 100 * timing["loader_fraction"])
        if self.writer is not None:
            self.writer.close()
        return timing


def _log_unsup_schedule(cfg: TrainConfig) -> None:
    """Say at which step the self-supervised term switches on and when it reaches its weight."""
    s = cfg.self_supervision
    if not s.unsup:
        return
    warmup, ramp = cfg.unsup_schedule()
    scaled = ("" if (warmup, ramp) == (s.warmup_steps, s.ramp_steps) else
              f" (--warmup-steps {s.warmup_steps} and --ramp-steps {s.ramp_steps} shrunk in proportion "
              f"to fit the {cfg.schedule.steps} steps)")
    # steps counted from 1, as the progress and TensorBoard count them
    log.info("self-supervised term: switches on at step %d, alpha reaches %g at step %d%s", warmup + 1,
             s.alpha, warmup + max(ramp, 1), scaled)


def _finished(source, out: Path, cfg: TrainConfig, step: int, info: DistInfo) -> TrainResult:
    """A resumed run with nothing left to train: checked as ``--resume`` checks a run, then returned as it is,
    with nothing written (no history entry, log line or TensorBoard file)."""
    check_trained_as(source, out, cfg)
    model, meta = load_network(out)
    if info.main:
        setup_logging(None, True)
        log.info("%s is complete at step %d: nothing to train (a larger --steps continues it)", out, step)
    return TrainResult(model.train(), meta, step, "done")


def _initial_weights(run: str | Path, meta: DetectorMeta) -> dict[str, Any]:
    """The network weights of the run ``run`` for a run of ``meta`` to start from.

    Raises:
        UserError: naming the run and what differs (keypoints, architecture).
    """
    model, theirs = load_network(run, "cpu")
    if list(theirs.keypoints) != list(meta.keypoints):
        raise UserError(f"--init-from {run}: its keypoints {theirs.keypoints} are not this dataset's "
                        f"{meta.keypoints}", hint="fine-tune a run trained on the same keypoints")
    if UNetConfig.from_dict(theirs.model) != UNetConfig.from_dict(meta.model):
        raise UserError(f"--init-from {run}: its network ({theirs.model}) differs from this run's "
                        f"({meta.model})", hint="give the options it was trained with (--channels, --stride, "
                        "--norm ...)")
    return model.state_dict()


def train_one_pass(data: str | Path | DatasetLike, out: str | Path, cfg: TrainConfig, *, resume: bool = False,
                   progress=None, overwrite: bool = False, command: str | None = None,
                   init_from: str | Path | None = None) -> TrainResult:
    """Train a one-pass detector on the dataset folder ``data`` into the run folder ``out`` (what
    :func:`s3k.train.train` does for a configuration without ``two_pass``, and for each pass of one with).

    Args:
        data: dataset folder (``s3k.data``), with labelled and (for S3K) unlabelled frames; or a dataset held
            in memory (:class:`s3k.data.crops.CropDataset`: the refining pass's crops), whose run records
            its source folder.
        out: run folder (created); see ``s3k.detector``.
        cfg: configuration.
        resume: continue from ``out/checkpoint.pt`` (starts afresh when there is none); the configuration and
            the dataset must match the run's except for ``s3k.config.resumable_fields``.
        progress: optional ``f(step, terms)`` called after every completed step (``step`` counts completed
            steps; ``terms`` holds the loss terms, alpha, the gradient norm and the step's timings
            ``time_data_s``, ``time_step_s``); an exception it raises aborts the run like a kill would.
        overwrite: replace the run in ``out`` (only the files a run holds are deleted).
        command: the command line, recorded in the run's history.
        init_from: a one-pass run folder whose network (same keypoints and architecture) starts this run
            instead of a random one: fine-tuning, with this run's own steps, learning rate and schedule. A
            run resumed from its checkpoint ignores it.

    Returns:
        A :class:`TrainResult`.

    Raises:
        UserError: before anything is written, naming what is wrong (see ``s3k.train.out_folder``).
    """
    cfg.validate()
    check_batches(cfg.schedule.batch_labelled, cfg.schedule.batch_unlabelled, cfg.self_supervision.unsup,
                  world_size())
    info = init_distributed(cfg.execution.device)
    try:
        return _train(data, Path(out), cfg, resume, overwrite, progress, command, info, init_from)
    finally:
        finish_distributed(info)


def _train(source: str | Path | DatasetLike, out: Path, cfg: TrainConfig, resume: bool, overwrite: bool,
           callback, command: str | None, info: DistInfo, init_from: str | Path | None = None) -> TrainResult:
    data = data_path(source)
    device = pick_device(cfg.execution.device, info.local_rank)
    if device.type == "cuda":
        torch.cuda.set_device(device)
    if cfg.execution.threads > 0:
        torch.set_num_threads(cfg.execution.threads)
    if info.main:
        out_folder.check_out(out, resume, overwrite, data)  # before the dataset is read: cheap refusals first
    if resume and (done := out_folder.finished_step(out, cfg.schedule.steps)) is not None:
        return _finished(source, out, cfg, done, info)
    d = open_data(source, cfg)
    distances = labelled_distances(d.ds, d.labelled)  # triangulated once: the rigid layout and its size
    layout = reference_layout(data, distances, cfg)
    meta = detector_meta(d, cfg, distances)
    start = _initial_weights(init_from, meta) if init_from is not None else None  # refused before any write
    # the images are read (preloaded) before the run is written: a corrupt one leaves no run behind
    t0, preload = time.perf_counter(), cfg.execution.preload_mb
    lab_store = FrameStore(d.ds, d.labelled, preload, labels=True)  # every rank: every frame
    unl_store = FrameStore(d.ds, d.unlabelled, preload) if cfg.self_supervision.unsup else None
    val_store = FrameStore(d.ds, d.val, preload, labels=True, points=True) if info.main else None
    if device.type != "cpu":  # the frames held once on the training device, batches drawn there
        for store in (lab_store, unl_store):
            if store is not None:
                store.to(device)
    t_load = time.perf_counter() - t0
    state = start_run(data, out, cfg, d, meta, resume, overwrite, command, info)
    if not info.main:
        setup_logging(out, False)
    loop = _Loop(cfg, meta, device, info, out, layout)
    if state is not None:
        loop.restore(state, out / CHECKPOINT_FILE)
        del state
    elif start is not None:
        loop.start_from(start, init_from)
    elif resume:
        log.info("no checkpoint in %s: starting a new run", out)
    ref_layout = layout_size(distances)
    size = meta.image_size
    log.info("dataset %s: %d labelled, %d unlabelled frames, %d cameras, keypoints %s; images %dx%d "
             "(stored %dx%d), heatmaps stride %d, sigma %.2f px; %s, %d parameters; %s on %s x%d (%s); "
             "frames loaded in %.1f s (preloaded: %s)", data, len(d.labelled), len(d.unlabelled),
             len(meta.cameras), meta.keypoints, size[0], size[1], d.source_size[0], d.source_size[1],
             cfg.model.stride, meta.sigma, "S3K" if cfg.self_supervision.unsup else "labels only",
             sum(p.numel() for p in loop.net.parameters()), "DDP" if info.enabled else "single process",
             device, info.world, loop.precision, t_load, lab_store.preloaded)
    log_sessions(d.ds, d.labelled, d.unlabelled)
    log.info("labelled layout: mean distance between keypoints %.4g %s", ref_layout, meta.units)
    _log_unsup_schedule(cfg)

    monitor = _Monitor(cfg, out, info, loop.step)
    aug = cfg.augmentation if cfg.augmentation.augment else None
    noise_bank = NoiseBank(seed=cfg.execution.seed)
    history: list[dict[str, Any]] = []
    status = "done"
    loop.net.train()
    mon, steps = cfg.monitoring, cfg.schedule.steps
    while loop.step < steps:
        terms = loop.train_step(lab_store, unl_store, aug, noise_bank)
        step = loop.step
        monitor.record(step, terms, float(loop.sched.get_last_lr()[0]))
        if loop.nonfinite_run >= mon.max_nonfinite:
            log.error("stopping at step %d after %d consecutive non-finite steps; the last checkpoint is "
                      "the last good state", step, loop.nonfinite_run)
            status = "nonfinite"
            break
        if info.main and mon.val_every > 0 and (step % mon.val_every == 0 or step == steps):
            history.append(validate(loop.net, meta, val_store, device, ref_layout, cfg, step, monitor.writer))
            loop.net.train()
        if step % mon.checkpoint_every == 0 or step == steps:
            loop.save(final=step == steps, val_store=val_store)
        if callback is not None:
            callback(step, terms)
    broadcast_buffers(loop.net, info)
    if status == "done" and not all_finite(loop.net):  # e.g. a learning rate too large for float32
        log.error("training ended at step %d with non-finite weights; no model was written", loop.step)
        status = "nonfinite"
    timing = monitor.close(status, loop.step)
    return TrainResult(loop.net, meta, loop.step, status, history, timing)
