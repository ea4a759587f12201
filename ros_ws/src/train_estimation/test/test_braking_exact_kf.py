"""The exact reference (``BrakingKF``: one KF on (D, v, a_hat, a_z, f)) against exact oracles."""

import os
import sys

import numpy as np
import pytest

from train_estimation.core.braking.braking_filters import BrakingKF
from train_estimation.core.braking.braking_model import (
    BrakingModel,
    BrakingParams,
    continuous_matrices,
)
from train_estimation.core.numerics.batched_kf import predict, update
from train_estimation.core.numerics.discretize import zoh

sys.path.insert(0, os.path.dirname(__file__))
from braking_toy import simulate_open_loop  # noqa: E402  (test support: the model's own data)
from test_braking_kf import _dense_posterior  # noqa: E402  (the dense joint-Gaussian oracle)

X0 = np.array([0.0, 20.0, -1.0, -2.0])
P0 = np.diag([0.3, 0.05, 0.02, 0.0])  # a_z known (variance 0): the KF is then exact


def _f_column(params, az, u, dt):
    """d/df of the exact ZOH map at two *other* f values (0.3, 0.8): independent of the
    module's cached affine pieces; exact because the map is affine in f."""
    A, B = continuous_matrices(np.array([0.3, 0.8]), params)
    Phi, Bd = zoh(A, B, dt)
    x = np.array([0.0, 0.0, 0.0, az])
    return ((Phi[1] - Phi[0]) @ x + (Bd[1] - Bd[0]) @ u) / 0.5, Phi


def test_kf_equals_dense_joint_gaussian_with_random_walk_f():
    params = BrakingParams(standstill_speed=None)
    fam = BrakingModel(params)
    rng = np.random.default_rng(4)
    K, q = 9, 2e-3
    dts = rng.uniform(0.2, 1.6, K)
    a_tar = np.array([-1.0, -0.8, -1.2, 0.4, -1.0, -0.5, 0.0, -1.1, -0.9])
    masks = [rng.random(3) < 0.7 for _ in range(K)]
    masks[1][:] = False
    masks[4][:] = True
    ys = [rng.standard_normal(3) + [20.0 * k, 20.0, -2.0] for k in range(K)]
    R = np.asarray(params.meas_var)
    H5 = np.hstack([np.eye(4)[[0, 1, 3]], np.zeros((3, 1))])
    kf = BrakingKF(fam, braking_rate_q=q, braking_rate_prior=(0.9, 0.2))
    kf.reset(X0, P0, t0=0.0)
    models = []
    az, t, total = X0[3], 0.0, 0.0
    for k in range(K):
        u = np.array([a_tar[k], 0.05])
        F = np.zeros((5, 5))
        F[4, 4] = 1.0
        b = np.zeros(5)
        Q = np.zeros((5, 5))
        g = np.array([dts[k] ** 2 / 2, dts[k], 0.0, 0.0])
        Q[:4, :4] = params.accel_var * np.outer(g, g)
        if a_tar[k] < 0:  # braking: f enters through the known column
            c, _ = _f_column(params, az, u, dts[k])
            A, B = continuous_matrices(np.array([0.0]), params)
            Phi0, Bd0 = zoh(A, B, dts[k])
            F[:4, :4], F[:4, 4], b[:4] = Phi0[0], c, Bd0[0] @ u
            Q[4, 4] = q * dts[k]
        else:  # traction: gain 1, f frozen
            A, B = continuous_matrices(np.array([1.0]), params)
            Phi1, Bd1 = zoh(A, B, dts[k])
            F[:4, :4], b[:4] = Phi1[0], Bd1[0] @ u
        models.append((F, b, Q, H5, R))
        az = F[3, 3] * az + b[3]  # a_z: the Pade response to the known command
        t += dts[k]
        e = kf.step(a_tar[k], np.where(masks[k], ys[k], np.nan), masks[k], t=t, d=0.05)
        assert e.accepted, e.reason
        assert e.informative == (a_tar[k] < 0)
        if masks[k].any():
            total += e.log_evidence
    z0 = np.append(X0, 0.9)
    Pz0 = np.zeros((5, 5))
    Pz0[:4, :4] = P0
    Pz0[4, 4] = 0.04
    m, c, lik = _dense_posterior(z0, Pz0, models, ys, masks)
    np.testing.assert_allclose(e.x_mean, m[:4], rtol=0, atol=1e-9)
    np.testing.assert_allclose(e.theta_mean, m[4:], rtol=0, atol=1e-9)
    np.testing.assert_allclose(e.mean, m[[0, 1, 2, 4]], rtol=0, atol=1e-9)
    np.testing.assert_allclose(e.cov, c[np.ix_([0, 1, 2, 4], [0, 1, 2, 4])], rtol=0, atol=1e-9)
    assert total == pytest.approx(lik, abs=1e-8)


def test_static_f_posterior_equals_grid_integration():
    """q = 0: p(f | y) ∝ N(f; prior) p(y | f), p(y | f) from a KF *with f fixed* (one per
    grid value, 4 states, the particle filters' code path). Its moments on a fine grid must
    equal the KF's (Gaussian)."""
    params = BrakingParams(meas_var=(0.25, 0.09, 1e-4))
    fam = BrakingModel(params)
    K = 25
    f_true = np.full(K, 0.7)
    u = np.column_stack([-np.ones(K), np.zeros(K)])
    _, y = simulate_open_loop(params, f_true, u, X0, np.random.default_rng(8))
    kf = BrakingKF(fam, braking_rate_q=0.0, braking_rate_prior=(0.8, 0.15))
    kf.reset(X0, P0)
    for k in range(K):
        e = kf.step(-1.0, y[k])
    grid = np.linspace(0.8 - 1.2, 0.8 + 1.2, 2401)
    x = np.repeat(X0[None], grid.size, 0)
    P = np.repeat(P0[None], grid.size, 0)
    loglik = np.zeros(grid.size)
    for k in range(K):  # every grid value's own KF, batched (the particle filters' code path)
        Phi, Bu, Qd = fam.matrices(grid, u[k], 1.0, True)
        x, P = predict(x, P, Phi, Bu, Qd)
        x, P, ll = update(x, P, y[k], fam.H, fam.R, np.ones(3, bool))
        loglik += ll
    lp = loglik - 0.5 * ((grid - 0.8) / 0.15) ** 2
    w = np.exp(lp - lp.max())
    w /= w.sum()
    mean = w @ grid
    var = w @ (grid - mean) ** 2
    assert e.theta_mean[0] == pytest.approx(mean, abs=1e-6)
    assert e.theta_cov[0, 0] == pytest.approx(var, rel=1e-4)
    assert abs(e.theta_mean[0] - 0.7) < 4 * np.sqrt(var)


def test_kf_holds_f_when_not_braking_and_rejects_bad_input():
    params = BrakingParams(standstill_speed=0.05)
    kf = BrakingKF(BrakingModel(params), braking_rate_q=1e-3, braking_rate_prior=(1.0, 0.15))
    e0 = kf.reset([100.0, 0.0, 0.0, 0.0], P0, t0=0.0)
    assert e0.mean[3] == 1.0 and e0.cov[3, 3] == pytest.approx(0.0225)
    rng = np.random.default_rng(0)
    for k in range(50):  # braking at standstill: no information, no random walk
        e = kf.step(-1.0, [100.0, 0.0, 0.0] + 0.01 * rng.standard_normal(3), t=k + 1.0)
        assert e.accepted and not e.informative
    assert e.mean[3] == pytest.approx(1.0, abs=1e-12)
    assert e.cov[3, 3] == pytest.approx(0.0225, abs=1e-12)
    bad = kf.step(-1.0, [np.nan, 0.0, 0.0], t=60.0)
    assert not bad.accepted and bad.reason and kf.t == 50.0
    assert sum(kf.rejected.values()) == 1
