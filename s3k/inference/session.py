"""A trained detector placed on a rig: the one preparation of ``s3k track``, ``s3k stream``, ``s3k predict``
and the labelling app's suggestions.

:meth:`RigSession.place` takes a loaded :class:`s3k.detector.Detector` and the frames' sizes per camera and,
from the detector's own (typed) meta, does everything that stands between a calibration file and the first
frame: it refuses cameras the run was never trained on (:func:`s3k.inference.rig_check.check_rig`), reads
the calibration with the frames' sizes and the region of the calibrated image each camera shows, refuses
frames of another size than the calibrated one, chooses each camera's box onto the detector's input (the
``--crop`` given, else the box the run was trained on, else :func:`fit_box`) and gathers what the user should
hear (the boxes applied, a calibration that differs from the run's), logged once.
:meth:`RigSession.on_dataset` is the same for a dataset's frames (its cameras are its own).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from s3k.base.choices import Device, Fit
from s3k.base.errors import UserError
from s3k.data import Dataset
from s3k.data.formats.calibration_files import read_calibration
from s3k.detector import Detector
from s3k.detector.geometry_record import Box, fit_box, input_boxes, recorded_geometry
from s3k.geometry import Cameras
from s3k.inference.rig_check import calibration_notes, check_dataset_rig, check_rig

__all__ = ["Box", "RigOptions", "RigSession", "fit_box"]

log = logging.getLogger(__name__)

@dataclass(frozen=True)
class RigOptions:
    """The rig of ``s3k track`` and ``s3k stream`` (``s3k.cli.options.add_rig_options``).

    Attributes:
        calibration: a calibration file of any format
            :func:`s3k.data.formats.calibration_files.read_calibration` reads.
        units: world unit of the calibration when the file does not say.
        video_regions: ``{camera: box}``, the region of the calibrated image each camera's frames show
            (:meth:`s3k.data.rig.Rig.with_video_regions`).
        crops: ``{camera: box}`` onto the detector's input, as given to ``s3k import --crop`` (default: the
            boxes the run was trained on).
        fit: how frames map onto the input when no box is given or recorded (None: ``"pad"``, and the
            recorded boxes apply).
        device: where the detector runs (``"auto"``, ``"cpu"``, ``"cuda"``...).
        other_rig: use the run on cameras it was not trained on.
        frame_offsets: ``{camera: N}`` for cameras whose clocks are off: the camera's frame ``i`` shows the
            others' frame ``i + N`` (``--frame-offsets``; default 0 for every camera).
    """

    calibration: str | Path
    units: str | None = None
    video_regions: dict[str, Box] | None = None
    crops: dict[str, Box] | None = None
    fit: Fit | None = None
    device: Device = "auto"
    other_rig: bool = False
    frame_offsets: dict[str, int] | None = None


@dataclass
class RigSession:
    """A loaded detector placed on a rig (module docstring).

    Attributes:
        detector: the detector.
        names: the cameras, in the order of the frames.
        cameras: their calibration ``(C,)`` float64 in the frames' own pixels (None: per-frame, a dataset's).
        boxes: ``(C, 4)`` each camera's box onto the detector's input (None: the whole frame).
        units: the calibration's world unit.
        notes: what the user should hear (``warning: ...`` lines among them), logged when placed.
        offsets: each camera's frame offset (:attr:`RigOptions.frame_offsets`), 0 for a synchronized one.
    """

    detector: Detector
    names: list[str]
    cameras: Cameras | None
    boxes: np.ndarray | None
    units: str
    notes: list[str] = field(default_factory=list)
    offsets: list[int] = field(default_factory=list)

    @classmethod
    def place(cls, detector: Detector, sizes: dict[str, tuple[int, int]], rig: RigOptions,
              what: str = "--videos", sources: Mapping[str, object] | None = None,
              level: int = logging.INFO) -> RigSession:
        """Place ``detector`` on the cameras of ``sizes`` (``{camera: (W, H)}`` of their frames, in the order
        of the frames) calibrated by ``rig``; the notes are logged, warnings as warnings and the others at
        ``level`` (:data:`s3k.base.messages.NOTE` where standard output is the command's data).

        Raises:
            UserError: fewer than two cameras, one the run was not trained on (unless ``rig.other_rig``) or
                the calibration lacks, frames of another size than the calibrated one (naming ``what`` and
                the camera's entry of ``sources``).
        """
        names = list(sizes)
        if len(names) < 2:
            raise UserError(f"{what}: triangulation needs at least 2 cameras, got {len(names)} "
                            f"({', '.join(names)})")
        meta = detector.frame_meta
        if not rig.other_rig:
            check_rig(meta, detector.run, names, what=what)
        calib = read_calibration(rig.calibration, units=rig.units)
        unknown = [c for c in names if c not in calib.names]
        if unknown:
            raise UserError(f"{what}: camera {', '.join(map(repr, unknown))} is not in the calibration "
                            f"(its cameras are {', '.join(calib.names)})")
        calib = calib.with_sizes(sizes)
        if rig.video_regions:
            try:
                calib = calib.with_video_regions(rig.video_regions)  # type: ignore[arg-type]
            except (KeyError, ValueError) as exc:
                raise UserError(f"--video-region: {exc.args[0]}") from None
        calib = calib.select(names)
        sizes_of = {n: (int(w), int(h)) for n, (w, h) in zip(calib.names, calib.size)}
        notes = calibration_notes(meta, detector.run, calib.cameras, calib.names, calib.units, sizes_of,
                                  rig.calibration)
        for name in names:
            if tuple(sizes[name]) != sizes_of[name]:
                (W, H), (cw, ch) = sizes[name], sizes_of[name]
                raise UserError(
                    f"camera {name!r}: {what} {(sources or {}).get(name, name)} is {W}x{H} pixels but the "
                    f"calibration gives {cw}x{ch}; the intrinsics apply only to images of the calibrated "
                    "size",
                    hint="if the frames are the calibrated image cropped or padded by a few pixels, declare "
                         f"it with --video-region {name}=X0,Y0,X1,Y1")
        boxes, crop_notes = input_boxes(recorded_geometry(meta.geometry), sizes, rig.crops, rig.fit,
                                        detector.input_size)
        offsets = [int((rig.frame_offsets or {}).get(n, 0)) for n in names]
        unknown = sorted(set(rig.frame_offsets or {}) - set(names))
        if unknown:
            raise UserError(f"--frame-offsets {unknown[0]}: no camera {unknown[0]!r} in {what} "
                            f"(cameras: {', '.join(names)})")
        return cls(detector, names, calib.cameras, boxes, calib.units, crop_notes + notes,
                   offsets).said(level)

    @classmethod
    def on_dataset(cls, detector: Detector, ds: Dataset, other_rig: bool = False,
                   option: str = "--other-rig", rig: bool = True) -> RigSession:
        """Place ``detector`` on the frames of the dataset ``ds`` (its own cameras, frame by frame): images
        of another part of the frames and (``rig``) other cameras or keypoints are refused unless
        ``other_rig`` (``option`` names the override), and a calibration that differs from the run's is
        logged (:func:`s3k.inference.rig_check.check_dataset_rig`)."""
        check_dataset_rig(detector.frame_meta, detector.run, ds, not other_rig, option, rig)
        return cls(detector, list(ds.cameras), None, None, str(ds.units))

    def said(self, level: int = logging.INFO) -> RigSession:
        """Log the notes, warnings as warnings and the others at ``level``; returns ``self``."""
        for line in self.notes:
            if line.startswith("warning: "):
                log.warning(line.removeprefix("warning: "))
            else:
                log.log(level, line)
        return self
