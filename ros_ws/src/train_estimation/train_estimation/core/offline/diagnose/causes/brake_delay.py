"""``brake_delay``: braking commands take effect later than train.yaml's delay (traction does
not: the brake is its own chain). The extra delay is profiled over a grid of re-timed braking
columns, jointly with the common command-time offset (a nuisance)."""

from __future__ import annotations

import math

import numpy as np
from train_core.effects import BrakeDelayEffect

from .base import Cause, resolved
from .braking_rate import brakes_while_moving


class BrakeDelay(Cause):
    name = "brake_delay"
    # no halves test: the delay's standard error is the profile's curvature at the best
    # command offset alone (the two trade off), too small to compare the folds by (true
    # subtle delays fitted 1.638 and 1.580 s, z +4.2; 0.922 and 0.842 s, z +3.5)
    halves = ()

    def nominal(self, mo) -> dict:
        return {"delay": mo.train.brake.delay}
    family = "motion"

    def untestable(self, run, cfg, own) -> str | None:
        return None if brakes_while_moving(run, cfg) else "no braking while moving in the data"

    def fit(self, st) -> tuple:
        """Profile over (common offset, extra braking delay > 0): the brake chain's own
        timing; the delay refined by a parabola through the profile at the best offset."""
        mo = st.mo
        grid = []
        for s in mo.shifts:
            for d in mo.delays:
                if d <= 0.0:
                    continue
                key = round(float(s + d), 6)
                if key not in mo.braking_cols and key != 0.0:
                    continue
                grid.append((float(s), float(d)))
        lls = st.fixed_lls([st.retime(s, d) for s, d in grid]).tolist() if grid else []
        prof = dict(zip(grid, lls))
        if not prof:
            return -math.inf, 1, {}, {}, {}
        (s_b, d_b), ll = max(prof.items(), key=lambda kv: kv[1])
        ds = sorted(d for (s, d) in prof if s == s_b)
        lls = [prof[(s_b, d)] for d in ds]
        d_hat, se = _parabola(ds, lls, ds.index(d_b))
        delay = mo.train.brake.delay + d_hat
        return ll, 1, {"delay": delay}, {"delay": se}, {"offset": s_b, "extra": d_hat,
                                                          "profile": [(d, lls[k]) for k, d in
                                                                      enumerate(ds)]}

    def resolution(self, fit, mo) -> str | None:
        """A delay change below one odometer period is not a delay the samples can show."""
        t = mo.ev.t[mo.ev.odo]
        period = float(np.median(np.diff(t))) if t.size > 1 else 0.0
        return resolved("delay", fit.parameters["delay"] - mo.train.brake.delay,
                        fit.std_errors.get("delay"), period, " s")

    def extend_null(self, null, fit, mo) -> None:
        ex = fit.extra
        null.shift = ex["offset"]
        # snap to the grid the columns exist on
        d = min(mo.delays, key=lambda d: abs(d - ex["extra"]))
        null.brake_extra = float(d)

    def replay_offset(self, extra: dict, shift: float) -> float:
        # a brake delay is fitted with its own offset: the pair is the extension's timing
        return extra["offset"]

    def effect(self, params: dict, duration: float) -> BrakeDelayEffect:
        return BrakeDelayEffect(float(params["delay"]))


def _parabola(ds: list, lls: list, i: int) -> tuple[float, float]:
    """Vertex of the parabola through the profile at i - 1, i, i + 1 and its standard error
    from the curvature of the profile log-likelihood; (ds[i], nan) at an edge or when flat."""
    d_hat, se = ds[i], math.nan
    if 0 < i < len(ds) - 1:
        y0, y1, y2 = lls[i - 1], lls[i], lls[i + 1]
        h = ds[i + 1] - ds[i]
        den = y0 - 2 * y1 + y2
        if den < 0:
            d_hat = ds[i] + 0.5 * h * (y0 - y2) / den
            se = h / math.sqrt(-den)
    return d_hat, se


CAUSE = BrakeDelay()
