"""Radio link statistics against the formulas, with tolerances derived from the statistics.

Tolerance: a count of n Bernoulli(P) trials has standard deviation sqrt(n P (1 - P)); by the normal
approximation (n = 1e5, n P (1 - P) > 1e3) a two-sided 4.5 sigma band is violated with
probability 6.8e-6 by a correct implementation, while a wrong formula (e.g. 1 - p^(r-1) = 0.75
instead of 0.875) is off by > 100 sigma.
"""

import math

import numpy as np
import pytest
from scipy import stats
from train_core.link import Link, LinkParams, bernoulli_received_probability, burst_lengths

Z = 4.5
N = 100_000


def test_wen_formula():
    assert bernoulli_received_probability(0.5, 3) == 0.875  # Wen eq. (12) example
    for p in (0.0, 0.1, 0.5, 0.9):
        for r in (1, 2, 5):
            assert bernoulli_received_probability(p, r) == pytest.approx(1 - p**r, abs=1e-15)


@pytest.mark.parametrize("p,r", [(0.5, 3), (0.3, 1), (0.8, 4)])
def test_bernoulli_received_fraction_in_binomial_interval(p, r):
    P = bernoulli_received_probability(p, r)
    link = Link(LinkParams("bernoulli", p=p, r=r), np.random.default_rng(12345))
    ok = link.transmit_many(N)
    sigma = math.sqrt(P * (1 - P) / N)
    assert abs(ok.mean() - P) < Z * sigma
    assert link.dropped == N - ok.sum() and link.sent == N


def test_transmit_many_equals_repeated_transmit():
    params = LinkParams("bernoulli", p=0.5, r=3)
    a = Link(params, np.random.default_rng(7)).transmit_many(1000)
    link = Link(params, np.random.default_rng(7))
    b = np.array([link.transmit() for _ in range(1000)])
    assert np.array_equal(a, b)


def test_gilbert_elliott_bursts_geometric_with_mean_one_over_p_bad_good():
    pgb, pbg = 0.05, 0.25
    params = LinkParams("gilbert_elliott", p_good_bad=pgb, p_bad_good=pbg)
    ok = Link(params, np.random.default_rng(2024)).transmit_many(N)
    L = burst_lengths(ok)
    # Bursts are i.i.d. Geometric(q = p_bad_good) on {1, 2, ...}: mean 1/q, sd sqrt(1-q)/q.
    q = pbg
    se = math.sqrt(1 - q) / q / math.sqrt(len(L))
    assert abs(L.mean() - 1 / q) < Z * se
    # Shape: chi-square goodness of fit on {1..9, >=10}; reject only at p < 1e-5.
    k = np.arange(1, 10)
    pmf = np.append((1 - q) ** (k - 1) * q, (1 - q) ** 9)
    obs = np.append([np.sum(L == j) for j in k], np.sum(L >= 10))
    assert stats.chisquare(obs, pmf * len(L)).pvalue > 1e-5
    # Received fraction: stationary P(good) = pbg / (pgb + pbg); the indicator of a two-state
    # chain with lag-1 correlation rho = 1 - pgb - pbg has asymptotic variance
    # pi (1 - pi) (1 + rho) / (1 - rho) per sample.
    pi = params.received_probability
    assert pi == pytest.approx(pbg / (pgb + pbg))
    rho = 1 - pgb - pbg
    sigma = math.sqrt(pi * (1 - pi) * (1 + rho) / (1 - rho) / N)
    assert abs(ok.mean() - pi) < Z * sigma


def test_bernoulli_bursts_are_not_gilbert_elliott_like():
    """Sanity of the burst statistic itself: Bernoulli losses give Geometric(P) bursts."""
    P = 0.875
    ok = Link(LinkParams("bernoulli", p=0.5, r=3), np.random.default_rng(3)).transmit_many(N)
    L = burst_lengths(ok)
    se = math.sqrt(1 - P) / P / math.sqrt(len(L))
    assert abs(L.mean() - 1 / P) < Z * se


def test_burst_lengths_helper():
    assert list(burst_lengths(np.array([1, 0, 0, 1, 0, 1, 1, 0, 0, 0], bool))) == [2, 1, 3]
    assert list(burst_lengths(np.ones(5, bool))) == []


def test_gilbert_elliott_in_time_slots():
    """With a time slot the chain steps per slot elapsed: one message per slot is the per-message
    chain exactly (same draws), and a topic sending every 200 slots meets the channel at its
    stationary state, nearly independently (lag-1 correlation lambda^200 ~ 0), not in bursts of
    its own messages."""
    pgb, pbg = 0.03, 0.05  # slow channel: bursts of 20 slots
    params = LinkParams("gilbert_elliott", p_good_bad=pgb, p_bad_good=pbg)
    per_msg = Link(params, np.random.default_rng(5)).transmit_many(2000)
    slotted = Link(params, np.random.default_rng(5), slot=0.1)
    same = np.array([slotted.send(0.1 * k) is not None for k in range(2000)])
    assert np.array_equal(per_msg, same)
    n = 4000
    sparse = Link(params, np.random.default_rng(6), slot=0.1)
    ok = np.array([sparse.send(20.0 * k) is not None for k in range(n)])
    pi = params.received_probability
    assert abs(ok.mean() - pi) < Z * math.sqrt(pi * (1 - pi) / n)
    # the chain per message would give bursts of mean 1 / p_bad_good = 20; here ~ 1 / pi_good
    L = burst_lengths(ok)
    assert abs(L.mean() - 1 / pi) < Z * math.sqrt(1 - pi) / pi / math.sqrt(len(L))
