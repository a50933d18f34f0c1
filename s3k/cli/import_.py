"""`s3k import`: command-line front end of :mod:`s3k.data.importers`."""

from s3k.data.importers import configure_parser, run

__all__ = ["configure_parser", "run"]
