"""``resistance``: the running resistance (Davis a + b v + c v^2) differs from train.yaml's."""

from __future__ import annotations

import numpy as np
from train_core.effects import ResistanceEffect

from train_estimation.core.numerics.augmented_kf import gls
from train_estimation.core.numerics.special import chdtri

from ..phases import MIN_CELL_TIME, grid_phase
from ..stage import Stage
from .base import Cause, fleet_se, resolved

RESISTANCE_COLS = ("one", "v", "v2")  # the Davis terms' elementary columns (a, b, c)
# 2 ln LR of the free Davis fit against the best with a, b, c >= 0 beyond which the data need
# a resistance no Davis curve gives: chi-square(3) at 1e-3 (the statistic of a bound on three
# parameters is a chi-bar-square, below chi-square(3) in its tail)
NONNEG_LR = 16.27
# a resistance free in speed: this many bands of equal width from standstill to the top speed
# (bands with less than MIN_CELL_TIME s of motion are left out), tested against the Davis curve
# at this level (the same as the bound above)
SPEED_BANDS = 8
CURVE_ALPHA = 1e-3


class Resistance(Cause):
    name = "resistance"
    halves = ("force_at_v_ref",)

    def nominal(self, mo) -> dict:
        """The believed force at the run's typical speed (as :meth:`params` takes it)."""
        vr = float(np.sqrt(np.mean(mo.v_ref[mo.moving > 0] ** 2))) if mo.moving.any() \
            else 0.0
        return {"force_at_v_ref": float(mo.train.davis.force(vr))}
    family = "motion"
    linear = True
    model_file = "train"

    def free(self, st, extra=None) -> list:
        return [{n: 1.0} for n in RESISTANCE_COLS]

    def params(self, st, th, cov, extra=None) -> tuple:
        mo = st.mo
        sd = np.sqrt(np.clip(np.diag(cov), 0, None))
        meff = mo.train.effective_mass
        d = st.null.drift
        null_res = np.array([d.get("one", 0.0), d.get("v", 0.0), d.get("v2", 0.0)])
        val = (np.array([mo.alpha0, mo.beta0, mo.gamma0]) + null_res + th) * meff
        se = sd * meff
        # a, b and c are strongly correlated over one run's speeds; the resistance force
        # at the run's typical speed is what the data determine well (reported too)
        vr = float(np.sqrt(np.mean(mo.v_ref[mo.moving > 0] ** 2))) if mo.moving.any() \
            else 0.0
        gv = np.array([1.0, vr, vr * vr])
        se_force = float(np.sqrt(max(gv @ cov @ gv, 0.0))) * meff
        # the reported curve holds what the null already had in the Davis columns (a mass
        # change scales the believed resistance: its part is there); extend_null adds only
        # the cause's own part, so it is kept with the fit
        return {"a": val[0], "b": val[1], "c": val[2]}, \
            {"a": se[0], "b": se[1], "c": se[2], "force_at_v_ref": se_force}, \
            {"v_ref": vr, "force_at_v_ref": float(gv @ val), "null_davis": null_res.tolist()}

    def fit(self, st) -> tuple:
        return self.fit_linear(st)

    def resolution(self, fit, mo) -> str | None:
        """The resistance force at the run's typical speed (what one run determines well):
        more than 3 % of the believed force there."""
        v = fit.extra.get("v_ref", 0.0)
        f0 = float(mo.train.davis.force(v))
        df = fit.extra.get("force_at_v_ref", f0) - f0
        return resolved(f"resistance force at {v:.1f} m/s", df,
                        fit.std_errors.get("force_at_v_ref"), 0.03 * abs(f0), " N")

    def plausible_data(self, mo, others, fit, cfg, noise) -> str | None:
        """Every Davis term is a resistance (rolling, flange and bearing, air): a, b, c >= 0.
        A resistance that steps or bends with speed (bogies hunting above a critical speed,
        an aerodynamic effect at some speeds) is fitted by a Davis curve with a negative term,
        which no train has. The best fit with a, b, c >= 0 (each subset of them held at its
        bound, the rest free on the model ``others``) against the free one: 2 ln LR above
        ``NONNEG_LR`` says the data need such a curve, and the resistance is not confirmed.
        At or below it the data do not need the negative term, and that best curve becomes
        the fit (``fit.parameters``, in place): the physically right one, which the later
        checks test. Below about 15 m/s the three terms are nearly collinear, and a free fit
        can take a shape no train has (a tram's resistance x 0.62: a -251 N, b 217 N/(m/s),
        c -11.4 N/(m/s)^2 for a true 387, 16, 1.2) that the split test then contradicts."""
        why = self._not_a_curve(mo, others, fit, cfg, noise)
        if why is not None:
            return why
        st = Stage(mo, others, cfg, noise=noise)
        d = others.drift
        # the bound on each column's coefficient: believed plus the others' part plus it >= 0
        base = np.array([mo.alpha0 + d.get("one", 0.0), mo.beta0 + d.get("v", 0.0),
                         mo.gamma0 + d.get("v2", 0.0)])
        lb = -base
        free = self.free(st)
        th, _, ll_free, _ = st.fit({}, free)
        if np.all(th >= lb - 1e-12 * np.abs(lb)):
            return None
        best, coef = -np.inf, None
        for mask in range(1, 8):  # the subsets held at their bound
            held = [k for k in range(3) if mask >> k & 1]
            rest = [k for k in range(3) if k not in held]
            t, _, ll, _ = st.fit({RESISTANCE_COLS[k]: lb[k] for k in held},
                                 [free[k] for k in rest])
            if all(t[i] >= lb[k] - 1e-12 * abs(lb[k]) for i, k in enumerate(rest)) \
                    and ll > best:
                best, coef = ll, lb.copy()
                coef[rest] = t
        lr = 2.0 * (ll_free - best)
        fit.extra["nonnegative_lr"] = float(lr)
        meff = mo.train.effective_mass
        if lr <= NONNEG_LR:
            val = (base + coef) * meff
            fit.extra["free_fit"] = dict(fit.parameters)
            fit.extra["null_davis"] = [float(x) for x in base - np.array(
                [mo.alpha0, mo.beta0, mo.gamma0])]
            fit.parameters = {"a": float(val[0]), "b": float(val[1]), "c": float(val[2])}
            vr = fit.extra.get("v_ref", 0.0)
            fit.extra["force_at_v_ref"] = float(val @ np.array([1.0, vr, vr * vr]))
            return None
        tot = (base + th) * meff
        neg = ", ".join(f"{n} {v:.3g}" for n, v in zip("abc", tot) if v < 0)
        return (f"not a running resistance: the data need a Davis curve with a negative term "
                f"({neg}; 2 ln LR {lr:.1f} > {NONNEG_LR:g} against the best with a, b, c >= 0): "
                f"a resistance that steps or bends with speed is something else")

    def _not_a_curve(self, mo, others, fit, cfg, noise) -> str | None:
        """A running resistance is smooth in speed: a + b v + c v^2. Against it, a resistance
        free in speed: the Davis terms plus a free extra force in each of ``SPEED_BANDS`` bands
        of equal width (all phases; one band is the reference), both on the model ``others``.
        The two are nested and linear, so 2 ln LR is chi-square with one degree of freedom
        per extra band when the Davis curve is right; beyond its ``CURVE_ALPHA`` quantile the
        data need a resistance that steps or bends with speed (bogies that hunt above a
        critical speed: 2 ln LR 27.8-93.4 on eight runs, where the bench's 17 resistance
        changes give 1.1-16.6), and the resistance is not confirmed. Equal widths, not
        quantiles: a run spends most of its time at one cruising speed, and quantile bands
        crowd there."""
        g, v = mo.grid, mo.v_ref
        mov = grid_phase(mo) >= 0
        if not mov.any():
            return None
        edges = np.linspace(0.0, float(v[mov].max()) * (1 + 1e-9), SPEED_BANDS + 1)
        R = np.stack([(mov & (v >= a) & (v < b)).astype(float)
                      for a, b in zip(edges[:-1], edges[1:])], axis=1)
        R = R[:, R.sum(axis=0) * g.dt >= MIN_CELL_TIME]
        k = R.shape[1] - 1
        if k < 1:
            return None
        Bv, Bs = g.integrate(R[:, 1:], mo.ev.t.size)
        js = [mo.col[n] for n in RESISTANCE_COLS]
        Dv, Ds = mo.Dv[:, js], mo.Ds[:, js]
        st = Stage(mo, others, cfg, noise=noise, big=False)
        # one filter run over [fixed, s0, Davis a, b, c, bands ...]: the Davis curve is its
        # first five columns, the free resistance all of them
        W = st.augmented(st.fv, st.fs, drift=(np.hstack([Dv, Bv]), np.hstack([Ds, Bs]))).W
        lr = max(gls(W[:5, :5])[2] - gls(W)[2], 0.0)
        bar = float(chdtri(k, CURVE_ALPHA))
        fit.extra["free_in_speed_lr"] = float(lr)
        if lr <= bar:
            return None
        return (f"not a running resistance: a force free in {k + 1} speed bands fits better "
                f"than any Davis curve (2 ln LR {lr:.1f} > {bar:.1f}, chi-square({k}) at "
                f"{CURVE_ALPHA:g}): a resistance that steps or bends with speed is something "
                "else")

    def extend_null(self, null, fit, mo) -> None:
        """Add the cause's own part of the Davis terms: the reported curve less the believed
        one and less what the null it was fitted against had in those columns (a mass
        change's scaling of the believed resistance, ``extra["null_davis"]``), which the
        null extended holds already. Adding the whole reported curve counted that part twice:
        a resistance fitted on a fold beside a mass change then predicted the held-out blocks
        with the mass change's share of the resistance once more."""
        p = fit.parameters
        meff = mo.train.effective_mass
        had = (fit.extra or {}).get("null_davis") or (0.0, 0.0, 0.0)
        for name, val, base, h in (("one", p["a"], mo.alpha0, had[0]),
                                   ("v", p["b"], mo.beta0, had[1]),
                                   ("v2", p["c"], mo.gamma0, had[2])):
            null.drift[name] = null.drift.get(name, 0.0) + val / meff - base - h

    def effect(self, params: dict, duration: float) -> ResistanceEffect:
        return ResistanceEffect(params["a"], params["b"], params["c"])

    def model_effect(self, fit, ctx):
        """The fitted Davis terms, projected onto a, b, c >= 0 if one is negative."""
        p = fit.parameters
        abc, projected = davis_nonnegative((p["a"], p["b"], p["c"]), ctx.odo_speed)
        return ResistanceEffect(*abc), "resistance: fitted Davis a, b, c in train.yaml" + (
            " (a negative coefficient was projected onto a, b, c >= 0 over the run's speeds)"
            if projected else "")

    def fleet_row(self, fit, evidence, accepted, train) -> dict:
        """The fitted minus the believed resistance force at the run's typical speed (the
        quantity one run determines well: a, b, c alone are nearly collinear) and its standard
        error (the fleet's per-line resistance consensus)."""
        se = fleet_se(evidence, "force_at_v_ref")
        vr = (evidence.get("details") or {}).get("v_ref")
        if not se or vr is None:
            return {}
        p, d = fit.parameters, train.davis
        return {"resistance_v_ref": vr,
                "resistance_dforce": (p["a"] + p["b"] * vr + p["c"] * vr * vr
                                      - (d.a + d.b * vr + d.c * vr * vr)),
                "resistance_dforce_se": se}


def davis_nonnegative(abc, speeds) -> tuple[list[float], bool]:
    """Davis (a, b, c) with every coefficient >= 0, as train.yaml requires. A fit with a negative
    coefficient is replaced by the non-negative a + b v + c v^2 closest to its curve (least
    squares) over the speeds of the run (m/s), so the resistance the data showed is kept."""
    abc = [float(x) for x in abc]
    if min(abc) >= 0.0:
        return abc, False
    from scipy.optimize import nnls

    speeds = np.asarray(speeds, float)
    v_max = float(np.nanmax(speeds)) if speeds.size and np.isfinite(speeds).any() else 20.0
    v = np.linspace(0.0, max(v_max, 1.0), 200)
    A = np.stack([np.ones_like(v), v, v * v], axis=1)
    target = A @ np.array(abc)
    # scale the columns so the three coefficients are equally well conditioned
    sc = np.abs(A).max(axis=0)
    x, _ = nnls(A / sc, target)
    return [float(u) for u in x / sc], True


CAUSE = Resistance()
