"""Camera rigs outside a scene's training rig: test sets whose cameras a detector never saw in training.

Every scene draws its cameras from its :class:`s3k.sim.scene.CameraSampler` (distance, elevation above the
table, vertical field of view). A named rig changes one of those ranges to lie wholly outside the scene's
own, everything else (aim point, azimuth spread, roll, object poses, lighting) as in training:

- ``train``: the scene's own rig (the in-range reference);
- ``low``: elevations 15 to 5 degrees below the lowest of training (at least 5 degrees);
- ``high``: elevations 5 to 15 degrees above the highest (at most 88 degrees);
- ``far``: distances 1.15 to 1.4 times the farthest;
- ``wide``: a lens with 1.5 times the field of view (the object smaller in the image at the same distance).

Each frame draws the same random numbers whatever the rig, so test sets of one ``--seed`` show the same
object poses and lighting seen from other cameras.

A training rig may itself be other than the scene's (``s3k simulate --elevation LO,HI --distance LO,HI``,
:func:`ranged_sampler`); the named rigs are then drawn relative to that one.
"""

from __future__ import annotations

import dataclasses
import math

from s3k.sim.scene import CameraSampler

#: The named rigs, the scene's own first.
RIGS = ("train", "low", "high", "far", "wide")
#: How far outside the training ranges each rig lies (see the module's documentation).
LOW_DEG = (15.0, 5.0)
HIGH_DEG = (5.0, 15.0)
FAR_FACTOR = (1.15, 1.4)
WIDE_FACTOR = 1.5
#: The elevations a rig may be given (degrees above the table): from nearly edge-on to nearly straight above.
ELEVATION_LIMITS = (5.0, 88.0)
#: The distances a rig may be given (metres from the aim point).
DISTANCE_LIMITS = (0.2, 10.0)


def _clip(low: float, high: float) -> tuple[float, float]:
    """An elevation range kept between 5 and 88 degrees (the table edge-on, a camera straight above)."""
    return min(88.0, max(5.0, low)), min(88.0, max(5.0, high))


def rig_sampler(train: CameraSampler, rig: str) -> CameraSampler:
    """The camera sampler of rig ``rig`` (one of :data:`RIGS`) for a scene whose training rig is ``train``.

    Raises:
        ValueError: an unknown rig name.
    """
    lo, hi = train.elevation_deg
    if rig == "train":
        return train
    if rig == "low":
        return dataclasses.replace(train, elevation_deg=_clip(lo - LOW_DEG[0], lo - LOW_DEG[1]))
    if rig == "high":
        return dataclasses.replace(train, elevation_deg=_clip(hi + HIGH_DEG[0], hi + HIGH_DEG[1]))
    if rig == "far":
        far = train.distance[1]
        return dataclasses.replace(train, distance=(far * FAR_FACTOR[0], far * FAR_FACTOR[1]))
    if rig == "wide":
        return dataclasses.replace(train, fovy_deg=train.fovy_deg * WIDE_FACTOR)
    raise ValueError(f"camera rig: unknown {rig!r}; choose from {', '.join(RIGS)}")


def range_problem(values: tuple[float, float] | None, limits: tuple[float, float], unit: str) -> str | None:
    """Why ``values`` is no range ``LO,HI`` within ``limits`` (None when it is one or is not given)."""
    if values is None:
        return None
    if len(values) != 2 or not all(math.isfinite(v) for v in values):
        return f"expected two numbers LO,HI, got {values!r}"
    lo, hi = values
    if not limits[0] <= lo <= hi <= limits[1]:
        return (f"expected LO <= HI, both from {limits[0]:g} to {limits[1]:g} {unit}, got "
                f"{lo:g},{hi:g}")
    return None


def ranged_sampler(base: CameraSampler, elevation: tuple[float, float] | None = None,
                   distance: tuple[float, float] | None = None) -> CameraSampler:
    """``base`` with its elevation range (degrees) and distance range (metres) replaced where given.

    Raises:
        ValueError: a range out of order or outside :data:`ELEVATION_LIMITS` / :data:`DISTANCE_LIMITS`.
    """
    for name, values, limits, unit in (("elevation", elevation, ELEVATION_LIMITS, "degrees"),
                                       ("distance", distance, DISTANCE_LIMITS, "m")):
        problem = range_problem(values, limits, unit)
        if problem:
            raise ValueError(f"camera {name}: {problem}")
    if elevation is not None:
        base = dataclasses.replace(base, elevation_deg=(float(elevation[0]), float(elevation[1])))
    if distance is not None:
        base = dataclasses.replace(base, distance=(float(distance[0]), float(distance[1])))
    return base


def describe_rig(sampler: CameraSampler) -> dict:
    """The ranges of a camera sampler, for a dataset's metadata."""
    return {"distance_m": list(sampler.distance), "elevation_deg": list(sampler.elevation_deg),
            "fovy_deg": sampler.fovy_deg}
