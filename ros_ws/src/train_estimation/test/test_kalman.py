"""The Kalman toolbox: the two forms of the steps in ``core/numerics/kalman.py`` give the same
numbers;
the RTS smoother and the GLS of ``core/numerics/augmented_kf.py`` equal direct dense solves."""

import numpy as np
import pytest

from train_estimation.core.numerics import kalman
from train_estimation.core.numerics.augmented_kf import gls, information_condition


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


@pytest.mark.parametrize("n_particles", [1, 4])
def test_update_takes_one_reading_per_particle(n_particles):
    """``y (N, p)``: each particle updated with its own reading equals N separate updates."""
    rng = np.random.default_rng(2)
    x = rng.normal(size=(n_particles, 2))
    P = np.stack([_random_cov(rng) for _ in range(n_particles)])
    y = rng.normal(size=(n_particles, 2))
    R, used = np.array([0.5, 0.2]), np.array([True, True])
    xb, Pb, ll = kalman.update(x, P, y, np.eye(2), R, used)
    for i in range(n_particles):
        xi, Pi, li = kalman.update(x[i:i + 1], P[i:i + 1], y[i], np.eye(2), R, used)
        np.testing.assert_allclose(xb[i], xi[0], rtol=1e-14, atol=1e-15)
        np.testing.assert_allclose(Pb[i], Pi[0], rtol=1e-14, atol=1e-15)
        np.testing.assert_allclose(ll[i], li[0], rtol=1e-14)


def _linear_gaussian(rng, T, n, p, batch):
    """A random time-varying linear-Gaussian model: x_0 ~ N(m0, P0), x_t = F_t x_{t-1} + c_t
    + w_t, y_t = H x_t + e_t (t = 1..T-1), diagonal R; ``batch`` independent data sets."""
    m0 = rng.normal(size=n)
    L0 = rng.normal(size=(n, n))
    P0 = L0 @ L0.T + 0.5 * np.eye(n)
    F = np.zeros((T, n, n))
    F[1:] = np.eye(n) + 0.3 * rng.normal(size=(T - 1, n, n))
    c = rng.normal(size=(T, n))
    Lq = rng.normal(size=(n, n)) * 0.4
    Q = Lq @ Lq.T + 0.05 * np.eye(n)
    H = rng.normal(size=(p, n))
    R = rng.uniform(0.1, 1.0, size=p)
    y = rng.normal(size=(T, batch, p)) * 3.0
    return m0, P0, F, c, Q, H, R, y


def _dense_posterior(m0, P0, F, c, Q, H, R, y):
    """Oracle: the stacked states x_0..x_{T-1} as one Gaussian (x = mean + G z, z ~ N(0, I)),
    conditioned on every reading by one dense solve. Returns the posterior mean (T, n) and the
    posterior covariance (T n, T n) of the stacked state."""
    T, n = F.shape[0], m0.size
    mean = np.zeros(T * n)
    G = np.zeros((T * n, T * n))
    mean[:n] = m0
    G[:n, :n] = np.linalg.cholesky(P0)
    Lq = np.linalg.cholesky(Q)
    for t in range(1, T):
        a, b = t * n, (t + 1) * n
        mean[a:b] = F[t] @ mean[a - n:a] + c[t]
        G[a:b] = F[t] @ G[a - n:a]
        G[a:b, a:b] += Lq
    Cx = G @ G.T
    Hs = np.zeros(((T - 1) * H.shape[0], T * n))
    for t in range(1, T):
        Hs[(t - 1) * H.shape[0]:t * H.shape[0], t * n:(t + 1) * n] = H
    Cy = Hs @ Cx @ Hs.T + np.diag(np.tile(R, T - 1))
    K = Cx @ Hs.T @ np.linalg.inv(Cy)
    post_m = mean + K @ (y[1:].ravel() - Hs @ mean)
    post_C = Cx - K @ Hs @ Cx
    return post_m.reshape(T, n), post_C


@pytest.mark.parametrize("seed", range(3))
def test_rts_smoother_is_the_dense_joint_gaussian_posterior(seed):
    """Filter (kalman.propagate_cov + kalman.update) and kalman.rts_smooth: the smoothed means,
    covariances and lag-one cross covariances are the posterior of the stacked Gaussian."""
    rng = np.random.default_rng(seed)
    T, n, p, batch = 7, 3, 2, 4
    m0, P0, F, c, Q, H, R, y = _linear_gaussian(rng, T, n, p, batch)
    m_f = np.zeros((T, batch, n))
    P_f = np.zeros((T, batch, n, n))
    m_p, P_p = np.zeros_like(m_f), np.zeros_like(P_f)
    m_f[0], P_f[0] = m0, P0
    for t in range(1, T):
        m_p[t] = m_f[t - 1] @ F[t].T + c[t]
        P_p[t] = kalman.propagate_cov(P_f[t - 1], F[t], Q)
        m_f[t], P_f[t], _ = kalman.update(m_p[t], P_p[t], y[t], H, R, np.ones(p, bool))
    m_s, P_s, C = kalman.rts_smooth(m_f, P_f, m_p, P_p, F)
    for b in range(batch):
        mean, cov = _dense_posterior(m0, P0, F, c, Q, H, R, y[:, b])
        np.testing.assert_allclose(m_s[:, b], mean, rtol=1e-9, atol=1e-9)
        for t in range(T):
            blk = cov[t * n:(t + 1) * n, t * n:(t + 1) * n]
            np.testing.assert_allclose(P_s[t, b], blk, rtol=1e-9, atol=1e-10)
        for t in range(T - 1):
            cross = cov[t * n:(t + 1) * n, (t + 1) * n:(t + 2) * n]
            np.testing.assert_allclose(C[t, b] @ P_s[t + 1, b], cross, rtol=1e-9, atol=1e-10)


def test_rts_smoother_broadcasts_a_covariance_common_to_the_batch():
    """A scalar state with one variance sequence for every batch element (the hybrid EM's
    position filter) gives the same means as the batch written out in full."""
    rng = np.random.default_rng(4)
    T, batch = 6, 3
    m_f, m_p = rng.normal(size=(T, batch, 1)), rng.normal(size=(T, batch, 1))
    P_f, P_p = rng.uniform(0.1, 1.0, (T, 1, 1)), rng.uniform(1.0, 2.0, (T, 1, 1))
    F = np.ones((T, 1, 1))
    m_s = kalman.rts_smooth(m_f, P_f, m_p, P_p, F)[0]
    full = kalman.rts_smooth(m_f, np.repeat(P_f[:, None], batch, 1),
                             m_p, np.repeat(P_p[:, None], batch, 1), F)[0]
    np.testing.assert_allclose(m_s, full, rtol=1e-14)


def _gls_problem(rng, m, k, scales):
    """A correlated linear regression y = X theta + e, e ~ N(0, S), with columns of very
    different scales, and W = E^T S^-1 E for the columns E = [y, -X] (so [1, theta] E^T S^-1
    E [1, theta]^T is the whitened residual sum of squares)."""
    X = rng.normal(size=(m, k)) * scales
    L = np.tril(rng.normal(size=(m, m)) * 0.2) + np.eye(m)
    S = L @ L.T
    y = X @ (rng.normal(size=k) / scales) + L @ rng.normal(size=m)
    E = np.column_stack([y, -X])
    return X, S, y, E.T @ np.linalg.solve(S, E)


@pytest.mark.parametrize("seed", range(3))
def test_gls_is_the_direct_generalised_least_squares(seed):
    rng = np.random.default_rng(seed)
    scales = np.array([1e-4, 1.0, 1e3, 10.0])
    X, S, y, W = _gls_problem(rng, 40, 4, scales)
    th, cov, quad = gls(W)
    Si = np.linalg.inv(S)
    info = X.T @ Si @ X
    want = np.linalg.solve(info, X.T @ Si @ y)
    np.testing.assert_allclose(th * scales, want * scales, rtol=1e-9)
    np.testing.assert_allclose(cov, np.linalg.inv(info), rtol=1e-8)
    r = y - X @ want
    np.testing.assert_allclose(quad, r @ Si @ r, rtol=1e-9)
    # M maps [1, theta'] onto the columns: theta_1 = theta_2 tied, theta_3, theta_4 at zero
    M = np.zeros((5, 2))
    M[0, 0], M[1, 1], M[2, 1] = 1.0, 1.0, 1.0
    th2, cov2, quad2 = gls(W, M)
    x = X[:, 0] + X[:, 1]
    want2 = (x @ Si @ y) / (x @ Si @ x)
    np.testing.assert_allclose(th2, [want2], rtol=1e-9)
    np.testing.assert_allclose(cov2, [[1.0 / (x @ Si @ x)]], rtol=1e-9)
    np.testing.assert_allclose(quad2, (y - want2 * x) @ Si @ (y - want2 * x), rtol=1e-9)


def test_gls_refuses_or_zeroes_an_undetermined_parameter():
    rng = np.random.default_rng(7)
    X, S, y, W = _gls_problem(rng, 30, 3, np.ones(3))
    W0 = W.copy()
    W0[3, :] = W0[:, 3] = 0.0  # the third parameter carries no information
    th, cov, _ = gls(W0)
    assert th[2] == 0.0 and np.all(cov[2] == 0.0)
    np.testing.assert_allclose(th[:2], gls(W0[:3, :3])[0], rtol=1e-10)
    assert not np.isfinite(information_condition(W0)) or information_condition(W0) > 1e15
    with pytest.raises(np.linalg.LinAlgError):
        gls(W0, max_condition=1e12)
    # units alone do not make a fit singular: rescaling a parameter leaves the condition alone
    D = np.diag([1.0, 1e-6, 1.0, 1e6])
    assert information_condition(D @ W @ D) == pytest.approx(information_condition(W), rel=1e-6)
