"""Rao-Blackwellised estimation of a braking rate (or any parameter of a linear-Gaussian family).

Joint posterior, Zheng et al. (2015) eq. (8)::

    p(theta_k, x_k | y_{1:k}) = p(x_k | theta_{1:k}, y_{1:k}) p(theta_{1:k} | y_{1:k})

The first factor is a Kalman filter per particle (``batched_kf``, leading particle axis); the
parameter factor is carried by weighted particles ``{theta_i, log w_i}``. All algorithms share one
step (``RaoBlackwellFilter.step``):

1. validate the input (reject with a reason, count it, leave the state untouched);
2. ``informative = family.gate(u, E[x])``: can this step say anything about theta?
3. parameter transition (only if informative, else *frozen*): algorithm specific, see below;
4. KF prediction of every particle with its own ``Phi(theta_i)`` (exact ZOH);
5. log predictive likelihood ``l_i = log N(y; H x_i, S_i)`` (Zheng (12)/(17), Q-GRBPF (5));
   ``log w_i += l_i``, normalised in log space (no underflow: no exp before the max is removed);
6. algorithm specific reduction (pruning / proposal selection), then KF update of survivors;
7. estimate = moments of the Gaussian mixture (mean and covariance of (D, v, a_hat, f) with the
   between-particle spread, law of total covariance), then resampling if the algorithm does.

Algorithms (theta = braking rate f):

* ``DiscreteRBPF`` -- particles on a discrete set, transition matrix ``T[j, m] = p(theta_k =
  v_m | theta_{k-1} = v_j)`` (eq. (5)). ``proposal="prior"``: sample from ``T`` and weight by the
  likelihood (bootstrap). ``proposal="optimal"``: sample from eq. (12),
  ``q(m) ∝ T[j, m] N(y; y_hat(v_m), S(v_m))``, weight with eq. (13),
  ``w ∝ w_prev sum_m T[j, m] N(...)``. Systematic resampling when ``N_eff < ess_frac * N``.
* ``SMA`` -- every particle branches to all values (uniform prior over children), the best
  ``n_keep`` (by weight) are kept when the count exceeds ``q_max`` (Section 3.4).
* ``GSMA`` -- every particle branches only to the group whose member mean is closest to its value;
  default groups: overlapping neighbour triples (Section 3.5); same pruning.
* ``QGRBPF`` -- continuous theta. Guan et al., steps (1)-(6): weights (1), Gaussian moments of the
  parameter posterior (2) (7)-(8), new parameters drawn from ``N(theta_hat, P + Q_theta dt)``
  (3) (9), the KF states paired with them by the paper's search algorithm (5) (17) (see
  ``QGRBPF``), KF update (4) and prediction (6). No weight-based resampling step of its own.
  ``quadrature=True``: the same Gaussian over theta carried by N Gauss-Hermite nodes whose KF
  states are the joint Gaussian's conditional -- no random draw, no resampling, few particles.
* ``RandomWalkRBPF`` -- continuous theta, Gaussian random-walk kernel, systematic resampling:
  the "RBPF" the Q-GRBPF paper compares with.
* ``BrakingKF`` -- one Kalman filter on (D, v, a_hat, a_z, f), f a random walk: the exact
  Bayesian estimator of the braking model (f enters linearly given the known command;
  ``braking_model.augmented_model``), the reference every table compares with.
* ``OracleKF`` -- one Kalman filter told the true theta_k.

**Priors and calibration (issue 15).** ``prior = (mean, std)``: discrete algorithms draw their
initial values from the Gaussian's mass on each value's cell (``grid_prior``), continuous ones
from the Gaussian (reflected into the bounds); None = the papers' uniform prior. A discrete
value stands for its cell, so each particle carries the cell's variance ``h^2 / 12``
(``cell_variance``) in the reported f variance, and SMA/GSMA form the estimate from *every*
evaluated branch before pruning to the N best (``_after``) -- otherwise the reported f variance
collapses to exactly 0 whenever the survivors share one value. ``merge=True`` (SMA/GSMA) replaces
pruning by merging the particles of each value into one Gaussian (at most values x children KFs
per step).

**Standstill, coasting, traction.** When ``informative`` is False (``BrakingModel.gate``: no
braking command, or standstill) every particle has the same model, so the likelihood is flat in
f *given the same state*; any f transition would only act on the f marginal: a random walk would
spread it step after step, SMA/GSMA branching with top-N pruning would collapse it onto
whichever children sort first, resampling would add Monte-Carlo drift. So the transition is
**frozen**: no sampling, branching, redraw, pruning or resampling; the particles keep their f and
their weights are only multiplied by the (state-dependent) likelihood. The f marginal therefore
holds exactly when the particles' KF states agree, and otherwise changes only by what the data
say about past braking through the states (legitimate evidence, decaying as the states
converge). ``test_braking_filters.py`` checks both.

**Bad input** never reaches the state: non-finite command/measurement/variance, bad mask,
non-finite or non-increasing time stamps are rejected with a reason (``Estimate.reason``,
counted in ``filter.rejected``); a numerical failure inside a step (all likelihoods -inf,
non-positive-definite innovation covariance) rejects the step the same way. Steps work on new
arrays and commit at the end, so a rejection cannot leave a half-updated particle set.

Pure: numpy/scipy only; randomness only through the ``rng`` argument.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np
from scipy.special import ndtr

from . import smc
from .batched_kf import mixture_moments, predict, update
from .braking_model import augmented_model
from .smc import effective_sample_size, log_normalize

__all__ = [
    "Estimate",
    "RaoBlackwellFilter",
    "DiscreteRBPF",
    "SMA",
    "GSMA",
    "QGRBPF",
    "RandomWalkRBPF",
    "OracleKF",
    "BrakingKF",
    "grid_prior",
    "cell_variance",
    "systematic_resample",
    "effective_sample_size",
    "neighbour_groups",
    "sticky_transition",
]


# ----------------------------------------------------------------------------------------------
# helpers


def systematic_resample(logw, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` ancestor indices by systematic resampling of log-weights (smc.systematic_resample);
    ``-inf`` entries are never drawn; ``ValueError`` if no weight is positive."""
    w, _ = log_normalize(logw)
    return smc.systematic_resample(w, rng, n)


def neighbour_groups(n_values: int) -> list[tuple[int, ...]]:
    """Groups of three overlapping neighbours ``{i-1, i, i+1}``, ``i = 1..M-1`` (Section 3.5).

    With ``M + 1`` values there are ``M - 1`` such groups (the paper says at most ``M - 2``, and
    Section 4 lists eight groups for eleven values, omitting ``{1.0, 0.9, 0.8}`` -- then a particle
    at 1.0 could never stay at 1.0 although f_0 = 1: both slips; we use all ``M - 1``).
    """
    if n_values < 3:
        return [tuple(range(n_values))]
    return [(i - 1, i, i + 1) for i in range(1, n_values - 1)]


def sticky_transition(n_values: int, p_move: float) -> np.ndarray:
    """Transition matrix on an ordered grid: stay with ``1 - p_move``, move to each neighbour
    with ``p_move / 2``; at the two ends the missing neighbour's mass stays (rows sum to one).
    ``p_move = 0`` is the static parameter the paper's RBPF suffers from."""
    T = np.eye(n_values) * (1.0 - p_move)
    for j in range(n_values):
        for m in (j - 1, j + 1):
            if 0 <= m < n_values:
                T[j, m] += p_move / 2.0
            else:
                T[j, j] += p_move / 2.0
    return T


def _lse_norm(lw):
    """``(max, log sum exp)`` of log-weights; raises ``ValueError`` unless some entry is finite
    and none is NaN/+inf (what ``log_normalize`` checks, without forming the weights)."""
    m = np.max(lw)
    if not np.isfinite(m) or np.isnan(lw).any():
        raise ValueError("log-weights: none finite, or NaN/+inf")
    return m, float(m + np.log(np.sum(np.exp(lw - m))))


def _reflect(theta, lo, hi):
    """Reflect into ``[lo, hi]`` (per column); keeps a Gaussian draw's shape near the bounds."""
    width = hi - lo
    y = np.mod(theta - lo, 2.0 * width)
    y = np.where(y > width, 2.0 * width - y, y)
    return lo + y


@dataclass(frozen=True)
class Estimate:
    """Posterior summary after one step (or the last good one, if the step was rejected)."""

    accepted: bool
    reason: str  # "" if accepted, else why the input was rejected (for the node's log)
    t: float | None  # s, time of the estimate (None if the filter runs on implicit steps)
    mean: np.ndarray  # (r + d,) e.g. (D m, v m/s, a_hat m/s^2, f -): report states + parameter
    cov: np.ndarray  # (r + d, r + d), mixture covariance (includes the f variance and cross terms)
    x_mean: np.ndarray  # (n,) whole linear state, e.g. (D, v, a_hat, a_z)
    x_cov: np.ndarray  # (n, n)
    theta_mean: np.ndarray  # (d,)
    theta_cov: np.ndarray  # (d, d)
    n_particles: int
    n_eff: float
    informative: bool  # the step could inform theta (transition not frozen)
    measurement_used: bool
    log_evidence: float = float("nan")  # log p(y_k | y_{1:k-1}); NaN if no measurement


@dataclass
class _Set:
    """The particle set (new arrays each step; committed at the end)."""

    theta: np.ndarray  # (N, d)
    x: np.ndarray  # (N, n)
    P: np.ndarray  # (N, n, n)
    logw: np.ndarray  # (N,) normalised: logsumexp = 0
    idx: np.ndarray | None = None  # (N,) value index (discrete algorithms)
    extra: dict = field(default_factory=dict)


# ----------------------------------------------------------------------------------------------
# base


class RaoBlackwellFilter:
    """Common step of all algorithms (module docstring). Subclasses override the hooks
    ``_initial_theta``, ``_transition``, ``_reduce`` and ``_after``."""

    name = "rb"
    #: s, minimum time between two parameter transitions (branching, sampling, redraw). 0: every
    #: step (the paper, dt = 1 s). The discrete kernels are *per transition*, so a live node
    #: stepping at every odometer/balise message (10 Hz and irregular) should set this to the
    #: step the kernel was designed for (1.0 s) to keep its meaning independent of the rate.
    transition_interval: float = 0.0

    def __init__(self, family):
        self.family = family
        self.rejected: Counter = Counter()
        self.n_steps = 0
        self._s: _Set | None = None
        self._t: float | None = None
        self._last: Estimate | None = None
        self._since = 0.0  # s since the last parameter transition

    # -- life cycle ------------------------------------------------------------------------
    def reset(self, x0, P0, rng: np.random.Generator | None = None, theta0=None,
              t0: float | None = None) -> Estimate:
        """Start from ``x_0 ~ N(x0, P0)`` for every particle and parameter particles ``theta0``
        (``(N,)`` or ``(N, d)``), or the algorithm's initial draw with ``rng`` if None."""
        fam = self.family
        x0 = np.asarray(x0, dtype=float).reshape(fam.n)
        P0 = np.asarray(P0, dtype=float).reshape(fam.n, fam.n)
        if not (np.all(np.isfinite(x0)) and np.all(np.isfinite(P0))):
            raise ValueError("reset: x0 and P0 must be finite")
        if np.any(np.linalg.eigvalsh(0.5 * (P0 + P0.T)) < 0):
            raise ValueError("reset: P0 must be positive semi-definite")
        if theta0 is None:
            if rng is None:
                raise ValueError("reset: give theta0 or an rng for the initial draw")
            theta, idx = self._initial_theta(rng)
        else:
            theta, idx = self._theta_from_values(np.asarray(theta0, dtype=float))
        N = theta.shape[0]
        lw0 = self._initial_logw(N) if theta0 is None else None
        self._s = _Set(theta=theta, x=np.repeat(x0[None], N, axis=0),
                       P=np.repeat(P0[None], N, axis=0),
                       logw=np.full(N, -np.log(N)) if lw0 is None else lw0, idx=idx)
        self._t = None if t0 is None else float(t0)
        self.rejected = Counter()
        self.n_steps = 0
        self._since = 0.0
        self._last = self._summary(self._s, True, "", False, False, float("nan"))
        return self._last

    def _theta_from_values(self, values):
        theta = values.reshape(values.shape[0], -1)
        return theta, None

    def _initial_theta(self, rng):
        raise NotImplementedError

    def _initial_logw(self, N):
        """Initial normalised log-weights of the initial draw; None: uniform."""
        return None

    # -- properties ------------------------------------------------------------------------
    @property
    def t(self) -> float | None:
        return self._t

    @property
    def particles(self) -> tuple[np.ndarray, np.ndarray]:
        """``(theta (N, d), log w (N,))`` copies, for tests and diagnostics."""
        return self._s.theta.copy(), self._s.logw.copy()

    def estimate(self) -> Estimate:
        return self._last

    # -- the step --------------------------------------------------------------------------
    def step(self, a_tar: float, y=None, mask=None, rng: np.random.Generator | None = None, *,
             t: float | None = None, meas_var=None, d: float = 0.0) -> Estimate:
        """Advance to the next measurement time and assimilate ``y``.

        ``a_tar`` (m/s^2): command held since the previous step (ZOH). ``y (3,)``: (D m, v m/s,
        a_z m/s^2) with ``mask (3,)`` bool saying which are measured (None: all; ``y`` None:
        predict only). ``t`` (s): absolute stamp; ``dt = t - t_prev`` (the first stamped step
        after a reset without ``t0`` only updates). Without ``t``, ``dt = family.default_dt()``.
        ``meas_var (3,)``: this step's variances (None: the model's). ``d`` (m/s^2): known extra
        acceleration on v (gradient/resistance; 0 in the paper).
        """
        if self._s is None:
            raise RuntimeError("call reset() first")
        fam = self.family
        reason, dt, y_arr, mask_arr, R = self._validate(a_tar, y, mask, t, meas_var, d)
        if reason:
            return self._reject(reason)
        u = np.array([float(a_tar), float(d)])
        s = self._s
        informative = bool(fam.gate(u, self._last.x_mean))
        try:
            since = self._since + dt
            if dt > 0:
                due = informative and since >= self.transition_interval
                if due:
                    s = self._transition(s, True, rng, since)
                    since = 0.0
                else:
                    s = self._transition(s, False, rng, dt)
                x, P = self._predict(s, u, dt, informative)
                s = _Set(s.theta, x, P, s.logw, s.idx, s.extra)
            x, P, loglik = update(s.x, s.P, y_arr, fam.H, R, mask_arr)
            if np.any(np.isnan(loglik)):
                return self._reject("numerical failure: NaN likelihood")
            s = _Set(s.theta, x, P, s.logw, s.idx, s.extra)
            s, log_ev = self._reduce(s, loglik, informative, rng)
            used = bool(np.any(mask_arr))
            est = self._summary(s, True, "", informative, used, log_ev if used else np.nan, t)
            s = self._after(s, informative, rng)
        except (ValueError, np.linalg.LinAlgError) as exc:
            return self._reject(f"numerical failure: {exc}")
        if not (np.all(np.isfinite(s.x)) and np.all(np.isfinite(s.P))
                and np.all(np.isfinite(s.theta)) and s.theta.shape[0] > 0):
            return self._reject("numerical failure: non-finite particle state")
        self._s = s
        self._since = since
        if t is not None:
            self._t = float(t)
        self.n_steps += 1
        self._last = est
        return est

    def _validate(self, a_tar, y, mask, t, meas_var, d):
        fam = self.family
        p = fam.H.shape[0]
        bad = (None, None, None, None)
        try:
            a = float(a_tar)
            dd = float(d)
        except (TypeError, ValueError):
            return ("non-numeric command", *bad)
        if not (np.isfinite(a) and np.isfinite(dd)):
            return (f"non-finite command: a_tar={a_tar!r}, d={d!r}", *bad)
        if t is None:
            dt = float(fam.default_dt())
        else:
            try:
                tf = float(t)
            except (TypeError, ValueError):
                return ("non-numeric time stamp", *bad)
            if not np.isfinite(tf):
                return (f"non-finite time stamp: {t!r}", *bad)
            if self._t is None:
                dt = 0.0
            elif tf < self._t or (tf == self._t and y is None):
                # A reading stamped at the time of the previous step (two sensors sampled at
                # one instant, or a command and a reading of the same cycle) is an update with
                # dt = 0; only an earlier stamp, or an empty step to the same time, is refused.
                return (f"out-of-order or duplicate time stamp: {tf!r} <= {self._t!r}", *bad)
            else:
                dt = tf - self._t
        if y is None:
            y_arr = np.zeros(p)
            mask_arr = np.zeros(p, dtype=bool)
        else:
            y_arr = np.asarray(y, dtype=float).reshape(-1)
            if y_arr.shape != (p,):
                return (f"bad measurement shape: {y_arr.shape} != ({p},)", *bad)
            mask_arr = (np.ones(p, dtype=bool) if mask is None
                        else np.asarray(mask, dtype=bool).reshape(-1))
            if mask_arr.shape != (p,):
                return (f"bad mask shape: {mask_arr.shape} != ({p},)", *bad)
            if not np.all(np.isfinite(y_arr[mask_arr])):
                return (f"non-finite measurement: {y_arr[mask_arr].tolist()}", *bad)
        if meas_var is None:
            R = np.asarray(fam.R, dtype=float)
        else:
            R = np.asarray(meas_var, dtype=float).reshape(-1)
            if R.shape != (p,):
                return (f"bad measurement variance shape: {R.shape} != ({p},)", *bad)
            Rm = R[mask_arr]
            if not (np.all(np.isfinite(Rm)) and np.all(Rm > 0)):
                return (f"non-positive or non-finite measurement variance: {Rm.tolist()}", *bad)
        if dt == 0.0 and t is None:
            return ("zero default step", *bad)
        return "", dt, y_arr, mask_arr, R

    def _reject(self, reason: str) -> Estimate:
        self.rejected[reason.split(":")[0]] += 1
        last = self._last
        return Estimate(False, reason, last.t, last.mean, last.cov, last.x_mean, last.x_cov,
                        last.theta_mean, last.theta_cov, last.n_particles, last.n_eff,
                        last.informative, False, float("nan"))

    def _summary(self, s: _Set, accepted, reason, informative, used, log_ev, t=None) -> Estimate:
        # Moments of the mixture over (x, theta) with per-particle covariance blkdiag(P_i,
        # theta_var_i): law of total covariance, written out so that no (N, n + d, n + d)
        # stack is built (the mean of P_i is one matrix-vector product over the flat P).
        w, _ = log_normalize(s.logw)
        N, n = s.x.shape
        dth = s.theta.shape[1]
        xm = w @ s.x
        tm = w @ s.theta
        dx = s.x - xm
        dt_ = s.theta - tm
        wdx = dx * w[:, None]
        c = np.empty((n + dth, n + dth))
        c[:n, :n] = (w @ s.P.reshape(N, n * n)).reshape(n, n) + wdx.T @ dx
        c[:n, n:] = wdx.T @ dt_
        c[n:, :n] = c[:n, n:].T
        c[n:, n:] = (dt_ * w[:, None]).T @ dt_
        tv = self._theta_var(s)
        if tv is not None:
            c[n:, n:] += (w @ tv.reshape(N, dth * dth)).reshape(dth, dth)
        c = 0.5 * (c + c.T)
        m = np.concatenate([xm, tm])
        ri = self._report_index(n, dth)
        return Estimate(accepted, reason, self._t if t is None else float(t), m[ri],
                        c[np.ix_(ri, ri)], xm, c[:n, :n], tm, c[n:, n:],
                        int(N), float(1.0 / np.sum(w * w)), bool(informative),
                        bool(used), float(log_ev))

    def _report_index(self, n, dth):
        ri = self.__dict__.get("_ri")
        if ri is None:
            ri = np.array(list(self.family.report_index) + list(range(n, n + dth)), dtype=int)
            self._ri = ri
        return ri

    # -- hooks -----------------------------------------------------------------------------
    def _theta_var(self, s: _Set):
        """Per-particle variance of theta around the particle's value, ``(N, d, d)``, or None
        (point masses)."""
        return None

    def _predict(self, s: _Set, u, dt: float, informative: bool):
        """KF prediction of every particle with this step's model: the family's own
        ``predict`` if it has one (``BrakingModel.predict``: the affine form, no per-particle
        matrices), else ``batched_kf.predict`` on ``family.matrices``. A step that cannot
        inform theta uses one model shared by all particles (``family.hold_gain``)."""
        fam = self.family
        kw = {}
        if not informative and hasattr(fam, "hold_gain"):
            kw["hold"] = fam.hold_gain(u, self._last.x_mean, float(self._last.theta_mean[0]))
        if hasattr(fam, "predict"):
            return fam.predict(s.x, s.P, s.theta, u, dt, informative, **kw)
        return predict(s.x, s.P, *fam.matrices(s.theta, u, dt, informative, **kw))

    def _transition(self, s: _Set, informative: bool, rng, dt: float) -> _Set:
        """Parameter transition before the KF prediction (identity by default / when frozen or
        not due). ``dt``: time the transition covers (since the last one, for random walks)."""
        return s

    def _reduce(self, s: _Set, loglik, informative: bool, rng):
        """Weight by the likelihood (log space); return ``(set, log evidence)``; algorithms
        that prune or select return only the surviving particles."""
        lw = s.logw + loglik
        _, logz = _lse_norm(lw)
        return _Set(s.theta, s.x, s.P, lw - logz, s.idx, s.extra), logz

    def _after(self, s: _Set, informative: bool, rng) -> _Set:
        return s


# ----------------------------------------------------------------------------------------------
# discrete parameter set


def grid_prior(values, prior) -> np.ndarray:
    """Probabilities of the discrete values under ``prior = (mean, std)``: the Gaussian's mass
    on each value's cell (the half-way points to its neighbours; the outer cells are open, so
    the tails pile on the end values). ``prior`` None: uniform (Zheng Section 4)."""
    v = np.asarray(values, dtype=float).reshape(-1)
    if prior is None:
        return np.full(v.size, 1.0 / v.size)
    m, sd = (float(a) for a in prior)
    if not (np.isfinite(m) and np.isfinite(sd) and sd > 0):
        raise ValueError(f"prior must be a finite (mean, std > 0), got {prior!r}")
    order = np.argsort(v)
    vs = v[order]
    edges = np.concatenate([[-np.inf], 0.5 * (vs[1:] + vs[:-1]), [np.inf]])
    p_sorted = np.diff(ndtr((edges - m) / sd))
    p = np.empty_like(p_sorted)
    p[order] = p_sorted
    if not p.sum() > 0:
        raise ValueError("prior has no mass on the discrete set")
    return p / p.sum()


def cell_variance(values) -> np.ndarray:
    """Variance ``h^2 / 12`` of a uniform spread over each value's cell, ``h`` the distance
    between the half-way points to its neighbours (an end value: twice its inner half-width).
    A discrete value stands for a continuous f anywhere in its cell (Sheppard's correction):
    without it a grid posterior on one value reports std 0 while f can be up to h / 2 away.
    One value: 0 (no grid, nothing to spread)."""
    v = np.asarray(values, dtype=float).reshape(-1)
    if v.size < 2:
        return np.zeros(v.size)
    order = np.argsort(v)
    vs = v[order]
    half = 0.5 * np.diff(vs)
    lo = np.concatenate([[half[0]], half])
    hi = np.concatenate([half, [half[-1]]])
    out = np.empty(v.size)
    out[order] = (lo + hi) ** 2 / 12.0
    return out


class _DiscreteBase(RaoBlackwellFilter):
    def __init__(self, family, values, n_init: int, prior=None, cell_var: bool = True):
        super().__init__(family)
        self.values = np.asarray(values, dtype=float).reshape(-1)
        if self.values.size == 0 or not np.all(np.isfinite(self.values)):
            raise ValueError("values must be a non-empty finite set")
        self.n_init = int(n_init)
        self.prior_p = grid_prior(self.values, prior)
        self.prior = prior
        self._cell_var = cell_variance(self.values) if cell_var else np.zeros(self.values.size)

    def _initial_theta(self, rng):
        # Zheng Section 4: initial particles sampled in the discrete space (uniform prior);
        # with ``prior`` = (mean, std) from the Gaussian's mass on each value's cell.
        if self.prior is None:
            idx = rng.integers(0, self.values.size, self.n_init)
        else:
            idx = rng.choice(self.values.size, self.n_init, p=self.prior_p)
        return self.values[idx][:, None], idx

    def _theta_var(self, s):
        if s.idx is None:
            return None
        return self._cell_var[s.idx][:, None, None]

    def _theta_from_values(self, values):
        v = values.reshape(-1)
        idx = np.argmin(np.abs(v[:, None] - self.values[None, :]), axis=1)
        if not np.allclose(self.values[idx], v, rtol=0, atol=1e-12):
            raise ValueError("theta0 must be members of the discrete set")
        return self.values[idx][:, None], idx


class DiscreteRBPF(_DiscreteBase):
    """RBPF on a discrete parameter set (Zheng 3.3), see the module docstring.

    ``transition (M, M)``: per-step kernel (eq. (5)); for variable ``dt`` it is applied per
    step, not per second. ``ess_frac``: resample when ``N_eff < ess_frac * N``.
    """

    name = "rbpf"

    def __init__(self, family, values, transition, n_particles: int = 250,
                 proposal: str = "prior", ess_frac: float = 0.5, prior=None,
                 cell_var: bool = True):
        super().__init__(family, values, n_particles, prior, cell_var)
        T = np.asarray(transition, dtype=float)
        M = self.values.size
        if T.shape != (M, M) or np.any(T < 0) or not np.allclose(T.sum(axis=1), 1.0):
            raise ValueError("transition must be a row-stochastic (M, M) matrix")
        if proposal not in ("prior", "optimal"):
            raise ValueError("proposal must be 'prior' or 'optimal'")
        self.T = T
        self.cdf = np.cumsum(T, axis=1)
        self.cdf[:, -1] = 1.0
        self.proposal = proposal
        self.ess_frac = float(ess_frac)
        # padded children table for the optimal proposal: support of each row
        kmax = int(np.max(np.sum(T > 0, axis=1)))
        self._child = np.zeros((M, kmax), dtype=int)
        self._logp = np.full((M, kmax), -np.inf)
        for j in range(M):  # setup only (M rows), not per particle
            sup = np.flatnonzero(T[j] > 0)
            self._child[j, :sup.size] = sup
            self._child[j, sup.size:] = j  # padding: a valid model, zero prior mass
            self._logp[j, :sup.size] = np.log(T[j, sup])

    def _transition(self, s, informative, rng, dt):
        if not informative:
            return s
        if self.proposal == "prior":
            # theta_k ~ T[theta_{k-1}, :] by inverse CDF, all particles at once
            u = rng.random(s.idx.size)
            idx = np.minimum((self.cdf[s.idx] < u[:, None]).sum(axis=1), self.values.size - 1)
            return _Set(self.values[idx][:, None], s.x, s.P, s.logw, idx)
        # optimal proposal (eq. (12)): branch to the support, choose after the likelihood
        N, kmax = s.idx.size, self._child.shape[1]
        parent = np.repeat(np.arange(N), kmax)
        idx = self._child[s.idx].reshape(-1)
        logp = self._logp[s.idx].reshape(-1)
        return _Set(self.values[idx][:, None], s.x[parent], s.P[parent], s.logw[parent], idx,
                    {"logp": logp, "N": N, "kmax": kmax})

    def _reduce(self, s, loglik, informative, rng):
        if "logp" not in s.extra:
            return super()._reduce(s, loglik, informative, rng)
        N, kmax = s.extra["N"], s.extra["kmax"]
        lq = (s.extra["logp"] + loglik).reshape(N, kmax)  # log T + log N(y; ...)
        mx = np.max(lq, axis=1, keepdims=True)  # finite: every row has prior mass
        lsum = mx[:, 0] + np.log(np.sum(np.exp(lq - mx), axis=1))  # eq. (13), per parent
        # sample one child per parent from q ∝ exp(lq) (Gumbel-max: exact, vectorised)
        g = rng.gumbel(size=lq.shape)
        choice = np.argmax(np.where(np.isfinite(lq), lq + g, -np.inf), axis=1)
        keep = np.arange(N) * kmax + choice
        lw = s.logw[keep] + lsum
        _, logz = _lse_norm(lw)
        out = _Set(s.theta[keep], s.x[keep], s.P[keep], lw - logz, s.idx[keep])
        return out, logz

    def _after(self, s, informative, rng):
        if not informative:
            return s  # frozen: no resampling noise on the f marginal
        N = s.idx.size
        w, _ = log_normalize(s.logw)
        if 1.0 / np.sum(w * w) >= self.ess_frac * N:
            return s
        a = systematic_resample(s.logw, N, rng)
        return _Set(s.theta[a], s.x[a], s.P[a], np.full(N, -np.log(N)), s.idx[a])


def _merge_by_value(s: _Set, values) -> _Set:
    """Collapse the particles that share a value into one Gaussian (moment matching: weight sum,
    weighted mean, law of total covariance). Particles on one value have the same model from now
    on, so their KF states only differ by their past; merging them keeps the mixture's first two
    moments per value and bounds the particle count by the number of values (GPB1-style)."""
    w, _ = log_normalize(s.logw)
    present = np.flatnonzero(np.bincount(s.idx, weights=w, minlength=values.size) > 0)
    G = (s.idx[None, :] == present[:, None]) * w[None, :]  # (K, N) weights per value
    W = G.sum(axis=1)
    Gn = G / W[:, None]
    x = Gn @ s.x
    dev = s.x[None, :, :] - x[:, None, :]  # (K, N, n)
    P = np.einsum("kj,jab->kab", Gn, s.P) + np.einsum("kj,kja,kjb->kab", Gn, dev, dev)
    lw = np.log(W)
    return _Set(values[present][:, None], x, 0.5 * (P + np.swapaxes(P, -1, -2)),
                lw - _lse_norm(lw)[1], present)


class _BranchingFilter(_DiscreteBase):
    """SMA/GSMA: branch every particle to its allowed children, keep the best ``n_keep`` when
    the count exceeds ``q_max`` (Zheng 3.4-3.5). ``kernel[j, m] >= 0``: value j may go to value
    m iff positive; the prior over the children of one parent is the row normalised (uniform
    over the allowed children for a 0/1 kernel, as in the paper)."""

    def __init__(self, family, values, kernel, n_init: int = 50, n_keep: int = 50,
                 q_max: int = 500, prior=None, cell_var: bool = True, merge: bool = False):
        super().__init__(family, values, n_init, prior, cell_var)
        self.merge = bool(merge)
        kernel = np.asarray(kernel, dtype=float)
        M = self.values.size
        if kernel.shape != (M, M) or np.any(kernel < 0) or not np.all((kernel > 0).any(axis=1)):
            raise ValueError("kernel: non-negative (M, M), every value needs an allowed child")
        if not (1 <= n_keep <= q_max):
            raise ValueError("need 1 <= n_keep <= q_max")
        self.allowed = kernel > 0
        with np.errstate(divide="ignore"):
            self._logprior = np.log(kernel / kernel.sum(axis=1, keepdims=True))
        self.n_keep = int(n_keep)
        self.q_max = int(q_max)

    def _transition(self, s, informative, rng, dt):
        if not informative:
            return s
        parent, child = np.nonzero(self.allowed[s.idx])  # all (particle, child value) pairs
        lw = s.logw[parent] + self._logprior[s.idx[parent], child]
        return _Set(self.values[child][:, None], s.x[parent], s.P[parent],
                    lw - _lse_norm(lw)[1], child)

    def _initial_theta(self, rng):
        if not self.merge:
            return super()._initial_theta(rng)
        # merged form: one hypothesis per value, weighted by the prior (see _initial_logw)
        idx = np.arange(self.values.size)
        return self.values[:, None], idx

    def _initial_logw(self, N):
        if not self.merge:
            return None
        with np.errstate(divide="ignore"):
            lw = np.log(self.prior_p)
        return lw - _lse_norm(lw)[1]

    def _after(self, s, informative, rng):
        # Reduction happens *after* the estimate of this step is formed (base step): the
        # estimate uses every evaluated branch. Pruning before it (as the paper's loop reads)
        # throws away the branches' probability mass and reports a too narrow f posterior --
        # with all kept particles on one value, a variance of exactly 0.
        if not informative:
            return s
        if self.merge:
            return _merge_by_value(s, self.values)
        if s.logw.size > self.q_max:
            # keep the n_keep largest weights; sorted by index for reproducibility
            keep = np.sort(np.argpartition(-s.logw, self.n_keep - 1)[: self.n_keep])
            lw = s.logw[keep] - _lse_norm(s.logw[keep])[1]
            return _Set(s.theta[keep], s.x[keep], s.P[keep], lw, s.idx[keep])
        return s


class SMA(_BranchingFilter):
    """Stochastic M-algorithm: every particle branches to every value (Section 3.4), with a
    uniform prior over the children, or ``transition[j, m]`` if given (its support decides the
    children)."""

    name = "sma"

    def __init__(self, family, values, n_init: int = 50, n_keep: int = 50, q_max: int = 500,
                 transition=None, prior=None, cell_var: bool = True, merge: bool = False):
        M = np.asarray(values).size
        kernel = np.ones((M, M)) if transition is None else transition
        super().__init__(family, values, kernel, n_init, n_keep, q_max, prior, cell_var, merge)


class GSMA(_BranchingFilter):
    """Group SMA (Section 3.5): a particle at value ``v`` branches to the members of the group
    whose mean is closest to ``v`` (first such group on ties). ``groups``: lists of value
    indices; default ``neighbour_groups``. Prior over the children: uniform in the group (paper)
    or ``transition`` restricted to the group and renormalised."""

    name = "gsma"

    def __init__(self, family, values, groups=None, n_init: int = 50, n_keep: int = 50,
                 q_max: int = 500, transition=None, prior=None, cell_var: bool = True,
                 merge: bool = False):
        vals = np.asarray(values, dtype=float).reshape(-1)
        groups = neighbour_groups(vals.size) if groups is None else [tuple(g) for g in groups]
        means = np.array([vals[list(g)].mean() for g in groups])
        M = vals.size
        member = np.zeros((M, M))
        closest = np.argmin(np.abs(vals[:, None] - means[None, :]), axis=1)
        for j in range(M):  # setup only
            member[j, list(groups[closest[j]])] = 1.0
        kernel = member if transition is None else member * np.asarray(transition, dtype=float)
        self.groups = groups
        super().__init__(family, vals, kernel, n_init, n_keep, q_max, prior, cell_var, merge)


# ----------------------------------------------------------------------------------------------
# continuous parameter


class _ContinuousBase(RaoBlackwellFilter):
    def __init__(self, family, bounds, n_particles: int, q_theta, prior=None):
        super().__init__(family)
        if prior is not None:
            m, sd = (float(a) for a in np.broadcast_to(np.asarray(prior, float), (2,)))
            if not (np.isfinite(m) and np.isfinite(sd) and sd > 0):
                raise ValueError(f"prior must be a finite (mean, std > 0), got {prior!r}")
        self.prior = prior
        b = np.asarray(bounds, dtype=float).reshape(-1, 2)
        if b.shape[0] != family.d or not np.all(b[:, 1] > b[:, 0]):
            raise ValueError("bounds: one (lo, hi) with lo < hi per parameter")
        self.lo, self.hi = b[:, 0], b[:, 1]
        self.n = int(n_particles)
        q = np.asarray(q_theta, dtype=float)
        self.q_theta = np.diag(np.broadcast_to(q, (family.d,))) if q.ndim <= 1 else q
        if not np.all(np.linalg.eigvalsh(self.q_theta) >= 0):
            raise ValueError("q_theta must be positive semi-definite")

    def _initial_theta(self, rng):
        # Q-GRBPF step 1: uniform in [theta_min, theta_max]; with ``prior`` = (mean, std):
        # N(mean, std^2) reflected into the bounds
        if self.prior is None:
            return self.lo + (self.hi - self.lo) * rng.random((self.n, self.family.d)), None
        m, sd = self.prior
        th = m + sd * rng.standard_normal((self.n, self.family.d))
        return _reflect(th, self.lo, self.hi), None


class QGRBPF(_ContinuousBase):
    """Quasi-Gaussian RBPF (Guan, Fang, Hu), continuous theta, see the module docstring.

    Each informative step starts by redrawing the parameter particles from the Gaussian
    approximation of the posterior, eq. (7)-(9), widened by the random-walk kernel
    ``Q_theta dt`` (``q_theta`` per second; 0 = static parameter) and floored at ``min_var``
    (so it cannot collapse to a point): ``theta_j = theta_hat + L z_j``, reflected into
    ``bounds``, equal weights.

    Pairing with KF states (paper step (5), eq. (17)). The paper draws uniforms ``u_p`` and finds
    ``l`` with ``sum_{j<l} q_j < u_p <= sum_{j<=l} q_j``. We use ``u_p = Phi(z_p1)`` (``z_p1``: the
    coordinate of draw p along the principal axis of the Gaussian, ``Phi`` the normal CDF, so
    ``u_p`` is exactly uniform) and the old particles sorted along that axis with their weights:
    the search then maps each new theta to the old particle at the same weighted quantile, i.e.
    the monotone (optimal-transport) coupling, so a new f inherits the KF state of a particle
    with a similar f. With ``u_p`` independent of ``z_p`` the pairing would be random and the
    KF states (a_hat depends on f) would not match their parameter.
    (The paper says resampling is omitted and still performs this search: the search *is* a
    multinomial resampling of the KF states. What it omits is resampling of the parameters.)
    """

    name = "qgrbpf"

    def __init__(self, family, bounds, n_particles: int = 50, q_theta=0.0, min_var=1e-8,
                 prior=None, quadrature: bool = False):
        super().__init__(family, bounds, n_particles, q_theta, prior)
        self.min_var = float(min_var)
        self.quadrature = bool(quadrature)
        if self.quadrature:
            if family.d != 1:
                raise ValueError("quadrature: one parameter only")
            z, wq = np.polynomial.hermite_e.hermegauss(self.n)  # nodes/weights for N(0, 1)
            self._gh = (z, np.log(wq / wq.sum()))

    def _initial_theta(self, rng):
        if not self.quadrature:
            return super()._initial_theta(rng)
        m, sd = self.prior if self.prior is not None else (
            0.5 * (self.lo[0] + self.hi[0]), (self.hi[0] - self.lo[0]) / np.sqrt(12.0))
        return np.clip(m + sd * self._gh[0], self.lo, self.hi)[:, None], None

    def _initial_logw(self, N):
        return self._gh[1].copy() if self.quadrature else None

    def _transition(self, s, informative, rng, dt):
        if not informative:
            return s  # frozen: keep particles and weights
        if self.quadrature:
            return self._transition_quadrature(s, dt)
        N, dth = self.n, self.family.d
        w, _ = log_normalize(s.logw)
        mu, cov = mixture_moments(w, s.theta)  # eq. (7), (8)
        cov = cov + self.q_theta * dt + self.min_var * np.eye(dth)
        ev, V = np.linalg.eigh(cov)
        ev, V = ev[::-1], V[:, ::-1]  # principal axis first
        z = rng.standard_normal((N, dth))
        theta = mu + (z * np.sqrt(np.clip(ev, 0.0, None))) @ V.T  # eq. (9)
        theta = _reflect(theta, self.lo, self.hi)
        # eq. (17) with u_p = Phi(z_p1): weighted quantile search along the principal axis
        proj = (s.theta - mu) @ V[:, 0]
        order = np.argsort(proj, kind="stable")
        cdf = np.cumsum(w[order])
        cdf[-1] = 1.0
        anc = order[np.minimum(np.searchsorted(cdf, ndtr(z[:, 0]), side="left"), w.size - 1)]
        return _Set(theta, s.x[anc], s.P[anc], np.full(N, -np.log(N)))

    def _transition_quadrature(self, s, dt):
        """Deterministic form (``quadrature=True``): the Gaussian of eq. (7)-(9) over
        ``(x, theta)`` jointly, represented by ``N`` Gauss-Hermite nodes in theta; no random
        draw and no resampling search. The KF state of node j is the Gaussian conditional
        ``E[x | theta_j] = x_bar + C_x,theta / var (theta_j - theta_hat)`` with the conditional
        covariance ``Sigma_x - C C^T / var`` (``var`` includes the random-walk step, which is
        independent of x). The nodes' weighted mixture then has exactly the joint Gaussian's
        mean and covariance. Because theta enters the braking model linearly, few nodes suffice.
        """
        w, _ = log_normalize(s.logw)
        th = s.theta[:, 0]
        mu = w @ th
        dth = th - mu
        var = w @ (dth * dth) + self.q_theta[0, 0] * dt + self.min_var
        xm = w @ s.x
        dx = s.x - xm
        cxt = (w * dth) @ dx  # (n,) Cov(x, theta)
        Sx = np.einsum("k,kij->ij", w, s.P) + (w[:, None] * dx).T @ dx
        beta = cxt / var
        Pc = Sx - np.outer(cxt, beta)
        z, lw = self._gh
        theta = np.clip(mu + np.sqrt(var) * z, self.lo[0], self.hi[0])
        x = xm + (theta - mu)[:, None] * beta[None, :]
        P = np.repeat(0.5 * (Pc + Pc.T)[None], z.size, axis=0)
        return _Set(theta[:, None], x, P, lw.copy())


class RandomWalkRBPF(_ContinuousBase):
    """Bootstrap RBPF with a Gaussian random-walk kernel ``theta_k = theta_{k-1} + N(0, Q dt)``
    (reflected into ``bounds``) and systematic resampling when ``N_eff < ess_frac N``."""

    name = "rbpf_rw"

    def __init__(self, family, bounds, n_particles: int = 250, q_theta=1e-4,
                 ess_frac: float = 0.5, prior=None):
        super().__init__(family, bounds, n_particles, q_theta, prior)
        self.ess_frac = float(ess_frac)
        ev, V = np.linalg.eigh(self.q_theta)
        self._L = V * np.sqrt(np.clip(ev, 0.0, None))

    def _transition(self, s, informative, rng, dt):
        if not informative:
            return s
        theta = s.theta + np.sqrt(dt) * rng.standard_normal(s.theta.shape) @ self._L.T
        return _Set(_reflect(theta, self.lo, self.hi), s.x, s.P, s.logw)

    def _after(self, s, informative, rng):
        if not informative:
            return s
        N = s.theta.shape[0]
        w, _ = log_normalize(s.logw)
        if 1.0 / np.sum(w * w) >= self.ess_frac * N:
            return s
        a = systematic_resample(s.logw, N, rng)
        return _Set(s.theta[a], s.x[a], s.P[a], np.full(N, -np.log(N)))


class OracleKF(RaoBlackwellFilter):
    """The Kalman filter that is told the true parameter of every step (one particle)."""

    name = "oracle"

    def reset(self, x0, P0, rng=None, theta0=1.0, t0=None) -> Estimate:
        return super().reset(x0, P0, None, np.atleast_1d(np.asarray(theta0, float))[:1], t0)

    def step(self, a_tar, y=None, mask=None, rng=None, *, theta_true=None, **kw) -> Estimate:
        """As ``RaoBlackwellFilter.step``; ``theta_true``: the true parameter over this step."""
        if theta_true is not None:
            th = np.asarray(theta_true, dtype=float).reshape(1, -1)
            if not np.all(np.isfinite(th)):
                return self._reject(f"non-finite true parameter: {theta_true!r}")
            self._pending = th
        try:
            return super().step(a_tar, y, mask, rng, **kw)
        finally:
            self._pending = None

    _pending = None

    def _transition(self, s, informative, rng, dt):
        if self._pending is None:
            return s
        return _Set(self._pending.copy(), s.x, s.P, s.logw)


# ----------------------------------------------------------------------------------------------
# the exact reference: one Kalman filter with f in the state


class _AugmentedFamily:
    """``BrakingModel`` seen with f as a fifth KF state (``braking_model.augmented_model``).

    Only what the common step needs: ``n`` = 5, no particle parameter (``d`` = 0), the
    measurement rows padded with a zero f column, the braking model's gates.
    """

    n = 5
    d = 0
    report_index = (0, 1, 2, 4)  # D, v, a_hat, f

    def __init__(self, family):
        self.base = family
        self.params = family.params
        self.H = np.hstack([family.H, np.zeros((family.H.shape[0], 1))])
        self.R = family.R

    def default_dt(self) -> float:
        return self.base.default_dt()

    def gate(self, u, x_mean) -> bool:
        return self.base.gate(u, x_mean)

    def hold_gain(self, u, x_mean, f_mean: float) -> float:
        return self.base.hold_gain(u, x_mean, f_mean)


class BrakingKF(RaoBlackwellFilter):
    """Kalman filter on ``(D, v, a_hat, a_z, f)`` with f a random walk: the exact Bayesian
    estimator of the braking model for a Gaussian prior on f, given the known command (see
    ``braking_model.augmented_model``; exact when ``a_z`` is known, i.e. its variance is 0 --
    ``a_z`` is the Pade response to the command, so in the live system it is). One "particle";
    the common step (validation, rejection, gating, ``batched_kf.predict`` / ``update``) is the
    base class's.

    ``f_prior = (mean, std)`` of f at reset (``reset(theta0=...)`` overrides the mean);
    ``q_theta`` (1/s): random-walk variance of f per second of *informative* time (frozen
    otherwise, like the particle filters).
    """

    name = "kf"

    def __init__(self, family, q_theta: float = 1e-4, f_prior=(1.0, 0.15)):
        if not (np.isfinite(q_theta) and q_theta >= 0):
            raise ValueError(f"q_theta must be finite and >= 0, got {q_theta!r}")
        m, sd = (float(v) for v in f_prior)
        if not (np.isfinite(m) and np.isfinite(sd) and sd >= 0):
            raise ValueError(f"f_prior must be a finite (mean, std >= 0), got {f_prior!r}")
        super().__init__(_AugmentedFamily(family))
        self.q_theta = float(q_theta)
        self.f_prior = (m, sd)

    def reset(self, x0, P0, rng=None, theta0=None, t0=None) -> Estimate:
        """``x0 (4,)``, ``P0 (4, 4)``: (D, v, a_hat, a_z) as for the particle filters; f starts
        at ``N(theta0 or f_prior mean, f_prior std^2)``, uncorrelated with the rest."""
        x0 = np.asarray(x0, dtype=float).reshape(4)
        P0 = np.asarray(P0, dtype=float).reshape(4, 4)
        m = self.f_prior[0] if theta0 is None else float(np.mean(theta0))
        z = np.append(x0, m)
        Pz = np.zeros((5, 5))
        Pz[:4, :4] = P0
        Pz[4, 4] = self.f_prior[1] ** 2
        est = super().reset(z, Pz, None, np.zeros((1, 0)), t0)
        return est

    def _theta_from_values(self, values):
        return np.zeros((1, 0)), None

    def _predict(self, s, u, dt, informative):
        hold = None
        if not informative:
            hold = self.family.hold_gain(u, self._last.x_mean, float(self._last.theta_mean[0]))
        F, b, Q = augmented_model(self.family.params, u, dt, float(s.x[0, 3]), informative,
                                  hold, self.q_theta)
        return predict(s.x, s.P, F[None], b[None], Q)

    def _summary(self, s, accepted, reason, informative, used, log_ev, t=None) -> Estimate:
        x, P = s.x[0], s.P[0]
        ri = list(self.family.report_index)
        return Estimate(accepted, reason, self._t if t is None else float(t), x[ri],
                        P[np.ix_(ri, ri)], x[:4], P[:4, :4], x[4:], P[4:, 4:], 1, 1.0,
                        bool(informative), bool(used), float(log_ev))
