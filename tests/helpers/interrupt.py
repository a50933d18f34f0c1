"""A training stopped part-way, as a kill would stop it, for the tests of ``--resume``."""


class Killed(Exception):
    """Raised by :func:`kill_after_three` in place of a kill."""


def kill_after_three(step, terms):
    """A training callback that aborts the run after its third step, as a kill would."""
    if step == 3:
        raise Killed
