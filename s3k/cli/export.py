"""`s3k export`: command-line front end of :mod:`s3k.export`."""

from s3k.export import configure_parser, run

__all__ = ["configure_parser", "run"]
