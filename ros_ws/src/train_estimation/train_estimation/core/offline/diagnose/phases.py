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

**The balise readings' tests** (a balise's offset, the reader's latency, the map's datum, the
readings' scatter) are in :mod:`.balise_rounds`; each competes in every round as the families
do.

The checks of a confirmed cause against the rest of the data (where it must show and where it
must not) are in :mod:`.contradict`.
"""

from __future__ import annotations

import copy
import math

import numpy as np

from train_estimation.core.numerics.tails import chi2_logsf

from .balise_rounds import (
    balise_round,
    datum_columns,
    datum_round,
    latency_round,
    origin_innovations,
    reading_points,
    scatter_round,
    scatter_wins,
)
from .motion import Motion
from .stage import Null, Stage, fit_columns, plus_drift

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


def structure(mo: Motion, null: Null, cfg, noise, beta: float = 1.0, alpha: float = 1e-3,
              cell_z: float = 3.0, min_accel: float = 0.01, max_entries: int = 3,
              min_offset: float = 2.0) -> tuple:
    """What the model ``null`` leaves in the data (module docstring): ([signature], [tests])
    with a signature {phase, where, when, speed, size} per entry and each round's figures.
    Every round tests the motion families, the odometer family and the balise readings
    (:mod:`.balise_rounds`), ``alpha`` shared among them all; the one with the smallest p-value
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
    datum = datum_columns(mo)  # the datum's column, None on a line without gradients
    for _ in range(max_entries):
        best = None
        round_tests = {}
        fits = {}  # family -> (log p, fitted extras, cells) of the significant ones
        for name in list(fam) + (["odometer"] if odo is not None else []):
            if name == "odometer":
                stat, th, se = fit_columns(st, None, None, extra, meas=odo[:2])
                floor = MIN_SCALE
            else:
                stat, th, se = fit_columns(st, *ig[name], extra)
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
            sca = scatter_round(mo, st, extra, bal_in, a_f)
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
        if scatter and sca["significant"] and not fits and scatter_wins(sca, best,
                                                                         round_tests):
            best = (sca["logp_family"], "balise_scatter", None, None)
        tests.append(round_tests)
        if best is None:
            break
        _, name, th, cells = best
        if name == "datum":
            # the gradients moved by the shift become part of the model; test again
            found.append(dat["entry"])
            extra = plus_drift(extra, *(c * dat["entry"]["size"] for c in datum))
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
        extra = plus_drift(extra, ig[name][0][:, cells] @ th[cells],
                           ig[name][1][:, cells] @ th[cells])
    return found, tests


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
    _, c, se = fit_columns(st, Bv, Bs, extra)
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


# the families of the structure test that model the balise readings or the count between them:
# with one of them found, the readings' residuals are that entry's, not tested again
READING_FAMILIES = ("balise", "balise_scatter", "balise_latency", "datum", "odometer")


def balise_residuals(mo: Motion, null: Null, cfg, noise, found: list,
                     alpha: float = 1e-3) -> dict:
    """The balise readings' residual checks (:func:`.residuals.balise_checks`, ``alpha`` the
    false-alarm rate of the three together) under the model ``null`` at ``noise``: their
    whitened innovations with the count's origin at its GLS value, and the covariance that
    fitting the origin leaves them. ``innovations`` keeps them ({z, c, info, speed,
    position}) for the fleet to pool over a train's runs (:mod:`..fleet_readers`), also when
    one run has too few to be tested."""
    from .residuals import balise_checks

    ev = mo.ev
    kinds = sorted({u.get("family") for u in found} & set(READING_FAMILIES))
    if kinds:
        return {"readings": int(ev.bal.size), "tested": False, "finding": False,
                "signature": None, "note": f"the readings' structure is an entry ({kinds[0]})"}
    if ev.bal.size == 0:
        return {"readings": 0, "tested": False, "finding": False, "signature": None,
                "note": "no balise reading places the run"}
    st = Stage(mo, null, cfg, noise=noise, big=False)
    z, kf = origin_innovations(st, st.fv, st.fs)
    c, info = kf.Z_bal[:, 1], float(kf.W[1, 1])
    if not info > 0:
        return {"readings": int(ev.bal.size), "tested": False, "finding": False,
                "signature": None, "note": "no balise reading places the run"}
    gi = reading_points(mo)
    v, x = np.asarray(mo.v_ref, float)[gi], np.asarray(mo.x_ref, float)[gi]
    out = balise_checks(z, np.eye(z.size) - np.outer(c, c) / info, v, x, alpha)
    # what a fleet pools over a train's passes (fleet_readers): a run has too few readings
    out["innovations"] = {"z": z.tolist(), "c": c.tolist(), "info": info,
                          "speed": v.tolist(), "position": x.tolist()}
    return out
