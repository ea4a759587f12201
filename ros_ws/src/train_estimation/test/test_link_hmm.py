"""Gilbert-Elliott fit (Baum-Welch on lost seq numbers): E-step against brute force, EM
monotone, recovery within the observed information, Bernoulli data, degenerate input."""

import itertools
import math

import numpy as np
import pytest
from train_core.link import Link, LinkParams

from train_estimation.core.offline import link_hmm as L

N = 6000  # a 10-minute run at 10 Hz


def link_losses(p: L.GilbertElliott, n: int, seed: int) -> np.ndarray:
    """The simulator's own link (train_core.link) as the data source."""
    lk = Link(LinkParams(model="gilbert_elliott", p_good_bad=p.p_good_bad,
                         p_bad_good=p.p_bad_good, loss_good=p.loss_good, loss_bad=p.loss_bad),
              np.random.default_rng(seed))
    return ~lk.transmit_many(n)


def brute_log_likelihood(lost, pi, a, q):
    total = 0.0
    for path in itertools.product((0, 1), repeat=len(lost)):
        pr = pi[path[0]]
        for k, z in enumerate(path):
            if k:
                pr *= a[path[k - 1], z]
            pr *= q[z] if lost[k] else 1.0 - q[z]
        total += pr
    return math.log(total)


def test_e_step_is_exact():
    rng = np.random.default_rng(0)
    lost = np.array([0, 1, 1, 0, 0, 1, 0, 0, 0, 1], bool)
    pi, a, q = L._starts(lost, 4, rng)
    st = L.statistics(lost, pi, a, q)
    for s in range(4):
        assert st[-1][s] == pytest.approx(brute_log_likelihood(lost, pi[s], a[s], q[s]),
                                          rel=1e-12)
    # the run-length E-step equals the per-sample forward-backward on a long sequence
    lost = link_losses(L.GilbertElliott(0.03, 0.2, 0.05, 0.7), 3000, 1)
    pi, a, q = L._starts(lost, 3, rng)
    g, xi, ll = L.forward_backward(lost, pi, a, q)
    st = L.statistics(lost, pi, a, q)
    for x, y in zip(L._sums(lost, g, xi), st[:4]):
        assert np.allclose(x, y, rtol=1e-9, atol=1e-9)
    assert np.allclose(ll, st[4], rtol=1e-12)
    assert np.allclose(st[2].sum(axis=1), lost.size)  # occupancy counts every sample once


@pytest.mark.parametrize("params", [L.GilbertElliott(0.02, 0.25, 0.0, 1.0),
                                    L.GilbertElliott(0.1, 0.9, 0.1, 0.1)])
def test_em_never_decreases_the_likelihood(params):
    lost = link_losses(params, 3000, 2)
    pi, a, q = L._starts(lost, 5, np.random.default_rng(3))
    *_, hist, _ = L.baum_welch(lost, pi, a, q, max_iter=150, tol=0.0, prune=None)
    step = np.diff(hist, axis=0)
    assert hist.shape[0] == 151
    assert step.min() >= -1e-9 * np.abs(hist).max(), step.min()


# (true parameters, seed): interior losses, so that every parameter has an observed information
SETS = [L.GilbertElliott(0.01, 0.1, 0.02, 0.8), L.GilbertElliott(0.03, 0.2, 0.05, 0.7),
        L.GilbertElliott(0.02, 0.3, 0.01, 0.9)]


@pytest.mark.parametrize("true", SETS)
def test_recovers_the_parameters_within_their_standard_errors(true):
    lost = link_losses(true, N, 11)
    fit = L.fit_link(lost, np.random.default_rng(5), n_starts=4)
    assert fit.bursty and fit.hmm is fit.params
    assert fit.params.loss_bad > fit.params.loss_good  # bad = the lossier state
    assert set(fit.std_errors) == {"p_good_bad", "p_bad_good", "loss_good", "loss_bad"}
    for k, se in fit.std_errors.items():
        est, tru = getattr(fit.params, k), getattr(true, k)
        # 4 standard errors: 12 comparisons, a false failure has probability ~1e-3
        assert abs(est - tru) <= 4.0 * se, (k, est, tru, se)
    assert fit.lr > 0 and fit.log_likelihood >= fit.log_likelihood_bernoulli


def test_zero_one_losses_the_simulators_default():
    """loss_good = 0, loss_bad = 1: the hidden state is the loss; the fit heads for the
    boundary (EM approaches it slowly: it stops within a fraction of a standard error)."""
    true = L.GilbertElliott(0.02, 0.25, 0.0, 1.0)
    lost = link_losses(true, N, 4)
    fit = L.fit_link(lost, np.random.default_rng(6), n_starts=3)
    assert fit.bursty and fit.params.loss_bad > 1 - 1e-6
    assert {"p_good_bad", "p_bad_good"} <= set(fit.std_errors)
    for k, se in fit.std_errors.items():
        assert abs(getattr(fit.params, k) - getattr(true, k)) <= 4.0 * se, k
    assert fit.params.loss_good <= fit.std_errors.get("loss_good", 0.0)


def test_bernoulli_data_give_the_bernoulli_link():
    rng = np.random.default_rng(7)
    lost = rng.random(3000) < 0.12
    fit = L.fit_link(lost, rng, n_starts=2)
    assert not fit.bursty and "not bursty" in fit.reason
    q = lost.mean()
    assert fit.params == L.GilbertElliott(q, 1 - q, 0.0, 1.0)
    assert fit.loss_rate == q and fit.params.loss_rate == pytest.approx(q)
    # the GE fit on Bernoulli data gains little (its states nearly merge)
    assert fit.lr < 15.0


def test_markov_test_is_calibrated_and_sees_bursts():
    rng = np.random.default_rng(8)
    p = np.array([L.markov_test(rng.random(600) < 0.1)[1] for _ in range(400)])
    # P(p < 0.05) = 0.05 under Bernoulli: 400 draws, 4 binomial standard deviations
    assert abs(np.mean(p < 0.05) - 0.05) <= 4 * math.sqrt(0.05 * 0.95 / 400)
    lost = link_losses(L.GilbertElliott(0.02, 0.25, 0.0, 1.0), 3000, 9)
    assert L.markov_test(lost)[1] < 1e-6


def test_bootstrap_lr_test():
    rng = np.random.default_rng(10)
    lost = link_losses(L.GilbertElliott(0.03, 0.2, 0.0, 1.0), 1000, 12)
    fit = L.fit_link(lost, rng, n_starts=2, n_boot=4, alpha=0.25)
    assert fit.bursty and fit.p_value == pytest.approx(0.2)  # no replicate comes near
    assert "bootstrap" not in fit.reason


@pytest.mark.parametrize("lost, reason", [
    (np.zeros(0, bool), "too short"), (np.array([True]), "too short"),
    (np.zeros(10, bool), "too short"), (np.zeros(500, bool), "no sample lost"),
    (np.ones(500, bool), "every sample lost")])
def test_degenerate_input(lost, reason):
    fit = L.fit_link(lost, np.random.default_rng(0))
    assert not fit.bursty and reason in fit.reason and fit.hmm is None
    if lost.size:
        q = float(lost.mean())
        assert fit.params == L.GilbertElliott.bernoulli(q) and fit.n == lost.size


def test_very_short_but_fittable():
    lost = np.array([0, 0, 1, 1, 1, 0, 0, 0, 0, 1, 1, 0, 0, 0, 0, 0, 0, 1, 1, 1, 0, 0], bool)
    fit = L.fit_link(lost, np.random.default_rng(1), n_starts=3)
    assert fit.hmm is not None and np.isfinite(fit.log_likelihood)
    for v in fit.hmm.as_dict().values():
        assert 0.0 <= v <= 1.0


def test_lost_from_seq():
    seq = np.array([5, 6, 9, 7, 7, 12], dtype=np.uint32)  # reordered, a duplicate
    assert L.lost_from_seq(seq).tolist() == [0, 0, 0, 1, 0, 1, 1, 0]
    wrap = np.array([2**32 - 2, 2**32 - 1, 1, 2], dtype=np.uint32)  # 0 lost across the wrap
    assert L.lost_from_seq(wrap).tolist() == [0, 0, 1, 0, 0]
    assert L.lost_from_seq([]).size == 0


def test_labels_bad_is_the_lossier_state():
    a = L._matrix(np.array([0.3]), np.array([0.05]))[0]
    g = L._labelled(a, np.array([0.9, 0.1]))
    assert g == L.GilbertElliott(0.05, 0.3, 0.1, 0.9)
