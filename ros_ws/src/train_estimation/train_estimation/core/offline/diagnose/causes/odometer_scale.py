"""``odometer_scale``: the odometer reads ``scale`` times the true distance and speed (wheel
wear). Measured against the balises: untestable with fewer than two readings."""

from __future__ import annotations

import numpy as np
from train_core.effects import OdometerScaleEffect

from .base import Cause, fleet_se, resolved


class OdometerScale(Cause):
    name = "odometer_scale"
    range_bound = True  # plausible() is a sign bound
    halves = ("scale",)

    def nominal(self, mo) -> dict:
        return {"scale": 1.0}

    def halves_own(self, mo, others, cfg, noise, alpha: float, min_share: float,
                   fit=None) -> dict:
        """The scale over the halves of the distance run and of the speeds run
        (:func:`..halves.odometer_halves`): a scale that changed mid-run, or an error that
        depends on speed, counts the halves differently."""
        from ..halves import odometer_halves

        return odometer_halves(mo, others, cfg, noise, alpha, min_share)
    family = "odometer"
    linear = True
    count_rival = "an odometer error that grows with speed (k v / v_top: a radar's)"
    offset_rival = "an odometer that reads b m/s more or less than the speed while moving"

    def untestable(self, run, cfg, own) -> str | None:
        if run.bal_t.size < 2:
            return "fewer than two balise readings: distance has no reference"
        return None

    def free(self, st, extra=None) -> list:
        return [{"scale": 1.0}]

    def params(self, st, th, cov, extra=None) -> tuple:
        sd = np.sqrt(np.clip(np.diag(cov), 0, None))
        return {"scale": 1.0 + st.null.scale + th[0]}, {"scale": sd[0]}, {}

    def fit(self, st) -> tuple:
        return self.fit_linear(st)

    def resolution(self, fit, mo) -> str | None:
        """A scale within 0.1 % of 1 is within a wheel's wear between calibrations."""
        return resolved("scale", fit.parameters["scale"] - 1.0, fit.std_errors.get("scale"),
                        1e-3)

    def plausible(self, fit, mo) -> str | None:
        """An odometer counts the distance run, more or less: a scale at or below 0 is no
        wheel's."""
        sc = float(fit.parameters["scale"])
        return None if sc > 0.0 else f"not an odometer scale: {sc:.3f}"

    def extend_null(self, null, fit, mo) -> None:
        null.scale = fit.parameters["scale"] - 1.0

    def effect(self, params: dict, duration: float) -> OdometerScaleEffect:
        return OdometerScaleEffect(float(params["scale"]))

    def gain(self, fit, ctx) -> dict:
        """Balise positions predicted from the odometer distance: s0 (and the scale) fitted on
        the odd-numbered readings, error at the even-numbered ones."""
        run = ctx.mo.run
        d_at = np.interp(run.bal_t, run.odo_t, run.odo_d)
        fit_ = np.arange(run.bal_t.size) % 2 == 1
        test = ~fit_
        if fit_.sum() < 2 or test.sum() < 1:
            return {"metric": "held-out balise position error RMS (m)", "before": None,
                    "after": None}
        s0_b = float(np.mean(run.bal_p[fit_] - d_at[fit_]))
        A = np.stack([np.ones(fit_.sum()), d_at[fit_]], axis=1)
        (s0_a, inv_scale), *_ = np.linalg.lstsq(A, run.bal_p[fit_], rcond=None)
        before = float(np.sqrt(np.mean((s0_b + d_at[test] - run.bal_p[test]) ** 2)))
        after = float(np.sqrt(np.mean((s0_a + inv_scale * d_at[test] - run.bal_p[test]) ** 2)))
        return {"metric": "held-out balise position error RMS (m), odometer distance placed by "
                          "the odd-numbered balises, tested on the even-numbered",
                "before": before, "after": after, "scale_fitted_on_half": float(1.0 / inv_scale)}

    def fleet_row(self, fit, evidence, accepted, train) -> dict:
        """The fitted scale and its standard error (the fleet's per-train trend)."""
        se = fleet_se(evidence, "scale")
        return {"odometer_scale": fit.parameters["scale"], "odometer_scale_se": se} if se else {}


CAUSE = OdometerScale()
