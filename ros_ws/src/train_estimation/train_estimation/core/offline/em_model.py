"""The M-step of the hybrid-filter EM paper for its single mass-point train model (eq. (1)-(7)).

The model (eq. (1)-(7): Euler discretisation with step T of ds/dt = v,
dv/dt = epsilon (f(v) - w(v)), Davis w(v) = a + b v + c v^2, noisy s and v readings) is
``train_core.mass_point``, shared with the simulator of the paper's data (``train_sim.crh3``).

Reparametrisation (eq. (31)-(34)): dbar = 0.0098 T / (1 + d) and

    phi(t) = v(t) - v(t-1),   Phi(t) = [u(t), -1, -v(t-1), -v(t-1)^2]^T,
    vartheta = [dbar, dbar a, dbar b, dbar c]^T,   phi(t) = Phi(t)^T vartheta + w2(t),

so the velocity transition is *linear in vartheta* and the M-step is the least-squares problem of
eq. (35)-(36). With an exact E-step the expectations are over the smoothing distribution
p(v(t-1), v(t) | y(1:n)), i.e. (this is what eq. (29)-(30) should read, see "paper slips")::

    vartheta_k = [sum_t E Phi Phi^T]^{-1} [sum_t E Phi phi]                       (36, exact)

The paper instead plugs the filtered means vbar(t) into Phi and phi (certainty equivalence);
:func:`plugin_stats` implements that literally, :func:`pair_stats` the Monte Carlo version of the
exact expectation and :func:`gaussian_pair_stats` the closed form for Gaussian smoothed moments.

Paper slips found (and what is done here instead):

* eq. (27): the weight is printed as ``exp(+[y2 - v]^2 / (2 delta2^2))`` -- sign and variance
  are wrong: the likelihood of y2(t) = v(t) + e2(t) is ``exp(-[y2 - v]^2 / (2 sigma2^2))``
  (measurement variance sigma2^2, not the process variance delta2^2).
* eq. (22): ``K = P^-(P^{-1} + sigma1^2)^{-1}`` must be ``K = P^-(P^- + sigma1^2)^{-1}``.
* eq. (25): the weighted mean lacks its sum: ``vbar = sum_i beta_i vhat_i``; eq. (28) normalises
  with ``sum_j betahat_j`` (printed index i).
* eq. (26) propagates particles without drawing w2 and the algorithm never resamples: such a
  "particle filter" is an output-error simulation from the initial spread. The bootstrap filter
  here samples w2 and resamples (systematic, when the effective sample size drops below N/2).
* eq. (29)-(30): the expectation is written over the *transition* p(v(t)|v(t-1), Theta_{k-1})
  (so delta2^2 appears as the variance) and ``-2 psi_{k-1}^2 psi`` has a spurious square; the EM
  Q-function needs the *posterior* p(v(t-1), v(t) | C_obs, Theta_{k-1}). Eq. (31) mixes
  iterations (``vbar_{k-1}`` in phi, ``vbar_k`` in Phi): both come from the same E-step.
* eq. (39) prints ``-0.000001 v(t-1)``; the Davis term is ``-dbar c v(t-1)^2``. The printed
  vartheta = [0.0092, 0.0049, 0.00004, 0.000001] is a rounding of
  0.0098/1.06 * [1, 0.53, 0.0039, 0.000114] = [0.009245, 0.0049, 3.6e-5, 1.05e-6]; the benchmark
  uses the printed vector as the truth (as the paper's delta does). The CRH3 coefficients
  0.0039 and 0.000114 are the usual ones for v in km/h, while T = 1 s with ``s += v`` means v in
  m/s: a unit slip that only matters for the physical meaning, not for the reproduction.
* Theta_30 below Table 1 is printed in the order [d, a, b, c], not [a, b, c, d] (eq. (9)).
* Step 7 stops on ||Theta_k - Theta_{k-1}|| <= eps in the original parameters, whose entries
  differ by four orders of magnitude; :func:`theta_change` offers that and a relative change in
  vartheta (the default in hybrid_em).

Pure: numpy only. Arrays carry the time index first and an optional batch (independent data sets,
e.g. Monte Carlo seeds) in trailing axes; particle arrays carry particles first.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from train_core.mass_point import (
    CRH3_PARAMS,
    CRH3_VARTHETA,
    G_PER_KN,
    MassPointParams,
    NoiseParams,
    expand_to,
    regressors,
    velocity_drift,
)

__all__ = [
    "G_PER_KN",
    "CRH3_PARAMS",
    "CRH3_VARTHETA",
    "MassPointParams",
    "NoiseParams",
    "SuffStats",
    "expand_to",
    "regressors",
    "velocity_drift",
    "m_step",
    "plugin_stats",
    "pair_stats",
    "gaussian_pair_stats",
    "param_error",
    "theta_change",
]


@dataclass(frozen=True)
class SuffStats:
    """Sufficient statistics of the velocity transition for the M-step (eq. (35)-(36)).

    PP = sum_t E[Phi Phi^T] (*batch, 4, 4), Pp = sum_t E[Phi phi] (*batch, 4),
    pp = sum_t E[phi^2] (*batch), count = number of transitions.
    """

    PP: np.ndarray
    Pp: np.ndarray
    pp: np.ndarray
    count: int

    def __add__(self, other: SuffStats) -> SuffStats:
        return SuffStats(self.PP + other.PP, self.Pp + other.Pp, self.pp + other.pp,
                         self.count + other.count)

    def residual_variance(self, vt) -> np.ndarray:
        """(1/count) sum_t E[(phi - Phi^T vt)^2]: the M-step estimate of delta2^2 at ``vt``."""
        vt = np.moveaxis(np.asarray(vt, float), 0, -1)  # (*batch, 4)
        quad = np.einsum("...i,...ij,...j->...", vt, self.PP, vt)
        return (self.pp - 2.0 * np.einsum("...i,...i->...", vt, self.Pp) + quad) / self.count


def m_step(stats: SuffStats, rcond: float = 1e-12) -> np.ndarray:
    """eq. (36): vartheta = [sum E Phi Phi^T]^{-1} [sum E Phi phi], per batch element.

    The normal equations are solved after scaling to unit diagonal (the columns of Phi differ by
    ~4 orders of magnitude: u ~ 10, v^2 ~ 10^3). Raises ``np.linalg.LinAlgError`` with a reason if
    the scaled matrix is rank deficient (no excitation of some regressor).
    Returns vartheta with shape (4, *batch) (parameters lead, batch trails, like the data).
    """
    PP, Pp = np.asarray(stats.PP, float), np.asarray(stats.Pp, float)
    dg = np.sqrt(np.clip(np.einsum("...ii->...i", PP), 1e-300, None))
    A = PP / (dg[..., :, None] * dg[..., None, :])
    bvec = Pp / dg
    cond = np.linalg.cond(A)
    if np.any(~np.isfinite(cond)) or np.any(cond > 1.0 / rcond):
        raise np.linalg.LinAlgError(
            f"M-step normal equations are singular (condition {np.max(cond):.3g}): "
            "the data do not excite all of u, 1, v, v^2")
    sol = np.linalg.solve(A, bvec[..., None])[..., 0] / dg
    return np.moveaxis(sol, -1, 0)


def plugin_stats(vbar, u) -> SuffStats:
    """Paper's E-step statistics: eq. (31), (33) with the filtered means plugged in.

    ``vbar`` (n+1, *batch) holds vbar(0..n), ``u`` (n, *batch) or (n,) holds u(1..n).
    """
    vbar = np.asarray(vbar, float)
    Phi = regressors(expand_to(u, vbar.ndim), vbar[:-1])
    phi = vbar[1:] - vbar[:-1]
    return SuffStats(PP=np.einsum("t...i,t...j->...ij", Phi, Phi),
                     Pp=np.einsum("t...i,t...->...i", Phi, phi),
                     pp=np.sum(phi * phi, axis=0), count=vbar.shape[0] - 1)


def pair_stats(v_prev, v_curr, w, u_t) -> SuffStats:
    """Monte Carlo E[.] of one transition from weighted particle pairs (exact EM statistics).

    ``v_prev``, ``v_curr``, ``w`` (N, *batch): pairs (v(t-1), v(t)) drawn from the filtering
    (lag 0) or fixed-lag smoothing distribution with normalised weights ``w``; ``u_t`` scalar or
    (*batch). E[Phi Phi^T] = sum_i w_i Phi_i Phi_i^T etc. (this keeps the posterior spread that the
    plug-in of eq. (31) drops, which matters for the v^2 column: E[v^2] = vbar^2 + Var v).
    """
    Phi = regressors(np.broadcast_to(u_t, v_prev.shape), v_prev)
    phi = v_curr - v_prev
    return SuffStats(PP=np.einsum("n...,n...i,n...j->...ij", w, Phi, Phi),
                     Pp=np.einsum("n...,n...i,n...->...i", w, Phi, phi),
                     pp=np.sum(w * phi * phi, axis=0), count=1)


def gaussian_pair_stats(u, m_prev, m_curr, P_prev, P_cross, P_curr, v_ref) -> SuffStats:
    """Closed-form statistics for the *linearised* transition of the exact (Kalman) variant.

    The quadratic term is linearised about a fixed reference v_ref(t-1) (fixed over the EM run,
    so the model -- and with it the likelihood -- does not change between iterations):
    v^2 ~ 2 v_ref v - v_ref^2, hence Phi_lin = g + h x with x = v(t-1),
    g = [u, -1, 0, v_ref^2], h = [0, 0, -1, -2 v_ref]. With smoothed moments of (x, z = v(t)):
    m_prev = E x, m_curr = E z, P_prev = Var x, P_curr = Var z, P_cross = Cov(x, z), all (n, *b).

    E[Phi Phi^T] = g g^T + (g h^T + h g^T) E x + h h^T E x^2,
    E[Phi phi] = g (E z - E x) + h (E xz - E x^2),  E phi^2 = E z^2 - 2 E xz + E x^2.
    """
    u = np.broadcast_to(expand_to(u, m_prev.ndim), m_prev.shape)
    vr = np.broadcast_to(v_ref, m_prev.shape)
    zero, one = np.zeros_like(m_prev), np.ones_like(m_prev)
    g = np.stack([u, -one, zero, vr * vr], axis=-1)
    h = np.stack([zero, zero, -one, -2.0 * vr], axis=-1)
    Ex, Ez = m_prev, m_curr
    Exx = P_prev + m_prev * m_prev
    Ezz = P_curr + m_curr * m_curr
    Exz = P_cross + m_prev * m_curr
    PP = (np.einsum("t...i,t...j->...ij", g, g)
          + np.einsum("t...,t...i,t...j->...ij", Ex, g, h)
          + np.einsum("t...,t...i,t...j->...ij", Ex, h, g)
          + np.einsum("t...,t...i,t...j->...ij", Exx, h, h))
    Pp = (np.einsum("t...i,t...->...i", g, Ez - Ex) + np.einsum("t...i,t...->...i", h, Exz - Exx))
    pp = np.sum(Ezz - 2.0 * Exz + Exx, axis=0)
    return SuffStats(PP=PP, Pp=Pp, pp=pp, count=m_prev.shape[0])


def param_error(vt, vt_true=CRH3_VARTHETA) -> np.ndarray:
    """The paper's delta = ||vartheta_k - vartheta|| / ||vartheta|| (Tables 1-3), per batch."""
    vt = np.asarray(vt, float)
    tr = np.asarray(vt_true, float).reshape((4,) + (1,) * (vt.ndim - 1))
    return np.linalg.norm(vt - tr, axis=0) / np.linalg.norm(vt_true)


def theta_change(vt_new, vt_old, T: float = 1.0, space: str = "vartheta") -> np.ndarray:
    """Step 7's change measure. ``space='Theta'``: ||Theta_k - Theta_{k-1}|| in [a, b, c, d]
    (the paper's literal rule); ``'vartheta'``: ||vt_k - vt_{k-1}|| / ||vt_k|| (scale free)."""
    vt_new, vt_old = np.asarray(vt_new, float), np.asarray(vt_old, float)
    if space == "vartheta":
        return np.linalg.norm(vt_new - vt_old, axis=0) / np.linalg.norm(vt_new, axis=0)
    if space != "Theta":
        raise ValueError(f"unknown space {space!r}")

    def to_theta(vt):
        dbar = vt[0]
        return np.stack([vt[1] / dbar, vt[2] / dbar, vt[3] / dbar, G_PER_KN * T / dbar - 1.0])

    return np.linalg.norm(to_theta(vt_new) - to_theta(vt_old), axis=0)
