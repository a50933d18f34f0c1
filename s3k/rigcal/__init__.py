"""Calibrating a rig from a board seen by its cameras (``s3k calibrate``; ``s3k check-calibration
--recalibrate`` uses the same solver): :mod:`~s3k.rigcal.boards` (boards and their detection),
:mod:`~s3k.rigcal.solve` (intrinsics, the camera graph), :mod:`~s3k.rigcal.bundle` (bundle adjustment),
:mod:`~s3k.rigcal.rig` (the whole rig), :mod:`~s3k.rigcal.figure` (the picture)."""
