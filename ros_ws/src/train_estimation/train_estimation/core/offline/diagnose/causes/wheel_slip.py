"""``wheel_slip``: episodes in which the odometer's axle turns faster (slip) or slower (slide)
than the train moves; the counted distance keeps the excess afterwards.

Candidate episodes are where the null's standardised speed innovation is large; each is fitted
as an interval [t0, t1) with its own slip fraction, the boundaries profiled at the decimated
odometer rate (per-sample measurement columns, contiguous sums); then neighbours that are one
episode are merged and episodes that do not pay for themselves in the joint fit are dropped
(:func:`refine_episodes`). Each episode's depth is reported: 1 - odometer speed / train speed
(> 0: the odometer misses speed, a slide; < 0: it reads too much, a slip)."""

from __future__ import annotations

import math

import numpy as np
from train_core.effects import WheelSlipEffect

from train_estimation.core.numerics.augmented_kf import gls
from train_estimation.core.offline.identify import moving_average

from ..motion import slip_cols
from ..stage import best_section
from .base import Cause, resolved

# s: neighbouring episodes closer than this are tested as one (refine_episodes)
MERGE_GAP = 10.0


class WheelSlip(Cause):
    name = "wheel_slip"
    family = "odometer"

    def fit(self, st) -> tuple:
        cands = _candidates(st)
        null_ll = st.null_ll()
        if not cands:
            return null_ll, 3, {"intervals": []}, {}, {"candidates": 0}
        cols, Md, Mv = _sample_columns(st, cands)
        kf = st.augmented(st.fv, st.fs, meas=(Md, Mv))
        nc = len(cols)
        u = np.zeros(nc + 2)
        u[0] = 1.0
        e1 = np.zeros(nc + 2)
        e1[1] = 1.0
        base_quad = gls(kf.W, np.stack([u, e1], axis=1))[2]
        pen = 3 * math.log(st.n_meas)
        t = st.mo.ev.t[st.mo.ev.odo]
        # each candidate's best interval alone ...
        best_iv = []
        for c in range(len(cands)):
            idx = np.array([2 + j for j, (cc, _) in enumerate(cols) if cc == c])
            if idx.size == 0:
                continue
            quad, a, b, eps, se = best_section(kf.W, u, e1, idx, 1)
            if 2 * 0.5 * (base_quad - quad) - pen > 0:
                col = np.zeros(nc + 2)
                col[idx[a:b]] = 1.0
                i0 = cols[idx[a] - 2][1]
                i1 = cols[idx[b - 1] - 2][1] + 1
                best_iv.append((float(t[i0]), float(t[i1]), col))
        chosen, _ = _forward_selection(kf.W, u, e1, best_iv, base_quad, pen)
        if not chosen:
            return null_ll, 3, {"intervals": []}, {}, {"candidates": len(cands)}
        ivs, eps, se, quad_now = refine_episodes(st, [(c[0], c[1]) for c in chosen], pen)
        return null_ll + 0.5 * (base_quad - quad_now), 3 * len(ivs), \
            {"intervals": [list(iv) for iv in ivs], "depths": [-e for e in eps]}, \
            {"slip_fraction": se, "depths": se}, \
            {"slip_fraction": eps, "candidates": len(cands), "found": len(chosen)}

    def resolution(self, fit, mo) -> str | None:
        """An episode is resolved when its slip fraction is more than 0.01 and 3 SE from 0
        and it lasts at least one odometer period."""
        t = mo.ev.t[mo.ev.odo]
        period = float(np.median(np.diff(t))) if t.size > 1 else 0.0
        eps = fit.extra.get("slip_fraction", [])
        se = fit.std_errors.get("slip_fraction", [None] * len(eps))
        why = "below resolution: no episode"
        for (t0, t1), e, s in zip(fit.parameters.get("intervals", []), eps, se):
            r = resolved(f"slip fraction on [{t0:.1f}, {t1:.1f}] s", e, s, 0.01)
            if r is None and t1 - t0 >= period:
                return None
            why = r or f"below resolution: episode shorter than one odometer period ({period:g} s)"
        return why

    def extend_null(self, null, fit, mo) -> None:
        for (t0, t1), eps in zip(fit.parameters["intervals"],
                                 fit.extra.get("slip_fraction", [])):
            null.slip.append((t0, t1, eps))

    def report(self, params: dict, beta: float) -> dict:
        params["intervals"] = [[a / beta, b / beta] for a, b in params.get("intervals", [])]
        return params

    def effect(self, params: dict, duration: float) -> WheelSlipEffect:
        fr = [-x for x in params.get("depths", []) if x is not None]
        return WheelSlipEffect(tuple(tuple(iv) for iv in params.get("intervals", [])),
                               float(np.mean(fr)) if fr else 0.0)

    def model_effect(self, fit, ctx):
        """One slip fraction for all episodes (as the simulator's effect has), times on true
        time from the start of the run."""
        k = 1.0 + ctx.drift
        ivs = [[round(float(t0) / k, 3), round(float(t1) / k, 3)]
               for t0, t1 in fit.parameters.get("intervals", []) if t1 > t0 >= 0.0]
        if not ivs:
            return None, None
        frac = float(np.clip(slip_fraction(fit, ctx), -0.9, 1.0))
        return WheelSlipEffect(tuple(tuple(iv) for iv in ivs), round(frac, 5)), None

    def gain(self, fit, ctx) -> dict:
        """Odometer speed minus the model's smoothed speed inside the episodes, raw against
        corrected by the fitted slip (the episodes are local: nothing to hold out)."""
        run = ctx.mo.run
        ivs = fit.parameters.get("intervals", [])
        if not ivs:
            return {"metric": "odometer speed error in the slip episodes (m/s)", "before": None,
                    "after": None}
        inside = np.zeros(run.odo_t.size, bool)
        corr = np.ones(run.odo_t.size)
        for (t0, t1) in ivs:
            inside |= (run.odo_t >= t0) & (run.odo_t < t1)
        w = max(1, int(round(3.0 / max(np.median(np.diff(run.odo_t)), 1e-3))))
        ref = moving_average(run.odo_v, w)
        # the reference outside the episodes: interpolate across them
        ref_i = np.interp(run.odo_t, run.odo_t[~inside], ref[~inside]) if (~inside).any() \
            else ref
        eps = float(np.mean(run.odo_v[inside] / np.maximum(ref_i[inside], 0.1) - 1.0))
        corr[inside] = 1.0 + eps
        before = float(np.sqrt(np.mean((run.odo_v[inside] - ref_i[inside]) ** 2)))
        after = float(np.sqrt(np.mean((run.odo_v[inside] / corr[inside] - ref_i[inside]) ** 2)))
        return {"metric": "odometer speed error in the slip episodes (m/s), raw vs corrected "
                          "by the fitted slip (local: not held out)", "before": before,
                "after": after}

    def series(self, params: dict, mo, out: dict) -> None:
        out["slip_intervals"] = params["intervals"]


def _candidates(st) -> list:
    """[t0, t1] of the candidate episodes, strongest first (at most max_slip_candidates)."""
    cfg, ev = st.cfg, st.mo.ev
    o = ev.odo
    s0_hat = st.fit({}, [])[3]
    nu = (st.kf.E0[o, 0] + s0_hat * st.kf.E1[o, 0]) / np.sqrt(st.kf.S_v[o])
    t = ev.t[o]
    cands = []
    for k in np.flatnonzero(np.abs(nu) > cfg.slip_threshold):
        if cands and t[k] - cands[-1][1] < 3.0:
            cands[-1][1] = t[k]
        else:
            cands.append([t[k], t[k]])
    cands = sorted(cands, key=lambda c: -np.max(np.abs(nu[(t >= c[0]) & (t <= c[1])])))
    return cands[:cfg.max_slip_candidates]


def _sample_columns(st, cands: list):
    """Per-sample slip columns of every candidate window: ([(candidate, odometer event i)],
    Md, Mv) with column j the slip of bin [t_i, t_i+1) at unit fraction."""
    mo, ev = st.mo, st.mo.ev
    o = ev.odo
    t = ev.t[o]
    g = mo.grid
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (mo.v_ref[1:] + mo.v_ref[:-1]) * g.dt)])
    cols = []
    for c, (c0, c1) in enumerate(cands):
        for i in np.flatnonzero((t >= c0 - 2.0) & (t <= c1 + 3.0))[:-1]:
            if i + 1 < t.size:
                cols.append((c, int(i)))
    n, nc = ev.t.size, len(cols)
    Md = np.zeros((n, nc))
    Mv = np.zeros((n, nc))
    for j, (_, i) in enumerate(cols):
        Mv[o[i], j] = np.interp(t[i], g.t, mo.v_ref)
        Md[o[i + 1:], j] = np.interp(t[i + 1], g.t, cum) - np.interp(t[i], g.t, cum)
    return cols, Md, Mv


def _forward_selection(W, u, e1, best_iv: list, base_quad: float, pen: float):
    """Episodes added one at a time by the joint fit: every episode's distance excess persists,
    so episodes compete for the same evidence and their gains must not be added up."""
    chosen, quad_now = [], base_quad
    while best_iv:
        trials = []
        for m, (_a, _b, col) in enumerate(best_iv):
            M = np.stack([u, e1] + [c[2] for c in chosen] + [col], axis=1)
            trials.append((gls(W, M)[2], m))
        q_new, m = min(trials)
        if (quad_now - q_new) - pen <= 0:
            break
        chosen.append(best_iv.pop(m))
        quad_now = q_new
    return chosen, quad_now


def refine_episodes(st, intervals: list, pen: float) -> tuple:
    """One episode where the data say one, and only episodes that pay for themselves.

    A long episode shows in the null's speed innovations at its onset and its end (in between
    the filter, its noise inflated by the episode, follows the odometer), so the search can
    return it as two or more pieces. Here, on the joint fit of all episodes (one filter run per
    round over each episode's columns and each merge of neighbours closer than ``MERGE_GAP``),
    the merge that costs least is made while it costs less than an episode's BIC penalty
    ``pen`` (3 ln n: a merged pair has 3 parameters fewer), then the episode whose removal
    costs least is dropped while that costs less than ``pen``. Returns (intervals, slip
    fractions, their standard errors, quadratic form of the final joint fit)."""
    ivs = sorted((float(a), float(b)) for a, b in intervals)
    for _ in range(2 * len(ivs) + 1):
        pairs = [i for i in range(len(ivs) - 1) if ivs[i + 1][0] - ivs[i][1] < MERGE_GAP]
        W, cols = _episode_filter(st, ivs + [(ivs[i][0], ivs[i + 1][1]) for i in pairs])
        n = len(ivs)
        q_all = _quad(W, cols, range(n))
        merges = [(_quad(W, cols, [j for j in range(n) if j not in (i, i + 1)] + [n + m]), i)
                  for m, i in enumerate(pairs)]
        if merges and min(merges)[0] - q_all < pen:
            i = min(merges)[1]
            ivs[i:i + 2] = [(ivs[i][0], ivs[i + 1][1])]
            continue
        drops = [(_quad(W, cols, [j for j in range(n) if j != i]), i)
                 for i in range(n)] if n > 1 else []
        if drops and min(drops)[0] - q_all < pen:
            del ivs[min(drops)[1]]
            continue
        th, cov, q = gls(W, cols[:, :2 + n])
        se = np.sqrt(np.clip(np.diag(cov)[1:], 0, None))
        return ivs, th[1:].tolist(), se.tolist(), float(q)
    raise RuntimeError("episode refinement did not settle")  # pragma: no cover - bounded


def _quad(W, cols, sel) -> float:
    """Quadratic form of the joint fit of the episodes ``sel`` (indices of the columns)."""
    return gls(W, cols[:, [0, 1] + [2 + j for j in sel]])[2]


def _episode_filter(st, ivs: list) -> tuple:
    """The augmented filter over [null, s0, one measurement column per interval (unit slip
    fraction)]: (W, identity selector over its columns)."""
    n_ev = st.mo.ev.t.size
    Md = np.zeros((n_ev, len(ivs)))
    Mv = np.zeros((n_ev, len(ivs)))
    for j, iv in enumerate(ivs):
        Md[:, j], Mv[:, j] = slip_cols(st.mo, [iv])
    kf = st.augmented(st.fv, st.fs, meas=(Md, Mv), update=st.update)
    return kf.W, np.eye(len(ivs) + 2)


def slip_fraction(fit, ctx) -> float:
    """The slip fraction of an accepted wheel_slip for a model (one value for all episodes):
    the mean of the fitted per-episode fractions the diagnosis reports, else measured from the
    odometer speed inside the episodes against the speed just around them."""
    ev = (ctx.evidence or {}).get("wheel_slip", {})
    for src in (ev.get("details", {}) if isinstance(ev, dict) else {}, ev):
        v = src.get("slip_fraction") if isinstance(src, dict) else None
        if v is not None and not isinstance(v, dict):
            vals = [float(x) for x in np.atleast_1d(v) if x is not None and math.isfinite(x)]
            if vals and all(abs(x) < 1.0 for x in vals):
                return float(np.mean(vals))
    t = np.asarray(ctx.odo_stamp, float) - ctx.t_first
    v = np.asarray(ctx.odo_speed, float)
    order = np.argsort(t)
    t, v = t[order], v[order]
    ratios = []
    for t0, t1 in fit.parameters.get("intervals", []):
        inside = (t >= t0) & (t < t1)
        around = ((t >= t0 - 3.0) & (t < t0)) | ((t >= t1) & (t < t1 + 3.0))
        if inside.any() and around.sum() >= 2:
            ref = np.interp(t[inside], t[around], v[around])
            ok = ref > 1.0
            if ok.any():
                ratios.append(float(np.mean(v[inside][ok] / ref[ok] - 1.0)))
    return float(np.mean(ratios)) if ratios else 0.0


CAUSE = WheelSlip()
