"""`s3k check-calibration`: command-line front end of :mod:`s3k.calibration`."""

from s3k.calibration import configure_parser, run

__all__ = ["configure_parser", "run"]
