"""The Kalman steps, written once: prediction and measurement update.

Two forms of the same equations, for the two ways the estimators run a Kalman filter:

1. **Batched** (:func:`propagate_cov`, :func:`predict`, :func:`update`): a leading particle axis
   (``N``), used by the braking-rate particle filters (``batched_kf``), the
   ``IntermittentKF`` of ``robust_filter`` (``N = 1``) and every model shape.

   Shapes: ``x (N, n)``, ``P (N, n, n)``; model matrices may carry a leading axis of N or 1
   (broadcast), so particles with their own model (one braking rate each) and particles sharing
   one model are the same code path.

   Predict::

       x' = Phi x + Bu,          P' = Phi P Phi^T + Qd          (symmetrised)

   Update with the rows ``mask`` of ``y = H x + e``, ``e ~ N(0, diag(R))``. With a *diagonal* R the
   joint update equals the sequential update by one scalar row at a time (the rows' noises are
   independent, so conditioning on them one after the other is exact), and the log predictive
   likelihood factorises into the scalar ones (chain rule)::

       for each used row h, variance r:
           s = h P h^T + r,   k = P h^T / s,   e = y_h - h x
           x <- x + k e,      P <- P - (P h^T)(P h^T)^T / s      (symmetric by construction)
           log p += -1/2 (log 2 pi + log s + e^2 / s)

   No matrix inverse, no per-particle LAPACK call: a few vectorised array operations per row,
   which is what keeps a step of 1350 particles well under a millisecond. The summed log
   predictive likelihood ``log N(y_m; H_m x', H_m P' H_m^T + R_m)`` is the Rao-Blackwellised
   particle weight (Zheng eq. (12), (17); Q-GRBPF eq. (3)-(5)). ``test_braking_kf.py`` checks all
   of this against a dense joint-Gaussian solve.

2. **Closed form for the (distance, speed) model** (:func:`predict_cov`,
   :func:`odometer_update`, :func:`balise_update`): the same predict and update written out in
   scalars for ``A = [[1, h], [0, 1]]`` with white acceleration noise and an odometer (both
   components, diagonal R) or a balise (distance) reading. ``augmented_kf`` runs them once per
   event in a Python loop over thousands of events per hypothesis, where a numpy call per
   operation would cost more than the arithmetic; they also return the intermediate S, S^-1
   and K that the augmented filter needs for its columns. ``test_kalman.py`` checks that both
   forms give the same numbers.

3. **Smoothing** (:func:`rts_smooth`): the Rauch-Tung-Striebel backward pass over the stored
   filtered and predicted moments of any of the filters above (time on the leading axis, any
   batch axes, any state size), with the smoother gains that give the lag-one cross covariances
   the exact EM statistics need. ``test_kalman.py`` checks it against the posterior of the
   stacked Gaussian of all states.

Pure: numpy only.
"""

from __future__ import annotations

import numpy as np

__all__ = ["propagate_cov", "predict", "update", "rts_smooth", "predict_cov", "odometer_update",
           "balise_update"]

_LOG2PI = float(np.log(2.0 * np.pi))


def _sym(P):
    return 0.5 * (P + np.swapaxes(P, -1, -2))


def propagate_cov(P, Phi, Qd):
    """``Phi P Phi^T + Qd`` (symmetrised); ``P (..., n, n)``, ``Phi`` broadcasting with it."""
    return _sym(np.matmul(np.matmul(Phi, P), np.swapaxes(Phi, -1, -2)) + Qd)


def predict(x, P, Phi, Bu, Qd):
    """One prediction step for every particle (see module docstring).

    ``Phi (N or 1, n, n)``, ``Bu (N or 1, n)``, ``Qd (n, n)``.
    """
    if Phi.shape[0] == x.shape[0]:
        x_new = np.matmul(Phi, x[:, :, None])[:, :, 0] + Bu
    else:
        x_new = x @ Phi[0].T + Bu
    return x_new, propagate_cov(P, Phi, Qd)


_SEL: dict = {}


def _selectors(H) -> tuple[int, ...]:
    """Per row of ``H``: the state index if the row is a selector (a single 1: the braking
    model's D, v, a_z rows), else -1. Selector rows need no matmul (``P h`` is a column of P).
    Cached by the matrix's bytes (a few models per process)."""
    key = (H.shape, H.tobytes())
    hit = _SEL.get(key)
    if hit is None:
        hit = tuple(int(np.argmax(h)) if (np.count_nonzero(h) == 1 and h.max() == 1.0) else -1
                    for h in H)
        if len(_SEL) > 64:
            _SEL.clear()
        _SEL[key] = hit
    return hit


def update(x, P, y, H, R, mask):
    """Sequential exact update of every particle with the rows ``mask`` of ``y``.

    ``y (p,)`` one reading for every particle, or ``(N, p)`` one per particle (independent data
    sets run side by side), ``H (p, n)``, ``R (p,)`` variances (> 0), ``mask (p,)`` bool
    (missing components are skipped). Returns ``(x+, P+, loglik (N,))``; with no row used,
    ``(x, P, 0)``.
    """
    mask = np.asarray(mask, dtype=bool)
    rows = np.flatnonzero(mask)
    N = x.shape[0]
    if rows.size == 0:
        return x, P, np.zeros(N)
    H = np.asarray(H, dtype=float)
    R = np.asarray(R, dtype=float)
    y = np.asarray(y, dtype=float)
    if y.ndim == 2:  # (N, p) -> (p, N): y[j] is then a row over the particles, like xt[i]
        y = y.T
    sel = _selectors(H)
    n = x.shape[1]
    # Work with the particles on the *last* axis (xt (n, N), Pt (n, n, N), copies): every
    # operation below is then elementwise over long contiguous rows of N values instead of
    # numpy's slow inner loops of length n = 4 (measured 2x faster at N = 1350; the same
    # arithmetic, results identical bit for bit). The interface keeps the leading axis.
    # (always copies: with N = 1 the transposes are contiguous already, ascontiguousarray would
    # return views, and the in-place steps below would overwrite the caller's x and P)
    xt = x.T.copy()
    Pt = P.reshape(N, n * n).T.copy().reshape(n, n, N)
    logs = np.empty((rows.size, N))
    quad = np.empty((rows.size, N))
    for r, j in enumerate(rows.tolist()):  # rows (at most a handful), not particles
        i = sel[j]
        if i >= 0:
            Ph = Pt[i].copy()  # (n, N) = (P h)^T (P symmetric); a copy: Pt is updated below
            e = y[j] - xt[i]
            s = Ph[i] + R[j]  # (N,)
        else:
            h = H[j]
            Ph = np.tensordot(h, Pt, axes=(0, 0))
            e = y[j] - h @ xt
            s = h @ Ph + R[j]
        xt += Ph * (e / s)
        # P - s k k^T = P - (Ph)(Ph)^T / s: elements (i, j) and (j, i) are the same products, so
        # P stays exactly symmetric (the "symmetrised" form; Joseph's form would cost three
        # outer products per row, ~2x the time of the whole update, for no gain at R > 0)
        outer = Ph[:, None, :] * Ph[None, :, :]
        outer /= s
        Pt -= outer
        logs[r] = s
        quad[r] = e * e / s
    loglik = -0.5 * (rows.size * _LOG2PI + np.log(logs).sum(axis=0) + quad.sum(axis=0))
    return xt.T.copy(), Pt.reshape(n * n, N).T.reshape(N, n, n).copy(), loglik


def rts_smooth(m_f, P_f, m_p, P_p, F):
    """Rauch-Tung-Striebel smoother over stored Kalman filter moments (time on axis 0).

    ``m_f (T, ..., n)``, ``P_f (T, ..., n, n)``: filtered x_{t|t}, P_{t|t}; ``m_p``, ``P_p`` the
    same shapes: predicted x_{t|t-1}, P_{t|t-1} (entry 0 unused); ``F (T, ..., n, n)`` the
    transition from t-1 to t (entry 0 unused). Batch axes ``...`` broadcast: covariances and
    transitions common to all batch elements may omit them. For t = T-2 .. 0::

        C_t = P_{t|t} F_{t+1}^T P_{t+1|t}^-1
        x_{t|T} = x_{t|t} + C_t (x_{t+1|T} - x_{t+1|t})
        P_{t|T} = P_{t|t} + C_t (P_{t+1|T} - P_{t+1|t}) C_t^T

    Returns ``(m_s, P_s, C)`` with ``C (T-1, ..., n, n)`` the smoother gains: the lag-one cross
    covariance is Cov(x_t, x_{t+1} | y_1..T) = C_t P_{t+1|T} (Shumway & Stoffer 1982). The
    smoothed moments equal the posterior of the stacked Gaussian of all states (tested).
    """
    m_s = np.array(m_f, dtype=float, copy=True)
    P_s = np.array(P_f, dtype=float, copy=True)
    gains = []
    for t in range(m_s.shape[0] - 2, -1, -1):
        C = np.matmul(np.matmul(P_f[t], np.swapaxes(F[t + 1], -1, -2)),
                      np.linalg.inv(P_p[t + 1]))
        m_s[t] = m_f[t] + np.matmul(C, (m_s[t + 1] - m_p[t + 1])[..., None])[..., 0]
        P_s[t] = P_f[t] + np.matmul(np.matmul(C, P_s[t + 1] - P_p[t + 1]), np.swapaxes(C, -1, -2))
        gains.append(C)
    gains.reverse()
    C = np.stack(gains) if gains else np.empty((0,) + np.shape(P_f)[1:])
    return m_s, P_s, C


def predict_cov(p00: float, p01: float, p11: float, h: float, q: float):
    """P <- A P A^T + Q for A = [[1, h], [0, 1]], Q = q [[h^3/3, h^2/2], [h^2/2, h]] (white
    acceleration noise of PSD q over h seconds); P symmetric 2x2 as (p00, p01, p11)."""
    return (p00 + 2 * h * p01 + h * h * p11 + q * h ** 3.0 / 3.0,
            p01 + h * p11 + q * h * h / 2.0, p11 + q * h)


def odometer_update(p00: float, p01: float, p11: float, r_s: float, r_v: float):
    """An odometer reading of (s, v) with noise diag(r_s, r_v): S = P + R, its inverse
    (i00, i01, i11), det S, the gain K = P S^-1 (k00, k01, k10, k11) and the updated P."""
    s00, s01, s11 = p00 + r_s, p01, p11 + r_v
    det = s00 * s11 - s01 * s01
    i00, i01, i11 = s11 / det, -s01 / det, s00 / det
    k00, k01 = p00 * i00 + p01 * i01, p00 * i01 + p01 * i11
    k10, k11 = p01 * i00 + p11 * i01, p01 * i01 + p11 * i11
    n00 = (1 - k00) * p00 - k01 * p01
    n01 = (1 - k00) * p01 - k01 * p11
    n11 = -k10 * p01 + (1 - k11) * p11
    return (s00, s01, s11, det, (i00, i01, i11), (k00, k01, k10, k11), (n00, n01, n11))


def balise_update(p00: float, p01: float, p11: float, r_b: float):
    """A balise reading of s with noise r_b: S, the gain (k0, k1) and the updated P."""
    s = p00 + r_b
    k0, k1 = p00 / s, p01 / s
    return s, (k0, k1), ((1 - k0) * p00, (1 - k0) * p01, p11 - k1 * p01)
