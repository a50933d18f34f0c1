"""`s3k predict`: command-line front end of :mod:`s3k.predict`."""

from s3k.predict import configure_parser, run

__all__ = ["configure_parser", "run"]
