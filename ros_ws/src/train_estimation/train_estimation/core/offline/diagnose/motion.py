"""The motion model of one run: its events, the time grid, the reference trajectory and the
elementary columns every cause is built from.

The model (train_core physics, as ``identify``; Zheng et al. 2015 eq. (1) for the actuator)::

    ds/dt = v
    dv/dt = a_tr(t) + f0 a_br(t) - (alpha + beta v + gamma v^2)
            - g sin(theta(s0 + s)) / (1 + lambda) + sum_j theta_j r_j(t) + w,   w white, PSD q
    odometer:  d_k = s(t_k) + m_d,k . theta + e_d,    y_k = v(t_k) + m_v,k . theta + e_v
    balise:    p_b = s0 + s(t_b) + e_b

``a_tr``/``a_br`` are the traction and braking parts of the recorded commands through the
believed delay and lag (train_core.actuator.grid_part). A cause is a set of extra drift columns
``r_j`` or measurement columns ``m_j``, linear in its parameters once the nonlinear ones are
fixed. The regressors are evaluated on a reference trajectory (smoothed odometer speed, and
odometer distance placed on the line piecewise between balise fixes, so a wrong odometer scale
does not misplace the map's gradient changes).
"""

from __future__ import annotations

import math

import numpy as np
from train_core.actuator import grid_part
from train_core.model import G, Line, TrainParams

from train_estimation.core.numerics.augmented_kf import Events

from ..identify import moving_average
from .run import DiagConfig, Run


def events(run: Run, cfg: DiagConfig) -> Events:
    """Odometer samples (decimated by time: the first in each 1/max_rate slot) and balise
    readings, in time order."""
    slot = np.floor(run.odo_t * cfg.max_rate + 1e-9).astype(np.int64)
    keep = np.concatenate([[True], np.diff(slot) > 0])
    t_o = run.odo_t[keep]
    n_o, n_b = t_o.size, run.bal_t.size
    t = np.concatenate([t_o, run.bal_t])
    kind = np.concatenate([np.zeros(n_o, np.int8), np.ones(n_b, np.int8)])
    y_d = np.concatenate([run.odo_d[keep], run.bal_p])
    y_v = np.concatenate([run.odo_v[keep], np.zeros(n_b)])
    r_v = np.concatenate([np.maximum(run.odo_rv[keep], 1e-8), np.maximum(run.bal_r, 1e-4)])
    o = np.argsort(t, kind="stable")
    t, kind, y_d, y_v, r_v = t[o], kind[o], y_d[o], y_v[o], r_v[o]
    return Events(t=t, kind=kind, y_d=y_d, y_v=y_v, r_v=r_v,
                  held=np.zeros(t.size, bool), odo=np.flatnonzero(kind == 0),
                  bal=np.flatnonzero(kind == 1))


class Grid:
    """Uniform time grid for the actuator and reference trajectory, and the map from grid steps
    to event intervals (a step belongs to the interval holding its midpoint)."""

    def __init__(self, ev: Events, dt: float):
        t0, t1 = ev.t[0], ev.t[-1]
        n = int(math.ceil((t1 - t0) / dt)) + 1
        self.t = t0 + dt * np.arange(n)
        self.dt = dt
        self.mid = self.t[:-1] + 0.5 * dt
        # interval k (between events k-1 and k) for k = 1..n_ev-1
        self.k = np.clip(np.searchsorted(ev.t, self.mid, side="right"), 1, ev.t.size - 1)
        starts = np.flatnonzero(np.concatenate([[True], np.diff(self.k) > 0]))
        self.starts = starts
        self.kk = self.k[starts]  # interval index of each run of steps
        self.lever = ev.t[self.k] - self.mid  # t_{k} - tau for the position integral

    def integrate(self, R: np.ndarray, n_ev: int) -> tuple[np.ndarray, np.ndarray]:
        """Interval integrals of grid columns R (n_grid, p) -> (Bv, Bs), each (n_ev, p):
        Bv[k] = int r over interval k, Bs[k] = int (t_k - tau) r(tau) dtau (midpoint rule).

        Many columns are best passed as ``np.stack(cols).T`` (the columns stacked as rows, a
        Fortran-ordered view): stacking them as columns is a strided copy, twice as slow here
        and in the sums. The sums are the same bit for bit in either order (``reduceat`` adds
        each column's run of steps alike; tested)."""
        inc = 0.5 * (R[1:] + R[:-1]) * self.dt
        Bv = np.zeros((n_ev, R.shape[1]))
        Bs = np.zeros((n_ev, R.shape[1]))
        Bv[self.kk] = np.add.reduceat(inc, self.starts, axis=0)
        Bs[self.kk] = np.add.reduceat(inc * self.lever[:, None], self.starts, axis=0)
        return Bv, Bs


def place_on_line(d: np.ndarray, d_bal: np.ndarray, p_bal: np.ndarray) -> np.ndarray:
    """Track positions (m) of odometer distances ``d``, placed by the balise fixes (odometer
    distance ``d_bal`` at each balise read at map position ``p_bal``): piecewise linear between
    consecutive fixes, as a train's positioning resets at each balise, and beyond the first
    and last fix by the least-squares scale of all fixes. A wrong odometer scale (1 % is 60 m
    over a 6 km line) or a slip episode would otherwise misplace the map's gradient changes,
    which then look like a gradient error. With one fix: the offset only."""
    if d_bal.size == 0:
        return d.astype(float).copy()
    order = np.argsort(d_bal)
    db, pb = d_bal[order], p_bal[order]
    keep = np.concatenate([[True], np.diff(db) > 1.0])  # one fix per balise passage
    db, pb = db[keep], pb[keep]
    if db.size < 2:
        return d + float(np.median(p_bal - d_bal))
    k = np.polyfit(db, pb, 1)[0]
    keep = consistent_fixes(db, pb, k)
    db, pb = db[keep], pb[keep]
    x = np.interp(d, db, pb)
    x = np.where(d < db[0], pb[0] + k * (d - db[0]), x)
    return np.where(d > db[-1], pb[-1] + k * (d - db[-1]), x)


# m, a balise fix off the odometer's track through its neighbours by more than this is a
# placement outlier when leaving it out brings every other fix within 1/STANDS_OUT of it and
# within OUTLIER_FIX (a balise's location accuracy is metres, and a fix at either end is
# carried by one neighbour only; a moved balise of the benches is 8-20 m off)
OUTLIER_FIX = 5.0
STANDS_OUT = 3.0


def _loo(db: np.ndarray, pb: np.ndarray, k: float) -> np.ndarray:
    """Each fix's map position minus where its neighbours put it: interpolated between the two
    around it by odometer distance, an end fix carried from its one neighbour at scale ``k``."""
    if db.size < 2:
        return np.zeros(db.size)
    pred = np.empty(db.size)
    pred[0] = pb[1] + k * (db[0] - db[1])
    pred[-1] = pb[-2] + k * (db[-1] - db[-2])
    if db.size > 2:
        w = (db[1:-1] - db[:-2]) / (db[2:] - db[:-2])
        pred[1:-1] = pb[:-2] + w * (pb[2:] - pb[:-2])
    return pb - pred


def consistent_fixes(db: np.ndarray, pb: np.ndarray, k: float) -> np.ndarray:
    """Mask of the balise fixes that place the odometer on the line (``db`` odometer distance,
    ``pb`` map position, sorted; ``k`` the least-squares scale): a fix that lies elsewhere than
    the map says (a balise moved by 12 m) pins the reference trajectory 12 m off around it,
    which misplaces the map's gradient changes there, and a gradient of 2 per mille over 100 m
    beside a gradient change fits what that leaves (an independent simulator's bag). One fix
    is left out at a time while some fix is more than ``OUTLIER_FIX`` off its neighbours'
    track and leaving out one fix r m off brings every other within r / ``STANDS_OUT`` and
    ``OUTLIER_FIX``; an odometer that counts more or less (a slip episode, a changed scale)
    between fixes moves two fixes or more off that track by as much, and is left to the
    piecewise placement. At most a quarter of the fixes go. The diagnosis still reports the
    reading (balise_rounds.balise_round)."""
    keep = np.ones(db.size, bool)
    for _ in range(db.size // 4):
        idx = np.flatnonzero(keep)
        r = np.abs(_loo(db[idx], pb[idx], k))
        if idx.size < 4 or np.max(r) <= OUTLIER_FIX:
            break
        best = None
        for j in range(idx.size):
            rest = np.delete(idx, j)
            worst = float(np.max(np.abs(_loo(db[rest], pb[rest], k))))
            if worst <= min(OUTLIER_FIX, r[j] / STANDS_OUT) and (best is None
                                                                 or worst < best[0]):
                best = (worst, idx[j])
        if best is None:
            break
        keep[best[1]] = False
    return keep


def shift_grid(grid: tuple, excess: float, floor: float = 0.2, most: int = 49) -> np.ndarray:
    """The command-time offsets profiled (s): ``grid`` = (lo, hi, step), reaching up to
    ``excess + floor`` where the link's mean latency lies ``excess`` s above its floor.

    The clock fit puts the odometer's mean latency into the offset between the clocks, so
    commands stamped when they were sent land that mean latency early: the offset to profile
    is the latency's floor (unknown, taken as at most ``floor``) plus its mean above the floor.
    A radio's jitter of tens of milliseconds stays inside the grid; a link with a tail of half
    a second (a congested radio) needs the grid extended, or the remainder is read as a brake
    and a traction delay. The step grows (in whole steps) to keep at most ``most`` offsets."""
    lo, hi, st = grid
    hi = max(hi, excess + floor)
    st = st * max(1, math.ceil((hi - lo) / st / (most - 1)))
    return np.round(np.arange(lo, hi + 1e-9, st), 6)


class Motion:
    """Columns of the motion model on the events of one run, built once.

    Dense elementary columns (``dense_names``): the traction and braking commands through the
    actuator (``tr``, ``br``), the braking gain's drift (``brt``), the Davis terms (``one``,
    ``v``, ``v2``), re-timed traction (``T<shift>``) and braking (``B<shift+delay>``) minus the
    believed ones; then one column per position bin (``G<i>``, per permille) for gradient
    sections; the odometer-scale measurement columns ``sc_d``, ``sc_v``."""

    def __init__(self, run: Run, line: Line, train: TrainParams, cfg: DiagConfig):
        self.run, self.line, self.train, self.cfg = run, line, train, cfg
        ev = events(run, cfg)
        self.ev = ev
        g = Grid(ev, cfg.grid_dt)
        self.grid = g
        # reference trajectory: odometer speed averaged over 1 s, counted distance; placed on
        # the line by the balises (median offset)
        w = max(1, int(round(1.0 / max(np.median(np.diff(run.odo_t)), 1e-3))))
        v_s = moving_average(run.odo_v, w)
        self.v_ref = np.clip(np.interp(g.t, run.odo_t, v_s), 0.0, None)
        d_ref = np.interp(g.t, run.odo_t, run.odo_d)
        self.x_ref = place_on_line(d_ref, np.interp(run.bal_t, run.odo_t, run.odo_d), run.bal_p)
        moving = (self.v_ref >= cfg.standstill_speed).astype(float)
        cm = np.concatenate([[0.0], np.cumsum(1.0 - moving)])
        # interval k is modelled only if the train moves throughout it
        ig = np.searchsorted(g.t, ev.t)
        held = np.zeros(ev.t.size, bool)
        held[1:] = (cm[np.minimum(ig[1:] + 1, g.t.size)] - cm[ig[:-1]]) > 0
        ev.held = held
        self.moving = moving
        b = train.brake
        self.f0 = b.braking_rate
        self.tau_norm = (g.t - g.t[0]) / max(g.t[-1] - g.t[0], 1e-9)
        meff = train.effective_mass
        self.alpha0, self.beta0, self.gamma0 = (train.davis.a / meff, train.davis.b / meff,
                                                train.davis.c / meff)
        self.k_grad = 1.0 / (1.0 + train.rotary_allowance)
        self.a_tr0, self.a_br0 = self._part(0.0, "traction"), self._part(0.0, "braking")
        # shifts (nuisance) and extra braking delays
        self.shifts = shift_grid(cfg.shift_grid, float(run.clock.get("latency_excess", 0.0)))
        lo, hi, st = cfg.delay_grid
        self.delays = np.round(np.arange(lo, hi + 1e-9, st), 6)
        names, R = self._dense_columns()
        self.dense_names = names
        Bv, Bs = g.integrate(np.stack(R).T, ev.t.size)  # Grid.integrate: stacked as rows
        Gv, Gs = self._gradient_bins()
        self._believed_drift()
        self.Dv = np.concatenate([Bv, Gv], axis=1)
        self.Ds = np.concatenate([Bs, Gs], axis=1)
        self.names = names + [f"G{i}" for i in range(self.n_bins)]
        self.col = {n: i for i, n in enumerate(self.names)}
        # measurement columns: odometer scale (scale - 1) * (s, v) of the reference
        n = ev.t.size
        self.sc_d = np.zeros(n)
        self.sc_v = np.zeros(n)
        o = ev.odo
        self.sc_d[o] = np.interp(ev.t[o], g.t, d_ref)
        self.sc_v[o] = np.interp(ev.t[o], g.t, self.v_ref)

    def _dense_columns(self) -> tuple[list, list]:
        names, R = [], []
        v, moving = self.v_ref, self.moving

        def add(name, col):
            names.append(name)
            R.append(col * moving)

        add("tr", self.a_tr0)
        add("br", self.a_br0)
        add("brt", self.a_br0 * self.tau_norm)
        add("one", -np.ones_like(v))
        add("v", -v)
        add("v2", -v * v)
        for s in self.shifts:
            if s != 0.0:
                add(f"T{s:+.3f}", self._part(s, "traction") - self.a_tr0)
        self.braking_cols = {}
        for s in self.shifts:
            for d in self.delays:
                key = round(float(s + d), 6)
                if key == 0.0 or key in self.braking_cols:
                    continue
                self.braking_cols[key] = f"B{key:+.3f}"
                add(f"B{key:+.3f}", self.f0 * (self._part(key, "braking", key) - self.a_br0))
        return names, R

    def _gradient_bins(self) -> tuple[np.ndarray, np.ndarray]:
        """Drift columns of the position bins (sparse: one bin per grid step), per permille."""
        g, ev, cfg, moving = self.grid, self.ev, self.cfg, self.moving
        xm = 0.5 * (self.x_ref[1:] + self.x_ref[:-1])
        mov = 0.5 * (moving[1:] + moving[:-1]) > 0.5
        lo_x, hi_x = float(np.min(xm[mov])) if mov.any() else 0.0, \
            float(np.max(xm[mov])) if mov.any() else 1.0
        width = max(cfg.gradient_bin, (hi_x - lo_x) / cfg.max_bins)
        nb = max(1, int(math.ceil((hi_x - lo_x) / width)))
        self.bin_edges = lo_x + width * np.arange(nb + 1)
        self.n_bins = nb
        j = np.clip(((xm - lo_x) / width).astype(int), 0, nb - 1)
        # per grid step: its position bin and whether the train moves there (the causes that
        # act at a place build their columns on these)
        self.step_bin, self.step_moving = j, mov
        gper = -G / 1000.0 * self.k_grad  # m/s^2 per permille (small-angle: sin(atan p) ~ p)
        inc = np.where(mov, gper * g.dt, 0.0)
        Gv = np.zeros((ev.t.size, nb))
        Gs = np.zeros((ev.t.size, nb))
        np.add.at(Gv, (g.k, j), inc)
        np.add.at(Gs, (g.k, j), inc * g.lever)
        return Gv, Gs

    def _believed_drift(self) -> None:
        """The fixed (believed) part: a_tr + f0 a_br - resistance - mapped gradient."""
        v, g = self.v_ref, self.grid
        base = (self.a_tr0 + self.f0 * self.a_br0 - (self.alpha0 + (self.beta0 + self.gamma0 * v)
                                                     * v)
                - self.line.gradient_accel(self.x_ref) * self.k_grad) * self.moving
        bv0, bs0 = g.integrate(base[:, None], self.ev.t.size)
        self.base_v, self.base_s = bv0[:, 0], bs0[:, 0]

    def _part(self, shift: float, part: str, brake_shift: float = 0.0):
        """The believed actuator's ``part`` ("traction" or "braking") on the grid, with the
        commands re-timed by ``shift`` s and the braking delayed ``brake_shift`` s more than
        the shift leaves it."""
        b = self.train.brake
        delay = b.delay if part == "traction" else b.delay - shift + brake_shift
        return grid_part(self.grid.t, self.run.ctrl_t + shift, self.run.ctrl_a,
                         b.time_constant, delay, part)


# the shapes an episode's slip fraction may take over its interval [t0, t1), as a weight of
# the peak fraction at the share x = (t - t0) / (t1 - t0) of the interval: held from the first
# instant to the last (``step``), or built up and died away smoothly as adhesion is lost and
# regained (``sine``, a half sine). A trapezoid (linear ramps over a quarter at each end) was
# tried as well: it fitted a drag on a stretch, a motion misfit, as a 1.7 % slip at a departure.
SLIP_SHAPES = ("step", "sine")


def slip_shape(shape: str, x) -> np.ndarray:
    """-, the weight of the peak slip fraction at the shares ``x`` of an episode (0 outside
    [0, 1))."""
    x = np.asarray(x, float)
    inside = (x >= 0.0) & (x < 1.0)
    if shape == "step":
        return inside.astype(float)
    if shape == "sine":
        return np.where(inside, np.sin(np.pi * np.clip(x, 0.0, 1.0)), 0.0)
    raise ValueError(f"slip shape {shape!r}: one of {SLIP_SHAPES}")


def slip_cols(mo: Motion, intervals) -> tuple[np.ndarray, np.ndarray]:
    """Measurement columns of slip episodes with unit coefficient: the odometer's own speed
    inside, and after t_k the distance the odometer counted over the part of the episode before
    t_k. Both already hold the episode (the odometer reads (1 + eps) v there), so a coefficient
    theta is the slip fraction eps = theta / (1 - theta), at every sample of the episode alike
    (a reference speed smoothed across the onset would be partly slipped at the edges only).
    An interval is (t0, t1) or (t0, t1, shape) (:data:`SLIP_SHAPES`, default ``step``): with a
    shape, both are weighted by it (:func:`slip_shape`) and theta is the slip at its peak."""
    ev = mo.ev
    md = np.zeros(ev.t.size)
    mv = np.zeros(ev.t.size)
    o = ev.odo
    t = ev.t[o]
    for iv in intervals:
        t0, t1 = float(iv[0]), float(iv[1])
        shape = iv[2] if len(iv) > 2 else "step"
        inside = (t >= t0) & (t < t1)
        if shape == "step":
            mv[o[inside]] += odometer_speed(mo, t[inside])
            c0 = counted(mo, t0)
            md[o] += np.clip(counted(mo, np.minimum(t, t1)) - c0, 0.0, None)
            continue
        span = max(t1 - t0, 1e-9)
        mv[o[inside]] += slip_shape(shape, (t[inside] - t0) / span) * odometer_speed(
            mo, t[inside])
        # the counted distance weighted by the shape, on the odometer's own samples
        ro = mo.run.odo_t
        g = np.concatenate([[t0], ro[(ro > t0) & (ro < t1)], [t1]])
        w = slip_shape(shape, (0.5 * (g[1:] + g[:-1]) - t0) / span)
        cum = np.concatenate([[0.0], np.cumsum(w * np.diff(counted(mo, g)))])
        md[o] += np.interp(t, g, cum, left=0.0, right=float(cum[-1]))
    return md, mv


def odometer_speed(mo: Motion, t) -> np.ndarray:
    """m/s, the odometer's measured speed at times ``t`` (linear between samples, >= 0)."""
    return np.clip(np.interp(t, mo.run.odo_t, mo.run.odo_v), 0.0, None)


def counted(mo: Motion, t) -> np.ndarray:
    """m, the odometer's counted distance at times ``t`` (linear between samples)."""
    return np.interp(t, mo.run.odo_t, mo.run.odo_d)
