"""Where the residuals of a model hold structure: by phase, speed, position, time and around
command onsets; and whether a fitted cause shows where it predicts it shows.

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

**Split test** (:func:`split_test`). A confirmed cause's contribution d (its drift columns:
the model with it minus the model without it) is split into cells (phase x speed tercile,
quarters of its position range, quarters of its time range), each with a free multiplier
1 + c_j. If the cause is right, every c_j is 0 within noise; a chi-square test per partition at
``alpha`` with some |c_j| > ``min_share`` (more than 3 standard errors) says the cause does not
show where it predicts (a braking-rate change that only shows at low speed, a mass change that
shows in traction but not in braking).

**A piece of a larger structure** (:func:`piece_of`). A confirmed cause whose contribution lies
mostly (> half of its energy) inside a structure still found in the residuals, while that
structure lies mostly outside the cause's own support, is one instance of something that
recurs where the cause does not act (a gradient section on one braking approach while every
braking approach shows the same weaker braking at low speed). Likewise a structure lying
mostly where the cause acts with more than half the cause's own acceleration there: the
cause does not describe what acts there.

**Place test** (:func:`place_test`). A cause fitted on a stretch, continued beyond it in the
same phases and speed halves with a free multiplier per cell, must not be needed there.

**Flexible rival** (:func:`flexible_rival`). A cause confirmed with others must explain the
data better (BIC) than free accelerations per phase x speed quarter where it acts.

**Causes that cancel** (:func:`cancelling`). Two confirmed causes whose contributions are
each large in a phase (> 1/4 of their own energy there) while their sum there is small (< 1/4
of the larger) act together as one effect confined to the other phases (a heavier train and a
stronger brake: traction alone is weaker). No listed cause is that effect.
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
# s, a cell of the place test holds at least this much time outside the stretch (a stop's last
# few m/s of braking last a few seconds; the cell's standard error states what it can test)
PLACE_MIN_TIME = 1.0
# a cell tests a cause's prediction when a departure of min_share of it there would be a
# Z_SEEN-standard-error result (a two-sided 0.3 % chance under the cause)
Z_SEEN = 3.0


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


def _fit_columns(st: Stage, Bv: np.ndarray, Bs: np.ndarray, extra=None):
    """GLS of free drift columns (Bv, Bs) on top of the stage's model (plus fixed extra
    drift): (chi-square statistic 2 dll, theta, se)."""
    fv, fs = st.fv, st.fs
    if extra is not None:
        fv, fs = fv + extra[0], fs + extra[1]
    kf = st.augmented(fv, fs, drift=(Bv, Bs))
    q0 = gls(kf.W[:2, :2])[2]
    th, cov, q1 = gls(kf.W)
    se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    return max(q0 - q1, 0.0), th[1:], se[1:]


def structure(mo: Motion, null: Null, cfg, noise, beta: float = 1.0, alpha: float = 1e-3,
              cell_z: float = 3.0, min_accel: float = 0.01, max_entries: int = 3) -> tuple:
    """What the model ``null`` leaves in the data (module docstring): ([signature], [tests])
    with a signature {phase, where, when, speed, size} per entry and the tests' figures."""
    fam = families(mo, beta)
    st = Stage(mo, null, cfg, noise=noise, big=False)
    n_ev = mo.ev.t.size
    ig = {k: mo.grid.integrate(R, n_ev) for k, (R, _) in fam.items()}
    a_f = alpha / max(len(fam), 1)
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
    return found, tests


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


def split_test(mo: Motion, others: Null, full: Null, cfg, noise, alpha: float,
               min_share: float) -> dict:
    """The split test of the module docstring for the cause that makes ``others`` into
    ``full``: {"contradicted", "why", per-partition figures}."""
    st0 = Stage(mo, others, cfg, noise=noise, big=False)
    st1 = Stage(mo, full, cfg, noise=noise, big=False)
    dv, ds = st1.fv - st0.fv, st1.fs - st0.fs
    energy = dv * dv
    if not energy.sum() > 0:
        return {"contradicted": False, "note": "no drift part to split"}
    gi = _event_grid_index(mo)
    ph = grid_phase(mo)[gi]
    v, x, t = mo.v_ref[gi], mo.x_ref[gi], mo.ev.t
    on = energy > 1e-6 * energy.max()
    out = {"contradicted": False}
    bad = []
    for part, cells in _partitions(ph, v, x, t, on).items():
        cols = [(m, lab) for m, lab in cells if energy[m].sum() > 0.02 * energy.sum()]
        if len(cols) < 2 and part != "phase":
            continue
        Bv = np.stack([dv * m for m, _ in cols], axis=1)
        Bs = np.stack([ds * m for m, _ in cols], axis=1)
        stat, c, se = _fit_columns(st1, Bv, Bs)
        p = float(chi2.sf(stat, len(cols)))
        out[part] = {"chi2": stat, "dof": len(cols), "p": p,
                     "multipliers": {lab: 1.0 + float(cj) for (_, lab), cj in zip(cols, c)},
                     "std_errors": {lab: float(sj) for (_, lab), sj in zip(cols, se)}}
        if part == "phase":
            # the phases where the data could have shown the cause off by min_share (at
            # Z_SEEN standard errors): only there is its prediction for that phase tested
            out["phases_seen"] = [lab[3:] for (_, lab), sj in zip(cols, se)
                                  if sj <= min_share / Z_SEEN]
        if len(cols) >= 2 and p < alpha:
            bad += [f"x{1 + cj:.2f} of itself {lab}" for (_, lab), cj, sj in zip(cols, c, se)
                    if abs(cj) > max(min_share, 3.0 * sj)]
    if bad:
        out["contradicted"] = True
        out["why"] = "the fitted effect is needed " + ", ".join(bad[:4])
    return out


def _partitions(ph, v, x, t, on) -> dict:
    """Cells (event masks, label) of the split test over the events where the cause acts."""
    out = {"phase": [(on & (ph == p), f"in {PHASES[p]}") for p in range(3)]}
    vt = np.quantile(v[on], [1 / 3, 2 / 3]) if on.any() else [0.0, 0.0]
    vb = [(-np.inf, vt[0]), (vt[0], vt[1]), (vt[1], np.inf)]
    out["phase x speed"] = [(on & (ph == p) & (v >= a) & (v < b),
                             f"in {PHASES[p]} at {max(a, 0):.0f}-{b:.0f} m/s")
                            for p in range(3) for a, b in vb]
    for name, q, unit in (("position", x, "m"), ("time", t, "s")):
        e = np.quantile(q[on], [0, 0.25, 0.5, 0.75, 1.0]) if on.any() else np.zeros(5)
        e[-1] += 1e-9
        out[name] = [(on & (q >= a) & (q < b), f"on {a:.0f}-{b:.0f} {unit}")
                     for a, b in zip(e[:-1], e[1:])]
    return out


def piece_of(mo: Motion, others: Null, full: Null, cfg, noise, found: list) -> str | None:
    """The ``unexplained`` signature the cause (``others`` -> ``full``) is a piece of (module
    docstring), in words, or None."""
    dv = Stage(mo, full, cfg, noise=noise, big=False).fv - \
        Stage(mo, others, cfg, noise=noise, big=False).fv
    energy = dv * dv
    if not energy.sum() > 0:
        return None
    gi = _event_grid_index(mo)
    support = (energy > 1e-6 * energy.max())[mo.grid.k]
    # the cause's acceleration on the grid (its drift increment per event interval)
    dt_ev = np.diff(mo.ev.t, prepend=mo.ev.t[0] - mo.grid.dt)
    acc = (dv / np.maximum(dt_ev, 1e-9))[mo.grid.k]
    for u in found:
        on = u["mask"]
        inside = energy[on[gi]].sum() / energy.sum()
        outside = (on[:-1] & ~support).sum() / max(on[:-1].sum(), 1)
        if inside > 0.5 and outside > 0.5:
            return (f"{100 * inside:.0f} % of it lies in a structure that also shows where it "
                    f"does not act (phase {u['phase']}, speed {_rng(u['speed'])} m/s, "
                    f"{100 * outside:.0f} % of that structure outside it)")
        # a remainder mostly where the cause acts and as large as half of it there: the
        # cause does not describe what acts there
        both = on[:-1] & support
        if both.sum() > 0.5 * max(on[:-1].sum(), 1):
            own = float(np.median(np.abs(acc[both])))
            if abs(u["size"]) > 0.5 * own:
                return (f"what is left where it acts ({abs(u['size']):.3f} m/s^2, phase "
                        f"{u['phase']}, speed {_rng(u['speed'])} m/s) is more than half of "
                        f"its own {own:.3f} m/s^2 there")
    return None


def _rng(r) -> str:
    return "-" if r is None else f"{r[0]:.0f}-{r[1]:.0f}"


def cancelling(mo: Motion, nulls: dict, base: Null, full: Null, cfg, noise) -> dict:
    """Causes (``nulls``: cause -> the model of all confirmed causes but it) whose
    contributions cancel in a phase (module docstring): cause -> reason in words."""
    gi = _event_grid_index(mo)
    ph = grid_phase(mo)[gi]
    fv_full = Stage(mo, full, cfg, noise=noise, big=False).fv
    total = fv_full - Stage(mo, base, cfg, noise=noise, big=False).fv
    parts = {c: fv_full - Stage(mo, n, cfg, noise=noise, big=False).fv
             for c, n in nulls.items()}
    out = {}
    for p in range(3):
        m = ph == p
        big = {c: float(np.sum(d[m] ** 2)) for c, d in parts.items()
               if np.sum(d[m] ** 2) > 0.25 * max(np.sum(d ** 2), 1e-300)}
        if len(big) < 2 or np.sum(total[m] ** 2) >= 0.25 * max(big.values()):
            continue
        for c in big:
            rest = ", ".join(sorted(set(big) - {c}))
            out[c] = (f"cancels with {rest} in {PHASES[p]} (together they leave "
                      f"{100 * np.sum(total[m] ** 2) / max(big.values()):.0f} % of the larger "
                      f"there: an effect confined to the other phases)")
    return out


def place_test(mo: Motion, full: Null, cfg, noise, inside: np.ndarray, beyond: np.ndarray,
               alpha: float, min_share: float) -> dict:
    """Whether a cause fitted on a stretch of track (``inside``: its grid points) acts at that
    place or in a phase and speed band everywhere: the cause's effect continued beyond its
    stretch (``beyond``: m/s^2 per grid point if it acted at every place) gets a free multiplier
    per cell (phase x speed half of the stretch) outside the stretch, on top of the model
    ``full``. A place effect leaves these at 0; a chi-square at ``alpha`` with a cell needing
    more than ``min_share`` of the effect (beyond 3 SE, the same sign) says the same shows at
    the other places run in that phase and speed (braking weaker at low speed at every stop,
    not on one stretch)."""
    ph = grid_phase(mo)
    v = mo.v_ref
    on = inside & (beyond != 0) & (ph >= 0)
    out_ = ~inside & (beyond != 0) & (ph >= 0)
    res = {"contradicted": False}
    if not on.any() or not out_.any():
        res["note"] = "no data outside the stretch in its phases"
        return res
    # speed halves of the stretch: a stop's last metres are run for a few seconds only, and a
    # finer band at low speed would hold too little of the other stops to test
    vm = float(np.median(v[on]))
    vb = [(0.0, vm), (vm, np.inf)]
    cols, labels = [], []
    e_in = float(np.sum(beyond[on] ** 2))
    for p in range(3):
        for a, b in vb:
            band = (ph == p) & (v >= a) & (v < b)
            cell = out_ & band
            # cells of the phases and speeds the stretch itself holds, with data outside it
            if (np.sum(beyond[on & band] ** 2) < 0.02 * e_in
                    or np.sum(beyond[cell] ** 2) < 0.02 * e_in
                    or cell.sum() * mo.grid.dt < PLACE_MIN_TIME):
                continue
            cols.append(beyond * cell)
            labels.append(f"in {PHASES[p]} at {a:.0f}-{min(b, 999):.0f} m/s")
    if not cols:
        res["note"] = "no phase and speed of the stretch run elsewhere"
        return res
    Bv, Bs = mo.grid.integrate(np.stack(cols, axis=1), mo.ev.t.size)
    st = Stage(mo, full, cfg, noise=noise, big=False)
    stat, c, se = _fit_columns(st, Bv, Bs)
    p = float(chi2.sf(stat, len(cols)))
    res.update(chi2=stat, dof=len(cols), p=p,
               multipliers={lab: float(cj) for lab, cj in zip(labels, c)},
               std_errors={lab: float(sj) for lab, sj in zip(labels, se)})
    bad = [f"x{cj:.2f} of it {lab}" for lab, cj, sj in zip(labels, c, se)
           if cj > max(min_share, 3.0 * sj)]
    if p < alpha and bad:
        res["contradicted"] = True
        res["why"] = ("the same shows outside its stretch (not a place effect): "
                      + ", ".join(bad[:3]))
    return res


def flexible_rival(mo: Motion, others: Null, full: Null, cfg, noise, k_cause: int) -> dict:
    """Whether a cause confirmed together with others explains the data better than a flexible
    term in the phases and speeds it acts in: free extra accelerations per phase x quarter of
    the top speed (the structure test's ``speed`` family) on the cells holding its
    contribution, on top of the other causes (``others``). Both by BIC (``k_cause``: the
    cause's parameters, one per cell for the flexible term): {"better", figures}."""
    st0 = Stage(mo, others, cfg, noise=noise, big=False)
    dv = Stage(mo, full, cfg, noise=noise, big=False).fv - st0.fv
    ds = Stage(mo, full, cfg, noise=noise, big=False).fs - st0.fs
    fam = families(mo).get("speed")
    if fam is None or not np.any(dv):
        return {"better": True, "note": "no flexible term to compare"}
    R, labels = fam
    gi = _event_grid_index(mo)
    energy = dv * dv
    keep = [j for j in range(R.shape[1])
            if energy[R[gi, j] > 0].sum() > 0.02 * energy.sum()]
    if not keep:
        return {"better": True, "note": "no flexible term to compare"}
    Bv, Bs = mo.grid.integrate(R[:, keep], mo.ev.t.size)
    stat_f = _fit_columns(st0, Bv, Bs)[0]
    stat_c = _fit_columns(st0, dv[:, None], ds[:, None])[0]
    ln_n = math.log(max(mo.ev.t.size, 2))
    bic_c = stat_c - k_cause * ln_n
    bic_f = stat_f - len(keep) * ln_n
    return {"better": bool(bic_c > bic_f), "chi2_cause": stat_c, "k_cause": k_cause,
            "chi2_flexible": stat_f, "k_flexible": len(keep),
            "cells": [labels[j] for j in keep]}
