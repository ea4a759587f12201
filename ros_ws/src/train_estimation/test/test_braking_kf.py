"""Batched Kalman filter vs a dense joint-Gaussian solve; log-space weights; mixtures."""

import numpy as np
import pytest

from train_estimation.core.numerics.batched_kf import mixture_moments, predict, update
from train_estimation.core.numerics.smc import log_normalize


def _random_model(rng, n=4, p=3):
    Phi = np.eye(n) + 0.3 * rng.standard_normal((n, n))
    Bu = rng.standard_normal(n)
    G = rng.standard_normal((n, n))
    Qd = 0.1 * G @ G.T
    H = rng.standard_normal((p, n))
    H[0] = np.eye(n)[0]  # one selector row (the fast path) next to general rows
    R = rng.uniform(0.05, 0.5, p)
    return Phi, Bu, Qd, H, R


def _dense_posterior(x0, P0, models, ys, masks):
    """Condition the joint Gaussian of (x_K, all used y) on the y's: no recursion at all."""
    n = x0.size
    K = len(models)
    # x_k = F_k x0 + c_k + sum_{j<=k} F_{k,j} w_j ; stack x0 and the w's as independent blocks
    blocks = [P0] + [m[2] for m in models]
    Sig0 = np.zeros((n * (K + 1), n * (K + 1)))
    for i, b in enumerate(blocks):
        Sig0[i * n:(i + 1) * n, i * n:(i + 1) * n] = b
    # linear maps from (x0, w_1..w_K) to x_k
    maps, means = [], []
    L = np.zeros((n, n * (K + 1)))
    L[:, :n] = np.eye(n)
    mu = x0.copy()
    for k, (Phi, Bu, _Qd, _H, _R) in enumerate(models):
        L = Phi @ L
        L[:, n * (k + 1):n * (k + 2)] += np.eye(n)
        mu = Phi @ mu + Bu
        maps.append(L.copy())
        means.append(mu.copy())
    rows, ymean, yval, rvar = [], [], [], []
    for k, (_Phi, _Bu, _Qd, H, R) in enumerate(models):
        for j in np.flatnonzero(masks[k]):
            rows.append(H[j] @ maps[k])
            ymean.append(H[j] @ means[k])
            yval.append(ys[k][j])
            rvar.append(R[j])
    A = np.array(rows).reshape(-1, n * (K + 1))
    Syy = A @ Sig0 @ A.T + np.diag(rvar)
    Sxy = maps[-1] @ Sig0 @ A.T
    Sxx = maps[-1] @ Sig0 @ maps[-1].T
    r = np.array(yval) - np.array(ymean)
    post_mean = means[-1] + Sxy @ np.linalg.solve(Syy, r)
    post_cov = Sxx - Sxy @ np.linalg.solve(Syy, Sxy.T)
    _, logdet = np.linalg.slogdet(Syy)
    loglik = -0.5 * (r.size * np.log(2 * np.pi) + logdet + r @ np.linalg.solve(Syy, r))
    return post_mean, post_cov, loglik


def test_batched_kf_equals_dense_joint_gaussian():
    rng = np.random.default_rng(42)
    N, n, p, K = 5, 4, 3, 7
    x0 = rng.standard_normal(n)
    P0 = np.diag(rng.uniform(0.1, 1.0, n))
    # one shared H, R per step (as in the filters) but a different Phi/Bu per particle
    models = [[_random_model(rng) for _ in range(K)] for _ in range(N)]
    for i in range(1, N):  # same H and R as particle 0 at each step
        for k in range(K):
            models[i][k] = (*models[i][k][:3], models[0][k][3], models[0][k][4])
    masks = [rng.random(p) < 0.6 for _ in range(K)]
    masks[2][:] = False  # a step without any measurement
    masks[3][:] = True
    ys = [rng.standard_normal(p) for _ in range(K)]
    ys[4][~masks[4]] = np.nan  # missing components may be NaN
    x = np.repeat(x0[None], N, 0)
    P = np.repeat(P0[None], N, 0)
    total = np.zeros(N)
    for k in range(K):
        Phi = np.array([models[i][k][0] for i in range(N)])
        Bu = np.array([models[i][k][1] for i in range(N)])
        Qd = models[0][k][2]
        # Qd must be shared in predict(); use particle 0's for everyone in the dense solve too
        for i in range(N):
            models[i][k] = (models[i][k][0], models[i][k][1], Qd, *models[i][k][3:])
        x, P = predict(x, P, Phi, Bu, Qd)
        x, P, ll = update(x, P, ys[k], models[0][k][3], models[0][k][4], masks[k])
        total += ll
    for i in range(N):
        m, c, lik = _dense_posterior(x0, P0, models[i], ys, masks)
        np.testing.assert_allclose(x[i], m, rtol=0, atol=1e-9)
        np.testing.assert_allclose(P[i], c, rtol=0, atol=1e-9)
        assert total[i] == pytest.approx(lik, abs=1e-9)
        np.testing.assert_array_equal(P[i], P[i].T)


def test_predict_broadcast_equals_per_particle():
    rng = np.random.default_rng(3)
    Phi, Bu, Qd, _, _ = _random_model(rng)
    x = rng.standard_normal((6, 4))
    G = rng.standard_normal((6, 4, 4))
    P = G @ np.swapaxes(G, 1, 2)
    xb, Pb = predict(x, P, Phi[None], Bu[None], Qd)
    xf, Pf = predict(x, P, np.repeat(Phi[None], 6, 0), np.repeat(Bu[None], 6, 0), Qd)
    np.testing.assert_allclose(xb, xf, atol=1e-12)
    np.testing.assert_allclose(Pb, Pf, atol=1e-12)


def test_empty_mask_is_identity():
    x = np.ones((3, 4))
    P = np.repeat(np.eye(4)[None], 3, 0)
    x2, P2, ll = update(x, P, np.full(3, np.nan), np.eye(4)[:3], np.ones(3), np.zeros(3, bool))
    assert np.array_equal(x2, x) and np.array_equal(P2, P) and np.array_equal(ll, np.zeros(3))


def test_log_normalize_underflow_and_degenerate():
    w, logz = log_normalize(np.array([-1e4, -1e4 - np.log(3.0), -np.inf]))
    np.testing.assert_allclose(w, [0.75, 0.25, 0.0], atol=1e-15)
    assert logz == pytest.approx(-1e4 + np.log(4.0 / 3.0))
    for bad in ([-np.inf, -np.inf], [0.0, np.nan], [0.0, np.inf], []):
        with pytest.raises(ValueError):
            log_normalize(np.array(bad))


def test_mixture_moments_law_of_total_covariance():
    rng = np.random.default_rng(5)
    w = np.array([0.2, 0.5, 0.3])
    m = rng.standard_normal((3, 2))
    C = np.array([np.eye(2) * s for s in (0.1, 0.2, 0.3)])
    mean, cov = mixture_moments(w, m, C)
    ref_mean = sum(w[i] * m[i] for i in range(3))
    second = sum(w[i] * (C[i] + np.outer(m[i], m[i])) for i in range(3))
    np.testing.assert_allclose(mean, ref_mean, atol=1e-15)
    np.testing.assert_allclose(cov, second - np.outer(ref_mean, ref_mean), atol=1e-14)
