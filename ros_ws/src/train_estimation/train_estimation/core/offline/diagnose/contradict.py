"""Whether a confirmed cause shows where it predicts it shows, and only there: its checks
against the rest of the data (see :mod:`.phases` for the phases and cells; the rival laws of
the same effect, drag for a gradient, fading brakes for a weaker braking, an error growing with
speed for an odometer scale, are in :mod:`.laws`).

**Split test** (:func:`split_test`). A confirmed cause's contribution d (its drift columns:
the model with it minus the model without it) is split into cells (phase x speed tercile,
quarters of its position range, quarters of its time range), each with a free multiplier
1 + c_j. If the cause is right, every c_j is 0 within noise; a chi-square test per partition at
``alpha`` with some |c_j| > ``min_share`` (more than 3 standard errors) says the cause does not
show where it predicts (a braking-rate change that only shows at low speed, a mass change that
shows in traction but not in braking). Then smooth slopes, one degree of freedom each: the
contribution times a centred covariate (speed; time over the span where it acts; the traction
command in traction, the braking command in braking), whose coefficient is the cause's change
from the covariate's 5th to its 95th percentile; a likelihood ratio at ``alpha`` with a change
of more than ``min_share`` (and 3 SE) contradicts the cause (a traction loss above a speed
taken for a power limit's p_spec / v; a loss that scales with the traction command taken for a
gradient; a resistance that decays as the train warms up taken for a gradient over the first
kilometres, whose force falls across its stretch: every listed cause holds its size over the
time it acts, a gradient section and a low-adhesion section over their stretch, a braking-rate
drift along its own line).

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

**A slip's step in the readings** (:func:`slip_step`). A slip is the odometer's, not the
train's: the axle turns faster or slower than the train moves, so the odometer's speed readings
step by the episode's depth where it begins and step back where it ends, while the train's
speed (smooth: the drive goes through the actuator's lag) does not. Around each episode the
readings alone get a smooth curve in time (a cubic, plus the integrated traction and braking
commands with free gains: it bends where the commands change) plus the episode's step (the
same column as the filter's: the reading's own speed inside it). Two one-sided tests at
``z`` SE (the SE widened by the local fit's reduced chi-square when above 1), one per
hypothesis. Readings that reject a step of half the fitted size *contradict* the slip: the
episode stands in for motion the model lacks (where a traction failed at a departure the
filter's fit was +38 % while the readings stepped +3 +- 4 %). Readings that do not reject
*no step* leave it *unsupported*: the episode may be the odometer's or the train's, and the
data cannot say which (a passing train's pressure wave, 4 s of a 0.3 m/s^2 retarding force,
fitted as a 1.4 % slip whose readings stepped -0.2 +- 0.2 %, where half the fit was only 2.9
SE: nothing could have contradicted it, and it was confirmed). Either way the episode is not
the slip's. On the bench's slips the readings give 0.77-1.09 of the fitted depth at 9-70 SE.
A change of the drive inside the episode that the commands do not show (a traction lost where
the command holds) bends the speed where the cubic cannot follow, and the step takes part of
it (at a neutral section's start: fitted +1.4 %, the readings +0.4 +- 0.2 %, 2 SE:
unsupported).

**Causes that cancel** (:func:`cancelling`). Two confirmed causes whose contributions are
each large in a phase (> ``CANCEL_SHARE`` = 1/10 of their own energy there) while their sum
there is small (< 1/4 of the larger) act together as one effect confined to the other phases
(a heavier train and a stronger brake: traction alone is weaker). No listed cause is that
effect. The same on the stretch of a cause at a place: a resistance change with a gradient
that takes it back over the last 5.7 km is a resistance confined to the first kilometres (a
warm-up, in one run).
"""

from __future__ import annotations

import math

import numpy as np

from train_estimation.core.numerics.special import chdtrc

from .motion import Motion, slip_shape
from .phases import (
    PHASES,
    _event_grid_index,
    counted_columns,
    families,
    grid_phase,
)
from .stage import Null, Stage, cause_stat, fit_columns

# s, a cell of the place test holds at least this much time outside the stretch (a stop's last
# few m/s of braking last a few seconds; the cell's standard error states what it can test)
PLACE_MIN_TIME = 1.0
# a cell tests a cause's prediction when a departure of min_share of it there would be a
# Z_SEEN-standard-error result (a two-sided 0.3 % chance under the cause)
Z_SEEN = 3.0


def split_test(mo: Motion, others: Null, full: Null, cfg, noise, alpha: float,
               min_share: float) -> dict:
    """The split test of the module docstring for the cause that makes ``others`` into
    ``full``: {"contradicted", "why", per-partition figures}."""
    st0 = Stage(mo, others, cfg, noise=noise, big=False)
    st1 = Stage(mo, full, cfg, noise=noise, big=False)
    dv, ds = st1.fv - st0.fv, st1.fs - st0.fs
    energy = dv * dv
    if not energy.sum() > 0:
        return _split_measurement(mo, st1, st1.md - st0.md, st1.mv - st0.mv, alpha, min_share)
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
        stat, c, se = fit_columns(st1, Bv, Bs)
        bad += _cells(out, part, cols, stat, c, se, alpha, min_share)
        if part == "phase":
            # the phases where the data could have shown the cause off by min_share (at
            # Z_SEEN standard errors): only there is its prediction for that phase tested
            out["phases_seen"] = [lab[3:] for (_, lab), sj in zip(cols, se)
                                  if sj <= min_share / Z_SEEN]
    # smooth departures, one degree of freedom each (more power than the cells against a
    # cause whose shape in speed or in the command is wrong: a knee p_spec / v against a step
    # at a speed, a force fixed in place against one that scales with the traction asked for)
    for name, z in _slopes(mo, ph, v, gi, on, energy, t):
        stat, c, se = fit_columns(st1, (dv * z)[:, None], (ds * z)[:, None])
        p = float(chdtrc(1, stat))
        out[f"slope in {name}"] = {"chi2": stat, "dof": 1, "p": p, "change": float(c[0]),
                                   "std_error": float(se[0])}
        if p < alpha and abs(c[0]) > max(min_share, 3.0 * se[0]):
            bad.append(f"{1 - c[0] / 2:.2f} to {1 + c[0] / 2:.2f} of itself from the low to "
                       f"the high end of its {name}")
    if bad:
        out["contradicted"] = True
        out["why"] = "the fitted effect is needed " + ", ".join(bad[:4])
    return out


def _cells(out: dict, part: str, cols: list, stat: float, c, se, alpha: float,
           min_share: float) -> list:
    """One partition of a split test: its figures into ``out[part]`` (chi-square with a degree
    of freedom per cell, each cell's multiplier 1 + c_j and standard error); the cells that
    contradict the cause (the partition significant at ``alpha``, two cells at least, a cell
    off by more than ``min_share`` and 3 SE), in words."""
    p = float(chdtrc(len(cols), stat))
    out[part] = {"chi2": stat, "dof": len(cols), "p": p,
                 "multipliers": {lab: 1.0 + float(cj) for (_, lab), cj in zip(cols, c)},
                 "std_errors": {lab: float(sj) for (_, lab), sj in zip(cols, se)}}
    if len(cols) < 2 or not p < alpha:
        return []
    return [f"x{1 + cj:.2f} of itself {lab}" for (_, lab), cj, sj in zip(cols, c, se)
            if abs(cj) > max(min_share, 3.0 * sj)]


def _split_measurement(mo: Motion, st1: Stage, dmd: np.ndarray, dmv: np.ndarray, alpha: float,
                       min_share: float) -> dict:
    """The split test of a cause that acts on the odometer's readings (an odometer scale, slip
    episodes): its measurement contribution, the distance part ``dmd`` (counted: what the
    cause adds to the distance grows with the distance run) and the speed part ``dmv``, split
    into cells of phase, phase x speed, position and time with a free multiplier each. A cell
    takes the cause's distance increments inside it (carried on after it) and its speed part
    inside it, so a multiplier of 1 everywhere is the cause as fitted: a scale that changes in
    the middle of the run (the odometer moved to another axle) needs x0 before and x2 after."""
    o = mo.ev.odo
    inc = np.zeros(dmd.size)
    inc[o] = np.diff(dmd[o], prepend=0.0)
    energy = inc * inc + dmv * dmv
    if not energy.sum() > 0:
        return {"contradicted": False, "note": "nothing to split"}
    gi = _event_grid_index(mo)
    ph = grid_phase(mo)[gi]
    v, x, t = mo.v_ref[gi], mo.x_ref[gi], mo.ev.t
    on = energy > 1e-6 * energy.max()
    out, bad = {"contradicted": False, "on": "the odometer's readings"}, []
    for part, cells in _partitions(ph, v, x, t, on).items():
        cols = [(m, lab) for m, lab in cells if energy[m].sum() > 0.02 * energy.sum()]
        if len(cols) < 2:
            continue
        Md = counted_columns(mo, inc, [m for m, _ in cols])
        Mv = np.stack([dmv * m for m, _ in cols], axis=1)
        stat, c, se = fit_columns(st1, None, None, meas=(Md, Mv))
        bad += _cells(out, part, cols, stat, c, se, alpha, min_share)
    if bad:
        out["contradicted"] = True
        out["why"] = "the fitted effect on the odometer is needed " + ", ".join(bad[:4])
    return out


# the 5-95 % range of a covariate below which a slope in it is not tested (m/s, m/s^2)
SLOPE_MIN_RANGE = {"speed": 2.0, "traction command": 0.05, "braking command": 0.05,
                   "time span": 10.0}


def _slopes(mo: Motion, ph, v, gi, on, energy, t=None) -> list:
    """[(name, z per event)]: centred covariates over the events where the cause acts, scaled
    so that a coefficient c is the change of the cause from the 5th to the 95th percentile of
    the covariate (x (1 - c/2) to x (1 + c/2)): speed, time (``t``, s: over the events where
    the cause acts; the train runs a stretch once, so on a place cause's stretch this is also
    the position along it), and the commanded traction (braking) in traction (braking) where
    the cause holds more than 2 % of its energy there."""
    out = []
    covs = [("speed", v, on)] + ([("time span", t, on)] if t is not None else [])
    for p, name, cmd in ((0, "traction command", mo.a_tr0), (2, "braking command", -mo.a_br0)):
        m = on & (ph == p)
        if energy[m].sum() > 0.02 * energy.sum():
            covs.append((name, cmd[gi], m))
    for name, q, m in covs:
        if m.sum() < 10:
            continue
        lo, hi = np.percentile(q[m], [5, 95])
        if hi - lo < SLOPE_MIN_RANGE[name]:
            continue
        out.append((name, np.where(m, (np.clip(q, lo, hi) - 0.5 * (lo + hi)) / (hi - lo), 0.0)))
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
        if u["family"] in ("balise", "balise_latency"):  # readings' offsets: no acceleration
            continue  # to be a piece of
        on = u["mask"]
        inside = energy[on[gi]].sum() / energy.sum()
        outside = (on[:-1] & ~support).sum() / max(on[:-1].sum(), 1)
        if inside > 0.5 and outside > 0.5:
            return (f"{100 * inside:.0f} % of it lies in a structure that also shows where it "
                    f"does not act (phase {u['phase']}, speed {_rng(u['speed'])} m/s, "
                    f"{100 * outside:.0f} % of that structure outside it)")
        # a remainder mostly where the cause acts and as large as half of it there: the
        # cause does not describe what acts there (an acceleration: not the odometer's
        # count, whose size is in m)
        if u["family"] == "odometer":
            continue
        both = on[:-1] & support
        if both.sum() > 0.5 * max(on[:-1].sum(), 1):
            own = float(np.median(np.abs(acc[both])))
            if abs(u["size"]) > 0.5 * own:
                return (f"what is left where it acts ({abs(u['size']):.3f} m/s^2, phase "
                        f"{u['phase']}, speed {_rng(u['speed'])} m/s) is more than half of "
                        f"its own {own:.3f} m/s^2 there")
    return None


def slip_step(mo: Motion, interval, theta: float, z: float = 3.0, others=(),
              shape: str = "step") -> dict:
    """The slip step tests of the module docstring for one episode ``interval`` [t0, t1) (s,
    the run's clock) with the filter's column coefficient ``theta`` (the share of the reading
    inside that is slip): {step, se, contradicted, supported}. Readings inside the ``others``
    episodes ([t0, t1) each) are left out (they hold their own steps). The train's speed
    around it is a cubic in time plus the integrals of the traction and of the braking
    commanded (through the believed actuator), each with a free gain: it bends where the
    commands change, whatever the drive delivers, and cannot step. With a ``shape``
    (motion.SLIP_SHAPES) the step is the episode's peak, the readings inside weighted by the
    shape."""
    r = mo.run
    t0, t1 = float(interval[0]), float(interval[1])
    pad = max(3.0, t1 - t0)
    k = (r.odo_t >= t0 - pad) & (r.odo_t < t1 + pad)
    for a, b in others:
        k &= (r.odo_t < a) | (r.odo_t >= b)
    t, y = r.odo_t[k], r.odo_v[k]
    inside = (t >= t0) & (t < t1)
    if inside.sum() < 2 or (~inside).sum() < 8:
        return {"step": None, "se": None, "contradicted": False, "supported": False}
    g = mo.grid.t
    drives = []
    for part in (mo.a_tr0, mo.a_br0):
        cum = np.concatenate([[0.0], np.cumsum(0.5 * (part[1:] + part[:-1]) * np.diff(g))])
        drives.append(np.interp(t, g, cum))
    tau = (t - 0.5 * (t0 + t1)) / (0.5 * (t1 - t0) + pad)
    w = 1.0 / np.sqrt(np.maximum(r.odo_rv[k], 1e-8))
    inside = slip_shape(shape, (t - t0) / max(t1 - t0, 1e-9))
    X = np.column_stack([tau ** p for p in range(4)] + drives + [y * inside]) * w[:, None]
    th, *_ = np.linalg.lstsq(X, y * w, rcond=None)
    dof = y.size - np.linalg.matrix_rank(X)
    red = float(np.sum((X @ th - y * w) ** 2)) / max(dof, 1)
    cov = np.linalg.pinv(X.T @ X)
    se = math.sqrt(max(cov[-1, -1], 0.0) * max(red, 1.0))
    step = float(th[-1])
    # one-sided: the readings' step falls short of half the fitted one by more than z SE
    short = (0.5 * abs(theta) - math.copysign(1.0, theta) * step) / se if se > 0 else 0.0
    # and the other way: the readings step, in the fit's direction, by more than z SE
    beyond = math.copysign(1.0, theta) * step / se if se > 0 else 0.0
    return {"step": step, "se": se, "contradicted": bool(dof > 0 and short > z),
            "supported": bool(dof > 0 and beyond > z)}


def _rng(r) -> str:
    return "-" if r is None else f"{r[0]:.0f}-{r[1]:.0f}"


# share of a cause's energy (its contribution squared) that a region must hold for the cause
# to count as acting there in the cancelling test: a traction x 0.71 on a tram, read as a
# heavier train (x 1.40) with a stronger brake (x 1.30), had 24.5 % of the mass change's
# energy in braking, where the two summed to nothing (a quarter, the first bar, missed it)
CANCEL_SHARE = 0.1


def cancelling(mo: Motion, nulls: dict, base: Null, full: Null, cfg, noise,
               stretches: dict | None = None) -> dict:
    """Causes (``nulls``: cause -> the model of all confirmed causes but it) whose
    contributions cancel in a phase, or on the stretch of a cause at a place (``stretches``:
    cause -> its grid mask; module docstring): cause -> reason in words."""
    gi = _event_grid_index(mo)
    ph = grid_phase(mo)[gi]
    fv_full = Stage(mo, full, cfg, noise=noise, big=False).fv
    total = fv_full - Stage(mo, base, cfg, noise=noise, big=False).fv
    parts = {c: fv_full - Stage(mo, n, cfg, noise=noise, big=False).fv
             for c, n in nulls.items()}
    regions = [(ph == p, f"in {PHASES[p]}", "the other phases") for p in range(3)]
    for c, on in (stretches or {}).items():
        x = mo.x_ref[on]
        if x.size:
            regions.append((on[gi], f"on {x.min():.0f}-{x.max():.0f} m (the stretch of {c})",
                            "the rest of the run"))
    out = {}
    for m, where, elsewhere in regions:
        big = {c: float(np.sum(d[m] ** 2)) for c, d in parts.items()
               if np.sum(d[m] ** 2) > CANCEL_SHARE * max(np.sum(d ** 2), 1e-300)}
        if len(big) < 2 or np.sum(total[m] ** 2) >= 0.25 * max(big.values()):
            continue
        for c in big:
            if c in out:
                continue
            rest = ", ".join(sorted(set(big) - {c}))
            out[c] = (f"cancels with {rest} {where} (together they leave "
                      f"{100 * np.sum(total[m] ** 2) / max(big.values()):.0f} % of the larger "
                      f"there: an effect confined to {elsewhere})")
    return out


def place_cells(mo: Motion, inside: np.ndarray, beyond: np.ndarray) -> tuple:
    """The cells of the place test (:func:`place_test`): (columns, labels, note), the cause's
    effect continued beyond its stretch in each phase x speed half of the stretch that the
    run also holds outside it; no columns and the note why when there is none (the run cannot
    show the cause absent anywhere else)."""
    ph = grid_phase(mo)
    v = mo.v_ref
    on = inside & (beyond != 0) & (ph >= 0)
    out_ = ~inside & (beyond != 0) & (ph >= 0)
    if not on.any() or not out_.any():
        return [], [], "no data outside the stretch in its phases"
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
    return cols, labels, None if cols else "no phase and speed of the stretch run elsewhere"


def place_seen(mo: Motion, full: Null, cfg, noise, inside: np.ndarray, beyond: np.ndarray,
               min_share: float) -> bool:
    """Whether the run could show a cause at a place absent outside its stretch: some cell of
    the place test (:func:`place_cells`) where a departure of ``min_share`` of the cause would
    be a ``Z_SEEN``-standard-error result, on top of the model ``full``."""
    cols, _, _ = place_cells(mo, inside, beyond)
    if not cols:
        return False
    _, _, se = _fit_cells(mo, full, cfg, noise, cols)
    return bool(np.any(se <= min_share / Z_SEEN))


def _fit_cells(mo: Motion, full: Null, cfg, noise, cols: list) -> tuple:
    """GLS of free multipliers of the place test's grid columns ``cols`` on top of the model
    ``full``: (chi-square statistic, multipliers, standard errors)."""
    Bv, Bs = mo.grid.integrate(np.stack(cols, axis=1), mo.ev.t.size)
    return fit_columns(Stage(mo, full, cfg, noise=noise, big=False), Bv, Bs)


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
    res = {"contradicted": False}
    cols, labels, note = place_cells(mo, inside, beyond)
    if not cols:
        res["note"] = note
        return res
    stat, c, se = _fit_cells(mo, full, cfg, noise, cols)
    p = float(chdtrc(len(cols), stat))
    res.update(chi2=stat, dof=len(cols), p=p,
               multipliers={lab: float(cj) for lab, cj in zip(labels, c)},
               std_errors={lab: float(sj) for lab, sj in zip(labels, se)})
    bad = [f"x{cj:.2f} of it {lab}" for lab, cj, sj in zip(labels, c, se)
           if cj > max(min_share, 3.0 * sj)]
    if p < alpha:
        # the same shows elsewhere, if less than min_share of it: evidence for an effect of
        # the phase, which a cause seen in one phase only cannot be told from (confirm.py)
        res["elsewhere"] = [f"x{cj:.2f} of it {lab}" for lab, cj, sj in zip(labels, c, se)
                            if cj > 3.0 * sj]
    if p < alpha and bad:
        res["contradicted"] = True
        res["why"] = ("the same shows outside its stretch (not a place effect): "
                      + ", ".join(bad[:3]))
    return res


def flexible_rival(mo: Motion, others: Null, full: Null, cfg, noise, k_cause: int,
                   free=None) -> dict:
    """Whether a cause confirmed together with others explains the data better than a flexible
    term in the phases and speeds it acts in: free extra accelerations per phase x quarter of
    the top speed (the structure test's ``speed`` family) on the cells holding its
    contribution, on top of the other causes (``others``). Both by BIC (``k_cause``: the
    cause's parameters, one per cell for the flexible term): {"better", figures}. The cause
    is fitted in the parameters BIC charges it (:func:`.stage.cause_stat`)."""
    st0 = Stage(mo, others, cfg, noise=noise, big=False)
    st1 = Stage(mo, full, cfg, noise=noise, big=False)
    dv, ds = st1.fv - st0.fv, st1.fs - st0.fs
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
    stat_f = fit_columns(st0, Bv, Bs)[0]
    stat_c = cause_stat(st0, dv, ds, free)
    ln_n = math.log(max(mo.ev.t.size, 2))
    bic_c = stat_c - k_cause * ln_n
    bic_f = stat_f - len(keep) * ln_n
    return {"better": bool(bic_c > bic_f), "chi2_cause": stat_c, "k_cause": k_cause,
            "chi2_flexible": stat_f, "k_flexible": len(keep),
            "cells": [labels[j] for j in keep]}
