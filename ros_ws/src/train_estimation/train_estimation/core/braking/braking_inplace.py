"""Each braking-filter step as one compiled call on the filter's own buffers: the kernels of
``braking_compiled`` with their set read from and written back into preallocated arrays, and
the estimate's moments into one flat array, so that nothing is returned to box but two
integers.

Why. A compiled call costs its Python entry: about 0.2 us per array argument and, on the way
back, about 1 us per new array returned (numba wraps each in a numpy array). The kernels of
``braking_compiled`` take ~30 arguments and return a dozen arrays (the new set, the weights,
the moments): ~15 us of a step whose Kalman filters cost 0.3-0.6 us each, at the tens of
filters the papers' cost ratios are measured at. Here:

* the particle set lives in five buffers per filter (``theta (C, d)``, ``x (C, n)``,
  ``P (C, n, n)``, ``log w (C,)``, ``idx (C,)``; capacity C), the set of N particles their
  first N rows; a step reads them, runs the ``braking_compiled`` kernel (the same arithmetic:
  the numbers are those of that kernel to the last bit) and, only if it succeeded, copies the
  new set into the buffers' first N' rows (a rejected step leaves them as they were);
* the prediction's eleven maps are two arrays (:func:`pack_pred`: the integer and the float
  ones with their boundaries), packed once per dt (:class:`PredPack`), the command's entries
  written into a copy at each step;
* the estimate goes into ``E``: the mixture's mean ``(m,)`` and covariance ``(m, m)`` over
  (x, theta), the reported mean and covariance (``ri``: the report index), the log evidence,
  N_eff and the particle count at the estimate (:data:`E_TAIL`). ``Estimate`` reads its
  fields from it as views when they are asked for;
* a step returns ``(status, N')``: ``bank.OK`` and the new set's size, the kernel's reason
  code, or :data:`GROW` when N' exceeds the capacity (nothing written: the caller grows the
  buffers and calls again with the same random numbers).

Pure: numpy (+ numba when installed); without numba these run interpreted, with the numbers
of the compiled run (``test_bank.py``).
"""

from __future__ import annotations

import numpy as np

from ..numerics.bank import OK, _log_normalize
from ..numerics.jit import jit
from .braking_compiled import (
    branching_step,
    discrete_step,
    kf_step,
    qgrbpf_step,
    random_walk_step,
    resample,
)

__all__ = ["GROW", "E_TAIL", "e_size", "pack_pred", "PredPack", "pack_const", "pack_kf",
           "kf_command", "branching_run", "discrete_run", "random_walk_run", "qgrbpf_run",
           "resample_run", "kf_run", "warm_up"]

GROW = 6  # the new set exceeds the buffers' capacity: nothing written, grow and call again
E_TAIL = 3  # log evidence, N_eff, particle count at the estimate: the last entries of E


def e_size(m: int, r: int) -> int:
    """Length of the estimate array ``E`` for ``m`` mixture dimensions, ``r`` reported."""
    return m + m * m + r + r * r + E_TAIL


def pack_pred(pred, fh):
    """``(pi, pf)``: the prediction maps of ``BrakingModel.bank_pred`` ``(xp, xc, xv, kp, kc,
    kv, bu, qd, full)`` and the shared braking rate ``fh`` as one int64 and one float64 array
    (``pi[0:6]`` the boundaries of the integer maps xp, xc, kp, kc, full in ``pi``;
    ``pi[6:12]`` those of xv, kv, bu, qd, fh in ``pf``)."""
    xp, xc, xv, kp, kc, kv, bu, qd, full = pred
    ints = (xp, xc, kp, kc, full)
    flts = (xv, kv, bu, qd, fh)
    bi = np.cumsum([12] + [a.size for a in ints])
    bf = np.cumsum([0] + [a.size for a in flts])
    pi = np.concatenate([bi, bf] + [np.asarray(a, dtype=np.int64).ravel() for a in ints])
    pf = np.concatenate([np.asarray(a, dtype=np.float64).ravel() for a in flts])
    return pi.astype(np.int64), pf


class PredPack:
    """:func:`pack_pred`'s two arrays for one dt, with the entries that depend on the command
    ``u = (a_Tar, d)`` -- ``B0 u | B1 u`` and the shared braking rate ``fh`` -- written anew
    at each step (:meth:`arrays`).

    Why. A live node's command and its known acceleration d (resistance and gradient, which
    follow the train's speed and position) change at every step, while its dts repeat (a
    period's, and the ulps its stamps differ by). Packing the eleven maps takes ~12 us, as
    much as the rest of a small filter's step; their rows depend on dt alone, so the filters
    keep one of these per dt (``RaoBlackwellFilter._per_dt``) and write a step's command
    into a copy (~0.6 us)."""

    __slots__ = ("pi", "_pf", "_bu", "_fh")

    def __init__(self, pred, fh):
        """From ``BrakingModel.bank_pred``'s maps of this dt and a braking rate ``fh`` (the
        command's entries of this template are overwritten at each step)."""
        self.pi, self._pf = pack_pred(pred, fh)
        b = self.pi
        self._bu = slice(int(b[8]), int(b[9]))
        self._fh = slice(int(b[10]), int(b[11]))

    def arrays(self, bu, fh):
        """``(pi, pf)``: :func:`pack_pred`'s arrays of this dt's maps with ``bu`` (``B0 u | B1
        u``, as ``bank_pred`` computes it) and ``fh``, the very numbers it packs. ``pf`` is a
        new array: the template is shared by the filter's snapshots and never written."""
        pf = self._pf.copy()
        pf[self._bu] = bu
        pf[self._fh] = fh
        return self.pi, pf


@jit
def _pred(pi, pf):
    return (pi[pi[0]:pi[1]], pi[pi[1]:pi[2]], pf[pi[6]:pi[7]], pi[pi[2]:pi[3]],
            pi[pi[3]:pi[4]], pf[pi[7]:pi[8]], pf[pi[8]:pi[9]], pf[pi[9]:pi[10]],
            pi[pi[4]:pi[5]], pf[pi[10]:pi[11]])


@jit
def _write_estimate(mean, cov, ri, logz, ess, n_est, E):
    m = mean.shape[0]
    r = ri.shape[0]
    for a in range(m):
        E[a] = mean[a]
        for b in range(m):
            E[m + a * m + b] = cov[a, b]
    o = m + m * m
    for a in range(r):
        E[o + a] = mean[ri[a]]
        for b in range(r):
            E[o + r + a * r + b] = cov[ri[a], ri[b]]
    k = E.shape[0] - 3
    E[k] = logz
    E[k + 1] = ess
    E[k + 2] = float(n_est)


@jit
def _commit(theta, x, P, lw, idx, tb, xb, Pb, lb, ib):
    """The new set into the buffers' first rows (False: it does not fit, nothing written)."""
    N, n = x.shape
    if N > xb.shape[0]:
        return False
    d = theta.shape[1]
    for i in range(N):
        for a in range(d):
            tb[i, a] = theta[i, a]
        for a in range(n):
            xb[i, a] = x[i, a]
            for b in range(n):
                Pb[i, a, b] = P[i, a, b]
        lb[i] = lw[i]
    for i in range(idx.shape[0]):
        ib[i] = idx[i]
    return True


@jit
def _finish(out, tb, xb, Pb, lb, ib, ri, E):
    status, theta, x, P, lw, idx, w, mean, cov, logz, ess, n_est = out
    if status != OK:
        return status, 0
    if not _commit(theta, x, P, lw, idx, tb, xb, Pb, lb, ib):
        return GROW, x.shape[0]
    _write_estimate(mean, cov, ri, logz, ess, n_est, E)
    return OK, x.shape[0]


def pack_const(H, sel, ri, floats=(), ints=()):
    """``(kf, ki)``: a filter's constants as one float64 and one int64 array -- the
    measurement rows ``H (p, n)``, their selectors ``sel (p,)``, the report index ``ri`` and
    the algorithm's own tables (``floats``, ``ints``: 1-D or 2-D arrays, in the order its
    kernel reads them). ``ki[0:16]`` are the boundaries of the float segments in ``kf``,
    ``ki[16:32]`` those of the integer segments in ``ki`` (H first, then ``floats``; sel, ri,
    then ``ints``)."""
    fl = [np.asarray(H, dtype=np.float64)] + [np.asarray(a, dtype=np.float64) for a in floats]
    it = [np.asarray(sel, dtype=np.int64), np.asarray(ri, dtype=np.int64)] + [
        np.asarray(a, dtype=np.int64) for a in ints]
    if len(fl) > 15 or len(it) > 15:
        raise ValueError("pack_const: at most 15 float and 15 integer arrays")
    bf = np.zeros(16, dtype=np.int64)
    bf[1:len(fl) + 1] = np.cumsum([a.size for a in fl])
    bf[len(fl) + 1:] = bf[len(fl)]
    bi = np.zeros(16, dtype=np.int64)
    bi[1:len(it) + 1] = 32 + np.cumsum([a.size for a in it])
    bi[0] = 32
    bi[len(it) + 1:] = bi[len(it)]
    kf = np.concatenate([a.ravel() for a in fl])
    ki = np.concatenate([bf, bi] + [a.ravel() for a in it])
    return kf, ki


@jit
def _fseg(kf, ki, k):
    return kf[ki[k]:ki[k + 1]]


@jit
def _iseg(ki, k):
    return ki[ki[16 + k]:ki[17 + k]]


@jit
def _rows(kf, ki):
    """``(H, sel, ri)`` of :func:`pack_const`."""
    sel = _iseg(ki, 0)
    p = sel.shape[0]
    h = _fseg(kf, ki, 0)
    return h.reshape((p, h.shape[0] // p)), sel, _iseg(ki, 1)


@jit
def branching_run(kf, ki, merge, q_max, n_keep, tb, xb, Pb, lb, ib, N, due, informative,
                  do_predict, pi, pf, y, R, rows, E):
    """``braking_compiled.branching_step`` on the buffers' first ``N`` rows (module
    docstring); ``kf, ki``: :func:`pack_const` of the values, their cell variances, the log
    prior ``(M, M)``; the children's CSR rows ``ptr``, ``col``."""
    H, sel, ri = _rows(kf, ki)
    values = _fseg(kf, ki, 1)
    M = values.shape[0]
    logprior = _fseg(kf, ki, 3).reshape((M, M))
    xp, xc, xv, kp, kc, kv, bu, qd, full, fh = _pred(pi, pf)
    out = branching_step(values, _fseg(kf, ki, 2), _iseg(ki, 2), _iseg(ki, 3), logprior, merge,
                         q_max, n_keep, tb[:N], xb[:N], Pb[:N], lb[:N], ib[:N], due,
                         informative, do_predict, xp, xc, xv, kp, kc, kv, bu, qd, full, fh,
                         y.reshape((1, y.shape[0])), H, R, rows, sel)
    return _finish(out, tb, xb, Pb, lb, ib, ri, E)


@jit
def discrete_run(kf, ki, uni, tb, xb, Pb, lb, ib, N, due, informative, do_predict, pi, pf, y,
                 R, rows, E):
    """``braking_compiled.discrete_step`` on the buffers (module docstring); ``kf``: the
    values, their cell variances, the transition's CDF ``(M, M)``."""
    H, sel, ri = _rows(kf, ki)
    values = _fseg(kf, ki, 1)
    M = values.shape[0]
    xp, xc, xv, kp, kc, kv, bu, qd, full, fh = _pred(pi, pf)
    out = discrete_step(values, _fseg(kf, ki, 2), _fseg(kf, ki, 3).reshape((M, M)), uni,
                        tb[:N], xb[:N], Pb[:N], lb[:N], ib[:N], due, informative, do_predict,
                        xp, xc, xv, kp, kc, kv, bu, qd, full, fh, y.reshape((1, y.shape[0])),
                        H, R, rows, sel)
    return _finish(out, tb, xb, Pb, lb, ib, ri, E)


@jit
def random_walk_run(kf, ki, lo, hi, sqdt, L00, z, tb, xb, Pb, lb, ib, N, due, informative,
                    do_predict, pi, pf, y, R, rows, E):
    """``braking_compiled.random_walk_step`` on the buffers (module docstring)."""
    H, sel, ri = _rows(kf, ki)
    xp, xc, xv, kp, kc, kv, bu, qd, full, fh = _pred(pi, pf)
    out = random_walk_step(lo, hi, sqdt, L00, z, tb[:N], xb[:N], Pb[:N], lb[:N], due,
                           informative, do_predict, xp, xc, xv, kp, kc, kv, bu, qd, full, fh,
                           y.reshape((1, y.shape[0])), H, R, rows, sel)
    return _finish(out, tb, xb, Pb, lb, ib, ri, E)


@jit
def qgrbpf_run(kf, ki, lo, hi, qdt, min_var, quadrature, z, uz, lw_n, gh_lw, tb, xb, Pb, lb,
               ib, N, due, informative, do_predict, pi, pf, y, R, rows, E):
    """``braking_compiled.qgrbpf_step`` on the buffers (module docstring)."""
    H, sel, ri = _rows(kf, ki)
    xp, xc, xv, kp, kc, kv, bu, qd, full, fh = _pred(pi, pf)
    out = qgrbpf_step(lo, hi, qdt, min_var, quadrature, z, uz, lw_n, gh_lw, tb[:N], xb[:N],
                      Pb[:N], lb[:N], due, informative, do_predict, xp, xc, xv, kp, kc, kv, bu,
                      qd, full, fh, y.reshape((1, y.shape[0])), H, R, rows, sel)
    return _finish(out, tb, xb, Pb, lb, ib, ri, E)


@jit
def resample_run(U, lw_n, tb, xb, Pb, lb, ib, N, discrete):
    """``braking_compiled.resample`` of the buffers' first ``N`` rows, in place; the weights
    are ``braking_base._weights`` of the log-weights, as the bank step computed them (the
    same operations: the numbers the resampling saw before)."""
    w = np.empty(N)
    # bank's normalisation (the same loops); its checks do not fail here, the bank step
    # checked these log-weights -- if they did, NaN weights, as the loops alone would give
    if _log_normalize(lb[:N], w)[0] != OK:
        w[:] = np.nan
    idx = ib[:N] if discrete else ib[:0]
    th, x, P, lwo, ia = resample(w, U, lw_n, tb[:N], xb[:N], Pb[:N], idx)
    _commit(th, x, P, lwo, ia, tb, xb, Pb, lb, ib)


def pack_kf(P0, P1, B0, B1, Qd, u):
    """The exact KF's model pieces for one dt (``braking_model._affine_pieces``: m x m, m x
    m, m x 2, m x 2, m x m) and the command ``u (2,)`` as one float64 array."""
    return np.concatenate([np.ravel(a) for a in (P0, P1, B0, B1, Qd, u)]).astype(np.float64)


def kf_command(pk, u):
    """:func:`pack_kf`'s array ``pk`` (one dt's pieces, kept per dt: the command changes at
    every step of a live node, the pieces with dt alone) with the command ``u (2,)`` in place of
    its own: a new array (``pk`` is shared by the filter's snapshots and never written)."""
    out = pk.copy()
    out[-2:] = u
    return out


@jit
def kf_run(kf, ki, xb, Pb, pk, informative, gain, q_dt, do_predict, y, R, rows, E):
    """``braking_compiled.kf_step`` on the filter's buffers ``x (1, m + 1)``, ``P (1, m + 1,
    m + 1)`` (``kf, ki``: :func:`pack_const` of its rows and report index; ``pk``:
    :func:`pack_kf`); its estimate (N_eff 1, one particle) into ``E``."""
    H, sel, ri = _rows(kf, ki)
    m = xb.shape[1] - 1
    q = m * m
    P0 = pk[0:q].reshape((m, m))
    P1 = pk[q:2 * q].reshape((m, m))
    B0 = pk[2 * q:2 * q + 2 * m].reshape((m, 2))
    B1 = pk[2 * q + 2 * m:2 * q + 4 * m].reshape((m, 2))
    Qd = pk[2 * q + 4 * m:3 * q + 4 * m].reshape((m, m))
    u = pk[3 * q + 4 * m:3 * q + 4 * m + 2]
    status, xo, Po, ll = kf_step(xb, Pb, P0, P1, B0, B1, Qd, u, informative, gain, q_dt,
                                 do_predict, y.reshape((1, y.shape[0])), H, R, rows, sel)
    if status != OK:
        return status, 0
    n = xo.shape[1]
    for a in range(n):
        xb[0, a] = xo[0, a]
        for b in range(n):
            Pb[0, a, b] = Po[0, a, b]
    _write_estimate(xo[0], Po[0], ri, ll, 1.0, 1, E)
    return OK, 1


# ----------------------------------------------------------------------------------------------

_WARMED: set = set()


def warm_up() -> None:
    """Compile (first run on a machine) or load from numba's cache the in-place steps with the
    filters' argument types, once per process (as ``braking_compiled.warm_up``, which it
    runs first: these call its kernels)."""
    from ..numerics.jit import COMPILED
    from . import braking_compiled

    if not COMPILED or "inplace" in _WARMED:
        return
    braking_compiled.warm_up()
    x, P, th, lw, idx, common, vals, cv = braking_compiled._example()
    do, xp, xc, xv, kp, kc, kv, bu, qd, full, fh, y, H, R, rows, sel = common
    pi, pf = pack_pred((xp, xc, xv, kp, kc, kv, bu, qd, full), fh)
    cap = 8

    def bufs():
        tb, xb, Pb = np.empty((cap, 1)), np.empty((cap, 4)), np.empty((cap, 4, 4))
        lb, ib = np.empty(cap), np.zeros(cap, dtype=np.int64)
        tb[:2], xb[:2], Pb[:2], lb[:2], ib[:2] = th, x, P, lw, idx
        return tb, xb, Pb, lb, ib

    ri = np.array([0, 1, 2, 4], dtype=np.int64)
    tail = (do, pi, pf, y[0].copy(), R, rows, np.empty(e_size(5, 4)))
    ptr, col = np.array([0, 2, 4], dtype=np.int64), np.array([0, 1, 0, 1], dtype=np.int64)
    lp = np.full((2, 2), -np.log(2.0))
    kb = pack_const(H, sel, ri, (vals, cv, lp), (ptr, col))
    for merge in (False, True):
        branching_run(*kb, merge, 3, 2, *bufs(), 2, True, True, *tail)
    cdf = np.array([[1.0, 1.0], [0.0, 1.0]])
    discrete_run(*pack_const(H, sel, ri, (vals, cv, cdf)), np.full(2, 0.5), *bufs(), 2, True,
                 True, *tail)
    z = np.zeros((2, 1))
    kc = pack_const(H, sel, ri)
    random_walk_run(*kc, 0.0, 1.0, 1.0, 0.1, z, *bufs(), 2, True, True, *tail)
    resample_run(0.5, -np.log(2.0), *bufs(), 2, True)
    for quad in (False, True):
        qgrbpf_run(*kc, 0.0, 1.0, 1e-3, 1e-8, quad, z, np.full(2, 0.5), -np.log(2.0), lw,
                   *bufs(), 2, True, True, *tail)
    H5 = np.hstack([H, np.zeros((3, 1))])
    pk = pack_kf(np.eye(4), np.zeros((4, 4)), np.zeros((4, 2)), np.zeros((4, 2)), np.eye(4),
                 np.zeros(2))
    kf_run(*pack_const(H5, sel, ri), np.zeros((1, 5)), np.eye(5)[None].copy(), pk, True, 1.0,
           1e-3, True, y[0].copy(), R, rows, np.empty(e_size(5, 4)))
    _WARMED.add("inplace")
