""":func:`train_core.motion.replay`'s loop compiled: the actuator's warm-up, its delay lines and
lag, the RK4 steps with the standstill rule and the optional power limit and low-adhesion
section, as one scalar loop (pure: numpy, numba when installed).

Every operation is that of :class:`~train_core.actuator.Actuator`, :class:`~train_core.motion.
Motion` and :class:`~train_core.dynamics.Dynamics` (``integrate``, ``_integrate_plain``,
``segment``, ``advance``, ``command``, ``step``, ``drive``, the RK4 and the gradient's
``bisect_right``), written out in the same order on the same doubles (numba's IEEE arithmetic,
no fast-math; Python's ``max(a, 0.0)`` as ``0.0 if 0.0 > a else a``): the same positions and
speeds bit for bit (tested against the interpreted replay). ``diagnose`` replays the recorded
commands open loop some 50 times per bag (the held-out gain and the replay plot: 0.3-0.5 s of
a process interpreted, about 2 us per step). A braking rate that varies in time (a Python
callable) and the simulator's hooks are not taken: the interpreted replay runs those.

The loop is compiled ahead of time (:mod:`train_core.aot`, :func:`build_aot`) where that was
built for this source, else by numba at the first call; without numba :func:`kernel` is None.
"""

from __future__ import annotations

import math

import numpy as np

from . import aot

_EPS = 1e-9  # s, as actuator.py and motion.py


def _activate(A, P, pt, pv, bt, bv):
    """Actuator._activate: A = [t, a, a_br, u_tr, u_br], P = [traction head, tail, brake
    head, tail] of the delay lines (pt, pv) and (bt, bv)."""
    t = A[0] + _EPS
    while P[0] < P[1] and pt[P[0]] <= t:
        A[3] = pv[P[0]]
        P[0] += 1
    while P[2] < P[3] and bt[P[2]] <= t:
        A[4] = bv[P[2]]
        P[2] += 1


def _next_switch(P, pt, bt):
    a = pt[P[0]] if P[0] < P[1] else math.inf
    b = bt[P[2]] if P[2] < P[3] else math.inf
    return a if a < b else b


def _command(A, P, pt, pv, bt, bv, t, a_tar, delay, bdelay):
    """Actuator.command; False where the commands are out of time order (it raises)."""
    t_act = t + delay
    if P[0] < P[1] and t_act < pt[P[1] - 1] - _EPS:
        return False
    pt[P[1]] = t_act
    pv[P[1]] = 0.0 if 0.0 > a_tar else a_tar
    P[1] += 1
    t_act = t + bdelay
    if P[2] < P[3] and t_act < bt[P[3] - 1] - _EPS:
        return False
    bt[P[3]] = t_act
    bv[P[3]] = 0.0 if 0.0 < a_tar else a_tar
    P[3] += 1
    _activate(A, P, pt, pv, bt, bv)
    return True


def _segment(A, P, pt, pv, bt, bv, B, h, f, tau):
    """Actuator.segment with its braking part tracked (its three values into B)."""
    ub = f * A[4]
    ue = A[3] + ub
    a0 = A[1]
    e = math.exp(-0.5 * h / tau)
    a_mid = ue + (a0 - ue) * e
    a_end = ue + (a_mid - ue) * e
    A[1] = a_end
    b0 = A[2]
    b_mid = ub + (b0 - ub) * e
    b_end = ub + (b_mid - ub) * e
    A[2] = b_end
    B[0] = b0
    B[1] = b_mid
    B[2] = b_end
    A[0] += h
    _activate(A, P, pt, pv, bt, bv)
    return a0, a_mid, a_end


def _advance(A, P, pt, pv, bt, bv, B, t_new, f, tau):
    """Actuator.advance."""
    while A[0] < t_new - _EPS:
        ns = _next_switch(P, pt, bt)
        t_stop = ns if ns < t_new else t_new
        _segment(A, P, pt, pv, bt, bv, B, t_stop - A[0], f, tau)
        A[0] = t_stop
        _activate(A, P, pt, pv, bt, bv)


def _grad(bounds, values, x):
    """GradientLookup: values[bisect_right(bounds, x)] (bisect's own loop)."""
    lo = 0
    hi = bounds.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if x < bounds[mid]:
            hi = mid
        else:
            lo = mid + 1
    return values[lo]


def _accel(D, bounds, values, x, v, a_hat):
    """Dynamics.accel; D = [kappa, ra, rb, rc, static, p_spec, has_p, start, end, factor,
    has_adhesion]."""
    if v < 0.0:
        v = 0.0
    return D[0] * a_hat - (D[1] + (D[2] + D[3] * v) * v) - _grad(bounds, values, x)


def _drive(D, x, v, a_hat, a_br):
    """Dynamics.drive (no hook)."""
    a_tr = a_hat - a_br
    p = D[5]
    if D[6] != 0.0 and a_tr > 0.0 and a_tr * v > p:
        a_tr = p / v
    if D[10] != 0.0 and D[7] <= x < D[8]:
        a_br = D[9] * a_br
    return a_tr + a_br


def _rk4(D, bounds, values, x, v, a0, a_mid, a_end, h):
    h2 = 0.5 * h
    k1 = _accel(D, bounds, values, x, v, a0)
    v2 = v + h2 * k1
    k2 = _accel(D, bounds, values, x + h2 * v, v2, a_mid)
    v3 = v + h2 * k2
    k3 = _accel(D, bounds, values, x + h2 * v2, v3, a_mid)
    v4 = v + h * k3
    k4 = _accel(D, bounds, values, x + h * v3, v4, a_end)
    return (x + h * (v + 2.0 * v2 + 2.0 * v3 + v4) / 6.0,
            v + h * (k1 + 2.0 * k2 + 2.0 * k3 + k4) / 6.0)


def _rk4_split(D, bounds, values, x, v, a0, a_mid, a_end, b0, b_mid, b_end, h):
    h2 = 0.5 * h
    k1 = _accel(D, bounds, values, x, v, _drive(D, x, v, a0, b0))
    x2, v2 = x + h2 * v, v + h2 * k1
    k2 = _accel(D, bounds, values, x2, v2, _drive(D, x2, v2, a_mid, b_mid))
    x3, v3 = x + h2 * v2, v + h2 * k2
    k3 = _accel(D, bounds, values, x3, v3, _drive(D, x3, v3, a_mid, b_mid))
    x4, v4 = x + h * v3, v + h * k3
    k4 = _accel(D, bounds, values, x4, v4, _drive(D, x4, v4, a_end, b_end))
    return (x + h * (v + 2.0 * v2 + 2.0 * v3 + v4) / 6.0,
            v + h * (k1 + 2.0 * k2 + 2.0 * k3 + k4) / 6.0)


def _step(S, D, bounds, values, h, a0, a_mid, a_end, ue, tau, split, b0, b_mid, b_end, ub):
    """Dynamics.step; S = [x, v, stopped]."""
    if S[2] != 0.0:
        a = _drive(D, S[0], 0.0, a0, b0) if split else a0
        if not D[0] * a - _grad(bounds, values, S[0]) > D[4]:
            return
        S[2] = 0.0
    if split:
        x1, v1 = _rk4_split(D, bounds, values, S[0], S[1], a0, a_mid, a_end, b0, b_mid, b_end,
                            h)
    else:
        x1, v1 = _rk4(D, bounds, values, S[0], S[1], a0, a_mid, a_end, h)
    if v1 > 0.0:
        S[0] = x1
        S[1] = v1
        return
    v0 = S[1]
    if v0 <= 0.0:
        S[1] = 0.0
        S[2] = 1.0
        return
    lo, vlo, hi, vhi = 0.0, v0, h, v1
    xr = S[0]
    for _ in range(4):
        r = lo + (hi - lo) * vlo / (vlo - vhi)
        r = 1e-12 if 1e-12 > r else r
        r = h if h < r else r
        er = math.exp(-0.5 * r / tau)
        am = ue + (a0 - ue) * er
        ae = ue + (am - ue) * er
        if split:
            bm = ub + (b0 - ub) * er
            xr, vr = _rk4_split(D, bounds, values, S[0], v0, a0, am, ae, b0, bm,
                                ub + (bm - ub) * er, r)
        else:
            xr, vr = _rk4(D, bounds, values, S[0], v0, a0, am, ae, r)
        if abs(vr) < 1e-10:
            break
        if vr > 0.0:
            lo, vlo = r, vr
        else:
            hi, vhi = r, vr
    S[0] = xr
    S[1] = 0.0
    S[2] = 1.0


def _integrate(A, P, pt, pv, bt, bv, B, S, D, bounds, values, t_start, t_next, max_step, f,
               tau, split):
    """Motion.integrate from ``t_start`` (its ``t``) to ``t_next``, without a visit."""
    span = t_next - t_start
    n = max(1, math.ceil(span / max_step - 1e-9))
    h = span / n
    if split:
        for _ in range(n):
            ue = A[3] + f * A[4]
            ub = f * A[4]
            a0, a_mid, a_end = _segment(A, P, pt, pv, bt, bv, B, h, f, tau)
            _step(S, D, bounds, values, h, a0, a_mid, a_end, ue, tau, True, B[0], B[1], B[2],
                  ub)
    else:  # Motion._integrate_plain
        e = math.exp(-0.5 * h / tau)
        for _ in range(n):
            ue = A[3] + f * A[4]
            a0 = A[1]
            a_mid = ue + (a0 - ue) * e
            a_end = ue + (a_mid - ue) * e
            A[1] = a_end
            A[0] += h
            ta = A[0] + _EPS
            if (P[0] < P[1] and pt[P[0]] <= ta) or (P[2] < P[3] and bt[P[2]] <= ta):
                _activate(A, P, pt, pv, bt, bv)
            if S[2] != 0.0:
                _step(S, D, bounds, values, h, a0, a_mid, a_end, ue, tau, False, 0.0, 0.0, 0.0,
                      0.0)
            else:
                x1, v1 = _rk4(D, bounds, values, S[0], S[1], a0, a_mid, a_end, h)
                if v1 > 0.0:
                    S[0] = x1
                    S[1] = v1
                else:
                    _step(S, D, bounds, values, h, a0, a_mid, a_end, ue, tau, False, 0.0, 0.0,
                          0.0, 0.0)
    A[0] = t_next
    _activate(A, P, pt, pv, bt, bv)


def _replay(wt, wa, ct, ca, t_rel, x0, v0, f, tau, delay, bdelay, warmup, D, bounds, values,
            max_step, xs, vs):
    """warm_actuator and replay's loop: ``wt, wa`` the commands before the start (times
    relative to it, those warm_actuator keeps), ``ct, ca`` those from it on, ``t_rel`` the
    output times; positions and speeds into ``xs, vs``. Returns 0, or 1 where the commands are
    out of time order (the interpreted replay raises)."""
    cap = wt.shape[0] + ct.shape[0] + 1
    pt, pv, bt, bv = np.empty(cap), np.empty(cap), np.empty(cap), np.empty(cap)
    P = np.zeros(4, np.int64)
    A = np.zeros(5)
    A[0] = -warmup
    B = np.zeros(3)
    for i in range(wt.shape[0]):
        t_i, a_i = wt[i], wa[i]
        if t_i >= -warmup:
            _advance(A, P, pt, pv, bt, bv, B, t_i, f, tau)
            if not _command(A, P, pt, pv, bt, bv, t_i, a_i, delay, bdelay):
                return 1
        else:
            A[3] = 0.0 if 0.0 > a_i else a_i
            A[4] = 0.0 if 0.0 < a_i else a_i
    _advance(A, P, pt, pv, bt, bv, B, 0.0, f, tau)
    A[0] = 0.0
    split = D[6] != 0.0 or D[10] != 0.0
    S = np.zeros(3)
    S[0] = x0
    S[1] = v0
    S[2] = 1.0 if v0 == 0.0 else 0.0
    t = 0.0  # Motion.t
    k = 0
    nc = ct.shape[0]
    for i in range(t_rel.shape[0]):
        tr = t_rel[i]
        while True:
            t_c = ct[k] if k < nc else math.inf
            t_next = tr
            if t_c < t_next:
                t_next = t_c
            ns = _next_switch(P, pt, bt)
            if ns < t_next:
                t_next = ns
            if t_next > t + _EPS:
                _integrate(A, P, pt, pv, bt, bv, B, S, D, bounds, values, t, t_next, max_step,
                           f, tau, split)
                t = t_next
            if k < nc and ct[k] <= t + _EPS:
                if not _command(A, P, pt, pv, bt, bv, t, ca[k], delay, bdelay):
                    return 1
                k += 1
                continue
            if t >= tr - _EPS:
                break
        xs[i] = S[0]
        vs[i] = S[1]
    return 0


_C1 = "f8[::1]"
SIGNATURE = (f"i8({_C1}, {_C1}, {_C1}, {_C1}, {_C1}, f8, f8, f8, f8, f8, f8, f8, {_C1}, "
             f"{_C1}, {_C1}, f8, {_C1}, {_C1})")
_HELPERS = ("_activate", "_next_switch", "_command", "_segment", "_advance", "_grad",
            "_accel", "_drive", "_rk4", "_rk4_split", "_step", "_integrate")
_KERNEL = None  # made at the first call of kernel()


def _jit_all():
    """The helpers and the loop as numba's jit dispatchers (module globals: what the loop and
    pycc compile against); None without numba."""
    from .jit import COMPILED, jit

    if not COMPILED:
        return None
    g = globals()
    for name in _HELPERS:
        if not hasattr(g[name], "py_func"):
            g[name] = jit(g[name])
    return jit(_replay)


def kernel():
    """The compiled loop (ahead of time, else numba's jit), or None without numba."""
    global _KERNEL
    if _KERNEL is None:
        mod = aot.load("replay_loop", [__file__])
        _KERNEL = mod.replay if mod is not None else (_jit_all() or False)
    return _KERNEL or None


def build_aot():
    """Compile :func:`_replay` ahead of time for :func:`kernel` (``./run setup``)."""
    fn = _jit_all()
    if fn is None:
        raise RuntimeError("compiling ahead of time needs numba")
    return aot.build("replay_loop", [__file__], {"replay": (fn.py_func, SIGNATURE)})
