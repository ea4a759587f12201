"""Braking model (Zheng et al. 2015 eq. (4)): exact discretisation, noise, gating, data."""

import os
import sys

import numpy as np
import pytest
from scipy.linalg import expm

from train_estimation.core.braking.braking_model import (
    BrakingModel,
    BrakingParams,
    continuous_matrices,
    discretize,
    process_noise,
)
from train_estimation.core.numerics.discretize import zoh

sys.path.insert(0, os.path.dirname(__file__))
from braking_toy import simulate_open_loop  # noqa: E402  (test support: the model's own data)

PAPER = BrakingParams()  # tau = 0.4 s, T = 1.2 s (lambda = 1.6667), dt = 1 s


def test_lambda_is_two_over_T():
    assert PAPER.lam == pytest.approx(1.6667, abs=1e-4)


def test_affine_in_f_equals_batched_expm():
    rng = np.random.default_rng(0)
    f = np.concatenate([rng.uniform(-0.5, 2.0, 20), [0.0, 1.0]])
    for dt in (0.05, 1.0, 2.7):
        Phi, Bd, _ = discretize(f, PAPER, dt)
        A, B = continuous_matrices(f, PAPER)
        Phi_ref, Bd_ref = zoh(A, B, dt)
        np.testing.assert_allclose(Phi, Phi_ref, rtol=0, atol=1e-12)
        np.testing.assert_allclose(Bd, Bd_ref, rtol=0, atol=1e-12)


def _rk4(f_val, x0, u, dt, n):
    """Fine-step RK4 of dx/dt = A x + B u with u held (independent of expm)."""
    A, B = continuous_matrices(f_val, PAPER)
    A, B = A[0], B[0]
    h = dt / n
    x = np.array(x0, dtype=float)
    rhs = lambda z: A @ z + B @ u  # noqa: E731
    for _ in range(n):
        k1 = rhs(x)
        k2 = rhs(x + 0.5 * h * k1)
        k3 = rhs(x + 0.5 * h * k2)
        k4 = rhs(x + h * k3)
        x = x + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


def test_zoh_matches_fine_step_integration_and_euler_does_not():
    x0 = np.array([3.0, 20.0, -0.7, -1.5])
    u = np.array([-1.0, 0.05])
    for f_val in (1.0, 0.63, 0.0):
        Phi, Bd, _ = discretize([f_val], PAPER, 1.0)
        x_zoh = Phi[0] @ x0 + Bd[0] @ u
        # RK4 global error ~ (h/tau)^4 with h = 1e-3 s: ~1e-11; 1e-8 is a safe margin
        x_ref = _rk4(f_val, x0, u, 1.0, 1000)
        np.testing.assert_allclose(x_zoh, x_ref, rtol=0, atol=1e-8)
        # why exact discretisation: one Euler step of 1 s with tau = 0.4 s is far off
        A, B = continuous_matrices(f_val, PAPER)
        x_euler = x0 + 1.0 * (A[0] @ x0 + B[0] @ u)
        assert np.max(np.abs(x_euler - x_ref)) > 0.1


def test_steady_state_pade_has_unit_dc_gain():
    # constant command u: a_z -> 2u, delayed command a_z - u -> u, a_hat -> f u
    f_val, u = 0.7, -0.9
    Phi, Bd, _ = discretize([f_val], PAPER, 1.0)
    x = np.zeros(4)
    for _ in range(200):
        x = Phi[0] @ x + Bd[0] @ np.array([u, 0.0])
    assert x[3] == pytest.approx(2 * u, abs=1e-10)
    assert x[2] == pytest.approx(f_val * u, abs=1e-10)


def test_process_noise_zoh_and_white():
    dt = 0.7
    Qz = process_noise(BrakingParams(accel_var=0.05, noise_model="zoh"), dt)
    g = np.array([dt * dt / 2, dt, 0, 0])
    np.testing.assert_allclose(Qz, 0.05 * np.outer(g, g), atol=1e-15)
    # white noise on v and on a_hat vs trapezoidal quadrature of int e^{As} G Qc G^T e^{A^T s} ds
    p = BrakingParams(accel_var=0.03, noise_model="white", ahat_var=0.02)
    Qw = process_noise(p, dt)
    A = continuous_matrices(0.37, p)[0][0]  # any f: the noise columns never reach a_z
    Qc = np.diag([0.0, 0.03, 0.02, 0.0])
    s = np.linspace(0.0, dt, 4001)
    vals = np.array([expm(A * si) @ Qc @ expm(A * si).T for si in s])
    ref = np.trapezoid(vals, s, axis=0)
    # trapezoid error ~ dt^3/(12 n^2) * max|f''| ~ 1e-9
    np.testing.assert_allclose(Qw, ref, rtol=0, atol=1e-8)


def test_params_validation():
    for kw in ({"tau": 0.0}, {"delay": -1.0}, {"dt": np.nan}, {"accel_var": -1.0},
               {"noise_model": "euler"}, {"meas_var": (1.0, 0.0, 1.0)}, {"meas_var": (1.0, 1.0)}):
        with pytest.raises(ValueError):
            BrakingParams(**kw)


def test_gate_braking_coasting_standstill():
    fam = BrakingModel(BrakingParams(standstill_speed=0.05))
    x_moving = np.array([0.0, 10.0, 0.0, 0.0])
    x_stopped = np.array([0.0, 0.01, 0.0, 0.0])
    assert fam.gate([-0.5, 0.0], x_moving)
    assert not fam.gate([0.0, 0.0], x_moving)  # coasting
    assert not fam.gate([0.4, 0.0], x_moving)  # traction
    assert not fam.gate([-0.5, 0.0], x_stopped)  # held at standstill
    assert BrakingModel(BrakingParams()).gate([-0.5, 0.0], x_stopped)  # toy: no standstill gate
    # non-informative steps: one shared model whatever the particles' f
    Phi, Bu, _ = fam.matrices(np.array([[0.2], [0.9]]), np.array([0.3, 0.0]), 1.0, False)
    assert Phi.shape == (1, 4, 4) and Bu.shape == (1, 4)
    Phi1, _, _ = discretize([1.0], fam.params, 1.0)
    np.testing.assert_array_equal(Phi, Phi1)


def test_simulate_open_loop_noise_free_is_the_recursion():
    p = BrakingParams(accel_var=0.0)
    K = 30
    f = 1 - 0.005 * np.arange(1, K + 1)
    u = np.column_stack([-np.ones(K), np.zeros(K)])
    x0 = np.array([0.0, 20.0, -1.0, -2.0])
    x, y = simulate_open_loop(p, f, u, x0, np.random.default_rng(1), meas_std=np.zeros(3))
    xr = x0.copy()
    for k in range(K):
        Phi, Bd, _ = discretize([f[k]], p, 1.0)
        xr = Phi[0] @ xr + Bd[0] @ u[k]
        np.testing.assert_allclose(x[k + 1], xr, atol=1e-12)
    np.testing.assert_allclose(y, x[1:][:, [0, 1, 3]], atol=1e-12)


@pytest.mark.parametrize("noise_model", ["zoh", "white"])
def test_affine_prediction_equals_the_generic_kalman_prediction(noise_model):
    """``BrakingModel.predict`` (affine form, particles on the last axis inside) is the Kalman
    prediction with ``matrices`` for every particle, informative or held, and keeps P exactly
    symmetric -- also past the block size of its matrix products (many particles)."""
    from train_estimation.core.numerics.batched_kf import predict

    fam = BrakingModel(BrakingParams(noise_model=noise_model, ahat_var=0.01))
    rng = np.random.default_rng(3)
    for N in (1, 7, 5000):
        x = rng.standard_normal((N, 4))
        G = rng.standard_normal((N, 4, 4))
        P = G @ np.swapaxes(G, 1, 2)
        theta = rng.uniform(0.0, 1.3, (N, 1))
        u = np.array([-0.7, 0.1])
        for informative, hold in ((True, None), (False, 0.6), (False, None)):
            xa, Pa = fam.predict(x, P, theta, u, 0.37, informative, hold)
            xb, Pb = predict(x, P, *fam.matrices(theta, u, 0.37, informative, hold))
            np.testing.assert_allclose(xa, xb, rtol=0, atol=1e-12)
            np.testing.assert_allclose(Pa, Pb, rtol=0, atol=1e-11)
            assert np.array_equal(Pa, np.swapaxes(Pa, 1, 2))
