r"""The step functions of the recursive robust filter under packet dropouts (Wen et al. 2017).

Model (``wen_model``, eq. (10))::

    x(k+1) = (A + H Delta(k) Eu) x(k) + u_k + E w(k),   Delta Delta^T <= I,  w^2 <= q,
    y(k)   = C x(k) + nu(k),   ybar(k) = Lambda(k) y(k),   Lambda = diag(alpha_i(k)),   (5), (11)

with ``u_k`` the known input (drive force, a0, gradient) and ``alpha_i(k)`` Bernoulli with mean
``abar_i`` (eq. (12)); the filter knows the realised ``alpha(k)`` (Remark 3: from the message
sequence numbers). Filter (13)::

    x^(k+1|k)   = A x^(k|k) + u_k
    x^(k+1|k+1) = x^(k+1|k) + K(k+1) Lambda(k+1) (y(k+1) - C x^(k+1|k))

Upper bound of the error second moment, Theorem 2, eq. (21)-(22) (Lemma 1 with general ``Eu``;
the paper has ``Eu = I``)::

    Sigma(k+1|k) = q E E^T + (1 + eps) (A (Sigma^{-1} - gamma Eu^T Eu)^{-1} A^T + H H^T / gamma)
                   + (1 + 1/eps) lambda_bar H H^T,   lambda_bar = |Eu x^(k|k)|^2           (21)
    Sigma(k+1|k+1) = (I - K Abar C) Sigma (I - K Abar C)^T
                     + K [ (Pi - abar abar^T) o (C Sigma C^T) + Pi o R ] K^T                (22)

``Abar = diag(abar)``, ``Pi = E[alpha alpha^T]`` (``Pi_ij = abar_i`` for two channels of one
packet, ``abar_i abar_j`` otherwise) and ``o`` the elementwise product. For one packet
(``Pi = abar 1 1^T``) this is exactly eq. (22); several sensors at different rates and missing
samples are the same update with a different channel list and mask.

**Paper slip in the gain.** Eq. (22) expands to ``Sigma - abar (K C Sigma + Sigma C^T K^T) +
abar K (C Sigma C^T + R) K^T``; its trace is minimised by ``K = Sigma C^T (R + C Sigma
C^T)^{-1}``, *without* the factor ``abar`` of eq. (24)/(33): the derivative (32) drops the
``abar`` of the quadratic term. Both gains give a valid bound (22 holds for any K), but only the
corrected one minimises it, as the theorem claims. ``gain="corrected"`` (default) uses
``K = Sigma C^T Abar (Pi o S)^{-1}``, ``S = C Sigma C^T + R``, the minimiser of tr (22) in the
multi-channel form; ``gain="paper"`` uses eq. (24) literally, ``K = Sigma C^T Abar S^{-1}``.

**Rule for gamma_k** (constraint (23): ``gamma^{-1} I - Eu Sigma Eu^T > 0``). Only the bracket
``A (Sigma^{-1} - gamma Eu^T Eu)^{-1} A^T + H H^T / gamma`` of (21) depends on gamma. We take
the gamma in the open interval ``(0, 1 / lambda_max(Eu Sigma Eu^T))`` that minimises its trace:
with ``Eu Sigma Eu^T = V diag(s) V^T`` and ``g_i = |A Sigma Eu^T V_i|^2`` (Woodbury)
``tr = tr(A Sigma A^T) + sum_i g_i gamma / (1 - gamma s_i) + tr(H H^T) / gamma``, strictly convex
on the interval and infinite at both ends, so the minimiser is the unique root of the increasing
function ``sum_i g_i gamma^2 / (1 - gamma s_i)^2 - tr(H H^T)`` (bracketed Newton). Why: (23)
then holds by construction (strictly inside the interval); Sigma(k+1|k+1) of (22) is monotone in
Sigma(k+1|k) (proof of Thm 2), so the smallest prior bound gives the smallest posterior bound
that a choice of gamma can give -- the same greedy criterion the paper uses for K.
A fixed gamma would violate (23) as soon as Sigma grows, and Remark 6 asks for a per-step choice.

**epsilon.** A parameter (``epsilon > 0``). ``epsilon=None`` picks it per step as
``sqrt(b / a)``, the minimiser of ``(1 + eps) a + (1 + 1/eps) b`` with ``a`` the trace of the
gamma-bracket and ``b = lambda_bar tr(H H^T)``; the proof of Theorem 2 holds for any positive
eps at each step, so this is allowed (for ``b = 0`` the cross terms of (28) vanish and eps -> 0).

**Caveats of Theorem 2 as printed** (kept, but stated): ``lambda_bar`` uses the random estimate
``x^(k|k)`` where the proof needs a deterministic one, and ``Delta(k)`` depends on the random true
speed; the bound is therefore checked by Monte Carlo in the tests and the benchmark.

The stateful filters that call these steps (validation, time keeping, the actuator) are in
``filter_base`` and ``robust_filter``; the message-shaped readings in ``readings``.

Pure: numpy/scipy only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from .wen_model import DiscreteWen, WenModel

__all__ = ["Measurement", "choose_gamma", "robust_predict_cov", "robust_predict",
           "packet_moments", "robust_update"]


@dataclass(frozen=True)
class Measurement:
    """Channels that could arrive at one instant. ``mask[i]`` is the realised ``alpha_i``."""

    y: np.ndarray  # (m,) values (anything where mask is False)
    C: np.ndarray  # (m, n) measurement matrix
    R: np.ndarray  # (m, m) noise covariance (SI units squared)
    abar: np.ndarray  # (m,) Prob(channel received), eq. (12)
    group: np.ndarray  # (m,) int: channels of one packet share alpha
    mask: np.ndarray  # (m,) bool, alpha_i(k)


def choose_gamma(Sigma: np.ndarray, A: np.ndarray, H: np.ndarray, Eu: np.ndarray) -> float:
    """gamma_k minimising tr[A (Sigma^{-1} - gamma Eu^T Eu)^{-1} A^T] + tr(H H^T) / gamma on
    (0, 1/lambda_max(Eu Sigma Eu^T)) (constraint (23)); see the module docstring.

    The stationarity condition is ``r(gamma) = sum_i g_i t_i^2 - h = 0`` with
    ``t_i = gamma / (1 - gamma s_i)``; ``r`` is increasing and convex on the interval and
    infinite at its right end. Replacing every ``s_i`` by ``s_max`` (``s_min``) gives functions
    above (below) ``r`` with closed-form roots ``sqrt(h) / (sqrt(sum g) + s sqrt(h))``, so the
    root lies in ``[gamma_lo, min(gamma_hi, 1/s_max))``; safeguarded Newton (bisection whenever
    a Newton step leaves the bracket) converges in a few iterations.
    Returns 0.0 when ``H = 0`` (no uncertainty: the bracket is ``A Sigma A^T`` in the limit).
    """
    return _choose_gamma(Sigma, A, float(np.sum(H * H)), Eu, None)


def _choose_gamma(Sigma: np.ndarray, A: np.ndarray, h: float, Eu: np.ndarray, S_u) -> float:
    """:func:`choose_gamma` with ``h = sum(H * H)`` and ``S_u = Eu Sigma Eu^T`` (None: computed
    here) given by the caller, who has them already."""
    if h == 0.0:
        return 0.0
    s, V = np.linalg.eigh(Eu @ Sigma @ Eu.T if S_u is None else S_u)
    G = A @ Sigma @ Eu.T @ V
    g = [float(v) for v in np.sum(G * G, axis=0)]
    s = [float(v) for v in s]
    sh, sg = math.sqrt(h), math.sqrt(sum(g))
    lo = sh / (sg + s[-1] * sh)
    pole = 1.0 / s[-1]
    ghi = sh / (sg + max(s[0], 0.0) * sh)  # guard: s_min >= 0 in exact arithmetic
    hi = min(ghi, pole)
    gam = ghi if ghi < pole else 0.5 * (lo + hi)
    for _ in range(200):
        r, dr = -h, 0.0
        for gi, si in zip(g, s):
            d = 1.0 - gam * si
            t = gam / d
            r += gi * t * t
            dr += 2.0 * gi * t / (d * d)
        if r > 0.0:
            hi = gam
        else:
            lo = gam
        if abs(r) <= 1e-14 * h or hi - lo <= 1e-15 * hi:
            break
        new = gam - r / dr if dr > 0.0 else 0.5 * (lo + hi)
        if not lo < new < hi:
            new = 0.5 * (lo + hi)
        if abs(new - gam) <= 1e-15 * gam:
            break
        gam = new
    return gam


def robust_predict_cov(Sigma: np.ndarray, dm: DiscreteWen, q: float, lam_bar: float,
                       gamma: float | None = None, epsilon: float | None = None
                       ) -> tuple[np.ndarray, float, float]:
    """Eq. (21). Returns ``(Sigma(k+1|k), gamma, epsilon)`` actually used.

    ``gamma=None``: :func:`choose_gamma`. ``epsilon=None``: per-step minimiser ``sqrt(b/a)``.
    Raises ValueError when a given gamma violates (23).
    """
    A, Eu = dm.A, dm.Eu
    HH = dm.HH  # H H^T, computed once per period (DiscreteWen)
    check = gamma is not None
    S_u = None
    if gamma is None:
        S_u = Eu @ Sigma @ Eu.T if dm.hh != 0.0 else None
        gamma = _choose_gamma(Sigma, A, dm.hh, Eu, S_u)
    if gamma > 0.0:
        if S_u is None:
            S_u = Eu @ Sigma @ Eu.T
        W = dm.I_u / gamma - S_u
        if check and np.linalg.eigvalsh(W)[0] <= 0.0:  # choose_gamma's is inside by construction
            raise ValueError("gamma violates constraint (23): 1/gamma I - Eu Sigma Eu^T not > 0")
        SE = Sigma @ Eu.T
        M = Sigma + SE @ np.linalg.solve(W, SE.T)  # (Sigma^{-1} - gamma Eu^T Eu)^{-1}, Woodbury
        bracket = A @ M @ A.T + HH / gamma
    else:
        bracket = A @ Sigma @ A.T
    b_term = lam_bar * HH
    if epsilon is None:
        a_tr, b_tr = float(np.trace(bracket)), float(np.trace(b_term))
        epsilon = math.sqrt(b_tr / a_tr) if b_tr > 0.0 else 0.0
    if epsilon > 0.0:
        out = (1.0 + epsilon) * bracket + (1.0 + 1.0 / epsilon) * b_term
    elif np.any(b_term != 0.0):
        raise ValueError("epsilon must be > 0 when lambda_bar H H^T != 0")
    else:
        out = bracket
    out = out + q * dm.EE
    return 0.5 * (out + out.T), float(gamma), float(epsilon)


def robust_predict(x: np.ndarray, Sigma: np.ndarray, model: WenModel, dm: DiscreteWen,
                   control_accel: float, epsilon: float | None = None,
                   clamp_standstill: bool = True) -> tuple[np.ndarray, np.ndarray, float, float]:
    """First line of (13) and eq. (21): ``(x^(k+1|k), Sigma(k+1|k), gamma, epsilon)``."""
    Eux = dm.Eu @ x
    lam_bar = float(Eux @ Eux)  # lambda_max(Eu x x^T Eu^T) = |Eu x|^2
    Sp, gamma, eps = robust_predict_cov(Sigma, dm, model.q, lam_bar, None, epsilon)
    xp = model.predict_mean(dm, x, control_accel)
    if clamp_standstill:
        # The world never rolls back (true v >= 0): stop instead of reversing. For the
        # velocity this is a projection onto v >= 0, which cannot increase its error.
        xp = model.standstill(x, xp, dm.dt)
    return xp, Sp, gamma, eps


def packet_moments(meas: Measurement) -> np.ndarray:
    """``Pi = E[alpha alpha^T]``: ``abar_i`` within one packet, ``abar_i abar_j`` across."""
    ab = meas.abar
    same = meas.group[:, None] == meas.group[None, :]
    return np.where(same, np.minimum(ab[:, None], ab[None, :]), np.outer(ab, ab))


def robust_update(x_pred: np.ndarray, Sigma_pred: np.ndarray, meas: Measurement,
                  gain: str = "corrected") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Second line of (13) with the gain (24) (or its correction) and eq. (22).

    Returns ``(x^(k+1|k+1), Sigma(k+1|k+1), K)``. Channels with ``abar = 0`` are dropped.
    """
    keep = meas.abar > 0.0
    if not keep.all():
        if not keep.any():
            return x_pred, Sigma_pred, np.zeros((x_pred.size, 0))
        meas = replace(meas, C=meas.C[keep], R=meas.R[np.ix_(keep, keep)],
                       abar=meas.abar[keep], group=meas.group[keep], mask=meas.mask[keep],
                       y=meas.y[keep])
    C, R, ab, mask = meas.C, meas.R, meas.abar, meas.mask
    Pi = packet_moments(meas)
    CS = C @ Sigma_pred
    S = CS @ C.T + R
    PiS = Pi * S
    if gain == "corrected":
        K = np.linalg.solve(PiS.T, (Sigma_pred @ C.T * ab).T).T  # Sigma C^T Abar (Pi o S)^{-1}
    elif gain == "paper":
        K = np.linalg.solve(S.T, (Sigma_pred @ C.T * ab).T).T  # eq. (24): abar Sigma C^T S^{-1}
    else:
        raise ValueError(f"gain must be 'corrected' or 'paper', got {gain!r}")
    IKC = np.eye(x_pred.size) - K @ (ab[:, None] * C)
    inner = (Pi - np.outer(ab, ab)) * (CS @ C.T) + Pi * R
    Sig = IKC @ Sigma_pred @ IKC.T + K @ inner @ K.T  # eq. (22) in a sum-of-PSD form
    innov = np.where(mask, meas.y - C @ x_pred, 0.0)  # eq. (13): ybar - alpha C x^
    x_new = x_pred + K @ innov
    return x_new, 0.5 * (Sig + Sig.T), K
