"""The run folder: :class:`RunFolder` alone names the files a training writes, reads and writes a run's
``config.json`` (the one place it is parsed), reads a run's configuration and brings older runs' records up to
date.

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
from pathlib import Path
from typing import Any

from s3k.base.errors import UserError
from s3k.base.fileio import atomic_write_json
from s3k.config import TrainConfig, config_from_dict

__all__ = ["RunFolder"]


class RunFolder:
    """The files of one run folder (one pass, or two passes and their two one-pass folders).

    Example:
        >>> run = RunFolder("runs/box")
        >>> run.model.name, run.coarse.config_file.relative_to(run.path).as_posix()
        ('model.pt', 'coarse/config.json')
    """

    CONFIG = "config.json"
    CHECKPOINT = "checkpoint.pt"
    MODEL = "model.pt"
    LOG = "train.log"
    PROGRESS = "progress.json"
    TENSORBOARD = "tensorboard"
    TWO_PASS = "two_pass.json"
    OPTIONS = "two_pass_options.json"
    COARSE = "coarse"
    FINE = "fine"
    ESTIMATES = "estimates.csv"
    CPU = "cpu.json"
    CROPS = "crops"
    ONE_PASS_FILES = (CONFIG, CHECKPOINT, MODEL, LOG, TENSORBOARD, PROGRESS)
    """Every file a one-pass run holds: what ``--overwrite`` may delete."""
    TWO_PASS_FILES = (TWO_PASS, OPTIONS, COARSE, FINE, ESTIMATES, CPU, CROPS)
    """Every file a two-pass run holds besides."""
    STUB_FILES = frozenset({OPTIONS, CPU})
    """What a two-pass start that trained nothing leaves."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    def __repr__(self) -> str:
        return f"RunFolder({str(self.path)!r})"

    def __truediv__(self, name: str) -> Path:
        return self.path / name

    # -- the files ------------------------------------------------------------------------------------------
    config_file = property(lambda self: self.path / self.CONFIG, doc="``config.json`` of a one-pass run")
    checkpoint = property(lambda self: self.path / self.CHECKPOINT, doc="``checkpoint.pt``")
    model = property(lambda self: self.path / self.MODEL, doc="``model.pt``")
    log = property(lambda self: self.path / self.LOG, doc="``train.log``")
    progress = property(lambda self: self.path / self.PROGRESS, doc="``progress.json``")
    tensorboard = property(lambda self: self.path / self.TENSORBOARD, doc="``tensorboard/``")
    two_pass_file = property(lambda self: self.path / self.TWO_PASS, doc="``two_pass.json``")
    options_file = property(lambda self: self.path / self.OPTIONS, doc="``two_pass_options.json``")
    estimates = property(lambda self: self.path / self.ESTIMATES, doc="``estimates.csv``")
    cpu = property(lambda self: self.path / self.CPU, doc="``cpu.json``")
    crops = property(lambda self: self.path / self.CROPS, doc="``crops/`` (``--keep-crops``)")

    @property
    def coarse(self) -> RunFolder:
        """The coarse pass's folder of a two-pass run."""
        return RunFolder(self.path / self.COARSE)

    @property
    def fine(self) -> RunFolder:
        """The refining pass's folder of a two-pass run."""
        return RunFolder(self.path / self.FINE)

    # -- what the folder holds ------------------------------------------------------------------------------
    def is_two_pass(self) -> bool:
        """Whether this is a complete two-pass run (its ``two_pass.json``)."""
        return self.two_pass_file.is_file()

    def is_one_pass_run(self) -> bool:
        """Whether the folder holds what a one-pass training writes (a configuration, checkpoint or model)."""
        return any(p.exists() for p in (self.config_file, self.checkpoint, self.model))

    def is_two_pass_run(self) -> bool:
        """Whether the folder holds a two-pass run, complete or not."""
        return self.is_two_pass() or self.coarse.path.is_dir() or self.options_file.is_file()

    def is_complete(self) -> bool:
        """Whether training finished: a two-pass run's ``two_pass.json``, a one-pass run's ``model.pt``."""
        return self.is_two_pass() or self.model.is_file()

    def is_stub(self) -> bool:
        """Whether the folder holds nothing but what a failed two-pass start wrote: no pass trained."""
        return self.path.is_dir() and all(p.name in self.STUB_FILES for p in self.path.iterdir())

    # -- config.json ----------------------------------------------------------------------------------------
    def read_record(self) -> dict[str, Any]:
        """``config.json`` of a one-pass run: ``{"config", "meta", "dataset", ...}``.

        Raises:
            FileNotFoundError: naming the file when it is absent.
            UserError: naming the file when it is not an s3k run configuration.
        """
        path = self.config_file
        if not path.is_file():
            raise FileNotFoundError(f"{path} not found: {self.path} is not an s3k run folder")
        try:
            doc = json.loads(path.read_text())
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise UserError(f"{path}: not valid JSON ({exc})") from None
        if not isinstance(doc, dict) or not isinstance(doc.get("config"), dict):
            raise UserError(f"{path}: not an s3k run configuration (no 'config' table)")
        return doc

    def record(self) -> dict[str, Any] | None:
        """:meth:`read_record`, or None where ``config.json`` is missing, unreadable or not an s3k run
        configuration (a folder asked whether it holds a run)."""
        try:
            return self.read_record()
        except (OSError, UserError):
            return None

    def holds_record(self) -> bool:
        """Whether ``config.json`` is a run's record: its configuration and its detector's meta."""
        doc = self.record()
        return doc is not None and "meta" in doc

    def write_record(self, config: dict[str, Any], meta: dict[str, Any], dataset: str | None = None,
                     **extra: Any) -> None:
        """Write ``config.json``: ``{"config": config, "meta": meta, "dataset": dataset, **extra}``."""
        atomic_write_json({"config": config, "meta": meta, "dataset": dataset, **extra}, self.config_file)

    def first_pass(self) -> RunFolder:
        """The folder whose ``config.json`` describes the run's detector: the coarse pass of a complete
        two-pass run, else the folder itself."""
        return self.coarse if self.is_two_pass() else self

    def meta(self) -> dict[str, Any] | None:
        """The ``meta`` the run's ``config.json`` holds (its coarse pass's for a two-pass run): keypoints,
        cameras, units, geometry; None when there is none to read."""
        doc = self.first_pass().record()
        meta = doc.get("meta") if doc is not None else None
        return meta if isinstance(meta, dict) else None

    def dataset(self) -> str | None:
        """The dataset folder the run (of a two-pass run, its coarse pass) was trained on, as its
        ``config.json`` records it; None when it does not.

        Raises:
            FileNotFoundError, UserError: as :meth:`read_record`.
        """
        dataset = self.first_pass().read_record().get("dataset")
        return str(dataset) if dataset else None

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

    # -- the CPU record of a two-pass run -------------------------------------------------------------------
    def read_cpu(self) -> dict[str, float]:
        """CPU seconds per stage of a two-pass run (``cpu.json``); empty for a run trained without it."""
        if not self.cpu.is_file():
            return {}
        try:
            return {str(k): float(v) for k, v in json.loads(self.cpu.read_text()).items()}
        except (ValueError, AttributeError, TypeError) as e:
            raise UserError(f"{self.cpu}: not a CPU record ({type(e).__name__}: {e})") from None

    def write_cpu(self, spent: dict[str, float]) -> None:
        """Write the CPU record ``{stage: seconds}``."""
        atomic_write_json(spent, self.cpu)


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
