"""The augmented Kalman filter: exact Gaussian likelihood of every linear hypothesis at once.

State x = (s, v) of a train (distance, speed) with white acceleration noise of PSD q; odometer
readings measure (s, v), balise readings s0 + s. The model's known drift and any number of
parameter columns (drift columns: integrals of regressors over each interval; measurement
columns) ride along as extra columns of the state (de Jong 1991, "the diffuse Kalman filter";
the GLS of ``identify`` and every hypothesis of ``diagnose``). The Kalman gains do not depend on
the columns, so one run gives

    W = sum_k E_k^T S_k^-1 E_k,    log L(theta) = -0.5 (sum_k log det S_k + m log 2 pi + z^T W z)

for z = [1, theta] and any theta: the likelihood of a hypothesis that is a linear combination
of the columns is then a small quadratic problem (:func:`gls`). Tested against a dense
joint-Gaussian solve.

Pure: numpy only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .kalman import balise_update, odometer_update, predict_cov

LOG2PI = math.log(2.0 * math.pi)


@dataclass
class Events:
    t: np.ndarray  # s, event times (odometer samples kept and balise readings)
    kind: np.ndarray  # 0 odometer, 1 balise
    y_d: np.ndarray  # m (odometer distance) or balise position
    y_v: np.ndarray  # m/s
    r_v: np.ndarray  # (m/s)^2 or balise variance m^2
    held: np.ndarray  # interval ending at event k is not modelled (standstill)
    odo: np.ndarray  # indices of the odometer events
    bal: np.ndarray  # indices of the balise events


@dataclass
class KFResult:
    W: np.ndarray  # (p+1, p+1)
    logdet: float
    m: int  # scalar measurements
    E0: np.ndarray | None = None  # (n_ev, 2) innovations of column 0 (speed, distance/balise)
    E1: np.ndarray | None = None  # (n_ev, 2) the same for column 1 (s0): innovation at s0 is
    #                               E0 + s0 E1
    S_v: np.ndarray | None = None  # innovation variance of the speed (odometer events)

    def loglik(self, z: np.ndarray) -> float:
        return -0.5 * (self.logdet + self.m * LOG2PI + z @ self.W @ z)


def augmented_kf(ev: Events, q: float, r_s: float, Bv, Bs, Md, Mv, Mb, q_held: float,
                 keep_innov: bool = False, update: np.ndarray | None = None,
                 q_per_event: np.ndarray | None = None) -> KFResult:
    """One Kalman filter run on x = (s, v) carrying p + 1 columns (column 0: the data with the
    fixed part of the model; columns 1..p: the parameters' sensitivities).

    Bv, Bs (n_ev, p+1): drift increments of the interval ending at event k; Md, Mv (n_ev, p+1):
    odometer measurement columns; Mb (n_ev, p+1): balise measurement columns (s0 is one).
    Process noise: ``q`` (``q_held`` where ``ev.held``), or ``q_per_event[k]`` for the
    interval ending at event k when given. The
    innovation at theta is E_k [1, theta]; W = sum E_k^T S_k^-1 E_k, accumulated as Z^T Z of the
    whitened innovations (Cholesky of each S_k). ``update[k]`` False skips event k's measurement
    (held-out data)."""
    n, p1 = ev.t.size, Bv.shape[1]
    Z = np.zeros((2 * n, p1))
    Xs = -Md[0].copy()
    Xv = -Mv[0].copy()
    Xs[0] += ev.y_d[0]
    Xv[0] += ev.y_v[0]
    p00, p01, p11 = r_s, 0.0, float(ev.r_v[0])
    logdet, m, row = 0.0, 0, 0
    E0 = np.zeros((n, 2)) if keep_innov else None
    E1 = np.zeros((n, 2)) if keep_innov else None
    S_v = np.full(n, np.nan) if keep_innov else None
    dts = np.diff(ev.t, prepend=ev.t[0]).tolist()
    kinds, held = ev.kind.tolist(), ev.held.tolist()
    yd, yv, rv = ev.y_d.tolist(), ev.y_v.tolist(), ev.r_v.tolist()
    upd = [True] * n if update is None else update.tolist()
    qs = None if q_per_event is None else np.asarray(q_per_event, float).tolist()
    for k in range(1, n):
        h = dts[k]
        qk = qs[k] if qs is not None else (q_held if held[k] else q)
        Xs = Xs + h * Xv + Bs[k]
        Xv = Xv + Bv[k]
        p00, p01, p11 = predict_cov(p00, p01, p11, h, qk)
        if not upd[k]:
            continue
        if kinds[k] == 0:
            s00, s01, s11, det, _, (k00, k01, k10, k11), pn = odometer_update(
                p00, p01, p11, r_s, rv[k])
            es = -Xs - Md[k]
            ev_ = -Xv - Mv[k]
            es[0] += yd[k]
            ev_[0] += yv[k]
            # whitening: S = L L^T, rows of L^-1 E
            l00 = math.sqrt(s00)
            l10 = s01 / l00
            l11 = math.sqrt(s11 - l10 * l10)
            z0 = es / l00
            Z[row] = z0
            Z[row + 1] = (ev_ - l10 * z0) / l11
            row += 2
            logdet += math.log(det)
            m += 2
            if keep_innov:
                E0[k] = (ev_[0], es[0])
                E1[k] = (ev_[1], es[1])
                S_v[k] = s11
            Xs = Xs + k00 * es + k01 * ev_
            Xv = Xv + k10 * es + k11 * ev_
            p00, p01, p11 = pn
        else:
            s, (k0, k1), pn = balise_update(p00, p01, p11, rv[k])
            eb = -Xs - Mb[k]
            eb[0] += yd[k]
            Z[row] = eb / math.sqrt(s)
            row += 1
            logdet += math.log(s)
            m += 1
            if keep_innov:
                E0[k] = (np.nan, eb[0])
                E1[k] = (np.nan, eb[1])
            Xs = Xs + k0 * eb
            Xv = Xv + k1 * eb
            p00, p01, p11 = pn
    Z = Z[:row]
    return KFResult(W=Z.T @ Z, logdet=logdet, m=m, E0=E0, E1=E1, S_v=S_v)


def _equilibrated(A: np.ndarray):
    """``A`` scaled to unit diagonal, ``A / sqrt(diag A diag A^T)``, and the scales (1 where a
    parameter carries no information): the parameters' units then do not enter the condition
    number or the pseudo-inverse's cut-off."""
    dg = np.diag(A)
    d = np.where(dg > 0, np.sqrt(np.abs(dg)), 1.0)
    return A / np.outer(d, d), d


def information_condition(W: np.ndarray, M: np.ndarray | None = None) -> float:
    """Condition number of the equilibrated information of theta (see :func:`gls`)."""
    Wh = W if M is None else M.T @ W @ M
    return float(np.linalg.cond(_equilibrated(Wh[1:, 1:])[0]))


def gls(W: np.ndarray, M: np.ndarray | None = None, max_condition: float = np.inf):
    """Maximise -0.5 [1, theta]^T Wh [1, theta] over theta, Wh = M^T W M: (theta, cov, quad).

    The generalised least squares of every augmented-filter fit. ``M`` (p+1, 1+k) maps
    [1, theta] onto the elementary columns (None: theta are the columns 1..p themselves). With
    A = Wh[1:, 1:] (the information of theta) and b = Wh[1:, 0]::

        theta = -A^-1 b,   cov = A^-1,   quad = Wh[0, 0] + b^T theta = min over theta

    so the log-likelihood at the optimum is -0.5 (logdet + m log 2 pi + quad). A is inverted
    after equilibration to unit diagonal, by the pseudo-inverse: a parameter without
    information gets theta 0 and variance 0 instead of an error. ``max_condition``: raise
    ``numpy.linalg.LinAlgError`` when the equilibrated information's condition number exceeds it
    (the caller needs every parameter determined)."""
    Wh = W if M is None else M.T @ W @ M
    A, b = Wh[1:, 1:], Wh[1:, 0]
    As, d = _equilibrated(A)
    if np.isfinite(max_condition):
        cond = np.linalg.cond(As)
        if not cond <= max_condition:
            raise np.linalg.LinAlgError(f"information matrix singular (condition {cond:.3g})")
    cov = np.linalg.pinv(As) / np.outer(d, d)
    th = -cov @ b
    quad = float(Wh[0, 0] + b @ th)
    return th, cov, quad


def kf2_loglik(ev: Events, q: float, r_s: float, bv, bs, md, mv, q_held: float) -> float:
    """The fast path of :func:`augmented_kf` for two columns, [fixed model, s0]: the profile
    log-likelihood with s0 eliminated exactly by GLS, as ``gls(W, I)`` on the general filter
    with ``Bv = [bv, 0]``, ``Bs = [bs, 0]``, ``Md = [md, 0]``, ``Mv = [mv, 0]``, ``Mb = [0, 1]``
    gives (tested equal). A scalar loop on Python floats with kalman.predict_cov,
    odometer_update and balise_update written out (no calls, no tuples, no arrays): a noise
    fit calls it some 30 times, and per event the general filter's array work, or calls,
    would cost several times the arithmetic."""
    n = ev.t.size
    xs0, xv0 = ev.y_d[0] - md[0], ev.y_v[0] - mv[0]
    xs1 = xv1 = 0.0
    p00, p01, p11 = r_s, 0.0, float(ev.r_v[0])
    w00 = w01 = w11 = 0.0
    logdet, m = 0.0, 0
    t, kind, yd, yv, rv, held = (ev.t.tolist(), ev.kind.tolist(), ev.y_d.tolist(),
                                 ev.y_v.tolist(), ev.r_v.tolist(), ev.held.tolist())
    bv, bs, md, mv = bv.tolist(), bs.tolist(), md.tolist(), mv.tolist()
    log = math.log
    t_prev = t[0]
    for k in range(1, n):
        tk = t[k]
        h = tk - t_prev
        t_prev = tk
        qk = q_held if held[k] else q
        xs0 += h * xv0 + bs[k]
        xv0 += bv[k]
        xs1 += h * xv1
        p00, p01, p11 = (p00 + 2 * h * p01 + h * h * p11 + qk * h ** 3 / 3.0,
                         p01 + h * p11 + qk * h * h / 2.0, p11 + qk * h)
        if kind[k] == 0:
            s00, s11 = p00 + r_s, p11 + rv[k]
            det = s00 * s11 - p01 * p01
            i00, i01, i11 = s11 / det, -p01 / det, s00 / det
            k00, k01 = p00 * i00 + p01 * i01, p00 * i01 + p01 * i11
            k10, k11 = p01 * i00 + p11 * i01, p01 * i01 + p11 * i11
            es0, ev0 = yd[k] - xs0 - md[k], yv[k] - xv0 - mv[k]
            es1, ev1 = -xs1, -xv1
            w00 += es0 * (i00 * es0 + i01 * ev0) + ev0 * (i01 * es0 + i11 * ev0)
            w01 += es0 * (i00 * es1 + i01 * ev1) + ev0 * (i01 * es1 + i11 * ev1)
            w11 += es1 * (i00 * es1 + i01 * ev1) + ev1 * (i01 * es1 + i11 * ev1)
            logdet += log(det)
            m += 2
            xs0 += k00 * es0 + k01 * ev0
            xv0 += k10 * es0 + k11 * ev0
            xs1 += k00 * es1 + k01 * ev1
            xv1 += k10 * es1 + k11 * ev1
            p00, p01, p11 = ((1 - k00) * p00 - k01 * p01, (1 - k00) * p01 - k01 * p11,
                             -k10 * p01 + (1 - k11) * p11)
        else:
            s = p00 + rv[k]
            k0, k1 = p00 / s, p01 / s
            e0, e1 = yd[k] - xs0, -xs1 - 1.0
            w00 += e0 * e0 / s
            w01 += e0 * e1 / s
            w11 += e1 * e1 / s
            logdet += log(s)
            m += 1
            xs0 += k0 * e0
            xv0 += k1 * e0
            xs1 += k0 * e1
            xv1 += k1 * e1
            p00, p01, p11 = (1 - k0) * p00, (1 - k0) * p01, p11 - k1 * p01
    quad = w00 - w01 * w01 / w11 if w11 > 0 else w00
    return -0.5 * (logdet + m * LOG2PI + quad)
