"""The odometer's calibration against the balises (``core/online/odometer_scale.py``): exact
against a dense solve, calibrated by seeded Monte Carlo, a change of scale acting forward only,
the count relocated on two agreeing balises and never on one; and through the estimators, an
odometer 2 % off is never wrong-side."""

import math
import os
import sys

import numpy as np
import pytest

from train_estimation.core.online.odometer_scale import BaliseFix, OdometerCalibration
from train_estimation.tools import faults as F

sys.path.insert(0, os.path.dirname(__file__))
from clocks import adapter, run  # noqa: E402


def _static(start=100.0, start_std=5.0, scale_std=0.01):
    return OdometerCalibration(start, start_std, scale_std, count_walk=0.0, scale_walk=0.0)


def test_balises_fused_one_by_one_equal_the_dense_least_squares_solve():
    """Without walks the parameters are constant and the balises linear in them: the recursive
    estimate is the Gaussian posterior of the stacked problem, solved in one go."""
    rng = np.random.default_rng(1)
    cal = _static()
    d = np.sort(rng.uniform(50.0, 6000.0, 7))
    r = rng.uniform(0.5, 3.0, 7)
    b = 98.0 + 1.013 * d + rng.normal(0.0, np.sqrt(r))
    for bi, ri, di in zip(b, r, d):
        assert cal.balise(BaliseFix(float(bi), float(ri), float(di)))
    H = np.column_stack([np.ones_like(d), d])
    P0 = np.diag([25.0, 1e-4])
    info = np.linalg.inv(P0) + H.T @ (H / r[:, None])
    Sigma = np.linalg.inv(info)
    theta = Sigma @ (np.linalg.solve(P0, [100.0, 1.0]) + H.T @ (b / r))
    np.testing.assert_allclose(cal.theta, theta, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(cal.Sigma, Sigma, rtol=1e-7, atol=1e-14)


def test_the_stated_variance_is_the_error_variance_in_seeded_monte_carlo():
    """Scales drawn from the prior, balises every 400-900 m with their stated noise: the
    position error at a count 500 m past the last balise, over its stated sd, has a mean
    square of 1 within 4 standard errors of a chi-square(1) mean (sqrt(2 / n))."""
    rng = np.random.default_rng(7)
    n = 2000
    z2 = np.empty(n)
    for i in range(n):
        x0 = 100.0 + rng.normal(0.0, 5.0)
        c = 1.0 + rng.normal(0.0, 0.01)
        cal = _static()
        d = 0.0
        for _ in range(4):
            d += rng.uniform(400.0, 900.0)
            cal.balise(BaliseFix(x0 + c * d + rng.normal(0.0, 1.0), 1.0, d))
        dq = d + 500.0
        z2[i] = (cal.position(dq) - (x0 + c * dq)) ** 2 / cal.position_variance(dq)
    assert abs(z2.mean() - 1.0) <= 4.0 * math.sqrt(2.0 / n), z2.mean()


def test_a_change_of_scale_acts_on_the_distance_run_after_it():
    """The walk on the scale is integrated along the count: a step of the scale at the count
    s moves the position at d by (d - s) times it, so the variance at d gains q (d^3 - a^3) / 3
    over a walk from a; any path between the same counts adds the same."""
    q = 1e-8
    cal = OdometerCalibration(0.0, 1.0, 1e-3, count_walk=0.0, scale_walk=q)
    cal.walk_to(5000.0)
    assert cal.position_variance(5000.0) == pytest.approx(1.0 + (1e-3 * 5000.0) ** 2
                                                          + q * 5000.0 ** 3 / 3.0)
    assert cal.position_variance(6000.0) == pytest.approx(
        1.0 + (1e-3 * 6000.0) ** 2 + q * (6000.0 ** 3 - 1000.0 ** 3) / 3.0)
    steps = OdometerCalibration(0.0, 1.0, 1e-3, count_walk=1e-3, scale_walk=q)
    direct = OdometerCalibration(0.0, 1.0, 1e-3, count_walk=1e-3, scale_walk=q)
    for d in np.linspace(0.0, 5000.0, 37):
        steps.walk_to(float(d))
    direct.walk_to(5000.0)
    np.testing.assert_allclose(steps.Sigma, direct.Sigma, rtol=1e-12)


@pytest.mark.parametrize("offset", [-30.0, -10.0, 10.0, 30.0])
def test_a_balise_that_lies_is_covered_until_later_balises_outvote_it(offset):
    """A balise 10-30 m from where its telegram says (a survey error), fused because the
    scale is not known yet, moves the count's calibration; the published variance covers the
    solution without it (solution separation), so the truth stays within 5 sd ahead of it,
    and three good balises later the count is right again."""
    cal = OdometerCalibration(100.0, 5.0, 0.01)
    truth = lambda d: 100.0 + d  # noqa: E731  (an exact odometer)
    worst = 0.0
    for k, db in enumerate((350.0, 1000.0, 1600.0, 2300.0, 2900.0, 3500.0)):
        lie = offset if k == 1 else 0.0
        cal.walk_to(db)
        cal.balise(BaliseFix(truth(db) + lie, 2.0, db))
        for d in np.arange(db, db + 600.0, 50.0):
            cal.walk_to(float(d))
            var = cal.consider(float(d), 20.0)[0, 0]
            worst = max(worst, abs(cal.position(float(d)) - truth(float(d))) / math.sqrt(var))
    assert worst <= 5.0, worst
    assert abs(cal.position(4000.0) - truth(4000.0)) < 3.0


def test_one_far_balise_is_refused_and_two_agreeing_ones_relocate_the_count():
    cal = _static()
    assert cal.balise(BaliseFix(600.0, 1.0, 500.0))  # on the count
    far = BaliseFix(1200.0, 1.0, 1000.0)  # 100 m ahead of the count: sd ~ 5.2 m
    assert not cal.balise(far)
    assert cal.held == far and cal.relocated == 0
    # a second balise 100 m off too (sd ~ 10 m there): the count lost 100 m (a slide),
    # relocated onto both
    assert cal.balise(BaliseFix(1700.0, 1.0, 1500.0))
    assert cal.relocated == 1 and cal.held is None
    assert cal.position(1500.0) == pytest.approx(1700.0, abs=1.0)
    assert cal.position(2000.0) == pytest.approx(2200.0, abs=3.0)
    assert abs(cal.position(2000.0) - 2200.0) <= 3.0 * math.sqrt(cal.position_variance(2000.0))


def test_two_far_balises_that_disagree_with_each_other_move_nothing():
    cal = _static()
    assert cal.balise(BaliseFix(600.0, 1.0, 500.0))
    theta = cal.theta.copy()
    assert not cal.balise(BaliseFix(1200.0, 1.0, 1000.0))  # +100 m
    assert not cal.balise(BaliseFix(1500.0, 1.0, 1500.0))  # -100 m: not the same offset
    assert cal.relocated == 0
    np.testing.assert_array_equal(cal.theta, theta)


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_a_non_finite_balise_is_refused_without_touching_the_state(bad):
    cal = _static()
    theta, Sigma = cal.theta.copy(), cal.Sigma.copy()
    assert not cal.balise(BaliseFix(bad, 1.0, 500.0))
    assert not cal.balise(BaliseFix(600.0, 1.0, bad))
    assert not cal.balise(BaliseFix(600.0, -1.0, 500.0))
    np.testing.assert_array_equal(cal.theta, theta)
    np.testing.assert_array_equal(cal.Sigma, Sigma)


@pytest.mark.parametrize("kind", ["robust", "kf"])
@pytest.mark.parametrize("scale", [-0.02, 0.02])
def test_an_odometer_2_percent_off_is_never_wrong_side(kind, scale):
    """Every estimator read the odometer's count as the position to a metre: 2 % off, it was
    sure of a position drifting 20 m per km. The calibration carries the scale: no estimate is
    OK while more than 1 m and 5 sd off, and the balises bring the error back under 3 m after
    the second one."""
    sc, res = run("metro_demo", 3, 240.0)
    fl = F.inject(res.events(), F.Fault("odometer_scale", scale, 0.0), np.random.default_rng(0))
    a = adapter(sc, kind)
    outs, emitted, runner = F.run(fl.events, a, 0.1)
    s = F.score(outs, emitted, fl, res.truth, 10.0, 240.0 + F.LATENCY)
    assert s["wrong_side"] == 0 and s["bad_cov"] == 0, s
    assert a.cal.theta[1] == pytest.approx(1.0 / (1.0 + scale), abs=0.005)
    t2 = sorted(e[3] for e in fl.events if e[0] == "balise")[1] + 5.0
    tt = np.array([o.stamp for o in outs]) - F.EPOCH
    err = np.array([o.position for o in outs]) - np.interp(tt, res.truth["t"],
                                                            res.truth["position"])
    assert np.max(np.abs(err[emitted > t2])) < 3.0


def test_the_scale_learnt_on_one_run_starts_the_next():
    """A wheel 2 % off: a run from the default prior (1 +- 0.01) learns the scale from the
    balises and reports it in the parameter's terms (reading / true distance, as diagnose
    does); the next run of the train, started from it, is within 3 m before its second balise
    where the default start is metres further off, and neither is ever wrong-side."""
    scale = 0.02

    def one(seed, **cfg):
        sc, res = run("metro_demo", seed, 240.0)
        fl = F.inject(res.events(), F.Fault("odometer_scale", scale, 0.0),
                      np.random.default_rng(seed))
        a = adapter(sc, "robust", **cfg)
        outs, emitted, _ = F.run(fl.events, a, 0.1)
        s = F.score(outs, emitted, fl, res.truth, 10.0, 240.0 + F.LATENCY)
        assert s["wrong_side"] == 0 and s["bad_cov"] == 0, s
        t2 = sorted(e[3] for e in fl.events if e[0] == "balise")[1]
        tt = np.array([o.stamp for o in outs]) - F.EPOCH
        err = np.array([o.position for o in outs]) - np.interp(tt, res.truth["t"],
                                                                res.truth["position"])
        return a.odometer_scale(), float(np.max(np.abs(err[emitted < t2])))

    (learnt, sd), _ = one(3)
    assert learnt == pytest.approx(1.0 + scale, abs=3 * sd) and sd < 2e-3, (learnt, sd)
    _, cold = one(5)
    (_, sd2), warm = one(5, odometer_scale=learnt, odometer_scale_std=max(sd, 1e-3))
    assert warm < 3.0 < cold, (warm, cold)
    assert sd2 < sd + 1e-12  # a second run knows it at least as well


def test_the_prior_scale_is_the_parameters_inverse():
    cal = OdometerCalibration(100.0, 1.0, 1e-3, scale=1.0 / 1.02)
    assert cal.position(1020.0) == pytest.approx(1100.0)
    with pytest.raises(ValueError):
        OdometerCalibration(100.0, 1.0, 1e-3, scale=0.0)
