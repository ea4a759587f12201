"""``braking_rate``: the brakes deliver f(t) times the commanded deceleration, f drifting
linearly from f_start (first message) to f_end (last message)."""

from __future__ import annotations

import numpy as np
from train_core.effects import BrakingRateEffect

from .base import Cause, fleet_se, resolved


class BrakingRate(Cause):
    name = "braking_rate"
    range_bound = True  # plausible() is a sign bound
    halves = ("f_start", "f_end")

    def nominal(self, mo) -> dict:
        return {"f_start": mo.f0, "f_end": mo.f0}
    family = "motion"
    linear = True

    # a braking that fades within and after each application, as the brakes heat, is weaker
    # by a heat that builds and cools, neither a factor drifting in time nor one on a stretch
    heat_rival = "brakes that fade as they heat"

    def untestable(self, run, cfg, own) -> str | None:
        return None if brakes_while_moving(run, cfg) else "no braking while moving in the data"

    def free(self, st, extra=None) -> list:
        return [{"br": 1.0, "brt": -1.0}, {"brt": 1.0}]

    def params(self, st, th, cov, extra=None) -> tuple:
        sd = np.sqrt(np.clip(np.diag(cov), 0, None))
        f0 = st.mo.f0
        return {"f_start": f0 + th[0], "f_end": f0 + th[1]}, \
            {"f_start": sd[0], "f_end": sd[1]}, {}

    def fit(self, st) -> tuple:
        return self.fit_linear(st)

    def resolution(self, fit, mo) -> str | None:
        """The larger change of f (start or end) beyond 0.02 (2 % of the braking)."""
        p, se = fit.parameters, fit.std_errors
        k = max(("f_start", "f_end"), key=lambda k: abs(p[k] - mo.f0))
        return resolved(k, p[k] - mo.f0, se.get(k), 0.02)

    def plausible(self, fit, mo) -> str | None:
        """A brake delivers some of the deceleration asked for, never a drive: f above 0 at
        both ends (a fit at or below 0 is a force of another kind in the braking)."""
        p = fit.parameters
        low = min(float(p["f_start"]), float(p["f_end"]))
        if low > 0.0:
            return None
        return f"not a braking rate: f reaches {low:.2f} (a brake that drives the train)"

    def extend_null(self, null, fit, mo) -> None:
        p = fit.parameters
        ds, de = p["f_start"] - mo.f0, p["f_end"] - mo.f0
        null.drift["br"] = null.drift.get("br", 0.0) + ds
        null.drift["brt"] = null.drift.get("brt", 0.0) + de - ds

    def effect(self, params: dict, duration: float) -> BrakingRateEffect:
        return BrakingRateEffect(f_start=params["f_start"], f_end=params["f_end"],
                                 t_start=0.0, t_end=duration)

    def model_effect(self, fit, ctx):
        return self.effect({k: float(v) for k, v in fit.parameters.items()},
                           round(ctx.duration, 3)), None

    def series(self, params: dict, mo, out: dict) -> None:
        out["f_t"] = (np.array([0.0, mo.run.duration]),
                      np.array([params["f_start"], params["f_end"]]))

    def fleet_row(self, fit, evidence, accepted, train) -> dict:
        """The mean of f_start and f_end with the larger-correlation bound of its standard
        error: their correlation is not reported, so half the sum of the two (perfect
        correlation)."""
        se0, se1 = fleet_se(evidence, "f_start"), fleet_se(evidence, "f_end")
        if not (se0 and se1):
            return {}
        p = fit.parameters
        return {"braking_rate": 0.5 * (p["f_start"] + p["f_end"]),
                "braking_rate_se": 0.5 * (se0 + se1)}


def brakes_while_moving(run, cfg) -> bool:
    """Whether the data hold a braking command while the train moves (the brake's causes
    cannot be tested otherwise)."""
    braking = run.ctrl_a < -cfg.min_brake
    v_at_cmd = np.interp(run.ctrl_t, run.odo_t, run.odo_v)
    return bool(np.any(braking & (v_at_cmd > cfg.standstill_speed)))


CAUSE = BrakingRate()
