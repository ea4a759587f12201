"""Rival laws of a confirmed cause's effect: the same data explained by a force or a count that
follows another law, each law fitted on its own, compared by their likelihood ratio.

**Speed law** (:func:`speed_law`). A gradient is g sin(theta) at its place, whatever the
speed; drag in a tunnel at the same place grows as v^2. Each law gets its own best stretch near
the fitted one (same parameter count), and 2 ln of their likelihood ratio says which the data
prefer; at one steady speed the two are the same force and the ratio is near 0.

**Braking law** (:func:`braking_law`). A force fixed at a place against one in proportion to
the braking asked for there (an adhesion section), the same way.

**Heat law** (:func:`heat_law`). A braking weaker by the cause against brakes that fade as they
heat (:func:`heat_state`).

**Count law** (:func:`count_law`). An odometer that counts one scale times the distance at
every speed against one whose error grows with speed.

**Stop law** (:func:`stop_law`). Causes at places (a gradient the map lacks, a low-adhesion
section) against a train that changed at a stop: from a departure on, its traction and its
braking deliver other multiples of what is asked (a payload taken on with brakes that are not
load-weighed, a motor or a brake cut out while standing).
"""

from __future__ import annotations

import math

import numpy as np
from train_core.lag import first_order
from train_core.model import G as G_ACCEL

from train_estimation.core.numerics.augmented_kf import gls

from .motion import Motion
from .phases import counted_columns
from .stage import Null, Stage, best_section, cause_stat, fit_columns

# position bins by which the speed-law test moves a stretch's ends (each law gets its own best
# stretch near the fitted one: a fixed force fitted on a drag stretch overshoots it at the fast
# end, which alone would make the drag law look worse on the fixed force's own stretch)
LAW_REACH = 4


def speed_law(mo: Motion, others: Null, cfg, noise, bins: tuple, power: float = 2.0) -> dict:
    """A force fixed at a place against one that grows as v^power (aerodynamic drag: power 2,
    drag in a tunnel): :func:`law_test` with that law."""
    vm = 0.5 * (mo.v_ref[1:] + mo.v_ref[:-1])
    return law_test(mo, others, cfg, noise, bins, vm ** power, f"v^{power:g}")


def braking_law(mo: Motion, others: Null, cfg, noise, bins: tuple) -> dict:
    """A force fixed at a place against one in proportion to the braking asked for there
    (braking weaker on a stretch: an adhesion section): :func:`law_test` with that law."""
    br = -mo.f0 * mo.a_br0
    return law_test(mo, others, cfg, noise, bins, np.maximum(0.5 * (br[1:] + br[:-1]), 0.0),
                    "the braking command")


# s, cooling times of brakes tried by the heat law (a tread or a disc sheds its heat over
# minutes; the choice among them is charged 2 ln of their number)
HEAT_TAUS = (30.0, 60.0, 120.0, 300.0)


def heat_state(mo: Motion, tau: float) -> np.ndarray:
    """The brakes' heat on the grid, relative to that of one stop from the run's top speed:
    H' = P - H / tau with P = f0 |a_br| v the braking power per kg the brakes take (m^2/s^3),
    divided by v_top^2 / 2."""
    p = np.maximum(-mo.f0 * mo.a_br0, 0.0) * np.maximum(mo.v_ref, 0.0) * mo.moving
    dt = mo.grid.dt
    # h[k] = exp(-dt / tau) h[k-1] + dt p[k-1]: the heat taken up to grid point k, cooled
    h = first_order(p, math.exp(-dt / tau), dt)
    v_top = float(np.max(mo.v_ref * mo.moving)) if mo.moving.any() else 0.0
    return h / max(0.5 * v_top * v_top, 1e-9)


def heat_law(mo: Motion, others: Null, full: Null, cfg, noise, free=None) -> dict:
    """A braking weaker by the cause (``full`` against ``others``: a braking-rate change in
    time, a low-adhesion section) against brakes that fade as they heat: the braking asked for
    times (c1 + c2 H), H the brakes' heat (:func:`heat_state`) at the best of ``HEAT_TAUS``,
    two parameters on top of ``others``.

    The cause is fitted in its own parameters on the same stage (:func:`.stage.cause_stat`,
    ``free`` its combinations). A cause with two parameters held at the shape the joint refit
    gave it, one multiplier free, lost to a constant braking factor that it contains: a
    braking rate 0.924 throughout, beside a gradient, held as a drift 0.936 -> 0.921 lost to
    the heat law by 2 ln LR +80 with its fade at 0.0006, while the rate free on the heat
    law's stage fits as well as the law.

    Returns ``lr``: 2 ln of the likelihood ratio of the heat law against the cause, less 2 ln
    of the number of cooling times tried (> 0: the data prefer the heat law; near 0 where
    every braking holds the same heat, as on a run of equal stops); ``tau`` and the heat law's
    fade at the heat of one stop from the top speed (``fade``, -c2 / (f0 + c1)); the speeds
    braked at (5-95 %)."""
    st0 = Stage(mo, others, cfg, noise=noise, big=False)
    st1 = Stage(mo, full, cfg, noise=noise, big=False)
    dv, ds = st1.fv - st0.fv, st1.fs - st0.fs
    res = {"law": "heat"}
    brk = (mo.a_br0 < 0) & (mo.moving > 0)
    if not (dv * dv).sum() > 0 or brk.sum() < 10:
        res.update(lr=0.0, note="no braking while moving")
        return res
    cause = cause_stat(st0, dv, ds, free)
    fit = _heat_profile(mo, st0)
    vb = mo.v_ref[brk]
    v_lo, v_hi = np.percentile(vb, [5, 95])
    res.update(lr=float(fit.pop("stat") - cause - 2.0 * math.log(len(HEAT_TAUS))), **fit,
               speeds=[float(v_lo), float(v_hi)])
    return res


def heat_refit(mo: Motion, null: Null, cfg, noise, law: dict) -> dict:
    """The heat law ``law`` (:func:`heat_law`'s result) fitted again on top of the model
    ``null``, its cooling time profiled over ``REFIT_TAUS``: ``law`` with the new ``tau``,
    ``coefficients``, ``f_cold`` and ``fade`` (its ``lr`` stays the comparison's)."""
    fit = _heat_profile(mo, Stage(mo, null, cfg, noise=noise, big=False), REFIT_TAUS)
    fit.pop("stat")
    return dict(law, **fit)


# s, cooling times over which a heat law in a model (a nuisance beside the causes judged in it,
# not a comparison: no charge) is fitted again, in steps of a quarter from the shortest of
# HEAT_TAUS to twice the longest: on the foreign simulator's brakes cooling in 88 s, a heat law
# at 120 s left a braking remainder at one stop that a 4.3 per mille gradient took (held-out
# Z 2.0); at 95 s the gradient predicts nothing (Z 0.7)
REFIT_TAUS = tuple(float(x) for x in np.geomspace(HEAT_TAUS[0], 2.0 * HEAT_TAUS[-1], 14))


def _heat_profile(mo: Motion, st: Stage, taus: tuple = HEAT_TAUS) -> dict:
    """The heat law's best fit on top of the stage ``st``: its cooling time (the best of
    ``HEAT_TAUS``), the two coefficients (the braking asked for, and that times the heat),
    the brakes' factor cold (``f_cold``), the fade at one stop's heat and the fit's
    chi-square statistic (``stat``, 2 dll)."""
    n_ev = mo.ev.t.size
    best = (-math.inf, None, None)
    for tau in taus:
        stat, th, _ = fit_columns(st, *mo.grid.integrate(_heat_columns(mo, tau), n_ev))
        if stat > best[0]:
            best = (stat, tau, th)
    stat, tau, th = best
    return {"stat": float(stat), "tau": tau, "coefficients": [float(th[0]), float(th[1])],
            "f_cold": float(mo.f0 + th[0]),
            "fade": float(-th[1] / (mo.f0 + th[0])) if mo.f0 + th[0] else float("nan")}


def _heat_columns(mo: Motion, tau: float) -> np.ndarray:
    """The heat law's two acceleration columns on the grid (per grid point): the braking asked
    for, and the braking asked for times the brakes' heat (:func:`heat_state`)."""
    h = heat_state(mo, tau)
    return np.stack([mo.a_br0 * mo.moving, mo.a_br0 * h * mo.moving], axis=1)


def heat_fit(mo: Motion, res: dict) -> tuple:
    """The heat law fitted by :func:`heat_law` (its result ``res``) as a model's part: (Bv, Bs)
    its drift increments at the events (``Null.extra``'s form) and its acceleration on the
    grid (m/s^2, > 0 where the brakes deliver less than believed)."""
    acc = _heat_columns(mo, res["tau"]) @ np.asarray(res["coefficients"], float)
    bv, bs = mo.grid.integrate(acc[:, None], mo.ev.t.size)
    return bv[:, 0], bs[:, 0], acc


def stops(mo: Motion) -> list:
    """Grid indices of the departures after each stop of the run: where the reference speed
    rises to the standstill speed again after a standstill (not the run's first departure:
    a change from it on is one for the whole run, a listed cause's)."""
    mv = mo.moving > 0
    dep = np.flatnonzero(mv[1:] & ~mv[:-1]) + 1
    first = int(np.argmax(mv)) if mv.any() else mv.size
    return [int(k) for k in dep if k > first]


def stop_law(mo: Motion, others: Null, full: Null, cfg, noise, k_causes: int) -> dict:
    """Causes at places (``full`` against ``others``: their contribution, with a free
    multiplier; ``k_causes`` parameters fitted, their places included) against a train that
    changed at a stop: from the departure after stop k on, the traction and the braking asked
    for (through the believed actuator) times 1 + g_tr and 1 + g_br, two parameters, k the
    best of the run's stops (:func:`stops`; charged 2 ln of their number).

    The two have different numbers of parameters, so they are compared as the search scores
    causes (BIC: each parameter ln n, n the measurements): ``lr`` = (chi-square of the law -
    2 ln n - 2 ln stops) - (chi-square of the causes - k_causes ln n), > 0 where the data
    prefer a change at a stop (twice the log of an approximate Bayes factor); the departure's
    time ``t`` (s) and the factors ``traction`` and ``braking``; ``chi2`` of each; the run's
    speeds (5-95 %). Without stops, ``lr`` 0 and a note."""
    res = {"law": "stop"}
    deps = stops(mo)
    st0 = Stage(mo, others, cfg, noise=noise, big=False)
    st1 = Stage(mo, full, cfg, noise=noise, big=False)
    dv, ds = st1.fv - st0.fv, st1.fs - st0.fs
    if not deps or not (dv * dv).sum() > 0:
        res.update(lr=0.0, note="no stop after the first departure" if not deps else
                   "no contribution")
        return res
    causes = fit_columns(st0, dv[:, None], ds[:, None])[0]
    n_ev = mo.ev.t.size
    base = np.stack([mo.a_tr0 * mo.moving, mo.f0 * mo.a_br0 * mo.moving], axis=1)
    best = (-math.inf, None, None)
    for k in deps:
        cols = base.copy()
        cols[:k] = 0.0
        stat, th, _ = fit_columns(st0, *mo.grid.integrate(cols, n_ev))
        if stat > best[0]:
            best = (stat, k, th)
    stat, k, th = best
    v = mo.v_ref[mo.moving > 0]
    lo, hi = np.percentile(v, [5, 95]) if v.size else (0.0, 0.0)
    ln_n = math.log(max(n_ev, 2))
    res.update(lr=float((stat - 2.0 * ln_n - 2.0 * math.log(len(deps)))
                        - (causes - k_causes * ln_n)),
               t=float(mo.grid.t[k]), traction=float(1.0 + th[0]), braking=float(1.0 + th[1]),
               chi2_law=float(stat), chi2_causes=float(causes), k_causes=int(k_causes),
               speeds=[float(lo), float(hi)], stops=len(deps))
    return res


def count_law(mo: Motion, others: Null, cfg, noise) -> dict:
    """An odometer that counts one ``scale`` times the distance at every speed (a worn wheel)
    against one whose error grows with speed, k v / v_top (a Doppler radar's, an axle that
    slips more the faster it turns): both on top of the model ``others``, one parameter each,
    in the odometer's distance and speed readings alike.

    Returns ``lr``: 2 ln of the likelihood ratio of the speed law against the scale (> 0: the
    data prefer the law; near 0 when the run is at one speed, where the two are the same
    count); from the fit of both together, a ((1 - b) scale + b law) with the law scaled to
    the same count at the run's mean speed: ``b`` (0 the scale, 1 the law) and its standard
    error; ``k`` (the law's relative error at v_top) and the speeds moved at (5-95 %)."""
    n = mo.ev.t.size
    o = mo.ev.odo
    v = mo.sc_v[o]
    moving = v > cfg.standstill_speed
    res = {"law": "k v / v_top"}
    if moving.sum() < 10:
        res.update(lr=0.0, note="fewer than ten odometer readings while moving")
        return res
    v_top, v_mean = float(np.max(v)), float(np.mean(v[moving]))
    # the law's count: what the scale's distance increments become when each is weighted by
    # the speed it was run at relative to the run's mean moving speed (the same count as the
    # scale's over a run at that one speed), counted on; its speed reading the same
    w = np.zeros(n)
    w[o] = mo.sc_v[o] / v_mean
    inc = np.zeros(n)
    inc[o] = np.diff(mo.sc_d[o], prepend=mo.sc_d[o][0])
    law_d = counted_columns(mo, inc * w, [np.ones(n, bool)])[:, 0]
    st = Stage(mo, others, cfg, noise=noise, big=False)
    W = st.augmented(st.fv, st.fs, meas=(np.stack([mo.sc_d, law_d], axis=1),
                                         np.stack([mo.sc_v, mo.sc_v * w], axis=1))).W
    q0 = gls(W[:2, :2])[2]
    stat, fitted = {}, {}
    for name, j in (("scale", 2), ("law", 3)):
        M = np.zeros((W.shape[0], 3))
        M[0, 0] = M[1, 1] = M[j, 2] = 1.0
        th, _, q1 = gls(W, M)
        stat[name], fitted[name] = q0 - q1, float(th[1])
    # both: a scale + c (law - scale), c / a = b
    M = np.zeros((W.shape[0], 4))
    M[0, 0] = M[1, 1] = 1.0
    M[2, 2], M[3, 3], M[2, 3] = 1.0, 1.0, -1.0
    share, se = _law_share(W, M)
    v_lo, v_hi = np.percentile(v[moving], [5, 95])
    res.update(lr=float(stat["law"] - stat["scale"]), b=share, std_error=se,
               scale=1.0 + fitted["scale"],
               k=fitted["law"] * v_top / v_mean,
               speeds=[float(v_lo), float(v_hi)])
    return res


def _law_share(W: np.ndarray, M: np.ndarray) -> tuple[float, float]:
    """From the fit of a cause and a rival law together, a g + c (h - g) (``M``'s last two
    columns): the law's share b = c / a and its standard error."""
    th, cov, _ = gls(W, M)
    amp = float(th[1])
    if amp == 0:
        return float("nan"), float("inf")
    return float(th[2] / amp), float(math.sqrt(max(cov[2, 2], 0.0)) / abs(amp))


def law_test(mo: Motion, others: Null, cfg, noise, bins: tuple, shape: np.ndarray,
             name: str) -> dict:
    """A force fixed at a place (a gradient on the position bins ``bins`` = (i, j)) against a
    force at a place that follows ``shape`` (per grid step, >= 0: v^2 for drag in a tunnel, the
    braking asked for where the rail's adhesion is low), both on top of the model ``others``,
    each on its own best stretch within ``LAW_REACH`` bins of the fitted one (same parameter
    count: start, end, size), its ends then refined to a ``LAW_SPLIT``-th of a bin
    (:func:`_refined`).

    Returns ``lr``: 2 ln of the likelihood ratio of the law's best stretch against the fixed
    force's (> 0: the data prefer the law; near 0 at one steady speed, where the two are the
    same force); on the fixed force's stretch the fit of both together, a ((1 - b) g + b h)
    with h the law's column scaled to the same mean force: ``b`` (0 a fixed force, 1 the law)
    and its standard error (on that stretch, whose ends a fixed force fitted to drag moves:
    ``lr`` is the comparison); the speeds on it and the law over its mean there (``shape``;
    5-95 %) and both stretches (m)."""
    i, j = int(bins[0]), int(bins[1])
    lo, hi = max(0, i - LAW_REACH), min(mo.n_bins, j + LAW_REACH)
    mov, jb = mo.step_moving, mo.step_bin
    width = mo.bin_edges[1] - mo.bin_edges[0]
    res = {"law": name}
    on = mov & (jb >= i) & (jb < j)
    if on.sum() < 2:
        res.update(lr=0.0, note="the train does not move on the stretch")
        return res
    if not np.mean(shape[on]) > 0:
        res.update(lr=0.0, note=f"{name} is zero on the stretch")
        return res
    law = shape / float(np.mean(shape[on]))  # the law's force relative to its mean there
    st = Stage(mo, others, cfg, noise=noise, big=False)
    # the bins [lo, hi) each one column
    split = np.zeros(mo.n_bins, bool)
    W, _ = _law_columns(mo, st, law, lo, hi, split)
    m = hi - lo
    q0 = gls(W[:2, :2])[2]
    min_len = max(1, int(math.ceil(cfg.min_section / width - 1e-9)))
    best = {}
    pairs = [(a, b) for a in range(m) for b in range(a + min_len, m + 1)]
    for key, off in (("fixed", 0), ("law", m)):
        top = (-np.inf, None)
        for (a, b), quad in zip(pairs, _stretch_quads(W, off, pairs)):
            stat = q0 - quad
            if stat > top[0]:
                top = (stat, (lo + a, lo + b))
        best[key] = top
    return _refined(mo, st, law, lo, hi, best, res)


def _stretch_quads(W: np.ndarray, off: int, pairs: list) -> list:
    """``gls(W, M)[2]`` for the M of each stretch (a, b) of ``pairs``: [1, s0, one coefficient
    on the columns 2 + off + [a, b)]. Batched, with each stretch's BLAS and LAPACK calls those
    of ``gls`` (the same shapes and strides: M^T W M, the equilibrated 2 x 2 information's
    pseudo-inverse through the stacked SVD, then theta and the quadratic form one by one), so
    the same bits (tested), without gls's 3,000 calls' Python (0.3 s of a located cause)."""
    if not pairs:
        return []
    M = np.zeros((len(pairs), W.shape[0], 3))
    M[:, 0, 0] = M[:, 1, 1] = 1.0
    for k, (a, b) in enumerate(pairs):
        M[k, 2 + off + a:2 + off + b, 2] = 1.0
    Wh = np.matmul(np.matmul(M.transpose(0, 2, 1), W), M)
    A = Wh[:, 1:, 1:]
    dg = np.diagonal(A, axis1=1, axis2=2)
    d = np.where(dg > 0, np.sqrt(np.abs(dg)), 1.0)  # augmented_kf._equilibrated
    dd = d[:, :, None] * d[:, None, :]
    cov = np.linalg.pinv(A / dd) / dd
    out = []
    for k in range(len(pairs)):
        b = Wh[k, 1:, 0]
        th = -cov[k] @ b
        out.append(float(Wh[k, 0, 0] + b @ th))
    return out


# parts of a position bin to which the law tests refine the ends of each law's stretch: a
# fixed force and a law on stretches of whole bins (tens of metres) differ at the ends by more
# than the laws do where a stretch ends at a stop (the slow end of a braking, where the train
# spends seconds on a few metres) or at a tunnel's portal
LAW_SPLIT = 8


def _law_columns(mo: Motion, st: Stage, law: np.ndarray, lo: int, hi: int, split: np.ndarray):
    """The augmented filter's information W over the fixed force's and the law's columns on the
    bins [lo, hi): one column per bin, ``LAW_SPLIT`` per bin where ``split``; the fixed force's
    columns first, then the law's. Returns W and the columns' edges (m)."""
    g, ev = mo.grid, mo.ev
    mov, jb = mo.step_moving, mo.step_bin
    edges = mo.bin_edges
    width = edges[1] - edges[0]
    parts = np.where(split[lo:hi], LAW_SPLIT, 1)
    first = np.concatenate([[0], np.cumsum(parts)])  # column of each bin's first part
    ncol = int(first[-1])
    near = mov & (jb >= lo) & (jb < hi)
    xm = 0.5 * (mo.x_ref[1:] + mo.x_ref[:-1])
    rel = jb[near] - lo
    sub = np.clip(((xm[near] - edges[jb[near]]) / (width / LAW_SPLIT)).astype(int), 0,
                  LAW_SPLIT - 1)
    col = first[rel] + np.where(parts[rel] > 1, sub, 0)
    gper = -G_ACCEL / 1000.0 * mo.k_grad  # m/s^2 per permille
    Bv, Bs = np.zeros((ev.t.size, 2 * ncol)), np.zeros((ev.t.size, 2 * ncol))
    for off, w in ((0, np.ones(near.sum())), (ncol, law[near])):
        inc = gper * g.dt * w
        np.add.at(Bv, (g.k[near], off + col), inc)
        np.add.at(Bs, (g.k[near], off + col), inc * g.lever[near])
    W = st.augmented(st.fv, st.fs, drift=(Bv, Bs)).W
    col_edges = np.concatenate([edges[b] + width * np.arange(p) / p
                                for b, p in zip(range(lo, hi), parts)] + [[edges[hi]]])
    return W, col_edges


def _refined(mo: Motion, st: Stage, law: np.ndarray, lo: int, hi: int, best: dict,
             res: dict) -> dict:
    """The comparison of :func:`law_test` with each law's stretch ``best`` (whole bins) refined:
    the bins within one of either law's ends split in ``LAW_SPLIT`` parts, and each law's best
    stretch over those columns (it includes the stretch of whole bins)."""
    split = np.zeros(mo.n_bins, bool)
    for _, (a, b) in best.values():
        for e in (a, b):
            split[max(lo, e - 1):min(hi, e + 1)] = True
    W, col_edges = _law_columns(mo, st, law, lo, hi, split)
    n = col_edges.size - 1
    q0 = gls(W[:2, :2])[2]
    u, e1 = np.zeros(W.shape[0]), np.zeros(W.shape[0])
    u[0], e1[1] = 1.0, 1.0
    fine = {}
    for key, off in (("fixed", 0), ("law", n)):
        quad, a, b, _, _ = best_section(W, u, e1, 2 + off + np.arange(n), 1)
        fine[key] = (q0 - quad, (a, b)) if np.isfinite(quad) else None
    if fine["fixed"] is None or fine["law"] is None:
        fine = {k: (s, (int(np.searchsorted(col_edges, mo.bin_edges[a])),
                        int(np.searchsorted(col_edges, mo.bin_edges[b]))))
                for k, (s, (a, b)) in best.items()}
    # on the fixed force's own stretch: both columns, a g + c (h - g), c / a = b
    a0, b0 = fine["fixed"][1]
    M = np.zeros((W.shape[0], 4))
    M[0, 0] = M[1, 1] = 1.0
    M[2 + a0:2 + b0, 2] = 1.0
    M[2 + n + a0:2 + n + b0, 3] = 1.0
    M[2 + a0:2 + b0, 3] = -1.0
    share, se = _law_share(W, M)
    vm = 0.5 * (mo.v_ref[1:] + mo.v_ref[:-1])
    xm = 0.5 * (mo.x_ref[1:] + mo.x_ref[:-1])
    sec = mo.step_moving & (xm >= col_edges[a0]) & (xm < col_edges[b0])
    v_lo, v_hi = np.percentile(vm[sec], [5, 95]) if sec.any() else (0.0, 0.0)
    # the law over its mean on that stretch (5-95 %): near 1 throughout, the two are one force
    s_lo, s_hi = np.percentile(law[sec] / np.mean(law[sec]), [5, 95]) \
        if sec.any() and np.mean(law[sec]) > 0 else (0.0, 0.0)
    res.update(lr=float(fine["law"][0] - fine["fixed"][0]), b=share, std_error=se,
               speeds=[float(v_lo), float(v_hi)], shape=[float(s_lo), float(s_hi)],
               stretch_fixed=[float(col_edges[a0]), float(col_edges[b0])],
               stretch_law=[float(col_edges[fine["law"][1][0]]),
                            float(col_edges[fine["law"][1][1]])])
    return res
