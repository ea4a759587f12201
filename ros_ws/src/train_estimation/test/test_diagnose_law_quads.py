"""laws._stretch_quads (the law test's stretches, batched) is ``gls(W, M)[2]`` of each stretch
bit for bit: the same BLAS and LAPACK calls per stretch."""

import numpy as np

from train_estimation.core.numerics.augmented_kf import gls
from train_estimation.core.offline.diagnose.laws import _stretch_quads


def _information(rng, p: int) -> np.ndarray:
    Z = rng.normal(size=(4 * p, p)) * rng.uniform(0.01, 100.0, p)  # columns of mixed scale
    Z[:, p - 1] = 0.0  # a column without information (pinv's cut-off)
    return Z.T @ Z


def test_batched_stretches_are_gls_bit_for_bit():
    rng = np.random.default_rng(7)
    for m in (1, 2, 7, 23):
        W = _information(rng, 2 + 2 * m)
        pairs = [(a, b) for a in range(m) for b in range(a + 1, m + 1)]
        for off in (0, m):
            got = _stretch_quads(W, off, pairs)
            for (a, b), q in zip(pairs, got):
                M = np.zeros((W.shape[0], 3))
                M[0, 0] = M[1, 1] = 1.0
                M[2 + off + a:2 + off + b, 2] = 1.0
                assert np.float64(q).tobytes() == np.float64(gls(W, M)[2]).tobytes()
    assert _stretch_quads(np.eye(4), 0, []) == []
