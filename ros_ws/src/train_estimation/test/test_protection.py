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


def test_one_gaussian_gives_k_sigma_both_ways():
    ahead, behind = protection_levels(4.0, (), 1e-7)
    assert math.isclose(ahead, 2.0 * 5.326723886, rel_tol=1e-9) and ahead == behind


def test_a_separated_hypothesis_widens_its_side_only_by_its_shift():
    a0, b0 = protection_levels(1.0, [Hypothesis("clock", 0.0)], 1e-7)
    a1, b1 = protection_levels(1.0, [Hypothesis("clock", 30.0)], 1e-7)
    assert math.isclose(a1 - a0, 30.0) and math.isclose(b1, b0)


@pytest.mark.parametrize("var,hyp", [(math.nan, ()), (-1.0, ()), (0.0, ()),
                                     (1.0, (Hypothesis("x", math.inf),)),
                                     (1.0, (Hypothesis("x", 0.0, math.nan),))])
def test_no_bound_without_a_finite_positive_variance(var, hyp):
    assert protection_levels(var, hyp) == (math.inf, math.inf)


def test_labels_against_the_alert_limit():
    assert label(9.9, 10.0, 10.0) == OK
    assert label(10.1, 1.0, 10.0) == DEGRADED
    assert label(1.0, 1.0, 10.0, alarm=True) == ALARM
    assert label(math.inf, 1.0, 10.0) == ALARM
