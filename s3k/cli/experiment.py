"""`s3k experiment`: command-line front end of :mod:`s3k.experiments`."""

from s3k.experiments import configure_parser, run

__all__ = ["configure_parser", "run"]
