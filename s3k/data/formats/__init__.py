"""Other tools' files, one module per format: readers (and writers) of calibrations, 2D labels and 3D tracks.

- calibrations, each to a :class:`s3k.data.rig.Rig`: :mod:`~s3k.data.formats.anipose` (TOML, also written),
  :mod:`~s3k.data.formats.qualisys` (``.qca.txt``), :mod:`~s3k.data.formats.opencv_calib` (OpenCV / JARVIS
  YAML, XML), :mod:`~s3k.data.formats.deepfly3d` (pickles, also its 2D poses, read through
  :mod:`~s3k.data.formats.safe_pickle`, the restricted unpickler); :mod:`~s3k.data.formats.calibration_files`
  chooses among them by content.
- 2D labels, each to a :class:`~s3k.data.formats.labels2d.LabelTable` per camera: :mod:`~s3k.data.formats.dlc`
  (DeepLabCut / Lightning Pose CSVs), :mod:`~s3k.data.formats.sleap` (SLEAP analysis HDF5),
  :mod:`~s3k.data.formats.slp` (SLEAP projects), :mod:`~s3k.data.formats.nwb` (NWB with ndx-pose, also 3D
  tracks out), :mod:`~s3k.data.formats.pose_json` (OpenPose, MMPose JSON).
- :mod:`~s3k.data.formats.label_export`: a dataset's labels (and tracks) written out in those formats.

The modules import their optional dependencies (h5py, sleap-io, pynwb) only when called. Turning a recording
into an s3k dataset is :mod:`s3k.data.recording`'s job.
"""
