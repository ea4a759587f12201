"""The structure test's rounds on the balise readings (:func:`.phases.structure`): what the
motion families cannot see, since the odometer carries the position from one balise to the next.

**Balise test** (:func:`balise_round`). The motion families cannot see a balise that lies
elsewhere than the map says: the odometer carries the position from one balise to the next,
so one reading off by metres moves no acceleration. Each reading gets a free offset of its
own; the largest that is significant (Bonferroni over the readings, within the same
``alpha``) and more than ``min_offset`` m competes with the families in each round; as an
entry it has phase ``all``, ``where`` the balise's map position, ``size`` the offset in m.

**Latency test** (:func:`latency_round`). A balise reader that stamps its readings late puts
every reading ``v_b tau`` behind the train, in proportion to the speed it was read at: one
more free parameter (the latency, a balise measurement column ``-v_b``), tested in each round
with the same likelihood ratio and Bonferroni share until it is found; as an entry it has phase
``all``, no ``where`` nor ``when`` (every reading), ``speed`` the range of the readings'
speeds and ``size`` the latency in s.

**Datum test** (:func:`datum_round`). The balises place the run on the line, and the map's
gradients act where they place it; a balise map surveyed on another datum than the gradient
profile (every balise some metres off the gradients) moves each gradient change by that much,
which no listed cause and no single balise shows (each reading agrees with the odometer). One
more free parameter, the shift delta of the gradients against the balises (a drift column:
the change of the gradient's pull per metre of shift, a central difference over
``DATUM_STEP``), tested in each round until it is found; as an entry it has phase ``all``, no
``where`` nor ``when``, ``size`` delta in m (> 0: the gradients act further on than the
balises place them).

**Scatter test** (:func:`scatter_round`). A balise reader whose readings scatter more than
they state (its timing noisier than stated, or a map surveyed worse than it says) puts every
reading a random few metres off the odometer's track; tested one reading at a time, the
largest of them looks like one balise lying elsewhere, at every reading's stated variance. The
hypothesis is one more parameter, a scale of every balise reading's variance. Under the stated
variances the readings' whitened innovations (the odometer's track through the model, the
count's origin s0 fitted to the balises) are independent standard normals, so their sum of
squares is chi-square with one degree of freedom per reading less one for s0 and one for each
reading whose offset is in the model: excess scatter is its upper tail, tested in each round
with the same Bonferroni share until it is found. A single balise off by metres, or an
odometer that counts differently from a time on, raises the sum too. A structure that a motion
or the odometer family finds goes first (tested at the stated variance); against a balise's
offset, the latency or the datum, a variance and a mean being alternatives of different kinds,
the scatter is chosen when its likelihood is the higher (BIC over the readings).
As an entry it has phase ``all``, no ``where`` nor ``when`` (every reading), ``size`` the
readings' SD over their stated SD, and the readings' variances are scaled by its square in
the rounds that follow (a reading that is still an outlier at the found scatter is one).
"""

from __future__ import annotations

import math

import numpy as np

from train_estimation.core.numerics.augmented_kf import gls
from train_estimation.core.numerics.tails import chi2_logsf

from .motion import Motion
from .stage import Stage, fit_columns, plus_drift


def balise_round(mo: Motion, st: Stage, extra, inside: list, alpha: float, cell_z: float,
                 min_offset: float, beta: float = 1.0) -> dict:
    """One round of the balise test: the reading that the odometer continues least (a balise
    lying elsewhere than the map and its telegram say, a reading of another balise).

    Every reading j not yet in the model (``inside``: readings whose offset is) gets a free
    offset of its own (a balise measurement column that is 1 at that reading: p_b = s0 + s(t_b)
    + o_j + e_b) on top of the model ``st`` (plus the found drift ``extra``); 2 dll of adding
    it is chi-square with one degree of freedom under the model. The largest is significant
    below ``alpha`` / n (Bonferroni over the n readings) with the offset beyond ``cell_z`` SE
    and ``min_offset`` (m: a balise's location accuracy is metres; a misstated reading variance
    must not make a finding of less). No listed cause moves one reading: an odometer scale
    grows with distance, a slip episode shifts every reading after it, a clock or link cause
    moves none. Its entry's ``size`` is the offset in m (the reading's position minus the
    train's position by the odometer there), ``where`` the balise's map position, ``when`` the
    reading's time (stamp clock). Returns the figures, ``logp_family`` (log of n p: the round's
    comparison with the families) and, when significant, ``entry``."""
    ev = mo.ev
    n = ev.bal.size
    out = {"readings": int(n), "significant": False}
    left = [j for j in range(n) if j not in inside]
    if n < 3 or not left:
        out["note"] = "fewer than three balise readings" if n < 3 else "every reading in"
        return out
    cols = np.zeros((ev.t.size, len(left)))
    cols[ev.bal[left], np.arange(len(left))] = 1.0
    fv, fs = plus_drift(extra, st.fv, st.fs)
    W = st.augmented(fv, fs, bal=cols).W  # [data, s0, o_j for j in left]
    q0 = gls(W[:2, :2])[2]
    best = None
    for c, j in enumerate(left):
        idx = [0, 1, 2 + c]
        th, cov, q1 = gls(W[np.ix_(idx, idx)])
        stat = max(q0 - q1, 0.0)
        if best is None or stat > best[0]:
            best = (stat, j, float(th[-1]), float(math.sqrt(max(cov[-1, -1], 0.0))))
    stat, j, off, se = best
    logp = chi2_logsf(stat, 1)
    a_n = alpha / n
    sig = bool(logp < math.log(a_n) and abs(off) > max(cell_z * se, min_offset))
    out.update(reading=j, chi2=stat, p=math.exp(logp), offset=off, std_error=se,
               alpha_per_reading=a_n, significant=sig, logp_family=logp + math.log(n))
    if sig:
        k = ev.bal[j]
        gi = int(np.clip(np.searchsorted(mo.grid.t, ev.t[k]), 0, mo.grid.t.size - 1))
        v = float(mo.v_ref[gi])
        out["entry"] = {"phase": "all", "where": [float(ev.y_d[k])] * 2,
                        "when": [float(ev.t[k]) / beta] * 2, "speed": [v, v], "size": off,
                        "family": "balise", "onset": False,
                        "mask": np.zeros(mo.grid.t.size, bool)}
    return out


def scatter_wins(sca: dict, best, round_tests: dict) -> bool:
    """Whether the balise readings' scatter explains a round's balise readings better than
    ``best``, the round's other finding about them (None: none): a balise's offset, the
    reader's latency or the datum. A variance and a mean are alternatives of different kinds,
    and their p-values under the null do not say which explains better; their likelihoods do,
    each parameter charged ln n over the n readings (BIC): the scatter's log-likelihood ratio
    ``lr`` against the other's chi-square, one parameter each. (A structure that a motion or
    the odometer family finds goes first, tested at the stated variance: on the few balise
    readings of a run the scatter's likelihood came within a few units of an odometer that
    counts differently from a time on, whose cells did not fit it exactly.)"""
    if best is None:
        return True
    pen = math.log(max(sca["readings"], 2))
    return sca["lr"] - pen > round_tests[best[1]]["chi2"] - pen


def reading_points(mo: Motion) -> np.ndarray:
    """The grid point at each balise reading (its time, clipped to the grid): where the
    reference speed and position of a reading are read."""
    return np.clip(np.searchsorted(mo.grid.t, mo.ev.t[mo.ev.bal]), 0, mo.grid.t.size - 1)


def origin_innovations(st: Stage, fv: np.ndarray, fs: np.ndarray):
    """(z, kf): the balise readings' whitened innovations under the model ``st`` with the drift
    ``fv``, ``fs``, the count's origin s0 at its GLS optimum, and the augmented filter
    ([data, s0]) they come from (its ``W`` and ``Z_bal[:, 1]``, the origin's column)."""
    kf = st.augmented(fv, fs, keep_innov=True)  # [data, s0]
    s0 = gls(kf.W)[0][0]
    return kf.Z_bal[:, 0] + s0 * kf.Z_bal[:, 1], kf


def scatter_round(mo: Motion, st: Stage, extra, inside: list, alpha: float) -> dict:
    """One round of the scatter test (module doc): whether the balise readings scatter about
    the odometer's track more than their stated variances say, under the model ``st`` (plus
    the found drift ``extra``; ``inside``: readings whose offset is in the model). Returns the
    figures (``ratio``: the sum of squares over its degrees of freedom, the variance scale),
    ``logp_family`` (the round's comparison) and, when significant, ``entry``."""
    ev = mo.ev
    n = ev.bal.size
    dof = n - 1 - len(inside)
    out = {"readings": int(n), "significant": False}
    if dof < 2:
        out["note"] = "fewer than three balise readings outside the model"
        return out
    # the whitened innovations at s0 (a reading whose offset is fitted is about 0: one
    # degree of freedom less each)
    z, _ = origin_innovations(st, *plus_drift(extra, st.fv, st.fs))
    q = float(np.sum(z * z))
    ratio = q / dof
    logp = chi2_logsf(q, dof)
    # 2 x the log-likelihood ratio of the variance scale at its best, ratio, against 1
    lr = q - dof - dof * math.log(ratio) if ratio > 1.0 else 0.0
    sig = bool(logp < math.log(alpha))
    out.update(chi2=q, dof=int(dof), ratio=ratio, p=math.exp(logp), significant=sig,
               logp_family=logp, lr=lr)
    if sig:
        v = mo.v_ref[reading_points(mo)]
        out["entry"] = {"phase": "all", "where": None, "when": None,
                        "speed": [float(np.percentile(v, 5)), float(np.percentile(v, 95))],
                        "size": math.sqrt(ratio), "family": "balise_scatter", "onset": False,
                        "readings": int(n), "p": out["p"],
                        "mask": np.zeros(mo.grid.t.size, bool)}
    return out


# m, half the span of the central difference that makes the datum test's column (the map's
# gradient changes are steps: a span of metres puts each on the 0.1 s grid at every speed)
DATUM_STEP = 5.0


def datum_columns(mo: Motion):
    """(Bv, Bs) at the events: the drift a shift of one metre of the map's gradients against the
    balises' placement adds (:func:`datum_round`), or None where the gradients do not change
    along the run."""
    g = mo.line.gradient_accel
    acc = -(g(mo.x_ref + DATUM_STEP) - g(mo.x_ref - DATUM_STEP)) / (2.0 * DATUM_STEP) \
        * mo.k_grad * mo.moving
    if not np.any(acc):
        return None
    bv, bs = mo.grid.integrate(acc[:, None], mo.ev.t.size)
    return bv[:, 0], bs[:, 0]


def datum_round(mo: Motion, st: Stage, extra, cols: tuple, alpha: float, cell_z: float,
                min_offset: float) -> dict:
    """One round of the datum test (module docstring): the drift column ``cols``
    (:func:`_datum_columns`) on top of the model ``st`` (plus the found drift ``extra``), 2 dll
    chi-square with one degree of freedom under the model; significant below ``alpha`` with
    the shift beyond ``cell_z`` SE and ``min_offset`` m (a balise's location accuracy).
    Returns the figures, ``logp_family`` and, when significant, ``entry``."""
    stat, th, se = fit_columns(st, cols[0][:, None], cols[1][:, None], extra)
    delta, se = float(th[-1]), float(se[-1])
    logp = chi2_logsf(stat, 1)
    sig = bool(logp < math.log(alpha) and abs(delta) > cell_z * se and abs(delta) > min_offset)
    out = {"chi2": stat, "p": math.exp(logp), "shift": delta, "std_error": se,
           "significant": sig, "logp_family": logp}
    if sig:
        v = mo.v_ref[mo.moving > 0]
        out["entry"] = {"phase": "all", "where": None, "when": None,
                        "speed": [float(np.percentile(v, 5)), float(np.percentile(v, 95))],
                        "size": delta, "family": "datum", "onset": False,
                        "mask": np.zeros(mo.grid.t.size, bool)}
    return out


def latency_round(mo: Motion, st: Stage, extra, alpha: float, cell_z: float,
                  min_offset: float) -> dict:
    """One round of the balise reader's latency test (module docstring): readings stamped
    ``tau`` after the train passed their balises (a reader that stamps when it has decoded the
    telegram, not when its antenna passed the balise) lie ``v_b tau`` behind the train:
    ``p_b = s0 + s(t_b) - v_b tau + e_b``.

    One balise measurement column, ``-v_b`` at each reading (the reference speed there), on top
    of the model ``st`` (plus the found drift ``extra``): 2 dll of adding it is chi-square with
    one degree of freedom under the model. Significant below ``alpha`` with ``tau`` beyond
    ``cell_z`` SE and the fastest reading moved by more than ``min_offset`` (m: a balise's
    location accuracy). No listed cause moves the readings by the speed they are read at: an
    odometer scale moves them by the distance run, a clock cause the odometer's stamps with
    the balises' (one train clock), a slip episode every reading after it. Returns the
    figures, ``logp_family`` and, when significant, ``entry`` (with ``moved``: what the
    latency adds to the balise measurement offsets, popped when it joins the model)."""
    ev = mo.ev
    n = ev.bal.size
    out = {"readings": int(n), "significant": False}
    if n < 3:
        out["note"] = "fewer than three balise readings"
        return out
    v = np.asarray(mo.v_ref, float)[reading_points(mo)]
    col = np.zeros((ev.t.size, 1))
    col[ev.bal, 0] = -v
    stat, th, se = fit_columns(st, None, None, extra, bal=col)
    tau, se = float(th[-1]), float(se[-1])
    logp = chi2_logsf(stat, 1)
    sig = bool(logp < math.log(alpha) and abs(tau) > cell_z * se
               and abs(tau) * float(v.max()) > min_offset)
    out.update(chi2=stat, p=math.exp(logp), latency=tau, std_error=se, significant=sig,
               logp_family=logp)
    if sig:
        out["entry"] = {"phase": "all", "where": None, "when": None,
                        "speed": [float(v.min()), float(v.max())], "size": tau,
                        "family": "balise_latency", "onset": False,
                        "mask": np.zeros(mo.grid.t.size, bool), "moved": col[:, 0] * tau}
    return out
