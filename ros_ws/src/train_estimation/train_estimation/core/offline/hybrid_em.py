"""Hybrid Kalman/particle-filter EM (Section 2 of the hybrid-filter EM paper) and baselines.

Model and M-step: :mod:`train_estimation.core.offline.em_model` (eq. (1)-(7), (31)-(36)).

E-steps (all vectorised: particles on the leading axis, independent data sets -- e.g. Monte Carlo
seeds -- on trailing batch axes, so one Python loop over time serves a whole benchmark):

``hybrid``  (paper, Section 2.1) Kalman filter for the displacement given the velocity estimate
            (eq. (20)-(24)) and a bootstrap particle filter for the velocity on y2 only
            (eq. (25)-(28), with the slips fixed, see em_model). Options:
            ``position='rb'`` -- Rao-Blackwellised: each velocity particle carries the Kalman mean
            of s along its own path (the variance is common to all particles), and y1 weights the
            particles through the KF predictive density N(y1; shat_i, P^- + sigma1^2). The paper's
            split ignores that y1 carries information on v (y1(t) - y1(t-1) ~ T v(t-1)).
``pf``      both states by particles (the paper's Table 3 baseline), weights from y1 and y2.
``ekf``     extended Kalman filter on (s, v) (Table 2 baseline).
``exact``   (beyond the paper) Kalman filter + RTS smoother on the model *linearised* about a
            fixed reference speed trajectory v_ref (moving average of y2, fixed before EM). For
            that linear-Gaussian model the E-step is exact, so EM never decreases the
            log-likelihood, which is computed exactly from the innovations.

Statistics for the M-step: ``statistics='plugin'`` -- the paper's eq. (31)/(33) with the
(filtered, or fixed-lag smoothed) means plugged in; ``'pairs'`` -- weighted particle pairs
(v(t-1), v(t)), i.e. a Monte Carlo version of the exact EM expectation. ``lag`` L > 0 turns the
particle filter into a fixed-lag smoother: the pair for transition t is read off the ancestral
lines at time t + L, i.e. from p(v(t-1), v(t) | y(1..t+L)) (Kitagawa & Sato 2001; Olsson et al.
2008). The displacement then gets an RTS pass given the smoothed velocity.

Pure: numpy only; randomness only through ``rng``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..numerics import kalman
from ..numerics.smc import log_normalize, systematic_resample
from .em_model import (
    G_PER_KN,
    NoiseParams,
    SuffStats,
    expand_to,
    gaussian_pair_stats,
    m_step,
    pair_stats,
    plugin_stats,
    theta_change,
    velocity_drift,
)

__all__ = [
    "Prior",
    "EStepResult",
    "EMResult",
    "kalman_position",
    "particle_e_step",
    "kalman_e_step",
    "e_step",
    "run_em",
    "reference_speed",
    "METHODS",
]

METHODS = ("hybrid", "pf", "ekf", "exact")
LOG2PI = np.log(2.0 * np.pi)


@dataclass(frozen=True)
class Prior:
    """Initial state prior. Paper (Section 2.1 steps 1-2): sbar(0) = 0, P+(0) = 10,
    v_i(0) = 0.2 randn."""

    s0: float = 0.0  # m
    s0_var: float = 10.0  # m^2
    v0: float = 0.0  # m/s
    v0_var: float = 0.04  # (m/s)^2


DEFAULT_PRIOR = Prior()
DEFAULT_NOISE = NoiseParams()


@dataclass(frozen=True)
class EStepResult:
    stats: SuffStats  # for the M-step
    v_mean: np.ndarray  # (n+1, *b) m/s, filtered (lag 0) or smoothed means of v(0..n)
    s_mean: np.ndarray  # (n+1, *b) m, filtered or RTS-smoothed means of s(0..n)
    loglik: np.ndarray  # (*b), log p(y | vartheta): exact (Kalman) or particle estimate
    ess_min: np.ndarray | None = None  # (*b), smallest effective sample size seen (particles)


@dataclass(frozen=True)
class EMResult:
    method: str
    vartheta: np.ndarray  # (k+1, 4, *b): vartheta_0 .. vartheta_k
    loglik: np.ndarray  # (k, *b): log-likelihood at vartheta_0 .. vartheta_{k-1} (E-step's)
    iterations: int
    converged: np.ndarray  # (*b) bool, step-7 rule met
    seconds: float  # wall time of the EM loop
    last: EStepResult  # E-step at vartheta_{k-1}

    @property
    def final(self) -> np.ndarray:
        return self.vartheta[-1]


# ---------------------------------------------------------------------------------------------
# Particle machinery
# ---------------------------------------------------------------------------------------------


def _check_data(y1, y2, u):
    y1, y2, u = (np.asarray(x, float) for x in (y1, y2, u))
    if y1.shape != y2.shape or u.shape[0] != y1.shape[0]:
        raise ValueError(f"y1 {y1.shape}, y2 {y2.shape} and u {u.shape} must share the time axis")
    for name, x in (("y1", y1), ("y2", y2), ("u", u)):
        if not np.all(np.isfinite(x)):
            raise ValueError(f"{name} contains NaN or inf")
    if y1.shape[0] < 8:
        raise ValueError(f"need at least 8 samples, got {y1.shape[0]}")
    return y1, y2, u


def _vt_batch(vt, ndim_batch: int) -> np.ndarray:
    """vartheta as (4, *b) broadcastable against particle arrays (N, *b) from axis 1 on."""
    vt = np.asarray(vt, float)
    return vt.reshape(vt.shape + (1,) * (ndim_batch - (vt.ndim - 1)))


def kalman_position(y1, v_in, noise: NoiseParams, T: float = 1.0, prior: Prior = DEFAULT_PRIOR,
                    smooth: bool = True) -> np.ndarray:
    """Scalar Kalman filter (eq. (20)-(24), with (22) corrected) and optional RTS smoother for
    s(t) = s(t-1) + T v(t-1) + w1, y1 = s + e1, treating v_in(0..n-1) as a known input.

    ``y1`` (n, *b), ``v_in`` (n+1, *b). Returns s means (n+1, *b) for t = 0..n. The variance
    recursion does not depend on the data, so it is a plain scalar sequence common to the batch
    (the paper's scalar equations, written out); the smoother is :func:`kalman.rts_smooth`.
    """
    n = y1.shape[0]
    s_f = np.empty((n + 1,) + y1.shape[1:])
    s_p = np.empty_like(s_f)
    Pf = np.empty(n + 1)
    Pp = np.empty(n + 1)
    s_f[0], Pf[0] = prior.s0, prior.s0_var
    for t in range(1, n + 1):
        s_p[t] = s_f[t - 1] + T * v_in[t - 1]  # eq. (21)
        Pp[t] = Pf[t - 1] + noise.q_s  # eq. (23)
        K = Pp[t] / (Pp[t] + noise.r_s)  # eq. (22): P^-(P^- + sigma1^2)^{-1}
        s_f[t] = s_p[t] + K * (y1[t - 1] - s_p[t])  # eq. (20)
        Pf[t] = (1.0 - K) * Pp[t]  # eq. (24)
    if not smooth:
        return s_f
    s_s = kalman.rts_smooth(s_f[..., None], Pf[:, None, None], s_p[..., None],
                            Pp[:, None, None], np.ones((n + 1, 1, 1)))[0]
    return s_s[..., 0]


def particle_e_step(y1, y2, u, vt, noise: NoiseParams, rng: np.random.Generator,
                    n_particles: int = 200, position: str = "kf", lag: int = 0,
                    statistics: str = "plugin", T: float = 1.0, prior: Prior = DEFAULT_PRIOR,
                    ess_threshold: float = 0.5) -> EStepResult:
    """Particle E-step for the velocity (hybrid, Rao-Blackwellised hybrid, or joint PF).

    position: 'kf' (paper: KF for s on the particle mean, y1 does not weight the particles),
    'rb' (Rao-Blackwellised KF mean per particle, y1 weights), 'particles' (the PF baseline:
    s sampled too, weights from y1 and y2).
    Bootstrap filter: resample (systematic) when ESS < ess_threshold N, propagate with eq. (26)
    *plus* a w2 draw, weight by N(y2; v_i, sigma2^2) (eq. (27) corrected) [times the y1 term].
    ``lag`` >= 0: fixed-lag smoothing of the pair statistics/means (0 = filter).
    """
    if position not in ("kf", "rb", "particles"):
        raise ValueError(f"unknown position mode {position!r}")
    if statistics not in ("plugin", "pairs"):
        raise ValueError(f"unknown statistics {statistics!r}")
    if lag < 0 or n_particles < 2:
        raise ValueError("lag must be >= 0 and n_particles >= 2")
    y1, y2, u = _check_data(y1, y2, u)
    n, bshape = y2.shape[0], y2.shape[1:]
    N, L = n_particles, lag
    vtb = _vt_batch(vt, len(bshape))
    ue = expand_to(u, y2.ndim)
    sq, sr = np.sqrt(noise.q_v), np.sqrt(noise.q_s)

    v = prior.v0 + np.sqrt(prior.v0_var) * rng.standard_normal((N,) + bshape)
    w = np.full((N,) + bshape, 1.0 / N)
    if position == "particles":
        s = prior.s0 + np.sqrt(prior.s0_var) * rng.standard_normal((N,) + bshape)
    else:
        s = np.full((N,) + bshape, prior.s0)  # per-particle KF means ('rb'); 'kf' uses s[0]
    Ps = prior.s0_var  # common KF variance ('rb'); data independent
    # hist[j] = v(t - L - 1 + j), j = 0..L+1 (ancestral lines, re-indexed on every resampling)
    hist = np.broadcast_to(v, (L + 2,) + v.shape).copy()
    v_mean = np.empty((n + 1,) + bshape)
    v_mean[0] = np.sum(w * v, axis=0)
    stats = None
    loglik = np.zeros(bshape)
    ess_min = np.full(bshape, float(N))

    def emit(j0: int, tau: int, wts) -> None:
        nonlocal stats
        if statistics == "pairs":
            st = pair_stats(hist[j0], hist[j0 + 1], wts, ue[tau - 1])
            stats = st if stats is None else stats + st
        if L > 0:  # smoothed mean of v(tau) from the ancestral lines
            v_mean[tau] = np.sum(wts * hist[j0 + 1], axis=0)

    for t in range(1, n + 1):
        ess = 1.0 / np.sum(w * w, axis=0)
        ess_min = np.minimum(ess_min, ess)
        need = ess < ess_threshold * N
        if np.any(need):
            idx = systematic_resample(w, rng)
            idx = np.where(need, idx, np.arange(N).reshape((N,) + (1,) * len(bshape)))
            v = np.take_along_axis(v, idx, axis=0)
            s = np.take_along_axis(s, idx, axis=0)
            hist = np.take_along_axis(hist, idx[None], axis=1)
            w = np.where(need, 1.0 / N, w)
        v_prev = v
        # eq. (26) with the process noise draw the paper omits
        v = v_prev + velocity_drift(vtb, ue[t - 1], v_prev) + sq * rng.standard_normal(v.shape)
        logl = -0.5 * (LOG2PI + np.log(noise.r_v) + (y2[t - 1] - v) ** 2 / noise.r_v)  # (27)
        if position == "particles":
            s = s + T * v_prev + sr * rng.standard_normal(s.shape)
            logl = logl - 0.5 * (LOG2PI + np.log(noise.r_s) + (y1[t - 1] - s) ** 2 / noise.r_s)
        elif position == "rb":
            shat = s + T * v_prev  # eq. (21) along each particle's own path
            Pm = Ps + noise.q_s
            S = Pm + noise.r_s
            logl = logl - 0.5 * (LOG2PI + np.log(S) + (y1[t - 1] - shat) ** 2 / S)
            K = Pm / S
            s = shat + K * (y1[t - 1] - shat)
            Ps = (1.0 - K) * Pm
        w, lz = log_normalize(np.log(w) + logl)  # eq. (28)
        loglik = loglik + lz
        hist = np.concatenate([hist[1:], v[None]], axis=0)
        v_mean[t] = np.sum(w * v, axis=0)  # eq. (25) with its sum; overwritten if L > 0
        if t >= L + 1:
            emit(0, t - L, w)
    for tau in range(max(1, n - L + 1), n + 1):  # flush the last L transitions
        emit(tau - n + L, tau, w)

    if statistics == "plugin":
        stats = plugin_stats(v_mean, u)
    if position == "particles":
        s_mean = None
    else:
        s_mean = kalman_position(y1, v_mean, noise, T, prior, smooth=L > 0)
    if s_mean is None:  # PF baseline: filtered particle mean of s is all it keeps
        s_mean = np.full((n + 1,) + bshape, np.nan)
        s_mean[-1] = np.sum(w * s, axis=0)
    return EStepResult(stats=stats, v_mean=v_mean, s_mean=s_mean, loglik=loglik,
                       ess_min=ess_min)


# ---------------------------------------------------------------------------------------------
# Kalman E-steps (EKF baseline and the exact linearised variant)
# ---------------------------------------------------------------------------------------------


def reference_speed(y2, width: int = 5) -> np.ndarray:
    """Fixed linearisation reference for the exact variant: centred moving average of y2,
    prepended with the prior mean of v(0) (returned shape (n+1, *b), entry t = v_ref(t))."""
    y2 = np.asarray(y2, float)
    k = np.ones(width) / width
    pad = width // 2
    ypad = np.concatenate([np.repeat(y2[:1], pad, 0), y2, np.repeat(y2[-1:], pad, 0)], axis=0)
    sm = np.apply_along_axis(lambda c: np.convolve(c, k, mode="valid"), 0, ypad)
    return np.concatenate([np.zeros_like(y2[:1]), sm], axis=0)


def kalman_e_step(y1, y2, u, vt, noise: NoiseParams, T: float = 1.0, prior: Prior = DEFAULT_PRIOR,
                  v_ref=None, smooth: bool = True, statistics: str = "moments") -> EStepResult:
    """Kalman E-step on x = (s, v), vectorised over the batch.

    ``v_ref is None``: extended Kalman filter (Jacobian and mean propagation at the filtered
    estimate) -- the EKF baseline. ``v_ref`` (n+1, *b) given: the model with v^2 replaced by
    2 v_ref v - v_ref^2 (linear-Gaussian), for which the filter, the RTS smoother and the
    innovation log-likelihood are exact.

    Predict, update and smoother are :mod:`kalman`'s (``propagate_cov``, the sequential exact
    ``update`` -- R is diagonal -- and ``rts_smooth``), with the batch elements on the update's
    particle axis.

    statistics: 'plugin' (paper: means plugged into eq. (31)/(33); filtered if not smooth) or
    'moments' (exact expectations from smoothed first/second moments incl. the lag-one cross
    covariance Cov(v(t-1), v(t) | y) = [C_{t-1} P_{t|n}]_vv; requires smooth and v_ref).
    """
    y1, y2, u = _check_data(y1, y2, u)
    n, bshape = y2.shape[0], y2.shape[1:]
    vt = np.moveaxis(_vt_batch(vt, len(bshape)), 0, -1)  # (*b|1, 4)
    ue = expand_to(u, y2.ndim)
    lin = v_ref is not None
    if statistics == "moments" and not (lin and smooth):
        raise ValueError("exact moment statistics need the linearised model and smoothing")
    Q = np.diag([noise.q_s, noise.q_v])
    R = np.array([noise.r_s, noise.r_v])
    H, used = np.eye(2), np.ones(2, bool)
    m_f = np.empty((n + 1,) + bshape + (2,))
    P_f = np.empty((n + 1,) + bshape + (2, 2))
    m_p = np.empty_like(m_f)
    P_p = np.empty_like(P_f)
    F_all = np.empty_like(P_f)
    m_f[0] = np.array([prior.s0, prior.v0])
    P_f[0] = np.diag([prior.s0_var, prior.v0_var])
    loglik = np.zeros(bshape)
    Y = np.stack([y1, y2], axis=-1)
    for t in range(1, n + 1):
        s_, v_ = m_f[t - 1][..., 0], m_f[t - 1][..., 1]
        x_lin = v_ref[t - 1] if lin else v_
        dfdv = 1.0 - vt[..., 2] - 2.0 * vt[..., 3] * x_lin
        if lin:  # linear model: v^2 -> 2 v_ref v - v_ref^2
            v_pred = (v_ + vt[..., 0] * ue[t - 1] - vt[..., 1] - vt[..., 2] * v_
                      - vt[..., 3] * (2.0 * x_lin * v_ - x_lin * x_lin))
        else:
            v_pred = v_ + velocity_drift(np.moveaxis(vt, -1, 0), ue[t - 1], v_)
        F = np.zeros(bshape + (2, 2))
        F[..., 0, 0], F[..., 0, 1], F[..., 1, 1] = 1.0, T, dfdv
        F_all[t] = F
        m_p[t] = np.stack([s_ + T * v_, v_pred], axis=-1)
        P_p[t] = kalman.propagate_cov(P_f[t - 1], F, Q)
        # the batch elements are the update's particle axis (each with its own reading)
        x, P, ll = kalman.update(m_p[t].reshape(-1, 2), P_p[t].reshape(-1, 2, 2),
                                 Y[t - 1].reshape(-1, 2), H, R, used)
        m_f[t] = x.reshape(bshape + (2,))
        P_f[t] = P.reshape(bshape + (2, 2))
        loglik = loglik + ll.reshape(bshape)
    if not smooth:
        v_mean, s_mean = m_f[..., 1], m_f[..., 0]
        stats = plugin_stats(v_mean, u)
        return EStepResult(stats=stats, v_mean=v_mean, s_mean=s_mean, loglik=loglik)
    m_s, P_s, C = kalman.rts_smooth(m_f, P_f, m_p, P_p, F_all)
    # Cov(v(t-1), v(t) | y(1..n)), t = 1..n: the lag-one cross covariance C_{t-1} P_{t|n}
    cross = np.matmul(C, P_s[1:])[..., 1, 1]
    v_mean, s_mean = m_s[..., 1], m_s[..., 0]
    if statistics == "plugin":
        stats = plugin_stats(v_mean, u)
    else:
        Pv = P_s[..., 1, 1]
        stats = gaussian_pair_stats(u, v_mean[:-1], v_mean[1:], Pv[:-1], cross, Pv[1:],
                                    v_ref[:-1])
    return EStepResult(stats=stats, v_mean=v_mean, s_mean=s_mean, loglik=loglik)


# ---------------------------------------------------------------------------------------------
# EM driver
# ---------------------------------------------------------------------------------------------


def e_step(method: str, y1, y2, u, vt, noise: NoiseParams, rng: np.random.Generator | None,
           T: float = 1.0, prior: Prior = DEFAULT_PRIOR, **opts) -> EStepResult:
    """Dispatch one E-step. Options: n_particles, lag, statistics, position (particle methods);
    smooth, statistics, v_ref (Kalman methods)."""
    if method in ("hybrid", "pf"):
        if rng is None:
            raise ValueError(f"method {method!r} needs rng")
        pos = opts.pop("position", "kf") if method == "hybrid" else "particles"
        if method == "pf":
            opts.pop("position", None)
        return particle_e_step(y1, y2, u, vt, noise, rng, position=pos, T=T, prior=prior,
                               **opts)
    if method == "ekf":
        return kalman_e_step(y1, y2, u, vt, noise, T, prior, v_ref=None,
                             smooth=opts.get("smooth", False), statistics="plugin")
    if method == "exact":
        v_ref = opts.get("v_ref")
        if v_ref is None:
            raise ValueError("method 'exact' needs v_ref (see reference_speed)")
        return kalman_e_step(y1, y2, u, vt, noise, T, prior, v_ref=v_ref, smooth=True,
                             statistics="moments")
    raise ValueError(f"unknown method {method!r}; choose from {METHODS}")


def run_em(y1, y2, u, method: str = "hybrid", vt0=None, n_iter: int = 30, tol: float = 0.0,
           stop_space: str = "vartheta", noise: NoiseParams = DEFAULT_NOISE, T: float = 1.0,
           prior: Prior = DEFAULT_PRIOR, rng: np.random.Generator | None = None,
           progress: Callable[[int, int, np.ndarray, np.ndarray], None] | None = None,
           **opts) -> EMResult:
    """EM of Section 2.2 (steps 1-7).

    vt0: initial vartheta (4,) or (4, *b); default Theta_0 = [0, 0, 0, 0] (step 2), i.e.
    vartheta_0 = [0.0098 T, 0, 0, 0]. Each iteration: E-step at vartheta_{k-1}, M-step (36).
    Stops after ``n_iter`` iterations or when every batch element meets step 7,
    theta_change(vt_k, vt_{k-1}, space=stop_space) <= tol (tol = 0: never, run n_iter).
    ``progress(k, n_iter, vartheta_k, change_k)`` is called after every iteration.
    ``method='exact'`` computes its fixed v_ref from y2 unless ``v_ref`` is passed.
    """
    y1, y2, u = _check_data(y1, y2, u)
    bshape = y2.shape[1:]
    if vt0 is None:
        vt0 = np.array([G_PER_KN * T, 0.0, 0.0, 0.0])
    vt = np.broadcast_to(_vt_batch(vt0, len(bshape)), (4,) + bshape).astype(float)
    if method == "exact" and opts.get("v_ref") is None:
        opts["v_ref"] = reference_speed(y2)
    hist, lls = [vt], []
    converged = np.zeros(bshape, bool)
    t0 = time.perf_counter()
    res = None
    for k in range(1, n_iter + 1):
        res = e_step(method, y1, y2, u, vt, noise, rng, T, prior, **dict(opts))
        new = m_step(res.stats)
        change = theta_change(new, vt, T, stop_space)
        vt = new
        hist.append(vt)
        lls.append(res.loglik)
        if progress is not None:
            progress(k, n_iter, vt, change)
        converged = change <= tol
        if np.all(converged):
            break
    return EMResult(method=method, vartheta=np.stack(hist), loglik=np.stack(lls),
                    iterations=len(hist) - 1, converged=converged,
                    seconds=time.perf_counter() - t0, last=res)
