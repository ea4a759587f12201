"""Where the residuals of a model hold structure: by phase, speed, position, time and around
command onsets.

Phases, on the time grid of the motion model (commands through the believed actuator):
``traction`` (traction part > ``PHASE_ACCEL``), ``braking`` (braking part < -``PHASE_ACCEL``),
``coasting`` (moving, neither) and ``standstill`` (not modelled: the filter follows the data).

**Structure test** (:func:`structure`). Against the model of the confirmed causes, a flexible
alternative adds free extra accelerations on cells of one *family* of partitions of the run:

- ``phase``: one constant per phase;
- ``speed``: per phase and quarter of the top speed;
- ``position``: per track bin (200 m or 1/20 of the run's span, the larger);
- ``time``: per 60 s of the run;
- ``onset``: the first ``ONSET`` s after every traction and every braking onset.

Each family is a likelihood ratio 2 (ll_alt - ll_model) against chi-square with one degree of
freedom per cell (exact Gaussian likelihood of the augmented filter at the model's noise):
structure when its p-value is below ``alpha`` / (number of families) (Bonferroni), and a cell
carries it when its extra acceleration is more than ``cell_z`` standard errors and more than
``min_accel`` from zero. The strongest family (smallest p-value) gives one ``unexplained``
entry; its cells are then put into the model and the families tested again (at most
``max_entries``). The entry's phase is named only where the data show the pattern absent
from the other phases (per-phase families; a place or time cell run in one phase only
gives ``all``, unless a per-phase family significant in the same round finds its remainder
in that phase alone). Families are ordered by log p-values that stay finite far into the
tail (:func:`~train_estimation.core.numerics.tails.chi2_logsf`): strong families all have a
p-value of 0 in floating point.

**Odometer family** (:func:`odometer_family`). An odometer that counts differently from a
time on (moved to an axle with other wheels, a wheel re-profiled, a changed calibration) is
no acceleration: its speed readings jump by the change at once and its distance drifts from
the balises after it. Beside the motion families, one more family gives the odometer a free
scale change per 60 s of the run (the counted distance inside the cell x (1 + c_j), carried
on after it, and the speed read inside it x (1 + c_j)), the same likelihood ratio and
Bonferroni share; a cell carries it beyond ``cell_z`` SE and ``MIN_SCALE``. Its entry has
phase ``all``, ``where`` and ``when`` the span of its cells, and ``size`` the odometer error
in m it makes there (the largest distance the changed count puts between the odometer and
the train).

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

The checks of a confirmed cause against the rest of the data (where it must show and where it
must not) are in :mod:`.contradict`.
"""

from __future__ import annotations

import copy
import math

import numpy as np

from train_estimation.core.numerics.augmented_kf import gls
from train_estimation.core.numerics.tails import chi2_logsf

from .motion import Motion
from .stage import Null, Stage

PHASES = ("traction", "coasting", "braking")
PER_PHASE = ("phase", "speed", "onset")  # the families whose cells are per phase
PHASE_ACCEL = 0.02  # m/s^2, a command part above this sets the phase
ONSET = 4.0  # s, window after a command onset
MIN_CELL_TIME = 5.0  # s, cells with less moving time are dropped
# -, an odometer family cell's scale change below this is no finding: a wheel's wear between
# calibrations (the odometer_scale cause's resolution)
MIN_SCALE = 1e-3


def grid_phase(mo: Motion) -> np.ndarray:
    """Phase index per grid point: 0 traction, 1 coasting, 2 braking, -1 standstill."""
    moving = mo.moving > 0
    ph = np.where(moving, 1, -1)
    ph[moving & (mo.a_tr0 > PHASE_ACCEL)] = 0
    ph[moving & (mo.a_br0 < -PHASE_ACCEL)] = 2
    return ph


def _event_grid_index(mo: Motion) -> np.ndarray:
    """The grid point of the interval that ends at each event."""
    return np.clip(np.searchsorted(mo.grid.t, mo.ev.t) - 1, 0, mo.grid.t.size - 1)


def _bins(lo: float, hi: float, width: float) -> np.ndarray:
    n = max(1, int(math.ceil((hi - lo) / width - 1e-9)))
    return lo + (hi - lo) / n * np.arange(n + 1)


def families(mo: Motion, beta: float = 1.0) -> dict:
    """name -> (R (n_grid, k) indicator columns, [cell label]) of the structure test; a label
    holds ``phase``, ``where``, ``when`` (stamp clock: / beta) and ``speed``."""
    g, v, x = mo.grid, mo.v_ref, mo.x_ref
    ph = grid_phase(mo)
    mov = ph >= 0
    if not mov.any():
        return {}
    vmax = float(v[mov].max())
    out = {}
    cells = [((ph == p), {"phase": PHASES[p]}) for p in range(3)]
    out["phase"] = cells
    edges = np.linspace(0.0, vmax * (1 + 1e-9), 5)
    out["speed"] = [((ph == p) & (v >= a) & (v < b), {"phase": PHASES[p], "speed": [a, b]})
                    for p in range(3) for a, b in zip(edges[:-1], edges[1:])]
    lo, hi = float(x[mov].min()), float(x[mov].max())
    xe = _bins(lo, hi, max(200.0, (hi - lo) / 20.0))
    out["position"] = [(mov & (x >= a) & (x < b), {"phase": "all", "where": [a, b]})
                       for a, b in zip(xe[:-1], xe[1:])]
    t_mov = g.t[mov]
    te = _bins(float(t_mov[0]), float(t_mov[-1]) + 1e-6, 60.0)
    out["time"] = [(mov & (g.t >= a) & (g.t < b), {"phase": "all", "when": [a / beta, b / beta]})
                   for a, b in zip(te[:-1], te[1:])]
    onset = []
    for p, part in ((0, mo.a_tr0 > PHASE_ACCEL), (2, mo.a_br0 < -PHASE_ACCEL)):
        starts = g.t[1:][part[1:] & ~part[:-1]]
        win = np.zeros(g.t.size, bool)
        for t0 in starts:
            win |= (g.t >= t0) & (g.t < t0 + ONSET)
        onset.append((mov & win, {"phase": PHASES[p], "onset": True}))
    out["onset"] = onset
    keep = {}
    for name, cl in out.items():
        cl = [(m, lab) for m, lab in cl if m.sum() * g.dt >= MIN_CELL_TIME]
        if cl:
            keep[name] = (np.stack([m.astype(float) for m, _ in cl], axis=1),
                          [lab for _, lab in cl])
    return keep


def odometer_family(mo: Motion, beta: float = 1.0):
    """The odometer family of the module docstring: (Md, Mv) measurement columns (n_events, k),
    one per 60 s of the moving run with at least ``MIN_CELL_TIME`` s of motion, their labels
    (``when``, stamp clock: / beta) and grid masks; None when fewer than two cells."""
    g, ev = mo.grid, mo.ev
    mov = mo.moving > 0
    if not mov.any():
        return None
    o = ev.odo
    inc = np.zeros(ev.t.size)
    inc[o] = np.diff(mo.sc_d[o], prepend=mo.sc_d[o][0])
    t_mov = g.t[mov]
    te = _bins(float(t_mov[0]), float(t_mov[-1]) + 1e-6, 60.0)
    cells, labels, masks = [], [], []
    for a, b in zip(te[:-1], te[1:]):
        on_g = mov & (g.t >= a) & (g.t < b)
        if on_g.sum() * g.dt < MIN_CELL_TIME:
            continue
        cells.append((ev.t >= a) & (ev.t < b))
        labels.append({"phase": "all", "when": [a / beta, b / beta]})
        masks.append(on_g)
    if len(cells) < 2:
        return None
    return (counted_columns(mo, inc, cells), np.stack([mo.sc_v * m for m in cells], axis=1),
            labels, np.stack(masks, axis=1))


def counted_columns(mo: Motion, inc: np.ndarray, cells: list) -> np.ndarray:
    """Odometer distance columns (n_events, len(cells)): the distance increments ``inc`` (m
    per odometer event) inside each cell (an event mask), counted on after it, at the odometer
    events (0 elsewhere): what the odometer's count gains from a change of 1 inside the cell."""
    is_odo = np.zeros(inc.size, bool)
    is_odo[mo.ev.odo] = True
    return np.stack([np.where(is_odo, np.cumsum(inc * m), 0.0) for m in cells], axis=1)


def _fit_columns(st: Stage, Bv: np.ndarray | None, Bs: np.ndarray | None, extra=None,
                 meas=None, bal=None):
    """GLS of free drift columns (Bv, Bs), or with Bv, Bs None of free odometer measurement
    columns ``meas`` = (Md, Mv) or balise measurement columns ``bal``, on top of the stage's
    model (plus fixed extra drift): (chi-square statistic 2 dll, theta, se)."""
    fv, fs = st.fv, st.fs
    if extra is not None:
        fv, fs = fv + extra[0], fs + extra[1]
    kf = st.augmented(fv, fs, drift=None if Bv is None else (Bv, Bs), meas=meas, bal=bal)
    q0 = gls(kf.W[:2, :2])[2]
    th, cov, q1 = gls(kf.W)
    se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    return max(q0 - q1, 0.0), th[1:], se[1:]


def structure(mo: Motion, null: Null, cfg, noise, beta: float = 1.0, alpha: float = 1e-3,
              cell_z: float = 3.0, min_accel: float = 0.01, max_entries: int = 3,
              min_offset: float = 2.0) -> tuple:
    """What the model ``null`` leaves in the data (module docstring): ([signature], [tests])
    with a signature {phase, where, when, speed, size} per entry and each round's figures.
    Every round tests the motion families, the odometer family and the balise readings
    (:func:`balise_round`), ``alpha`` shared among them all; the one with the smallest p-value
    (a balise's times the readings tested: Bonferroni) becomes an entry and part of the model,
    and the next round tests what is left. A balise offset and an odometer that counts
    differently both move the balise readings: in one round, the data say which fits."""
    fam = families(mo, beta)
    odo = odometer_family(mo, beta)
    st = Stage(mo, null, cfg, noise=noise, big=False)
    n_ev = mo.ev.t.size
    ig = {k: mo.grid.integrate(R, n_ev) for k, (R, _) in fam.items()}
    # Bonferroni over the families, the balise readings' tests (one reading, their scatter),
    # the latency's and the datum's
    a_f = alpha / (len(fam) + 4 + (odo is not None))
    extra = None
    found, tests, bal_in = [], [], []
    late = True  # the latency is still to be tested (one entry at most)
    scatter = True  # the balise readings' scatter is still to be tested (one entry at most)
    datum = _datum_columns(mo)  # the datum's column, None on a line without gradients
    for _ in range(max_entries):
        best = None
        round_tests = {}
        fits = {}  # family -> (log p, fitted extras, cells) of the significant ones
        for name in list(fam) + (["odometer"] if odo is not None else []):
            if name == "odometer":
                stat, th, se = _fit_columns(st, None, None, extra, meas=odo[:2])
                floor = MIN_SCALE
            else:
                stat, th, se = _fit_columns(st, *ig[name], extra)
                floor = min_accel
            k = th.size
            logp = chi2_logsf(stat, k)
            cells = [j for j in range(k) if abs(th[j]) > max(cell_z * se[j], floor)]
            round_tests[name] = {"chi2": stat, "dof": k, "p": math.exp(logp),
                                 "significant": bool(logp < math.log(a_f) and cells)}
            if round_tests[name]["significant"]:
                fits[name] = (logp, th, cells)
                if best is None or logp < best[0]:
                    best = (logp, name, th, cells)
        bal = balise_round(mo, st, extra, bal_in, a_f, cell_z, min_offset, beta)
        round_tests["balise"] = {k: v for k, v in bal.items() if k != "entry"}
        if bal["significant"] and (best is None or bal["logp_family"] < best[0]):
            best = (bal["logp_family"], "balise", None, None)
        if scatter:
            sca = scatter_round(mo, st, extra, bal_in, a_f, beta)
            round_tests["balise_scatter"] = {k: v for k, v in sca.items() if k != "entry"}
        if late:
            lat = latency_round(mo, st, extra, a_f, cell_z, min_offset)
            round_tests["balise_latency"] = {k: v for k, v in lat.items() if k != "entry"}
            if lat["significant"] and (best is None or lat["logp_family"] < best[0]):
                best = (lat["logp_family"], "balise_latency", None, None)
        if datum is not None:
            dat = datum_round(mo, st, extra, datum, a_f, cell_z, min_offset)
            round_tests["datum"] = {k: v for k, v in dat.items() if k != "entry"}
            if dat["significant"] and (best is None or dat["logp_family"] < best[0]):
                best = (dat["logp_family"], "datum", None, None)
        if scatter and sca["significant"] and not fits and _scatter_wins(sca, best,
                                                                         round_tests):
            best = (sca["logp_family"], "balise_scatter", None, None)
        tests.append(round_tests)
        if best is None:
            break
        _, name, th, cells = best
        if name == "datum":
            # the gradients moved by the shift become part of the model; test again
            found.append(dat["entry"])
            extra = _plus(extra, *(c * dat["entry"]["size"] for c in datum))
            datum = None  # one datum shift
            continue
        if name == "balise_scatter":
            # every reading's variance scaled by the scatter found; test again at it
            found.append(sca["entry"])
            scatter = False
            st = copy.copy(st)
            st.bal_scale *= sca["ratio"]
            continue
        if name == "balise_latency":
            # the readings moved by the latency become part of the model; test again
            found.append(lat["entry"])
            late = False
            st = copy.copy(st)
            st.mb = st.mb + lat["entry"].pop("moved")
            continue
        if name == "balise":
            # the reading's offset becomes part of the model; test again
            found.append(bal["entry"])
            bal_in.append(bal["reading"])
            st = copy.copy(st)
            st.mb = st.mb.copy()
            st.mb[mo.ev.bal[bal["reading"]]] += bal["offset"]
            continue
        if name == "odometer":
            # the changed count becomes part of the measurement model; test again
            add_d, add_m = odo[0][:, cells] @ th[cells], odo[1][:, cells] @ th[cells]
            found.append(_odometer_signature(mo, odo, th, cells, add_d))
            found[-1]["meas"] = (add_d, add_m)
            st = copy.copy(st)
            st.md, st.mv = st.md + add_d, st.mv + add_m
            odo = None  # one odometer entry: its cells hold the change wherever it is
            continue
        R, labels = fam[name]
        pattern = R[:, cells] @ th[cells]
        phase, c = _attribute_phase(mo, st, pattern, extra, cell_z,
                                    by_phase=name in PER_PHASE)
        round_tests[name]["phase_multipliers"] = c
        lone = _lone_phase(mo, pattern)
        if phase == "all" and lone is not None:
            # a place or time remainder run in one phase only: that phase is named when a
            # family that tests every phase, significant in the same round, finds the
            # remainder in that phase and absent from the others
            for other in sorted((f for f in fits if f in PER_PHASE), key=lambda f: fits[f][0]):
                _, th2, cells2 = fits[other]
                R2 = fam[other][0]
                p2, _ = _attribute_phase(mo, st, R2[:, cells2] @ th2[cells2], extra, cell_z)
                if p2 == lone:
                    phase = lone
                    round_tests[name]["phase_from"] = other
                    break
        found.append(_signature(mo, name, R, labels, th, cells, phase))
        # the cells found become part of the model; test again for what is left
        extra = _plus(extra, ig[name][0][:, cells] @ th[cells], ig[name][1][:, cells] @ th[cells])
    return found, tests


def _plus(extra, add_v: np.ndarray, add_s: np.ndarray) -> tuple:
    """The found drift ``extra`` ((Bv, Bs) at the events, or None) with (``add_v``, ``add_s``)
    added: what an entry of the structure test puts into the model the next round tests."""
    return (add_v, add_s) if extra is None else (extra[0] + add_v, extra[1] + add_s)


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
    fv, fs = (st.fv, st.fs) if extra is None else (st.fv + extra[0], st.fs + extra[1])
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


def _scatter_wins(sca: dict, best, round_tests: dict) -> bool:
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


def scatter_round(mo: Motion, st: Stage, extra, inside: list, alpha: float,
                  beta: float = 1.0) -> dict:
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
    fv, fs = (st.fv, st.fs) if extra is None else (st.fv + extra[0], st.fs + extra[1])
    kf = st.augmented(fv, fs, keep_innov=True)  # [data, s0]
    th = gls(kf.W)[0]  # [s0] at the GLS optimum
    # the whitened innovations at s0 (a reading whose offset is fitted is about 0: one
    # degree of freedom less each)
    z = kf.Z_bal[:, 0] + th[0] * kf.Z_bal[:, 1]
    q = float(np.sum(z * z))
    ratio = q / dof
    logp = chi2_logsf(q, dof)
    # 2 x the log-likelihood ratio of the variance scale at its best, ratio, against 1
    lr = q - dof - dof * math.log(ratio) if ratio > 1.0 else 0.0
    sig = bool(logp < math.log(alpha))
    out.update(chi2=q, dof=int(dof), ratio=ratio, p=math.exp(logp), significant=sig,
               logp_family=logp, lr=lr)
    if sig:
        t = ev.t[ev.bal]
        gi = np.clip(np.searchsorted(mo.grid.t, t), 0, mo.grid.t.size - 1)
        v = mo.v_ref[gi]
        out["entry"] = {"phase": "all", "where": None, "when": None,
                        "speed": [float(np.percentile(v, 5)), float(np.percentile(v, 95))],
                        "size": math.sqrt(ratio), "family": "balise_scatter", "onset": False,
                        "readings": int(n), "p": out["p"],
                        "mask": np.zeros(mo.grid.t.size, bool)}
    return out


# m, half the span of the central difference that makes the datum test's column (the map's
# gradient changes are steps: a span of metres puts each on the 0.1 s grid at every speed)
DATUM_STEP = 5.0


def _datum_columns(mo: Motion):
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
    stat, th, se = _fit_columns(st, cols[0][:, None], cols[1][:, None], extra)
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
    gi = np.clip(np.searchsorted(mo.grid.t, ev.t[ev.bal]), 0, mo.grid.t.size - 1)
    v = np.asarray(mo.v_ref, float)[gi]
    col = np.zeros((ev.t.size, 1))
    col[ev.bal, 0] = -v
    stat, th, se = _fit_columns(st, None, None, extra, bal=col)
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


def _attribute_phase(mo: Motion, st: Stage, pattern: np.ndarray, extra, cell_z: float,
                     by_phase: bool = True):
    """The phase a found pattern (extra acceleration on the grid) belongs to: the pattern
    restricted to each phase gets a free multiplier; the phases where it is needed (more than
    half of itself, beyond ``cell_z`` SE) name it, one phase or ``all``. A phase is named only
    where the data show the pattern absent from the others: a family of cells per phase
    (``by_phase``) tests every phase; a place or time cell run in one phase only does not,
    and its pattern is ``all``."""
    R = _by_phase(mo, pattern)
    live = _live(R)
    if not live or (len(live) == 1 and not by_phase):
        return "all", {}
    Bv, Bs = mo.grid.integrate(R[:, live], mo.ev.t.size)
    _, c, se = _fit_columns(st, Bv, Bs, extra)
    mult = {PHASES[p]: float(cj) for p, cj in zip(live, c)}
    need = [PHASES[p] for p, cj, sj in zip(live, c, se) if cj > 0.5 and cj > cell_z * sj]
    return (need[0] if len(need) == 1 else "all"), mult


def _by_phase(mo: Motion, pattern: np.ndarray) -> np.ndarray:
    """(n_grid, 3): ``pattern`` restricted to each phase (traction, coasting, braking)."""
    ph = grid_phase(mo)
    return np.stack([pattern * (ph == p) for p in range(3)], axis=1)


def _live(R: np.ndarray) -> list[int]:
    """The phases (indices) where a pattern split by :func:`_by_phase` is not zero."""
    return [p for p in range(3) if np.any(R[:, p] != 0)]


def _lone_phase(mo: Motion, pattern: np.ndarray) -> str | None:
    """The phase a pattern lives in when it lives in one only, else None."""
    live = _live(_by_phase(mo, pattern))
    return PHASES[live[0]] if len(live) == 1 else None


def _odometer_signature(mo: Motion, odo, th, cells, add_d) -> dict:
    """The ``unexplained`` entry of the odometer family's significant ``cells``: ``where`` and
    ``when`` their span, ``size`` the largest odometer error (m) the changed count makes
    (``add_d``: what it adds to the counted distance at each event)."""
    _, _, labels, masks = odo
    on = masks[:, cells].any(axis=1)
    v, x = mo.v_ref[on], mo.x_ref[on]
    size = float(add_d[np.argmax(np.abs(add_d))])
    return {"phase": "all", "where": [float(x.min()), float(x.max())],
            "when": [min(labels[j]["when"][0] for j in cells),
                     max(labels[j]["when"][1] for j in cells)],
            "speed": [float(np.percentile(v, 5)), float(np.percentile(v, 95))],
            "size": size, "family": "odometer", "onset": False, "mask": on,
            "scale_changes": [[labels[j]["when"][0], labels[j]["when"][1], float(th[j])]
                              for j in cells]}


def _signature(mo: Motion, family: str, R, labels, th, cells, phase: str) -> dict:
    """One ``unexplained`` entry from the significant cells of a family (``mask``: the grid
    points it covers)."""
    on = (R[:, cells] > 0).any(axis=1)
    if phase in PHASES:
        on &= grid_phase(mo) == PHASES.index(phase)
    v = mo.v_ref[on]
    where = when = None
    if family == "position":
        where = [min(labels[j]["where"][0] for j in cells),
                 max(labels[j]["where"][1] for j in cells)]
    if family == "time":
        when = [min(labels[j]["when"][0] for j in cells),
                max(labels[j]["when"][1] for j in cells)]
    size = float(th[cells][np.argmax(np.abs(th[cells]))])
    return {"phase": phase, "where": where, "when": when,
            "speed": [float(np.percentile(v, 5)), float(np.percentile(v, 95))] if v.size
            else None, "size": size, "family": family,
            "onset": any(labels[j].get("onset") for j in cells), "mask": on}


def sensor_residuals(mo: Motion, null: Null, cfg, noise, alpha: float = 1e-3) -> dict:
    """The odometer's residual checks (:func:`.residuals.sensor_checks`, ``alpha`` the
    false-alarm rate of the four together) under the model ``null`` at ``noise``: its speed
    readings with their stated variances, less the model's speed."""
    from .residuals import sensor_checks

    st = Stage(mo, null, cfg, noise=noise, big=False)
    o = mo.ev.odo
    # the model's speed (its velocity increments summed; a constant per stretch is the
    # spline's) with what it adds to the readings (a scale, slip episodes), and a new stretch
    # after every interval it does not model (a standstill)
    held = np.cumsum(mo.ev.held)[o]
    cut = np.r_[False, np.diff(held) > 0]
    r = mo.run
    raw = (r.odo_t, r.odo_d, r.odo_v, np.interp(r.odo_t, mo.grid.t, mo.v_ref))
    return sensor_checks(mo.ev.t[o], mo.ev.y_v[o], mo.ev.r_v[o], mo.sc_v[o], mo.sc_d[o],
                         alpha, base=np.cumsum(st.fv)[o] + st.mv[o], cut=cut, raw=raw,
                         min_speed=cfg.standstill_speed)
