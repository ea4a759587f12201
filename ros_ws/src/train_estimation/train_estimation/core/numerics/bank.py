"""One compiled step for a bank of Kalman filters (the particles of a Rao-Blackwellised filter).

The numpy form of a particle filter's step (``kalman.predict``/``update``, ``smc.log_normalize``,
the mixture's moments in ``braking_base``) costs a fixed ~1 us per numpy call whatever the
number of particles N, and a step makes about a hundred such calls: at the particle counts the
papers use (tens to hundreds of Kalman filters) that fixed cost, not the arithmetic, is most of
the step. :func:`bank_step` does the same arithmetic for every particle in one compiled call
(``numerics.jit``: numba, no fast-math): the affine braking-model prediction, the sequential
scalar-row update with its log likelihood, the log-space reweighting and the moments of the
Gaussian mixture. Its cost is then what the papers counted: Kalman filters per step.

**Same arithmetic as the numpy form.** Every elementwise operation is the numpy form's, in the
same order, so the update's states and covariances are equal to the last bit
(``test_bank.py``). Where numpy hands a sum to a library whose order is not its own (BLAS
products, ``einsum``, pairwise ``sum``, its SIMD ``log``/``exp``) the loop sums in index order,
which differs from numpy's by rounding only: ``|compiled - numpy| <= 8 eps sum |terms|`` (the
bound ``test_bank.py`` checks; eps = 2^-52). The compiled and the interpreted kernel
(``.py_func``) agree to the last bit.

**Without numba** (not installed, or ``TRAIN_NO_JIT=1``) :data:`COMPILED` is False and the
callers keep the numpy form, which has no per-particle Python loop (an interpreted
``bank_step`` would cost ~10 us per particle).

Layout: particles on the leading axis, ``x (N, n)``, ``P (N, n, n)``, C-contiguous float64.

Pure: numpy (+ numba when installed).
"""

from __future__ import annotations

import math

import numpy as np

from . import smc
from .jit import COMPILED, jit

__all__ = ["COMPILED", "bank_step", "update", "log_normalize", "all_finite", "gauss_hermite",
           "warm_up", "csr", "LOG2PI", "OK", "BAD_WEIGHT", "ALL_INF", "NAN_LIK"]

LOG2PI = float(np.log(2.0 * np.pi))  # the numpy form's constant (kalman._LOG2PI)

# status codes of bank_step (the numpy form raises ValueError / rejects at the same points)
OK = 0
NAN_LIK = 1  # a NaN log likelihood: "numerical failure: NaN likelihood"
BAD_WEIGHT = 2  # a NaN or +inf log-weight (smc.log_normalize)
ALL_INF = 3  # every log-weight -inf (smc.log_normalize)


def _c(a):
    """``a`` as the compiled kernels take it: float64, C-contiguous, writeable (numba types a
    read-only array apart, and each new type is a new compile); a copy only if needed."""
    if a.dtype == np.float64 and a.flags.c_contiguous and a.flags.writeable:
        return a
    return np.array(a, dtype=np.float64, order="C")


def csr(K):
    """Rows of a small dense matrix as (start, column, value) arrays of its non-zero entries:
    the compiled products skip the zeros (the braking model's maps are mostly zeros)."""
    K = np.asarray(K, dtype=float)
    rows, cols = np.nonzero(K)  # row-major: each row's columns in increasing order
    ptr = np.zeros(K.shape[0] + 1, dtype=np.int64)
    np.cumsum(np.bincount(rows, minlength=K.shape[0]), out=ptr[1:])
    return ptr, cols.astype(np.int64), K[rows, cols]


@jit
def _to_cols(x, P, xt, Pt):
    """Particles to the last axis: ``xt (n, N)``, ``Pt (n n, N)`` (row-major vec of P)."""
    N, n = x.shape
    for i in range(N):
        for a in range(n):
            xt[a, i] = x[i, a]
            for b in range(n):
                Pt[a * n + b, i] = P[i, a, b]


@jit
def _from_cols(xt, Pt, x, P):
    N, n = x.shape
    for i in range(N):
        for a in range(n):
            x[i, a] = xt[a, i]
            for b in range(n):
                P[i, a, b] = Pt[a * n + b, i]


@jit
def _sparse_rows(ptr, col, val, src, out):
    """``out[k] = sum_q val[q] src[col[q]]`` over row k's non-zeros, in index order, every
    particle at once (the inner loop runs along the particles: contiguous, vectorised)."""
    N = src.shape[1]
    for k in range(out.shape[0]):
        for i in range(N):
            out[k, i] = 0.0
        for q in range(ptr[k], ptr[k + 1]):
            v = val[q]
            c = col[q]
            for i in range(N):
                out[k, i] += v * src[c, i]


@jit
def _predict_cols(xin, Pin, f, xp, xc, xv, kp, kc, kv, bu, qd, full, xt, Pt):
    """``BrakingModel.predict``'s Horner form (x' = (E x + B1 u) f + Phi0 x + B0 u, P' =
    (K2 P f + K1 P) f + K0 P + Qd), the products as sparse rows, particles on the last axis."""
    n, N = xin.shape
    m = qd.shape[0]
    X = np.empty((2 * n, N))
    Y = np.empty((3 * m, N))
    _sparse_rows(xp, xc, xv, xin, X)
    _sparse_rows(kp, kc, kv, Pin, Y)
    one = f.shape[0] == 1
    for a in range(n):
        for i in range(N):
            fi = f[0] if one else f[i]
            xt[a, i] = ((X[n + a, i] + bu[n + a]) * fi + X[a, i]) + bu[a]
    for c in range(n * n):
        u = full[c]
        for i in range(N):
            fi = f[0] if one else f[i]
            Pt[c, i] = ((Y[2 * m + u, i] * fi + Y[m + u, i]) * fi + Y[u, i]) + qd[u]


@jit
def _update_cols(xt, Pt, y, H, R, rows, sel, loglik):
    """``kalman.update``'s sequential scalar rows with the particles on the last axis (its own
    layout), in place; ``loglik (N,)`` with its summation order (log s over the rows, then
    e^2 / s)."""
    n, N = xt.shape
    Ph = np.empty((n, N))
    e = np.empty(N)
    s = np.empty(N)
    sl = np.zeros(N)
    sq = np.zeros(N)
    ny = y.shape[0]
    for r in range(rows.shape[0]):
        j = rows[r]
        k = sel[j]
        if k >= 0:
            for b in range(n):
                for i in range(N):
                    Ph[b, i] = Pt[k * n + b, i]
            for i in range(N):
                e[i] = y[i if ny > 1 else 0, j] - xt[k, i]
                s[i] = Ph[k, i] + R[j]
        else:
            for b in range(n):
                for i in range(N):
                    acc = 0.0
                    for a in range(n):
                        acc += H[j, a] * Pt[a * n + b, i]
                    Ph[b, i] = acc
            for i in range(N):
                xh = 0.0
                hph = 0.0
                for a in range(n):
                    xh += H[j, a] * xt[a, i]
                    hph += H[j, a] * Ph[a, i]
                e[i] = y[i if ny > 1 else 0, j] - xh
                s[i] = hph + R[j]
        for b in range(n):
            for i in range(N):
                xt[b, i] += Ph[b, i] * (e[i] / s[i])
        for a in range(n):
            for b in range(n):
                for i in range(N):
                    Pt[a * n + b, i] -= (Ph[a, i] * Ph[b, i]) / s[i]
        for i in range(N):
            if r == 0:
                sl[i] = math.log(s[i])
                sq[i] = e[i] * e[i] / s[i]
            else:
                sl[i] += math.log(s[i])
                sq[i] += e[i] * e[i] / s[i]
    nr = rows.shape[0]
    for i in range(N):
        loglik[i] = -0.5 * ((nr * LOG2PI + sl[i]) + sq[i])


@jit
def _update_bank(x, P, y, H, R, rows, sel, xo, Po, loglik):
    N, n = x.shape
    xt = np.empty((n, N))
    Pt = np.empty((n * n, N))
    _to_cols(x, P, xt, Pt)
    _update_cols(xt, Pt, y, H, R, rows, sel, loglik)
    _from_cols(xt, Pt, xo, Po)


def update(x, P, y, H, R, rows, sel):
    """``kalman.update`` compiled: copies of ``x (N, n)``, ``P (N, n, n)`` updated with the
    rows ``rows`` (int array, non-empty) of ``y ((1 or N), p)``; ``sel`` as
    ``kalman._selectors(H)``. Returns ``(x+, P+, loglik (N,))``."""
    xo = np.empty(x.shape)
    Po = np.empty(P.shape)
    ll = np.empty(x.shape[0])
    _update_bank(_c(x), _c(P), _c(y), _c(H), _c(R), rows, sel, xo, Po, ll)
    return xo, Po, ll


@jit
def _bank_step(x, P, f, do_predict, xp, xc, xv, kp, kc, kv, bu, qd, full,
               y, H, R, rows, sel, logw, theta, tv, xo, Po, lwo, w, mean, cov):
    """The fused step (see :func:`bank_step`); returns ``(status, log evidence, N_eff)``."""
    N, n = x.shape
    d = theta.shape[1]
    xin = np.empty((n, N))
    Pin = np.empty((n * n, N))
    _to_cols(x, P, xin, Pin)
    # 1. prediction and update of every particle, the log likelihood added to its weight
    if do_predict:
        xt = np.empty((n, N))
        Pt = np.empty((n * n, N))
        _predict_cols(xin, Pin, f, xp, xc, xv, kp, kc, kv, bu, qd, full, xt, Pt)
    else:
        xt, Pt = xin, Pin
    if rows.shape[0] > 0:
        _update_cols(xt, Pt, y, H, R, rows, sel, lwo)
        for i in range(N):
            if math.isnan(lwo[i]):
                return NAN_LIK, 0.0, 0.0
            lwo[i] = logw[i] + lwo[i]
    else:
        for i in range(N):
            lwo[i] = logw[i] + 0.0
    _from_cols(xt, Pt, xo, Po)
    # 2. smc.log_normalize: lw - log sum exp lw
    mx = -np.inf
    for i in range(N):
        v = lwo[i]
        if math.isnan(v) or v == np.inf:
            return BAD_WEIGHT, 0.0, 0.0
        if v > mx:
            mx = v
    if not math.isfinite(mx):
        return ALL_INF, 0.0, 0.0
    acc = 0.0
    for i in range(N):
        acc += math.exp(lwo[i] - mx)
    logz = mx + math.log(acc)
    for i in range(N):
        lwo[i] = lwo[i] - logz
    # 3. braking_base._weights of the normalised log-weights
    mx = -np.inf
    for i in range(N):
        if lwo[i] > mx:
            mx = lwo[i]
    acc = 0.0
    for i in range(N):
        w[i] = math.exp(lwo[i] - mx)
        acc += w[i]
    ess = 0.0
    for i in range(N):
        w[i] = w[i] / acc
        ess += w[i] * w[i]
    # 4. moments of the mixture over (x, theta), law of total covariance (braking_base._summary)
    m = n + d
    for a in range(m):
        mean[a] = 0.0
        for b in range(m):
            cov[a, b] = 0.0
    for i in range(N):
        wi = w[i]
        for a in range(n):
            mean[a] += wi * xo[i, a]
        for a in range(d):
            mean[n + a] += wi * theta[i, a]
    dev = np.empty(m)
    for i in range(N):
        wi = w[i]
        for a in range(n):
            dev[a] = xo[i, a] - mean[a]
        for a in range(d):
            dev[n + a] = theta[i, a] - mean[n + a]
        for a in range(m):
            wd = dev[a] * wi
            for b in range(m):
                cov[a, b] += wd * dev[b]
        for a in range(n):
            for b in range(n):
                cov[a, b] += wi * Po[i, a, b]
        if tv.shape[0] > 0:
            for a in range(d):
                for b in range(d):
                    cov[n + a, n + b] += wi * tv[i, a, b]
    for a in range(m):
        for b in range(a + 1, m):
            c = 0.5 * (cov[a, b] + cov[b, a])
            cov[a, b] = c
            cov[b, a] = c
    return OK, logz, 1.0 / ess


_NO_PREDICT = (np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0),
               np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0),
               np.zeros(0), np.zeros(0), np.zeros(1, dtype=np.int64))


def bank_step(x, P, y, H, R, rows, sel, logw, theta, tv=None, pred=None, f=None):
    """Prediction (``pred`` given), update, reweighting and mixture moments of a particle bank
    in one compiled call.

    ``pred``: the affine prediction maps of ``BrakingModel.bank_maps`` (CSR rows of ``x ->
    (Phi0 x, E x)`` and of ``vec P -> (K0, K1, K2) P``, ``(B0 u, B1 u)``, ``Qd``'s distinct
    entries, the index spreading them over a symmetric matrix) and ``f`` (N or 1) each
    particle's braking rate; None: no prediction (dt = 0). ``y ((1 or N), p)``, ``rows`` the
    used rows (int, may be empty), ``sel`` as ``kalman._selectors(H)``; ``logw (N,)``
    normalised log-weights, ``theta (N, d)``, ``tv (N, d, d)`` per-particle theta variance or
    None.

    Returns ``(status, x, P, logw, w, mean (n + d,), cov (n + d, n + d), log evidence,
    N_eff)``; ``status`` OK or the reason code (the numpy form's rejection).
    """
    N, n = x.shape
    d = theta.shape[1]
    xo = np.empty((N, n))
    Po = np.empty((N, n, n))
    lwo = np.empty(N)
    w = np.empty(N)
    mean = np.empty(n + d)
    cov = np.empty((n + d, n + d))
    if pred is None:
        pred, f, do = _NO_PREDICT, np.zeros(1), False
    else:
        do = True
    tv = np.zeros((0, d, d)) if tv is None else _c(tv)
    status, logz, ess = _bank_step(_c(x), _c(P), _c(f), do, *pred, _c(y), _c(H), _c(R), rows,
                                   sel, _c(logw), _c(theta), tv, xo, Po, lwo, w, mean, cov)
    return status, xo, Po, lwo, w, mean, cov, logz, ess


@jit
def _log_normalize(lw, w):
    """``smc.log_normalize`` of a 1-D array: status, log Z; ``w`` the normalised weights."""
    N = lw.shape[0]
    mx = -np.inf
    for i in range(N):
        v = lw[i]
        if math.isnan(v) or v == np.inf:
            return BAD_WEIGHT, 0.0
        if v > mx:
            mx = v
    if not math.isfinite(mx):
        return ALL_INF, 0.0
    acc = 0.0
    for i in range(N):
        w[i] = math.exp(lw[i] - mx)
        acc += w[i]
    for i in range(N):
        w[i] = w[i] / acc
    return OK, mx + math.log(acc)


_LN_ERRORS = {BAD_WEIGHT: "NaN or +inf log-weight", ALL_INF: "all log-weights are -inf"}


def log_normalize(logw):
    """``smc.log_normalize`` of a non-empty 1-D array in one compiled call (its checks and
    messages; the sums in index order, within their rounding bound of numpy's pairwise
    ones). Without numba: ``smc.log_normalize`` itself."""
    if not COMPILED:
        return smc.log_normalize(logw)
    lw = _c(np.asarray(logw))
    if lw.ndim != 1 or lw.size == 0:
        return smc.log_normalize(logw)
    w = np.empty(lw.size)
    status, logz = _log_normalize(lw, w)
    if status != OK:
        raise ValueError(_LN_ERRORS[status])
    return w, logz


@jit
def _all_finite(x, P, theta):
    for v in x.ravel():
        if not math.isfinite(v):
            return False
    for v in P.ravel():
        if not math.isfinite(v):
            return False
    for v in theta.ravel():
        if not math.isfinite(v):
            return False
    return True


def all_finite(x, P, theta) -> bool:
    """Every entry of the three arrays finite (one compiled pass; numpy without numba)."""
    if COMPILED:
        return bool(_all_finite(_c(x), _c(P), _c(theta)))
    return bool(np.isfinite(x).all() and np.isfinite(P).all() and np.isfinite(theta).all())


@jit
def _gauss_hermite(logw, th, x, P, z, qdt, min_var, lo, hi, th_out, x_out, P_out):
    """``QGRBPF._transition_quadrature`` (its formulas, sums in index order): the joint
    Gaussian of (x, theta) under the weights, its conditional at each node ``z_j``."""
    N, n = x.shape
    w = np.empty(N)
    status, _ = _log_normalize(logw, w)
    if status != OK:
        return status
    mu = 0.0
    for i in range(N):
        mu += w[i] * th[i]
    var = 0.0
    for i in range(N):
        d = th[i] - mu
        var += w[i] * (d * d)
    var = (var + qdt) + min_var
    xm = np.zeros(n)
    for i in range(N):
        for a in range(n):
            xm[a] += w[i] * x[i, a]
    cxt = np.zeros(n)
    S = np.zeros((n, n))
    for i in range(N):
        wd = w[i] * (th[i] - mu)
        for a in range(n):
            da = x[i, a] - xm[a]
            cxt[a] += wd * da
            wa = w[i] * da
            for b in range(n):
                S[a, b] += w[i] * P[i, a, b] + wa * (x[i, b] - xm[b])
    beta = np.empty(n)
    for a in range(n):
        beta[a] = cxt[a] / var
    Pc = np.empty((n, n))
    for a in range(n):
        for b in range(n):
            Pc[a, b] = S[a, b] - cxt[a] * beta[b]
    sd = math.sqrt(var)
    for j in range(z.shape[0]):
        t = min(max(mu + sd * z[j], lo), hi)
        th_out[j, 0] = t
        for a in range(n):
            x_out[j, a] = xm[a] + (t - mu) * beta[a]
            for b in range(n):
                P_out[j, a, b] = 0.5 * (Pc[a, b] + Pc[b, a])
    return OK


def gauss_hermite(logw, theta, x, P, z, qdt, min_var, lo, hi):
    """Compiled ``QGRBPF._transition_quadrature``: ``(theta (K, 1), x (K, n), P (K, n, n))``
    for the K nodes ``z``; raises ``smc.log_normalize``'s ValueError."""
    K, n = z.shape[0], x.shape[1]
    th_out, x_out, P_out = np.empty((K, 1)), np.empty((K, n)), np.empty((K, n, n))
    status = _gauss_hermite(_c(logw), _c(theta[:, 0]), _c(x), _c(P), _c(z), float(qdt),
                            float(min_var), float(lo), float(hi), th_out, x_out, P_out)
    if status != OK:
        raise ValueError(_LN_ERRORS[status])
    return th_out, x_out, P_out


_WARMED: set = set()
KERNELS = ("bank_step", "update", "log_normalize", "all_finite", "gauss_hermite")


def warm_up(*kernels: str) -> None:
    """Compile (first run on a machine: ~20-40 s on a loaded 2-core machine) or load from
    numba's cache (a few tenths of a second each) the named kernels (default: all of
    :data:`KERNELS`) with the types the filters pass, once per process. The filters warm the
    ones they use at construction, so that a node pays this while it starts, not in the
    callback of its first reading; ``./run setup`` warms all once after a change of this
    file, so that the tests and nodes find numba's cache filled."""
    todo = [k for k in (kernels or KERNELS) if k not in _WARMED]
    if not todo or not COMPILED:
        return
    x, P = np.zeros((2, 2)), np.tile(np.eye(2), (2, 1, 1))
    th, lw = np.ones((2, 1)), np.full(2, -np.log(2.0))
    H, R = np.eye(2), np.ones(2)
    rows, sel = np.arange(2, dtype=np.int64), np.arange(2, dtype=np.int64)
    ptr = np.zeros(5, dtype=np.int64)
    pred = (ptr, np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(10, dtype=np.int64),
            np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(4), np.zeros(3),
            np.zeros(4, dtype=np.int64))
    calls = {
        "bank_step": lambda: bank_step(x, P, np.zeros((1, 2)), H, R, rows, sel, lw, th, None,
                                       pred, np.ones(1)),
        "update": lambda: update(x, P, np.zeros((1, 2)), H, R, rows, sel),
        "log_normalize": lambda: log_normalize(lw),
        "all_finite": lambda: all_finite(x, P, th),
        "gauss_hermite": lambda: gauss_hermite(lw, th, x, P, np.zeros(1), 0.0, 1e-8, 0.0, 1.0),
    }
    for k in todo:
        calls[k]()
        _WARMED.add(k)
