"""numerics.lsq_spline is scipy.interpolate's least-squares spline, values and design matrix bit
for bit, and diagnose's imports need neither scipy.interpolate nor scipy.optimize."""

import subprocess
import sys

import numpy as np
import pytest
from scipy.interpolate import BSpline, make_lsq_spline

from train_estimation.core.numerics import lsq_spline


def _stretch(rng, n, period):
    """Readings as residuals.spline_residuals fits them: jittered times, knots every 2 s."""
    x = np.cumsum(rng.uniform(0.5, 1.5, n) * period)
    y = np.sin(x / 3.0) * 4.0 + rng.normal(0.0, 0.05, n)
    w = 1.0 / np.sqrt(rng.uniform(0.001, 0.01, n))
    m = max(int((x[-1] - x[0]) // 2.0), 1)
    inner = x[0] + (x[-1] - x[0]) * np.arange(1, m) / m
    knots = np.r_[[x[0]] * 4, inner, [x[-1]] * 4]
    return x, y, w, knots


def _same_bits(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and a.tobytes() == b.tobytes()


@pytest.mark.parametrize("seed,n,period", [(0, 30, 0.2), (1, 400, 0.2), (2, 2500, 0.1),
                                           (3, 64, 0.5), (4, 1000, 0.04)])
def test_the_same_bits_as_scipy(seed, n, period):
    x, y, w, knots = _stretch(np.random.default_rng(seed), n, period)
    sp = make_lsq_spline(x, y, knots, k=3, w=w)
    c = lsq_spline.lsq_coefficients(x, y, knots, 3, w)
    assert _same_bits(c, sp.c)
    assert _same_bits(lsq_spline.evaluate(knots, c, 3, x), sp(x))
    beyond = np.r_[x[0] - 1.0, x, x[-1] + 1.0]  # extrapolated, as BSpline does by default
    assert _same_bits(lsq_spline.evaluate(knots, c, 3, beyond), sp(beyond))
    ref = BSpline.design_matrix(x, knots, 3).toarray()
    A = lsq_spline.design_matrix(x, knots, 3)
    assert _same_bits(A, ref)
    assert not np.signbit(A[A == 0]).any()
    c_unweighted = lsq_spline.lsq_coefficients(x, y, knots, 3)
    assert _same_bits(c_unweighted, make_lsq_spline(x, y, knots, k=3).c)


@pytest.mark.parametrize("spoil", ["nan_y", "inf_w", "x_outside", "x_decreasing",
                                   "knots_decreasing", "too_few"])
def test_refuses_what_scipy_refuses(spoil):
    x, y, w, knots = _stretch(np.random.default_rng(5), 50, 0.2)
    if spoil == "nan_y":
        y[7] = np.nan
    elif spoil == "inf_w":
        w[3] = np.inf
    elif spoil == "x_outside":
        knots = knots.copy()
        knots[-4:] = x[-2]
    elif spoil == "x_decreasing":
        x[10], x[11] = x[11], x[10]
    elif spoil == "knots_decreasing":
        knots = knots.copy()
        knots[5], knots[6] = knots[6], knots[5]
    elif spoil == "too_few":
        x, y, w = x[:3], y[:3], w[:3]
    with pytest.raises(ValueError):
        make_lsq_spline(x, y, knots, k=3, w=w)
    with pytest.raises(ValueError):
        lsq_spline.lsq_coefficients(x, y, knots, 3, w)


def test_diagnose_imports_no_interpolate_or_optimize():
    """The point of lsq_spline and numerics.brent: a diagnose process imports neither package
    (0.3-0.4 s of CPU at its start), and the spline module is scipy's own, loaded alone."""
    code = ("import sys\n"
            "import train_estimation.tools.diagnose, train_estimation.core.offline.diagnose\n"
            "from train_estimation.core.numerics import lsq_spline\n"
            "lsq_spline._dierckx()\n"
            "print(sorted(m for m in sys.modules if m.startswith(('scipy.interpolate', "
            "'scipy.optimize', 'scipy.linalg', 'scipy.sparse'))))\n"
            "print(lsq_spline._dierckx().__file__)\n"
            # scipy.interpolate imported after it still works as ever
            "import numpy as np\n"
            "from scipy.interpolate import make_lsq_spline\n"
            "x = np.linspace(0.0, 9.0, 40); t = np.r_[[0.0] * 4, 3.0, 6.0, [9.0] * 4]\n"
            "print(make_lsq_spline(x, np.sin(x), t).c.tobytes() == "
            "lsq_spline.lsq_coefficients(x, np.sin(x), t).tobytes())\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.splitlines()
    assert out[0] == "[]"
    assert "scipy/interpolate/_dierckx" in out[1]
    assert out[2] == "True"
