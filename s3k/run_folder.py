"""The run folder: :class:`RunFolder` is a run's files (:class:`s3k.base.run_files.RunFiles`, which
names them and reads and writes ``config.json``, the one place it is parsed) and its configuration: it reads a
run's configuration and brings older runs' records up to date.

A one-pass run (``s3k train``)::

    RUN/config.json      the resolved TrainConfig (flat), "meta" (what inference needs), the dataset, history
    RUN/checkpoint.pt    full training state for --resume          (s3k.train.loop, s3k.train.checkpoint)
    RUN/model.pt         final weights + meta                       (s3k.train.loop, s3k.detector.model_file)
    RUN/train.log        the log                                    (s3k.train.run_setup)
    RUN/progress.json    step, steps, seconds: a live progress view (s3k.train.loop)
    RUN/tensorboard/     TensorBoard event files                    (s3k.train.loop)

A two-pass run (``s3k train --two-pass``) holds two one-pass runs and what joins them::

    RUN/two_pass_options.json  the configuration of the run, both passes and the two-pass section (flat)
    RUN/coarse/, RUN/fine/     the coarse and the refining pass, each a one-pass run folder
    RUN/estimates.csv          the coarse pass's 3D keypoints of the frames the refining pass reads
    RUN/cpu.json               CPU seconds per stage (coarse, crops, fine), summed over a run's attempts
    RUN/crops/                 the crops as a dataset folder, only with --keep-crops
    RUN/two_pass.json          the crop rule and the passes' folders, written last: the run is complete

(all written by :mod:`s3k.train.two_pass`; ``two_pass.json`` through :mod:`s3k.detector.crop_rule`). The
geometry a run was trained on is a part of ``config.json``'s meta (:mod:`s3k.detector.geometry_record`).

Older runs: a two-pass run from before its configuration held the two-pass section kept the two-pass options
beside it in ``two_pass_options.json`` (``margin``, ``extent``), and one from before that file was written
holds only its passes' ``config.json`` files; :meth:`RunFolder.config` reads each as the configuration of
today (:func:`_migrate`, the one place that knows the older layouts).
"""

from __future__ import annotations

import json
from typing import Any

from s3k.base.errors import UserError
from s3k.base.fileio import atomic_write_json
from s3k.base.run_files import RunFiles
from s3k.config import TrainConfig, config_from_dict

__all__ = ["RunFolder"]


class RunFolder(RunFiles):
    """The files of one run folder (:class:`RunFiles`) and the configuration it was trained with.

    Example:
        >>> run = RunFolder("runs/box")
        >>> run.model.name, run.coarse.config_file.relative_to(run.path).as_posix()
        ('model.pt', 'coarse/config.json')
    """

    # -- the configuration ----------------------------------------------------------------------------------

    def config(self) -> TrainConfig | None:
        """The configuration the run was trained with (of a two-pass run: both passes and the two-pass
        section), older records brought up to date; None where the folder records none yet (a two-pass run
        whose refining pass has not started and that kept no options: its options are the call's)."""
        flat, where = self.config_fields()
        return None if flat is None else config_from_dict(TrainConfig, flat, where=where)

    def config_fields(self) -> tuple[dict[str, Any] | None, str]:
        """The flat configuration fields :meth:`config` builds from, and the file they come from."""
        if self.options_file.is_file():
            try:
                doc = json.loads(self.options_file.read_text())
                return _migrate(dict(doc["config"]), doc), str(self.options_file)
            except (ValueError, KeyError, TypeError) as e:
                raise UserError(f"{self.options_file}: not a two-pass configuration ({type(e).__name__}: "
                                f"{e})") from None
        if self.coarse.path.is_dir() or self.is_two_pass():
            return _from_passes(self), str(self.fine.config_file)
        if self.config_file.is_file():
            return dict(self.read_record()["config"]), str(self.config_file)
        return None, str(self.path)

    def write_config(self, cfg: TrainConfig) -> None:
        """Record a two-pass run's configuration (``two_pass_options.json``)."""
        atomic_write_json({"config": cfg.to_dict()}, self.options_file)


_RENAMED = {"margin": "crop_margin", "extent": "crop_extent"}
"""Two-pass options whose field has another name than the option kept beside the configuration had."""


def _migrate(flat: dict[str, Any], doc: dict[str, Any]) -> dict[str, Any]:
    """A two-pass run's flat configuration from its ``two_pass_options.json``: today's ``{"config"}`` as it
    is; an older one kept the two-pass options beside the configuration (``coarse_size``, ..., ``margin``,
    ``extent``), and they join it."""
    options = {_RENAMED.get(k, k): v for k, v in doc.items() if k != "config"}
    return {**flat, **options, "two_pass": True}


def _from_passes(run: RunFolder) -> dict[str, Any] | None:
    """The configuration of a two-pass run started before it was recorded: the coarse pass's configuration
    with the refining pass's own steps, rotation, stride and learning rate, and the crops' size and extent
    where they were cut. None until the refining pass has started: a coarse pass alone does not say what the
    refining pass's options are (its rotation, stride, learning rate and steps may be the coarse pass's own),
    so they are the call's, and the coarse pass is checked against them."""
    coarse_doc, fine_doc = run.coarse.record(), run.fine.record()
    if coarse_doc is None or fine_doc is None:
        return None
    coarse, fine = dict(coarse_doc["config"]), dict(fine_doc["config"])
    flat = dict(coarse, image_size=0, steps=fine["steps"], rotation_deg=fine["rotation_deg"],
                stride=fine["stride"], lr=fine["lr"], two_pass=True, coarse_steps=coarse["steps"],
                coarse_rotation=coarse["rotation_deg"], coarse_stride=coarse["stride"],
                coarse_lr=coarse["lr"])
    if coarse.get("image_size"):
        flat["coarse_size"] = coarse["image_size"]
    try:  # the crops' size is the refining pass's input
        flat["crop_size"] = int(fine_doc["meta"]["image_size"][0])
    except (ValueError, KeyError, TypeError, IndexError):
        pass
    for source in (run.two_pass_file, run.crops / "s3k.json"):
        try:
            doc = json.loads(source.read_text())
        except (OSError, ValueError):
            continue
        rule = doc.get("source", doc) if isinstance(doc, dict) else {}
        if isinstance(rule, dict) and rule.get("extent") is not None and rule.get("size") is not None:
            flat.update(crop_extent=float(rule["extent"]), crop_size=int(rule["size"]))
            break
    return flat
