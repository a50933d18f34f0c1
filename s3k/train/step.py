"""The loss of one training step (docs/method.md#losses) and the learning-rate schedule."""

from __future__ import annotations

import math

import torch
from torch import nn

from s3k.base.choices import Arithmetic
from s3k.config import TrainConfig
from s3k.detector import autocast
from s3k.readout import ReadoutConfig
from s3k.train.losses import l2_non_bias, self_supervised_loss, supervised_loss


def compute_losses(model: nn.Module, lab: tuple, unl: tuple | None, cfg: TrainConfig, alpha: float,
                   weight_decay_model: nn.Module, rule: ReadoutConfig,
                   teacher: nn.Module | None = None, precision: Arithmetic = "float32"
                   ) -> tuple[torch.Tensor, dict[str, float]]:
    """The training loss of one step (one forward pass over labelled and unlabelled images).

    Args:
        model: the (possibly DDP-wrapped) network.
        lab: (images (Bl, C, 3, H, W), cams (Bl, C), labels_uv (Bl, C, K, 2), labels_mask (Bl, C, K)).
        unl: (images (Bu, C, 3, H, W), cams (Bu, C)) or None when the self-supervised term is off.
        cfg: configuration (stride, sigma, weight decay).
        alpha: weight of the self-supervised term at this step.
        weight_decay_model: the unwrapped network (for the L2 term).
        rule: how the unlabelled frames' detections become pseudo-labels (a
            :class:`s3k.readout.ReadoutConfig`, built once per run from ``cfg`` and the labelled layout, so
            the layout check is never left out).
        teacher: optional network whose read-out of the unlabelled images gives the pseudo-labels
            (``--teacher-ema``); without one they come from ``model``'s own logits.
        precision: the networks' arithmetic (``"float32"`` or ``"bfloat16"`` autocast); the logits, losses
            and pseudo-labels are float32 either way.

    Returns:
        ``(loss, terms)``: the scalar loss and a dict of float terms for logging.
    """
    images_l, cams_l, uv_l, mask_l = lab
    Bl, C = images_l.shape[:2]
    images = images_l if unl is None else torch.cat([images_l, unl[0]])
    flat = images.reshape(-1, *images.shape[2:]).contiguous(memory_format=torch.channels_last)
    device = flat.device
    with autocast(device, precision):
        logits = model(flat)
    logits = logits.float().reshape(images.shape[0], C, *logits.shape[1:])
    sigma = cfg.sigma_px()
    l_sup, info = supervised_loss(logits[:Bl], cams_l, uv_l, mask_l, cfg.model.stride, sigma,
                                   coord_weight=cfg.self_supervision.coord_weight)
    loss = l_sup
    terms = {"sup": float(l_sup.detach())}
    if unl is not None:
        target_logits = None
        if teacher is not None:
            with torch.no_grad():
                flat_u = unl[0].reshape(-1, *unl[0].shape[2:]).contiguous(memory_format=torch.channels_last)
                with autocast(device, precision):
                    target_logits = teacher(flat_u).float().reshape(logits[Bl:].shape)
        l_uns, info_u = self_supervised_loss(logits[Bl:], unl[1], cfg.model.stride, sigma,
                                             rule=rule, target_logits=target_logits,
                                             coord_weight=cfg.self_supervision.coord_weight)
        loss = loss + alpha * l_uns
        terms["unsup"] = float(l_uns.detach())
        terms["unsup_valid"] = float(info_u["points_valid"].float().mean())
        terms["unsup_weight"] = float(info_u["weights"].mean())
    if cfg.schedule.weight_decay > 0:
        l2 = l2_non_bias(weight_decay_model)
        loss = loss + cfg.schedule.weight_decay * l2
        terms["l2"] = float(l2.detach())
    terms["loss"] = float(loss.detach())
    return loss, terms


def lr_lambda(cfg: TrainConfig):
    def f(step: int) -> float:
        frac = min(max(step / max(cfg.schedule.steps, 1), 0.0), 1.0)
        return cfg.schedule.lr_final + (1.0 - cfg.schedule.lr_final) * 0.5 * (1.0 + math.cos(math.pi * frac))

    return f


def optimizer(net: nn.Module, cfg: TrainConfig
              ) -> tuple[torch.optim.Adam, torch.optim.lr_scheduler.LambdaLR]:
    """Adam and its schedule (:func:`lr_lambda`). A pretrained encoder (``encoder_parameters``) is a group of
    its own: ``--encoder-lr`` times the rate, and none during the first ``--freeze-encoder-steps``."""
    encoder = getattr(net, "encoder_parameters", None)
    if encoder is None:  # the U-Net: one group, as every run before the encoder option
        opt = torch.optim.Adam(net.parameters(), lr=cfg.schedule.lr)
        return opt, torch.optim.lr_scheduler.LambdaLR(opt, lr_lambda(cfg))
    mine = {id(p) for p in encoder()}
    rest = [p for p in net.parameters() if id(p) not in mine]
    groups = [{"params": rest}, {"params": encoder(), "lr": cfg.schedule.lr * cfg.backbone.encoder_lr}]
    opt = torch.optim.Adam(groups, lr=cfg.schedule.lr)
    rate, freeze = lr_lambda(cfg), int(cfg.backbone.freeze_encoder_steps)

    def encoder_rate(step: int) -> float:
        return 0.0 if step < freeze else rate(step)

    return opt, torch.optim.lr_scheduler.LambdaLR(opt, [rate, encoder_rate])


def all_finite(module: nn.Module) -> bool:
    return all(bool(torch.isfinite(t).all()) for t in list(module.parameters()) + list(module.buffers())
               if t.is_floating_point())
