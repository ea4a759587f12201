"""Protection levels against exact oracles: the interval's risk computed from the normal
distribution of each hypothesis, the multiplier, the labels."""

import math
from statistics import NormalDist

import numpy as np
import pytest

from train_estimation.core.online.protection import (
    ALARM,
    DEGRADED,
    OK,
    RARE_SHARE,
    Hypothesis,
    k_factor,
    label,
    protection_levels,
)

N = NormalDist()


def test_k_factor_is_the_two_sided_normal_quantile():
    assert math.isclose(k_factor(1e-7), 5.326723886, rel_tol=1e-9)
    assert math.isclose(k_factor(0.05), 1.959963985, rel_tol=1e-9)
    with pytest.raises(ValueError):
        k_factor(0.0)


@pytest.mark.parametrize("seed", range(5))
def test_the_interval_holds_under_every_hypothesis_with_the_stated_risk(seed):
    """Whichever live hypothesis is true (the train at shift_i with sd sqrt(var + extra_i)),
    the probability that it lies outside [x - behind, x + ahead] is at most the risk: computed
    exactly from the normal distribution, for random hypothesis sets."""
    rng = np.random.default_rng(seed)
    risk = 10.0 ** rng.uniform(-9, -3)
    var = rng.uniform(0.01, 25.0)
    hyps = [Hypothesis("h", rng.normal(0, 20.0), rng.uniform(0, 10.0))
            for _ in range(rng.integers(0, 5))]
    ahead, behind = protection_levels(var, hyps, risk)
    for h in [Hypothesis("fault-free", 0.0)] + hyps:
        sd = math.sqrt(var + h.extra)
        outside = N.cdf((-behind - h.shift) / sd) + 1.0 - N.cdf((ahead - h.shift) / sd)
        assert outside <= risk * (1 + 1e-9)
    # and it is tight: under one of the hypotheses each side's bound is met with equality
    sides = [(h.shift + k_factor(risk) * math.sqrt(var + h.extra)) for h in
             [Hypothesis("f", 0.0)] + hyps]
    assert math.isclose(ahead, max(sides), rel_tol=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_the_risk_is_met_averaged_over_any_prior_on_the_hypotheses(seed):
    """One hypothesis is true and which is unknown: for any prior over them (random ones,
    and all the weight on each in turn), the probability that the train lies outside the
    interval is at most the risk, computed exactly; with the whole prior on the binding
    hypothesis it equals the risk on that side's half (no needless width)."""
    rng = np.random.default_rng(100 + seed)
    risk = 10.0 ** rng.uniform(-9, -3)
    var = rng.uniform(0.01, 25.0)
    hyps = [Hypothesis("f", 0.0)] + [Hypothesis("h", rng.normal(0, 20.0), rng.uniform(0, 10.0))
                                     for _ in range(rng.integers(1, 6))]
    ahead, behind = protection_levels(var, hyps[1:], risk)
    out = np.array([(N.cdf((-behind - h.shift) / math.sqrt(var + h.extra)),
                     1.0 - N.cdf((ahead - h.shift) / math.sqrt(var + h.extra))) for h in hyps])
    priors = [rng.dirichlet(np.ones(len(hyps))) for _ in range(20)] + list(np.eye(len(hyps)))
    for p in priors:
        assert float(p @ out.sum(axis=1)) <= risk * (1 + 1e-9)
    assert math.isclose(out[:, 1].max(), risk / 2.0, rel_tol=1e-6)
    assert math.isclose(out[:, 0].max(), risk / 2.0, rel_tol=1e-6)


def _tails(var, h, ahead, behind):
    sd = math.sqrt(var + h.extra)
    return N.cdf((-behind - h.shift) / sd), 1.0 - N.cdf((ahead - h.shift) / sd)


@pytest.mark.parametrize("seed", range(8))
def test_with_stated_priors_each_side_misses_within_half_the_risk(seed):
    """Rare faults with stated priors beside hypotheses without one (module doc): on each
    side, the worst of the unprioritised hypotheses' tails plus the rare ones' tails weighted
    by their priors is at most half the risk, computed exactly; an unmonitored rare fault
    (prior within its share) is counted as certain to miss."""
    rng = np.random.default_rng(200 + seed)
    risk = 10.0 ** rng.uniform(-9, -4)
    var = rng.uniform(0.01, 25.0)
    plain = [Hypothesis("h", rng.normal(0, 20.0), rng.uniform(0, 10.0))
             for _ in range(rng.integers(0, 4))]
    rare = [Hypothesis("balise_map", rng.normal(0, 30.0), rng.uniform(0, 50.0),
                       10.0 ** rng.uniform(-12, -2)) for _ in range(rng.integers(1, 4))]
    hyps = plain + rare
    rng.shuffle(hyps)
    ahead, behind = protection_levels(var, hyps, risk)
    nominal = np.array([_tails(var, h, ahead, behind)
                        for h in [Hypothesis("f", 0.0)] + plain])
    weighted = sum(h.prior * np.array(_tails(var, h, ahead, behind)) for h in rare)
    assert np.all(nominal.max(axis=0) + weighted <= risk / 2.0 * (1 + 1e-9)), \
        (nominal, weighted, risk)
    # every rare fault below its share of the risk is left out: as if certain to miss
    share = RARE_SHARE * risk / (2.0 * len(rare))
    assert sum(h.prior for h in rare if h.prior <= share) <= RARE_SHARE * risk / 2.0


def test_a_prior_of_one_is_no_prior():
    """Prior 1 (not stated) on every hypothesis: the levels without priors, to the bit."""
    rng = np.random.default_rng(7)
    hyps = [Hypothesis("h", rng.normal(0, 20.0), rng.uniform(0, 10.0)) for _ in range(4)]
    assert protection_levels(3.0, hyps, 1e-7) == protection_levels(
        3.0, [Hypothesis(h.name, h.shift, h.extra, 1.0) for h in hyps], 1e-7)


def test_a_rare_fault_is_covered_at_its_own_multiplier_or_left_out():
    """One rare solution 30 m ahead with sd 4 m beside a fault-free sd of 1 m, at 1e-7: with
    prior 1e-5 its side is 30 + Phi^-1(1 - a / 1e-5) x 4 (a = 0.5 x 1e-7 / 2: K_j = 2.81
    against 5.33 without the prior), the other side the fault-free one's at K_N = 5.45; with a
    prior of 1e-9, within its share, it is left out and both sides are K_N sigma."""
    risk = 1e-7
    a = RARE_SHARE * risk / 2.0
    k_n = N.inv_cdf(1.0 - (1.0 - RARE_SHARE) * risk / 2.0)
    ahead, behind = protection_levels(1.0, [Hypothesis("balise_map", 30.0, 15.0, 1e-5)], risk)
    assert math.isclose(ahead, 30.0 + N.inv_cdf(1.0 - a / 1e-5) * 4.0, rel_tol=1e-9)
    assert math.isclose(behind, k_n, rel_tol=1e-9)
    assert 2.80 < N.inv_cdf(1.0 - a / 1e-5) < 2.82 and 5.44 < k_n < 5.46
    ahead, behind = protection_levels(1.0, [Hypothesis("balise_map", 30.0, 15.0, 1e-9)], risk)
    assert math.isclose(ahead, k_n, rel_tol=1e-9) and math.isclose(behind, k_n, rel_tol=1e-9)


def test_one_gaussian_gives_k_sigma_both_ways():
    ahead, behind = protection_levels(4.0, (), 1e-7)
    assert math.isclose(ahead, 2.0 * 5.326723886, rel_tol=1e-9) and ahead == behind


def test_a_separated_hypothesis_widens_its_side_only_by_its_shift():
    a0, b0 = protection_levels(1.0, [Hypothesis("clock", 0.0)], 1e-7)
    a1, b1 = protection_levels(1.0, [Hypothesis("clock", 30.0)], 1e-7)
    assert math.isclose(a1 - a0, 30.0) and math.isclose(b1, b0)


@pytest.mark.parametrize("var,hyp", [(math.nan, ()), (-1.0, ()), (0.0, ()),
                                     (1.0, (Hypothesis("x", math.inf),)),
                                     (1.0, (Hypothesis("x", 0.0, math.nan),)),
                                     (1.0, (Hypothesis("x", 0.0, 1.0, math.nan),)),
                                     (1.0, (Hypothesis("x", 0.0, 1.0, -0.1),))])
def test_no_bound_without_a_finite_positive_variance(var, hyp):
    assert protection_levels(var, hyp) == (math.inf, math.inf)


def test_labels_against_the_alert_limit():
    assert label(9.9, 10.0, 10.0) == OK
    assert label(10.1, 1.0, 10.0) == DEGRADED
    assert label(1.0, 1.0, 10.0, alarm=True) == ALARM
    assert label(math.inf, 1.0, 10.0) == ALARM
