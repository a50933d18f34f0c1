"""`s3k demo`: command-line front end of :mod:`s3k.demo`."""

from s3k.demo import configure_parser, run

__all__ = ["configure_parser", "run"]
