"""Fine-tuning's configuration (``s3k train DATASET --out RUN-2 --init-from RUN``): RUN's own configuration,
continued where its training ended.

A fine-tune starts from a trained network; a fresh learning rate (and a warm-up of the self-supervised term
that a random network needs) would throw away what the last steps of its cosine decay refined. So the
configuration of a fine-tune is RUN's (:meth:`s3k.run_folder.RunFolder.config`) with each pass's learning
rate at the value it ended at, ``lr x lr_final`` (of a two-pass run the coarse pass's and the refining
pass's), and the self-supervised term on from the first step (no warm-up or ramp). What the caller sets
itself (``given``: the options given on the command line or in ``--config``) is left to it; ``--steps`` or
``--lr`` given without ``--coarse-steps`` or ``--coarse-lr`` sets both passes', as it does in a run of its
own.
"""

from __future__ import annotations

from collections.abc import Collection
from pathlib import Path

from s3k.base.errors import UserError
from s3k.config import TrainConfig
from s3k.run_folder import RunFolder

__all__ = ["continued", "fine_tune_config"]


def continued(cfg: TrainConfig, given: Collection[str] = (), run: str | Path = "RUN"
              ) -> tuple[TrainConfig, list[str]]:
    """``cfg`` (a trained run's) continued where it ended: each pass's learning rate at its final value and
    no warm-up or ramp, except for the fields in ``given``.

    Returns:
        The configuration and, per change, a few words saying what it is (for the log).
    """
    changes: dict[str, object] = {}
    said = []
    lr, final, two_pass = cfg.schedule.lr, cfg.schedule.lr_final, cfg.passes.two_pass
    if "lr" not in given:
        changes["lr"] = lr * final
        said.append(f"{'the refining pass at' if two_pass else 'at'} the learning rate it ended at, "
                    f"{changes['lr']:.3g} (--lr {lr:g} x --lr-final {final:g})")
    if two_pass and "coarse_lr" not in given:
        if "lr" in given:  # the learning rate given is both passes', as in a run of its own
            changes["coarse_lr"] = None
        else:
            first = lr if cfg.passes.coarse_lr is None else cfg.passes.coarse_lr
            changes["coarse_lr"] = first * final
            said.append(f"the coarse pass at {changes['coarse_lr']:.3g} ({first:g} x {final:g})")
    if two_pass and "steps" in given and "coarse_steps" not in given:
        changes["coarse_steps"] = None  # the steps given are both passes'
    for name in ("warmup_steps", "ramp_steps"):
        if name not in given:
            changes[name] = 0
    if "warmup_steps" not in given and "ramp_steps" not in given:
        said.append("the self-supervised term on from the first step (--warmup-steps 0 --ramp-steps 0)")
    for name, value in changes.items():
        if name in ("lr", "coarse_lr") and value == 0:
            raise UserError(f"--init-from {run}: it ended at a learning rate of 0 "
                            f"(--lr-final {final:g}), at which a fine-tune trains nothing",
                            hint=f"give --{name.replace('_', '-')}")
    return cfg.replace(**changes), said


def fine_tune_config(run: str | Path, given: Collection[str] = ()) -> tuple[TrainConfig, str]:
    """The configuration of a fine-tune of ``run`` (:func:`continued` over its own), and the line that says
    what was taken from it. ``given``: the fields the caller sets itself."""
    cfg = RunFolder(run).config()
    if cfg is None:
        raise UserError(f"--init-from {run}: not a trained run (no configuration recorded in it)",
                        hint="give the folder 's3k train --out' wrote")
    cfg, said = continued(cfg, given, run)
    line = f"fine-tuning {run}: its configuration ({'two passes' if cfg.passes.two_pass else 'one pass'})"
    if said:
        line += ", " + ", ".join(said)
    if given:
        line += "; given here: " + ", ".join(f"--{name.replace('_', '-')}" for name in sorted(given))
    return cfg, line
