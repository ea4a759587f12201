"""Tests of the mass-point model and the closed-form M-step (eq. (31)-(36))."""

import numpy as np
import pytest

from train_estimation.core.offline.em_model import (
    CRH3_PARAMS,
    CRH3_VARTHETA,
    MassPointParams,
    NoiseParams,
    gaussian_pair_stats,
    m_step,
    pair_stats,
    param_error,
    plugin_stats,
    theta_change,
)
from train_sim.crh3 import simulate_crh3

TINY = NoiseParams(q_s=1e-300, q_v=1e-300)  # noise-free states (std 1e-150)


def test_m_step_recovers_parameters_exactly_from_noise_free_states():
    d = simulate_crh3(300, np.random.default_rng(0), noise=TINY)
    vt = m_step(plugin_stats(d.v, d.u))
    np.testing.assert_allclose(vt, CRH3_VARTHETA, rtol=1e-8)
    assert param_error(vt) < 1e-8


def test_m_step_batched_equals_single():
    d = simulate_crh3(600, np.random.default_rng(1), batch=3, noise=TINY)
    vt = m_step(plugin_stats(d.v, d.u))
    assert vt.shape == (4, 3)
    for b in range(3):
        np.testing.assert_allclose(vt[:, b], m_step(plugin_stats(d.v[:, b], d.u[:, b])))


def test_vartheta_roundtrip_and_paper_rounding():
    vt = CRH3_PARAMS.to_vartheta()
    back = MassPointParams.from_vartheta(vt)
    np.testing.assert_allclose([back.a, back.b, back.c, back.d], [0.53, 0.0039, 0.000114, 0.06])
    # the printed vector of Section 3 is a rounding of this one (a paper slip, see em_model)
    np.testing.assert_allclose(vt, CRH3_VARTHETA, rtol=0.1)
    with pytest.raises(ValueError):
        MassPointParams.from_vartheta([0.0, 1, 1, 1])


def test_pair_stats_with_point_masses_equal_plugin():
    d = simulate_crh3(50, np.random.default_rng(2))
    v = d.v
    tot = None
    for t in range(1, 51):
        st = pair_stats(v[t - 1][None], v[t][None], np.ones(1), d.u[t - 1])
        tot = st if tot is None else tot + st
    ref = plugin_stats(v, d.u)
    np.testing.assert_allclose(tot.PP, ref.PP, rtol=1e-12)
    np.testing.assert_allclose(tot.Pp, ref.Pp, rtol=1e-12)
    np.testing.assert_allclose(tot.pp, ref.pp, rtol=1e-12)


def test_gaussian_pair_stats_zero_variance_at_reference_equals_plugin():
    d = simulate_crh3(60, np.random.default_rng(3))
    z = np.zeros(60)
    g = gaussian_pair_stats(d.u, d.v[:-1], d.v[1:], z, z, z, d.v[:-1])
    ref = plugin_stats(d.v, d.u)
    np.testing.assert_allclose(g.PP, ref.PP, rtol=1e-10)
    np.testing.assert_allclose(g.Pp, ref.Pp, rtol=1e-10, atol=1e-12)


def test_residual_variance_estimates_process_noise():
    """With true states, (1/n) sum (phi - Phi^T vt)^2 at the truth is q * chi2_n / n:
    mean q, sd q sqrt(2/n); 4 sd tolerance."""
    n, q = 4000, 0.01
    d = simulate_crh3(n, np.random.default_rng(4))
    r = plugin_stats(d.v, d.u).residual_variance(CRH3_VARTHETA)
    assert abs(r - q) < 4 * q * np.sqrt(2 / n)


def test_m_step_rejects_no_excitation():
    v = np.full(101, 10.0)  # constant speed: -1, -v, -v^2 collinear
    with pytest.raises(np.linalg.LinAlgError, match="excite"):
        m_step(plugin_stats(v, np.ones(100)))


def test_theta_change_spaces():
    a = CRH3_VARTHETA
    assert theta_change(a, a) == 0
    assert theta_change(a, a, space="Theta") == 0
    with pytest.raises(ValueError):
        theta_change(a, a, space="x")
    with pytest.raises(ValueError):
        NoiseParams(q_v=0.0)
