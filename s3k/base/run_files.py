"""The files of a run folder, by name: :class:`RunFiles` names every file a training writes and reads a
run's ``config.json`` as JSON. What a run's configuration means (a ``TrainConfig``, older layouts brought up
to date) is :class:`s3k.run_folder.RunFolder`'s, which adds it; this module stands below it so that the
output checks (:mod:`s3k.base.outputs`) know a run's files without the configuration.

The layout is described in :mod:`s3k.run_folder`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, TypeVar

from s3k.base.errors import UserError
from s3k.base.fileio import atomic_write_json

__all__ = ["RunFiles"]

_Run = TypeVar("_Run", bound="RunFiles")


class RunFiles:
    """The files of one run folder (one pass, or two passes and their two one-pass folders).

    Example:
        >>> run = RunFiles("runs/box")
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
        return f"{type(self).__name__}({str(self.path)!r})"

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
    def coarse(self: _Run) -> _Run:
        """The coarse pass's folder of a two-pass run."""
        return type(self)(self.path / self.COARSE)

    @property
    def fine(self: _Run) -> _Run:
        """The refining pass's folder of a two-pass run."""
        return type(self)(self.path / self.FINE)

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

    def first_pass(self: _Run) -> _Run:
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
