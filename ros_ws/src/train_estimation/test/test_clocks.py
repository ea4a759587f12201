"""Offline clock mapping (core/clocks.py): the odometer's stamps and log times tie the train
clock to the reference clock on which control is stamped."""

import numpy as np

from train_estimation.core.clocks import ClockFit, control_on_train_clock


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
