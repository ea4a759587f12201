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
gives ``all``).

**Balise test** (:func:`balise_test`). The motion families cannot see a balise that lies
elsewhere than the map says: the odometer carries the position from one balise to the next,
so one reading off by metres moves no acceleration. Each reading gets a free offset of its
own; the largest that is significant (Bonferroni over the readings, within the same
``alpha``) and more than ``min_offset`` m is an entry (phase ``all``, ``where`` the balise's
map position, ``size`` the offset in m), and the rest are tested again.

The checks of a confirmed cause against the rest of the data (where it must show and where it
must not) are in :mod:`.contradict`.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.stats import chi2

from train_estimation.core.numerics.augmented_kf import gls

from .motion import Motion
from .stage import Null, Stage

PHASES = ("traction", "coasting", "braking")
PHASE_ACCEL = 0.02  # m/s^2, a command part above this sets the phase
ONSET = 4.0  # s, window after a command onset
MIN_CELL_TIME = 5.0  # s, cells with less moving time are dropped


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


def _fit_columns(st: Stage, Bv: np.ndarray | None, Bs: np.ndarray | None, extra=None,
                 meas=None):
    """GLS of free drift columns (Bv, Bs), or with Bv, Bs None of free odometer measurement
    columns ``meas`` = (Md, Mv), on top of the stage's model (plus fixed extra drift):
    (chi-square statistic 2 dll, theta, se)."""
    fv, fs = st.fv, st.fs
    if extra is not None:
        fv, fs = fv + extra[0], fs + extra[1]
    kf = st.augmented(fv, fs, drift=None if Bv is None else (Bv, Bs), meas=meas)
    q0 = gls(kf.W[:2, :2])[2]
    th, cov, q1 = gls(kf.W)
    se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    return max(q0 - q1, 0.0), th[1:], se[1:]


def structure(mo: Motion, null: Null, cfg, noise, beta: float = 1.0, alpha: float = 1e-3,
              cell_z: float = 3.0, min_accel: float = 0.01, max_entries: int = 3,
              min_offset: float = 2.0) -> tuple:
    """What the model ``null`` leaves in the data (module docstring): ([signature], [tests])
    with a signature {phase, where, when, speed, size} per entry and the tests' figures. The
    motion families first, then the balise readings (:func:`balise_test`), ``alpha`` shared
    among them all."""
    fam = families(mo, beta)
    st = Stage(mo, null, cfg, noise=noise, big=False)
    n_ev = mo.ev.t.size
    ig = {k: mo.grid.integrate(R, n_ev) for k, (R, _) in fam.items()}
    a_f = alpha / (len(fam) + 1)
    extra = None
    found, tests = [], []
    for _ in range(max_entries):
        best = None
        round_tests = {}
        for name in fam:
            stat, th, se = _fit_columns(st, *ig[name], extra)
            k = th.size
            logp = float(chi2.logsf(stat, k))
            cells = [j for j in range(k) if abs(th[j]) > max(cell_z * se[j], min_accel)]
            round_tests[name] = {"chi2": stat, "dof": k, "p": math.exp(logp),
                                 "significant": bool(logp < math.log(a_f) and cells)}
            if round_tests[name]["significant"] and (best is None or logp < best[0]):
                best = (logp, name, th, cells)
        tests.append(round_tests)
        if best is None:
            break
        _, name, th, cells = best
        R, labels = fam[name]
        phase, c = _attribute_phase(mo, st, R[:, cells] @ th[cells], extra, cell_z,
                                    by_phase=name in ("phase", "speed", "onset"))
        round_tests[name]["phase_multipliers"] = c
        found.append(_signature(mo, name, R, labels, th, cells, phase))
        # the cells found become part of the model; test again for what is left
        add_v = ig[name][0][:, cells] @ th[cells]
        add_s = ig[name][1][:, cells] @ th[cells]
        extra = (add_v, add_s) if extra is None else (extra[0] + add_v, extra[1] + add_s)
    bal, bal_test = balise_test(mo, st, extra, a_f, cell_z, min_offset,
                                max_entries - len(found), beta)
    tests.append({"balise": bal_test})
    return found + bal, tests


def balise_test(mo: Motion, st: Stage, extra, alpha: float, cell_z: float, min_offset: float,
                max_entries: int, beta: float = 1.0) -> tuple:
    """Balise readings that the odometer does not continue (a balise lying elsewhere than the
    map and its telegram say, a reading of another balise): ([signature], figures).

    Every reading j gets a free offset of its own (a balise measurement column that is 1 at
    that reading: p_b = s0 + s(t_b) + o_j + e_b) on top of the model ``st`` (plus the found
    drift ``extra``). For each reading not yet in the model, 2 dll of adding its offset is
    chi-square with one degree of freedom under the model; the largest, below ``alpha`` / n
    (Bonferroni over the n readings) with the offset beyond ``cell_z`` SE and ``min_offset``
    (m: a balise's location accuracy is metres; a misstated reading variance must not make a
    finding of less), is an entry; its offset is put into the model and the rest tested again.
    No listed cause moves one reading: an odometer scale grows with distance, a slip episode
    shifts every reading after it, a clock or link cause moves none. An entry's ``size`` is the
    offset in m (the reading's position minus the train's position by the odometer there),
    ``where`` the balise's map position, ``when`` the reading's time (stamp clock)."""
    ev = mo.ev
    n = ev.bal.size
    if n < 3 or max_entries <= 0:
        return [], {"readings": int(n), "note": "fewer than three balise readings"
                    if n < 3 else "no entries left"}
    cols = np.zeros((ev.t.size, n))
    cols[ev.bal, np.arange(n)] = 1.0
    fv, fs = (st.fv, st.fs) if extra is None else (st.fv + extra[0], st.fs + extra[1])
    W = st.augmented(fv, fs, bal=cols).W  # [data, s0, o_1 .. o_n]
    a_n = alpha / n
    inside, found = [], []
    out = {"readings": int(n), "alpha_per_reading": a_n, "rounds": []}
    for _ in range(max_entries):
        base = [0, 1] + [2 + j for j in inside]
        q0 = gls(W[np.ix_(base, base)])[2]
        best = None
        for j in range(n):
            if j in inside:
                continue
            idx = base + [2 + j]
            th, cov, q1 = gls(W[np.ix_(idx, idx)])
            stat = max(q0 - q1, 0.0)
            if best is None or stat > best[0]:
                best = (stat, j, float(th[-1]), float(math.sqrt(max(cov[-1, -1], 0.0))))
        if best is None:
            break
        stat, j, off, se = best
        logp = float(chi2.logsf(stat, 1))
        sig = bool(logp < math.log(a_n) and abs(off) > max(cell_z * se, min_offset))
        out["rounds"].append({"reading": j, "chi2": stat, "p": math.exp(logp), "offset": off,
                              "std_error": se, "significant": sig})
        if not sig:
            break
        inside.append(j)
        k = ev.bal[j]
        gi = int(np.clip(np.searchsorted(mo.grid.t, ev.t[k]), 0, mo.grid.t.size - 1))
        v = float(mo.v_ref[gi])
        found.append({"phase": "all", "where": [float(ev.y_d[k])] * 2,
                      "when": [float(ev.t[k]) / beta] * 2, "speed": [v, v], "size": off,
                      "family": "balise", "onset": False,
                      "mask": np.zeros(mo.grid.t.size, bool)})
    return found, out


def _attribute_phase(mo: Motion, st: Stage, pattern: np.ndarray, extra, cell_z: float,
                     by_phase: bool = True):
    """The phase a found pattern (extra acceleration on the grid) belongs to: the pattern
    restricted to each phase gets a free multiplier; the phases where it is needed (more than
    half of itself, beyond ``cell_z`` SE) name it, one phase or ``all``. A phase is named only
    where the data show the pattern absent from the others: a family of cells per phase
    (``by_phase``) tests every phase; a place or time cell run in one phase only does not,
    and its pattern is ``all``."""
    ph = grid_phase(mo)
    R = np.stack([pattern * (ph == p) for p in range(3)], axis=1)
    live = [p for p in range(3) if np.any(R[:, p] != 0)]
    if not live or (len(live) == 1 and not by_phase):
        return "all", {}
    Bv, Bs = mo.grid.integrate(R[:, live], mo.ev.t.size)
    _, c, se = _fit_columns(st, Bv, Bs, extra)
    mult = {PHASES[p]: float(cj) for p, cj in zip(live, c)}
    need = [PHASES[p] for p, cj, sj in zip(live, c, se) if cj > 0.5 and cj > cell_z * sj]
    return (need[0] if len(need) == 1 else "all"), mult


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
