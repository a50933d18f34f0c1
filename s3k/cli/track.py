"""`s3k track`: command-line front end of :mod:`s3k.track`."""

from s3k.track import configure_parser, run

__all__ = ["configure_parser", "run"]
