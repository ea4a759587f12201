"""f priors centred on train.yaml's braking rate, discrete cells, estimates before
pruning, merging by value."""

import dataclasses
import os
import sys

import numpy as np
import pytest

from train_estimation.core.braking.braking_base import _Set
from train_estimation.core.braking.braking_discrete import _merge_by_value
from train_estimation.core.braking.braking_filters import (
    GSMA,
    QGRBPF,
    SMA,
    BrakingKF,
    DiscreteRBPF,
    RandomWalkRBPF,
    cell_variance,
    grid_prior,
    sticky_transition,
)
from train_estimation.core.braking.braking_model import BrakingModel, BrakingParams
from train_estimation.core.numerics.batched_kf import mixture_moments
from train_estimation.core.numerics.smc import log_normalize

sys.path.insert(0, os.path.dirname(__file__))
from braking_toy import simulate_open_loop  # noqa: E402  (test support: the model's own data)

VALUES = np.round(np.arange(10, -1, -1) * 0.1, 10)
X0 = np.array([0.0, 20.0, -1.0, -2.0])
P0 = 0.001 * np.eye(4)


def test_grid_prior_is_the_gaussian_mass_per_cell():
    p = grid_prior(VALUES, (0.5, 0.1))
    assert p.sum() == pytest.approx(1.0)
    assert np.argmax(p) == list(VALUES).index(0.5)
    # cell of 0.5 is [0.45, 0.55]: mass 2 Phi(0.5) - 1
    assert p[list(VALUES).index(0.5)] == pytest.approx(0.38292492, abs=1e-7)
    np.testing.assert_allclose(p, p[::-1], atol=1e-15)  # symmetric around the middle value
    np.testing.assert_allclose(grid_prior(VALUES, None), np.full(11, 1 / 11))
    with pytest.raises(ValueError):
        grid_prior(VALUES, (0.5, 0.0))


def test_cell_variance():
    np.testing.assert_allclose(cell_variance(VALUES), np.full(11, 0.01 / 12))
    np.testing.assert_allclose(cell_variance([0.0, 0.1, 0.3]), [0.01, 0.0225, 0.04] / np.array(
        [12.0, 12.0, 12.0]))
    assert cell_variance([0.7]).tolist() == [0.0]


def _filters(fam, prior, n=4000):
    vals = np.round(np.arange(13, -1, -1) * 0.1, 10)  # 1.3 .. 0: the prior is not cut
    return {
        "rbpf": DiscreteRBPF(fam, vals, sticky_transition(14, 0.1), n, prior=prior),
        "sma": SMA(fam, vals, n_init=n, n_keep=n, q_max=10 * n, prior=prior),
        "gsma": GSMA(fam, vals, n_init=n, n_keep=n, q_max=10 * n, prior=prior),
        "gsma_merged": GSMA(fam, vals, prior=prior, merge=True),
        "qgrbpf": QGRBPF(fam, [(0.0, 2.0)], n, prior=prior),  # bounds far from the prior
        "rbpf_rw": RandomWalkRBPF(fam, [(0.0, 2.0)], n, prior=prior),
        "qgrbpf_gh": QGRBPF(fam, [(0.0, 2.0)], 5, prior=prior, quadrature=True),
        "kf": BrakingKF(fam, braking_rate_prior=prior),
    }


@pytest.mark.parametrize("name", ["rbpf", "sma", "gsma", "gsma_merged", "qgrbpf", "rbpf_rw",
                                  "qgrbpf_gh", "kf"])
def test_every_prior_is_centred_on_the_given_mean_with_the_given_spread(name):
    fam = BrakingModel(BrakingParams())
    for prior in ((1.0, 0.15), (0.7, 0.1)):
        e = _filters(fam, prior)[name].reset(X0, P0, np.random.default_rng(1))
        # On a grid of h = 0.1 the values' variance is sigma^2 + h^2 / 12 (Sheppard: rounding
        # adds an error independent of f), and the reported variance adds the cell's h^2 / 12.
        sd = prior[1] if name in ("qgrbpf", "rbpf_rw", "qgrbpf_gh", "kf") else np.hypot(prior[1],
                                                                          0.1 / np.sqrt(6))
        # Monte Carlo: 4000 draws, std error of the mean 0.15 / 63, of the std ~1 %
        assert e.mean[3] == pytest.approx(prior[0], abs=0.012), e.mean[3]
        assert np.sqrt(e.cov[3, 3]) == pytest.approx(sd, rel=0.03), e.cov[3, 3]


def test_adapter_prior_follows_train_yaml():
    from train_estimation.core.online.estimators import (
        ALGORITHMS,
        BrakingAdapter,
        BrakingConfig,
        StartState,
    )
    from train_sim.scenario import load_scenario

    sc = load_scenario("metro_demo")
    for f0 in (1.0, 0.8):
        train = dataclasses.replace(sc.train, brake=dataclasses.replace(sc.train.brake,
                                                                       braking_rate=f0))
        for alg in ALGORITHMS:
            ad = BrakingAdapter(train, sc.line, StartState(sc.start_position),
                                BrakingConfig(algorithm=alg))
            ad.start(0.0)
            o = ad.output(0.0)
            # 50-250 particles: Monte Carlo error ~0.15 / sqrt(50) = 0.02
            assert o.braking_rate == pytest.approx(f0, abs=0.06), (alg, o.braking_rate)
            assert np.sqrt(o.covariance[15]) == pytest.approx(0.15, abs=0.04), alg


def _data(seed, K=60, meas_var=(0.01, 0.0025, 1e-4)):
    params = BrakingParams(meas_var=meas_var)
    f = np.full(K, 0.63)  # between two grid values
    u = np.column_stack([-np.ones(K), np.zeros(K)])
    _, y = simulate_open_loop(params, f, u, X0, np.random.default_rng(seed))
    return BrakingModel(params), y


def test_gsma_estimate_is_formed_before_pruning():
    """The first branching step: GSMA pruning to N and GSMA never pruning have evaluated the same
    branches, so their estimates agree; only the next step differs."""
    fam, y = _data(3)
    a = GSMA(fam, VALUES, n_init=20, n_keep=20, q_max=20, prior=(1.0, 0.15))
    b = GSMA(fam, VALUES, n_init=20, n_keep=20, q_max=10**6, prior=(1.0, 0.15))
    ra, rb = np.random.default_rng(4), np.random.default_rng(4)
    a.reset(X0, P0, ra)
    b.reset(X0, P0, rb)
    ea, eb = a.step(-1.0, y[0], None, ra), b.step(-1.0, y[0], None, rb)
    assert ea.n_particles == eb.n_particles == 60
    np.testing.assert_allclose(ea.mean, eb.mean, rtol=0, atol=1e-12)
    np.testing.assert_allclose(ea.cov, eb.cov, rtol=0, atol=1e-12)
    assert a.particles[0].shape[0] == 20 and b.particles[0].shape[0] == 60


@pytest.mark.parametrize("merge", [False, True])
def test_gsma_f_variance_never_collapses_to_zero(merge):
    """Accurate data and f = 0.63 between grid values: the weights pile on one value, but the
    reported variance keeps the value's cell (0.1^2 / 12), and the truth stays within 3 std."""
    fam, y = _data(5)
    g = GSMA(fam, VALUES, n_init=30, n_keep=30, q_max=30, prior=(1.0, 0.15), merge=merge)
    rng = np.random.default_rng(6)
    g.reset(X0, P0, rng)
    for k in range(60):
        e = g.step(-1.0, y[k], None, rng)
        assert e.cov[3, 3] >= 0.01 / 12 - 1e-12
    assert abs(e.mean[3] - 0.63) <= 3 * np.sqrt(e.cov[3, 3])


def test_merge_by_value_keeps_the_mixture_moments_per_value():
    rng = np.random.default_rng(0)
    N, n = 12, 4
    idx = rng.integers(0, 4, N)
    idx[:4] = [0, 1, 2, 3]
    G = rng.standard_normal((N, n, n))
    s = _Set(VALUES[idx][:, None], rng.standard_normal((N, n)), G @ np.swapaxes(G, 1, 2),
             np.log(rng.dirichlet(np.ones(N))), idx)
    m = _merge_by_value(s, VALUES)
    assert sorted(m.idx.tolist()) == [0, 1, 2, 3]
    w, _ = log_normalize(s.logw)
    wm, _ = log_normalize(m.logw)
    for j, v in enumerate(m.idx):
        sel = idx == v
        mu, cov = mixture_moments(w[sel] / w[sel].sum(), s.x[sel], s.P[sel])
        assert wm[j] == pytest.approx(w[sel].sum())
        np.testing.assert_allclose(m.x[j], mu, atol=1e-12)
        np.testing.assert_allclose(m.P[j], cov, atol=1e-12)
        assert m.theta[j, 0] == VALUES[v]
    # the whole mixture's moments are unchanged
    mu0, c0 = mixture_moments(w, s.x, s.P)
    mu1, c1 = mixture_moments(wm, m.x, m.P)
    np.testing.assert_allclose(mu1, mu0, atol=1e-12)
    np.testing.assert_allclose(c1, c0, atol=1e-12)


def test_merged_gsma_with_one_value_equals_the_kf_of_that_value():
    fam, y = _data(7)
    g = GSMA(fam, [0.63], merge=True)
    r = DiscreteRBPF(fam, [0.63], np.ones((1, 1)), 1)
    rng = np.random.default_rng(0)
    g.reset(X0, P0, rng)
    r.reset(X0, P0, rng)
    for k in range(30):
        eg, er = g.step(-1.0, y[k], None, rng), r.step(-1.0, y[k], None, rng)
        np.testing.assert_allclose(eg.mean, er.mean, atol=1e-10)
        np.testing.assert_allclose(eg.cov, er.cov, atol=1e-10)


def test_quadrature_qgrbpf_nodes_carry_the_joint_gaussian():
    """One deterministic redraw: the Gauss-Hermite nodes with their conditional KF states have
    the mixture's mean and covariance of (x, theta), theta's variance widened by q dt."""
    fam = BrakingModel(BrakingParams())
    q = QGRBPF(fam, [(-5.0, 5.0)], 5, braking_rate_q=0.01, quadrature=True)
    rng = np.random.default_rng(2)
    N, n = 30, 4
    G = rng.standard_normal((N, n, n))
    th = 0.6 + 0.1 * rng.standard_normal(N)
    x = rng.standard_normal((N, n)) + 0.5 * th[:, None]  # x correlated with theta
    s = _Set(th[:, None], x, 0.1 * G @ np.swapaxes(G, 1, 2), np.log(rng.dirichlet(np.ones(N))))
    out = q._transition(s, True, None, 2.0)
    assert out.theta.shape == (5, 1)

    def joint(st, extra=0.0):
        w, _ = log_normalize(st.logw)
        z = np.concatenate([st.x, st.theta], axis=1)
        zc = np.zeros((z.shape[0], n + 1, n + 1))
        zc[:, :n, :n] = st.P
        m, c = mixture_moments(w, z, zc)
        c[n, n] += extra
        return m, c

    m0, c0 = joint(s, 0.01 * 2.0 + q.min_var)
    m1, c1 = joint(out)
    np.testing.assert_allclose(m1, m0, atol=1e-12)
    np.testing.assert_allclose(c1, c0, atol=1e-12)
    assert q._transition(s, False, None, 2.0) is s  # frozen when not informative


hyp = pytest.importorskip("hypothesis")
st = pytest.importorskip("hypothesis.strategies")

_value = st.one_of(st.floats(-50, 50), st.sampled_from([np.nan, np.inf, -np.inf, 1e200]))
_step = st.tuples(
    st.one_of(st.floats(-1.5, 1.0), st.sampled_from([np.nan, np.inf])),  # a_tar
    st.lists(_value, min_size=3, max_size=3),  # y
    st.lists(st.booleans(), min_size=3, max_size=3),  # mask
    st.one_of(st.floats(-0.5, 3.0), st.sampled_from([np.nan, 0.0])),  # dt (may be bad)
)


@hyp.settings(max_examples=25, deadline=None, derandomize=True)
@hyp.given(st.sampled_from(["kf", "gsma_merged", "qgrbpf_gh"]),
           st.lists(_step, min_size=1, max_size=25), st.integers(0, 2**31 - 1))
def test_new_filters_survive_random_inputs(name, steps, seed):
    fam = BrakingModel(BrakingParams(standstill_speed=0.05))
    filt = {"kf": BrakingKF(fam, braking_rate_q=1e-3),
            "gsma_merged": GSMA(fam, VALUES, prior=(1.0, 0.15), merge=True),
            "qgrbpf_gh": QGRBPF(fam, [(0.0, 1.0)], 3, braking_rate_q=1e-3, prior=(1.0, 0.15),
                                quadrature=True)}[name]
    rng = np.random.default_rng(seed)
    filt.reset(X0, P0, rng, t0=0.0)
    t = 0.0
    for a, y, mask, dt in steps:
        with np.errstate(over="ignore", invalid="ignore"):
            e = filt.step(a, y, mask, rng, t=t + dt)
        if e.accepted:
            t += dt
        assert np.all(np.isfinite(e.mean)) and np.all(np.isfinite(e.cov))
        assert e.cov[3, 3] >= 0.0
        assert filt.t == pytest.approx(t)
