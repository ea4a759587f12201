"""The shared SMC helpers: batched log-normalisation and systematic resampling."""

import numpy as np
import pytest

from train_estimation.core.numerics.smc import (
    effective_sample_size,
    log_normalize,
    systematic_resample,
)


def test_systematic_counts_are_floor_or_ceil_per_batch_element():
    rng = np.random.default_rng(0)
    w = rng.dirichlet(np.ones(7), size=(3, 5)).transpose(2, 0, 1)  # (N=7, 3, 5)
    for n in (7, 20, 3):
        idx = systematic_resample(w, rng, n)
        assert idx.shape == (n, 3, 5)
        for a in range(3):
            for b in range(5):
                counts = np.bincount(idx[:, a, b], minlength=7)
                expect = n * w[:, a, b]
                assert np.all(counts >= np.floor(expect) - 1e-9)
                assert np.all(counts <= np.ceil(expect) + 1e-9)


def test_zero_weights_are_never_drawn_and_degenerate_weights_fail():
    rng = np.random.default_rng(1)
    w = np.array([0.0, 0.5, 0.0, 0.5])
    for _ in range(50):
        assert set(systematic_resample(w, rng, 9)) <= {1, 3}
    with np.errstate(divide="ignore"):  # log 0 = -inf: a zero weight
        lw = np.log(np.array([[0.2, 0.0], [0.8, 1.0]]))
    wn, lz = log_normalize(lw)
    np.testing.assert_allclose(wn, [[0.2, 0.0], [0.8, 1.0]])
    with pytest.raises(ValueError):
        log_normalize(np.array([[-np.inf], [-np.inf]]))


def test_degenerate_batched_weights_resample_to_single_particle():
    w = np.zeros((10, 2))
    w[3, 0] = 1.0
    w[9, 1] = 1.0
    idx = systematic_resample(w, np.random.default_rng(1))
    assert np.all(idx[:, 0] == 3) and np.all(idx[:, 1] == 9)

def _resample_log(logw, n, rng):
    """Resampling from log-weights: log_normalize, then systematic_resample."""
    return systematic_resample(log_normalize(logw)[0], rng, n)


def test_systematic_resampling_degenerate_weights():
    rng = np.random.default_rng(0)
    # one weight 1, the rest exactly 0
    with np.errstate(divide="ignore"):
        lw = np.log([0.0, 1.0, 0.0, 0.0])
    np.testing.assert_array_equal(_resample_log(lw, 4, rng), [1, 1, 1, 1])
    # all -inf but one, and all underflowing but one (exp would give 0/0)
    np.testing.assert_array_equal(
        _resample_log(np.array([-np.inf, -np.inf, -3.0]), 5, rng), [2] * 5)
    np.testing.assert_array_equal(
        _resample_log(np.array([-1e300, -2e4, -1e300]), 3, rng), [1] * 3)
    # all equal: every particle exactly once, whatever the uniform
    for _ in range(20):
        np.testing.assert_array_equal(_resample_log(np.zeros(6), 6, rng), np.arange(6))
    with pytest.raises(ValueError):
        _resample_log(np.full(3, -np.inf), 3, rng)


def test_systematic_resampling_counts_are_floor_or_ceil():
    rng = np.random.default_rng(1)
    for _ in range(50):
        w = rng.dirichlet(np.full(9, 0.3))
        with np.errstate(divide="ignore"):
            a = _resample_log(np.log(w), 100, rng)
        c = np.bincount(a, minlength=9)
        assert np.all(c >= np.floor(100 * w) - 1e-9) and np.all(c <= np.ceil(100 * w) + 1e-9)


def test_effective_sample_size():
    assert effective_sample_size(np.zeros(8)) == pytest.approx(8.0)
    assert effective_sample_size(np.array([0.0, -np.inf, -np.inf])) == pytest.approx(1.0)
