"""The odometer's count as a clock: the fit of its recent links and the test of its level, one
compiled call each (pure; numba through :mod:`train_core.jit`, interpreted without it).

:class:`~train_estimation.core.numerics.clocks.StepWatch` times a stream without a sample
counter by its count (``clocks._count_link``: each link of two fused samples is its stamps'
difference less the count's time between them): at every fused reading of such a stream it
refits the model of :func:`count_fit` over the last 64 links and scans the last 128 for a move
of the level (:func:`level_scan`). As numpy calls these are about fifty small array
operations, 150-350 us a reading, the largest part of the runner's CPU on such a stream; as
compiled scalar loops 10-20 us, plus the links' conversion to an array.

The compiled fit and its numpy form agree to rounding, not to the last bit: numpy's means sum
pairwise and its matrix product sums in BLAS's order, the loop sums in order (tested against the
numpy form, ``test_count_fit.py``); the level's scan keeps numpy's order of its cumulative
sums. numba is imported with this module: ``clocks`` imports it only where a count is fitted,
so a process that reads a bag's clocks offline (``clock_fit``) does not pay numba's import.
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from .jit import COMPILED, jit

_WARMED: list = []


@jit
def _median(a):
    """The median of a 1-D float array (no NaN): the middle order statistic, or the two middle
    ones' sum halved (``clocks.median``'s number)."""
    b = np.sort(a)
    h = b.size // 2
    if b.size % 2:
        return b[h]
    return (b[h - 1] + b[h]) / 2.0


@jit
def _mean(a):
    """The mean of a 1-D float array summed in order (numpy's ``mean`` sums pairwise: the
    interpreted and the compiled form then differ)."""
    acc = 0.0
    for x in a:
        acc += x
    return acc / a.size


@jit
def _solve(M, w, s, pm, pv):
    """The weighted least squares of the cumulative residual ``M[3]`` on the stamps' time
    ``M[1]`` and ``M[2]`` = -ln v (each centred; ``M[0]`` ones for the intercept) with the lag's
    prior ``(pm, pv)`` (none where ``pv`` is NaN) in units of the residuals' scale ``s``:
    ``(a, b, cov aa, cov ab, cov bb)``; the rate alone (``b`` 0, its variance inf) where the speed
    did not change and there is no prior."""
    n = M.shape[1]
    G = np.zeros((4, 4))  # every weighted sum, then centred (the intercept taken out)
    for i in range(4):
        for j in range(i, 4):
            acc = 0.0
            for k in range(n):
                acc += M[i, k] * w[k] * M[j, k]
            G[i, j] = acc
    g0 = G[0, 0]
    a = G[1, 1] - G[0, 1] * G[0, 1] / g0
    b = G[1, 2] - G[0, 1] * G[0, 2] / g0
    c = G[2, 2] - G[0, 2] * G[0, 2] / g0
    ry = G[1, 3] - G[0, 1] * G[0, 3] / g0
    xy = G[2, 3] - G[0, 2] * G[0, 3] / g0
    if pv == pv:  # (lag - mean)^2 / var in units of the residuals' variance
        c += s * s / pv
        xy += s * s * pm / pv
    det = a * c - b * b
    if not det > 1e-12 * a * c:
        return ry / a, 0.0, s * s / a, 0.0, math.inf
    return (c * ry - b * xy) / det, (a * xy - b * ry) / det, s * s * c / det, \
        -s * s * b / det, s * s * a / det


@jit
def _ends_sd(R, S, L, v, a, b, m1, m2):
    """m, the robust scale of ``R``'s differences ``m`` links apart about the model (``m1`` and,
    where positive, ``m2``), at the later link's speed: the larger of the two, at least 1e-6."""
    sd = 1e-6
    n = R.size
    for m in (m1, m2):
        if m <= 0 or m >= n:
            continue
        e = np.empty(n - m)
        for i in range(n - m):
            e[i] = abs(R[i + m] - R[i] - a * (S[i + m] - S[i]) - b * (L[i + m] - L[i])) * v[i + m]
        sd = max(sd, 1.4826 * _median(e))
    return sd


@jit
def _fit(q, pm, pv, half):
    """The fit (:func:`count_fit`) of the links ``q`` (rows ``r s, count's time s, mean speed
    m/s, later speed m/s``): ``(rate, lag s, cov rate, cov rate-lag, cov lag, sd m)``."""
    n = q.shape[0]
    R, S, L, v = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    r = t = 0.0
    for i in range(n):
        r += q[i, 0]
        t += q[i, 1]
        R[i] = r
        S[i] = r + t
        L[i] = -math.log(q[i, 3])
        v[i] = q[i, 2]
    vmed = _median(v)
    # centred first: the weighted sums' own centring then cancels no digits (L of a cruise is
    # one number)
    ms, ml, mr = _mean(S), _mean(L), _mean(R)
    M = np.empty((4, n))
    for i in range(n):
        M[0, i] = 1.0
        M[1, i] = S[i] - ms
        M[2, i] = L[i] - ml
        M[3, i] = R[i] - mr
    rt2 = math.sqrt(2.0)
    s = _ends_sd(R, S, L, v, 0.0, 0.0, 1, 0) / (rt2 * vmed)
    w = np.ones(n)
    a, b, _, _, _ = _solve(M, w, s, pm, pv)
    e = np.empty(n)
    for i in range(n):
        e[i] = R[i] - a * S[i] - b * L[i]
    me = _median(e)
    for i in range(n):
        e[i] = abs(e[i] - me)
    s = max(1.4826 * _median(e), 1e-9)
    for i in range(n):  # Huber's weights at 1.345 robust scales
        w[i] = min(1.0, 1.345 * s / max(e[i], 1e-300))
    a, b, caa, cab, cbb = _solve(M, w, s, pm, pv)
    sd = _ends_sd(R, S, L, v, a, b, 1, half)
    if sd / (rt2 * vmed) > s:  # correlated residuals: the ends' noise scales it
        a, b, caa, cab, cbb = _solve(M, w, sd / (rt2 * vmed), pm, pv)
    if not a < 1.0:
        return 0.0, 0.0, math.inf, 0.0, math.inf, math.inf
    k = 1.0 / (1.0 - a)  # through the Jacobian of (a, b) -> (rate, lag), [[k^2, 0], [b k^2, k]]
    c_ll = b * b * k ** 4 * caa + 2.0 * b * k ** 3 * cab + k * k * cbb
    return a * k, b * k, k ** 4 * caa, b * k ** 4 * caa + k ** 3 * cab, c_ll, sd


@jit
def level_scan(q, lag, rate, m_max):
    """The scan of ``StepWatch._level_test`` over its steady stretch's links ``q`` (rows ``r s,
    count's time s, mean speed m/s, later speed m/s, stamp s, count m``): the cumulative
    residual less the speed's lag, ``y = R + lag / (1 + rate) ln v``, fitted by least squares
    on a line in the stamps' time ``S`` and a level move over the last ``m`` readings, for each
    ``m`` up to ``m_max`` at once from sums over the last ``m`` readings (the move by the Schur
    complement of the line's normal equations). Returns ``(slowest speed m/s, S's span over all
    links s, over the last m_max s, m, move d s, 1 / its variance in units of the level's, d^2
    times that)`` at the ``m`` whose move is largest in its standard errors (``m`` 0 where none
    is finite)."""
    n = q.shape[0]
    S, y = np.empty(n), np.empty(n)
    r = t = 0.0
    vmin = math.inf
    k = lag / (1.0 + rate)
    for i in range(n):
        r += q[i, 0]
        t += q[i, 0] + q[i, 1]
        S[i] = t
        y[i] = r + k * math.log(q[i, 3])
        vmin = min(vmin, q[i, 2])
    ms, my = _mean(S), _mean(y)
    sxx = sxy = 0.0
    for i in range(n):
        sxx += (S[i] - ms) * (S[i] - ms)
        sxy += (S[i] - ms) * (y[i] - my)
    px = py = 0.0
    best_m, best_d, best_den, best_z = 0, 0.0, 0.0, -math.inf
    for m in range(1, m_max + 1):
        px += S[n - m] - ms
        py += y[n - m] - my
        den = m - m * m / n - px * px / sxx  # 1 / the move's variance in units of the level's
        d = (py - px * sxy / sxx) / den
        z = d * d * den
        if z > best_z:
            best_m, best_d, best_den, best_z = m, d, den, z
    return vmin, S[n - 1] - S[0], S[n - 1] - S[n - m_max - 1], best_m, best_d, best_den, best_z


@jit
def accel(q, span):
    """m/s^2, ``clocks._accel``'s slope: the least squares slope of the latest links' speeds
    (``q[:, 3]``, rows oldest first as in :func:`_fit`) against their times, newest first
    back to the first beyond ``span`` s; 0 with fewer than 3. Summed in order, as Python's
    ``sum`` (3.11) sums its generator there."""
    m = q.shape[0]
    ts, vs = np.empty(m), np.empty(m)
    t = 0.0
    n = 0
    for i in range(m - 1, -1, -1):
        ts[n] = t
        vs[n] = q[i, 3]
        n += 1
        t -= q[i, 0] + q[i, 1]
        if -t > span:
            break
    if n < 3:
        return 0.0
    st = sv = 0.0
    for i in range(n):
        st += ts[i]
    for i in range(n):
        sv += vs[i]
    tm, vm = st / n, sv / n
    sxx = sxy = 0.0
    for i in range(n):
        sxx += (ts[i] - tm) ** 2
    for i in range(n):
        sxy += (ts[i] - tm) * (vs[i] - vm)
    return sxy / sxx if sxx > 0.0 else 0.0


def warm_up() -> None:
    """Compile (first run after a change of this file) or load from numba's cache the fit and
    the level's scan for their one signature, once per process, and forbid numba to compile
    them again (a node pays this while it starts,
    :class:`~train_estimation.core.numerics.clocks.StepWatch`, never in a reading's callback)."""
    if not COMPILED or _WARMED:
        return
    for kernel in (_fit, level_scan):
        kernel.compile("(float64[:, ::1], float64, float64, int64)")
        kernel.disable_compile()
    accel.compile("(float64[:, ::1], float64)")
    accel.disable_compile()
    _WARMED.append(True)


def count_fit(links, lag_prior: tuple | None, half: int) -> tuple[float, float, tuple, float]:
    """``(rate, lag s, covariance of (rate, lag), sd m)`` of the count's clock from recent
    fused pairs' links ``(r s, count's time dt s, mean speed m/s, the later sample's speed
    m/s)`` (``clocks._count_link``; tuples, or their (n, 4) float64 C-contiguous array): one
    linear model of the cumulative residual ``R`` (the inner counts cancel in it), ``R = rate
    D - lag ln v + c`` with ``D`` the count's time, fitted against the stamps' time and ``ln
    v`` (below).

    - ``rate``, the stamps' seconds per count second less one, holds the train clock's rate and
      the speed field's scale against the count (a speed from a radar or a second axle reads a
      few % off: each link's residual is then that share of its time).
    - ``lag``: a speed that lags its count by ``tau`` (a rate over a window of pulses, a
      filter) reads ``tau a`` off the count's while the train brakes or accelerates, so each
      link's count time is ``tau a / v`` off: ``-tau ln(v1 / v0)`` between two samples, which
      comes back to nothing when the speed does (taken as rate, it made false steps after
      every braking). Only speed changes identify it: ``lag_prior`` ``(mean, variance)`` holds
      what earlier windows learnt (``StepWatch.fused``) while the train cruises; None fits
      the window alone (covariance inf where its speed did not change).
    - Weighted least squares with that prior, once more with Huber weights (1.345 robust scales
      of the residuals) against the odd glitch; the covariance at the larger of the residuals'
      robust scale and the ends' noise below (a smoothed count's residuals are correlated, and
      their scale about the line then understates the slopes' errors).
    - ``sd``: the robust scale of ``R``'s differences about the model, in metres (times the
      speed): the noise of a chain's two ends, which ``StepWatch._count_resid`` bounds;
      the larger of neighbours' and of samples ``half`` apart (a smoothed count's noise is
      correlated from one sample to the next, and the speed's noise adds up along a chain).

    The stamps' time ``S``, not the count's, is the regressor: the count's noise is in both
    ``R`` and the count's time, and braking at one rate makes ``ln v`` nearly a line in time, so
    that the count's time fitted beside it took the noise in (a lag of 0.7 s fitted as 1.9 +-
    0.7 over a window braked at 0.8 m/s^2 with 0.3 m of count noise); ``R = c + a S - b L``,
    then ``rate = a / (1 - a)`` and ``lag = b / (1 - a)`` (the count's time is ``(S + lag L) /
    (1 + rate)``). A count that does not move while its speed reads on (frozen, ``a`` = 1) gives
    its samples no time at all, so it is no clock: unknown, as before any fit."""
    q = links if isinstance(links, np.ndarray) else \
        np.fromiter(itertools.chain.from_iterable(links), float, count=4 * len(links))
    pm, pv = lag_prior if lag_prior is not None else (math.nan, math.nan)
    rate, lag, c_rr, c_rl, c_ll, sd = _fit(q.reshape(-1, 4), float(pm), float(pv), int(half))
    return rate, lag, (c_rr, c_rl, c_ll), sd
