"""One compiled call per braking-filter step: each algorithm's transition, the particle bank
(``numerics.bank``), its pruning or merging and the finiteness check, fused.

The bank step alone left each step a fixed 50-110 us of Python and numpy around it (the
transitions' fancy indexing, the pruning's partition, the merging's products, a dozen calls of
a microsecond each), which at the tens of Kalman filters the papers' ratios are measured at
is most of a step. Here every algorithm's step is one compiled call (two on a step where the
RBPF resamples: whether it does depends on the step's N_eff, and the resampling's uniform is
only drawn then, as the numpy form draws it):

* :func:`branching_step` -- SMA and GSMA: branching to the allowed children with their prior
  (Zheng 3.4-3.5), the bank, then pruning to the ``n_keep`` largest weights or merging the
  particles of each value into one Gaussian;
* :func:`discrete_step` -- the discrete RBPF's draw from its transition matrix (inverse CDF
  of uniforms drawn by the caller), then the bank; :func:`resample` its systematic
  resampling;
* :func:`random_walk_step` -- the random-walk RBPF's Gaussian step (normals drawn by the
  caller), reflected into the bounds, then the bank; :func:`resample` as above;
* :func:`qgrbpf_step` -- Q-GRBPF's redraw from the posterior's Gaussian and the pairing of
  the KF states along the principal axis (normals and their normal CDF from the caller), or
  its Gauss-Hermite form (``bank._gauss_hermite``), then the bank;
* :func:`kf_step` -- the exact reference KF: its augmented model, prediction and update.

Randomness stays in the caller's ``numpy.random.Generator``: the caller draws what a step
needs, in the order and the shapes the numpy form draws it, and passes the numbers in; so the
compiled and the numpy form give the same particles for the same seed. The arithmetic is the
numpy form's, elementwise in its order; where numpy sums in its own order (BLAS, einsum,
pairwise sums) the kernels sum in index order, within the rounding bound ``test_bank.py``
states. Ties in the pruning are broken by the lower index (``_BranchingFilter._after`` does
the same). Without numba (or with ``TRAIN_NO_JIT=1``) the filters run their numpy form; the
kernels' interpreted ``.py_func`` gives the compiled numbers bit for bit (``test_bank.py``).

Layout as ``numerics.bank``: particles on the leading axis, C-contiguous; ``idx`` (int64) the
value index of the discrete algorithms (empty for the continuous ones). Every step returns
``(status, theta, x, P, logw, idx, w, mean, cov, log evidence, N_eff, N at the estimate)``:
the set after the step, the estimate's weights and moments (before pruning, merging and
resampling); ``status`` ``bank.OK`` or the reason code (the inputs then come back unchanged).

Pure: numpy (+ numba when installed).
"""

from __future__ import annotations

import math

import numpy as np

from ..numerics import bank
from ..numerics.bank import OK, _all_finite, _bank_step, _gauss_hermite, _log_normalize
from ..numerics.jit import COMPILED, jit

__all__ = ["COMPILED", "NONFINITE", "KF_LOGLIK", "branching_step", "discrete_step",
           "random_walk_step", "qgrbpf_step", "resample", "kf_step", "warm_up"]

NONFINITE = 4  # "numerical failure: non-finite particle state" (the step's final check)
KF_LOGLIK = 5  # the KF's log likelihood infinite (BrakingKF._reduce's rejection)


@jit
def _finite_set(theta, x, P):
    return theta.shape[0] > 0 and _all_finite(x, P, theta)


@jit
def _gather(theta, x, P, a):
    """``theta[a], x[a], P[a]`` (new C-contiguous arrays)."""
    K = a.shape[0]
    n = x.shape[1]
    d = theta.shape[1]
    th = np.empty((K, d))
    xo = np.empty((K, n))
    Po = np.empty((K, n, n))
    for k in range(K):
        i = a[k]
        for b in range(d):
            th[k, b] = theta[i, b]
        for b in range(n):
            xo[k, b] = x[i, b]
            for c in range(n):
                Po[k, b, c] = P[i, b, c]
    return th, xo, Po


@jit
def _bank(theta, x, P, logw, tv, informative, do_predict, xp, xc, xv, kp, kc, kv, bu, qd, full,
          fh, y, H, R, rows, sel):
    """``RaoBlackwellFilter._bank_step``'s compiled call: each particle's braking rate its
    theta on an informative step, else the one shared gain ``fh``."""
    N, n = x.shape
    d = theta.shape[1]
    if informative:
        f = np.empty(N)
        for i in range(N):
            f[i] = theta[i, 0]
    else:
        f = fh
    xo = np.empty((N, n))
    Po = np.empty((N, n, n))
    lwo = np.empty(N)
    w = np.empty(N)
    mean = np.empty(n + d)
    cov = np.empty((n + d, n + d))
    status, logz, ess = _bank_step(x, P, f, do_predict, xp, xc, xv, kp, kc, kv, bu, qd, full,
                                   y, H, R, rows, sel, logw, theta, tv, xo, Po, lwo, w, mean,
                                   cov)
    return status, xo, Po, lwo, w, mean, cov, logz, ess


@jit
def _cell_tv(cell_var, idx):
    """``cell_var[idx][:, None, None]``: each discrete particle's cell variance."""
    tv = np.empty((idx.shape[0], 1, 1))
    for i in range(idx.shape[0]):
        tv[i, 0, 0] = cell_var[idx[i]]
    return tv


@jit
def _normalized(lw):
    """``lw - log_normalize(lw)[1]`` (status, the normalised log-weights)."""
    w = np.empty(lw.shape[0])
    status, logz = _log_normalize(lw, w)
    out = np.empty(lw.shape[0])
    for i in range(lw.shape[0]):
        out[i] = lw[i] - logz
    return status, out


# ----------------------------------------------------------------------------------------------
# SMA / GSMA


@jit
def _branch(values, ptr, col, logprior, theta, x, P, logw, idx):
    """``_BranchingFilter._transition``: every (particle, allowed child) pair in row-major
    order (``np.nonzero`` of the allowed rows), the child's log prior added to the parent's
    log-weight, normalised."""
    N = idx.shape[0]
    M = 0
    for i in range(N):
        M += ptr[idx[i] + 1] - ptr[idx[i]]
    parent = np.empty(M, dtype=np.int64)
    child = np.empty(M, dtype=np.int64)
    lw = np.empty(M)
    k = 0
    for i in range(N):
        j = idx[i]
        for q in range(ptr[j], ptr[j + 1]):
            c = col[q]
            parent[k] = i
            child[k] = c
            lw[k] = logw[i] + logprior[j, c]
            k += 1
    status, lw = _normalized(lw)
    th, xo, Po = _gather(theta, x, P, parent)
    for k in range(M):
        th[k, 0] = values[child[k]]
    return status, th, xo, Po, lw, child


@jit
def _prune(theta, x, P, logw, idx, n_keep):
    """The ``n_keep`` largest log-weights (ties: the lower index), in index order,
    renormalised."""
    order = np.argsort(-logw, kind="mergesort")  # stable: equal weights keep index order
    keep = np.sort(order[:n_keep])
    th, xo, Po = _gather(theta, x, P, keep)
    lw = np.empty(n_keep)
    ik = np.empty(n_keep, dtype=np.int64)
    for k in range(n_keep):
        lw[k] = logw[keep[k]]
        ik[k] = idx[keep[k]]
    status, lw = _normalized(lw)
    return status, th, xo, Po, lw, ik


@jit
def _merge(values, x, P, logw, idx):
    """``braking_discrete._merge_by_value``: the particles of each value collapsed into one
    Gaussian (weight sum, weighted mean, law of total covariance), sums in index order."""
    N, n = x.shape
    M = values.shape[0]
    w = np.empty(N)
    status, _ = _log_normalize(logw, w)
    acc = np.zeros(M)
    for i in range(N):
        acc[idx[i]] += w[i]
    K = 0
    for v in range(M):
        if acc[v] > 0:
            K += 1
    present = np.empty(K, dtype=np.int64)
    slot = np.full(M, -1, dtype=np.int64)
    k = 0
    for v in range(M):
        if acc[v] > 0:
            present[k] = v
            slot[v] = k
            k += 1
    W = np.empty(K)
    for k in range(K):
        W[k] = acc[present[k]]
    gn = np.zeros(N)
    xm = np.zeros((K, n))
    for i in range(N):
        k = slot[idx[i]]
        if k >= 0:
            gn[i] = w[i] / W[k]
            for a in range(n):
                xm[k, a] += gn[i] * x[i, a]
    Pa = np.zeros((K, n, n))
    Pb = np.zeros((K, n, n))
    dev = np.empty(n)
    for i in range(N):
        k = slot[idx[i]]
        if k < 0:
            continue
        g = gn[i]
        for a in range(n):
            dev[a] = x[i, a] - xm[k, a]
        for a in range(n):
            ga = g * dev[a]
            for b in range(n):
                Pa[k, a, b] += g * P[i, a, b]
                Pb[k, a, b] += ga * dev[b]
    Po = np.empty((K, n, n))
    for k in range(K):
        for a in range(n):
            for b in range(n):
                Po[k, a, b] = 0.5 * ((Pa[k, a, b] + Pb[k, a, b]) + (Pa[k, b, a] + Pb[k, b, a]))
    th = np.empty((K, 1))
    lw = np.empty(K)
    for k in range(K):
        th[k, 0] = values[present[k]]
        lw[k] = math.log(W[k])
    st2, lw = _normalized(lw)
    if status == OK:
        status = st2
    return status, th, xm, Po, lw, present


@jit
def branching_step(values, cell_var, ptr, col, logprior, merge, q_max, n_keep,
                   theta, x, P, logw, idx, due, informative, do_predict,
                   xp, xc, xv, kp, kc, kv, bu, qd, full, fh, y, H, R, rows, sel):
    """SMA / GSMA step (see the module docstring): branching if ``due``, the bank, then (if
    ``informative``) merging or pruning when the set exceeds ``q_max``. The children of value
    j are ``col[ptr[j]:ptr[j + 1]]`` (the allowed kernel's rows), their log prior
    ``logprior[j, child]``."""
    t0, x0, P0, l0, i0 = theta, x, P, logw, idx
    if due:
        status, theta, x, P, logw, idx = _branch(values, ptr, col, logprior, theta, x, P,
                                                 logw, idx)
        if status != OK:
            return (status, t0, x0, P0, l0, i0, np.empty(0), np.empty(0), np.empty((0, 0)),
                    0.0, 0.0, 0)
    tv = _cell_tv(cell_var, idx)
    status, xo, Po, lwo, w, mean, cov, logz, ess = _bank(
        theta, x, P, logw, tv, informative, do_predict, xp, xc, xv, kp, kc, kv, bu, qd, full,
        fh, y, H, R, rows, sel)
    n_est = xo.shape[0]
    if status == OK and informative:
        if merge:
            status, theta, xo, Po, lwo, idx = _merge(values, xo, Po, lwo, idx)
        elif lwo.shape[0] > q_max:
            status, theta, xo, Po, lwo, idx = _prune(theta, xo, Po, lwo, idx, n_keep)
    if status == OK and not _finite_set(theta, xo, Po):
        status = NONFINITE
    if status != OK:
        return (status, t0, x0, P0, l0, i0, np.empty(0), np.empty(0), np.empty((0, 0)),
                0.0, 0.0, 0)
    return status, theta, xo, Po, lwo, idx, w, mean, cov, logz, ess, n_est


# ----------------------------------------------------------------------------------------------
# discrete RBPF, random-walk RBPF and their resampling


@jit
def discrete_step(values, cell_var, cdf, uni, theta, x, P, logw, idx, due, informative,
                  do_predict, xp, xc, xv, kp, kc, kv, bu, qd, full, fh, y, H, R, rows, sel):
    """``DiscreteRBPF`` (prior proposal) step: if ``due``, each particle's next value from
    its row of the transition's CDF at the uniform ``uni[i]`` (``DiscreteRBPF._transition``),
    then the bank. Resampling, if N_eff calls for it: :func:`resample`."""
    t0, i0 = theta, idx
    if due:
        M = values.shape[0]
        N = idx.shape[0]
        idx = np.empty(N, dtype=np.int64)
        theta = np.empty((N, 1))
        for i in range(N):
            c = 0
            for m in range(M):
                if cdf[i0[i], m] < uni[i]:
                    c += 1
            idx[i] = min(c, M - 1)
            theta[i, 0] = values[idx[i]]
    tv = _cell_tv(cell_var, idx)
    status, xo, Po, lwo, w, mean, cov, logz, ess = _bank(
        theta, x, P, logw, tv, informative, do_predict, xp, xc, xv, kp, kc, kv, bu, qd, full,
        fh, y, H, R, rows, sel)
    if status == OK and not _finite_set(theta, xo, Po):
        status = NONFINITE
    if status != OK:
        return (status, t0, x, P, logw, i0, np.empty(0), np.empty(0), np.empty((0, 0)), 0.0,
                0.0, 0)
    return status, theta, xo, Po, lwo, idx, w, mean, cov, logz, ess, xo.shape[0]


@jit
def _reflect(v, lo, hi):
    """``braking_continuous._reflect`` of one value (``np.mod``'s floor remainder)."""
    width = hi - lo
    b = 2.0 * width
    a = v - lo
    r = np.fmod(a, b)
    if r != 0.0:
        if (b < 0) != (r < 0):
            r += b
    else:
        r = math.copysign(0.0, b)
    if r > width:
        r = b - r
    return lo + r


@jit
def random_walk_step(lo, hi, sqdt, L00, z, theta, x, P, logw, due, informative, do_predict,
                     xp, xc, xv, kp, kc, kv, bu, qd, full, fh, y, H, R, rows, sel):
    """``RandomWalkRBPF`` step (one parameter): if ``due``, ``theta + (sqrt(dt) z) L``
    reflected into ``[lo, hi]``, then the bank. Resampling: :func:`resample`."""
    t0 = theta
    if due:
        N = theta.shape[0]
        theta = np.empty((N, 1))
        for i in range(N):
            theta[i, 0] = _reflect(t0[i, 0] + (sqdt * z[i, 0]) * L00, lo, hi)
    status, xo, Po, lwo, w, mean, cov, logz, ess = _bank(
        theta, x, P, logw, np.zeros((0, 1, 1)), informative, do_predict, xp, xc, xv, kp, kc,
        kv, bu, qd, full, fh, y, H, R, rows, sel)
    if status == OK and not _finite_set(theta, xo, Po):
        status = NONFINITE
    empty = np.empty(0, dtype=np.int64)
    if status != OK:
        return (status, t0, x, P, logw, empty, np.empty(0), np.empty(0), np.empty((0, 0)),
                0.0, 0.0, 0)
    return status, theta, xo, Po, lwo, empty, w, mean, cov, logz, ess, xo.shape[0]


@jit
def resample(w, U, lw_n, theta, x, P, idx):
    """``smc.systematic_resample`` of the set (one batch element, as many draws as particles:
    ``u_j = (U + j) / N``, the first bin whose cumulative weight exceeds it), equal
    log-weights ``lw_n`` (= -log N, the numpy form's value)."""
    N = w.shape[0]
    cw = np.empty(N)
    acc = 0.0
    for i in range(N):
        acc += w[i]
        cw[i] = acc
    cw[N - 1] = 1.0
    a = np.empty(N, dtype=np.int64)
    i = 0
    for j in range(N):
        pos = (U + float(j)) / N
        while i < N and cw[i] <= pos:
            i += 1
        a[j] = min(i, N - 1)
    th, xo, Po = _gather(theta, x, P, a)
    ia = np.empty(idx.shape[0], dtype=np.int64)
    for j in range(idx.shape[0]):
        ia[j] = idx[a[j]]
    return th, xo, Po, np.full(N, lw_n), ia


# ----------------------------------------------------------------------------------------------
# Q-GRBPF


@jit
def _qg_redraw(lo, hi, qdt, min_var, z, uz, lw_n, theta, x, P, logw):
    """``QGRBPF._transition`` (one parameter): the weighted mean and variance of theta (eq.
    (7), (8)), widened by ``qdt`` and floored by ``min_var``; new thetas ``mu + sd z``
    reflected into the bounds (eq. (9)); each paired with the KF state of the old particle at
    the weighted quantile ``uz = Phi(z)`` along the axis (eq. (17), a stable sort)."""
    N0 = theta.shape[0]
    w = np.empty(N0)
    status, _ = _log_normalize(logw, w)
    if status != OK:
        return status, theta, x, P, logw
    mu = 0.0
    for i in range(N0):
        mu += w[i] * theta[i, 0]
    var = 0.0
    for i in range(N0):
        dv = theta[i, 0] - mu
        var += (w[i] * dv) * dv
    var = (var + qdt) + min_var
    sd = math.sqrt(max(var, 0.0))
    N = z.shape[0]
    th = np.empty((N, 1))
    for j in range(N):
        th[j, 0] = _reflect(mu + z[j, 0] * sd, lo, hi)
    proj = np.empty(N0)
    for i in range(N0):
        proj[i] = theta[i, 0] - mu
    order = np.argsort(proj, kind="mergesort")
    cdf = np.empty(N0)
    acc = 0.0
    for i in range(N0):
        acc += w[order[i]]
        cdf[i] = acc
    cdf[N0 - 1] = 1.0
    anc = np.empty(N, dtype=np.int64)
    for j in range(N):
        # searchsorted(cdf, uz, side="left"): the first bin whose cumulative weight reaches uz
        lo_i, hi_i = 0, N0
        while lo_i < hi_i:
            mid = (lo_i + hi_i) // 2
            if cdf[mid] < uz[j]:
                lo_i = mid + 1
            else:
                hi_i = mid
        anc[j] = order[min(lo_i, N0 - 1)]
    _, xo, Po = _gather(theta, x, P, anc)
    return OK, th, xo, Po, np.full(N, lw_n)


@jit
def qgrbpf_step(lo, hi, qdt, min_var, quadrature, z, uz, lw_n, gh_lw, theta, x, P, logw, due,
                informative, do_predict, xp, xc, xv, kp, kc, kv, bu, qd, full, fh, y, H, R,
                rows, sel):
    """``QGRBPF`` step (one parameter): if ``due``, the redraw and pairing (:func:`_qg_redraw`)
    or, with ``quadrature``, the Gauss-Hermite nodes ``z`` of the joint Gaussian with the
    log-weights ``gh_lw`` (``bank._gauss_hermite``); then the bank."""
    t0, x0, P0, l0 = theta, x, P, logw
    empty = np.empty(0, dtype=np.int64)
    status = OK
    if due:
        if quadrature:
            K, n = z.shape[0], x.shape[1]
            theta, x, P = np.empty((K, 1)), np.empty((K, n)), np.empty((K, n, n))
            status = _gauss_hermite(l0, t0[:, 0].copy(), x0, P0, z[:, 0].copy(), qdt, min_var,
                                    lo, hi, theta, x, P)
            logw = gh_lw.copy()
        else:
            status, theta, x, P, logw = _qg_redraw(lo, hi, qdt, min_var, z, uz, lw_n, t0, x0,
                                                   P0, l0)
    if status != OK:
        return (status, t0, x0, P0, l0, empty, np.empty(0), np.empty(0), np.empty((0, 0)),
                0.0, 0.0, 0)
    status, xo, Po, lwo, w, mean, cov, logz, ess = _bank(
        theta, x, P, logw, np.zeros((0, 1, 1)), informative, do_predict, xp, xc, xv, kp, kc,
        kv, bu, qd, full, fh, y, H, R, rows, sel)
    if status == OK and not _finite_set(theta, xo, Po):
        status = NONFINITE
    if status != OK:
        return (status, t0, x0, P0, l0, empty, np.empty(0), np.empty(0), np.empty((0, 0)),
                0.0, 0.0, 0)
    return status, theta, xo, Po, lwo, empty, w, mean, cov, logz, ess, xo.shape[0]


# ----------------------------------------------------------------------------------------------
# the exact reference KF


@jit
def kf_step(x, P, P0, P1, B0, B1, Qd, u, informative, gain, q_dt, do_predict, y, H, R, rows,
            sel):
    """``BrakingKF`` step: the augmented model of ``braking_model.augmented_model`` (f the
    fifth state; an uninformative step the shared ``gain`` and no f column), its prediction
    ``F x + b``, ``F P F^T + Q`` (symmetrised) and the sequential update of ``rows``
    (``numerics.bank``). Returns ``(status, x, P, log likelihood)``; ``x (1, 5)``,
    ``P (1, 5, 5)``; ``P0 .. Qd`` the model's affine pieces for this dt."""
    n = x.shape[1]
    m = n - 1
    xt = np.empty((n, 1))
    Pt = np.empty((n * n, 1))
    if do_predict:
        F = np.zeros((n, n))
        b = np.zeros(n)
        F[m, m] = 1.0
        for i in range(m):
            if informative:
                for j in range(m):
                    F[i, j] = P0[i, j]
                F[i, m] = P1[i, 3] * x[0, 3] + (B1[i, 0] * u[0] + B1[i, 1] * u[1])
                b[i] = B0[i, 0] * u[0] + B0[i, 1] * u[1]
            else:
                for j in range(m):
                    F[i, j] = P0[i, j] + gain * P1[i, j]
                b[i] = (B0[i, 0] + gain * B1[i, 0]) * u[0] + (B0[i, 1] + gain * B1[i, 1]) * u[1]
        FP = np.zeros((n, n))
        for i in range(n):
            acc = 0.0
            for j in range(n):
                acc += F[i, j] * x[0, j]
            xt[i, 0] = acc + b[i]
            for j in range(n):
                a2 = 0.0
                for k in range(n):
                    a2 += F[i, k] * P[0, k, j]
                FP[i, j] = a2
        Pp = np.empty((n, n))
        for i in range(n):
            for j in range(n):
                a2 = 0.0
                for k in range(n):
                    a2 += FP[i, k] * F[j, k]
                q = 0.0
                if i < m and j < m:
                    q = Qd[i, j]
                elif i == m and j == m and informative:
                    q = q_dt
                Pp[i, j] = a2 + q
        for i in range(n):
            for j in range(n):
                Pt[i * n + j, 0] = 0.5 * (Pp[i, j] + Pp[j, i])
    else:
        for i in range(n):
            xt[i, 0] = x[0, i]
            for j in range(n):
                Pt[i * n + j, 0] = P[0, i, j]
    ll = np.zeros(1)
    if rows.shape[0] > 0:
        bank._update_cols(xt, Pt, y, H, R, rows, sel, ll)
        if math.isnan(ll[0]):
            return bank.NAN_LIK, x, P, 0.0
        if not math.isfinite(ll[0]):
            return KF_LOGLIK, x, P, 0.0
    xo = np.empty((1, n))
    Po = np.empty((1, n, n))
    for i in range(n):
        xo[0, i] = xt[i, 0]
        for j in range(n):
            Po[0, i, j] = Pt[i * n + j, 0]
    if not _finite_set(np.zeros((1, 1)), xo, Po):
        return NONFINITE, x, P, 0.0
    return OK, xo, Po, ll[0]


# ----------------------------------------------------------------------------------------------

_WARMED: set = set()


def _example():
    """Arguments of the kernels with the types the filters pass (two particles, n = 4)."""
    x, P = np.zeros((2, 4)), np.tile(np.eye(4), (2, 1, 1))
    th, lw, idx = np.ones((2, 1)), np.full(2, -np.log(2.0)), np.zeros(2, dtype=np.int64)
    i0 = np.zeros(0, dtype=np.int64)
    common = (True, np.zeros(9, dtype=np.int64), i0, np.zeros(0), np.zeros(31, dtype=np.int64),
              i0, np.zeros(0), np.zeros(8), np.zeros(10), np.zeros(16, dtype=np.int64),
              np.ones(1), np.zeros((1, 3)), np.eye(3, 4), np.ones(3),
              np.arange(3, dtype=np.int64), np.array([0, 1, 3], dtype=np.int64))
    vals, cv = np.array([1.0, 0.5]), np.zeros(2)
    return x, P, th, lw, idx, common, vals, cv


def warm_up() -> None:
    """Compile (first run on a machine) or load from numba's cache the step kernels with the
    filters' argument types, once per process (see ``numerics.bank.warm_up``; ``./run setup``
    does it once after a change of this file)."""
    if not COMPILED or "steps" in _WARMED:
        return
    bank.warm_up()
    x, P, th, lw, idx, common, vals, cv = _example()
    ptr, col = np.array([0, 2, 4], dtype=np.int64), np.array([0, 1, 0, 1], dtype=np.int64)
    lp = np.full((2, 2), -np.log(2.0))
    for merge in (False, True):
        branching_step(vals, cv, ptr, col, lp, merge, 3, 2, th, x, P, lw, idx, True, True,
                       *common)
    cdf = np.array([[1.0, 1.0], [0.0, 1.0]])
    discrete_step(vals, cv, cdf, np.full(2, 0.5), th, x, P, lw, idx, True, True, *common)
    z = np.zeros((2, 1))
    random_walk_step(0.0, 1.0, 1.0, 0.1, z, th, x, P, lw, True, True, *common)
    resample(np.full(2, 0.5), 0.5, -np.log(2.0), th, x, P, idx)
    for quad in (False, True):
        qgrbpf_step(0.0, 1.0, 1e-3, 1e-8, quad, z, np.full(2, 0.5), -np.log(2.0), lw, th, x,
                    P, lw, True, True, *common)
    H5 = np.hstack([common[12], np.zeros((3, 1))])
    kf_step(np.zeros((1, 5)), np.eye(5)[None].copy(), np.eye(4), np.zeros((4, 4)),
            np.zeros((4, 2)), np.zeros((4, 2)), np.eye(4), np.zeros(2), True, 1.0, 1e-3, True,
            common[11], H5, common[13], common[14], common[15])
    _WARMED.add("steps")
