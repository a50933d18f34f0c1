"""`s3k evaluate`: command-line front end of :mod:`s3k.evaluate`."""

from s3k.evaluate import configure_parser, run

__all__ = ["configure_parser", "run"]
