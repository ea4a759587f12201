"""The shared SMC helpers: batched log-normalisation and systematic resampling."""

import numpy as np
import pytest

from train_estimation.core.smc import log_normalize, systematic_resample


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
