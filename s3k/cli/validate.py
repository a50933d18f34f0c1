"""`s3k validate`: command-line front end of :mod:`s3k.data.validate`."""

from s3k.data.validate import configure_parser, run

__all__ = ["configure_parser", "run"]
