"""What the tests share: small datasets and run folders built in a few seconds, the real recording's place.

- :mod:`helpers.synthetic_rig`: a static 4-camera rig looking at a rigid triangle of three keypoints;
  ``make_dataset`` writes a dataset folder of it (``KEYPOINTS``, ``CAMERAS``, ``LAYOUT``, ``rig``,
  ``project``, ``random_rotation``; ``count_decodes`` counts the images a module decodes).
- :mod:`helpers.label_data`: coloured dots for the labelling app's tests (``make_label_dataset``,
  ``save_label_run``).
- :mod:`helpers.tiny_detector`: ``save_run``, a run folder holding an untrained tiny detector; ``make_run``.
- :mod:`helpers.track_rig`: the three-camera rig, videos and run of ``s3k track``'s tests.
- :mod:`helpers.recordings`: recordings for ``s3k import`` (``write_recording``, ``write_import_recording``).
- :mod:`helpers.experiment_results`: made-up results of ``s3k experiment`` runs.
- :mod:`helpers.paths`: ``REPO``, ``TESTS``, ``OLD_RUNS``.
- :mod:`helpers.files`: ``contents``, every file of a folder with its bytes and time, to tell nothing was
  written.
- :mod:`helpers.real_recording`: ``REAL``, the read-only real recording; ``needs_real`` skips without it.

``tests/conftest.py`` builds fixtures on them (``tiny_dataset``, ``tiny_run``, ``track_recording``,
``import_recording``, ``device``, ``dtype``).
"""
