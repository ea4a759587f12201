"""The train clock model's contract, through the runner's clocks and door alone
(``tools.clock_runs``: a cruising train through the integrity campaign's link, no filter).
``./run bench clocks`` prints the same figures over an hour per link and every step."""

import math

import pytest

from train_estimation.tools.clock_runs import run_link


@pytest.mark.parametrize("counter", [True, False])
def test_a_clean_jittery_link_is_one_clock_with_no_step(counter):
    """Ten minutes at 10 Hz on one clock (commands and readings share the epoch and the rate),
    latency 50 ms plus an exponential jitter of mean 200 ms, 5 % lost: no step declared, no
    reading refused, the clocks judged one, the drift within a few ppm of 0, and the clock's
    centre below the least-latency line by less than the jitter's spread (its standard
    deviation is its mean). A rate fit whose stated error was half its spread judged these
    clocks separate (a -1.9e-4 rate difference at 5 standard errors)."""
    jitter = 0.2
    r = run_link(600.0, 10.0, counter, jitter, 0.05, None, seed=0)
    assert r["false_steps_per_h"] == 0 and r["refused"] == 0, r
    assert not r["separate"], r
    assert abs(r["drift_ppm"]) < 20.0, r
    assert -1e3 * jitter < r["bias_ms"] < 0.0, r


@pytest.mark.parametrize("counter", [False, True])
@pytest.mark.parametrize("drain", [2.0, 1.5, 1.2])
def test_a_queue_that_drains_is_no_step(drain, counter):
    """At 10 Hz, a link that holds the readings for 1 s every 30 s and then delivers them
    ``drain`` times as fast as they were sampled: no step declared, no reading refused, one
    clock judged one, the filter's time on the readings' own. Their offsets climb back to the
    clock as the queue drains, which a step never does (a rank trend, StepWatch._returning):
    taken for steps without a counter, 72 to 114 per hour, the filter's time ran 8 to 15 s off
    within ten minutes; and the rate fit, judging its line's level by the offsets' centre,
    took the slow drains' climbs for slope (250-2,300 ppm, the clocks judged separate)."""
    r = run_link(600.0, 10.0, counter, 0.03, 0.05, None, seed=0, queue=drain)
    assert r["false_steps_per_h"] == 0 and r["refused"] == 0, r
    assert r["time_err_all_ms"] < 1.0 and not r["separate"], r


@pytest.mark.parametrize("rate", [10.0, 1.0])
@pytest.mark.parametrize("rise", [0.45, 1.5])
def test_a_latency_that_rises_and_stays_is_no_step(rate, rise):
    """Without a sample counter, the link's latency rises by ``rise`` s and stays (a slower
    route): the offsets fall as a backward step's would, but the stamps run on in the stream's
    slots (StepWatch._stamps_ran_on): no step, one move of the latency, the filter's time on
    the readings' own. Taken for a -1.5 s step, crh3_high_speed's estimates were up to 119 m
    off (kf, the integrity campaign's fault ``route``)."""
    r = run_link(900.0, rate, False, 0.03, 0.05, None, seed=0, route=rise)
    assert r["false_steps_per_h"] == 0 and r["latency_moved"] == 1 and r["refused"] == 0, r
    assert r["time_err_all_ms"] < 1.0, r


@pytest.mark.parametrize("step", [-3.0, 0.1])
def test_a_step_is_measured_exactly_on_the_sample_grid(step):
    """At 1 Hz with a sample counter a step (here -3 s or +0.1 s, inside a 50 ms jitter) is
    measured by the grid, not the arrivals: re-anchored by exactly the step, the readings after
    it fused at their true sampling times, decided after min_judged (9) readings of the new
    clock (the old clock's silence alone would have taken six on this link, which lost 3 of
    the 131 slots before the step: clocks.silence_risk), the estimates published meanwhile in
    doubt."""
    r = run_link(900.0, 1.0, True, 0.05, 0.05, step, seed=0)
    assert r["shift_err_ms"] == pytest.approx(0.0, abs=1e-3), r
    assert r["time_err_ms"] == pytest.approx(0.0, abs=1e-3), r
    assert r["decided_readings"] == 9 and r["doubted"] == 9, r
    assert r["refused"] == 0, r


def test_without_a_counter_a_step_beyond_the_jitter_is_measured_from_the_arrivals():
    """Without a sample counter the step is the held readings' offsets against the clock's
    centre: a -3 s step at 1 Hz on a 50 ms jitter is measured to tens of milliseconds."""
    r = run_link(900.0, 1.0, False, 0.05, 0.05, -3.0, seed=0)
    assert math.isfinite(r["decided_s"]) and abs(r["shift_err_ms"]) < 50.0, r


@pytest.mark.xfail(strict=True, reason="without a sample counter a step within the bar "
                   "(10 robust spreads of the offsets, about 0.3 s on a 50 ms exponential jitter) "
                   "is not told from jitter: the filter's time stays 0.1 s off; a change "
                   "detector on the clock's envelope would see it")
def test_without_a_counter_a_small_step_is_declared():
    r = run_link(900.0, 1.0, False, 0.05, 0.05, 0.1, seed=0)
    assert math.isfinite(r["decided_s"]) and abs(r["shift_err_ms"]) < 50.0, r

