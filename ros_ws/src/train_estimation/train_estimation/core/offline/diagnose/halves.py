"""The halves tests of their own: one odometer scale counts every half of the run alike
(:func:`odometer_halves`), and a cause at a place is one size over both halves of its stretch
(:func:`place_halves`).

The held-out check's folds of an odometer cause are alternate odometer samples: each fold
holds the whole run, so their fits agree whatever the odometer does over the run, and a
comparison of the two folds tests nothing a sensor can do. A sensor's halves are halves of
the run instead: the distance counted over the first half of the distance run against the
second half (an odometer moved to other wheels, or re-calibrated, mid-run counts the two
halves at two scales).

A scale's dependence on speed is left to the rival laws, one parameter each against the
scale (:func:`.laws.count_law`: an error growing with speed; :func:`bias_law`: a speed
read b m/s more or less while moving, a scale 1 + b / v). Halves of the distance run below and
above the median speed were tried as a second partition: on 24 bags with a true constant
scale (seed 7, ``train_sim.cases``), |z| was 5.5 and 5.8 in two (metro lines), far from a
standard normal, while a bias of 0.095 m/s on a high-speed line fitted the same scale in both
(z 0.5) and its law a 2 ln LR of 105 over the scale.

Each partition is one augmented filter over the model ``others`` (the confirmed causes
without the scale) with two odometer columns, the scale's columns restricted to each half:
the distance increments run in the half, counted on after it, and the speed read in it, as
:func:`.phases.counted_columns` builds them. Their coefficients c_A, c_B (scale - 1 in each
half) come from one GLS with their covariance, so under one scale z = (c_A - c_B) / sd(c_A -
c_B) is standard normal: the partitions disagree when some |z| exceeds the two-sided quantile
of ``alpha`` shared out over the partitions (Bonferroni; ``alpha`` is the false-rejection rate
of a true constant scale) and the difference is more than ``min_share`` of the scale's
fitted change (as :func:`.confirm.halves_test` for a motion cause).
"""

from __future__ import annotations

import math

import numpy as np

from train_estimation.core.numerics.augmented_kf import gls
from train_estimation.core.numerics.special import ndtri

from .motion import Motion
from .phases import counted_columns
from .stage import Null, Stage

# odometer readings while moving that each half must hold to be compared
MIN_READINGS = 10


def odometer_partitions(mo: Motion, standstill: float) -> dict:
    """{partition: (mask of the first half, mask of the second half, what each half is)} over
    the events (only odometer events matter): the halves of the distance run, each with every
    odometer reading in it (the scale counts creeping too); halves with fewer than
    ``MIN_READINGS`` readings faster than ``standstill`` (m/s) are not compared."""
    n = mo.ev.t.size
    o = mo.ev.odo
    inc = np.zeros(n)
    inc[o] = np.clip(np.diff(mo.sc_d[o], prepend=mo.sc_d[o][0]), 0.0, None)
    is_odo = np.zeros(n, bool)
    is_odo[o] = True
    moving = is_odo & (mo.sc_v > standstill)
    out = {}
    run = np.cumsum(inc)
    if run[-1] > 0:
        half = 0.5 * run[-1]
        first = is_odo & (run <= half)
        if min(np.count_nonzero(moving & first), np.count_nonzero(moving & ~first)) \
                >= MIN_READINGS:
            out["distance"] = (first, is_odo & ~first,
                               (f"over the first {half:.0f} m", f"over the last {half:.0f} m"))
    return out


def odometer_halves(mo: Motion, others: Null, cfg, noise, alpha: float,
                    min_share: float) -> dict:
    """The halves test of an odometer scale against the model ``others`` (without the scale)
    at ``noise`` (module docstring): {tested, consistent, z_needed, quantities: {partition:
    {halves, scale: [A, B], std_errors, z, disagree}}, why (when not consistent)}."""
    parts = odometer_partitions(mo, cfg.standstill_speed)
    if not parts:
        return {"tested": False, "consistent": True,
                "note": f"fewer than {MIN_READINGS} odometer readings while moving in a half"}
    zc = float(-ndtri(alpha / (2 * len(parts))))
    out = {"test": "scale over the halves of the distance run", "tested": True,
           "consistent": True, "z_needed": zc, "quantities": {}}
    st = Stage(mo, others, cfg, noise=noise, big=False)
    n = mo.ev.t.size
    o = mo.ev.odo
    inc = np.zeros(n)
    inc[o] = np.diff(mo.sc_d[o], prepend=mo.sc_d[o][0])
    for name, (a, b, words) in parts.items():
        md = counted_columns(mo, inc, [a, b])
        mv = np.stack([mo.sc_v * a, mo.sc_v * b], axis=1)
        th, cov, _ = gls(st.augmented(st.fv, st.fs, meas=(md, mv)).W)
        c, C = th[1:3], cov[1:3, 1:3]
        var = float(C[0, 0] + C[1, 1] - 2.0 * C[0, 1])
        se = [float(math.sqrt(max(C[i, i], 0.0))) for i in (0, 1)]
        if not (var > 0 and all(s > 0 for s in se)):
            out["quantities"][name] = {"halves": list(words), "note": "no information"}
            continue
        z = float((c[0] - c[1]) / math.sqrt(var))
        size = abs(0.5 * (c[0] + c[1]))
        bad = bool(abs(z) > zc and abs(c[0] - c[1]) > min_share * size)
        sc = [1.0 + float(c[0]), 1.0 + float(c[1])]
        out["quantities"][name] = {"halves": list(words), "scale": sc, "std_errors": se,
                                   "z": z, "disagree": bad}
        if bad and out["consistent"]:
            out["consistent"] = False
            out["why"] = (f"not one scale: the odometer counts {sc[0]:.4f} times the distance "
                          f"{words[0]} and {sc[1]:.4f} {words[1]} (z {z:+.1f}, beyond "
                          f"{zc:.1f}: {alpha:g} two-sided)")
    return out


def bias_law(mo: Motion, others: Null, cfg, noise) -> dict:
    """An odometer that counts one scale times the distance against one that reads ``b`` m/s
    more speed than the train's while moving (and counts it: b per second moved), one
    parameter each, on top of the model ``others`` at ``noise``, in the distance and speed
    readings alike. A speed offset is a scale 1 + b / v: the two differ where the train
    moves slowly (departures, approaches) and a scale fitted to it changes with speed.

    Returns ``lr``: 2 ln of the likelihood ratio of the offset against the scale (> 0: the
    data prefer the offset); ``b`` (m/s) and its standard error, the scale fitted alone."""
    n = mo.ev.t.size
    o = mo.ev.odo
    moving = np.zeros(n, bool)
    moving[o] = mo.sc_v[o] > cfg.standstill_speed
    if np.count_nonzero(moving) < MIN_READINGS:
        return {"law": "b m/s while moving", "lr": 0.0,
                "note": f"fewer than {MIN_READINGS} odometer readings while moving"}
    dt = np.zeros(n)
    dt[o] = np.diff(mo.ev.t[o], prepend=mo.ev.t[o][0])
    law_d = counted_columns(mo, dt, [moving])[:, 0]
    st = Stage(mo, others, cfg, noise=noise, big=False)
    W = st.augmented(st.fv, st.fs, meas=(np.stack([mo.sc_d, law_d], axis=1),
                                         np.stack([mo.sc_v, moving.astype(float)],
                                                  axis=1))).W
    q0 = gls(W[:2, :2])[2]
    stat, fit, se = {}, {}, {}
    for name, j in (("scale", 2), ("bias", 3)):
        M = np.zeros((W.shape[0], 3))
        M[0, 0] = M[1, 1] = M[j, 2] = 1.0
        th, cov, q1 = gls(W, M)
        stat[name], fit[name] = q0 - q1, float(th[1])
        se[name] = float(math.sqrt(max(cov[1, 1], 0.0)))
    return {"law": "b m/s while moving", "lr": float(stat["bias"] - stat["scale"]),
            "b": fit["bias"], "std_error": se["bias"], "scale": 1.0 + fit["scale"],
            "speeds": [float(x) for x in np.percentile(mo.sc_v[moving], [5, 95])]}


# s, the least time a cause at a place acts in each half of its stretch for the halves to be
# compared (ten odometer samples at 5 Hz, as a held-out block's least: heldout.MIN_PLACE_BLOCK)
MIN_HALF_TIME = 2.0


def place_halves(mo: Motion, others: Null, cause, fit, cfg, noise, alpha: float,
                 min_share: float) -> dict:
    """The halves test of a cause at a place (``Cause.beyond``: a gradient, a low-adhesion
    section): the stretch stays the one the whole data's fit found, cut where half the time the
    cause acts on it is done (the median place of its acting time, so that both halves hold
    about the same information), and the cause's size on each half comes from one augmented
    filter over the model ``others`` (without the cause) at ``noise`` with the cause's columns
    restricted to each half (``cause.half_columns``): c_A, c_B with their covariance, z =
    (c_A - c_B) / sd(c_A - c_B), standard normal when the cause is one size over its stretch.
    They disagree beyond the two-sided ``alpha`` quantile and more than ``min_share`` of the
    cause's fitted size (as :func:`.heldout.halves_test`). The folds of the held-out check are
    not compared: each chooses its own stretch, so their two sizes are of two sections."""
    bey = cause.beyond(fit, mo)
    if bey is None:
        return {"tested": False, "consistent": True, "note": "not a cause at a place"}
    inside, pattern = bey
    on = inside & (pattern != 0)
    x_on = mo.x_ref[on]
    t_half = 0.5 * float(np.count_nonzero(on)) * mo.grid.dt
    if t_half < MIN_HALF_TIME:
        return {"tested": False, "consistent": True,
                "note": f"acts for {2 * t_half:.1f} s on its stretch, less than "
                        f"{MIN_HALF_TIME:g} s in each half"}
    start, end = float(fit.parameters["start"]), float(fit.parameters["end"])
    cut = float(np.median(x_on))
    zc = float(-ndtri(alpha / 2))
    st = Stage(mo, others, cfg, noise=noise, big=False)
    Bv, Bs = cause.half_columns(fit, mo, others, np.array([start, cut, end]))
    th, cov, _ = gls(st.augmented(st.fv, st.fs, drift=(Bv, Bs)).W)
    c, C = th[1:3], cov[1:3, 1:3]
    var = float(C[0, 0] + C[1, 1] - 2.0 * C[0, 1])
    se = [float(math.sqrt(max(C[i, i], 0.0))) for i in (0, 1)]
    key, value = cause.half_quantity
    words = (f"on [{start:.0f}, {cut:.0f}) m", f"on [{cut:.0f}, {end:.0f}) m")
    out = {"test": f"{key} over the halves of its stretch (half its acting time each)",
           "tested": True, "consistent": True, "z_needed": zc, "quantities": {}}
    if not (var > 0 and all(s > 0 for s in se)):
        out.update(tested=False, note="no information in a half")
        return out
    z = float((c[0] - c[1]) / math.sqrt(var))
    size = abs(0.5 * (c[0] + c[1]))
    bad = bool(abs(z) > zc and abs(c[0] - c[1]) > min_share * size)
    vals = [value(float(c[0])), value(float(c[1]))]
    out["quantities"][key] = {"halves": list(words), "folds": vals, "std_errors": se, "z": z,
                              "disagree": bad}
    if bad:
        out["consistent"] = False
        out["why"] = (f"the data's halves fit it differently: {key} {vals[0]:.4g} {words[0]} "
                      f"and {vals[1]:.4g} {words[1]} (z {z:+.1f}, beyond {zc:.1f}: "
                      f"{alpha:g} two-sided)")
    return out
