r"""The robust filter's prediction (eq. (13) first line, (21)) and update (eq. (13) second line,
(22)-(24)) on the 2-state model, each one compiled scalar call (``numerics.jit``: numba, no
fast-math), for :class:`~.robust_filter.RobustFilter`.

Why: the numpy form (``robust_steps``) spends its ~200 us per reading on 2x2 arrays: some
forty numpy calls of about a microsecond each (``eigh`` and two ``solve`` among them) and the
Python between them, not arithmetic. Here the same formulas run on scalars.

**Same formulas, same order.** Every elementwise operation is ``robust_steps``' own in its
order; the rule for gamma_k (``robust_steps._choose_gamma``: the trace minimiser of the
bracket of (21) on the interval of constraint (23), by the same bracketed Newton iteration,
step for step), the per-step epsilon ``sqrt(b / a)``, the packet moments ``Pi``, both gains
(the corrected minimiser of tr (22) and eq. (24) as printed), the standstill clamp and the
drop of channels with ``abar = 0`` are written out once more on scalars. What differs is what
numpy hands to a library whose rounding is not its own:

* the 2-term sums of the 2x2 products (BLAS: possibly fused multiply-adds) are summed here in
  index order, rounding each product;
* ``np.linalg.solve`` (LAPACK ``gesv``) is LU with partial pivoting here too, dividing by the
  pivots where a BLAS triangular solve may multiply by their reciprocals;
* ``np.linalg.eigh`` of ``Eu Sigma Eu^T`` (``uncertainty="paper"``: Sigma itself) is the
  closed form of a symmetric 2x2 (LAPACK's ``dlaev2``: the larger eigenvalue from the
  half-sum and the rotated half-difference, the smaller as det / larger, a unit eigenvector
  by the tangent of the rotation). For ``uncertainty="velocity"`` it is the 1x1 case
  (``s = Sigma_vv``, ``V = 1``), exact in both.

So the results differ from ``robust_steps`` by rounding only; ``test_robust_compiled.py``
states and checks the bound. The compiled kernels and their interpreted form (``.py_func``,
or all of them under ``TRAIN_NO_JIT=1``) agree to the last bit.

The update kernel first applies ``FilterBase._gate_ok``'s gate (every received channel's
innovation within ``gate`` standard deviations of ``C P C^T + R`` and the ``gate_accel``
look-ahead), as the same sums: on the filter's channels (rows of the identity) both are exact,
so the decisions are the same.

**Every other path is ``robust_steps``'.** Where the numpy form raises (a zero divisor in the
gamma rule or in epsilon, a singular ``solve``, ``epsilon <= 0`` with a non-zero cross term
of (21)) or meets a non-finite number (non-finite inputs, or an overflow), the kernel returns
:data:`FALLBACK` and the caller runs the numpy form on the same inputs: it raises the same
exception or gives the same non-finite state, which ``FilterBase.update`` then refuses as
``numerical_failure``. The same for more than two channels and an ``Eu`` of neither form (none
of the filter's).

Without numba (or with ``TRAIN_NO_JIT=1``) :data:`COMPILED` is False and the same kernels run
interpreted: the filter's numbers are then the compiled ones bit for bit, and the interpreted
kernels still cost less than the numpy form (~17 and ~13 us against ~45 and ~50 us per
prediction and update).

Pure: numpy (+ numba when installed).
"""

from __future__ import annotations

import math

import numpy as np

from ..numerics.jit import COMPILED, jit

__all__ = ["COMPILED", "OK", "FALLBACK", "GATE", "predict", "update", "warm_up"]

OK = 0
FALLBACK = 1  # run the numpy form on the same inputs (it raises, or gives a non-finite state)
GATE = 2  # a received channel's innovation outside the gate (FilterBase._gate_ok)


@jit
def _eig_sym2(a, b, c):
    """Eigen-decomposition of the symmetric ``[[a, b], [b, c]]`` (LAPACK's ``dlaev2``):
    ``(s_min, s_max, v_min0, v_min1, v_max0, v_max1)`` with unit eigenvectors. ``rt1`` is the
    eigenvalue of the larger magnitude, ``rt2 = det / rt1`` (no cancellation between the two
    roots), ``(cs1, sn1)`` the eigenvector of ``rt1`` from the rotation's tangent."""
    sm = a + c
    df = a - c
    adf = abs(df)
    tb = b + b
    ab = abs(tb)
    if abs(a) > abs(c):
        acmx, acmn = a, c
    else:
        acmx, acmn = c, a
    if adf > ab:
        rt = adf * math.sqrt(1.0 + (ab / adf) ** 2)
    elif adf < ab:
        rt = ab * math.sqrt(1.0 + (adf / ab) ** 2)
    else:
        rt = ab * math.sqrt(2.0)
    if sm < 0.0:
        rt1 = 0.5 * (sm - rt)
        sgn1 = -1
        rt2 = (acmx / rt1) * acmn - (b / rt1) * b
    elif sm > 0.0:
        rt1 = 0.5 * (sm + rt)
        sgn1 = 1
        rt2 = (acmx / rt1) * acmn - (b / rt1) * b
    else:
        rt1 = 0.5 * rt
        rt2 = -0.5 * rt
        sgn1 = 1
    if df >= 0.0:
        cs = df + rt
        sgn2 = 1
    else:
        cs = df - rt
        sgn2 = -1
    if abs(cs) > ab:
        ct = -tb / cs
        sn1 = 1.0 / math.sqrt(1.0 + ct * ct)
        cs1 = ct * sn1
    elif ab == 0.0:
        cs1, sn1 = 1.0, 0.0
    else:
        tn = -cs / tb
        cs1 = 1.0 / math.sqrt(1.0 + tn * tn)
        sn1 = tn * cs1
    if sgn1 == sgn2:
        cs1, sn1 = -sn1, cs1
    # (cs1, sn1) belongs to rt1, (-sn1, cs1) to rt2; ascending as eigh returns them
    if rt1 >= rt2:
        return rt2, rt1, -sn1, cs1, cs1, sn1
    return rt1, rt2, cs1, sn1, -sn1, cs1


@jit
def _newton_gamma(h, s0, s1, g0, g1, n):
    """``robust_steps._choose_gamma``'s iteration on ``n`` (1 or 2) eigenvalues ``s0 <= s1``
    (``n = 1``: ``s0``, ``g0`` only) and ``g_i = |A Sigma Eu^T V_i|^2``, operation for
    operation. Returns -1.0 where the numpy form divides by zero (it raises there)."""
    gsum = g0 if n == 1 else g0 + g1
    smax = s0 if n == 1 else s1
    sh, sg = math.sqrt(h), math.sqrt(gsum)
    den = sg + smax * sh
    ghi_den = sg + (0.0 if 0.0 > s0 else s0) * sh  # guard: s_min >= 0 (Python's max(s0, 0.0))
    if den == 0.0 or smax == 0.0 or ghi_den == 0.0:
        return -1.0
    lo = sh / den
    pole = 1.0 / smax
    ghi = sh / ghi_den
    hi = pole if pole < ghi else ghi
    gam = ghi if ghi < pole else 0.5 * (lo + hi)
    for _ in range(200):
        r, dr = -h, 0.0
        for i in range(n):
            gi = g0 if i == 0 else g1
            si = s0 if i == 0 else s1
            d = 1.0 - gam * si
            if d == 0.0:
                return -1.0
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


@jit
def _finite(*vals):
    for v in vals:
        if not math.isfinite(v):
            return False
    return True


@jit
def predict(x, P, A, B, E, HH, hh, EE, Eu, q, eps_auto, eps_set, fb, fe, dt, clamp):
    """``robust_steps.robust_predict`` on the 2-state model: ``(status, x(k+1|k) (2,),
    Sigma(k+1|k) (2, 2), gamma, epsilon)``.

    ``A, B, E, HH = H H^T, hh = tr(H H^T), EE = E E^T, Eu``: the period's ``DiscreteWen``
    (``Eu`` one of its two forms, ``[[0, 1]]`` or ``I``; another: :data:`FALLBACK`);
    ``eps_auto``: epsilon per step (``epsilon=None``), else ``eps_set``; ``fb, fe``: the known
    input's forces (``WenModel.known_input``: drive, resistance + gravity); ``clamp``: the
    standstill rule."""
    xo = np.empty(2)
    Po = np.empty((2, 2))
    velocity = Eu.shape[0] == 1
    if velocity:
        if Eu.shape[1] != 2 or Eu[0, 0] != 0.0 or Eu[0, 1] != 1.0:
            return FALLBACK, xo, Po, 0.0, 0.0
    elif (Eu.shape[0] != 2 or Eu.shape[1] != 2 or Eu[0, 0] != 1.0 or Eu[0, 1] != 0.0
          or Eu[1, 0] != 0.0 or Eu[1, 1] != 1.0):
        return FALLBACK, xo, Po, 0.0, 0.0
    x0, x1 = x[0], x[1]
    s00, s01, s10, s11 = P[0, 0], P[0, 1], P[1, 0], P[1, 1]
    if not _finite(x0, x1, s00, s01, s10, s11):
        return FALLBACK, xo, Po, 0.0, 0.0
    a00, a01, a10, a11 = A[0, 0], A[0, 1], A[1, 0], A[1, 1]
    # lambda_bar = |Eu x^(k|k)|^2 (lambda_max of Eu x x^T Eu^T), eq. (21)
    lam = x1 * x1 if velocity else x0 * x0 + x1 * x1
    # A Sigma: G = A Sigma Eu^T V of the gamma rule and, with gamma = 0, the bracket
    as00, as01 = a00 * s00 + a01 * s10, a00 * s01 + a01 * s11
    as10, as11 = a10 * s00 + a11 * s10, a10 * s01 + a11 * s11
    gamma = 0.0
    if hh != 0.0:
        # gamma rule (robust_steps module doc): eigen-decomposition of Eu Sigma Eu^T, then
        # the root of sum_i g_i gamma^2 / (1 - gamma s_i)^2 = tr(H H^T) inside (23)
        if velocity:  # Eu Sigma Eu^T = Sigma_vv, V = 1
            gamma = _newton_gamma(hh, s11, 0.0, as01 * as01 + as11 * as11, 0.0, 1)
        else:  # eigh reads the lower triangle
            e0, e1, v00, v10, v01, v11 = _eig_sym2(s00, s10, s11)
            g00, g10 = as00 * v00 + as01 * v10, as10 * v00 + as11 * v10
            g01, g11 = as00 * v01 + as01 * v11, as10 * v01 + as11 * v11
            gamma = _newton_gamma(hh, e0, e1, g00 * g00 + g10 * g10, g01 * g01 + g11 * g11, 2)
        if gamma < 0.0:
            return FALLBACK, xo, Po, 0.0, 0.0
    if gamma > 0.0:
        # M = (Sigma^{-1} - gamma Eu^T Eu)^{-1} = Sigma + Sigma Eu^T W^{-1} Eu Sigma (Woodbury),
        # W = I / gamma - Eu Sigma Eu^T, as robust_predict_cov solves it
        ig = 1.0 / gamma
        if velocity:
            w = ig - s11
            if w == 0.0:
                return FALLBACK, xo, Po, 0.0, 0.0
            y0, y1 = s01 / w, s11 / w  # W^{-1} Eu Sigma^T (1 x 2)
            m00, m01 = s00 + s01 * y0, s01 + s01 * y1
            m10, m11 = s10 + s11 * y0, s11 + s11 * y1
        else:
            ok, y00, y01, y10, y11 = _solve2(ig - s00, 0.0 - s01, 0.0 - s10, ig - s11,
                                             s00, s10, s01, s11)
            if not ok:
                return FALLBACK, xo, Po, 0.0, 0.0
            m00 = s00 + (s00 * y00 + s01 * y10)
            m01 = s01 + (s00 * y01 + s01 * y11)
            m10 = s10 + (s10 * y00 + s11 * y10)
            m11 = s11 + (s10 * y01 + s11 * y11)
        t00, t01 = a00 * m00 + a01 * m10, a00 * m01 + a01 * m11
        t10, t11 = a10 * m00 + a11 * m10, a10 * m01 + a11 * m11
        b00 = (t00 * a00 + t01 * a01) + HH[0, 0] / gamma
        b01 = (t00 * a10 + t01 * a11) + HH[0, 1] / gamma
        b10 = (t10 * a00 + t11 * a01) + HH[1, 0] / gamma
        b11 = (t10 * a10 + t11 * a11) + HH[1, 1] / gamma
    else:
        b00, b01 = as00 * a00 + as01 * a01, as00 * a10 + as01 * a11
        b10, b11 = as10 * a00 + as11 * a01, as10 * a10 + as11 * a11
    # eq. (21)'s cross term lambda_bar H H^T with its (1 + 1/eps), the bracket with (1 + eps)
    c00, c01, c10, c11 = lam * HH[0, 0], lam * HH[0, 1], lam * HH[1, 0], lam * HH[1, 1]
    eps = eps_set
    if eps_auto:  # the minimiser sqrt(b / a) of (1 + eps) a + (1 + 1/eps) b
        a_tr, b_tr = b00 + b11, c00 + c11
        if b_tr > 0.0:
            if not a_tr > 0.0:  # the numpy form raises (zero division, sqrt of a negative)
                return FALLBACK, xo, Po, 0.0, 0.0
            eps = math.sqrt(b_tr / a_tr)
        else:
            eps = 0.0
    if eps > 0.0:
        f1, f2 = 1.0 + eps, 1.0 + 1.0 / eps
        o00, o01 = f1 * b00 + f2 * c00, f1 * b01 + f2 * c01
        o10, o11 = f1 * b10 + f2 * c10, f1 * b11 + f2 * c11
    elif c00 != 0.0 or c01 != 0.0 or c10 != 0.0 or c11 != 0.0:
        return FALLBACK, xo, Po, 0.0, 0.0  # robust_predict_cov raises ValueError
    else:
        o00, o01, o10, o11 = b00, b01, b10, b11
    o00, o01 = o00 + q * EE[0, 0], o01 + q * EE[0, 1]
    o10, o11 = o10 + q * EE[1, 0], o11 + q * EE[1, 1]
    Po[0, 0] = 0.5 * (o00 + o00)
    Po[0, 1] = 0.5 * (o01 + o10)
    Po[1, 0] = 0.5 * (o10 + o01)
    Po[1, 1] = 0.5 * (o11 + o11)
    # the mean, eq. (13): A x + B F_drive + E (f~ + F_grad), then the standstill clamp
    p0 = (a00 * x0 + a01 * x1) + (B[0] * fb + E[0] * fe)
    p1 = (a10 * x0 + a11 * x1) + (B[1] * fb + E[1] * fe)
    if clamp and not p1 >= 0.0:  # WenModel.standstill: stop inside the step, no reversing
        v0 = 0.0 if 0.0 > x1 else x1  # max(x1, 0.0)
        acc = (p1 - x1) / dt if dt > 0 else -math.inf
        travel = 0.5 * v0 * v0 / -acc if acc < 0 else 0.0
        p0, p1 = x0 + travel, 0.0
    xo[0], xo[1] = p0, p1
    if not _finite(p0, p1, Po[0, 0], Po[0, 1], Po[1, 1], gamma, eps):
        return FALLBACK, xo, Po, 0.0, 0.0
    return OK, xo, Po, gamma, eps


@jit
def _solve2(m00, m01, m10, m11, r00, r01, r10, r11):
    """``X = M^{-1} R`` for 2x2 ``M``, ``R`` (``R``'s columns the right-hand sides) by LU with
    partial pivoting, as LAPACK's ``gesv`` (a row swap only for a strictly larger pivot).
    ``(ok, x00, x01, x10, x11)``; ok False where ``gesv`` reports an exactly zero pivot."""
    if abs(m10) > abs(m00):
        m00, m01, m10, m11 = m10, m11, m00, m01
        r00, r01, r10, r11 = r10, r11, r00, r01
    if m00 == 0.0:
        return False, 0.0, 0.0, 0.0, 0.0
    lf = m10 / m00
    u11 = m11 - lf * m01
    if u11 == 0.0:
        return False, 0.0, 0.0, 0.0, 0.0
    z0, z1 = r10 - lf * r00, r11 - lf * r01
    x10, x11 = z0 / u11, z1 / u11
    return True, (r00 - m01 * x10) / m00, (r01 - m01 * x11) / m00, x10, x11


@jit
def update(x, P, y, C, R, abar, group, mask, corrected, gate, gate_accel, since):
    """``robust_steps.robust_update`` on the 2-state model with at most two channels, after
    ``FilterBase._gate_ok``'s gate (``gate``: inf = none; ``gate_accel``, ``since``):
    ``(status, x(k+1|k+1) (2,), Sigma(k+1|k+1) (2, 2))``, status :data:`GATE` when a
    received channel is outside it. ``corrected``: the minimiser of tr (22), else eq. (24)."""
    xo = np.empty(2)
    Po = np.empty((2, 2))
    m = y.shape[0]
    if m > 2 or C.shape[1] != 2:
        return FALLBACK, xo, Po
    x0, x1 = x[0], x[1]
    s00, s01, s10, s11 = P[0, 0], P[0, 1], P[1, 0], P[1, 1]
    # the gate: |nu_i| <= gate sqrt(S_ii) on every received channel, S_ii = C_i P C_i^T + R_ii
    # + (C_i (a since^2 / 2, a since))^2 (not applied to a non-finite P, as _gate_ok)
    if math.isfinite(gate) and _finite(s00, s01, s10, s11):
        for i in range(m):
            if not mask[i]:
                continue
            c0, c1 = C[i, 0], C[i, 1]
            si = ((c0 * s00 * c0 + c0 * s01 * c1) + c1 * s10 * c0) + c1 * s11 * c1
            si = si + R[i, i]
            if gate_accel > 0.0 and since > 0.0:
                d = c0 * (0.5 * gate_accel * since * since) + c1 * (gate_accel * since)
                si = si + d * d
            if not abs(y[i] - (c0 * x0 + c1 * x1)) <= gate * math.sqrt(si):
                return GATE, xo, Po
    if not _finite(x0, x1, s00, s01, s10, s11):
        return FALLBACK, xo, Po
    # channels with abar = 0 never arrive: dropped (robust_update)
    n = 0
    k0 = k1 = 0
    for i in range(m):
        if abar[i] > 0.0:
            if n == 0:
                k0 = i
            else:
                k1 = i
            n += 1
    if n == 0:
        xo[0], xo[1] = x0, x1
        Po[0, 0], Po[0, 1], Po[1, 0], Po[1, 1] = s00, s01, s10, s11
        return OK, xo, Po
    # C Sigma, C Sigma C^T, N = Sigma C^T Abar: channel j in column j
    ca0, ca1 = C[k0, 0], C[k0, 1]
    ab0 = abar[k0] * 1.0
    cs00, cs01 = ca0 * s00 + ca1 * s10, ca0 * s01 + ca1 * s11
    q00 = cs00 * ca0 + cs01 * ca1
    n00, n10 = (s00 * ca0 + s01 * ca1) * ab0, (s10 * ca0 + s11 * ca1) * ab0
    if n == 1:
        pi00 = ab0  # min(abar, abar)
        r00 = R[k0, k0] * 1.0
        s_00 = q00 + r00
        den = pi00 * s_00 if corrected else s_00
        if den == 0.0:
            return FALLBACK, xo, Po  # solve: singular
        K00, K10 = n00 / den, n10 / den
        # I - K Abar C; inner = (Pi - abar abar^T) o (C Sigma C^T) + Pi o R, eq. (22)
        i00, i01 = 1.0 - K00 * (ab0 * ca0), 0.0 - K00 * (ab0 * ca1)
        i10, i11 = 0.0 - K10 * (ab0 * ca0), 1.0 - K10 * (ab0 * ca1)
        inner = (pi00 - ab0 * ab0) * q00 + pi00 * r00
        kn0, kn1 = K00 * inner, K10 * inner
        j00, j01, j10, j11 = kn0 * K00, kn0 * K10, kn1 * K00, kn1 * K10
        nu0 = y[k0] - (ca0 * x0 + ca1 * x1) if mask[k0] else 0.0
        p0, p1 = x0 + K00 * nu0, x1 + K10 * nu0
    else:
        cb0, cb1 = C[k1, 0], C[k1, 1]
        ab1 = abar[k1] * 1.0
        cs10, cs11 = cb0 * s00 + cb1 * s10, cb0 * s01 + cb1 * s11
        q01, q10 = cs00 * cb0 + cs01 * cb1, cs10 * ca0 + cs11 * ca1
        q11 = cs10 * cb0 + cs11 * cb1
        n01, n11 = (s00 * cb0 + s01 * cb1) * ab1, (s10 * cb0 + s11 * cb1) * ab1
        # Pi = E[alpha alpha^T]: abar_i within a packet (min, as packet_moments), else the
        # product
        pi00, pi11 = ab0, ab1
        if group[k0] == group[k1]:
            pi01 = ab0 if ab0 < ab1 else ab1
            pi10 = ab1 if ab1 < ab0 else ab0
        else:
            pi01, pi10 = ab0 * ab1, ab1 * ab0
        r00, r01, r10, r11 = R[k0, k0] * 1.0, R[k0, k1] * 1.0, R[k1, k0] * 1.0, R[k1, k1] * 1.0
        S00, S01, S10, S11 = q00 + r00, q01 + r01, q10 + r10, q11 + r11
        if corrected:  # K = Sigma C^T Abar (Pi o S)^{-1}
            d00, d01, d10, d11 = pi00 * S00, pi01 * S01, pi10 * S10, pi11 * S11
        else:  # eq. (24): K = Sigma C^T Abar S^{-1}
            d00, d01, d10, d11 = S00, S01, S10, S11
        # K^T = D^{-T} N^T (np.linalg.solve(D.T, N.T).T)
        ok, K00, K10, K01, K11 = _solve2(d00, d10, d01, d11, n00, n10, n01, n11)
        if not ok:
            return FALLBACK, xo, Po  # solve: singular
        e00, e01, e10, e11 = ab0 * ca0, ab0 * ca1, ab1 * cb0, ab1 * cb1  # Abar C
        i00 = 1.0 - (K00 * e00 + K01 * e10)
        i01 = 0.0 - (K00 * e01 + K01 * e11)
        i10 = 0.0 - (K10 * e00 + K11 * e10)
        i11 = 1.0 - (K10 * e01 + K11 * e11)
        in00 = (pi00 - ab0 * ab0) * q00 + pi00 * r00
        in01 = (pi01 - ab0 * ab1) * q01 + pi01 * r01
        in10 = (pi10 - ab1 * ab0) * q10 + pi10 * r10
        in11 = (pi11 - ab1 * ab1) * q11 + pi11 * r11
        kn00, kn01 = K00 * in00 + K01 * in10, K00 * in01 + K01 * in11
        kn10, kn11 = K10 * in00 + K11 * in10, K10 * in01 + K11 * in11
        j00, j01 = kn00 * K00 + kn01 * K01, kn00 * K10 + kn01 * K11
        j10, j11 = kn10 * K00 + kn11 * K01, kn10 * K10 + kn11 * K11
        nu0 = y[k0] - (ca0 * x0 + ca1 * x1) if mask[k0] else 0.0
        nu1 = y[k1] - (cb0 * x0 + cb1 * x1) if mask[k1] else 0.0
        p0, p1 = x0 + (K00 * nu0 + K01 * nu1), x1 + (K10 * nu0 + K11 * nu1)
    # eq. (22) in its sum-of-PSD form: (I - K Abar C) Sigma (I - K Abar C)^T + K inner K^T
    h00, h01 = i00 * s00 + i01 * s10, i00 * s01 + i01 * s11
    h10, h11 = i10 * s00 + i11 * s10, i10 * s01 + i11 * s11
    o00 = (h00 * i00 + h01 * i01) + j00
    o01 = (h00 * i10 + h01 * i11) + j01
    o10 = (h10 * i00 + h11 * i01) + j10
    o11 = (h10 * i10 + h11 * i11) + j11
    xo[0], xo[1] = p0, p1
    Po[0, 0] = 0.5 * (o00 + o00)
    Po[0, 1] = 0.5 * (o01 + o10)
    Po[1, 0] = 0.5 * (o10 + o01)
    Po[1, 1] = 0.5 * (o11 + o11)
    if not _finite(p0, p1, Po[0, 0], Po[0, 1], Po[1, 1]):
        return FALLBACK, xo, Po
    return OK, xo, Po


_WARMED: list = []


def _signatures():
    """The kernels' one signature each, general enough for every array the filter passes:
    float64 of any layout (``A``: a model's cached, read-only matrices, slices of them,
    transposes) and either writability, integer and Boolean flags as numba converts them."""
    from numba import types as t

    f8, b1 = t.float64, t.boolean
    vec, mat = t.Array(f8, 1, "A", readonly=True), t.Array(f8, 2, "A", readonly=True)
    ints, flags = t.Array(t.int64, 1, "A", readonly=True), t.Array(b1, 1, "A", readonly=True)
    return ((vec, mat, mat, vec, vec, mat, f8, mat, mat, f8, b1, f8, f8, f8, f8, b1),
            (vec, mat, vec, mat, mat, vec, ints, flags, b1, f8, f8, f8))


def warm_up() -> None:
    """Compile (first run after a change of this file) or load from numba's cache the two
    kernels, once per process, each for one general signature (:func:`_signatures`), and then
    forbid numba to compile them again in this process: every later call converts its arguments
    to that signature (a contiguous writable array is a read-only ``A`` one without a copy).
    So a node pays this while it starts (``RobustFilter.__init__``), never in a reading's
    callback: numba compiles a new specialization for each new combination of layouts and
    writability it meets (the model's cached matrices are read-only, a slice is not
    contiguous), which was seconds of a loaded machine's CPU at a node's first reading or at a
    restored state's."""
    if not COMPILED or _WARMED:
        return
    for kernel, sig in zip((predict, update), _signatures()):
        kernel.compile(sig)
        kernel.disable_compile()
    _WARMED.append(True)
