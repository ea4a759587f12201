"""train_core.lag: the first-order recurrence is scipy's lfilter with the same arithmetic."""

import numpy as np
import pytest
from scipy.signal import lfilter
from train_core.lag import _first_order, first_order


@pytest.mark.parametrize("n", [1, 2, 3, 17, 6000])
@pytest.mark.parametrize("a", [0.0, 0.7788007830714049, 0.999])
def test_first_order_is_lfilter_bit_for_bit(n, a):
    x = np.random.default_rng(n).normal(size=n) * 3.0
    b = 1.0 - a if a else 0.1
    want = lfilter([0.0, b], [1.0, -a], x)
    assert np.array_equal(first_order(x, a, b), want)
    assert np.array_equal(_first_order(x, a, b), want)  # the interpreted loop too


def test_first_order_takes_any_float_array_view():
    x = np.arange(20.0)[::2]  # not contiguous
    assert np.array_equal(first_order(x, 0.5, 0.5), lfilter([0.0, 0.5], [1.0, -0.5], x))
