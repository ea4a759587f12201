"""``gradient``: a section of track whose true gradient differs from the map's.

A section is a sum of position bins: every section [i, j) is scored at once by 2-D prefix sums
(:func:`..stage.best_section`), (s0, permille) by GLS.

Gradient against resistance: on one run position and speed go together, so a long gradient
"section" at cruise speed is running resistance by another name (a line-long section is exactly
the Davis a-term). A section is therefore searched and scored with the Davis terms free as
nuisance: it is named only for what resistance cannot explain (a map error is local).
"""

from __future__ import annotations

import math

import numpy as np
from train_core.effects import GradientEffect
from train_core.model import G

from train_estimation.core.numerics.augmented_kf import LOG2PI, gls

from ..result import CauseFit
from ..stage import Stage, best_section
from .base import Cause, fleet_se, resolved
from .resistance import RESISTANCE_COLS

# per mille, the largest error of a surveyed gradient map that is not a section mapped with the
# wrong profile (a few per mille: a gradient map error of a survey)
MAP_ERROR = 10.0


class Gradient(Cause):
    name = "gradient"
    # the halves of its stretch (:meth:`halves_own`), not the held-out folds': each fold's fit
    # chooses its own stretch, so the two sizes are of two sections (a true 4.8 per mille
    # gradient fitted 2.75 and 6.06 on the folds of a high-speed pair, z -8.8)
    halves = ("permille",)
    half_quantity = ("permille", float)

    def nominal(self, mo) -> dict:
        return {"permille": 0.0}

    def half_columns(self, fit, mo, others, cuts) -> tuple:
        """(Gv, Gs) (n_ev, 2): one permille of gradient on the grid steps moving on [cuts[0],
        cuts[1]) and on [cuts[1], cuts[2]) (as the position bins' columns are built)."""
        g = mo.grid
        xm = 0.5 * (mo.x_ref[1:] + mo.x_ref[:-1])
        col = np.searchsorted(cuts, xm, side="right") - 1
        on = mo.step_moving & (col >= 0) & (col < 2)
        inc = -G / 1000.0 * mo.k_grad * g.dt
        Gv, Gs = np.zeros((mo.ev.t.size, 2)), np.zeros((mo.ev.t.size, 2))
        np.add.at(Gv, (g.k[on], col[on]), inc)
        np.add.at(Gs, (g.k[on], col[on]), inc * g.lever[on])
        return Gv, Gs
    family = "motion"
    linear = True
    located = True
    model_file = "line"

    def free(self, st, extra=None) -> list:
        bi, bj = extra["bins"]
        return [{f"G{b}": 1.0 for b in range(bi, bj)}]

    def params(self, st, th, cov, extra=None) -> tuple:
        sd = np.sqrt(np.clip(np.diag(cov), 0, None))
        bi, bj = extra["bins"]
        mo = st.mo
        start, end = float(mo.bin_edges[bi]), float(mo.bin_edges[bj])
        # the pass's mean square speed over the section: what tells a map error (the same at
        # any speed) from a tunnel's drag (growing as v^2) over several passes (fleet)
        inside = (mo.moving > 0) & (mo.x_ref >= start) & (mo.x_ref < end)
        v2 = float(np.mean(mo.v_ref[inside] ** 2)) if np.any(inside) else math.nan
        return {"start": start, "end": end, "permille": float(th[0])}, {"permille": sd[0]}, \
            dict(extra, v2=v2)

    def fit(self, st) -> tuple:
        """All sections [i, j) of the position bins, scored *against the running-resistance
        model* (Davis a, b, c free as nuisance: Frisch-Waugh on the metric); the permille
        reported (and added to the model) is the plain fit of the chosen section. Returns ll
        such that ll - null_ll() is the gain beyond resistance."""
        mo = st.mo
        idx = np.array([st.j(f"G{b}") for b in range(mo.n_bins)])
        width = mo.bin_edges[1] - mo.bin_edges[0]
        min_len = max(1, int(math.ceil(st.cfg.min_section / width - 1e-9)))
        e1 = np.zeros(st.p + 3)
        e1[1] = 1.0
        W = st.kf.W
        # Frisch-Waugh: partial the resistance columns out of the metric, then scan
        F = np.zeros((st.p + 3, 3))
        for r, name in enumerate(RESISTANCE_COLS):
            F[st.j(name), r] = 1.0
        WF = W @ F
        W_res = W - WF @ np.linalg.pinv(F.T @ WF) @ WF.T
        quad, bi, bj, _, _ = best_section(W_res, st.M({}, [])[:, 0], e1, idx, min_len)
        ll_res = st.fit({}, [{n: 1.0} for n in RESISTANCE_COLS])[2]
        ll_joint = st.loglik_of_quad(quad)
        extra = {"bins": (bi, bj), "bin_width": float(width)}
        th, cov, ll_plain, _ = st.fit({}, self.free(st, extra))
        extra["loglik_gain_plain"] = ll_plain - st.null_ll()
        return (st.null_ll() + (ll_joint - ll_res), 3, *self.params(st, th, cov, extra))

    def dll_at_noise(self, st, st_c, ll0: float) -> float:
        """The gain beyond resistance at the cause's noise (see :meth:`fit`): the null and the
        null with the section, both with the Davis terms free; the null at the better of the
        cause's noise and the stage's (as :meth:`Cause.dll_at_noise`: a null held at a noise
        that is not its own must not make the section look better than it is)."""
        mo = st.mo
        at = Stage(mo, st.null, st.cfg, big=False, noise=(st_c.q, st_c.r_s))
        cols = [mo.col[c] for c in RESISTANCE_COLS]
        lls = []
        for f_v, f_s in ((at.fv, at.fs), (st_c.fv, st_c.fs)):
            kf = at.augmented(f_v, f_s, drift=(mo.Dv[:, cols], mo.Ds[:, cols]))
            quad = gls(kf.W, np.eye(5))[2]
            lls.append(-0.5 * (kf.logdet + kf.m * LOG2PI + quad))
        ll_res = st.fit({}, [{n: 1.0} for n in RESISTANCE_COLS])[2]
        return lls[1] - max(lls[0], ll_res)

    def resolution(self, fit, mo) -> str | None:
        """A map error below 0.5 per mille is within a surveyed map's own precision."""
        return resolved("permille", fit.parameters["permille"],
                        fit.std_errors.get("permille"), 0.5, " per mille")

    def plausible(self, fit, mo) -> str | None:
        """A gradient map error is an error of a surveyed profile: a few per mille, or a
        section mapped with a profile the line has elsewhere (a sign or a change point in the
        wrong place). A change of more than ``MAP_ERROR`` whose corrected gradient is steeper
        than any the line's map holds is no map error: a force of that size on that stretch is
        something else (traction cut on a stretch, drag, a force in time)."""
        p = fit.parameters
        pm = float(p["permille"])
        if abs(pm) <= MAP_ERROR:
            return None
        steepest = max((abs(s.permille) for s in mo.line.gradients), default=0.0)
        xs = np.linspace(p["start"], p["end"], 64)
        corrected = float(np.max(np.abs(mo.line.gradient_permille(xs) + pm)))
        if corrected <= steepest:
            return None
        return (f"not a map error: {pm:+.1f} per mille is more than a map's error ({MAP_ERROR:g}) "
                f"and the corrected gradient ({corrected:.1f} per mille) is steeper than any on "
                f"the line's map ({steepest:.1f})")

    # at one place in one phase only, a map error and a force acting while the train was there
    # (headwind, a traction or braking fault of that moment) make the same residual
    phase_rival = "a force acting during that time"
    # g sin(theta) does not depend on speed; drag in a tunnel grows as v^2
    speed_rival = "aerodynamic drag at that place (a force growing as v^2: a tunnel)"
    time_rival = "a force acting while the train ran it (a headwind, a traction fault)"
    # run downhill in braking only, a map error is braking weaker there to the data (the braking
    # asked for at one level over the stretch: the same force)
    braking_rival = ("a low-adhesion section (braking weaker there in proportion to the braking "
                     "asked for)")

    def braking_rival_fit(self, fit, mo) -> CauseFit | None:
        """The low-adhesion section on the gradient's stretch that weakens the braking asked
        for there by the gradient's force on average (factor 1 - force / braking asked, over
        the braking done on it), or None where no section gives that force: an uphill map
        error (more braking than believed: a low-adhesion section only weakens it), no braking
        asked for on the stretch. Whether the railway could have that section is the
        section's own rule (``AdhesionSection.plausible``: a brake asking for less than any
        rail's adhesion gives is never weakened by it)."""
        inside, force = self.beyond(fit, mo)
        asked = np.maximum(-mo.f0 * mo.a_br0, 0.0) * mo.moving
        on = inside & (asked > 0)
        if not on.any() or not float(np.mean(force[on])) > 0.0:
            return None
        p = fit.parameters
        factor = 1.0 - float(np.mean(force[on])) / float(np.mean(asked[on]))
        return CauseFit("adhesion_section", 0.0,
                        {"start": float(p["start"]), "end": float(p["end"]), "factor": factor})

    def beyond(self, fit, mo):
        """The section's gradient force at every place run while moving."""
        p = fit.parameters
        mov = mo.moving > 0
        inside = mov & (mo.x_ref >= p["start"]) & (mo.x_ref < p["end"])
        return inside, np.where(mov, -G / 1000.0 * mo.k_grad * p["permille"], 0.0)

    def extend_null(self, null, fit, mo) -> None:
        i, j = fit.extra["bins"]
        null.gradient = (i, j, fit.parameters["permille"])

    def effect(self, params: dict, duration: float) -> GradientEffect:
        return GradientEffect(params["start"], params["end"], params["permille"])

    def model_effect(self, fit, ctx):
        """The section clipped to the line (the model directory's line.yaml holds it)."""
        p = fit.parameters
        start, end = max(0.0, float(p["start"])), min(ctx.line_length, float(p["end"]))
        if end <= start:
            return None, (f"gradient not in the model (section [{p['start']:.0f}, "
                          f"{p['end']:.0f}) m is outside the line)")
        return GradientEffect(start, end, float(p["permille"])), (
            f"gradient: {p['permille']:+.2f} per mille added on [{start:.0f}, {end:.0f}) m")

    def series(self, params: dict, mo, out: dict) -> None:
        out["gradient_section"] = (params["start"], params["end"], params["permille"])

    def fleet_row(self, fit, evidence, accepted, train) -> dict:
        """An accepted section: where, how steep, its standard error and score (the fleet's
        map-error test)."""
        if not accepted:
            return {}
        p = fit.parameters
        return {"gradient_start": p["start"], "gradient_end": p["end"],
                "gradient_permille": p["permille"], "gradient_se": fleet_se(evidence, "permille"),
                "gradient_score": fit.score, "gradient_v2": fit.extra.get("v2", math.nan)}


CAUSE = Gradient()
