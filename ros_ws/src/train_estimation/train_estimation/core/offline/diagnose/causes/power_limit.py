"""``power_limit``: traction limited by power. The traction acceleration delivered is at most
p_spec / v (train_core dynamics.py), so a command a is met below the knee speed p_spec / a and
falls short above it; braking is untouched.

The extension is the drift column -max(a_tr - p_spec / v, 0) (a_tr: the null's traction
through the actuator, re-timed by an accepted traction delay or else by the command-time
offset, so that the limit caps the traction the train is asked for when it arrives;
v: the reference speed), with coefficient 1: p_spec is profiled over a
log-spaced grid spanning the traction powers a_tr v the run reaches (one filter run for all of
them, ``drive.Candidates``) and refined by a parabola in log p_spec. A power limit shows only in
traction above the knee: a resistance or mass change acts in every phase, which is how the two
are told apart."""

from __future__ import annotations

import math

import numpy as np
from train_core.effects import PowerLimitEffect

from .base import Cause, resolved
from .drive import Candidates, null_traction, parabola, untestable_without_traction

GRID = 40  # candidate powers, log-spaced
MIN_TRACTION = 0.05  # m/s^2, traction commands below this cannot show a limit


class PowerLimit(Cause):
    name = "power_limit"
    halves = ("p_spec",)
    family = "motion"
    profiled = True

    def untestable(self, run, cfg, own) -> str | None:
        return untestable_without_traction(run, cfg, MIN_TRACTION)

    def fit(self, st) -> tuple:
        powers = _grid(st.mo)
        if powers.size < 3:
            return -math.inf, 1, {}, {}, {}
        a_tr = null_traction(st.mo, st.null)
        cand = Candidates(st, np.stack([deficit(st.mo, p, a_tr) for p in powers]).T)
        dll = np.array([cand.dll(q) for q in cand.quads_each()])
        i = int(np.argmax(dll))
        x_hat, se_x = parabola(np.log(powers), dll, i)
        p_hat = math.exp(x_hat)
        # the score is the grid's best (the refined power is not scored: one filter run less)
        ll = st.null_ll() + float(dll[i])
        return ll, 1, {"p_spec": p_hat}, {"p_spec": p_hat * se_x}, {
            "knee_speed_at_max_command": p_hat / max(float(np.max(st.mo.a_tr0)), 1e-9),
            "profile": list(zip(powers.tolist(), dll.tolist()))}

    def profile(self, st) -> tuple | None:
        """p_spec with its deficit columns: fitted first, a power limit takes the part of a
        resistance or mass change that shows in traction at speed; the joint refit profiles it
        with those free (a resistance change also shows when coasting and braking, a limit
        does not)."""
        powers = _grid(st.mo)
        if powers.size < 3:
            return None
        a_tr = null_traction(st.mo, st.null)
        return "p_spec", powers, st.null.drive_gain * np.stack(
            [deficit(st.mo, p, a_tr) for p in powers], axis=1)

    def resolution(self, fit, mo) -> str | None:
        """A limit is a limit only below the largest traction power the run asked for, by more
        than 3 SE and by 5 % of that power: a knee at the top of the run's powers takes away
        too little traction to tell from the believed train."""
        sel = (mo.a_tr0 > MIN_TRACTION) & (mo.moving > 0)
        if not sel.any():
            return "below resolution: no traction while moving"
        top = float(np.max(mo.a_tr0[sel] * mo.v_ref[sel]))
        return resolved("p_spec below the run's largest traction power",
                        top - fit.parameters["p_spec"], fit.std_errors.get("p_spec"),
                        0.05 * top, " W/kg (m^2/s^3)")

    def extend_null(self, null, fit, mo) -> None:
        R = deficit(mo, fit.parameters["p_spec"], null_traction(mo, null))[:, None]
        bv, bs = mo.grid.integrate(R, mo.ev.t.size)
        null.extra.append((bv[:, 0], bs[:, 0]))
        null.p_spec = float(fit.parameters["p_spec"])

    def effect(self, params: dict, duration: float) -> PowerLimitEffect:
        return PowerLimitEffect(float(params["p_spec"]))


def deficit(mo, p_spec: float, a_tr: np.ndarray | None = None) -> np.ndarray:
    """m/s^2 on the grid: the traction the power limit takes away from ``a_tr`` (default: the
    believed traction)."""
    a_tr = mo.a_tr0 if a_tr is None else a_tr
    v = np.maximum(mo.v_ref, 1e-3)
    return -np.maximum(a_tr - p_spec / v, 0.0) * mo.moving


def _grid(mo) -> np.ndarray:
    """Powers from the 5th percentile of the traction powers a_tr v of the run (below it the
    limit would act on nearly every traction) to their maximum (no limit)."""
    sel = (mo.a_tr0 > MIN_TRACTION) & (mo.moving > 0)
    if not sel.any():
        return np.zeros(0)
    pw = mo.a_tr0[sel] * mo.v_ref[sel]
    lo, hi = float(np.percentile(pw, 5)), float(np.max(pw))
    if not hi > lo > 0:
        return np.zeros(0)
    return np.geomspace(lo, hi, GRID)


CAUSE = PowerLimit()
