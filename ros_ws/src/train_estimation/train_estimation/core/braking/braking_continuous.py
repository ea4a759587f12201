"""Braking-rate filters with a continuous parameter: Q-GRBPF (Guan, Fang, Hu) in its paper form
and a Gauss-Hermite form, and the random-walk RBPF it is compared with (``braking_filters``
gives the overview).

Pure: numpy/scipy only; randomness only through the ``rng`` argument.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import ndtr

from ..numerics import bank, smc
from ..numerics.bank import log_normalize
from ..numerics.batched_kf import mixture_moments
from ..numerics.smc import systematic_resample
from . import braking_inplace
from .braking_base import RaoBlackwellFilter, _Set, _wsum

__all__ = ["QGRBPF", "RandomWalkRBPF"]

_NO_DRAW, _NO_DRAW2 = np.zeros(0), np.zeros((0, 1))  # a step's random numbers when it draws none


def _reflect(theta, lo, hi):
    """Reflect into ``[lo, hi]`` (per column); keeps a Gaussian draw's shape near the bounds."""
    width = hi - lo
    y = np.mod(theta - lo, 2.0 * width)
    y = np.where(y > width, 2.0 * width - y, y)
    return lo + y


# ----------------------------------------------------------------------------------------------
# continuous parameter


class _ContinuousBase(RaoBlackwellFilter):
    def __init__(self, family, bounds, n_particles: int, braking_rate_q, prior=None):
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
        q = np.asarray(braking_rate_q, dtype=float)
        self.braking_rate_q = np.diag(np.broadcast_to(q, (family.d,))) if q.ndim <= 1 else q
        if not np.all(np.linalg.eigvalsh(self.braking_rate_q) >= 0):
            raise ValueError("braking_rate_q must be positive semi-definite")

    def _scalars(self):
        """``(lo, hi)`` of the one parameter as floats, for the compiled steps."""
        hit = self.__dict__.get("_lohi")
        if hit is None or hit[0] is not self.lo or hit[1] is not self.hi:
            hit = self._lohi = (self.lo, self.hi, float(self.lo[0]), float(self.hi[0]))
        return hit[2], hit[3]

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
    ``Q_theta dt`` (``braking_rate_q`` per second; 0 = static parameter) and floored at ``min_var``
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

    def __init__(self, family, bounds, n_particles: int = 50, braking_rate_q=0.0, min_var=1e-8,
                 prior=None, quadrature: bool = False):
        super().__init__(family, bounds, n_particles, braking_rate_q, prior)
        self.min_var = float(min_var)
        self.quadrature = bool(quadrature)
        if self.quadrature:
            if family.d != 1:
                raise ValueError("quadrature: one parameter only")
            bank.warm_up("gauss_hermite")
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

    def _draws(self, N, due, rng, tdt):
        # the numpy form's draws: N standard normals (and their normal CDF) per redraw
        z, uz, gh_lw = _NO_DRAW2, _NO_DRAW, _NO_DRAW
        if due:
            if self.quadrature:
                z, gh_lw = self.__dict__.get("_ghc") or self.__dict__.setdefault(
                    "_ghc", (np.ascontiguousarray(self._gh[0][:, None]), self._gh[1].copy()))
            else:
                z = rng.standard_normal((self.n, self.family.d))
                uz = ndtr(z[:, 0])
        return float(self.braking_rate_q[0, 0] * tdt), z, uz, gh_lw

    def _fused(self, kc, buf, N, due, informative, common, draws):
        qdt, z, uz, gh_lw = draws
        return braking_inplace.qgrbpf_run(*kc, *self._scalars(), qdt, self.min_var,
                                          self.quadrature, z, uz, self._lw_n, gh_lw, buf.th,
                                          buf.x, buf.P, buf.lw, buf.idx, N, due, informative,
                                          *common)

    @property
    def _lw_n(self):
        """``-log N``, the redraw's equal log-weight (numpy's log, as the numpy form's)."""
        hit = self.__dict__.get("_lwn")
        if hit is None or hit[0] != self.n:
            hit = self._lwn = (self.n, -np.log(self.n))
        return hit[1]

    def _transition(self, s, informative, rng, dt):
        if not informative:
            return s  # frozen: keep particles and weights
        if self.quadrature:
            return self._transition_quadrature(s, dt)
        N, dth = self.n, self.family.d
        w, _ = log_normalize(s.logw)
        mu, cov = mixture_moments(w, s.theta)  # eq. (7), (8)
        cov = cov + self.braking_rate_q * dt + self.min_var * np.eye(dth)
        if dth == 1:  # the braking rate: the principal axis is the axis (no LAPACK call)
            ev, V = cov.reshape(1), np.ones((1, 1))
        else:
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
        z, lw = self._gh
        if bank.COMPILED:  # the same formulas in one compiled call (numerics.bank)
            theta, x, P = bank.gauss_hermite(s.logw, s.theta, s.x, s.P, z,
                                             self.braking_rate_q[0, 0] * dt, self.min_var,
                                             self.lo[0], self.hi[0])
            return _Set(theta, x, P, lw.copy())
        return self._quadrature_numpy(s, dt)

    def _quadrature_numpy(self, s, dt):
        """The numpy form of :meth:`_transition_quadrature` (without numba; the reference
        of ``test_bank.py``)."""
        z, lw = self._gh
        w, _ = smc.log_normalize(s.logw)
        th = s.theta[:, 0]
        mu = w @ th
        dth = th - mu
        var = w @ (dth * dth) + self.braking_rate_q[0, 0] * dt + self.min_var
        xm = _wsum(w, s.x)
        dx = s.x - xm
        cxt = (w * dth) @ dx  # (n,) Cov(x, theta)
        Sx = _wsum(w, s.P) + (w[:, None] * dx).T @ dx
        beta = cxt / var
        Pc = Sx - np.outer(cxt, beta)
        theta = np.clip(mu + np.sqrt(var) * z, self.lo[0], self.hi[0])
        x = xm + (theta - mu)[:, None] * beta[None, :]
        P = np.repeat(0.5 * (Pc + Pc.T)[None], z.size, axis=0)
        return _Set(theta[:, None], x, P, lw.copy())


class RandomWalkRBPF(_ContinuousBase):
    """Bootstrap RBPF with a Gaussian random-walk kernel ``theta_k = theta_{k-1} + N(0, Q dt)``
    (reflected into ``bounds``) and systematic resampling when ``N_eff < ess_frac N``."""

    name = "rbpf_rw"

    def __init__(self, family, bounds, n_particles: int = 250, braking_rate_q=1e-4,
                 ess_frac: float = 0.5, prior=None):
        super().__init__(family, bounds, n_particles, braking_rate_q, prior)
        self.ess_frac = float(ess_frac)
        ev, V = np.linalg.eigh(self.braking_rate_q)
        self._L = V * np.sqrt(np.clip(ev, 0.0, None))

    def _draws(self, N, due, rng, tdt):
        # (math.sqrt: IEEE square roots are correctly rounded, numpy's is the same number)
        return math.sqrt(tdt), (rng.standard_normal((N, 1)) if due else _NO_DRAW2)

    def _fused(self, kc, buf, N, due, informative, common, draws):
        sqdt, z = draws
        lo, hi = self._scalars()
        return braking_inplace.random_walk_run(
            *kc, lo, hi, sqdt, float(self._L[0, 0]), z, buf.th, buf.x, buf.P, buf.lw, buf.idx,
            N, due, informative, *common)

    def _after_fused(self, buf, N, E, rng):
        self._resample_if(buf, N, E, rng, self.ess_frac)

    def _transition(self, s, informative, rng, dt):
        if not informative:
            return s
        theta = s.theta + np.sqrt(dt) * rng.standard_normal(s.theta.shape) @ self._L.T
        return _Set(_reflect(theta, self.lo, self.hi), s.x, s.P, s.logw)

    def _after(self, s, informative, rng):
        if not informative:
            return s
        N = s.theta.shape[0]
        w, ess = self.weights_ess(s)
        if ess >= self.ess_frac * N:
            return s
        a = systematic_resample(w, rng, N)
        return _Set(s.theta[a], s.x[a], s.P[a], np.full(N, -np.log(N)))
