"""`s3k train`: command-line front end of :mod:`s3k.train`."""

from s3k.train import configure_parser, run

__all__ = ["configure_parser", "run"]
