"""The label formats ``s3k import`` reads: one small dataclass per format (:data:`LABEL_FORMATS`).

A format's dataclass holds its options (the files it reads and how to read them) and has two methods:

- ``files(cameras) -> {camera: file}``: the files it reads, for the dataset's provenance;
- ``read(cameras, sizes, rig) -> LabelsRead``: one :class:`s3k.data.formats.labels2d.LabelTable` per camera
  (pixel coordinates of the videos, frame ids of the videos' frames) and the notes to show the user.

:func:`s3k.data.recording.import_recording` takes one of them (or none) and does the rest: it never asks
which format it has. Adding a format is a reader in :mod:`s3k.data.formats`, a dataclass here registered
with :func:`register`, and a command-line option in :mod:`s3k.cli.import_` named for it (:func:`build`
makes the dataclass from the option's files and the options it takes; docs/importing.md, "Adding a label
format").

Example:
    >>> fmt = DeepLabCut({"cam0": "cam0.csv"}, frame_ids_from="row")
    >>> fmt.kind, fmt.files(["cam0"])
    ('deeplabcut', {'cam0': 'cam0.csv'})
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal, Protocol

from s3k.base.errors import UserError
from s3k.data.formats.deepfly3d import JOINTS, read_deepfly3d_pose
from s3k.data.formats.dlc import find_lightning_pose_csvs, read_dlc_csv
from s3k.data.formats.labels2d import LabelTable
from s3k.data.formats.nwb import read_nwb
from s3k.data.formats.pose_json import read_mmpose_json, read_openpose_folder
from s3k.data.formats.sleap import default_track, read_sleap_file
from s3k.data.formats.slp import read_slp
from s3k.data.rig import Rig

PathLike = str | Path


@dataclass
class LabelsRead:
    """What a label format read: its ``kind`` (recorded in the dataset), ``{camera: file}``, ``{camera:
    LabelTable}``, and notes for the user (what the format leaves out, and why)."""

    kind: str
    files: dict[str, str]
    tables: dict[str, LabelTable]
    notes: list[str] = field(default_factory=list)


class LabelFormat(Protocol):
    """A label format's options; see the module's docstring."""

    kind: ClassVar[str]

    def files(self, cameras: list[str]) -> dict[str, str]: ...

    def read(self, cameras: list[str], sizes: dict[str, tuple[int, int]], rig: Rig) -> LabelsRead: ...


LABEL_FORMATS: dict[str, type] = {}
"""Every label format by name (``"sleap"``, ``"deeplabcut"``, ...)."""


def register(name: str) -> Callable[[type], type]:
    """Class decorator: add a label format to :data:`LABEL_FORMATS` under ``name``."""

    def add(cls: type) -> type:
        LABEL_FORMATS[name] = cls
        return cls

    return add


def build(name: str, files: Any, **options: Any) -> Any:
    """The format ``name``'s dataclass (:data:`LABEL_FORMATS`) of its ``files`` (its first field: ``{camera:
    file}`` or one path) and of those ``options`` it takes; the others are left out, so that a caller offering
    every format's options (the command line) builds any format the same way."""
    if name not in LABEL_FORMATS:
        raise UserError(f"no label format {name!r}; the formats are {', '.join(LABEL_FORMATS)}")
    cls = LABEL_FORMATS[name]
    _, *rest = dataclasses.fields(cls)
    return cls(files, **{f.name: options[f.name] for f in rest if f.name in options})


def _per_camera(kind: str, files: Mapping[str, PathLike], cameras: list[str],
                reader: Callable[[str, PathLike], LabelTable]) -> LabelsRead:
    """Read one file per camera; refuse files of cameras that have no video."""
    unknown = sorted(set(files) - set(cameras))
    if unknown:
        raise UserError(f"labels given for cameras {unknown} that have no --videos entry "
                        f"({', '.join(cameras)})")
    tables = {cam: reader(cam, path) for cam, path in files.items()}
    return LabelsRead(kind, {cam: str(p) for cam, p in files.items()}, tables)


@register("sleap")
@dataclass
class SleapFiles:
    """SLEAP analysis HDF5 (``.analysis.h5``) or project (``.slp``) files, one per camera.

    ``track``: track name or index (default: the track labelled in the most frames); ``camera_map``: the
    video or camera name holding each camera's labels where names differ; ``accept_predictions``: predicted
    instances where no person labelled the frame.
    """

    kind: ClassVar[str] = "sleap"
    per_camera: Mapping[str, PathLike]
    track: str | int | None = None
    camera_map: Mapping[str, str] | None = None
    accept_predictions: bool = False

    def files(self, cameras: list[str]) -> dict[str, str]:
        return {cam: str(p) for cam, p in self.per_camera.items()}

    def read(self, cameras: list[str], sizes: dict[str, tuple[int, int]], rig: Rig) -> LabelsRead:
        track = self.track
        if track is None:
            track = default_track(list(self.per_camera.values()), self.accept_predictions)
        return _per_camera(self.kind, self.per_camera, cameras, lambda cam, p: read_sleap_file(
            p, cam, track, self.camera_map, self.accept_predictions))


@register("sleap-project")
@dataclass
class SleapProject:
    """One SLEAP project (``.slp``) with a video per camera (:mod:`s3k.data.formats.slp`); options as
    :class:`SleapFiles`'."""

    kind: ClassVar[str] = "sleap"
    project: PathLike
    track: str | int | None = None
    camera_map: Mapping[str, str] | None = None
    accept_predictions: bool = False

    def files(self, cameras: list[str]) -> dict[str, str]:
        return {cam: str(self.project) for cam in cameras}

    def read(self, cameras: list[str], sizes: dict[str, tuple[int, int]], rig: Rig) -> LabelsRead:
        track = self.track
        if track is None:
            track = default_track([self.project], self.accept_predictions)
        tables = read_slp(self.project, cameras, camera_map=self.camera_map, track=track,
                          predictions=self.accept_predictions)
        return LabelsRead(self.kind, {cam: str(self.project) for cam in tables}, tables)


@register("nwb")
@dataclass
class Nwb:
    """One NWB file with ndx-pose training frames (or, with ``accept_predictions``, pose estimation series)
    per camera (:mod:`s3k.data.formats.nwb`)."""

    kind: ClassVar[str] = "nwb"
    path: PathLike
    camera_map: Mapping[str, str] | None = None
    accept_predictions: bool = False

    def files(self, cameras: list[str]) -> dict[str, str]:
        return {cam: str(self.path) for cam in cameras}

    def read(self, cameras: list[str], sizes: dict[str, tuple[int, int]], rig: Rig) -> LabelsRead:
        tables = read_nwb(self.path, cameras, camera_map=self.camera_map, predictions=self.accept_predictions)
        return LabelsRead(self.kind, {cam: str(self.path) for cam in tables}, tables)


FrameIdsFrom = Literal["path", "row"]


@register("deeplabcut")
@dataclass
class DeepLabCut:
    """DeepLabCut / Lightning Pose label CSVs, one per camera; ``frame_ids_from``: a row's frame index from
    its image file name's digits (``"path"``) or the row's number (``"row"``)."""

    kind: ClassVar[str] = "deeplabcut"
    per_camera: Mapping[str, PathLike]
    frame_ids_from: FrameIdsFrom = "path"

    def files(self, cameras: list[str]) -> dict[str, str]:
        return {cam: str(p) for cam, p in self.per_camera.items()}

    def read(self, cameras: list[str], sizes: dict[str, tuple[int, int]], rig: Rig) -> LabelsRead:
        return _per_camera(self.kind, self.per_camera, cameras,
                           lambda _cam, p: read_dlc_csv(p, frame_ids_from=self.frame_ids_from))


@register("lightning-pose")
@dataclass
class LightningPose:
    """Lightning Pose's multi-view CSVs, ``FOLDER/CollectedData_<camera>.csv``; options as
    :class:`DeepLabCut`'s."""

    kind: ClassVar[str] = "lightning-pose"
    folder: PathLike
    frame_ids_from: FrameIdsFrom = "path"

    def files(self, cameras: list[str]) -> dict[str, str]:
        return {k: str(v) for k, v in find_lightning_pose_csvs(self.folder, cameras).items()}

    def read(self, cameras: list[str], sizes: dict[str, tuple[int, int]], rig: Rig) -> LabelsRead:
        return _per_camera(self.kind, self.files(cameras), cameras,
                           lambda _cam, p: read_dlc_csv(p, frame_ids_from=self.frame_ids_from))


@dataclass
class _ScoredFiles:
    """Per-camera prediction files whose points carry a score; points scored below ``min_score`` are
    unlabelled. Subclasses name their format and their reader."""

    kind: ClassVar[str]
    reader: ClassVar[Callable[..., Any]]
    per_camera: Mapping[str, PathLike]
    min_score: float = 0.5

    def files(self, cameras: list[str]) -> dict[str, str]:
        return {cam: str(p) for cam, p in self.per_camera.items()}

    def read(self, cameras: list[str], sizes: dict[str, tuple[int, int]], rig: Rig) -> LabelsRead:
        reader = type(self).reader
        return _per_camera(self.kind, self.per_camera, cameras, lambda _cam, p: reader(p, self.min_score))


@register("openpose")
@dataclass
class OpenPose(_ScoredFiles):
    """OpenPose ``--write_json`` folders, one per camera; points scored below ``min_score`` are unlabelled."""

    kind: ClassVar[str] = "openpose"
    reader: ClassVar[Callable[..., Any]] = staticmethod(read_openpose_folder)


@register("mmpose")
@dataclass
class MMPose(_ScoredFiles):
    """MMPose / RTMPose predictions JSON, one per camera; points scored below ``min_score`` are unlabelled."""

    kind: ClassVar[str] = "mmpose"
    reader: ClassVar[Callable[..., Any]] = staticmethod(read_mmpose_json)


@register("deepfly3d")
@dataclass
class DeepFly3D:
    """A DeepFly3D pose result (``df3d_result*.pkl``; cameras ``camera_0``, ``camera_1``, ...): its
    ``points2d``, where DeepFly3D's rule says the camera sees the joint."""

    kind: ClassVar[str] = "deepfly3d"
    path: PathLike

    def files(self, cameras: list[str]) -> dict[str, str]:
        return {cam: str(self.path) for cam in cameras}

    def read(self, cameras: list[str], sizes: dict[str, tuple[int, int]], rig: Rig) -> LabelsRead:
        tables = read_deepfly3d_pose(self.path, sizes, rig)
        if not tables:
            raise UserError(f"{self.path}: no camera camera_0, camera_1, ... among the videos' cameras "
                            f"({', '.join(cameras)})")
        notes = []
        hidden = sorted({len(t.unseen) for t in tables.values()})
        if hidden[-1]:
            shown = hidden[0] if len(hidden) == 1 else f"{hidden[0]} to {hidden[-1]}"
            notes.append(f"note: DeepFly3D's visibility rule leaves {shown} of the {len(JOINTS)} joints "
                         "unlabelled in each camera: those of the fly's far side "
                         "(docs/importing.md#what-happens-to-each-format)")
        return LabelsRead(self.kind, {cam: str(self.path) for cam in tables}, tables, notes)
