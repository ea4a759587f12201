"""System identification front end: fit the train's longitudinal parameters from
odometer, balise and control time series (plain arrays; the ``identify`` CLI reads the bag).

Model (train_core.model; actuator after Zheng et al. 2015 eq. (1))::

    ds/dt = v
    dv/dt = k a_tr(t) + k f a_br(t) - (a + b v + c v^2) / M_eff
            - g sin(theta(s0 + s)) / (1 + lambda) + w
    a_tr, a_br = first-order lag (tau) of max/min(a_Tar(t - T_delay), 0)     (m/s^2)
    M_eff = (1 + lambda) M,   k = M_prior / M  (traction gain)

The drive *force* is the command times the *believed* effective mass (train_sim dynamics.py and
effects.py "mass": the controller computes the force for train.yaml's mass), so a train of true
mass M accelerates by k = M_prior / M per unit of actuator output. k is the traction gain; the
braking column carries k f.

f multiplies the braking command before the lag; the lag is linear, so lag(f min(a, 0)) =
f lag(min(a, 0)) and f enters linearly. Stopping, standing and starting (brake holding,
the start-up transient) are not described by the model: intervals whose reference speed reaches
below ``standstill_speed`` get zero regressors and a large process noise, so the filter follows
the measurements there and those intervals carry no information on the parameters.

What the data can identify (no force is measured):

* alpha = a / M_eff, beta = b / M_eff, gamma = c / M_eff (m/s^2, 1/s, 1/m): the *specific*
  resistance. Identifiable when the speed range is wide (beta, gamma need speeds spread over a
  range; at one cruising speed only the sum alpha + beta v + gamma v^2 is determined).
* kappa = 1 / (1 + lambda): the gain on the known gradient acceleration g sin(theta). It is
  identifiable only if the gradient *varies* along the run (a constant grade is a constant
  acceleration, indistinguishable from alpha) and the variation is large against the noise.
* k f (``scaled_braking_rate``, the braking rate times the traction gain): identifiable when the
  run contains braking; f = (k f) / k.
* k (traction gain): identifiable from traction phases. M = M_prior / k is identifiable ONLY
  under the force-calibration assumption above (the applied force is exactly the command times
  the believed mass). Without it (if the command were an acceleration delivered whatever the
  mass) M cancels, k = 1, and only alpha, beta, gamma are determined: a, b, c in N scale with the
  assumed mass. ``fit_traction_gain=False`` encodes that assumption (k = 1, M = prior, a, b, c in
  N given the prior mass). ``mass_if_davis_nominal`` reports the alternative "Davis forces as
  in train.yaml, only the resistance per mass changed" (one scale on the prior specific
  resistance, gains as fitted), which is observationally equivalent to scaling a, b, c.

Estimator: the velocity regressors (-v, -v^2, -g sin theta(s)) are evaluated on a reference
trajectory (RTS-smoothed speed/position, re-linearised ``outer_iterations`` times); the model is
then linear-Gaussian in the state with a drift *linear in the parameters*, so the exact maximum
likelihood estimate is a generalised least squares computed with one Kalman filter run on the data
and on one sensitivity column per parameter ("augmented Kalman filter", de Jong 1991). The
standard errors are the exact inverse information of that linear model, plus (in quadrature) the
doubt of what the model takes as known: the commands' time offset (``_profiled``) and the run's
place on the line (``_placed``: the median of the balises' offsets, which places the map's
gradients). This is the fixed point of
the exact-EM variant of ``hybrid_em`` (Kalman E-step on a linearised model), reached directly.
Noise: the speed variance from the messages (or train.yaml), the process-noise PSD q and the
distance noise r_s by maximising the profile likelihood (Nelder-Mead on logs).

Pure: numpy/scipy only.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from train_core.actuator import grid_output as actuator_output
from train_core.model import Davis, Line, TrainParams

from ..numerics import kalman
from ..numerics.augmented_kf import Events, augmented_kf, gls, information_condition

__all__ = [
    "IdentificationError",
    "SIData",
    "SIConfig",
    "SIResult",
    "PARAM_NAMES",
    "actuator_output",
    "identify",
]

PARAM_NAMES = ("traction_gain", "scaled_braking_rate", "alpha", "beta", "gamma", "kappa")
LOG2PI = np.log(2.0 * np.pi)
# the equilibrated information's condition number above which the fit is refused as singular
MAX_CONDITION = 1e12


class IdentificationError(ValueError):
    """The data cannot support the fit. ``missing``: series/excitation that is absent;
    ``unidentifiable``: parameters that cannot be identified from these data."""

    def __init__(self, reason: str, missing=(), unidentifiable=()):
        self.reason = reason
        self.missing = tuple(missing)
        self.unidentifiable = tuple(unidentifiable)
        msg = reason
        if self.missing:
            msg += f" | missing: {', '.join(self.missing)}"
        if self.unidentifiable:
            msg += f" | cannot identify: {', '.join(self.unidentifiable)}"
        super().__init__(msg)


ALL_PHYSICAL = ("davis.a", "davis.b", "davis.c", "mass", "rotary_allowance", "braking_rate")


@dataclass(frozen=True)
class SIData:
    """Measured series (one run). Stamps in s on one clock, strictly increasing per series."""

    odo_t: np.ndarray  # s, odometer sample stamps
    odo_distance: np.ndarray  # m, distance counted since the run started
    odo_speed: np.ndarray  # m/s
    ctrl_t: np.ndarray  # s, control command stamps
    ctrl_a_tar: np.ndarray  # m/s^2, a_Tar (> 0 traction, < 0 braking), held until the next one
    balise_t: np.ndarray | None = None  # s, balise passing stamps
    balise_position: np.ndarray | None = None  # m, surveyed positions of those balises
    odo_speed_variance: np.ndarray | None = None  # (m/s)^2 per sample; None: train.yaml


@dataclass(frozen=True)
class SIConfig:
    max_rate: float = 2.0  # Hz, odometer samples are decimated to at most this rate
    grid_dt: float = 0.1  # s, grid for the actuator and the regressor integrals
    outer_iterations: int = 3  # re-linearisations about the smoothed trajectory
    standstill_speed: float = 1.0  # m/s, intervals reaching below this are not modelled
    standstill_q: float = 1.0  # (m/s^2)^2 s, process noise PSD there (the KF just follows data)
    min_duration: float = 120.0  # s
    min_samples: int = 50
    min_speed: float = 1.0  # m/s, the train must exceed this to count as moving
    min_speed_range: float = 3.0  # m/s, 5-95 % spread of moving speeds (else "only cruises")
    min_brake: float = 0.05  # m/s^2, |a_Tar| below this is not braking
    min_gradient_spread: float = 1e-3  # m/s^2, std of g sin(theta) over the run for kappa
    rel_se_max: float = 0.25  # tight: a free parameter's SE <= rel_se_max * |prior value|
    vif_max: float = 30.0  # separable: its variance inflation factor <= vif_max (see identify)
    reference_speed: float | None = None  # m/s, for the resistance force report; None: the
    #                                       median moving speed of the run
    fit_traction_gain: bool = True  # k = M_prior / M; False: k = 1 (mass not identifiable)
    min_distance_var: float = 1e-4  # m^2, floor for the distance noise variance
    command_offsets: tuple | None = (-0.2, 0.5, 0.1)  # s (lo, hi, step): the offsets of the
    #   commands' time profiled (they may act later than stamped: a link's latency, a
    #   controller's cycle; identify's _profiled); None: taken as stamped
    placement_doubt: bool = True  # every SE holds the doubt of the run's place on the line
    #   (the balises' median offset, identify's _placed); False: the place taken as exact


@dataclass(frozen=True)
class SIResult:
    """Fit result. Parameters too loosely determined are held at the prior; parameters fitted
    but not separable keep the joint fit's value; both are flagged False (see ``reasons``)."""

    train: TrainParams  # prior with the identified values substituted
    values: dict  # name -> fitted value (PARAM_NAMES and physical names)
    std_errors: dict  # name -> standard error (nan where fixed at the prior)
    identifiable: dict  # name -> bool
    reasons: dict  # name -> why it is / is not identifiable
    covariance: np.ndarray  # covariance of the free specific parameters (order: free_names)
    free_names: tuple
    mass_if_davis_nominal: tuple  # (kg, SE kg): mass explaining the data if a, b, c (N) = prior
    correlation: np.ndarray | None = None  # correlations of the free parameters (free_names)
    variance_inflation: dict = field(default_factory=dict)  # free name -> VIF (>= 1)
    force_at_reference_speed: dict = field(default_factory=dict)  # see _force_report
    fixed_by_rule: tuple = ()  # one dict per parameter held at the prior as too loose (in order)
    rule: str = ""  # the identifiability rule applied, in words
    diagnostics: dict = field(default_factory=dict)
    series: dict = field(default_factory=dict)  # t, measured and smoothed speed for plots


# ---------------------------------------------------------------------------------------------


def moving_average(x, width):
    """Centred moving average over ``width`` samples, the ends padded with the edge values."""
    if width <= 1:
        return x.copy()
    k = np.ones(width) / width
    pad = width // 2
    xp = np.concatenate([np.full(pad, x[0]), x, np.full(width - 1 - pad, x[-1])])
    return np.convolve(xp, k, mode="valid")


def _validate(data: SIData, line: Line):
    missing = []
    for name, arrs in (("odometer", (data.odo_t, data.odo_distance, data.odo_speed)),
                       ("control", (data.ctrl_t, data.ctrl_a_tar))):
        if any(a is None or np.size(a) == 0 for a in arrs):
            missing.append(name)
    no_balise = data.balise_t is None or np.size(data.balise_t) == 0
    if missing:
        raise IdentificationError("required series are missing", missing, ALL_PHYSICAL)
    out = {}
    for name in ("odo_t", "odo_distance", "odo_speed", "ctrl_t", "ctrl_a_tar"):
        a = np.asarray(getattr(data, name), float).ravel()
        if not np.all(np.isfinite(a)):
            raise IdentificationError(f"{name} contains NaN or inf", (), ALL_PHYSICAL)
        out[name] = a
    if not (out["odo_t"].size == out["odo_distance"].size == out["odo_speed"].size):
        raise IdentificationError("odometer arrays differ in length", (), ALL_PHYSICAL)
    if out["ctrl_t"].size != out["ctrl_a_tar"].size:
        raise IdentificationError("control arrays differ in length", (), ALL_PHYSICAL)
    for name in ("odo_t", "ctrl_t"):
        if np.any(np.diff(out[name]) <= 0):
            raise IdentificationError(f"{name} stamps are not strictly increasing "
                                      "(out of order or duplicated)", (), ALL_PHYSICAL)
    if data.odo_speed_variance is not None:
        sv = np.asarray(data.odo_speed_variance, float).ravel()
        if sv.size != out["odo_t"].size or np.any(~np.isfinite(sv)) or np.any(sv <= 0):
            raise IdentificationError("odo_speed_variance must be finite, > 0, one per sample",
                                      (), ALL_PHYSICAL)
        out["odo_speed_variance"] = sv
    if not no_balise:
        bt = np.asarray(data.balise_t, float).ravel()
        bp = np.asarray(data.balise_position, float).ravel()
        if bt.size != bp.size or not (np.all(np.isfinite(bt)) and np.all(np.isfinite(bp))):
            raise IdentificationError("balise arrays differ in length or are not finite", (),
                                      ALL_PHYSICAL)
        out["balise_t"], out["balise_position"] = bt, bp
    return out


# ---------------------------------------------------------------------------------------------
# Augmented Kalman filter (exact GLS for a drift linear in the parameters)
# ---------------------------------------------------------------------------------------------


def _aug_kf(Y, dt, Bv, Bs, base_v, base_s, q, r_s, r_v):
    """The KF on x = (s, v), x_{k+1} = A x_k + [Bs; Bv] theta + [base_s; base_v] + w, carrying
    the parameter columns (augmented_kf.augmented_kf, odometer readings only).

    Y (n, 2) measurements (distance, speed) at the n stamps, dt (n-1,), Bv/Bs (n-1, p) parameter
    columns, base_* (n-1,) known input, q (n-1,) process-noise PSD per interval, r_v (n,).
    Returns (W, logdet) with W = sum_k E_k^T S_k^{-1} E_k over columns [data, theta_1..p]: the
    log-likelihood at theta is -0.5 (logdet + z^T W z), z = [1, theta] (logdet includes the
    2 pi terms).
    """
    n, p = Y.shape[0], Bv.shape[1]
    t = np.concatenate([[0.0], np.cumsum(dt)])
    ev = Events(t=t, kind=np.zeros(n, np.int8), y_d=Y[:, 0], y_v=Y[:, 1],
                r_v=np.asarray(r_v, float), held=np.zeros(n, bool),
                odo=np.arange(n), bal=np.array([], int))
    zero = np.zeros((1, p + 1))
    Bv_ = np.concatenate([zero, np.concatenate([base_v[:, None], Bv], axis=1)])
    Bs_ = np.concatenate([zero, np.concatenate([base_s[:, None], Bs], axis=1)])
    M0 = np.zeros((n, p + 1))
    res = augmented_kf(ev, 0.0, r_s, Bv_, Bs_, M0, M0, M0, 0.0,
                       q_per_event=np.concatenate([[0.0], q]))
    return res.W, res.logdet + res.m * LOG2PI


def _kf_rts(Y, dt, drift_v, drift_s, q, r_s, r_v):
    """Kalman filter (closed-form odometer updates) + :func:`kalman.rts_smooth` for x = (s, v)
    with known drift; returns the smoothed (s, v) at the stamps."""
    n = Y.shape[0]
    m = np.zeros((n, 2))
    P = np.zeros((n, 2, 2))
    mp = np.zeros((n, 2))
    Pp = np.zeros((n, 2, 2))
    A = np.zeros((n, 2, 2))
    m[0] = Y[0]
    P[0] = np.diag([r_s, r_v[0]])
    for k in range(1, n):
        h = dt[k - 1]
        A[k] = [[1.0, h], [0.0, 1.0]]
        Q = q[k - 1] * np.array([[h ** 3 / 3, h * h / 2], [h * h / 2, h]])
        mp[k] = A[k] @ m[k - 1] + [drift_s[k - 1], drift_v[k - 1]]
        Pp[k] = kalman.propagate_cov(P[k - 1], A[k], Q)
        _, _, _, _, _, (k00, k01, k10, k11), (n00, n01, n11) = kalman.odometer_update(
            Pp[k, 0, 0], Pp[k, 0, 1], Pp[k, 1, 1], r_s, r_v[k])
        m[k] = mp[k] + np.array([[k00, k01], [k10, k11]]) @ (Y[k] - mp[k])
        P[k] = [[n00, n01], [n01, n11]]
    return kalman.rts_smooth(m, P, mp, Pp, A)[0]


class _QVec:
    """Per-interval process-noise PSD: exp(log q) where modelled, ``big`` where held."""

    def __init__(self, held, big):
        self.held, self.big = held, big

    def __call__(self, lq):
        return np.where(self.held, self.big, np.exp(lq))


# ---------------------------------------------------------------------------------------------


@dataclass
class _Run:
    """The run as the fit sees it: decimated odometer, the actuator on the grid, line position."""

    t_all: np.ndarray  # s, every odometer stamp
    t: np.ndarray  # s, decimated stamps
    Y: np.ndarray  # (n, 2) distance (m), speed (m/s) at t
    r_v: np.ndarray  # (m/s)^2, speed variance at t
    dt: np.ndarray  # s, np.diff(t)
    s0: float  # m, line position of odometer distance zero
    s0_var: float  # m^2, its variance (the median of the balises' offsets; nan without them)
    tg: np.ndarray  # s, uniform grid over the run
    a_tr: np.ndarray  # m/s^2, traction actuator output on tg
    a_br: np.ndarray  # m/s^2, braking actuator output on tg (before the braking rate)
    has_grad: bool  # the line has a gradient


def _check_run(d: dict, line: Line, cfg: SIConfig) -> tuple[float, float, float]:
    """Refuse runs that cannot support the fit; returns (duration s, 5 %, 95 % moving speed)."""
    t_all = d["odo_t"]
    duration = t_all[-1] - t_all[0] if t_all.size else 0.0
    if t_all.size < cfg.min_samples or duration < cfg.min_duration:
        raise IdentificationError(
            f"run too short: {t_all.size} odometer samples over {duration:.1f} s (need >= "
            f"{cfg.min_samples} samples and >= {cfg.min_duration:g} s)", ("longer run",),
            ALL_PHYSICAL)
    vmax = float(np.max(d["odo_speed"]))
    if vmax < cfg.min_speed:
        raise IdentificationError(
            f"the train never moves (max speed {vmax:.2f} m/s < {cfg.min_speed:g} m/s)",
            ("motion",), ALL_PHYSICAL)
    moving = d["odo_speed"] > cfg.min_speed
    lo, hi = np.percentile(d["odo_speed"][moving], [5, 95])
    if hi - lo < cfg.min_speed_range:
        raise IdentificationError(
            f"the train only cruises: moving speeds span {lo:.1f}-{hi:.1f} m/s (< "
            f"{cfg.min_speed_range:g} m/s); only the total resistance at that speed is "
            "determined, a, b and c cannot be separated", ("speed variation (accelerate/brake)",),
            ALL_PHYSICAL)
    if _has_gradient(line) and "balise_t" not in d:
        raise IdentificationError("no balise readings: the run cannot be placed on the line's "
                                  "gradients", ("balise",), ALL_PHYSICAL)
    return duration, lo, hi


def _has_gradient(line: Line) -> bool:
    return any(g.permille != 0 for g in line.gradients)


def _prepare(d: dict, line: Line, prior: TrainParams, cfg: SIConfig,
             s0_shift: float = 0.0) -> _Run:
    """Decimate the odometer, place the run on the line (balises; ``s0_shift`` m added to the
    place, :func:`_placed`), the actuator on the grid."""
    has_grad = _has_gradient(line)
    t_all = d["odo_t"]
    step = max(1, int(round(1.0 / (cfg.max_rate * np.median(np.diff(t_all))))))
    sel = np.arange(0, t_all.size, step)
    t = t_all[sel]
    Y = np.stack([d["odo_distance"][sel], d["odo_speed"][sel]], axis=1)
    if "odo_speed_variance" in d:
        r_v = d["odo_speed_variance"][sel]
    else:
        r_v = np.full(t.size, prior.odometer_speed_variance)
    r_v = np.maximum(r_v, 1e-8)

    if "balise_t" in d:
        inside = (d["balise_t"] >= t_all[0]) & (d["balise_t"] <= t_all[-1])
        if not np.any(inside) and has_grad:
            raise IdentificationError("no balise reading falls inside the odometer record",
                                      ("balise inside the run",), ALL_PHYSICAL)
        offs = d["balise_position"][inside] - np.interp(d["balise_t"][inside], t_all,
                                                        d["odo_distance"])
        s0 = float(np.median(offs)) if offs.size else 0.0
        s0_var = _placement_variance(offs, prior)
    else:
        s0, s0_var = 0.0, math.nan

    tg = t[0] + cfg.grid_dt * np.arange(int(np.floor((t[-1] - t[0]) / cfg.grid_dt + 1e-9)) + 1)
    # each command from its own stamp (substep): another producer's commands are not on this
    # grid's lattice, and held from the next grid point they put the actuator up to a step late
    a_tr, a_br = actuator_output(tg, d["ctrl_t"], d["ctrl_a_tar"], prior.brake.time_constant,
                                 prior.brake.delay, substep=True)
    return _Run(t_all=t_all, t=t, Y=Y, r_v=r_v, dt=np.diff(t), s0=s0 + s0_shift,
                s0_var=s0_var, tg=tg, a_tr=a_tr, a_br=a_br, has_grad=has_grad)


def _placement_variance(offs: np.ndarray, prior: TrainParams) -> float:
    """m^2, the variance of the median of the balises' offsets (surveyed position minus the
    distance counted at the reading): each offset is the place plus the reading's error, whose
    variance is train.yaml's balise and distance variances, or the offsets' own robust spread
    (1.4826 MAD) where that is larger (a producer whose balises are worse than stated, a reader's
    latency at speed); the median of n has (pi / 2) of the mean's variance (Gaussian errors).
    Taken as exact, the place left its doubt out of every parameter the gradients carry: on
    metro_demo (10 balises) the spread of the mass, the rotary allowance and f over 20 seeds of
    one trajectory was 1.15-1.38 of the standard errors, 0.86-0.99 with the balises exact."""
    n = offs.size
    if n == 0:
        return math.nan
    var = prior.balise_position_variance + prior.odometer_distance_variance
    if n >= 3:
        var = max(var, (1.4826 * float(np.median(np.abs(offs - np.median(offs))))) ** 2)
    return 0.5 * math.pi * var / n


def _regressors(run: _Run, line: Line, cfg: SIConfig, v_ref_g, s_ref_g):
    """Regressor columns (PARAM_NAMES order) on the grid -> their integrals over each interval
    between stamps: (Bv, Bs, gradient accel on the grid, moving mask, held intervals)."""
    tg, t = run.tg, run.t
    mv = (v_ref_g >= cfg.standstill_speed).astype(float)
    # an interval is modelled only if the train moves throughout it
    cm = np.concatenate([[0.0], np.cumsum(1.0 - mv)])
    ig = np.searchsorted(tg, t)
    held_k = (cm[np.minimum(ig[1:] + 1, tg.size)] - cm[ig[:-1]]) > 0
    gs = line.gradient_accel(run.s0 + s_ref_g) if run.has_grad else np.zeros_like(tg)
    R = np.stack([run.a_tr, run.a_br, -np.ones_like(tg), -v_ref_g, -v_ref_g ** 2, -gs], axis=1)
    R *= mv[:, None]
    # cumulative integrals I1 = int r, I2 = int tau r (trapezoid on the grid)
    inc = 0.5 * (R[1:] + R[:-1]) * cfg.grid_dt
    tm = 0.5 * (tg[1:] + tg[:-1])
    I1 = np.concatenate([np.zeros((1, 6)), np.cumsum(inc, axis=0)])
    I2 = np.concatenate([np.zeros((1, 6)), np.cumsum(inc * tm[:, None], axis=0)])
    J1 = np.stack([np.interp(t, tg, I1[:, j]) for j in range(6)], axis=1)
    J2 = np.stack([np.interp(t, tg, I2[:, j]) for j in range(6)], axis=1)
    Bv = np.diff(J1, axis=0)
    Bs = t[1:, None] * Bv - np.diff(J2, axis=0)  # int (t_{k+1} - tau) r dtau
    Bv[held_k] = 0.0
    Bs[held_k] = 0.0
    return Bv, Bs, gs, mv, held_k


def _fit(run: _Run, free: dict, prior_vals: dict, Bv, Bs, q_vec, r_s):
    """GLS of the free parameters, the others fixed at the prior: (names, theta, cov, loglik,
    condition)."""
    names = [k for k in PARAM_NAMES if free[k]]
    fixed = [k for k in PARAM_NAMES if not free[k]]
    jf = [PARAM_NAMES.index(k) for k in names]
    jx = [PARAM_NAMES.index(k) for k in fixed]
    thx = np.array([prior_vals[k] for k in fixed])
    base_v = Bv[:, jx] @ thx if jx else np.zeros(len(run.dt))
    base_s = Bs[:, jx] @ thx if jx else np.zeros(len(run.dt))
    W, ld = _aug_kf(run.Y, run.dt, Bv[:, jf], Bs[:, jf], base_v, base_s, q_vec, r_s, run.r_v)
    th, cov, quad = gls(W, max_condition=MAX_CONDITION)
    return names, th, cov, -0.5 * (ld + quad), information_condition(W)


def _fit_noise(run, free, prior_vals, Bv, Bs, qvec, log_q, log_rs, cfg: SIConfig):
    """(log q, log r_s) by the profile likelihood (Nelder-Mead on logs)."""
    # imported here: diagnose imports this module for moving_average, and scipy.optimize's
    # import is some 0.2 s of CPU that a diagnose process would pay for nothing
    from scipy.optimize import minimize

    def negll(z):
        try:
            return -_fit(run, free, prior_vals, Bv, Bs, qvec(z[0]), np.exp(z[1]))[3]
        except np.linalg.LinAlgError:
            return np.inf
    opt = minimize(negll, np.array([log_q, log_rs]), method="Nelder-Mead",
                   options={"xatol": 0.05, "fatol": 0.05, "maxfev": 60})
    return (float(np.clip(opt.x[0], np.log(1e-12), np.log(10.0))),
            float(max(opt.x[1], np.log(cfg.min_distance_var))))


def identifiability_rule(cfg: SIConfig) -> str:
    """The rule :func:`_eliminate` applies, in words (printed by the ``identify`` tool)."""
    r_max = float(np.sqrt(1.0 - 1.0 / cfg.vif_max)) if cfg.vif_max > 1 else 0.0
    return (f"identifiable = tight AND separable: relative standard error <= {cfg.rel_se_max:g} "
            f"(SE / |prior value|; otherwise held at the prior, loosest first, and the rest "
            f"refitted) and variance inflation factor <= {cfg.vif_max:g} in the joint fit (the "
            f"other free parameters reproduce at most {100 * (1 - 1 / cfg.vif_max):.1f} % of its "
            f"effect; for two parameters |correlation| <= {r_max:.3f}; otherwise the joint fit's "
            "value is kept and flagged)")


def _correlation(cov: np.ndarray) -> np.ndarray:
    se = np.sqrt(np.diag(cov))
    se = np.where(se > 0, se, 1.0)
    return cov / np.outer(se, se)


def _vif(cov: np.ndarray) -> np.ndarray:
    """Variance inflation factors: VIF_i = [R^-1]_ii for the correlation matrix R of the
    estimates, = Var(theta_i, the others fitted) / Var(theta_i, the others known) =
    1 / (1 - R_i^2), R_i^2 the share of theta_i's effect the other parameters reproduce (in
    the metric of the likelihood)."""
    if cov.shape[0] < 2:
        return np.ones(cov.shape[0])
    return np.diag(np.linalg.pinv(_correlation(cov)))


def _eliminate(run, free, reasons, prior_vals, Bv, Bs, q_vec, r_s, cfg: SIConfig, log=None):
    """Fit, holding at the prior the free parameter with the loosest interval until every free
    one has a relative standard error <= ``rel_se_max`` (``free`` and ``reasons`` are updated,
    each decision appended to ``log`` with the correlations at that moment); returns the last
    fit. Separability does not eliminate: a parameter the others reproduce keeps its joint
    value (holding it at a wrong prior would bias the others) and is only flagged."""
    while True:
        try:
            names, th, cov, ll, cond = _fit(run, free, prior_vals, Bv, Bs, q_vec, r_s)
        except np.linalg.LinAlgError as exc:
            raise IdentificationError(f"no excitation: {exc}", ("excitation",),
                                      ALL_PHYSICAL) from exc
        se = np.sqrt(np.diag(cov))
        rel = np.array([se[i] / max(abs(prior_vals[k]), 1e-12) for i, k in enumerate(names)])
        loose = [(rel[i], i) for i in range(len(names)) if rel[i] > cfg.rel_se_max]
        if not loose:
            return names, th, cov, ll, cond
        i = max(loose)[1]
        worst = names[i]
        free[worst] = False
        reasons[worst] = (f"relative standard error {rel[i]:.2f} > {cfg.rel_se_max:g}: "
                          "not identifiable from this run, prior kept")
        if log is not None:
            corr = _correlation(cov)
            log.append({"name": worst, "rule": "tight", "relative_se": float(rel[i]),
                        "variance_inflation": float(_vif(cov)[i]),
                        "correlations": {names[j]: float(corr[i, j])
                                         for j in range(len(names)) if j != i}})
        if not any(free[k] for k in ("alpha", "beta", "gamma")):
            raise IdentificationError(
                "no resistance parameter is identifiable from this run",
                ("excitation",), ("davis.a", "davis.b", "davis.c", "mass"))


def _separability(names, cov, reasons, cfg: SIConfig) -> dict:
    """name -> separable (VIF <= ``vif_max`` in the joint fit); the reason of a parameter that
    is not names its inflation and its two strongest correlations."""
    vif, corr = _vif(cov), _correlation(cov)
    sep = {}
    for i, k in enumerate(names):
        sep[k] = bool(vif[i] <= cfg.vif_max)
        if not sep[k]:
            partners = sorted(((corr[i, j], names[j]) for j in range(len(names)) if j != i),
                              key=lambda c: -abs(c[0]))
            with_ = ", ".join(f"{r:+.2f} with {p}" for r, p in partners[:2])
            reasons[k] = (f"fitted jointly but not separable: variance inflation {vif[i]:.3g} > "
                          f"{cfg.vif_max:g} (correlation {with_}): the other parameters "
                          "reproduce its effect, only their combination is determined (see the "
                          "force at the reference speed)")
    return sep


def _force_report(names, th, cov, prior_vals, meff: float, prior: TrainParams, v: float):
    """The resistance force a + b v + c v^2 (N) at speed ``v`` (m/s): fitted, its standard
    error (delta method over the free alpha, beta, gamma, given the fitted effective mass), the
    prior's and the difference in standard errors. The force at a speed the run spends its
    time at is determined far better than the terms a, b, c one by one when they are
    correlated."""
    vals = dict(prior_vals)
    vals.update(dict(zip(names, th)))
    grad = np.zeros(len(names))
    for k, x in (("alpha", 1.0), ("beta", v), ("gamma", v * v)):
        if k in names:
            grad[names.index(k)] = meff * x
    fitted = meff * (vals["alpha"] + vals["beta"] * v + vals["gamma"] * v * v)
    se = float(np.sqrt(max(grad @ cov @ grad, 0.0)))
    d = prior.davis
    at_prior = d.a + d.b * v + d.c * v * v
    return {"speed": float(v), "fitted": float(fitted), "std_error": se,
            "prior": float(at_prior),
            "z_vs_prior": float((fitted - at_prior) / se) if se > 0 else float("nan")}


def _physical(names, th, cov, free, reasons, prior_vals, prior: TrainParams, vif=None):
    """Specific parameters -> train.yaml quantities given the prior mass (delta method for the
    standard errors): (values, std_errors, identifiable, reasons, davis, lambda, mass, f)."""
    vals = dict(prior_vals)
    vals.update(dict(zip(names, th)))
    ses = {k: float("nan") for k in PARAM_NAMES}
    ses.update({k: float(s) for k, s in zip(names, np.sqrt(np.diag(cov)))})
    ident = {k: bool(free[k]) for k in PARAM_NAMES}
    for i, k in enumerate(names):
        infl = "" if vif is None else f", variance inflation {vif[i]:.3g}"
        reasons.setdefault(k, f"identified, relative SE {ses[k] / abs(prior_vals[k]):.3f}{infl}")
    kap = vals["kappa"]
    lam = 1.0 / kap - 1.0
    se_lam = ses["kappa"] / kap ** 2 if ident["kappa"] else float("nan")
    kg = vals["traction_gain"]
    mass = prior.mass / kg
    se_mass = prior.mass * ses["traction_gain"] / kg ** 2 if ident["traction_gain"] else np.nan
    braking_rate = vals["scaled_braking_rate"] / kg
    se_braking_rate = float("nan")
    if ident["scaled_braking_rate"]:
        # delta method for f = (k f) / k with the joint covariance of the free gains
        grad = np.zeros(len(names))
        grad[names.index("scaled_braking_rate")] = 1.0 / kg
        if ident["traction_gain"]:
            grad[names.index("traction_gain")] = -vals["scaled_braking_rate"] / kg ** 2
        se_braking_rate = float(np.sqrt(grad @ cov @ grad))
    meff = (1.0 + lam) * mass
    davis = Davis(a=vals["alpha"] * meff, b=vals["beta"] * meff, c=vals["gamma"] * meff)
    values = dict(vals)
    values.update({"davis.a": davis.a, "davis.b": davis.b, "davis.c": davis.c,
                   "mass": mass, "rotary_allowance": lam, "braking_rate": braking_rate})
    std = dict(ses)
    std.update({"davis.a": ses["alpha"] * meff, "davis.b": ses["beta"] * meff,
                "davis.c": ses["gamma"] * meff, "mass": se_mass, "rotary_allowance": se_lam,
                "braking_rate": se_braking_rate})
    ident.update({"davis.a": ident["alpha"], "davis.b": ident["beta"], "davis.c": ident["gamma"],
                  "mass": ident["traction_gain"], "rotary_allowance": ident["kappa"],
                  "braking_rate": ident["scaled_braking_rate"]})
    def mass_note(sym):
        return (f" (in N: {sym} M_eff with the fitted mass)" if ident["traction_gain"]
                else " (in N given the prior mass)")

    reasons.update({
        "davis.a": reasons["alpha"] + mass_note("alpha"),
        "davis.b": reasons["beta"] + mass_note("beta"),
        "davis.c": reasons["gamma"] + mass_note("gamma"),
        "mass": (("identified as M_prior / traction_gain, assuming the drive force is the "
                  "command times the believed mass") if ident["traction_gain"] else
                 ("not identifiable: " + reasons["traction_gain"])),
        "rotary_allowance": reasons["kappa"], "braking_rate": reasons["scaled_braking_rate"]})
    return values, std, ident, reasons, davis, lam, mass, braking_rate


def _mass_hypothesis(run, free, prior_vals, prior: TrainParams, Bv, Bs, q_vec, r_s):
    """The mass explaining the data if a, b, c (N) are train.yaml's: resistance = k * prior
    specific resistance, k = M_eff,prior / M_eff. Returns ((kg, SE kg), loglik)."""
    free_m = {k: (free[k] if k in ("scaled_braking_rate", "kappa") else False)
              for k in PARAM_NAMES}
    jx = [PARAM_NAMES.index(k) for k in PARAM_NAMES if not free_m[k] and k not in
          ("alpha", "beta", "gamma")]
    jf = [PARAM_NAMES.index(k) for k in PARAM_NAMES if free_m[k]]
    res_col = (Bv[:, 2:5] @ np.array([prior_vals["alpha"], prior_vals["beta"],
                                      prior_vals["gamma"]]))
    res_col_s = (Bs[:, 2:5] @ np.array([prior_vals["alpha"], prior_vals["beta"],
                                        prior_vals["gamma"]]))
    thx = np.array([prior_vals[PARAM_NAMES[j]] for j in jx])
    W, ld = _aug_kf(run.Y, run.dt, np.concatenate([Bv[:, jf], res_col[:, None]], axis=1),
                    np.concatenate([Bs[:, jf], res_col_s[:, None]], axis=1),
                    Bv[:, jx] @ thx, Bs[:, jx] @ thx, q_vec, r_s, run.r_v)
    thm, covm, quad = gls(W, max_condition=MAX_CONDITION)
    llm = -0.5 * (ld + quad)
    kscale, se_k = thm[-1], float(np.sqrt(covm[-1, -1]))
    m_eq = prior.mass / kscale
    return (float(m_eq), float(prior.mass * se_k / kscale ** 2)), llm


def identify(data: SIData, line: Line, prior: TrainParams, config: SIConfig = SIConfig(),
             progress: Callable[[int, int, str], None] | None = None) -> SIResult:
    """Fit braking rate f, specific Davis resistance (alpha, beta, gamma) and kappa = 1/(1+lambda)
    from one run; map them to train.yaml quantities given the prior mass.

    Raises :class:`IdentificationError` (with what is missing and which parameters cannot be
    identified) for missing series, too short runs, a train that never moves or only cruises.
    ``progress(step, total, what)`` is called as the fit proceeds.

    Steps: check the run (:func:`_check_run`), decimate and place it (:func:`_prepare`), then
    ``outer_iterations`` times: regressors about the reference trajectory (:func:`_regressors`),
    the noise by profile likelihood (first time only, :func:`_fit_noise`), the GLS with
    elimination of unidentifiable parameters (:func:`_eliminate`) and a new reference from the
    RTS smoother; finally the physical quantities (:func:`_physical`), the resistance force at
    the reference speed (:func:`_force_report`) and the mass hypothesis
    (:func:`_mass_hypothesis`).

    Identifiable means tight AND separable (:func:`identifiability_rule`): a parameter's
    interval must be narrow against its size (relative SE <= ``rel_se_max``; otherwise it is held
    at the prior and the rest refitted) and its effect must not be reproduced by the other free
    parameters (variance inflation factor <= ``vif_max``; VIF = 1 / (1 - R^2), R^2 the share of
    its effect the others explain; otherwise it keeps the joint fit's value and is flagged).
    The Davis terms are the usual case: over a run's speeds 1, v and v^2 are nearly collinear,
    so a, b and c trade off against each other (correlations near -1 between neighbours) and
    can each be well off while the force they sum to is well determined. The result reports
    the correlations and inflation factors of the free parameters, every parameter held at the
    prior (with its correlations at that moment) and the force at the reference speed with
    its standard error.
    """
    cfg = config
    d = _validate(data, line)
    duration, lo, hi = _check_run(d, line, cfg)
    if cfg.command_offsets is None:
        out = _identify_at(d, 0.0, duration, lo, hi, line, prior, cfg, progress)
    else:
        out = _profiled(d, duration, lo, hi, line, prior, cfg, progress)
    return _placed(out, d, duration, lo, hi, line, prior, cfg) if cfg.placement_doubt else out


def _placed(out: SIResult, d: dict, duration, lo, hi, line: Line, prior: TrainParams,
            cfg: SIConfig) -> SIResult:
    """``out`` with the doubt of the run's place on the line in every standard error: the fits
    with the place moved by -+ its standard deviation (the same command offset and noise), and
    ``SE^2 + ((v+ - v)^2 + (v- - v)^2) / 2`` (:func:`_doubted` with the fit itself: the
    unscented transform's two sigma points of one Gaussian quantity). The place sets where the
    map's gradients act on the run, so the parameters the gradients carry (the rotary allowance,
    and through them the mass, f and the Davis terms) move with it; on a line without gradients
    nothing does. A value is not linear in the place over its doubt (the gradients change in
    steps): on a hilly line the mass moved by -2.6 kg and +19.4 kg for a place moved by +-0.64 m,
    where the slope of a secant would have held (11 kg)^2 and the two sides hold (14 kg)^2."""
    dg = out.diagnostics
    var = dg.get("position_offset_var", math.nan)
    if not (_has_gradient(line) and math.isfinite(var) and var > 0.0):
        return out
    h = math.sqrt(var)
    noise = (math.log(dg["process_noise_psd"]), math.log(dg["distance_noise_var"]))
    shift = dg.get("command_offset_s", 0.0)
    shift = shift if math.isfinite(shift) else 0.0
    try:
        lo_f, hi_f = (_identify_at(d, shift, duration, lo, hi, line, prior, cfg, None,
                                   noise=noise, smooth=False, s0_shift=k * h) for k in (-1, 1))
    except IdentificationError:
        return dataclasses.replace(out, reasons={**out.reasons, "position_offset": (
            "the fit failed with the run's place on the line moved by its standard deviation: "
            "the place's doubt is in no standard error")})
    std, force = _doubted(out, lo_f, hi_f, h, var, mid=out)
    return dataclasses.replace(out, std_errors=std, force_at_reference_speed=force)


def _doubted(out: SIResult, lo_f: SIResult | None, hi_f: SIResult | None, h: float,
             var: float, mid: SIResult | None = None) -> tuple[dict, dict]:
    """(standard errors, force report) of ``out`` with the doubt of one quantity it took as
    known, added in quadrature (the marginal variance of a joint Gaussian): each value's slope
    along it (the fits ``lo_f``, ``hi_f`` at -+``h``) times its standard deviation; or, given
    the fit ``mid`` at the quantity itself and ``h`` its standard deviation, the mean square of
    the two sides' moves (sigma points: what a value not linear in it moves by)."""

    def with_doubt(se, v0, v1, vm=0.0):
        if lo_f is None or not all(isinstance(v, float | int) and math.isfinite(v)
                                   for v in (se, v0, v1, vm)):
            return se
        if mid is not None:
            return math.sqrt(se ** 2 + 0.5 * ((v0 - vm) ** 2 + (v1 - vm) ** 2))
        return math.sqrt(se ** 2 + ((v1 - v0) / (2.0 * h)) ** 2 * var)

    std = {name: with_doubt(se, lo_f.values.get(name) if lo_f else None,
                            hi_f.values.get(name) if hi_f else None,
                            mid.values.get(name) if mid else 0.0)
           for name, se in out.std_errors.items()}
    force = dict(out.force_at_reference_speed)
    if force and lo_f is not None:
        se = with_doubt(force.get("std_error"), lo_f.force_at_reference_speed.get("fitted"),
                        hi_f.force_at_reference_speed.get("fitted"),
                        mid.force_at_reference_speed.get("fitted") if mid else 0.0)
        if se != force.get("std_error"):
            force["std_error"] = se
            force["z_vs_prior"] = (force["fitted"] - force["prior"]) / se
    return std, force


OFFSET_TOL = 0.002  # s, the command offset's search resolution (its SE is 0.01 on 10-min runs)
OFFSET_H = 0.01  # s, the half-width of the parabola for the offset's variance
OFFSET_MAX = 2.0  # s, the latest the profile looks for the commands to act after their stamps


def _profiled(d: dict, duration, lo, hi, line: Line, prior: TrainParams, cfg: SIConfig,
              progress) -> SIResult:
    """:func:`identify` with the commands' time offset profiled: the fit at each offset of
    ``cfg.command_offsets`` (s added to every command stamp: the commands act that much after
    they were stamped), the best one refined by Brent's method between its neighbours (to
    ``OFFSET_TOL``), then the parabola through full fits at it and ``OFFSET_H`` either side:
    its vertex is the offset, its curvature the offset's variance; every standard error then
    holds the offset's doubt, ``SE^2 + (d value / d offset)^2 Var(offset)`` (the marginal
    variance of a joint Gaussian, the slope taken along the profile). Another producer's
    commands need not act when stamped: the foreign simulator's act about 0.05 s later, and
    taken as stamped its mass came 6-13 of its standard errors off the truth, the sign
    flipping with a shift of 0.1 s."""
    from scipy.optimize import minimize_scalar

    lo_s, hi_s, step = cfg.command_offsets
    grid = lo_s + step * np.arange(int(round((hi_s - lo_s) / step)) + 1)
    first_error: list = []
    # the search's fits linearise once, at the noise of the fit as stamped, without the last
    # smoothing (a fifth of a fit's time); about its best, fits in full give the offset and its
    # variance
    quick = dataclasses.replace(cfg, outer_iterations=1)
    try:
        dg = _identify_at(d, 0.0, duration, lo, hi, line, prior, quick, None,
                          smooth=False).diagnostics
        noise = (math.log(dg["process_noise_psd"]), math.log(dg["distance_noise_var"]))
    except IdentificationError:
        noise = None  # refused as stamped: each offset fits its own noise
    fits: dict = {}

    def ll(sh: float) -> float:
        sh = round(float(sh), 9)
        if sh not in fits:
            try:
                fits[sh] = _identify_at(d, sh, duration, lo, hi, line, prior, quick, None,
                                        noise=noise, smooth=False)
            except IdentificationError as exc:
                first_error.append(exc)
                fits[sh] = None
        return -math.inf if fits[sh] is None else fits[sh].diagnostics["loglik"]

    coarse = [ll(sh) for sh in grid]
    # the best at an end of the range: the range goes on a step at a time, up to OFFSET_MAX
    # later (a brake delay 0.6 s longer than believed is an offset of +0.6 s) and down to the
    # believed delay (commands cannot act before they are given)
    grid = list(grid)
    while np.isfinite(coarse[-1]) and int(np.argmax(coarse)) == len(grid) - 1 \
            and grid[-1] + step <= OFFSET_MAX + 1e-9:
        grid.append(grid[-1] + step)
        coarse.append(ll(grid[-1]))
    while np.isfinite(coarse[0]) and int(np.argmax(coarse)) == 0 \
            and prior.brake.delay + grid[0] - step > 0.0:
        grid.insert(0, grid[0] - step)
        coarse.insert(0, ll(grid[0]))
    grid, coarse = np.asarray(grid), np.asarray(coarse)
    if not np.any(np.isfinite(coarse)):
        raise first_error[0]
    i = int(np.argmax(coarse))
    best, var, reasons_extra = float(grid[i]), math.nan, {}
    inside = 0 < i < grid.size - 1 and np.isfinite(coarse[i - 1]) and np.isfinite(coarse[i + 1])
    if inside:
        res = minimize_scalar(lambda sh: -ll(sh), bounds=(grid[i - 1], grid[i + 1]),
                              method="bounded", options={"xatol": OFFSET_TOL})
        best = round(float(res.x), 9) if ll(res.x) >= coarse[i] else float(grid[i])
    else:
        reasons_extra["command_offset"] = (
            f"the likelihood is highest at the end of the offsets profiled ({grid[0]:+.2f} to "
            f"{grid[-1]:+.2f} s): the commands may act further off their stamps than that")
    lo_f = hi_f = None
    if inside:
        # in full about the quick search's best: the parabola through three fits OFFSET_H
        # apart, its vertex the offset and its curvature the offset's variance
        h = OFFSET_H
        try:
            lo_f, mid, hi_f = (_identify_at(d, best + k * h, duration, lo, hi, line, prior, cfg,
                                            None) for k in (-1, 0, 1))
        except IdentificationError:
            lo_f = hi_f = None
        if lo_f is not None:
            l0, l1, l2 = (r.diagnostics["loglik"] for r in (lo_f, mid, hi_f))
            curv = (l0 - 2.0 * l1 + l2) / h ** 2
            if curv < 0.0:
                var = -1.0 / curv
                best = round(best + float(np.clip((l0 - l2) / (2.0 * h * curv), -h, h)), 9)
            else:
                lo_f = hi_f = None
        if not math.isfinite(var):
            reasons_extra["command_offset"] = (
                "the likelihood is not curved about the offset found (the model's actuator "
                "lag or delay may be off, or the fit flat in it): its doubt is in no "
                "standard error")
    out = _identify_at(d, best, duration, lo, hi, line, prior, cfg, None)
    # the offset's doubt: its value's slope along the profile times its standard deviation
    std, force = _doubted(out, lo_f, hi_f, OFFSET_H, var)
    if progress is not None:
        progress(1, 1, "done")
    # commands that act later than stamped are an actuator that answers later: the fitted
    # train carries the offset in its delay (traction and brake share it, as the grid's
    # actuator has them), so that a replay of the commands as stamped with it moves as the fit
    train = out.train
    if prior.brake.delay + best > 0.0:
        train = train.with_changes(brake=dataclasses.replace(
            train.brake, delay=float(prior.brake.delay + best)))
    else:
        reasons_extra["command_offset"] = (
            f"the commands act {-best:.3f} s before their stamps, more than the believed "
            f"delay ({prior.brake.delay:g} s): the train's delay is left as believed")
    return dataclasses.replace(
        out, train=train, std_errors=std, reasons={**out.reasons, **reasons_extra},
        force_at_reference_speed=force,
        diagnostics={**out.diagnostics, "command_offset_s": best,
                     "command_offset_se": math.sqrt(var) if math.isfinite(var) else math.nan,
                     "command_offset_profile": dict(zip(map(float, grid), map(float, coarse)))})


def _identify_at(d: dict, shift: float, duration, lo, hi, line: Line, prior: TrainParams,
                 cfg: SIConfig, progress, noise: tuple | None = None,
                 smooth: bool = True, s0_shift: float = 0.0) -> SIResult:
    """The fit of :func:`identify` with every command stamp moved by ``shift`` s; ``noise``
    (log q, log r_s) given instead of fitted, and without ``smooth`` no smoothing after the
    last linearisation (the profile's points: their likelihood and values are all it uses;
    ``series`` then holds the measured speed's smoothing); ``s0_shift`` m added to the run's
    place on the line (:func:`_placed`)."""
    if shift:
        d = dict(d, ctrl_t=d["ctrl_t"] + shift)
    run = _prepare(d, line, prior, cfg, s0_shift)
    Y, dt, t, tg = run.Y, run.dt, run.t, run.tg
    braking_seen = bool(np.any(d["ctrl_a_tar"] < -cfg.min_brake))
    lam0 = prior.rotary_allowance
    meff0 = prior.effective_mass
    prior_vals = {"traction_gain": 1.0, "scaled_braking_rate": prior.brake.braking_rate,
                  "alpha": prior.davis.a / meff0, "beta": prior.davis.b / meff0,
                  "gamma": prior.davis.c / meff0, "kappa": 1.0 / (1.0 + lam0)}

    # initial reference: lightly smoothed measured speed, measured distance
    width = max(1, int(round(2.0 / np.median(dt))))
    v_ref = np.clip(moving_average(Y[:, 1], width), 0.0, None)
    s_ref = Y[:, 0]

    grad_spread = 0.0
    free = {"traction_gain": cfg.fit_traction_gain, "scaled_braking_rate": braking_seen,
            "alpha": True, "beta": True, "gamma": True, "kappa": True}
    reasons = {}
    if not cfg.fit_traction_gain:
        reasons["traction_gain"] = "fixed at 1 (fit_traction_gain=False): mass not identifiable"
    if not braking_seen:
        reasons["scaled_braking_rate"] = "no braking in the run: f not identifiable, prior kept"
    log_q, log_rs = np.log(1e-4), np.log(max(prior.odometer_distance_std ** 2,
                                             cfg.min_distance_var))
    total_steps = cfg.outer_iterations + 2
    fit = None
    fixed_log: list = []
    for outer in range(cfg.outer_iterations):
        Bv, Bs, gs, mv, held_k = _regressors(run, line, cfg, np.interp(tg, t, v_ref),
                                             np.interp(tg, t, s_ref))
        qvec = _QVec(held_k, cfg.standstill_q)
        if outer == 0:
            grad_spread = float(np.std(gs[mv > 0])) if np.any(mv > 0) else 0.0
            if grad_spread < cfg.min_gradient_spread:
                free["kappa"] = False
                reasons["kappa"] = (f"gradient acceleration varies too little along the run "
                                    f"(std {grad_spread:.2g} m/s^2): lambda not identifiable "
                                    "(confounded with a), prior kept")
            # noise once: the linearisation barely moves it
            log_q, log_rs = noise if noise is not None else _fit_noise(
                run, free, prior_vals, Bv, Bs, qvec, log_q, log_rs, cfg)
        names, th, cov, ll, cond = _eliminate(run, free, reasons, prior_vals, Bv, Bs,
                                              qvec(log_q), np.exp(log_rs), cfg, fixed_log)
        fit = (names, th, cov, ll, cond, Bv, Bs)
        if not smooth and outer == cfg.outer_iterations - 1:
            break
        # re-linearise about the smoothed trajectory under the fit
        vals = dict(prior_vals)
        vals.update(dict(zip(names, th)))
        thv = np.array([vals[k] for k in PARAM_NAMES])
        sm = _kf_rts(Y, dt, Bv @ thv, Bs @ thv, qvec(log_q), np.exp(log_rs), run.r_v)
        s_ref, v_ref = sm[:, 0], np.clip(sm[:, 1], 0.0, None)
        if progress is not None:
            progress(outer + 1, total_steps, f"linearisation {outer + 1}/{cfg.outer_iterations}")

    names, th, cov, ll, cond, Bv, Bs = fit
    vif = _vif(cov)
    separable = _separability(names, cov, reasons, cfg)
    values, std, fitted, reasons, davis, lam, mass, braking_rate = _physical(
        names, th, cov, free, reasons, prior_vals, prior, vif)
    ident = {k: fitted[k] and separable.get(k, True) for k in PARAM_NAMES}
    ident.update({"davis.a": ident["alpha"], "davis.b": ident["beta"], "davis.c": ident["gamma"],
                  "mass": ident["traction_gain"], "rotary_allowance": ident["kappa"],
                  "braking_rate": ident["scaled_braking_rate"]})
    if fitted["traction_gain"] and not separable.get("traction_gain", True):
        reasons["mass"] = reasons["traction_gain"]
    moving = d["odo_speed"][d["odo_speed"] > cfg.min_speed]
    v_force = (float(np.median(moving)) if cfg.reference_speed is None
               else float(cfg.reference_speed))
    force = _force_report(names, th, cov, prior_vals, (1.0 + lam) * mass, prior, v_force)
    mass_hyp, llm = _mass_hypothesis(run, free, prior_vals, prior, Bv, Bs, qvec(log_q),
                                     np.exp(log_rs))

    train = prior.with_changes(
        davis=davis if any(fitted[k] for k in ("alpha", "beta", "gamma")) else prior.davis,
        rotary_allowance=float(lam) if fitted["kappa"] else prior.rotary_allowance,
        brake=prior.brake.__class__(time_constant=prior.brake.time_constant,
                                    delay=prior.brake.delay,
                                    braking_rate=float(braking_rate)),
        mass=float(mass),
    )
    if progress is not None:
        progress(total_steps, total_steps, "done")
    resid = Y[:, 1] - v_ref
    return SIResult(
        train=train, values=values, std_errors=std, identifiable=ident, reasons=reasons,
        covariance=cov, free_names=tuple(names), mass_if_davis_nominal=mass_hyp,
        correlation=_correlation(cov), variance_inflation=dict(zip(names, map(float, vif))),
        force_at_reference_speed=force, fixed_by_rule=tuple(fixed_log),
        rule=identifiability_rule(cfg),
        diagnostics={"samples_used": int(t.size), "duration_s": float(duration),
                     "position_offset_m": run.s0, "position_offset_var": run.s0_var,
                     "process_noise_psd": float(np.exp(log_q)),
                     "distance_noise_var": float(np.exp(log_rs)), "loglik": float(ll),
                     "loglik_mass_hypothesis": float(llm), "condition": float(cond),
                     "speed_range": (float(lo), float(hi)), "gradient_spread": grad_spread,
                     "speed_residual_rms": float(np.sqrt(np.mean(resid ** 2)))},
        series={"t": t, "speed_measured": Y[:, 1], "speed_smoothed": v_ref,
                "distance_smoothed": s_ref},
    )
