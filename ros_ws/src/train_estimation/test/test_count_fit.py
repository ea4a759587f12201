"""The count's clock fit as one compiled call (``numerics/count_fit.py``) against the numpy form
it replaced (kept here as the oracle), and its own interpreted form."""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest

from train_estimation.core.numerics import count_fit as cf
from train_estimation.core.numerics.clocks import (
    COUNT_ACCEL_SPAN,
    COUNT_LEARN,
    Rows,
    _accel,
    _count_fit,
)


def _median(a):
    h = a.size // 2
    p = np.sort(a)
    return float(p[h]) if a.size % 2 else float((p[h - 1] + p[h]) / 2.0)


def numpy_fit(links, lag_prior, half=COUNT_LEARN // 2):
    """The numpy form: whole-array operations, the weighted normal equations by a matrix
    product (the production form until the compiled call replaced it)."""
    q = np.array(links)
    R, L, v = q[:, 0].cumsum(), -np.log(q[:, 3]), q[:, 2]
    S = R + q[:, 1].cumsum()
    vmed = _median(v)

    def ends_sd(a, b, ms=(1, half)):
        sd = 1e-6
        for m in ms:
            e = R[m:] - R[:-m] - a * (S[m:] - S[:-m]) - b * (L[m:] - L[:-m])
            sd = max(sd, 1.4826 * _median(np.abs(e) * v[m:]))
        return sd

    M = np.vstack((S, L, R))
    M = np.vstack((np.ones(R.size), M - M.mean(axis=1, keepdims=True)))

    def solve(w, s):
        G = (M * w) @ M.T
        G -= np.outer(G[0], G[0]) / G[0, 0]
        a, b, c, ry, xy = G[1, 1], G[1, 2], G[2, 2], G[1, 3], G[2, 3]
        if lag_prior is not None:
            c += s * s / lag_prior[1]
            xy += s * s * lag_prior[0] / lag_prior[1]
        det = a * c - b * b
        if not det > 1e-12 * a * c:
            return ry / a, 0.0, (s * s / a, 0.0, math.inf)
        return (c * ry - b * xy) / det, (a * xy - b * ry) / det, \
            (s * s * c / det, -s * s * b / det, s * s * a / det)

    s = ends_sd(0.0, 0.0, (1,)) / (math.sqrt(2.0) * vmed)
    w = np.ones(R.size)
    a, b, _ = solve(w, s)
    e = R - a * S - b * L
    e = np.abs(e - _median(e))
    s = max(1.4826 * _median(e), 1e-9)
    w = np.minimum(1.0, 1.345 * s / np.maximum(e, 1e-300))
    a, b, cov = solve(w, s)
    sd = ends_sd(a, b)
    if sd / (math.sqrt(2.0) * vmed) > s:
        a, b, cov = solve(w, sd / (math.sqrt(2.0) * vmed))
    if not a < 1.0:
        return 0.0, 0.0, (math.inf, 0.0, math.inf), math.inf
    k = 1.0 / (1.0 - a)
    c_aa, c_ab, c_bb = cov
    c_ll = b * b * k ** 4 * c_aa + 2.0 * b * k ** 3 * c_ab + k * k * c_bb
    return a * k, b * k, (k ** 4 * c_aa, b * k ** 4 * c_aa + k ** 3 * c_ab, c_ll), sd


def _window(rng, kind):
    """Links of one window: 16-64 of them at 10 Hz, cruising or braking (a lag of the speed
    behind the count), a clock 1e-4 fast, count noise, now and then a glitch."""
    n = int(rng.integers(16, 65))
    v0 = rng.uniform(2.0, 40.0)
    acc = {"cruise": 0.0, "brake": -rng.uniform(0.2, 1.0), "accel": rng.uniform(0.1, 0.5)}[kind]
    t = 0.1 * np.arange(n + 1)
    v = np.maximum(v0 + acc * t, 1.5)
    lag = rng.uniform(0.0, 0.8)
    dt = 0.1 * (1.0 + 1e-4) + rng.normal(0.0, 0.002, n)
    r = -lag * np.log(v[1:] / v[:-1]) + rng.normal(0.0, 0.01, n)
    if rng.random() < 0.3:
        r[rng.integers(n)] += 0.3
    vs = v[1:] + rng.normal(0.0, 0.05, n)
    return [(float(a), float(b), float(0.5 * (c + d)), float(d))
            for a, b, c, d in zip(r, dt, v[:-1], vs)]


CASES = [(seed, kind, prior) for seed in range(40) for kind in ("cruise", "brake", "accel")
         for prior in (None, (0.3, 0.04))]


def _rel(x, y):
    return 0.0 if x == y else abs(x - y) / max(abs(x), abs(y))


@pytest.mark.parametrize("kind", ["cruise", "brake", "accel"])
def test_the_compiled_fit_is_the_numpy_forms_to_rounding(kind):
    """Rate, lag, covariance and scale agree with the numpy form within 1e-9 relative over 80
    windows of each kind, with the lag's prior and without. Not to the last bit: the numpy form
    sums its means pairwise and its normal equations in BLAS's order, the loop in order, and the
    normal equations of a cruise (ln v nearly one number) amplify those roundings (measured: at
    most 3.4e-12 relative on these windows); 1e-9 is far inside any of the clock's tests."""
    worst = 0.0
    for seed, k, prior in CASES:
        if k != kind:
            continue
        links = _window(np.random.default_rng(seed), kind)
        a, b = numpy_fit(links, prior), _count_fit(links, prior)
        for x, y in zip((a[0], a[1], *a[2], a[3]), (b[0], b[1], *b[2], b[3])):
            if math.isinf(x) or math.isinf(y):
                assert x == y, (seed, prior, a, b)
            else:
                worst = max(worst, _rel(x, y))
    assert worst <= 1e-9, worst


def test_the_interpreted_fit_is_the_compiled_one():
    """Without numba the same loop runs interpreted (``.py_func``): the same operations in the
    same order, so the same numbers but for the logarithm's last bit (numba's and Python's
    libm): measured 7e-16 relative at most on these windows, 1e-14 allowed."""
    for seed, kind, prior in CASES[::5]:
        links = _window(np.random.default_rng(seed), kind)
        q = np.array(links, float)
        pm, pv = prior if prior is not None else (math.nan, math.nan)
        c = cf._fit(q, pm, pv, COUNT_LEARN // 2)
        i = cf._fit.py_func(q, pm, pv, COUNT_LEARN // 2) if cf.COMPILED else c
        for x, y in zip(c, i):
            assert x == y or _rel(x, y) <= 1e-14, (seed, kind, c, i)


def test_a_count_that_does_not_move_is_no_clock():
    """A frozen count (the stamps' time all residual: ``a`` = 1) gives its samples no time:
    the fit is unknown (inf covariance and scale), as before any fit, not a division by zero."""
    links = [(0.1, 0.0, 10.0, 10.0 + 0.01 * (i % 3)) for i in range(32)]
    rate, lag, cov, sd = _count_fit(links, (0.0, 0.25))
    assert (rate, lag) == (0.0, 0.0) and cov == (math.inf, 0.0, math.inf) and sd == math.inf
    assert numpy_fit(links, (0.0, 0.25)) == (rate, lag, cov, sd)


def numpy_scan(q, lag, rate, m_max):
    """The level's scan in numpy (the production form until the compiled call replaced it)."""
    R = np.cumsum(q[:, 0])
    S = np.cumsum(q[:, 0] + q[:, 1])
    y = R + lag / (1.0 + rate) * np.log(q[:, 3])
    N = y.size
    x = S - S.mean()
    y = y - y.mean()
    sxx, sxy = float(x @ x), float(x @ y)
    m = np.arange(1, m_max + 1)
    px, py = np.cumsum(x[::-1])[:m_max], np.cumsum(y[::-1])[:m_max]
    den = m - m * m / N - px * px / sxx
    d = (py - px * sxy / sxx) / den
    z = d * d * den
    i = int(np.argmax(z))
    return float(np.min(q[:, 2])), float(S[-1] - S[0]), float(S[-1] - S[-m_max - 1]), \
        int(m[i]), float(d[i]), float(den[i]), float(z[i])


@pytest.mark.parametrize("step", [0.0, 0.2, -0.3])
def test_the_level_scan_is_the_numpy_forms(step):
    """The scan of the count's level (``StepWatch._level_test``) finds the same move at the
    same place as its numpy form, the numbers to 1e-9 relative (sums in order against pairwise
    and BLAS ones), over 30 windows of 128 links cruising with count noise, a step of the
    stamps ``step`` s from 12 links before the end."""
    for seed in range(30):
        rng = np.random.default_rng(seed)
        n, v = 128, rng.uniform(3.0, 40.0)
        e = rng.normal(0.0, 0.3 / v, n + 1)  # the count's white noise, s at the speed
        r = e[1:] - e[:-1]
        r[-12] += step
        q = np.column_stack((r, 0.1 + rng.normal(0.0, 1e-3, n), np.full(n, v),
                             v + rng.normal(0.0, 0.05, n), 100.0 + 0.1 * np.arange(n),
                             v * 0.1 * np.arange(n)))
        q = np.ascontiguousarray(q)
        lag, rate = rng.uniform(0.0, 0.5), rng.normal(0.0, 1e-4)
        a, b = numpy_scan(q, lag, rate, 20), cf.level_scan(q, lag, rate, 20)
        assert a[3] == b[3], (seed, a, b)  # the same place
        if step:
            assert a[3] == 12, (seed, a)
        for x, y in zip(a[:3] + a[4:], b[:3] + b[4:]):
            assert x == y or _rel(x, y) <= 1e-9, (seed, a, b)


def python_accel(links, span):
    """The acceleration's slope as the runner computed it in Python before the compiled call
    (``clocks._accel``), kept as the oracle: the newest links first, Python's ``sum``."""
    ts, vs, t = [], [], 0.0
    for r, dt, _, v in reversed(links):
        ts.append(t)
        vs.append(v)
        t -= r + dt
        if -t > span:
            break
    n = len(ts)
    if n < 3:
        return 0.0
    tm, vm = sum(ts) / n, sum(vs) / n
    sxx = sum((x - tm) ** 2 for x in ts)
    return sum((x - tm) * (y - vm) for x, y in zip(ts, vs)) / sxx if sxx > 0.0 else 0.0


@pytest.mark.skipif(sys.version_info >= (3, 12), reason="Python 3.12's sum() compensates")
def test_the_compiled_acceleration_is_pythons_to_the_bit():
    """``count_fit.accel`` (the train's acceleration over the count's last 2 s of links, which
    decides whether the level test runs) gives the bits of the Python form it replaced over
    120 windows cruising, braking and accelerating, whole and cut to 1-3 links, and so does its
    interpreted form; through :class:`~.clocks.Rows` (the runner's buffer, past its length,
    one row rewritten) as through a list."""
    for seed, kind, _ in CASES[::2]:
        links = _window(np.random.default_rng(seed), kind)
        for part in (links, links[:1], links[:2], links[:3]):
            want = python_accel(part, COUNT_ACCEL_SPAN)
            q = np.array(part, float).reshape(-1, 4)
            assert cf.accel(q, COUNT_ACCEL_SPAN) == want, (seed, kind, len(part))
            assert cf.accel.py_func(q, COUNT_ACCEL_SPAN) == want, (seed, kind, len(part))
            assert _accel(part, COUNT_ACCEL_SPAN) == want
        rows = Rows(4, 32)
        for row in links:
            rows.append(row)
        rows[-3] = links[0]
        kept = list(links[-32:])
        kept[-3] = links[0]
        assert list(rows) == kept and len(rows) == len(kept)
        assert np.array_equal(rows.array(), np.array(kept, float))
        assert _accel(rows, COUNT_ACCEL_SPAN) == python_accel(kept, COUNT_ACCEL_SPAN)
        assert _count_fit(rows, None) == _count_fit(kept, None)
        rows.clear()
        assert len(rows) == 0 and rows.array().shape == (0, 4)
