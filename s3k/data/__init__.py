"""The dataset layer: the folder format, its loader and writer, importers, image and video sources.

Import the public names from here (``from s3k.data import Dataset``); the modules behind them may move.
"""

from s3k.data.format import (
    SPLITS,
    Dataset,
    DatasetError,
    DatasetWarning,
    DatasetWriter,
    Problem,
    check_dataset,
)

__all__ = ["SPLITS", "Dataset", "DatasetError", "DatasetWarning", "DatasetWriter", "Problem", "check_dataset"]
