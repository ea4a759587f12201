"""The generic stage: the null (believed model + accepted causes), its noise, the augmented
filter over every elementary column, and fitting any set of columns against it.

Exact likelihood for all causes from one filter run: the Kalman gains do not depend on the
drift or measurement columns, so one *augmented* Kalman filter run (de Jong 1991; the
``identify`` GLS) carrying every elementary column gives the matrix W = sum_k E_k^T S_k^-1 E_k
over [data, columns], and the exact log-likelihood of any hypothesis z = [1, theta] is
-0.5 (sum log det S_k + m log 2 pi + z^T W z). A hypothesis that is a linear combination of
elementary columns is then a small quadratic problem (:meth:`Stage.fit`); nonlinear parameters
are profiled over grids (the causes do that).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from train_estimation.core.numerics.augmented_kf import (
    LOG2PI,
    augmented_kf_blocks,
    digest,
    gls,
    kf2_loglik,
)
from train_estimation.core.numerics.brent import minimize_bounded

from .motion import Motion, slip_cols
from .run import DiagConfig


@dataclass
class Null:
    """What the current null adds to the believed model (accepted causes, nuisance shift)."""

    drift: dict = field(default_factory=dict)  # elementary drift column name -> coefficient
    scale: float = 0.0  # odometer (scale - 1)
    slip: list = field(default_factory=list)  # [(t0, t1, eps[, shape])]
    shift: float = 0.0  # s, command-time offset
    brake_extra: float = 0.0  # s, extra braking delay
    gradient: tuple | None = None  # (bin i, bin j, permille)
    # drift increments (Bv, Bs), each (n_ev,), of accepted causes whose columns are not
    # elementary (a power limit, a low-adhesion section, a traction delay)
    extra: list = field(default_factory=list)
    # the delivered traction's chain as far as the accepted causes change it: the traction
    # commands' re-timing (s, set by a traction delay) and the power limit (W/kg, set by
    # power_limit); a cause acting on the delivered traction composes with the other
    # (the limit caps the re-timed traction, the re-timing moves the capped one)
    traction_timing: float | None = None
    p_spec: float | None = None
    # the delivered drive's gain from an accepted mass change (believed / true mass): the truth
    # is that gain times the whole delivered drive, so the increments in ``extra`` (all of the
    # drive: a power limit, a traction delay, a low-adhesion section) are scaled by it
    drive_gain: float = 1.0
    # low-adhesion sections, (start m, end m, factor): the braking the null delivers on each
    # stretch is ``factor`` times the braking delayed by the brake delay's extra (brake_extra;
    # adhesion_section.null_braking), as in the train (train_core dynamics.py scales the
    # actuator's braking output, delay and lag included), whichever of the section and a brake
    # delay was accepted first: a section built on the braking at another timing leaves the
    # delay's re-timing unscaled on its stretch (a brake delay beside a section of x 0.52 was
    # fitted 1.04 s for 1.21 s and its split then needed it x 0.39 over the braking that held
    # the section)
    brake_sections: list = field(default_factory=list)
    # odometer measurement offsets (distance, speed), each (n_ev,), of structure found in the
    # residuals that no listed cause explains (an odometer that counts differently from a
    # time on: phases.odometer_family), put into the model to test what else is still needed
    meas: list = field(default_factory=list)


class Stage:
    """One greedy stage: the null, its noise (fitted unless given) and, with ``big``, the
    augmented filter over [fixed, s0, every elementary drift column, scale] (``kf``)."""

    def __init__(self, mo: Motion, null: Null, cfg: DiagConfig, noise=None, update=None,
                 big=True, fit_on=None):
        self.mo, self.null, self.cfg = mo, null, cfg
        # fixed part of drift and measurement (column 0)
        fv, fs = mo.base_v.copy(), mo.base_s.copy()
        for name, c in self._null_drift().items():
            j = mo.col[name]
            fv += c * mo.Dv[:, j]
            fs += c * mo.Ds[:, j]
        for bv, bs in null.extra:
            fv = fv + null.drive_gain * bv
            fs = fs + null.drive_gain * bs
        if null.brake_sections:
            from .causes.adhesion_section import section_increments  # causes import stage

            bv, bs = section_increments(mo, null)
            fv = fv + null.drive_gain * bv
            fs = fs + null.drive_gain * bs
        md = null.scale * mo.sc_d
        mv = null.scale * mo.sc_v
        for t0, t1, eps, *shape in null.slip:
            a, b = slip_cols(mo, [(t0, t1, *shape)])
            md = md + eps * a
            mv = mv + eps * b
        for d, m in null.meas:
            md, mv = md + d, mv + m
        self.fv, self.fs, self.md, self.mv = fv, fs, md, mv
        # fixed balise offsets (m, at balise events): readings the structure test found off
        self.mb = np.zeros(mo.ev.t.size)
        # the balise readings' variances times this: a reader (or a map) that scatters more
        # than it states, as the structure test found it (balise_rounds.scatter_round)
        self.bal_scale = 1.0
        self.update = update  # events whose measurement the filter uses (None: all)
        # events whose innovations the fits take (None: all updated): one fold of the data for
        # the held-out check, on a filter that still uses every reading (augmented_kf's ``use``)
        self.fit_on = fit_on
        # The search meets the same null more than once (the next stage's null is the last
        # refit's extended null; a stage rebuilt at the same noise): its noise fit and big
        # filter, deterministic functions of these inputs, are computed once per run.
        memo = _memo(mo)
        key = digest(repr(cfg), fv, fs, md, mv)
        if noise is None:
            if ("noise", key) not in memo:
                memo["noise", key] = self._fit_noise()
            noise = memo["noise", key]
        self.q, self.r_s = noise
        if not big:
            return
        # the big run: [fixed, s0, elementary drift columns..., scale]
        self.p = mo.Dv.shape[1]
        kkey = ("big", key, digest(self.q, self.r_s, update, fit_on))
        if kkey not in memo:
            memo[kkey] = self.augmented(fv, fs, drift=(mo.Dv, mo.Ds),
                                        meas=(mo.sc_d[:, None], mo.sc_v[:, None]),
                                        keep_innov=True, update=update)
        self.kf = memo[kkey]
        self.n_meas = self.kf.m

    def augmented(self, fv: np.ndarray, fs: np.ndarray, drift=None, meas=None, bal=None,
                  **kw):
        """One augmented filter at this stage's noise over the columns [fixed part (drift fv,
        fs; the null's measurement part), s0, drift columns ``drift = (Dv, Ds)``...,
        measurement columns ``meas = (Md, Mv)``..., balise measurement columns ``bal``...]
        (each pair (n_ev, k), ``bal`` (n_ev, k), or None); the innovations of :attr:`fit_on`
        only, unless ``use`` is given."""
        kw.setdefault("use", self.fit_on)
        return augmented_kf_blocks(self.events(), self.q, self.r_s,
                                   (fv, fs, self.md, self.mv, self.mb), drift=drift, meas=meas,
                                   bal=bal, q_held=self.cfg.standstill_q, **kw)

    def events(self):
        """The run's events with the balise readings' variances times :attr:`bal_scale`."""
        ev = self.mo.ev
        if self.bal_scale == 1.0:
            return ev
        r = ev.r_v.copy()
        r[ev.bal] *= self.bal_scale
        return dataclasses.replace(ev, r_v=r)

    def _null_drift(self) -> dict:
        null, mo = self.null, self.mo
        d = dict(null.drift)
        if null.shift != 0.0:
            name = f"T{null.shift:+.3f}"
            d[name] = d.get(name, 0.0) + 1.0
        key = round(null.shift + null.brake_extra, 6)
        if key != 0.0:
            name = mo.braking_cols[key]
            d[name] = d.get(name, 0.0) + 1.0
        if null.gradient is not None:
            i, j, pm = null.gradient
            for b in range(i, j):
                d[f"G{b}"] = d.get(f"G{b}", 0.0) + pm
        return d

    def loglik_at(self, q: float, r_s: float) -> float:
        """Log-likelihood of this stage's null at noise (q, r_s), s0 profiled."""
        return kf2_loglik(self.mo.ev, q, r_s, self.fv, self.fs, self.md, self.mv,
                          self.cfg.standstill_q)

    def _fit_noise(self):
        """Process-noise PSD q and distance-noise variance r_s by maximum likelihood under this
        stage's null (s0 profiled): coordinate-wise bounded Brent searches on their logs, q
        first (it matters most), then r_s, then q again (the two trade off against each other:
        too small a distance noise makes q absorb it)."""
        cfg = self.cfg

        def ll(lq, lr):
            return self.loglik_at(math.exp(lq), math.exp(lr))

        lr = math.log(max(float(np.median(self.mo.run.odo_rv)), 1e-4))
        q_lo, q_hi, r_lo, r_hi = (math.log(cfg.q_floor), math.log(1.0), math.log(1e-6),
                                  math.log(25))
        opts = {"xatol": 0.1, "maxiter": 14}
        lq = minimize_bounded(lambda x: -ll(x, lr), q_lo, q_hi, **opts)[0]
        lr = minimize_bounded(lambda x: -ll(lq, x), r_lo, r_hi, **opts)[0]
        lq = minimize_bounded(lambda x: -ll(x, lr), q_lo, q_hi, **opts)[0]
        return float(math.exp(lq)), float(math.exp(lr))

    def fixed_loglik(self) -> float:
        """Log-likelihood of this stage's null at its noise, s0 profiled (scalar filter)."""
        return self.loglik_at(self.q, self.r_s)

    def M(self, fixed: dict, free: list) -> np.ndarray:
        """[1, theta] -> full z over [fixed, s0, elementary..., scale]. ``fixed``: column name
        -> coefficient added to z[0]'s combination; ``free``: list of {column name: weight}
        (s0 is always free, first)."""
        p = self.p
        M = np.zeros((p + 3, 2 + len(free)))
        M[0, 0] = 1.0
        for name, c in fixed.items():
            M[self.j(name), 0] += c
        M[1, 1] = 1.0  # s0
        for i, combo in enumerate(free):
            for name, c in combo.items():
                M[self.j(name), 2 + i] += c
        return M

    def j(self, name: str) -> int:
        """Index of an elementary column (or ``scale``) in the big filter's z."""
        if name == "scale":
            return self.p + 2
        return 2 + self.mo.col[name]

    def fit(self, fixed: dict, free: list):
        """GLS of the free combinations with the fixed ones added: (theta, cov, ll, s0)."""
        th, cov, quad = gls(self.kf.W, self.M(fixed, free))
        ll = -0.5 * (self.kf.logdet + self.kf.m * LOG2PI + quad)
        return th[1:], cov[1:, 1:], ll, th[0]

    def fixed_lls(self, fixed: list) -> np.ndarray:
        """``fit(f, [])[2]`` for every fixed combination f in ``fixed`` at once (s0 the only
        free parameter, profiled in closed form): with u the combination over the big filter's
        z, w = W u, quad = u^T W u - (w_1)^2 / W_11, gathered from W's entries at the few
        columns each combination touches."""
        W = self.kf.W
        width = 1 + max((len(f) for f in fixed), default=0)
        idx = np.zeros((len(fixed), width), np.int64)  # column 0 (the data) in slot 0
        c = np.zeros((len(fixed), width))
        c[:, 0] = 1.0
        for r, f in enumerate(fixed):
            for i, (name, v) in enumerate(f.items()):
                idx[r, i + 1], c[r, i + 1] = self.j(name), v
        uwu = np.einsum("ka,kb,kab->k", c, c, W[idx[:, :, None], idx[:, None, :]])
        b = np.einsum("ka,ka->k", c, W[idx, 1])
        quad = uwu - b * b / W[1, 1] if W[1, 1] > 0 else uwu
        return -0.5 * (self.kf.logdet + self.kf.m * LOG2PI + quad)

    def loglik_of_quad(self, quad: float) -> float:
        """The big filter's log-likelihood for a quadratic form z^T W z = ``quad``."""
        return -0.5 * (self.kf.logdet + self.kf.m * LOG2PI + quad)

    def nuisance_shift(self) -> tuple[float, float]:
        """Best common command-time offset under the null (both chains re-timed): (s, ll)."""
        lls = self.fixed_lls([self.retime(float(s), 0.0) for s in self.mo.shifts])
        best = (-math.inf, 0.0)
        for s, ll in zip(self.mo.shifts, lls.tolist()):
            best = max(best, (ll, float(s)))
        return best[1], best[0]

    def retime(self, shift: float, extra: float) -> dict:
        """Fixed columns that move the null's command timing to (shift, extra braking)."""
        null, mo = self.null, self.mo
        d = {}
        if null.shift != 0.0:
            d[f"T{null.shift:+.3f}"] = -1.0
        if shift != 0.0:
            d[f"T{shift:+.3f}"] = d.get(f"T{shift:+.3f}", 0.0) + 1.0
        k_old = round(null.shift + null.brake_extra, 6)
        k_new = round(shift + extra, 6)
        if k_old != 0.0:
            d[mo.braking_cols[k_old]] = -1.0
        if k_new != 0.0:
            d[mo.braking_cols[k_new]] = d.get(mo.braking_cols[k_new], 0.0) + 1.0
        return {k: v for k, v in d.items() if v != 0.0}

    def null_ll(self) -> float:
        return self.fit({}, [])[2]


def plus_drift(extra, add_v: np.ndarray, add_s: np.ndarray) -> tuple:
    """The found drift ``extra`` ((Bv, Bs) at the events, or None) with (``add_v``, ``add_s``)
    added: what an entry of the structure test puts into the model the next round tests, and
    a stage's fixed drift (fv, fs) with what the rounds found so far."""
    return (add_v, add_s) if extra is None else (extra[0] + add_v, extra[1] + add_s)


def fit_columns(st: Stage, Bv: np.ndarray | None, Bs: np.ndarray | None, extra=None,
                meas=None, bal=None):
    """GLS of free drift columns (Bv, Bs), or with Bv, Bs None of free odometer measurement
    columns ``meas`` = (Md, Mv) or balise measurement columns ``bal``, on top of the stage's
    model (plus fixed extra drift): (chi-square statistic 2 dll, theta, se)."""
    kf = st.augmented(*plus_drift(extra, st.fv, st.fs),
                      drift=None if Bv is None else (Bv, Bs), meas=meas, bal=bal)
    q0 = gls(kf.W[:2, :2])[2]
    th, cov, q1 = gls(kf.W)
    se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    return max(q0 - q1, 0.0), th[1:], se[1:]


def cause_stat(st: Stage, dv: np.ndarray, ds: np.ndarray, free=None) -> float:
    """A cause's chi-square statistic (2 dll) on top of the stage ``st``, fitted as well as its
    parameters allow: its contribution (``dv``, ``ds``: the model with it less the model
    without it, as the joint refit fitted it) with a free multiplier, and, for a linear cause,
    each of its combinations free (``free``: ``st -> Cause.free(st, extra)``, the motion's
    elementary columns by name), the larger of the two. The contribution alone holds the
    cause at the shape the joint refit gave it beside causes that may have left the model
    (a braking rate's drift); the combinations alone miss what the cause does through the
    others (a mass change scales a power limit's deficit too)."""
    stat = fit_columns(st, dv[:, None], ds[:, None])[0]
    if free is None:
        return stat
    cols = [combo_drift(st.mo, f) for f in free(st)]
    if any(c is None for c in cols):  # a measurement column (a scale)
        return stat
    Bv, Bs = (np.stack(c, axis=1) for c in zip(*cols))
    return max(stat, fit_columns(st, Bv, Bs)[0])


def combo_drift(mo: Motion, combo: dict) -> tuple | None:
    """The drift increments (at the events, of speed and of distance) of a combination of the
    motion's elementary columns (``{name: weight}``, a ``Cause.free`` entry), or None if it
    names a column that is not a drift column (the odometer scale's measurement column)."""
    if not all(n in mo.col for n in combo):
        return None
    return (sum(w * mo.Dv[:, mo.col[n]] for n, w in combo.items()),
            sum(w * mo.Ds[:, mo.col[n]] for n, w in combo.items()))


def _memo(mo: Motion) -> dict:
    """The per-run memo of noise fits and big filters (on the Motion: it lives as long as the
    run's analysis; the big filters' results are shared, never modified)."""
    return mo.__dict__.setdefault("_stage_memo", {})


def best_section(W: np.ndarray, u: np.ndarray, e1: np.ndarray, idx: np.ndarray, min_len: int,
                 sign: float = 0.0):
    """The contiguous run [a, b) of the columns ``idx`` (b - a >= min_len) whose sum, with one
    free coefficient theta and the free nuisance e1 (s0), best explains the data: closed-form
    GLS for every run through prefix sums of W. ``u`` is the fixed combination (z[0]). ``sign``
    +1 or -1: only runs whose theta has that sign (0: any). Returns (quad, a, b, theta,
    se(theta))."""
    nb = idx.size
    w_uu, w_u1, w_11 = u @ W @ u, u @ W @ e1, e1 @ W @ e1
    a_ = W[idx] @ u
    b_ = W[idx] @ e1
    C = W[np.ix_(idx, idx)]
    A = np.concatenate([[0.0], np.cumsum(a_)])
    B = np.concatenate([[0.0], np.cumsum(b_)])
    P = np.zeros((nb + 1, nb + 1))
    P[1:, 1:] = np.cumsum(np.cumsum(C, axis=0), axis=1)
    i, j = np.triu_indices(nb + 1, k=min(min_len, nb))
    aS, bS = A[j] - A[i], B[j] - B[i]
    cS = P[j, j] - P[i, j] - P[j, i] + P[i, i]
    det = w_11 * cS - bS * bS
    ok = det > 1e-12 * np.maximum(w_11 * cS, 1e-300)
    safe = np.where(ok, det, 1.0)
    th_s0 = -(cS * w_u1 - bS * aS) / safe
    th = -(-bS * w_u1 + w_11 * aS) / safe
    quad = np.where(ok, w_uu + w_u1 * th_s0 + aS * th, np.inf)
    if sign:
        quad = np.where(sign * th > 0, quad, np.inf)
    best = int(np.argmin(quad))
    if not np.isfinite(quad[best]):
        return math.inf, 0, nb, 0.0, math.nan
    se = math.sqrt(max(w_11 / det[best], 0.0)) if ok[best] else math.nan
    return float(quad[best]), int(i[best]), int(j[best]), float(th[best]), se
