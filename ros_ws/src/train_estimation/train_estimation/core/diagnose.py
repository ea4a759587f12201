"""`diagnose` core: what the believed model of a train gets wrong in measured data.

Given one run (odometer, balise and control series with the bag's log times) and the railway's
believed ``line.yaml``/``train.yaml``, find which of docs/interfaces.md's causes explains the data,
fit it, and rank every cause.

The model (train_core physics, as ``identify``; Zheng et al. 2015 eq. (1) for the actuator)::

    ds/dt = v
    dv/dt = a_tr(t) + f0 a_br(t) - (alpha + beta v + gamma v^2)
            - g sin(theta(s0 + s)) / (1 + lambda) + sum_j theta_j r_j(t) + w,   w white, PSD q
    odometer:  d_k = s(t_k) + m_d,k . theta + e_d,    y_k = v(t_k) + m_v,k . theta + e_v
    balise:    p_b = s0 + s(t_b) + e_b

``a_tr``/``a_br`` are the traction and braking parts of the recorded commands through the
believed delay and lag (identify.actuator_output). Every cause is a set of extra drift columns
``r_j`` (gradient section, Davis terms, braking gain and its drift, the traction gain of a wrong
mass, the braking command re-timed by an extra delay) or measurement columns ``m_j`` (odometer
scale, slip episodes), linear in its parameters once the nonlinear ones (section ends, delay,
slip intervals) are fixed. The regressors are evaluated on a reference trajectory (smoothed
odometer speed, and odometer distance placed on the line piecewise between balise fixes, so a
wrong odometer scale does not misplace the map's gradient changes).

Exact likelihood for all causes from one filter run: the Kalman gains do not depend on the
drift or measurement columns, so one *augmented* Kalman filter run (de Jong 1991; the
``identify`` GLS) carrying every elementary column gives the matrix W = sum_k E_k^T S_k^-1 E_k
over [data, columns], and the exact log-likelihood of any hypothesis z = [1, theta] is
-0.5 (sum log det S_k + m log 2 pi + z^T W z). A hypothesis that is a linear combination of
elementary columns is then a small quadratic problem: a gradient section is a sum of position
bins (all sections by 2-D prefix sums), a brake delay picks one column of re-timed braking
commands (a grid of delays), the mass hypothesis is one combination of the traction, braking and
resistance columns. Nonlinear parameters are profiled over those grids.

Decision (the same for every cause): the score is the BIC-penalised log-likelihood ratio
against the current null with the prior odds of K causes against ``none``,
``2 (ll_cause - ll_null) - k ln n - 2 ln K`` (k = the cause's parameter count, profiled ones
included; n = number of scalar measurements of the likelihood it lives in; K = causes scored in
the stage). A cause is accepted when its score is > 0; ``none`` has score 0. Causes outside
the motion model have likelihoods of their own: the train clock (log time against stamp,
Gaussian jitter) and the link (Bernoulli against a two-state Markov chain on the loss
sequence). Two effects:
greedy: the best cause is put into the null (its fit fixed, noise refitted) and the rest are
scored again; at the end the accepted causes that are linear in their parameters are refitted
jointly (a cause accepted first must not keep the part of a later one it absorbed).

Gradient against resistance: on one run position and speed go together, so a long gradient
"section" at cruise speed is running resistance by another name (a line-long section is exactly
the Davis a-term). A gradient section is therefore searched and scored with the Davis terms free
as nuisance: it is named only for what resistance cannot explain (a map error is local).

Clocks (docs/interfaces.md): odometer and balise stamps are on the train's clock, control on the
reference clock. The rate and offset between them come from the odometer's (stamp, log time)
pairs; control stamps are mapped onto the train clock, and a residual common command-time offset
(the link's mean latency) is a nuisance parameter profiled with the brake timing. Times in the
report are seconds since the first odometer stamp, on the stamp clock.

Pure: numpy/scipy and train_core only.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize_scalar
from train_core.model import G, Line, TrainParams

from .augmented_kf import (
    LOG2PI,
    Events,
    augmented_kf,
    balise_update,
    gls,
    odometer_update,
    predict_cov,
)
from .clocks import ClockFit
from .identify import actuator_output, moving_average

CAUSES = ("gradient", "resistance", "braking_rate", "odometer_scale", "wheel_slip",
          "bursty_link", "brake_delay", "mass", "clock_drift")
MOTION_CAUSES = ("gradient", "resistance", "braking_rate", "brake_delay", "mass")
RESISTANCE_COLS = ("one", "v", "v2")  # the Davis terms' elementary columns (a, b, c)
REFIT_CAUSES = MOTION_CAUSES + ("odometer_scale", "wheel_slip")


class DiagnoseError(ValueError):
    """The data cannot be diagnosed (unusable input); the message is one line saying what is
    missing or wrong and what to do."""


@dataclass(frozen=True)
class DiagData:
    """Measured series of one run, as recorded (docs/interfaces.md clocks):

    odometer and balise ``*_stamp`` are on the train's clock (arbitrary epoch, may drift);
    ``control`` stamps are on the reference clock; ``*_recv`` are the bag's log (receive) times
    on the reference clock, s. Arrays in bag order (not necessarily sorted)."""

    odo_stamp: np.ndarray  # s, train clock
    odo_recv: np.ndarray  # s, reference clock (bag log time)
    odo_seq: np.ndarray  # -, uint32 sample counter before the link
    odo_distance: np.ndarray  # m
    odo_speed: np.ndarray  # m/s
    odo_speed_variance: np.ndarray  # (m/s)^2
    ctrl_stamp: np.ndarray  # s, reference clock
    ctrl_a_tar: np.ndarray  # m/s^2
    balise_stamp: np.ndarray  # s, train clock
    balise_recv: np.ndarray  # s, reference clock
    balise_id: np.ndarray  # -
    balise_position: np.ndarray  # m, surveyed position
    balise_variance: np.ndarray  # m^2


@dataclass(frozen=True)
class DiagConfig:
    max_rate: float = 5.0  # Hz, odometer samples are decimated to at most this rate
    grid_dt: float = 0.02  # s, grid of the actuator and the regressor integrals
    min_duration: float = 120.0  # s, shorter runs are refused
    min_speed: float = 1.0  # m/s, the train must exceed this somewhere
    min_brake: float = 0.05  # m/s^2, |a_Tar| above this counts as braking
    standstill_speed: float = 1.0  # m/s, intervals reaching below this are not modelled
    standstill_q: float = 1.0  # (m/s^2)^2 s, process noise there (the filter follows data)
    # (m/s^2)^2 s, smallest process-noise PSD: a real train has unmodelled accelerations (wind,
    # adhesion, track) of a few mm/s^2; without a floor a noise-free simulator drives q to 0
    # and any small mismatch of timing or discretisation passes for a second cause
    q_floor: float = 1e-5
    gradient_bin: float = 25.0  # m, finest resolution of the gradient-section search
    max_bins: int = 240  # at most this many position bins (coarser bins on long runs)
    min_section: float = 100.0  # m, shortest gradient section considered
    shift_grid: tuple = (-0.2, 0.4, 0.025)  # s, command-time offsets (nuisance): lo, hi, step
    delay_grid: tuple = (0.0, 1.6, 0.025)  # s, extra braking delays tested: lo, hi, step
    slip_threshold: float = 3.0  # |standardised speed innovation| that opens a slip candidate
    max_slip_candidates: int = 8
    stages: int = 3  # greedy stages (causes put into the null one after the other)
    gain_block: float = 30.0  # s, alternating fit/held-out blocks for the gain
    gain_min_change: float = 0.05  # m/s, RMS change of a block's prediction that counts
    noise_refits: int = 2  # best causes of a stage whose score is recomputed at their own noise


@dataclass
class Diagnosis:
    cause: str  # first entry of ranking
    parameters: dict  # its parameters (docs/interfaces.md units)
    ranking: list  # [{"cause", "score", "parameters"}], best first, "none" included
    untestable: list  # [{"cause", "why"}]
    evidence: dict  # per cause: log-likelihood gain, penalty, n, standard errors, ...
    gain: dict  # {"metric", "before", "after", ...} for the top cause
    accepted: list  # causes with score > 0 after the greedy refit, in order: [{"cause", ...}]
    series: dict = field(default_factory=dict)  # arrays for the plots


# =============================================================================================
# Preparation: order, clocks, decimation
# =============================================================================================


@dataclass
class _Run:
    """The run on one time axis: seconds since the first odometer sample on the reference
    clock (``odo_stamp``: the same on the train's clock, for the clock test and the report)."""

    t_first: float  # s, first odometer stamp (train clock)
    duration: float  # s
    odo_t: np.ndarray
    odo_stamp: np.ndarray
    odo_d: np.ndarray
    odo_v: np.ndarray
    odo_rv: np.ndarray
    odo_seq: np.ndarray  # unwrapped, int64
    odo_recv: np.ndarray
    ctrl_t: np.ndarray  # mapped onto the train clock
    ctrl_a: np.ndarray
    bal_t: np.ndarray
    bal_p: np.ndarray
    bal_r: np.ndarray
    bal_id: np.ndarray
    clock: dict
    notes: list


def _arr(x, dtype=float):
    return np.asarray(x if x is not None else [], dtype=dtype).ravel()


def _prepare(data: DiagData, line: Line, cfg: DiagConfig) -> _Run:
    notes = []
    odo_s, odo_r = _arr(data.odo_stamp), _arr(data.odo_recv)
    if odo_s.size == 0:
        raise DiagnoseError("no odometer messages in the bag: record the 'odometer' topic")
    if _arr(data.ctrl_stamp).size == 0:
        raise DiagnoseError("no control messages in the bag: diagnose replays the recorded "
                            "commands, record the 'control' topic")
    if _arr(data.balise_stamp).size == 0:
        raise DiagnoseError("no balise readings in the bag: the run cannot be placed on the "
                            "line (record the 'balise' topic)")
    fields = {"odo_distance": _arr(data.odo_distance), "odo_speed": _arr(data.odo_speed),
              "odo_speed_variance": _arr(data.odo_speed_variance)}
    ok = np.isfinite(odo_s) & np.isfinite(odo_r)
    for v in fields.values():
        if v.size != odo_s.size:
            raise DiagnoseError("odometer arrays differ in length")
        ok &= np.isfinite(v)
    ok &= fields["odo_speed_variance"] > 0
    if (~ok).sum():
        notes.append(f"{int((~ok).sum())} odometer readings with non-finite values or "
                     "non-positive variance dropped")
    seq = _arr(data.odo_seq, np.int64)
    if seq.size != odo_s.size:
        seq = np.arange(odo_s.size)
    idx = np.flatnonzero(ok)
    idx = idx[np.argsort(odo_s[idx], kind="stable")]
    # duplicates (same stamp) keep the first
    keep = np.concatenate([[True], np.diff(odo_s[idx]) > 0])
    if (~keep).sum():
        notes.append(f"{int((~keep).sum())} duplicate odometer stamps dropped")
    idx = idx[keep]
    s_odo, r_odo = odo_s[idx], odo_r[idx]
    # ---- clock: log time r = alpha + beta * stamp + latency (OLS; latency mean in alpha) -----
    cf = ClockFit.fit(s_odo, r_odo)
    t_first, alpha, beta = cf.t_first, cf.alpha, cf.beta
    x = s_odo - t_first
    if not (0.5 < beta < 1.5):
        raise DiagnoseError(f"odometer stamps and log times disagree (rate {beta:.3g}): the "
                            "bag's log times must be receive times on one clock")
    clock = {"alpha": alpha, "beta": beta}

    ctrl_s = _arr(data.ctrl_stamp)
    ctrl_a = _arr(data.ctrl_a_tar)
    if ctrl_a.size != ctrl_s.size:
        raise DiagnoseError("control arrays differ in length")
    okc = np.isfinite(ctrl_s) & np.isfinite(ctrl_a)
    order = np.argsort(ctrl_s[okc], kind="stable")
    # The motion is analysed on the reference clock (true seconds, so accelerations are not
    # scaled by a drifting train clock): odometer/balise times beta * (stamp - t_first), control
    # stamps less alpha. Times reported in parameters go back to the stamp clock (/ beta).
    ctrl_t = cf.ref_of_control(ctrl_s[okc][order])
    ctrl_a = ctrl_a[okc][order]
    keepc = np.concatenate([[True], np.diff(ctrl_t) > 0]) if ctrl_t.size else ctrl_t
    ctrl_t, ctrl_a = ctrl_t[keepc], ctrl_a[keepc]

    bal_s = _arr(data.balise_stamp)
    bp, br = _arr(data.balise_position), _arr(data.balise_variance)
    bid = _arr(data.balise_id, np.int64)
    okb = np.isfinite(bal_s) & np.isfinite(bp) & (np.isfinite(br) & (br > 0))
    known = {b.id: b.position for b in line.balises}
    if known:
        unknown = np.array([int(i) not in known for i in bid], dtype=bool)
        contra = np.array([(int(i) in known and abs(known[int(i)] - p) > 1.0)
                           for i, p in zip(bid, bp)], dtype=bool)
        if unknown.any():
            notes.append(f"{int(unknown.sum())} balise readings with ids not in line.yaml: "
                         "their reported positions are used")
        if contra.any():
            notes.append(f"{int(contra.sum())} balise readings contradict line.yaml's position: "
                         "line.yaml's is used")
            bp = np.where(contra, [known.get(int(i), p) for i, p in zip(bid, bp)], bp)
    ob = np.argsort(bal_s[okb], kind="stable")
    bal_t = beta * (bal_s[okb][ob] - t_first)
    t_end = float(beta * (s_odo[-1] - t_first))
    inside = (bal_t > 0) & (bal_t < t_end)
    bal_t = bal_t[inside]
    if bal_t.size == 0:
        raise DiagnoseError("no balise reading falls inside the odometer record: the run "
                            "cannot be placed on the line")

    v = fields["odo_speed"][idx]
    if t_end < cfg.min_duration:
        raise DiagnoseError(f"run too short: {t_end:.0f} s of odometer data (need >= "
                            f"{cfg.min_duration:g} s)")
    if np.max(v) < cfg.min_speed:
        raise DiagnoseError(f"the train never moves (max odometer speed {np.max(v):.2f} m/s)")
    if ctrl_t.size < 2 or ctrl_t[-1] < 0.0 or ctrl_t[0] > t_end:
        raise DiagnoseError("the control commands do not overlap the odometer record")

    return _Run(
        t_first=t_first, duration=t_end, odo_t=beta * x, odo_stamp=x,
        odo_d=fields["odo_distance"][idx],
        odo_v=v, odo_rv=fields["odo_speed_variance"][idx], odo_seq=_unwrap(seq[idx]),
        odo_recv=r_odo, ctrl_t=ctrl_t, ctrl_a=ctrl_a, bal_t=bal_t,
        bal_p=bp[okb][ob][inside], bal_r=br[okb][ob][inside], bal_id=bid[okb][ob][inside],
        clock=clock, notes=notes)


def _unwrap(seq: np.ndarray) -> np.ndarray:
    """uint32 sequence numbers in time order -> increasing int64 (wrap-around at 2^32)."""
    s = seq.astype(np.int64)
    d = np.diff(s)
    d = np.where(d < -(2 ** 31), d + 2 ** 32, d)
    return np.concatenate([[0], np.cumsum(d)]) + (s[0] if s.size else 0)


# =============================================================================================
# The clock and the link: likelihoods of their own
# =============================================================================================


def clock_test(run: _Run) -> dict:
    """Train clock rate against the reference clock: log time r = alpha + beta s + jitter.

    Null: beta = 1 (no drift); alternative: beta free. Gaussian jitter with its variance
    profiled; floor 1 us^2 (time resolution) so a jitter-free log does not divide by zero.
    drift = 1 / beta - 1 (stamp rate minus 1, docs/interfaces.md)."""
    s, r = run.odo_stamp, run.odo_recv
    n = s.size
    res0 = r - s
    rss0 = float(np.sum((res0 - res0.mean()) ** 2))
    A = np.stack([np.ones_like(s), s], axis=1)
    coef, *_ = np.linalg.lstsq(A, r, rcond=None)
    res1 = r - A @ coef
    rss1 = float(np.sum(res1 ** 2))
    floor = n * 1e-12
    dll = 0.5 * n * (math.log(max(rss0, floor)) - math.log(max(rss1, floor)))
    beta = float(coef[1])
    sig2 = max(rss1, floor) / max(n - 2, 1)
    se_beta = math.sqrt(sig2 / max(float(np.sum((s - s.mean()) ** 2)), 1e-12))
    drift = 1.0 / beta - 1.0
    half = s < 0.5 * s[-1]
    # held out: fit on the first half, predict the second half's log times
    gain = None
    if half.sum() > 10 and (~half).sum() > 10:
        c1, *_ = np.linalg.lstsq(A[half], r[half], rcond=None)
        off0 = float(np.median(r[half] - s[half]))
        before = float(np.sqrt(np.mean((r[~half] - s[~half] - off0) ** 2)))
        after = float(np.sqrt(np.mean((r[~half] - A[~half] @ c1) ** 2)))
        gain = {"metric": "held-out stamp residual RMS (s), second half predicted from the first",
                "before": before, "after": after}
    return {"dll": dll, "k": 1, "n": n, "parameters": {"drift": drift},
            "std_errors": {"drift": se_beta / beta ** 2}, "jitter_std": math.sqrt(sig2),
            "gain": gain}


def link_test(run: _Run) -> dict:
    """Odometer losses (gaps in seq): Bernoulli (one loss probability) against a two-state
    Markov chain on received/lost (Gilbert-Elliott with loss_good = 0, loss_bad = 1, whose state
    is then observed). p_good_bad = P(lost | previous received), p_bad_good = P(received |
    previous lost), per odometer sample."""
    seq = run.odo_seq
    seq = np.unique(seq)
    n = int(seq[-1] - seq[0] + 1) if seq.size else 0
    if n < 20 or n > 50 * seq.size:
        return {"dll": 0.0, "k": 1, "n": max(n, 1), "parameters": {}, "untestable":
                "too few odometer samples or sequence numbers that jump (sensor resets)"}
    recv = np.zeros(n, dtype=bool)
    recv[seq - seq[0]] = True
    return markov_vs_bernoulli(recv)


def markov_vs_bernoulli(recv: np.ndarray) -> dict:
    recv = np.asarray(recv, dtype=bool)
    n = recv.size

    def xlogy(a, b):
        return a * math.log(b) if a > 0 else 0.0

    lost = int((~recv).sum())
    p = lost / n
    ll0 = xlogy(lost, p) + xlogy(n - lost, 1 - p)
    prev, nxt = recv[:-1], recv[1:]
    n_rl = int((prev & ~nxt).sum())
    n_rr = int((prev & nxt).sum())
    n_lr = int((~prev & nxt).sum())
    n_ll = int((~prev & ~nxt).sum())
    p_gb = n_rl / max(n_rr + n_rl, 1)
    p_bg = n_lr / max(n_lr + n_ll, 1)
    first = xlogy(1, p) if not recv[0] else xlogy(1, 1 - p)
    ll1 = (first + xlogy(n_rl, p_gb) + xlogy(n_rr, 1 - p_gb) + xlogy(n_lr, p_bg)
           + xlogy(n_ll, 1 - p_bg))
    se = {"p_good_bad": math.sqrt(max(p_gb * (1 - p_gb), 1e-12) / max(n_rr + n_rl, 1)),
          "p_bad_good": math.sqrt(max(p_bg * (1 - p_bg), 1e-12) / max(n_lr + n_ll, 1))}
    out = {"dll": ll1 - ll0, "k": 1, "n": n,
           "parameters": {"p_good_bad": p_gb, "p_bad_good": max(p_bg, 1e-6)},
           "std_errors": se, "loss_fraction": p, "loss_runs": _runs(~recv)}
    # held out: fit on the first half, log-likelihood per sample on the second
    h = n // 2
    if h > 20:
        a, b = recv[:h], recv[h:]
        pa = max(min(float((~a).sum()) / a.size, 1 - 1e-6), 1e-6)
        pa_rl = (a[:-1] & ~a[1:]).sum() / max(a[:-1].sum(), 1)
        pa_lr = (~a[:-1] & a[1:]).sum() / max((~a[:-1]).sum(), 1)
        pa_rl = min(max(pa_rl, 1e-6), 1 - 1e-6)
        pa_lr = min(max(pa_lr, 1e-6), 1 - 1e-6)
        before = float(np.mean(np.where(b, math.log(1 - pa), math.log(pa))))
        pb, nb = b[:-1], b[1:]
        lp = np.where(pb, np.where(nb, math.log(1 - pa_rl), math.log(pa_rl)),
                      np.where(nb, math.log(pa_lr), math.log(1 - pa_lr)))
        after = float(np.mean(lp))
        out["gain"] = {"metric": "held-out log-likelihood per odometer sample (second half, "
                                 "fitted on the first)", "before": before, "after": after}
    return out


def _runs(mask: np.ndarray) -> np.ndarray:
    m = np.concatenate([[False], mask, [False]]).astype(np.int8)
    d = np.diff(m)
    return np.flatnonzero(d == -1) - np.flatnonzero(d == 1)


# =============================================================================================
# The motion model: events, columns, the augmented Kalman filter
# =============================================================================================


def _events(run: _Run, cfg: DiagConfig) -> Events:
    # decimate by time: first sample in each 1/max_rate slot
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


class _Grid:
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
        Bv[k] = int r over interval k, Bs[k] = int (t_k - tau) r(tau) dtau (midpoint rule)."""
        inc = 0.5 * (R[1:] + R[:-1]) * self.dt
        Bv = np.zeros((n_ev, R.shape[1]))
        Bs = np.zeros((n_ev, R.shape[1]))
        Bv[self.kk] = np.add.reduceat(inc, self.starts, axis=0)
        Bs[self.kk] = np.add.reduceat(inc * self.lever[:, None], self.starts, axis=0)
        return Bv, Bs


def _kf2_loglik(ev: Events, q: float, r_s: float, bv, bs, md, mv, q_held: float) -> float:
    """Profile log-likelihood of the two-column problem [fixed model, s0] (scalar loop, used
    for the noise fit): s0 is eliminated exactly by GLS."""
    n = ev.t.size
    xs0, xv0 = ev.y_d[0] - md[0], ev.y_v[0] - mv[0]
    xs1 = xv1 = 0.0
    p00, p01, p11 = r_s, 0.0, float(ev.r_v[0])
    w00 = w01 = w11 = 0.0
    logdet, m = 0.0, 0
    t, kind, yd, yv, rv, held = (ev.t.tolist(), ev.kind.tolist(), ev.y_d.tolist(),
                                 ev.y_v.tolist(), ev.r_v.tolist(), ev.held.tolist())
    bv, bs, md, mv = bv.tolist(), bs.tolist(), md.tolist(), mv.tolist()
    for k in range(1, n):
        h = t[k] - t[k - 1]
        qk = q_held if held[k] else q
        xs0 += h * xv0 + bs[k]
        xv0 += bv[k]
        xs1 += h * xv1
        p00, p01, p11 = predict_cov(p00, p01, p11, h, qk)
        if kind[k] == 0:
            _, _, _, det, (i00, i01, i11), (k00, k01, k10, k11), pn = odometer_update(
                p00, p01, p11, r_s, rv[k])
            es0, ev0 = yd[k] - xs0 - md[k], yv[k] - xv0 - mv[k]
            es1, ev1 = -xs1, -xv1
            w00 += es0 * (i00 * es0 + i01 * ev0) + ev0 * (i01 * es0 + i11 * ev0)
            w01 += es0 * (i00 * es1 + i01 * ev1) + ev0 * (i01 * es1 + i11 * ev1)
            w11 += es1 * (i00 * es1 + i01 * ev1) + ev1 * (i01 * es1 + i11 * ev1)
            logdet += math.log(det)
            m += 2
            xs0 += k00 * es0 + k01 * ev0
            xv0 += k10 * es0 + k11 * ev0
            xs1 += k00 * es1 + k01 * ev1
            xv1 += k10 * es1 + k11 * ev1
            p00, p01, p11 = pn
        else:
            s, (k0, k1), pn = balise_update(p00, p01, p11, rv[k])
            e0, e1 = yd[k] - xs0, -xs1 - 1.0
            w00 += e0 * e0 / s
            w01 += e0 * e1 / s
            w11 += e1 * e1 / s
            logdet += math.log(s)
            m += 1
            xs0 += k0 * e0
            xv0 += k1 * e0
            xs1 += k0 * e1
            xv1 += k1 * e1
            p00, p01, p11 = pn
    quad = w00 - w01 * w01 / w11 if w11 > 0 else w00
    return -0.5 * (logdet + m * LOG2PI + quad)


# =============================================================================================
# The analysis of one stage
# =============================================================================================


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
    x = np.interp(d, db, pb)
    x = np.where(d < db[0], pb[0] + k * (d - db[0]), x)
    return np.where(d > db[-1], pb[-1] + k * (d - db[-1]), x)


class _Motion:
    """Columns of the motion model on the events of one run, built once."""

    def __init__(self, run: _Run, line: Line, train: TrainParams, cfg: DiagConfig):
        self.run, self.line, self.train, self.cfg = run, line, train, cfg
        ev = _events(run, cfg)
        self.ev = ev
        g = _Grid(ev, cfg.grid_dt)
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
        self.a_tr0, self.a_br0 = self._act(0.0, 0.0)
        # shifts (nuisance) and extra braking delays
        lo, hi, st = cfg.shift_grid
        self.shifts = np.round(np.arange(lo, hi + 1e-9, st), 6)
        lo, hi, st = cfg.delay_grid
        self.delays = np.round(np.arange(lo, hi + 1e-9, st), 6)
        # elementary columns ------------------------------------------------------------------
        names, R = [], []
        v = self.v_ref

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
                a_tr, _ = self._act(s, 0.0)
                add(f"T{s:+.3f}", a_tr - self.a_tr0)
        self.braking_cols = {}
        for s in self.shifts:
            for d in self.delays:
                key = round(float(s + d), 6)
                if key == 0.0 or key in self.braking_cols:
                    continue
                _, a_br = self._act(key, key)
                self.braking_cols[key] = f"B{key:+.3f}"
                add(f"B{key:+.3f}", self.f0 * (a_br - self.a_br0))
        self.dense_names = names
        Bv, Bs = g.integrate(np.stack(R, axis=1), ev.t.size)
        # gradient bins (sparse: one bin per grid step)
        xm = 0.5 * (self.x_ref[1:] + self.x_ref[:-1])
        mov = 0.5 * (moving[1:] + moving[:-1]) > 0.5
        lo_x, hi_x = float(np.min(xm[mov])) if mov.any() else 0.0, \
            float(np.max(xm[mov])) if mov.any() else 1.0
        width = max(cfg.gradient_bin, (hi_x - lo_x) / cfg.max_bins)
        nb = max(1, int(math.ceil((hi_x - lo_x) / width)))
        self.bin_edges = lo_x + width * np.arange(nb + 1)
        j = np.clip(((xm - lo_x) / width).astype(int), 0, nb - 1)
        gper = -G / 1000.0 * self.k_grad  # m/s^2 per permille (small-angle: sin(atan p) ~ p)
        inc = np.where(mov, gper * g.dt, 0.0)
        Gv = np.zeros((ev.t.size, nb))
        Gs = np.zeros((ev.t.size, nb))
        np.add.at(Gv, (g.k, j), inc)
        np.add.at(Gs, (g.k, j), inc * g.lever)
        # fixed (believed) part: a_tr + f0 a_br - resistance - mapped gradient
        base = (self.a_tr0 + self.f0 * self.a_br0 - (self.alpha0 + (self.beta0 + self.gamma0 * v)
                                                     * v)
                - line.gradient_accel(self.x_ref) * self.k_grad) * moving
        bv0, bs0 = g.integrate(base[:, None], ev.t.size)
        self.base_v, self.base_s = bv0[:, 0], bs0[:, 0]
        self.Dv = np.concatenate([Bv, Gv], axis=1)
        self.Ds = np.concatenate([Bs, Gs], axis=1)
        self.names = names + [f"G{i}" for i in range(nb)]
        self.col = {n: i for i, n in enumerate(self.names)}
        self.n_bins = nb
        # measurement columns: odometer scale (scale - 1) * (s, v) of the reference
        n = ev.t.size
        self.sc_d = np.zeros(n)
        self.sc_v = np.zeros(n)
        o = ev.odo
        self.sc_d[o] = np.interp(ev.t[o], g.t, d_ref)
        self.sc_v[o] = np.interp(ev.t[o], g.t, self.v_ref)

    def _act(self, shift: float, brake_shift: float):
        b = self.train.brake
        return actuator_output(self.grid.t, self.run.ctrl_t + shift, self.run.ctrl_a,
                               b.time_constant, b.delay, b.delay - shift + brake_shift)


@dataclass
class _Null:
    """What the current null adds to the believed model (accepted causes, nuisance shift)."""

    drift: dict = field(default_factory=dict)  # elementary drift column name -> coefficient
    scale: float = 0.0  # odometer (scale - 1)
    slip: list = field(default_factory=list)  # [(t0, t1, eps)]
    shift: float = 0.0  # s, command-time offset
    brake_extra: float = 0.0  # s, extra braking delay
    gradient: tuple | None = None  # (bin i, bin j, permille)


def _slip_cols(mo: _Motion, intervals) -> tuple[np.ndarray, np.ndarray]:
    """Measurement columns of slip episodes with unit fraction: speed v_ref inside, distance
    the integral of v_ref over the part of the episode before t_k."""
    ev, g = mo.ev, mo.grid
    md = np.zeros(ev.t.size)
    mv = np.zeros(ev.t.size)
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (mo.v_ref[1:] + mo.v_ref[:-1]) * g.dt)])
    o = ev.odo
    t = ev.t[o]
    for t0, t1 in intervals:
        inside = (t >= t0) & (t < t1)
        mv[o[inside]] += np.interp(t[inside], g.t, mo.v_ref)
        c0 = np.interp(t0, g.t, cum)
        md[o] += np.clip(np.interp(np.minimum(t, t1), g.t, cum) - c0, 0.0, None)
    return md, mv


class _Stage:
    """One greedy stage: the null (believed model + accepted causes), its noise, the augmented
    filter over every elementary column, and each cause's best fit and score."""

    def __init__(self, mo: _Motion, null: _Null, cfg: DiagConfig, noise=None, update=None,
                 big=True):
        self.mo, self.null, self.cfg = mo, null, cfg
        # fixed part of drift and measurement (column 0)
        fv, fs = mo.base_v.copy(), mo.base_s.copy()
        for name, c in self._null_drift().items():
            j = mo.col[name]
            fv += c * mo.Dv[:, j]
            fs += c * mo.Ds[:, j]
        md = null.scale * mo.sc_d
        mv = null.scale * mo.sc_v
        for t0, t1, eps in null.slip:
            a, b = _slip_cols(mo, [(t0, t1)])
            md = md + eps * a
            mv = mv + eps * b
        self.fv, self.fs, self.md, self.mv = fv, fs, md, mv
        if noise is None:
            noise = self._fit_noise()
        self.q, self.r_s = noise
        if not big:
            return
        # the big run: [fixed, s0, elementary drift columns..., scale]
        self.p = mo.Dv.shape[1]
        self.kf = self.augmented(fv, fs, drift=(mo.Dv, mo.Ds),
                                 meas=(mo.sc_d[:, None], mo.sc_v[:, None]), keep_innov=True,
                                 update=update)
        self.n_meas = self.kf.m

    def augmented(self, fv: np.ndarray, fs: np.ndarray, drift=None, meas=None, **kw):
        """One augmented filter at this stage's noise over the columns [fixed part (drift fv,
        fs; the null's measurement part), s0, drift columns ``drift = (Dv, Ds)``...,
        measurement columns ``meas = (Md, Mv)``...] (each pair (n_ev, k) or None)."""
        n = self.mo.ev.t.size
        a = 0 if drift is None else drift[0].shape[1]
        b = 0 if meas is None else meas[0].shape[1]
        Bv, Bs, Md, Mv, Mb = (np.zeros((n, a + b + 2)) for _ in range(5))
        Bv[:, 0], Bs[:, 0] = fv, fs
        Md[:, 0], Mv[:, 0] = self.md, self.mv
        Mb[:, 1] = 1.0
        if a:
            Bv[:, 2:a + 2], Bs[:, 2:a + 2] = drift
        if b:
            Md[:, a + 2:], Mv[:, a + 2:] = meas
        return augmented_kf(self.mo.ev, self.q, self.r_s, Bv, Bs, Md, Mv, Mb,
                            self.cfg.standstill_q, **kw)

    # -- helpers --------------------------------------------------------------------------------
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

    def _fit_noise(self):
        """Process-noise PSD q and distance-noise variance r_s by maximum likelihood under this
        stage's null (s0 profiled): coordinate-wise bounded Brent searches on their logs, q
        first (it matters most), then r_s, then q again (the two trade off against each other:
        too small a distance noise makes q absorb it)."""
        ev, cfg = self.mo.ev, self.cfg

        def ll(lq, lr):
            return _kf2_loglik(ev, math.exp(lq), math.exp(lr), self.fv, self.fs, self.md,
                               self.mv, cfg.standstill_q)

        lr = math.log(max(float(np.median(self.mo.run.odo_rv)), 1e-4))
        q_lo, q_hi, r_lo, r_hi = (math.log(cfg.q_floor), math.log(1.0), math.log(1e-6),
                                  math.log(25))
        opts = {"xatol": 0.1, "maxiter": 14}
        lq = minimize_scalar(lambda x: -ll(x, lr), bounds=(q_lo, q_hi), method="bounded",
                             options=opts).x
        lr = minimize_scalar(lambda x: -ll(lq, x), bounds=(r_lo, r_hi), method="bounded",
                             options=opts).x
        lq = minimize_scalar(lambda x: -ll(x, lr), bounds=(q_lo, q_hi), method="bounded",
                             options=opts).x
        return float(math.exp(lq)), float(math.exp(lr))

    def fixed_loglik(self) -> float:
        """Log-likelihood of this stage's null at its noise, s0 profiled (scalar filter)."""
        return _kf2_loglik(self.mo.ev, self.q, self.r_s, self.fv, self.fs, self.md, self.mv,
                           self.cfg.standstill_q)

    def _M(self, fixed: dict, free: list) -> np.ndarray:
        """[1, theta] -> full z over [fixed, s0, elementary..., scale]. ``fixed``: column name
        -> coefficient added to z[0]'s combination; ``free``: list of {column name: weight}
        (s0 is always free, first)."""
        p = self.p
        M = np.zeros((p + 3, 2 + len(free)))
        M[0, 0] = 1.0
        for name, c in fixed.items():
            M[self._j(name), 0] += c
        M[1, 1] = 1.0  # s0
        for i, combo in enumerate(free):
            for name, c in combo.items():
                M[self._j(name), 2 + i] += c
        return M

    def _j(self, name: str) -> int:
        if name == "scale":
            return self.p + 2
        return 2 + self.mo.col[name]

    def fit(self, fixed: dict, free: list):
        th, cov, quad = gls(self.kf.W, self._M(fixed, free))
        ll = -0.5 * (self.kf.logdet + self.kf.m * LOG2PI + quad)
        return th[1:], cov[1:, 1:], ll, th[0]

    # -- the causes ---------------------------------------------------------------------------
    def nuisance_shift(self) -> tuple[float, float]:
        """Best common command-time offset under the null (both chains re-timed): (s, ll)."""
        best = (-math.inf, 0.0)
        for s in self.mo.shifts:
            fixed = self._retime(float(s), 0.0)
            ll = self.fit(fixed, [])[2]
            best = max(best, (ll, float(s)))
        return best[1], best[0]

    def _retime(self, shift: float, extra: float) -> dict:
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

    # Causes linear in their parameters: free combinations of elementary columns (``_free``)
    # and the map from the fitted coefficients to the contract's parameters (``_params``).
    # One definition serves the cause's own test and the final joint refit (``joint_refit``).
    def _free(self, cause: str, extra: dict | None = None) -> list:
        mo = self.mo
        if cause == "resistance":
            return [{n: 1.0} for n in RESISTANCE_COLS]
        if cause == "mass":
            return [{"tr": 1.0, "br": mo.f0, "one": mo.alpha0, "v": mo.beta0, "v2": mo.gamma0}]
        if cause == "braking_rate":
            return [{"br": 1.0, "brt": -1.0}, {"brt": 1.0}]
        if cause == "odometer_scale":
            return [{"scale": 1.0}]
        if cause == "gradient":
            bi, bj = extra["bins"]
            return [{f"G{b}": 1.0 for b in range(bi, bj)}]
        raise ValueError(cause)

    def _params(self, cause: str, th: np.ndarray, cov: np.ndarray, extra: dict | None = None):
        """(parameters, standard errors, extra) of a linear cause from its coefficients."""
        mo = self.mo
        sd = np.sqrt(np.clip(np.diag(cov), 0, None))
        if cause == "resistance":
            meff = mo.train.effective_mass
            val = (np.array([mo.alpha0, mo.beta0, mo.gamma0]) + self._null_res() + th) * meff
            se = sd * meff
            # a, b and c are strongly correlated over one run's speeds; the resistance force
            # at the run's typical speed is what the data determine well (reported too)
            vr = float(np.sqrt(np.mean(mo.v_ref[mo.moving > 0] ** 2))) if mo.moving.any() \
                else 0.0
            gv = np.array([1.0, vr, vr * vr])
            se_force = float(np.sqrt(max(gv @ cov @ gv, 0.0))) * meff
            return {"a": val[0], "b": val[1], "c": val[2]}, \
                {"a": se[0], "b": se[1], "c": se[2], "force_at_v_ref": se_force}, \
                {"v_ref": vr, "force_at_v_ref": float(gv @ val)}
        if cause == "mass":
            k = 1.0 + th[0]
            return {"mass": mo.train.mass / k}, {"mass": mo.train.mass * sd[0] / k ** 2}, \
                {"traction_gain": k}
        if cause == "braking_rate":
            return {"f_start": mo.f0 + th[0], "f_end": mo.f0 + th[1]}, \
                {"f_start": sd[0], "f_end": sd[1]}, {}
        if cause == "odometer_scale":
            return {"scale": 1.0 + self.null.scale + th[0]}, {"scale": sd[0]}, {}
        if cause == "gradient":
            bi, bj = extra["bins"]
            return {"start": float(mo.bin_edges[bi]), "end": float(mo.bin_edges[bj]),
                    "permille": float(th[0])}, {"permille": sd[0]}, dict(extra)
        raise ValueError(cause)

    def _linear(self, cause: str):
        free = self._free(cause)
        th, cov, ll, _ = self.fit({}, free)
        return (ll, len(free), *self._params(cause, th, cov))

    def resistance(self):
        return self._linear("resistance")

    def _null_res(self) -> np.ndarray:
        d = self.null.drift
        return np.array([d.get("one", 0.0), d.get("v", 0.0), d.get("v2", 0.0)])

    def mass(self):
        return self._linear("mass")

    def braking_rate(self):
        return self._linear("braking_rate")

    def odometer_scale(self):
        return self._linear("odometer_scale")

    def brake_delay(self):
        """Profile over (common offset, extra braking delay > 0): the brake chain's own timing."""
        mo = self.mo
        prof = {}
        for s in mo.shifts:
            for d in mo.delays:
                if d <= 0.0:
                    continue
                key = round(float(s + d), 6)
                if key not in mo.braking_cols and key != 0.0:
                    continue
                ll = self.fit(self._retime(float(s), float(d)), [])[2]
                prof[(float(s), float(d))] = ll
        if not prof:
            return -math.inf, 1, {}, {}, {}
        (s_b, d_b), ll = max(prof.items(), key=lambda kv: kv[1])
        # parabolic refinement along d at the best offset
        ds = sorted(d for (s, d) in prof if s == s_b)
        lls = [prof[(s_b, d)] for d in ds]
        i = ds.index(d_b)
        d_hat, se = d_b, math.nan
        if 0 < i < len(ds) - 1:
            y0, y1, y2 = lls[i - 1], lls[i], lls[i + 1]
            h = ds[i + 1] - ds[i]
            den = y0 - 2 * y1 + y2
            if den < 0:
                d_hat = d_b + 0.5 * h * (y0 - y2) / den
                se = h / math.sqrt(-den)  # curvature of the profile log-likelihood
        delay = self.mo.train.brake.delay + d_hat
        return ll, 1, {"delay": delay}, {"delay": se}, {"offset": s_b, "extra": d_hat,
                                                          "profile": [(d, lls[k]) for k, d in
                                                                      enumerate(ds)]}

    def gradient(self):
        """All sections [i, j) of the position bins by prefix sums; (s0, permille) by GLS.

        Scored *against the running-resistance model*: the section is searched and its
        likelihood gain measured with the Davis terms (a, b, c) free as nuisance. On one run,
        position and speed go together: a long "section" at cruise speed is running
        resistance by another name (a line-wide offset is exactly the a-term), and a map error
        is local. So a gradient is named only for what resistance cannot explain; the
        permille reported (and added to the model) is the plain fit of the chosen section.
        Returns ll such that ll - null_ll() is that gain."""
        mo = self.mo
        idx = np.array([self._j(f"G{b}") for b in range(mo.n_bins)])
        width = mo.bin_edges[1] - mo.bin_edges[0]
        min_len = max(1, int(math.ceil(self.cfg.min_section / width - 1e-9)))
        e1 = np.zeros(self.p + 3)
        e1[1] = 1.0
        W = self.kf.W
        # Frisch-Waugh: partial the resistance columns out of the metric, then scan
        F = np.zeros((self.p + 3, 3))
        for r, name in enumerate(RESISTANCE_COLS):
            F[self._j(name), r] = 1.0
        WF = W @ F
        W_res = W - WF @ np.linalg.pinv(F.T @ WF) @ WF.T
        quad, bi, bj, _, _ = best_section(W_res, self._M({}, [])[:, 0], e1, idx, min_len)
        ll_res = self.fit({}, self._free("resistance"))[2]
        ll_joint = -0.5 * (self.kf.logdet + self.kf.m * LOG2PI + quad)
        extra = {"bins": (bi, bj), "bin_width": float(width)}
        th, cov, ll_plain, _ = self.fit({}, self._free("gradient", extra))
        extra["loglik_gain_plain"] = ll_plain - self.null_ll()
        return (self.null_ll() + (ll_joint - ll_res), 3,
                *self._params("gradient", th, cov, extra))

    def gain_beyond_resistance(self, fv: np.ndarray, fs: np.ndarray) -> float:
        """Log-likelihood gain of the fixed drift (fv, fs) over this stage's null, both with
        the Davis terms free (small augmented filter at this stage's noise): the gradient's
        evidence at another noise level (see :meth:`gradient`)."""
        mo = self.mo
        cols = [mo.col[c] for c in RESISTANCE_COLS]
        lls = []
        for f_v, f_s in ((self.fv, self.fs), (fv, fs)):
            kf = self.augmented(f_v, f_s, drift=(mo.Dv[:, cols], mo.Ds[:, cols]))
            quad = gls(kf.W, np.eye(5))[2]
            lls.append(-0.5 * (kf.logdet + kf.m * LOG2PI + quad))
        return lls[1] - lls[0]

    def wheel_slip(self):
        """Candidate episodes where the standardised speed innovation of the null is large;
        each is fitted as an interval [t0, t1) with its own slip fraction, the boundaries
        profiled at the decimated odometer rate (per-sample columns, contiguous sums)."""
        mo, cfg, ev = self.mo, self.cfg, self.mo.ev
        o = ev.odo
        s0_hat = self.fit({}, [])[3]
        nu = (self.kf.E0[o, 0] + s0_hat * self.kf.E1[o, 0]) / np.sqrt(self.kf.S_v[o])
        t = ev.t[o]
        cands = []
        for k in np.flatnonzero(np.abs(nu) > cfg.slip_threshold):
            if cands and t[k] - cands[-1][1] < 3.0:
                cands[-1][1] = t[k]
            else:
                cands.append([t[k], t[k]])
        cands = sorted(cands, key=lambda c: -np.max(np.abs(nu[(t >= c[0]) & (t <= c[1])])))
        cands = cands[:cfg.max_slip_candidates]
        null_ll = self.null_ll()
        if not cands:
            return null_ll, 3, {"intervals": []}, {}, {"candidates": 0}
        # per-sample slip columns of every candidate window
        g = mo.grid
        cum = np.concatenate([[0.0], np.cumsum(0.5 * (mo.v_ref[1:] + mo.v_ref[:-1]) * g.dt)])
        cols = []  # (candidate, i) with odometer event positions i (bin [t_i, t_i+1))
        for c, (c0, c1) in enumerate(cands):
            for i in np.flatnonzero((t >= c0 - 2.0) & (t <= c1 + 3.0))[:-1]:
                if i + 1 < t.size:
                    cols.append((c, int(i)))
        n, nc = ev.t.size, len(cols)
        Md = np.zeros((n, nc))
        Mv = np.zeros((n, nc))
        for j, (_, i) in enumerate(cols):
            Mv[o[i], j] = np.interp(t[i], g.t, mo.v_ref)
            Md[o[i + 1:], j] = np.interp(t[i + 1], g.t, cum) - np.interp(t[i], g.t, cum)
        kf = self.augmented(self.fv, self.fs, meas=(Md, Mv))
        u = np.zeros(nc + 2)
        u[0] = 1.0
        e1 = np.zeros(nc + 2)
        e1[1] = 1.0
        base_quad = gls(kf.W, np.stack([u, e1], axis=1))[2]
        pen = 3 * math.log(self.n_meas)
        # each candidate's best interval alone ...
        best_iv = []
        for c in range(len(cands)):
            idx = np.array([2 + j for j, (cc, _) in enumerate(cols) if cc == c])
            if idx.size == 0:
                continue
            quad, a, b, eps, se = best_section(kf.W, u, e1, idx, 1)
            if 2 * 0.5 * (base_quad - quad) - pen > 0:
                col = np.zeros(nc + 2)
                col[idx[a:b]] = 1.0
                i0 = cols[idx[a] - 2][1]
                i1 = cols[idx[b - 1] - 2][1] + 1
                best_iv.append((float(t[i0]), float(t[i1]), col))
        # ... then forward selection by the joint fit: every episode's distance excess persists,
        # so episodes compete for the same evidence and their gains must not be added up
        chosen, quad_now = [], base_quad
        while best_iv:
            trials = []
            for m, (_a, _b, col) in enumerate(best_iv):
                M = np.stack([u, e1] + [c[2] for c in chosen] + [col], axis=1)
                trials.append((gls(kf.W, M)[2], m))
            q_new, m = min(trials)
            if (quad_now - q_new) - pen <= 0:
                break
            chosen.append(best_iv.pop(m))
            quad_now = q_new
        if not chosen:
            return null_ll, 3, {"intervals": []}, {}, {"candidates": len(cands)}
        chosen.sort(key=lambda c: c[0])
        th, cov, _ = gls(kf.W, np.stack([u, e1] + [c[2] for c in chosen], axis=1))
        eps = th[1:].tolist()
        se = np.sqrt(np.clip(np.diag(cov)[1:], 0, None)).tolist()
        return null_ll + 0.5 * (base_quad - quad_now), 3 * len(chosen), \
            {"intervals": [[c[0], c[1]] for c in chosen]}, {"slip_fraction": se}, \
            {"slip_fraction": eps, "candidates": len(cands)}


def best_section(W: np.ndarray, u: np.ndarray, e1: np.ndarray, idx: np.ndarray, min_len: int):
    """The contiguous run [a, b) of the columns ``idx`` (b - a >= min_len) whose sum, with one
    free coefficient theta and the free nuisance e1 (s0), best explains the data: closed-form
    GLS for every run through prefix sums of W. ``u`` is the fixed combination (z[0]).
    Returns (quad, a, b, theta, se(theta))."""
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
    best = int(np.argmin(quad))
    if not np.isfinite(quad[best]):
        return math.inf, 0, nb, 0.0, math.nan
    se = math.sqrt(max(w_11 / det[best], 0.0)) if ok[best] else math.nan
    return float(quad[best]), int(i[best]), int(j[best]), float(th[best]), se


# =============================================================================================
# The driver
# =============================================================================================


def diagnose(data: DiagData, line: Line, train: TrainParams, config: DiagConfig = DiagConfig(),
             progress: Callable[[int, int, str], None] | None = None) -> Diagnosis:
    """Diagnose one run. Raises :class:`DiagnoseError` on unusable input."""
    cfg = config
    total = 3 + 2 * cfg.stages

    def tick(i, what):
        if progress is not None:
            progress(i, total, what)

    run = _prepare(data, line, cfg)
    tick(1, "clock and link")
    clock = clock_test(run)
    link = link_test(run)
    untestable = []
    moving_cmd = run.ctrl_a < -cfg.min_brake
    v_at_cmd = np.interp(run.ctrl_t, run.odo_t, run.odo_v)
    if not np.any(moving_cmd & (v_at_cmd > cfg.standstill_speed)):
        for c in ("braking_rate", "brake_delay"):
            untestable.append({"cause": c, "why": "no braking while moving in the data"})
    if run.bal_t.size < 2:
        untestable.append({"cause": "odometer_scale",
                           "why": "fewer than two balise readings: distance has no reference"})
    if "untestable" in link:
        untestable.append({"cause": "bursty_link", "why": link["untestable"]})
    skip = {u["cause"] for u in untestable}

    tick(2, "motion model")
    mo = _Motion(run, line, train, cfg)
    null = _Null()
    accepted = []
    evidence = {}
    first_scores = None
    stage_results = []
    other = {"clock_drift": clock, "bursty_link": link}
    for stage_i in range(cfg.stages):
        tick(3 + 2 * stage_i, f"stage {stage_i + 1}: noise and filter")
        st = _Stage(mo, null, cfg)
        # the common command-time offset (nuisance) is re-estimated under every stage's null:
        # estimated under a null that misses a large effect it can be far off, and a wrong
        # offset would then pass for a brake delay
        if not null.brake_extra:
            s_hat, _ = st.nuisance_shift()
            if s_hat != null.shift:
                null.shift = s_hat
                st = _Stage(mo, null, cfg, noise=(st.q, st.r_s))
        tick(4 + 2 * stage_i, f"stage {stage_i + 1}: causes")
        ll0 = st.null_ll()
        n = st.n_meas
        scores = {}
        done = {a["cause"] for a in accepted}
        for cause in MOTION_CAUSES + ("odometer_scale", "wheel_slip"):
            if cause in skip or cause in done:
                continue
            ll, k, params, se, extra = getattr(st, cause)()
            dll = ll - ll0
            scores[cause] = {"score": 2 * dll - k * math.log(n), "dll": dll, "k": k, "n": n,
                             "parameters": params, "std_errors": se, "extra": extra}
        for cause, res in other.items():
            if cause in skip or cause in done:
                continue
            scores[cause] = {"score": 2 * res["dll"] - res["k"] * math.log(res["n"]),
                             "dll": res["dll"], "k": res["k"], "n": res["n"],
                             "parameters": res["parameters"],
                             "std_errors": res.get("std_errors", {}), "extra": {}}
        # A cause's likelihood ratio with the noise re-maximised under it: an unmodelled effect
        # inflates the null's process noise q, which understates the effect's own evidence.
        prelim = sorted((c for c in scores if c in REFIT_CAUSES),
                        key=lambda c: -scores[c]["score"])[:cfg.noise_refits]
        for cause in prelim:
            res = scores[cause]
            if res["score"] < -20.0:
                continue
            null_c = copy.deepcopy(null)
            _extend_null(null_c, cause, res, mo)
            st_c = _Stage(mo, null_c, cfg, big=False, noise=None)
            # the null at the cause's noise too: an optimiser that stopped short on the null
            # must not pass for evidence
            if cause == "gradient":  # its gain beyond resistance (see _Stage.gradient)
                dll_c = _Stage(mo, null, cfg, big=False, noise=(st_c.q, st_c.r_s)) \
                    .gain_beyond_resistance(st_c.fv, st_c.fs)
            else:
                ll0_c = max(ll0, _kf2_loglik(mo.ev, st_c.q, st_c.r_s, st.fv, st.fs, st.md,
                                             st.mv, cfg.standstill_q))
                dll_c = st_c.fixed_loglik() - ll0_c
            if dll_c > res["dll"]:
                res["dll_common_noise"] = res["dll"]
                res["dll"] = dll_c
                res["score"] = 2 * dll_c - res["k"] * math.log(n)
                res["noise"] = (st_c.q, st_c.r_s)
        # Prior odds: `none` against K causes, each 1/K as likely a priori as some effect at
        # all (BIC is the log Bayes factor at even odds): 2 ln K off every score. Without it
        # every cause tested is a chance of a false alarm (10 % of nominal bags with K = 9).
        prior = 2.0 * math.log(max(len(scores), 1))
        for res in scores.values():
            res["score"] -= prior
            res["prior_odds_penalty"] = prior
        stage_results.append({"null_loglik": ll0, "q": st.q, "r_s": st.r_s, "scores": scores,
                              "shift": null.shift})
        if first_scores is None:
            first_scores = scores
            first_stage = st
            first_null = copy.deepcopy(null)
        best = max(scores.items(), key=lambda kv: kv[1]["score"], default=None)
        if best is None or best[1]["score"] <= 0:
            break
        cause, res = best
        if "noise" in res:
            _refit_at_own_noise(mo, null, cause, res, cfg)
        accepted.append({"cause": cause, "score": res["score"], "parameters": res["parameters"],
                         "std_errors": res["std_errors"], "stage": stage_i + 1,
                         "extra": res["extra"]})
        _extend_null(null, cause, res, mo)
        if cause in ("clock_drift", "bursty_link"):
            skip.add(cause)

    joint_refit(mo, null, accepted, cfg, (st.q, st.r_s))
    for a in accepted:
        a.pop("extra", None)

    # ---- ranking: accepted causes in order, then the rest by their best score --------------
    ranking = []
    last = stage_results[-1]["scores"]
    seen = set()
    beta = run.clock["beta"]
    for a in accepted:
        ranking.append({"cause": a["cause"], "score": _r(a["score"]),
                        "parameters": _report(a["cause"], a["parameters"], beta)})
        seen.add(a["cause"])
    rest = []
    for cause in CAUSES:
        if cause in seen or cause not in first_scores:
            continue
        sc = last.get(cause, first_scores[cause])
        rest.append({"cause": cause, "score": _r(sc["score"]),
                     "parameters": _report(cause, sc["parameters"], beta)})
    rest.append({"cause": "none", "score": 0.0, "parameters": {}})
    rest.sort(key=lambda r: -r["score"])
    ranking += rest
    top = ranking[0]
    for cause, res in first_scores.items():
        evidence[cause] = {"score_alone": _r(res["score"]), "loglik_gain": _r(res["dll"]),
                           "n_params": res["k"], "n": res["n"],
                           "parameters_alone": _clean(res["parameters"]),
                           "std_errors": _clean(res["std_errors"]),
                           "details": _clean({k: v for k, v in res["extra"].items()
                                              if k != "profile"})}
    for a in accepted:
        evidence.setdefault(a["cause"], {})["accepted_at_stage"] = a["stage"]
        evidence[a["cause"]]["std_errors"] = _clean(a["std_errors"])
    evidence["_model"] = {"clock": {"offset_s": run.clock["alpha"], "rate": run.clock["beta"],
                                    "jitter_std_s": clock.get("jitter_std")},
                          "command_offset_s": stage_results[0]["shift"],
                          "stages": [{"null_loglik": _r(s["null_loglik"]), "q": s["q"],
                                      "r_s": s["r_s"]} for s in stage_results],
                          "samples": int(mo.ev.odo.size), "balises": int(mo.ev.bal.size),
                          "duration_s": run.duration, "score": "2 * loglik gain - k ln n (BIC)",
                          "notes": run.notes}
    tick(total - 1, "gain")
    first_stage.null = first_null
    gain = _gain(top, mo, first_stage, clock, link, cfg) if top["cause"] != "none" else \
        {"metric": "none: nothing to extend", "before": None, "after": None}
    tick(total, "done")
    series = _series(mo, accepted, link)
    return Diagnosis(cause=top["cause"], parameters=top["parameters"], ranking=ranking,
                     untestable=untestable, evidence=evidence, gain=gain, accepted=accepted,
                     series=series)


def _refit_at_own_noise(mo: _Motion, null: _Null, cause: str, res: dict, cfg: DiagConfig,
                        rounds: int = 2) -> None:
    """Re-fit an accepted cause's parameters at the noise of the model that includes it (in
    place). Its first fit ran at the null's noise, which the cause itself inflated (a slip
    episode not modelled makes q 100x too large, and at that q the filter follows the odometer
    and the slip fraction is barely determined): fit, re-maximise the noise under the extended
    null, fit again."""
    for _ in range(rounds):
        st = _Stage(mo, null, cfg, noise=res["noise"])
        _, _, res["parameters"], res["std_errors"], res["extra"] = getattr(st, cause)()
        null_c = copy.deepcopy(null)
        _extend_null(null_c, cause, res, mo)
        st_c = _Stage(mo, null_c, cfg, big=False)
        res["noise"] = (st_c.q, st_c.r_s)


LINEAR_CAUSES = ("resistance", "mass", "braking_rate", "odometer_scale", "gradient")


def joint_refit(mo: _Motion, null: _Null, accepted: list, cfg: DiagConfig, noise) -> None:
    """Re-estimate the accepted linear causes' parameters jointly (in place).

    Greedy stages fit each cause on top of the earlier ones held fixed: a cause accepted first
    absorbs part of a later one's effect (a gradient section fitted before a resistance
    change is biased by it). Given the discrete choices (sections, delays, slip episodes,
    command offset), the accepted linear causes are one GLS problem: fit them together."""
    lin = [a for a in accepted if a["cause"] in LINEAR_CAUSES]
    if len(lin) < 2:
        return
    base = _Null(shift=null.shift, brake_extra=null.brake_extra, slip=list(null.slip))
    st = _Stage(mo, base, cfg, noise=noise)
    free, blocks = [], []
    for a in lin:
        f = st._free(a["cause"], a["extra"])
        blocks.append((a, len(free), len(f)))
        free += f
    th, cov, _, _ = st.fit({}, free)
    for a, i, k in blocks:
        p, se, ex = st._params(a["cause"], th[i:i + k], cov[i:i + k, i:i + k], a["extra"])
        a["parameters"], a["std_errors"], a["extra"] = p, se, ex


def _extend_null(null: _Null, cause: str, res: dict, mo: _Motion) -> None:
    p = res["parameters"]
    ex = res["extra"]
    if cause == "gradient":
        i, j = ex["bins"]
        null.gradient = (i, j, p["permille"])
    elif cause == "resistance":
        meff = mo.train.effective_mass
        for name, val, base in (("one", p["a"], mo.alpha0), ("v", p["b"], mo.beta0),
                                ("v2", p["c"], mo.gamma0)):
            null.drift[name] = null.drift.get(name, 0.0) + val / meff - base
    elif cause == "mass":
        dk = ex["traction_gain"] - 1.0
        for name, c in (("tr", 1.0), ("br", mo.f0), ("one", mo.alpha0), ("v", mo.beta0),
                        ("v2", mo.gamma0)):
            null.drift[name] = null.drift.get(name, 0.0) + dk * c
    elif cause == "braking_rate":
        ds, de = p["f_start"] - mo.f0, p["f_end"] - mo.f0
        null.drift["br"] = null.drift.get("br", 0.0) + ds
        null.drift["brt"] = null.drift.get("brt", 0.0) + de - ds
    elif cause == "brake_delay":
        null.shift = ex["offset"]
        # snap to the grid the columns exist on
        d = min(mo.delays, key=lambda d: abs(d - ex["extra"]))
        null.brake_extra = float(d)
    elif cause == "odometer_scale":
        null.scale = p["scale"] - 1.0
    elif cause == "wheel_slip":
        for (t0, t1), eps in zip(p["intervals"], ex.get("slip_fraction", [])):
            null.slip.append((t0, t1, eps))


def _report(cause: str, params: dict, beta: float) -> dict:
    """Parameters as docs/interfaces.md reports them: times on the train's stamp clock (the analysis
    runs on the reference clock, t_ref = beta t_stamp)."""
    p = _clean(params)
    if cause == "wheel_slip":
        p["intervals"] = [[a / beta, b / beta] for a, b in p.get("intervals", [])]
    return p


def _r(x):
    return float(round(float(x), 3)) if x is not None and math.isfinite(float(x)) else x


def _clean(d):
    out = {}
    for k, v in d.items():
        if isinstance(v, (list, tuple)):
            out[k] = [_clean_v(x) for x in v]
        else:
            out[k] = _clean_v(v)
    return out


def _clean_v(v):
    if isinstance(v, (list, tuple)):
        return [_clean_v(x) for x in v]
    if isinstance(v, (float, np.floating)):
        return float(v) if math.isfinite(float(v)) else None
    if isinstance(v, (np.integer,)):
        return int(v)
    return v


# =============================================================================================
# Gain on held-out data
# =============================================================================================


def _gain(top: dict, mo: _Motion, st: _Stage, clock: dict, link: dict, cfg: DiagConfig) -> dict:
    cause = top["cause"]
    if cause == "clock_drift":
        return clock.get("gain") or {"metric": "stamp residual", "before": None, "after": None}
    if cause == "bursty_link":
        return link.get("gain") or {"metric": "held-out log-likelihood", "before": None,
                                    "after": None}
    if cause == "odometer_scale":
        return _gain_scale(mo, top["parameters"])
    if cause == "wheel_slip":
        return _gain_slip(mo, top["parameters"])
    return _gain_motion(cause, mo, st, cfg)


def _gain_scale(mo: _Motion, params: dict) -> dict:
    """Balise positions predicted from the odometer distance: s0 (and the scale) fitted on the
    odd-numbered readings, error at the even-numbered ones."""
    run = mo.run
    d_at = np.interp(run.bal_t, run.odo_t, run.odo_d)
    fit = np.arange(run.bal_t.size) % 2 == 1
    test = ~fit
    if fit.sum() < 2 or test.sum() < 1:
        return {"metric": "held-out balise position error RMS (m)", "before": None,
                "after": None}
    s0_b = float(np.mean(run.bal_p[fit] - d_at[fit]))
    A = np.stack([np.ones(fit.sum()), d_at[fit]], axis=1)
    (s0_a, inv_scale), *_ = np.linalg.lstsq(A, run.bal_p[fit], rcond=None)
    before = float(np.sqrt(np.mean((s0_b + d_at[test] - run.bal_p[test]) ** 2)))
    after = float(np.sqrt(np.mean((s0_a + inv_scale * d_at[test] - run.bal_p[test]) ** 2)))
    return {"metric": "held-out balise position error RMS (m), odometer distance placed by the "
                      "odd-numbered balises, tested on the even-numbered", "before": before,
            "after": after, "scale_fitted_on_half": float(1.0 / inv_scale)}


def _gain_slip(mo: _Motion, params: dict) -> dict:
    """Odometer speed minus the model's smoothed speed inside the episodes, raw against
    corrected by the fitted slip (the episodes are local: nothing to hold out)."""
    run = mo.run
    ivs = params.get("intervals", [])
    if not ivs:
        return {"metric": "odometer speed error in the slip episodes (m/s)", "before": None,
                "after": None}
    inside = np.zeros(run.odo_t.size, bool)
    corr = np.ones(run.odo_t.size)
    for (t0, t1) in ivs:
        m = (run.odo_t >= t0) & (run.odo_t < t1)
        inside |= m
    w = max(1, int(round(3.0 / max(np.median(np.diff(run.odo_t)), 1e-3))))
    ref = moving_average(run.odo_v, w)
    # the reference outside the episodes: interpolate across them
    ref_i = np.interp(run.odo_t, run.odo_t[~inside], ref[~inside]) if (~inside).any() else ref
    eps = float(np.mean(run.odo_v[inside] / np.maximum(ref_i[inside], 0.1) - 1.0))
    corr[inside] = 1.0 + eps
    before = float(np.sqrt(np.mean((run.odo_v[inside] - ref_i[inside]) ** 2)))
    after = float(np.sqrt(np.mean((run.odo_v[inside] / corr[inside] - ref_i[inside]) ** 2)))
    return {"metric": "odometer speed error in the slip episodes (m/s), raw vs corrected by "
                      "the fitted slip (local: not held out)", "before": before, "after": after}


def _gain_motion(cause: str, mo: _Motion, st: _Stage, cfg: DiagConfig) -> dict:
    """Fit the cause on alternate blocks (even), replay the recorded commands open loop through
    the believed and the extended model over the held-out (odd) blocks, each from the measured
    state at its start, and compare with the odometer speed."""
    from train_core.motion import replay

    run, ev = mo.run, mo.ev
    block = np.floor(ev.t / cfg.gain_block).astype(int)
    update = (block % 2 == 0)
    st_a = _Stage(mo, st.null, cfg, noise=(st.q, st.r_s), update=update)
    ll, k, params, se, extra = getattr(st_a, cause)()
    believed = mo.train
    extended, line_ext, brake_delay, braking_rate_of_t = _extended(cause, params, mo, believed)
    nb = int(block.max()) + 1
    # both models replay the commands with the analysis' command-time offset (the link's mean
    # latency, a nuisance of the alignment, not a cause)
    ctrl_t = run.ctrl_t + st.null.shift
    # (a brake delay is fitted with its own offset: the pair is the extension's timing)
    ctrl_t_ext = run.ctrl_t + (extra["offset"] if cause == "brake_delay" else st.null.shift)
    sq_b, sq_a, cnt, moved = [], [], [], []
    for b in range(1, nb, 2):
        t0, t1 = b * cfg.gain_block, (b + 1) * cfg.gain_block
        sel = (run.odo_t >= t0) & (run.odo_t < t1)
        if sel.sum() < 10:
            continue
        t_out = run.odo_t[sel]
        # the speed to predict: the odometer's, averaged over 1 s (centred), so that the
        # comparison is not floored by its sample noise, which both models share
        y = np.interp(t_out, mo.grid.t, mo.v_ref)
        v0 = float(y[0])
        x0 = float(np.interp(t_out[0], mo.grid.t, mo.x_ref))
        tt = t_out[0]
        if v0 < 0.5:
            v0 = 0.0
        # the simulator's physics (train_core.motion) at 50 ms RK4 steps: the motion is smooth
        # between command changes, and replay cuts its steps at every one of them
        _, vb = replay(mo.line, believed, ctrl_t, run.ctrl_a, tt, t_out, x0, v0,
                       max_step=0.05)
        _, va = replay(line_ext, extended, ctrl_t_ext, run.ctrl_a, tt, t_out, x0, v0,
                       believed=believed, brake_delay=brake_delay,
                       braking_rate_of_t=braking_rate_of_t,
                       max_step=0.05)
        sq_b.append(float(np.sum((vb - y) ** 2)))
        sq_a.append(float(np.sum((va - y) ** 2)))
        cnt.append(int(sel.sum()))
        moved.append(float(np.sqrt(np.mean((va - vb) ** 2))))
    sq_b, sq_a, cnt, moved = np.array(sq_b), np.array(sq_a), np.array(cnt), np.array(moved)
    if cnt.sum() == 0:
        return {"metric": "held-out speed RMSE (m/s)", "before": None, "after": None}
    all_b = float(np.sqrt(sq_b.sum() / cnt.sum()))
    all_a = float(np.sqrt(sq_a.sum() / cnt.sum()))
    # The blocks where the extension changes the prediction (selected on the two models'
    # predictions alone, never on their errors): a local effect (a 300 m section) is diluted
    # to nothing in a whole-run RMSE dominated by the odometer's noise elsewhere.
    changed = moved > cfg.gain_min_change
    out = {"metric": "held-out speed RMSE (m/s) against the odometer speed averaged over 1 s: "
                     "the recorded commands replayed open loop "
                     f"over alternate {cfg.gain_block:g} s blocks (cause fitted on the others), "
                     "in the blocks where the extended model's prediction moves by > "
                     f"{cfg.gain_min_change:g} m/s RMS",
           "blocks": int(cnt.size), "changed_blocks": int(changed.sum()),
           "before_all_blocks": all_b, "after_all_blocks": all_a,
           "fitted_on_half": _clean(params)}
    if changed.any():
        out["before"] = float(np.sqrt(sq_b[changed].sum() / cnt[changed].sum()))
        out["after"] = float(np.sqrt(sq_a[changed].sum() / cnt[changed].sum()))
    else:
        out["before"] = out["after"] = None
        out["note"] = "the cause fitted on half the data changes no held-out block"
    return out


def _extended(cause: str, params: dict, mo: _Motion, believed: TrainParams):
    """(true-train model, line, brake delay, f(t)) of the believed model extended by a cause."""
    from dataclasses import replace

    from train_core.effects import Effects, GradientEffect, true_line
    from train_core.model import Brake, Davis

    line, train, bd, braking_rate_of_t = mo.line, believed, None, None
    if cause == "gradient":
        line = true_line(mo.line, Effects(gradient=GradientEffect(
            params["start"], params["end"], params["permille"])))
    elif cause == "resistance":
        train = replace(believed, davis=Davis(params["a"], params["b"], params["c"]))
    elif cause == "mass":
        train = replace(believed, mass=params["mass"])
    elif cause == "brake_delay":
        bd = params["delay"]
    elif cause == "braking_rate":
        fs, fe, T = params["f_start"], params["f_end"], max(mo.run.duration, 1e-9)
        braking_rate_of_t = lambda t: fs + (fe - fs) * min(max(t / T, 0.0), 1.0)  # noqa: E731
        train = replace(believed, brake=Brake(believed.brake.time_constant,
                                              believed.brake.delay, fs))
    return train, line, bd, braking_rate_of_t


# =============================================================================================
# Series for the plots
# =============================================================================================


def _series(mo: _Motion, accepted: list, link: dict) -> dict:
    """Residual acceleration of the believed model (smoothed odometer speed derivative minus the
    model's acceleration) against position, speed and time; f(t); the loss runs."""
    g = mo.grid
    v = mo.v_ref
    dv = np.gradient(v, g.dt)
    model = (mo.a_tr0 + mo.f0 * mo.a_br0 - (mo.alpha0 + (mo.beta0 + mo.gamma0 * v) * v)
             - mo.line.gradient_accel(mo.x_ref) * mo.k_grad)
    res = np.where(mo.moving > 0, dv - model, np.nan)
    step = max(1, int(round(0.5 / g.dt)))
    sl = slice(0, None, step)
    out = {"t": g.t[sl], "position": mo.x_ref[sl], "speed": v[sl], "residual_accel": res[sl],
           "commanded_braking": mo.a_br0[sl], "commanded_traction": mo.a_tr0[sl],
           "odo_t": mo.run.odo_t, "odo_speed": mo.run.odo_v,
           "line_gradient": [(s.start, s.end, s.permille) for s in mo.line.gradients],
           "stations": [(s.name, s.position) for s in mo.line.stations],
           "balises": [b.position for b in mo.line.balises],
           "loss_runs": link.get("loss_runs", np.array([], int)),
           "loss_fraction": link.get("loss_fraction")}
    for a in accepted:
        if a["cause"] == "braking_rate":
            p = a["parameters"]
            out["f_t"] = (np.array([0.0, mo.run.duration]), np.array([p["f_start"], p["f_end"]]))
        if a["cause"] == "wheel_slip":
            out["slip_intervals"] = a["parameters"]["intervals"]
        if a["cause"] == "gradient":
            out["gradient_section"] = (a["parameters"]["start"], a["parameters"]["end"],
                                       a["parameters"]["permille"])
    return out
