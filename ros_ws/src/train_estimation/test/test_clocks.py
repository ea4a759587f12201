"""Offline clock mapping (core/numerics/clocks.py): the odometer's stamps and log times tie
the train
clock to the reference clock on which control is stamped."""

import numpy as np

from train_estimation.core.numerics.clocks import ClockFit, control_on_train_clock


def _streams(epoch, drift, latency, n=600, period=0.1):
    t = np.arange(n) * period  # reference (true) time of each sample
    odo_s = epoch + t * (1.0 + drift)  # train clock
    odo_r = 5000.0 + t + latency  # log time = reference clock at arrival
    ctrl_s = 5000.0 + t  # control: reference clock, not delayed
    return t, odo_s, odo_r, ctrl_s, ctrl_s.copy()


def test_fit_recovers_rate_and_offset():
    t, s, r, _, _ = _streams(1.7e9, 1e-3, 0.02)
    fit = ClockFit.fit(s, r)
    assert abs(fit.beta - 1 / (1 + 1e-3)) < 1e-9
    assert abs(fit.alpha - (5000.0 + 0.02)) < 1e-6
    np.testing.assert_allclose(fit.ref_of_train(s), t, atol=1e-6)


def test_control_mapped_onto_the_train_clock_up_to_the_latency():
    t, s, r, c, rc = _streams(1.7e9, 1e-3, 0.02)
    mapped = control_on_train_clock(s, r, c, rc)
    # the command issued at reference time t belongs with the sample stamped s(t); the mean
    # latency cannot be told from an offset: it stays, scaled to the train clock
    np.testing.assert_allclose(mapped, s - 0.02 * (1 + 1e-3), atol=1e-5)


def test_one_clock_is_left_alone():
    t = np.arange(300) * 0.1
    s = t.copy()  # a simulator's bag: everything stamped and logged on sim time
    same = control_on_train_clock(s, s + 0.001, t, t)
    np.testing.assert_array_equal(same, t)
    # logged on wall time at 20x: the two streams' offsets agree, nothing to map
    wall = 1.7e9 + t / 20
    np.testing.assert_array_equal(control_on_train_clock(s, wall, t, wall), t)


def _jittered(seed=0, n=6000, period=0.1):
    rng = np.random.default_rng(seed)
    s = 1.7e9 + np.arange(n) * period * (1 + 1e-4)  # train clock
    r = 5000.0 + np.arange(n) * period + 0.02 + rng.exponential(0.05, n)  # log times
    return s, r


def test_an_undisturbed_bag_keeps_the_least_squares_fit():
    s, r = _jittered()
    x = s - s[0]
    coef, *_ = np.linalg.lstsq(np.stack([np.ones_like(x), x], axis=1), r, rcond=None)
    fit = ClockFit.fit(s, r)
    assert (fit.alpha, fit.beta) == (float(coef[0]), float(coef[1]))


def test_a_recorder_stall_does_not_move_the_fit():
    """The recorder stalled 8 s (its backlog logged at once, late by up to 8 s) early, mid-way
    or near the end of a 10-minute bag. Plain least squares moved the command timing by up to
    0.2 s; the readings more than 0.5 s late are left out, and what stays of the backlog (at
    most 5 readings under 0.5 s late among 6000, leverage <= 4) moves it by < 2 ms."""
    s, r = _jittered()
    ref = ClockFit.fit(s, r)
    for start in (100.0, 300.0, 550.0, 590.0):
        stalled = r.copy()
        m = (r >= 5000.0 + start) & (r < 5008.0 + start)
        stalled[m] = 5008.0 + start
        fit = ClockFit.fit(s, stalled)
        err = np.abs(fit.ref_of_train(s) + fit.alpha - ref.ref_of_train(s) - ref.alpha)
        assert err.max() < 2e-3, (start, err.max())
