"""``mass``: the train's true mass differs from train.yaml's.

The drive force is computed for the believed mass (docs/interfaces.md), so a wrong mass scales the
traction, braking and resistance accelerations together: one combination of those columns.
"""

from __future__ import annotations

import numpy as np
from train_core.effects import MassEffect

from .base import Cause, fleet_se, resolved


class Mass(Cause):
    name = "mass"
    range_bound = True  # plausible() is a sign bound
    halves = ("mass",)

    def nominal(self, mo) -> dict:
        return {"mass": mo.train.mass}
    family = "motion"
    linear = True

    def free(self, st, extra=None) -> list:
        mo = st.mo
        return [{"tr": 1.0, "br": mo.f0, "one": mo.alpha0, "v": mo.beta0, "v2": mo.gamma0}]

    def params(self, st, th, cov, extra=None) -> tuple:
        mo = st.mo
        sd = np.sqrt(np.clip(np.diag(cov), 0, None))
        k = 1.0 + th[0]
        return {"mass": mo.train.mass / k}, {"mass": mo.train.mass * sd[0] / k ** 2}, \
            {"traction_gain": k}

    def fit(self, st) -> tuple:
        return self.fit_linear(st)

    def resolution(self, fit, mo) -> str | None:
        """A mass within 1 % of the believed one is within a train's load variation."""
        m0 = mo.train.mass
        se = fit.std_errors.get("mass")
        return resolved("mass (relative)", fit.parameters["mass"] / m0 - 1.0,
                        None if se is None else se / m0, 0.01)

    def plausible(self, fit, mo) -> str | None:
        """A mass is positive: a fit whose drive gain (believed / true mass) is at or below 0
        reverses every acceleration the commands give, which no load does."""
        k = float(fit.extra.get("traction_gain", 1.0)) if fit.extra else 1.0
        if k > 0.0:
            return None
        return f"not a mass: the accelerations the commands give x {k:.2f}"

    def extend_null(self, null, fit, mo) -> None:
        dk = fit.extra["traction_gain"] - 1.0
        null.drive_gain = fit.extra["traction_gain"]  # the other causes' drive increments too
        for name, c in (("tr", 1.0), ("br", mo.f0), ("one", mo.alpha0), ("v", mo.beta0),
                        ("v2", mo.gamma0)):
            null.drift[name] = null.drift.get(name, 0.0) + dk * c

    def effect(self, params: dict, duration: float) -> MassEffect:
        return MassEffect(float(params["mass"]))

    def model_effect(self, fit, ctx):
        return self.effect(fit.parameters, ctx.duration), (
            "mass: true mass in effects.yaml (the drive force stays computed for train.yaml's "
            "believed mass, as in the data)")

    def fleet_row(self, fit, evidence, accepted, train) -> dict:
        """The fitted mass and its standard error (the fleet's per-train trend)."""
        se = fleet_se(evidence, "mass")
        return {"mass": fit.parameters["mass"], "mass_se": se} if se else {}


CAUSE = Mass()
