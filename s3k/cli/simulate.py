"""`s3k simulate`: command-line front end of :mod:`s3k.sim.cli`."""

from s3k.sim.cli import configure_parser, run

__all__ = ["configure_parser", "run"]
