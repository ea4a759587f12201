"""The two forms of the Kalman steps in ``core/kalman.py`` give the same numbers."""

import numpy as np
import pytest

from train_estimation.core import kalman


def _random_cov(rng):
    L = rng.normal(size=(2, 2))
    return L @ L.T + 0.1 * np.eye(2)


@pytest.mark.parametrize("seed", range(5))
def test_closed_form_prediction_is_the_batched_one(seed):
    rng = np.random.default_rng(seed)
    P = _random_cov(rng)
    h, q = rng.uniform(0.01, 2.0), rng.uniform(0.0, 0.5)
    Phi = np.array([[1.0, h], [0.0, 1.0]])
    Q = q * np.array([[h ** 3 / 3, h * h / 2], [h * h / 2, h]])
    want = kalman.propagate_cov(P[None], Phi[None], Q)[0]
    got = kalman.predict_cov(P[0, 0], P[0, 1], P[1, 1], h, q)
    np.testing.assert_allclose([want[0, 0], want[0, 1], want[1, 1]], got, rtol=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_closed_form_updates_are_the_batched_one(seed):
    rng = np.random.default_rng(seed)
    P = _random_cov(rng)
    x = rng.normal(size=2)
    r_s, r_v, r_b = rng.uniform(0.01, 2.0, size=3)
    y = rng.normal(size=2)
    # odometer: (distance, speed), diagonal R
    xb, Pb, ll = kalman.update(x[None], P[None], y, np.eye(2), np.array([r_s, r_v]),
                               np.array([True, True]))
    s00, s01, s11, det, _, (k00, k01, k10, k11), pn = kalman.odometer_update(
        P[0, 0], P[0, 1], P[1, 1], r_s, r_v)
    K = np.array([[k00, k01], [k10, k11]])
    np.testing.assert_allclose(xb[0], x + K @ (y - x), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose([Pb[0, 0, 0], Pb[0, 0, 1], Pb[0, 1, 1]], pn, rtol=1e-10,
                               atol=1e-14)
    e = y - x
    S = np.array([[s00, s01], [s01, s11]])
    want_ll = -0.5 * (2 * np.log(2 * np.pi) + np.log(det) + e @ np.linalg.solve(S, e))
    np.testing.assert_allclose(ll[0], want_ll, rtol=1e-12)
    # balise: distance only
    xb, Pb, ll = kalman.update(x[None], P[None], y[:1], np.array([[1.0, 0.0]]),
                               np.array([r_b]), np.array([True]))
    s, (k0, k1), pn = kalman.balise_update(P[0, 0], P[0, 1], P[1, 1], r_b)
    np.testing.assert_allclose(xb[0], x + np.array([k0, k1]) * (y[0] - x[0]), rtol=1e-12)
    np.testing.assert_allclose([Pb[0, 0, 0], Pb[0, 0, 1], Pb[0, 1, 1]], pn, rtol=1e-10,
                               atol=1e-14)
    np.testing.assert_allclose(ll[0], -0.5 * (np.log(2 * np.pi * s) + (y[0] - x[0]) ** 2 / s),
                               rtol=1e-12)


@pytest.mark.parametrize("n_particles", [1, 3])
def test_update_leaves_its_inputs_alone(n_particles):
    """The batched update works on copies: with one particle the transposed arrays are
    contiguous views, and an in-place step would overwrite the caller's state (a filter's
    snapshot for rewinding, say)."""
    rng = np.random.default_rng(1)
    x = rng.normal(size=(n_particles, 2))
    P = np.stack([_random_cov(rng) for _ in range(n_particles)])
    x0, P0 = x.copy(), P.copy()
    kalman.update(x, P, rng.normal(size=2), np.eye(2), np.array([0.5, 0.2]),
                  np.array([True, True]))
    np.testing.assert_array_equal(x, x0)
    np.testing.assert_array_equal(P, P0)
