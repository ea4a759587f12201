"""chi2_logsf against exact tails: closed forms for k = 1, 2, 3 and even k, far past where
scipy's logsf underflows to -inf (where the strongest structure family used to be a tie)."""

import math

import numpy as np
import pytest
from scipy.special import gammaln, log_ndtr
from scipy.stats import chi2

from train_estimation.core.numerics.tails import chi2_logsf

FAR = (1.6e3, 5e3, 2e4, 1e5, 1e6)


def _exact_even(x, k):
    """log Q(s, z) for integer s = k / 2: e^-z sum_{j<s} z^j / j!."""
    s, z = k // 2, x / 2.0
    terms = [j * math.log(z) - gammaln(j + 1) for j in range(s)]
    return -z + float(np.logaddexp.reduce(terms))


def _exact_k1(x):
    # P(chi2_1 > x) = P(|N| > sqrt x) = 2 Phi(-sqrt x); log_ndtr stays finite in the tail
    return math.log(2.0) + float(log_ndtr(-math.sqrt(x)))


def _exact_k3(x):
    # Q(3/2, z) = Q(1/2, z) + z^(1/2) e^-z / Gamma(3/2)
    z = x / 2.0
    return float(np.logaddexp(_exact_k1(x), 0.5 * math.log(z) - z - gammaln(1.5)))


def test_scipy_underflows_where_this_does_not():
    assert chi2.logsf(FAR[0], 3) == -math.inf  # the reason for the module
    assert all(math.isfinite(chi2_logsf(x, k)) for x in FAR for k in (1, 3, 9, 20))


@pytest.mark.parametrize("x", FAR)
def test_two_degrees_of_freedom_is_exactly_half_the_statistic(x):
    assert chi2_logsf(x, 2) == pytest.approx(-x / 2.0, rel=1e-13)


@pytest.mark.parametrize("k", (4, 10, 20, 60))
@pytest.mark.parametrize("x", FAR)
def test_even_degrees_of_freedom_against_the_finite_sum(x, k):
    assert chi2_logsf(x, k) == pytest.approx(_exact_even(x, k), rel=1e-12)


@pytest.mark.parametrize("x", FAR)
def test_odd_degrees_of_freedom_against_the_normal_tail(x):
    # asymptotic series for half-integer s: its error is below its smallest term
    assert chi2_logsf(x, 1) == pytest.approx(_exact_k1(x), rel=1e-9)
    assert chi2_logsf(x, 3) == pytest.approx(_exact_k3(x), rel=1e-9)


def test_finite_values_are_scipys_and_the_order_of_strong_tests_is_kept():
    for x, k in ((10.0, 3), (500.0, 3), (1164.0, 9)):
        assert chi2_logsf(x, k) == float(chi2.logsf(x, k))
    # what the structure test compares: 20 position cells far beyond 3 phase cells
    assert chi2_logsf(15325.4, 20) < chi2_logsf(4438.0, 3) < chi2_logsf(1500.0, 3)
    xs = np.linspace(1e3, 1e5, 200)
    for k in (1, 3, 9, 20):
        v = [chi2_logsf(x, k) for x in xs]
        assert np.all(np.diff(v) < 0)
