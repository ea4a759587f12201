"""numerics.brent is scipy's bounded Brent search: the same evaluations and minimum, bit for bit."""

import math

import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from train_estimation.core.numerics.brent import minimize_bounded


def _objective(kind: int, c: float, w: float):
    if kind == 0:  # a parabola
        return lambda x: w * (x - c) ** 2
    if kind == 1:  # a minimum beyond the upper bound (the interval left of it)
        return lambda x: w * (x - c) ** 2 + math.sin(x)
    if kind == 2:  # flat stretches: ties between points
        return lambda x: round(abs(x - c), 1)
    if kind == 3:  # several local minima
        return lambda x: math.cos(w * x) + 0.01 * (x - c) ** 2
    # the diagnose noise fit's shape: a log-likelihood in log q, steep on one side
    return lambda x: math.exp(x - c) - (x - c)


def _cases():
    rng = np.random.default_rng(11)
    out = []
    for i in range(60):
        kind = i % 5
        c, w = rng.uniform(-5, 5), rng.uniform(0.1, 10.0)
        lo = c - rng.uniform(0.0, 10.0)
        hi = c + rng.uniform(0.0, 10.0)
        if kind == 1:
            hi = c - rng.uniform(0.5, 3.0)
            lo = hi - rng.uniform(1.0, 10.0)
        out.append((_objective(kind, c, w), lo, hi, float(rng.choice([1e-5, 1e-3, 0.1, 1.0])),
                    int(rng.choice([3, 14, 500]))))
    return out


@pytest.mark.parametrize("f,lo,hi,xatol,maxiter", _cases())
def test_the_same_search_as_scipy(f, lo, hi, xatol, maxiter):
    seen_ours, seen_scipy = [], []
    x, fx, n = minimize_bounded(lambda x: seen_ours.append(x) or f(x), lo, hi, xatol=xatol,
                                maxiter=maxiter)
    res = minimize_scalar(lambda x: seen_scipy.append(x) or f(x), bounds=(lo, hi),
                          method="bounded", options={"xatol": xatol, "maxiter": maxiter})
    assert seen_ours == [float(v) for v in seen_scipy]  # every point, bit for bit
    assert (x, fx, n) == (float(res.x), float(res.fun), res.nfev)


def test_a_nan_objective_ends_as_scipy_does():
    f = lambda x: math.nan if x > 1.0 else (x - 0.5) ** 2  # noqa: E731
    x, fx, n = minimize_bounded(f, 0.0, 3.0, xatol=1e-6, maxiter=40)
    res = minimize_scalar(f, bounds=(0.0, 3.0), method="bounded",
                          options={"xatol": 1e-6, "maxiter": 40})
    assert (x, n) == (float(res.x), res.nfev)
    assert fx == float(res.fun) or (math.isnan(fx) and math.isnan(res.fun))


def test_bad_bounds_are_refused():
    with pytest.raises(ValueError, match="finite"):
        minimize_bounded(abs, 0.0, math.inf)
    with pytest.raises(ValueError, match="exceeds"):
        minimize_bounded(abs, 1.0, 0.0)
