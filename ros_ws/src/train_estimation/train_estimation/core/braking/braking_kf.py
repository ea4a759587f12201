"""Kalman-filter braking estimators: the exact reference ``BrakingKF`` (f in the state) and the
``OracleKF`` told the true braking rate (``braking_filters`` gives the overview).

Pure: numpy only.
"""

from __future__ import annotations

import numpy as np

from ..numerics import bank
from ..numerics.batched_kf import predict
from . import braking_compiled, braking_inplace
from .braking_base import _STEP_REASONS, Estimate, RaoBlackwellFilter, _Set
from .braking_model import _affine_pieces, augmented_model

__all__ = ["BrakingKF", "OracleKF"]

_Z44, _Z42 = np.zeros((4, 4)), np.zeros((4, 2))
_NO_U = np.zeros(2)  # the command of a per-dt template (kf_command writes each step's)
_KF_NO_PREDICT = (braking_inplace.pack_kf(_Z44, _Z44, _Z42, _Z42, _Z44, _NO_U), False,
                  0.0, 0.0, False)
_KF_REASONS = {**_STEP_REASONS, braking_compiled.KF_LOGLIK:
               "numerical failure: log-weights: none finite, or NaN/+inf"}


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

    def hold_gain(self, u, x_mean, braking_rate_mean: float) -> float:
        return self.base.hold_gain(u, x_mean, braking_rate_mean)


class BrakingKF(RaoBlackwellFilter):
    """Kalman filter on ``(D, v, a_hat, a_z, f)`` with f a random walk: the exact Bayesian
    estimator of the braking model for a Gaussian prior on f, given the known command (see
    ``braking_model.augmented_model``; exact when ``a_z`` is known, i.e. its variance is 0 --
    ``a_z`` is the Pade response to the command, so in the live system it is). One "particle";
    the common step (validation, rejection, gating, ``batched_kf.predict`` / ``update``) is the
    base class's.

    ``braking_rate_prior = (mean, std)`` of f at reset (``reset(theta0=...)`` overrides the mean);
    ``braking_rate_q`` (1/s): random-walk variance of f per second of *informative* time (frozen
    otherwise, like the particle filters).
    """

    name = "kf"

    def __init__(self, family, braking_rate_q: float = 1e-4, braking_rate_prior=(1.0, 0.15)):
        if not (np.isfinite(braking_rate_q) and braking_rate_q >= 0):
            raise ValueError(f"braking_rate_q must be finite and >= 0, got {braking_rate_q!r}")
        m, sd = (float(v) for v in braking_rate_prior)
        if not (np.isfinite(m) and np.isfinite(sd) and sd >= 0):
            raise ValueError("braking_rate_prior must be a finite (mean, std >= 0), "
                             f"got {braking_rate_prior!r}")
        super().__init__(_AugmentedFamily(family))
        self.braking_rate_q = float(braking_rate_q)
        self.braking_rate_prior = (m, sd)

    def reset(self, x0, P0, rng=None, theta0=None, t0=None) -> Estimate:
        """``x0 (4,)``, ``P0 (4, 4)``: (D, v, a_hat, a_z) as for the particle filters; f starts
        at ``N(theta0 or braking_rate_prior mean, braking_rate_prior std^2)``, uncorrelated with
        the rest."""
        x0 = np.asarray(x0, dtype=float).reshape(4)
        P0 = np.asarray(P0, dtype=float).reshape(4, 4)
        m = self.braking_rate_prior[0] if theta0 is None else float(np.mean(theta0))
        z = np.append(x0, m)
        Pz = np.zeros((5, 5))
        Pz[:4, :4] = P0
        Pz[4, 4] = self.braking_rate_prior[1] ** 2
        est = super().reset(z, Pz, None, np.zeros((1, 0)), t0)
        return est

    def _theta_from_values(self, values):
        return np.zeros((1, 0)), None

    def _reduce(self, s, loglik, informative, rng):
        # one Gaussian: its weight stays 1 and the log evidence is its log likelihood (what the
        # base class's log-normalisation of a single weight returns, without the array work)
        logz = float(loglik[0])
        if not np.isfinite(logz):
            raise ValueError("log-weights: none finite, or NaN/+inf")
        return s, logz

    def _fused_ok(self) -> bool:
        # the whole step compiled (braking_compiled.kf_step) whenever numba is there
        return bank.COMPILED

    def _fused_step(self, s, u, dt, since, due, informative, y, mask, R, fused, t, rng):
        """:meth:`_predict`, ``_update``, :meth:`_reduce` and the finiteness check in one
        compiled call on the filter's own state arrays (``braking_inplace.kf_run``, the numpy
        form's arithmetic; the estimate into one flat array)."""
        buf = self._buf
        if buf is None or not (s is buf[0] and s.x is buf[1] and s.P is buf[2]):
            buf = self._load(s)
        if dt > 0:
            gain = 1.0
            if not informative:
                gain = self.family.hold_gain(u, self._last.x_mean,
                                             float(self._last.theta_mean[0]))
            key = (dt, u[0], u[1], informative, gain)
            hit = self._pred_last
            params = self.family.params
            if hit is None or hit[0] != key or hit[1] is not params:
                # this dt's model pieces, packed once per dt; the command written in
                pk = self._per_dt(dt, lambda: braking_inplace.pack_kf(
                    *_affine_pieces(params, float(dt)), _NO_U))
                hit = self._pred_last = (key, params, (
                    braking_inplace.kf_command(pk, u), bool(informative), float(gain),
                    self.braking_rate_q * float(dt), True))
            pred = hit[2]
        else:
            pred = _KF_NO_PREDICT
        kc = self._kc
        if kc[0] is not self.family.H:
            kc = self._pack()
        E = np.empty(self._esize)
        status, _ = braking_inplace.kf_run(*kc[1], buf[1], buf[2], *pred, y, R,
                                           kc[3] if mask is kc[2] else np.flatnonzero(mask), E)
        if status != bank.OK:
            return _KF_REASONS[status]
        return buf[0], Estimate._of(E, self._lay, informative, fused,
                                    self._t if t is None else float(t))

    def _load(self, s, cap=0):
        x = np.array(s.x, dtype=np.float64)
        P = np.array(s.P, dtype=np.float64)
        buf = self._buf = (_Set(s.theta, x, P, s.logw, s.idx, s.extra), x, P)
        # f, the fifth state, is the estimate's parameter (theta_mean), as in _summary
        self._fused_layout(self._report_index(5, 0)[0], 4, 5)
        return buf

    def _predict(self, s, u, dt, informative):
        hold = None
        if not informative:
            hold = self.family.hold_gain(u, self._last.x_mean, float(self._last.theta_mean[0]))
        F, b, Q = augmented_model(self.family.params, u, dt, float(s.x[0, 3]), informative,
                                  hold, self.braking_rate_q)
        return predict(s.x, s.P, F[None], b[None], Q)

    def _summary(self, s, accepted, reason, informative, used, log_ev, t=None) -> Estimate:
        x, P = s.x[0], s.P[0]
        ri, rix = self._report_index(5, 0)
        return Estimate(accepted, reason, self._t if t is None else float(t), x[ri],
                        P[rix], x[:4], P[:4, :4], x[4:], P[4:, 4:], 1, 1.0,
                        bool(informative), bool(used), float(log_ev))
