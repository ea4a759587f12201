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

The scalar loops (:func:`_column_pass` and :func:`_column_pass_blocks`, :func:`_gain_loop`,
:func:`_kf2_loop`) are compiled ahead of time where that was built for this source
(``train_core.aot``, :func:`build_aot`: no numba at run time, which saves a short process such
as ``diagnose`` 0.6 s), else by numba at their first call (``numerics.jit``), else
interpreted.

Pure: numpy only.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

import numpy as np
from train_core import aot

from . import kalman
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
    Z_bal: np.ndarray | None = None  # (balise updates, 2) their whitened innovations (e /
    #   sqrt(S)) of columns 0 and 1: at s0, Z_bal[:, 0] + s0 Z_bal[:, 1]

    def loglik(self, z: np.ndarray) -> float:
        return -0.5 * (self.logdet + self.m * LOG2PI + z @ self.W @ z)


def augmented_kf(ev: Events, q: float, r_s: float, Bv, Bs, Md, Mv, Mb, q_held: float,
                 keep_innov: bool = False, update: np.ndarray | None = None,
                 q_per_event: np.ndarray | None = None,
                 use: np.ndarray | None = None) -> KFResult:
    """One Kalman filter run on x = (s, v) carrying p + 1 columns (column 0: the data with the
    fixed part of the model; columns 1..p: the parameters' sensitivities).

    Bv, Bs (n_ev, p+1): drift increments of the interval ending at event k; Md, Mv (n_ev, p+1):
    odometer measurement columns; Mb (n_ev, p+1): balise measurement columns (s0 is one).
    Process noise: ``q`` (``q_held`` where ``ev.held``), or ``q_per_event[k]`` for the
    interval ending at event k when given. The
    innovation at theta is E_k [1, theta]; W = sum E_k^T S_k^-1 E_k, accumulated as Z^T Z of the
    whitened innovations (Cholesky of each S_k). ``update[k]`` False skips event k's measurement
    (held-out data). ``use[k]`` False keeps event k's measurement in the filter's state but its
    innovation out of W, ``logdet`` and ``m`` (and its E0, E1, S_v NaN): the normal equations
    of one fold of the data, on a filter that has seen every reading (:func:`_result`).

    Two passes: the covariances and gains (scalars, the same for every column:
    :func:`_gain_pass`, shared by the calls at the same noise), then the columns and their
    whitened innovations (:func:`_column_pass`, compiled; without numba the columns as whole
    rows in a few array operations per event): the same operations on every element as a
    filter written out step by step (the results are bit for bit those of that filter;
    tested)."""
    n, p1 = ev.t.size, Bv.shape[1]
    gp = _gain_pass(ev, q, r_s, q_held, update, q_per_event)
    odo, bal = gp.odo, gp.bal
    Z = np.empty((gp.m, p1))  # the whitened innovations, two rows per odometer reading
    # the innovations: every column's for the loop without numba (its working rows); compiled,
    # only those of columns 0 and 1 (E0, E1 below), and none without keep_innov
    E = np.zeros((n, 2, p1) if not COMPILED else (n, 2, 2) if keep_innov else (1, 2, 1))
    if COMPILED:  # the columns and their whitening in one compiled loop, no stacked copies
        f8 = np.float64
        _column_pass(np.ascontiguousarray(gp.h, f8), np.ascontiguousarray(gp.code, np.int64),
                     *(np.ascontiguousarray(a, f8) for a in (Bs, Bv, Md, Mv, Mb)),
                     np.ascontiguousarray(ev.y_d, f8), np.ascontiguousarray(ev.y_v, f8),
                     np.ascontiguousarray(gp.K), gp.L, gp.row, Z, E, keep_innov)
    else:
        _column_pass_numpy(ev, gp, Bs, Bv, Md, Mv, Mb, E)
        L = gp.L
        z0 = E[odo, 0] / L[odo, 0, None]
        Z[gp.row[odo]] = z0
        Z[gp.row[odo] + 1] = (E[odo, 1] - L[odo, 1, None] * z0) / L[odo, 2, None]
        Z[gp.row[bal]] = E[bal, 0] / L[bal, 0, None]
    return _result(gp, Z, E, keep_innov, use)


def _result(gp, Z: np.ndarray, E: np.ndarray, keep_innov: bool,
            use: np.ndarray | None = None) -> KFResult:
    """The run's KFResult from its gains, whitened innovations ``Z`` and innovations ``E``
    (those of columns 0 and 1 read when ``keep_innov``); with ``use``, of the events it marks
    only (the filter's state still updated by every reading: a fold's normal equations whose
    innovations are white against the other fold's, where a filter that skipped the other
    fold's readings carried their state error into its own later innovations)."""
    odo, bal = gp.odo, gp.bal
    logdet, m, Zu = gp.logdet, gp.m, Z
    if use is not None:
        use = np.asarray(use, bool)
        odo, bal = odo[use[odo]], bal[use[bal]]
        rows = np.sort(np.concatenate([gp.row[odo], gp.row[odo] + 1, gp.row[bal]]))
        Zu = Z[rows]
        L = gp.L  # log det S_k from its Cholesky factor: 2 log(l00 l11), a balise's 2 log l0
        logdet = float(np.sum(2.0 * (np.log(L[odo, 0]) + np.log(L[odo, 2])))
                       + np.sum(2.0 * np.log(L[bal, 0])))
        m = int(rows.size)
    W = Zu.T @ Zu
    if not keep_innov:
        return KFResult(W=W, logdet=logdet, m=m)
    n = gp.h.size
    E0, E1 = np.zeros((n, 2)), np.zeros((n, 2))
    if use is not None:  # the updated readings out of the fold: no innovation of theirs
        upd = np.concatenate([gp.odo, gp.bal])
        out = upd[~use[upd]]
        E0[out] = E1[out] = np.nan
    E0[odo] = E[odo, ::-1, 0]  # (speed, distance)
    E1[odo] = E[odo, ::-1, 1]
    E0[bal, 0] = E1[bal, 0] = np.nan
    E0[bal, 1], E1[bal, 1] = E[bal, 0, 0], E[bal, 0, 1]
    S_v = np.full(n, np.nan)
    S_v[odo] = gp.S_v[odo]
    return KFResult(W=W, logdet=logdet, m=m, E0=E0, E1=E1, S_v=S_v,
                    Z_bal=Z[gp.row[bal], :2].copy())


def _step(first, c, xs, xv, hk, bs, bv, md, mv, mb, ydk, yvk, k00, k10, k01, k11, l0, l1, l2):
    """One column of an augmented filter at one event (code ``c``): predict, update, whiten,
    in the order both column passes share (their results bit for bit the same). Its inputs:
    the column's state ``xs, xv``, its entries ``bs, bv, md, mv, mb`` there, the readings
    ``ydk, yvk`` (added to column 0 only: ``first``), the gains and the Cholesky factor of S.
    Returns the new state, the whitened innovations (z0, z1) and the innovations (e0, e1).

    Scalars in and out, the event's entries read once per event by the caller: a step that
    took the arrays (Z, E, K, L, the readings) and read them per element compiled, inlined or
    not, to about 45 ns per element, 20x these 2 ns (measured on the foreign traction-cut bag's
    widest pass, 5,108 x 482, the same bits; its 78 column passes took 2.0 s instead of 0.1)."""
    s_ = xs + xv * hk
    s_ = s_ + bs
    v_ = xv + bv
    z0 = 0.0
    z1 = 0.0
    e0 = 0.0
    e1 = 0.0
    if c == 0:  # odometer reading
        es = -md - s_
        ev_ = -mv - v_
        if first:
            es += ydk
            ev_ += yvk
        s_ = s_ + k00 * es
        v_ = v_ + k10 * es
        s_ = s_ + k01 * ev_
        v_ = v_ + k11 * ev_
        z0 = es / l0
        z1 = (ev_ - l1 * z0) / l2
        e0 = es
        e1 = ev_
    elif c == 1:  # balise reading
        eb = -mb - s_
        if first:
            eb += ydk
        s_ = s_ + k00 * eb
        v_ = v_ + k10 * eb
        z0 = eb / l0
        e0 = eb
    return s_, v_, z0, z1, e0, e1


def _store(k, j, c, r, out, Z, E, keep, xs, xv):
    """:func:`_step`'s ``out`` written back: the column's state, its whitened innovations in
    rows ``r`` (and ``r + 1`` for an odometer reading) of ``Z``, and the innovations of
    columns 0 and 1 in ``E`` when ``keep``."""
    xs[j] = out[0]
    xv[j] = out[1]
    if c == 0:
        Z[r, j] = out[2]
        Z[r + 1, j] = out[3]
        if keep and j < 2:
            E[k, 0, j] = out[4]
            E[k, 1, j] = out[5]
    elif c == 1:
        Z[r, j] = out[2]
        if keep and j < 2:
            E[k, 0, j] = out[4]


def _column_pass(h, code, Bs, Bv, Md, Mv, Mb, yd, yv, K, L, row, Z, E, keep):
    """The columns of an augmented filter run and their whitened innovations ``Z`` (two rows
    per odometer reading, one per balise reading; ``E`` (n, 2, 2) the innovations of columns 0
    and 1 when ``keep``: no caller reads the others). Per element the operations of a filter
    written out step by step, in its order: predict (s += h v, then the drift), then the
    odometer update (innovation -M - x + y; gain columns K[:, :, 0] on distance and K[:, :, 1]
    on speed) or the balise update (distance only); whitening by the Cholesky factor L of
    S_k."""
    n, p1 = Bs.shape[0], Bs.shape[1]
    xs = -Md[0].copy()
    xv = -Mv[0].copy()
    xs[0] += yd[0]
    xv[0] += yv[0]
    for k in range(1, n):
        hk = h[k]
        c = code[k]
        r = row[k]
        ydk, yvk = yd[k], yv[k]
        k00, k10, k01, k11 = K[k, 0, 0], K[k, 1, 0], K[k, 0, 1], K[k, 1, 1]
        l0, l1, l2 = L[k, 0], L[k, 1], L[k, 2]
        for j in range(p1):
            out = _step(j == 0, c, xs[j], xv[j], hk, Bs[k, j], Bv[k, j], Md[k, j], Mv[k, j],
                        Mb[k, j], ydk, yvk, k00, k10, k01, k11, l0, l1, l2)
            _store(k, j, c, r, out, Z, E, keep, xs, xv)


def augmented_kf_blocks(ev: Events, q: float, r_s: float, fixed, drift=None, meas=None,
                        bal=None, q_held: float = 0.0, keep_innov: bool = False,
                        update: np.ndarray | None = None,
                        use: np.ndarray | None = None) -> KFResult:
    """:func:`augmented_kf` over the columns [fixed part, s0, drift columns..., measurement
    columns..., balise columns...] given as blocks instead of five (n_ev, p+1) matrices that
    are zero but for them: ``fixed = (fv, fs, md, mv, mb)`` column 0's drift increments (speed,
    distance), odometer measurement offsets (distance, speed) and balise offsets, each (n_ev,);
    ``drift = (Dv, Ds)``, ``meas = (Md, Mv)``, each (n_ev, k), and ``bal`` (n_ev, k), or None.
    s0 is column 1 (balise measurement 1). The same result, bit for bit, as
    :func:`augmented_kf` on the matrices filled in (tested): compiled, the kernel reads the
    blocks where it read the matrices, and a zero of the matrices as 0.0; a run of diagnose
    with 361 columns no longer fills and reads five 7 MB matrices of which two columns are
    not zero. Without the compiled kernel, the matrices are filled in."""
    n = ev.t.size
    f8 = np.float64
    blocks = []
    for pair, k in ((drift, 2), (meas, 2), ((bal,), 1)):
        if pair is None or pair[0] is None:
            pair = (np.zeros((n, 0)),) * k
        blocks.extend(np.ascontiguousarray(x, f8) for x in pair)
    Dv, Ds, Mdb, Mvb, Mbb = blocks
    if not COMPILED:  # the matrices filled in, as augmented_kf takes them
        a, b, c = Dv.shape[1], Mdb.shape[1], Mbb.shape[1]
        Bv, Bs, Md, Mv, Mb = (np.zeros((n, a + b + c + 2)) for _ in range(5))
        fv, fs, md, mv, mb = fixed
        Bv[:, 0], Bs[:, 0], Md[:, 0], Mv[:, 0], Mb[:, 0], Mb[:, 1] = fv, fs, md, mv, mb, 1.0
        Bv[:, 2:a + 2], Bs[:, 2:a + 2] = Dv, Ds
        Md[:, a + 2:a + b + 2], Mv[:, a + 2:a + b + 2] = Mdb, Mvb
        Mb[:, a + b + 2:] = Mbb
        return augmented_kf(ev, q, r_s, Bv, Bs, Md, Mv, Mb, q_held, keep_innov=keep_innov,
                            update=update, use=use)
    gp = _gain_pass(ev, q, r_s, q_held, update, None)
    p1 = 2 + Dv.shape[1] + Mdb.shape[1] + Mbb.shape[1]
    Z = np.empty((gp.m, p1))
    E = np.zeros((n, 2, 2) if keep_innov else (1, 2, 1))
    F = np.empty((5, n))
    F[0], F[1], F[2], F[3], F[4] = fixed[1], fixed[0], fixed[2], fixed[3], fixed[4]
    _column_pass_blocks(np.ascontiguousarray(gp.h, f8), np.ascontiguousarray(gp.code, np.int64),
                        F, Ds, Dv, Mdb, Mvb, Mbb, np.ascontiguousarray(ev.y_d, f8),
                        np.ascontiguousarray(ev.y_v, f8), np.ascontiguousarray(gp.K), gp.L,
                        gp.row, Z, E, keep_innov)
    return _result(gp, Z, E, keep_innov, use)


def _column_pass_blocks(h, code, F, Ds, Dv, Mdb, Mvb, Mbb, yd, yv, K, L, row, Z, E, keep):
    """:func:`_column_pass` on the columns as blocks (:func:`augmented_kf_blocks`): ``F``
    (5, n) column 0's (Bs, Bv, Md, Mv, Mb); column 1 balise measurement 1; then the drift
    columns (Ds, Dv), the measurement columns (Mdb, Mvb) and the balise columns (Mbb). Each
    element's operations are _column_pass's, in its order, on the entry the matrices would
    hold (0.0 where they hold nothing)."""
    n = h.size
    a2 = 2 + Ds.shape[1]
    ab2 = a2 + Mdb.shape[1]
    p1 = ab2 + Mbb.shape[1]
    xs = np.empty(p1)
    xv = np.empty(p1)
    for j in range(p1):
        md = 0.0
        mv = 0.0
        if j == 0:
            md = F[2, 0]
            mv = F[3, 0]
        elif a2 <= j < ab2:
            md = Mdb[0, j - a2]
            mv = Mvb[0, j - a2]
        xs[j] = -md
        xv[j] = -mv
    xs[0] += yd[0]
    xv[0] += yv[0]
    for k in range(1, n):
        hk = h[k]
        c = code[k]
        r = row[k]
        ydk, yvk = yd[k], yv[k]
        k00, k10, k01, k11 = K[k, 0, 0], K[k, 1, 0], K[k, 0, 1], K[k, 1, 1]
        l0, l1, l2 = L[k, 0], L[k, 1], L[k, 2]
        for j in range(p1):
            bs = 0.0
            bv = 0.0
            md = 0.0
            mv = 0.0
            mb = 0.0
            if j == 0:
                bs = F[0, k]
                bv = F[1, k]
                md = F[2, k]
                mv = F[3, k]
                mb = F[4, k]
            elif j == 1:
                mb = 1.0
            elif j < a2:
                bs = Ds[k, j - 2]
                bv = Dv[k, j - 2]
            elif j < ab2:
                md = Mdb[k, j - a2]
                mv = Mvb[k, j - a2]
            else:
                mb = Mbb[k, j - ab2]
            out = _step(j == 0, c, xs[j], xv[j], hk, bs, bv, md, mv, mb, ydk, yvk, k00, k10, k01,
                        k11, l0, l1, l2)
            _store(k, j, c, r, out, Z, E, keep, xs, xv)


def _column_pass_numpy(ev: Events, gp, Bs, Bv, Md, Mv, Mb, E):
    """:func:`_column_pass` without numba: the innovations ``E`` of all columns as whole rows,
    a few array operations per event (interpreted, a scalar loop over the columns would cost
    some 50 times more); the caller whitens them. The same operations on every element in the
    same order: equal bit for bit (tested)."""
    n, p1 = E.shape[0], E.shape[2]
    B = np.stack([Bs, Bv], axis=1).astype(float, copy=False)  # (n, 2, p1): drift of (s, v)
    # minus the measurement columns: (-M) - x is -x - M (rounding is symmetric)
    Mn = np.stack([Md, Mv], axis=1).astype(float, copy=False)
    np.negative(Mn, out=Mn)
    Mbn = -np.asarray(Mb, float)
    Y = np.stack([ev.y_d, ev.y_v], axis=1).astype(float, copy=False)
    x = Mn[0].copy()
    x[0, 0] += Y[0, 0]
    x[1, 0] += Y[0, 1]
    xs, xv = x[0], x[1]
    kc0 = np.ascontiguousarray(gp.K[:, :, 0:1])  # (n, 2, 1): gain on the distance innovation
    kc1 = np.ascontiguousarray(gp.K[:, :, 1:2])  # on the speed innovation
    tmp, tmp2 = np.empty(p1), np.empty((2, p1))
    add, multiply, subtract = np.add, np.multiply, np.subtract
    hs, codes = gp.h.tolist(), gp.code.tolist()
    for k in range(1, n):
        multiply(xv, hs[k], out=tmp)
        add(xs, tmp, out=xs)
        add(x, B[k], out=x)
        c = codes[k]
        if c == 0:  # odometer reading
            ek = E[k]
            subtract(Mn[k], x, out=ek)
            ek[:, 0] += Y[k]
            multiply(kc0[k], ek[0], out=tmp2)
            add(x, tmp2, out=x)
            multiply(kc1[k], ek[1], out=tmp2)
            add(x, tmp2, out=x)
        elif c == 1:  # balise reading
            eb = E[k, 0]
            subtract(Mbn[k], xs, out=eb)
            eb[0] += Y[k, 0]
            multiply(kc0[k], eb, out=tmp2)
            add(x, tmp2, out=x)


@dataclass
class _Gains:
    """The column-independent part of one :func:`augmented_kf` run (see :func:`_gain_pass`)."""

    h: np.ndarray  # (n,) s, interval ending at event k
    code: np.ndarray  # (n,) event k's update: 0 odometer reading, 1 balise reading, 2 none
    K: np.ndarray  # (n, 2, 2) gain of event k's update (0 where none; balise: column 0)
    L: np.ndarray  # (n, 3) Cholesky factor of S_k (l00, l10, l11; a balise: sqrt(s), 0, 0)
    S_v: np.ndarray  # (n,) innovation variance of the speed (odometer updates)
    row: np.ndarray  # (n,) the first row of event k's whitened innovations in Z
    odo: np.ndarray  # indices of the odometer updates
    bal: np.ndarray  # indices of the balise updates
    logdet: float
    m: int


_GAINS: dict = {}  # digest of the inputs -> _Gains, the most recent few
_GAINS_KEEP = 16


def _gain_pass(ev: Events, q: float, r_s: float, q_held: float, update, q_per_event) -> _Gains:
    """Covariances, gains, innovation variances and log det S of an augmented filter run:
    functions of the events' times, kinds, standstill flags and variances and of the noise
    only, so computed once for all the runs at the same noise (kept for the most recent
    inputs; the scalar recursion of kalman.predict_cov, odometer_update and balise_update)."""
    parts = (ev.t, ev.kind, ev.held, ev.r_v, q, r_s, q_held,
             None if update is None else np.asarray(update, bool),
             None if q_per_event is None else np.asarray(q_per_event, float))
    key = digest(*parts)
    hit = _GAINS.get(key)
    if hit is not None:
        return hit
    n = ev.t.size
    h = np.diff(ev.t, prepend=ev.t[0]).astype(np.float64)
    upd = np.ones(n, np.bool_) if update is None else np.asarray(update, np.bool_)
    use_qs = q_per_event is not None
    qs = np.asarray(q_per_event, np.float64) if use_qs else np.zeros(n)
    K, L, S_v, row, code = (np.zeros((n, 2, 2)), np.zeros((n, 3)), np.full(n, np.nan),
                            np.zeros(n, np.int64), np.full(n, 2, np.int8))
    logdet, m = _gain_loop(h, np.ascontiguousarray(ev.kind, np.int64),
                           np.ascontiguousarray(ev.held, np.bool_),
                           np.ascontiguousarray(ev.r_v, np.float64), np.ascontiguousarray(upd),
                           np.ascontiguousarray(qs), use_qs, float(q), float(r_s),
                           float(q_held), K, L, S_v, row, code)
    odo, bal = np.flatnonzero(code == 0), np.flatnonzero(code == 1)
    out = _Gains(h=h, code=code, K=K, L=L, S_v=S_v, row=row, odo=odo, bal=bal,
                 logdet=logdet, m=m)
    if len(_GAINS) >= _GAINS_KEEP:
        _GAINS.pop(next(iter(_GAINS)))
    _GAINS[key] = out
    return out


def _gain_loop(h, kind, held, rv, upd, qs, use_qs, q, r_s, q_held, K, L, S_v, row, code):
    """_gain_pass's recursion (kalman.predict_cov, odometer_update and balise_update, compiled
    with the loop): fills K, L, S_v, row and code in place and
    returns (log det of all S_k, scalar measurements)."""
    n = h.size
    p00, p01, p11 = r_s, 0.0, rv[0]
    logdet, m = 0.0, 0
    for k in range(1, n):
        hk = h[k]
        qk = qs[k] if use_qs else (q_held if held[k] else q)
        p00, p01, p11 = _predict_cov(p00, p01, p11, hk, qk)
        if not upd[k]:
            continue
        row[k] = m
        if kind[k] == 0:
            s00, s01, s11, det, _, gain, (p00, p01, p11) = _odometer_update(p00, p01, p11, r_s,
                                                                            rv[k])
            l00 = math.sqrt(s00)
            l10 = s01 / l00
            K[k, 0, 0], K[k, 0, 1], K[k, 1, 0], K[k, 1, 1] = gain
            L[k, 0], L[k, 1], L[k, 2] = l00, l10, math.sqrt(s11 - l10 * l10)
            S_v[k] = s11
            code[k] = 0
            logdet += math.log(det)
            m += 2
        else:
            sb, (k0, k1), (p00, p01, p11) = _balise_update(p00, p01, p11, rv[k])
            K[k, 0, 0], K[k, 1, 0] = k0, k1
            L[k, 0] = math.sqrt(sb)
            code[k] = 1
            logdet += math.log(sb)
            m += 1
    return logdet, m


def digest(*parts) -> bytes:
    """A digest of arrays (dtype, shape, bytes) and other values (their repr): the key of the
    memos of filter runs by their inputs (here and in diagnose's stages)."""
    hsh = hashlib.blake2b(digest_size=20)
    for x in parts:
        if isinstance(x, np.ndarray):
            hsh.update(str((x.dtype, x.shape)).encode())
            hsh.update(np.ascontiguousarray(x).tobytes())
        else:
            hsh.update(repr(x).encode())
        hsh.update(b"|")
    return hsh.digest()


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
    gives (tested equal). A noise fit calls it some 30 times: the recursion is one scalar loop
    (:func:`_kf2_loop`), compiled by numba where it is installed (``numerics.jit``)."""
    f8 = np.float64
    arrays = (np.ascontiguousarray(ev.t, f8), np.ascontiguousarray(ev.kind, np.int64),
              np.ascontiguousarray(ev.y_d, f8), np.ascontiguousarray(ev.y_v, f8),
              np.ascontiguousarray(ev.r_v, f8), np.ascontiguousarray(ev.held, np.bool_),
              np.ascontiguousarray(bv, f8), np.ascontiguousarray(bs, f8),
              np.ascontiguousarray(md, f8), np.ascontiguousarray(mv, f8))
    if not COMPILED:  # interpreted: Python floats index faster from lists than from arrays
        arrays = tuple(a.tolist() for a in arrays)
    logdet, m, w00, w01, w11 = _kf2_loop(*arrays, float(q), float(r_s), float(q_held))
    quad = w00 - w01 * w01 / w11 if w11 > 0 else w00
    return -0.5 * (logdet + m * LOG2PI + quad)


def _kf2_loop(t, kind, yd, yv, rv, held, bv, bs, md, mv, q, r_s, q_held):
    """kf2_loglik's recursion: (sum log det S_k, scalar measurements, W entries of the two
    columns), with kalman.predict_cov, odometer_update and balise_update on scalars (compiled
    with the loop by numba; interpreted without it)."""
    n = len(t)
    xs0, xv0 = yd[0] - md[0], yv[0] - mv[0]
    xs1 = xv1 = 0.0
    p00, p01, p11 = r_s, 0.0, rv[0]
    w00 = w01 = w11 = 0.0
    logdet, m = 0.0, 0
    t_prev = t[0]
    for k in range(1, n):
        tk = t[k]
        h = tk - t_prev
        t_prev = tk
        qk = q_held if held[k] else q
        xs0 += h * xv0 + bs[k]
        xv0 += bv[k]
        xs1 += h * xv1
        p00, p01, p11 = _predict_cov(p00, p01, p11, h, qk)
        if kind[k] == 0:
            _, _, _, det, (i00, i01, i11), (k00, k01, k10, k11), pn = _odometer_update(
                p00, p01, p11, r_s, rv[k])
            es0, ev0 = yd[k] - xs0 - md[k], yv[k] - xv0 - mv[k]
            es1, ev1 = -xs1, -xv1
            w00 += es0 * (i00 * es0 + i01 * ev0) + ev0 * (i01 * es0 + i11 * ev0)
            w01 += es0 * (i00 * es1 + i01 * ev1) + ev0 * (i01 * es1 + i11 * ev1)
            w11 += es1 * (i00 * es1 + i01 * ev1) + ev1 * (i01 * es1 + i11 * ev1)
            logdet += math.log(det)
            m += 2
            xs0 += k00 * es0 + k01 * ev0
            xv0 += k10 * es0 + k11 * ev0
            xs1 += k00 * es1 + k01 * ev1
            xv1 += k10 * es1 + k11 * ev1
            p00, p01, p11 = pn
        else:
            s, (k0, k1), (p00, p01, p11) = _balise_update(p00, p01, p11, rv[k])
            e0, e1 = yd[k] - xs0, -xs1 - 1.0
            w00 += e0 * e0 / s
            w01 += e0 * e1 / s
            w11 += e1 * e1 / s
            logdet += math.log(s)
            m += 1
            xs0 += k0 * e0
            xv0 += k1 * e0
            xs1 += k0 * e1
            xv1 += k1 * e1
    return logdet, m, w00, w01, w11


# The loops above as they run: compiled ahead of time, or by numba (kalman's scalar steps, which
# they call, compiled with them: the same functions, one definition), or interpreted. The
# interpreted originals stay reachable as ``PY``.
PY = {"column_pass": _column_pass, "column_pass_blocks": _column_pass_blocks,
      "gain_loop": _gain_loop, "kf2_loop": _kf2_loop}
_SOURCES = [__file__, kalman.__file__]
# numba's signatures of the compiled-ahead forms: the callers pass contiguous arrays of these
# types (np.ascontiguousarray with the dtype)
_C1, _C2, _C3 = "f8[::1]", "f8[:, ::1]", "f8[:, :, ::1]"
AOT_SIGNATURES = {
    "column_pass": f"void({_C1}, i8[::1], {', '.join([_C2] * 5)}, {_C1}, {_C1}, {_C3}, {_C2}, "
                   f"i8[::1], {_C2}, {_C3}, b1)",
    "column_pass_blocks": f"void({_C1}, i8[::1], {', '.join([_C2] * 6)}, {_C1}, {_C1}, {_C3}, "
                          f"{_C2}, i8[::1], {_C2}, {_C3}, b1)",
    "gain_loop": f"Tuple((f8, i8))({_C1}, i8[::1], b1[::1], {_C1}, b1[::1], {_C1}, b1, f8, f8, "
                 f"f8, {_C3}, {_C2}, {_C1}, i8[::1], i1[::1])",
    "kf2_loop": f"Tuple((f8, i8, f8, f8, f8))({_C1}, i8[::1], {', '.join([_C1] * 3)}, b1[::1], "
                f"{', '.join([_C1] * 4)}, f8, f8, f8)",
}
_AOT = aot.load("augmented_kf", _SOURCES)
if _AOT is not None:
    COMPILED = True
    _predict_cov, _odometer_update, _balise_update = predict_cov, odometer_update, balise_update
    _column_pass, _gain_loop, _kf2_loop = _AOT.column_pass, _AOT.gain_loop, _AOT.kf2_loop
    _column_pass_blocks = _AOT.column_pass_blocks
else:
    from .jit import COMPILED, jit

    _predict_cov = jit(predict_cov)
    # the column passes' shared step, inlined into both (its scalars: see _step's docstring)
    _step = jit(_step, inline=True)
    _store = jit(_store, inline=True)
    _odometer_update = jit(odometer_update)
    _balise_update = jit(balise_update)
    _column_pass, _gain_loop, _kf2_loop = jit(_column_pass), jit(_gain_loop), jit(_kf2_loop)
    _column_pass_blocks = jit(_column_pass_blocks)


def build_aot():
    """Compile the loops ahead of time for this source (``./run setup``; 10-30 s): the
    extension :data:`_AOT` loads from the next process on. Needs numba."""
    if _AOT is not None:
        return aot.build("augmented_kf", _SOURCES, {})  # there already: its path
    if not COMPILED:
        raise RuntimeError("compiling ahead of time needs numba (TRAIN_NO_JIT is set or numba "
                           "is missing)")
    return aot.build("augmented_kf", _SOURCES,
                     {k: (PY[k], AOT_SIGNATURES[k]) for k in PY})
