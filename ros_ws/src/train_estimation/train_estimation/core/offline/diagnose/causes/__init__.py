"""The registry of causes: adding a cause is one module in this package and one line here.

``REGISTRY`` lists the causes in docs/interfaces.md's order (the ranking's order among equal
scores); ``SCORING`` is the order the search scores them in (by family: the motion model first).
"""

from __future__ import annotations

from . import (
    adhesion_section,
    brake_delay,
    braking_rate,
    bursty_link,
    clock_drift,
    gradient,
    mass,
    odometer_scale,
    power_limit,
    resistance,
    traction_delay,
    wheel_slip,
)
from .base import FAMILIES, Cause, ModelContext

REGISTRY: tuple[Cause, ...] = (
    gradient.CAUSE,
    resistance.CAUSE,
    braking_rate.CAUSE,
    odometer_scale.CAUSE,
    wheel_slip.CAUSE,
    bursty_link.CAUSE,
    brake_delay.CAUSE,
    mass.CAUSE,
    clock_drift.CAUSE,
    power_limit.CAUSE,
    adhesion_section.CAUSE,
    traction_delay.CAUSE,
)

CAUSES: tuple[str, ...] = tuple(c.name for c in REGISTRY)
BY_NAME: dict[str, Cause] = {c.name: c for c in REGISTRY}
SCORING: tuple[Cause, ...] = tuple(sorted(REGISTRY, key=lambda c: FAMILIES.index(c.family)))

__all__ = ["BY_NAME", "CAUSES", "FAMILIES", "REGISTRY", "SCORING", "Cause", "ModelContext"]
