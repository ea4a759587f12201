"""The train clock model's contract, through the runner's clocks and door alone
(``tools.clock_runs``: a cruising train through the integrity campaign's link, no filter).
``./run bench clocks`` prints the same figures over an hour per link and every step."""

import functools
import math

import numpy as np
import pytest

from train_estimation.core.numerics import envelope
from train_estimation.core.numerics.clocks import TREND_N, StepWatch
from train_estimation.tools.clock_runs import STEP_AT, run_link


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
@pytest.mark.parametrize("counter, count_clock", [(False, False), (False, True), (True, True)])
def test_a_latency_that_rises_and_stays_is_no_step(rate, rise, counter, count_clock):
    """The link's latency rises by ``rise`` s and stays (a slower route): the offsets fall as a
    backward step's would, but the stamps run on in the stream's slots
    (StepWatch._stamps_ran_on): no step, one move of the latency, the filter's time on the
    readings' own. Taken for a -1.5 s step, crh3_high_speed's estimates were up to 119 m off
    (kf, the integrity campaign's fault ``route``). Where the sample grid or the odometer's
    count judges the stamps (the train moving: StepWatch._count_resid) every reading lies on
    its clock and none is held; min_judged of them in a row behind the clock by more than the
    bar are the latency's move (StepWatch._latency_moved). Either way the clock's offset ends
    at the new latency (the link's floor plus ``rise``, within its jitter); left to follow
    the readings as they came, it stayed at the old one after 1.5 s (offset 14-21 ms off the
    old floor: every later reading late, fused by rewinding)."""
    r = run_link(900.0, rate, counter, 0.03, 0.05, None, seed=0, route=rise,
                 count_clock=count_clock)
    assert r["false_steps_per_h"] == 0 and r["refused"] == 0, r
    assert r["latency_moved"] == 1, r
    assert r["doubted"] == 0 or not count_clock, r  # (by the arrivals, held until judged)
    assert r["time_err_all_ms"] < 1.0, r
    assert abs(r["bias_ms"] + 1e3 * rise) < 50.0, r  # within the link's jitter (30 ms mean)


@pytest.mark.parametrize("rate", [10.0, 1.0])
@pytest.mark.parametrize("period", [60.0, 120.0])
def test_a_latency_that_wanders_is_no_clock_rate(period, rate):
    """Without a sample counter, on one clock, the link's latency rises by 0.4 s from 120 s and
    falls back over ``period`` s (a raised cosine): the offsets dip and climb back as a clock
    whose rate wandered would, but a clock's rate does not wander (StreamClock._off leaves the
    envelope's dips out of the rate fit). One clock judged one, the rate within 4 of its stated
    standard errors of 0, the filter's time on the readings' own. Fitted, the dip's climb back
    read as +528 ppm over two minutes at 10 Hz, the clocks were judged separate and the
    filter's time ended 0.40 s off."""
    r = run_link(600.0, rate, False, 0.05, 0.05, None, seed=0, wander=(0.4, period))
    assert r["false_steps_per_h"] == 0 and r["refused"] == 0, r
    assert not r["separate"] and abs(r["drift_ppm"]) <= 4.0 * r["drift_se_ppm"], r
    assert r["time_err_all_ms"] < 1.0, r


@pytest.mark.parametrize("count_clock", [False, True])
def test_a_queue_that_drains_slowly_is_no_forward_step(count_clock):
    """Without a sample counter at 10 Hz the link holds the readings for 1 s every 30 s and
    delivers them 1.2 times as fast as they were sampled (30 ms jitter): a drain that slow can
    pass for a slower route, and the readings after it then lie above the moved centre as a
    forward step's would. But a clock stepped forward by d stamps its first reading a period
    and d after the last one; these continue the stream, so the latency fell: no step, the
    filter's time on the readings' own. Taken for steps: two of +0.3-0.4 s in 800 s and the
    filter's time 0.6 s off."""
    r = run_link(800.0, 10.0, False, 0.03, 0.05, None, seed=0, queue=1.2, count_clock=count_clock)
    assert r["false_steps_per_h"] == 0 and r["refused"] == 0, r
    assert r["time_err_all_ms"] < 1.0, r


@pytest.mark.parametrize("rate", [10.0, 1.0])
def test_a_latency_that_falls_and_stays_is_no_clock_rate(rate):
    """Without a sample counter, on one clock, the link's latency falls by 30 ms at 600 s and
    stays (a faster route), less than the step watch's least move (50 ms): the offsets' level
    rises, a new level of the rate fit's points, not a slope (StreamClock._level_move).
    Absorbed into the line, they read as +75 ppm at 49 standard errors at 10 Hz (15 at 1 Hz)
    after ten more minutes."""
    r = run_link(1200.0, rate, False, 0.05, 0.05, None, seed=0, route=-0.03)
    assert r["false_steps_per_h"] == 0 and r["refused"] == 0, r
    assert not r["separate"] and abs(r["drift_ppm"]) <= 4.0 * r["drift_se_ppm"], r
    assert r["time_err_all_ms"] < 1.0, r


def test_a_latency_that_rises_a_little_and_stays_is_no_clock_rate():
    """The mirror at 10 Hz: the latency rises by 10 ms at 600 s and stays, about one standard
    deviation of the rate fit's envelope points. Each point lies a little below the line, and
    the line, judged point by point, tilted towards them (-13 to -20 standard errors in seeds
    1-4, the dip test never firing); the points on two levels of one slope are one more
    intercept (StreamClock._level_move's likelihood ratio over the candidate times). Seed 1
    (-15 standard errors without it); `./run bench clocks` runs seeds 0-5 of this link."""
    r = run_link(1200.0, 10.0, False, 0.05, 0.05, None, seed=1, route=0.01)
    assert r["false_steps_per_h"] == 0 and r["refused"] == 0, r
    assert not r["separate"] and abs(r["drift_ppm"]) <= 4.0 * r["drift_se_ppm"], r
    assert r["time_err_all_ms"] < 1.0, r


@pytest.mark.parametrize("step", [-3.0, 0.1])
def test_a_step_is_measured_exactly_on_the_sample_grid(step):
    """At 1 Hz with a sample counter a step (here -3 s or +0.1 s, inside a 50 ms jitter) is
    measured by the grid, not the arrivals: re-anchored by exactly the step, the readings after
    it fused at their true sampling times, decided after min_judged (9) readings of the new
    clock (the old clock's silence alone would have taken six on this link, which lost 3 of
    the 131 slots before the step: clocks.silence_risk), the estimates published meanwhile in
    doubt; the ones after carry the step's burst hypothesis, from the ninth reading of the new
    clock to its prior's last (integrity.burst_readings)."""
    from train_estimation.core.online.integrity import IntegrityParams, burst_readings

    r = run_link(900.0, 1.0, True, 0.05, 0.05, step, seed=0)
    assert r["shift_err_ms"] == pytest.approx(0.0, abs=1e-3), r
    assert r["time_err_ms"] == pytest.approx(0.0, abs=1e-3), r
    assert r["decided_readings"] == 9 and r["doubted"] == 9, r
    assert r["burst"] == burst_readings(IntegrityParams()) - 9 + 1, r
    assert r["refused"] == 0, r


@pytest.mark.parametrize("seed", [0, 3, 5])
def test_at_50_hz_a_step_is_measured_exactly_on_the_sample_grid(seed):
    """At 50 Hz with a sample counter, on a link with 0.1 s of exponential jitter (five
    periods), a +2 s step is measured by the grid as at 1 Hz: exactly, the filter's time on the
    readings' own, nothing refused. The grid's least tolerance (10 ms) was above the quarter
    period its trust asks (5 ms), so a 50 Hz grid was never trusted; the step was measured from
    the arrivals, whole periods off (20, 40 and 60 ms in 3 of 6 seeds, the filter's time as far
    off to the end), and seed 5 decided it after 118 readings, refusing 8."""
    r = run_link(640.0, 50.0, True, 0.1, 0.05, 2.0, seed)
    assert r["shift_err_ms"] == pytest.approx(0.0, abs=1e-3), r
    assert r["time_err_all_ms"] < 1.0, r
    assert r["refused"] == 0, r


@pytest.mark.parametrize("count_clock", [False, True])
def test_without_a_counter_a_step_beyond_the_jitter_is_measured_from_the_arrivals(count_clock):
    """Without a sample counter the step is the held readings' offsets against the clock's
    centre: a -3 s step at 1 Hz on a 50 ms jitter is measured to tens of milliseconds."""
    r = run_link(900.0, 1.0, False, 0.05, 0.05, -3.0, seed=0, count_clock=count_clock)
    assert math.isfinite(r["decided_s"]) and abs(r["shift_err_ms"]) < 50.0, r


@pytest.mark.parametrize("count_clock", [False, True])
def test_without_a_counter_a_small_step_is_declared(count_clock):
    """A +0.1 s step at 1 Hz without a counter, inside a 50 ms exponential jitter, a third of
    the bar (10 robust spreads of the offsets, 0.36 s): the new clock's readings lie above the
    old clock's ceiling, where latency never puts the old one's (clocks.StepWatch._envelope);
    declared and measured from the arrivals. Unwatched, the offsets' centre absorbed it and the
    filter's time stayed 0.1 s off."""
    r = run_link(900.0, 1.0, False, 0.05, 0.05, 0.1, seed=0, count_clock=count_clock)
    assert math.isfinite(r["decided_s"]) and abs(r["shift_err_ms"]) < 50.0, r



@pytest.mark.parametrize("n", [20, 600])
def test_the_envelope_test_is_exact_whatever_the_latency(n):
    """The envelope test's p-value (numerics.envelope.above_p: at least j of k new offsets
    above the largest of n earlier ones, all exchangeable) is the probability itself, for an
    exponential latency, a Gamma(4) one and a uniform one: 200,000 draws each, within four
    binomial standard errors."""
    rng = np.random.default_rng(1)
    k, m = 9, 200_000
    draws = {"exp": lambda size: rng.exponential(0.05, size),
             "gamma": lambda size: rng.gamma(4.0, 0.0125, size),
             "uniform": lambda size: rng.uniform(0.0, 0.1, size)}
    for law, draw in draws.items():
        old = -draw((m, n)).min(axis=1)  # the largest offset (minus the latency)
        new = -draw((m, k))
        j = (new > old[:, None]).sum(axis=1)
        for j0 in (1, 2, 3):
            p = envelope.above_p(k, j0, n)
            freq = float(np.mean(j >= j0))
            assert abs(freq - p) <= 4.0 * math.sqrt(p * (1.0 - p) / m) + 1e-6, (law, j0, freq, p)


def test_the_envelope_threshold_is_the_stated_rate():
    """One test per reading, each at any of TREND_N lengths: at 1e-4 false steps per hour a
    10 Hz stream is tested 36,000 times an hour, so each rejects at 1e-4 / (36,000 x 64)."""
    assert envelope.level(1e-4, 0.1, 64) == pytest.approx(1e-4 / (36_000 * 64))
    assert StepWatch(1.0, false_step_rate=1e-4).env_level == \
        pytest.approx(1e-4 / (3_600 * TREND_N))


@pytest.mark.slow
@pytest.mark.parametrize("shape", ["exp", "gamma"])
@pytest.mark.parametrize("jitter", [0.05, 0.2])
@pytest.mark.parametrize("rate", [10.0, 1.0])
def test_the_rate_fit_finds_the_clocks_rate_within_its_stated_error(rate, jitter, shape):
    """On a clean jittery link without a counter (five minutes at 10 Hz, a quarter of an hour at
    1 Hz, 5 % lost) the train clock's fitted rate lies within 4 of its stated standard errors of
    the truth: seeds of one clock shared with the commands (ten at 1 Hz, where the early points
    are few, four at 10 Hz), which ``control_clock: auto`` must judge one, and a clock 1e-4 and
    1e-3 fast and slow (the fault ``drift``), which at 1e-3 it must judge separate. A fit that
    took 4 points 20 s into a 1 Hz stream for its line held every later point off it and stayed
    at -3,988 ppm (stated error 445) for the hour; fits of 4 or 5 points stating a tenth of
    their error judged one clock two.

    No false step either, where the envelope test could err (an exponential and a Gamma(4)
    latency: the envelope sharp and blunt): the stated rate is 1e-4 per hour
    (EstimatorRunner.false_step_rate), and the one-clock runs alone are 0.33 h at 10 Hz and 2.5
    h at 1 Hz, in which one false step would reject it at p <= 2e-4, so none may be seen. (Nor
    did the envelope hold any reading on these links: the estimates in doubt were the same with
    it and without it, docs/integrity.md.)"""
    dur = 300.0 if rate == 10.0 else 900.0  # the lock and the wrong verdicts came in 30 s
    for drift, seeds in ((0.0, range(10 if rate == 1.0 else 4)), (1e-4, [0]), (-1e-4, [0]),
                         (1e-3, [0]), (-1e-3, [0])):
        for seed in seeds:
            r = run_link(dur, rate, False, jitter, 0.05, None, seed=seed, shape=shape,
                         drift=drift)
            assert abs(r["drift_ppm"] - 1e6 * drift) <= 4.0 * r["drift_se_ppm"], (drift, seed, r)
            assert r["false_steps_per_h"] == 0 and r["refused"] == 0, (drift, seed, r)
            if drift == 0.0 or abs(drift) >= 1e-3:
                assert r["separate"] == (drift != 0.0), (drift, seed, r)


@pytest.mark.parametrize("step", [0.1, 0.2, 0.5])
@pytest.mark.parametrize("rate", [10.0, 1.0])
@pytest.mark.parametrize("count_clock", [False, True])
def test_a_small_forward_step_is_declared_within_a_few_readings(rate, step, count_clock):
    """Without a counter, inside a 50 ms exponential jitter: steps of +0.1, +0.2, +0.5 s are
    declared after min_judged (9) to 12 readings of the new clock (min_judged of them above
    the old ceiling: each lies there with probability 1 - exp(-d / 50 ms), 0.86 for 0.1 s),
    and measured from the arrivals to the median offset's precision (1.25 x 50 ms / 3)."""
    r = run_link(STEP_AT + 120.0, rate, False, 0.05, 0.05, step, seed=0, count_clock=count_clock)
    assert 9 <= r["decided_readings"] <= 12, r
    assert abs(r["shift_err_ms"]) < 50.0 and r["refused"] == 0, r


@pytest.mark.parametrize("rate, step", [(1.0, -0.1), (1.0, -0.2), (10.0, -0.25)])
@pytest.mark.parametrize("count_clock", [False, True])
def test_without_a_counter_a_small_backward_step_is_declared(rate, step, count_clock):
    """Without a counter, inside a 50 ms exponential jitter, a backward step by a fraction of
    a period (-0.1 and -0.2 s at 1 Hz, -0.25 s at 10 Hz) moves the offsets down where the old
    clock's late readings lie, but it moves the stamps off the stream's sampling phase
    (StepWatch.phase), which a slower route leaves them on: held from the first reading of
    the new clock, declared after min_judged (9), and measured exactly (the phase gives the
    part of a period, the arrivals the whole periods). Unwatched, the filter's time stayed
    0.1 s off for the rest of the run."""
    r = run_link(900.0 if rate == 1.0 else 720.0, rate, False, 0.05, 0.05, step, seed=0,
                 count_clock=count_clock)
    assert math.isfinite(r["decided_s"]) and abs(r["shift_err_ms"]) < 50.0, r
    assert r["decided_readings"] == 9 and r["refused"] == 0, r
    assert r["time_err_ms"] == pytest.approx(0.0, abs=1e-3), r


@pytest.mark.parametrize("count_clock", [False, True])
def test_a_small_backward_step_is_measured_on_a_jittery_sampling_phase(count_clock):
    """The sampling loop's own jitter (each sample taken and stamped a Gaussian of 3 ms off its
    slot) scatters the phase (StepWatch.phase measures it): a -0.1 s step at 1 Hz without a
    counter is still declared after min_judged (9) readings, and measured to the median
    residual's precision (3 of its standard errors, 1.25 x 3 ms / 3)."""
    r = run_link(900.0, 1.0, False, 0.05, 0.05, -0.1, seed=0, sampling=0.003,
                 count_clock=count_clock)
    assert r["decided_readings"] == 9 and r["refused"] == 0, r
    assert abs(r["shift_err_ms"]) < 3.0 * 1.25 * 3.0 / 3.0, r


@pytest.mark.slow
@pytest.mark.parametrize("rate", [10.0, 1.0])
@pytest.mark.parametrize("count_clock", [False, True])
def test_no_false_step_nor_hold_on_a_jittery_sampling_phase(rate, count_clock):
    """With the sampling loop's jitter on the stamps (Gaussian, 3 ms) on a 50 ms exponential
    link without a counter (two seeds of ten minutes at 10 Hz, of an hour at 1 Hz): no false
    step, no reading refused, no estimate in doubt. The phase's own rate is 1e-4 readings held
    off it per hour (EstimatorRunner.false_step_rate); one held at 1 Hz is in doubt at once."""
    dur = 600.0 if rate == 10.0 else 3600.0
    for seed in range(2):
        r = run_link(dur, rate, False, 0.05, 0.05, None, seed=seed, sampling=0.003,
                     count_clock=count_clock)
        assert r["false_steps_per_h"] == 0 and r["refused"] == 0 and r["doubted"] == 0, (seed, r)


@functools.cache
def _count_link_run(rate: float, jitter: float, step: float | None) -> dict:
    return run_link(STEP_AT + 100.0 if rate == 10.0 else 900.0, rate, False, jitter, 0.05,
                    step, seed=0, noise=(0.5, 0.1), count_clock=True)


def _count_link(rate: float, jitter: float, step: float | None) -> dict:
    """The link of the test below, ``step`` at STEP_AT (None: none), run once per worker (a
    copy of its figures each call)."""
    return dict(_count_link_run(rate, jitter, step))


@pytest.mark.parametrize("rate, jitter, step", [(10.0, 0.2, -0.3), (10.0, 0.2, -1.0),
                                                (10.0, 0.2, 0.5), (10.0, 0.05, -0.3),
                                                (1.0, 0.2, -1.0)])
def test_without_a_counter_the_count_times_the_samples_a_jittery_link_hides(rate, jitter, step):
    """Without a sample counter the odometer's count is a clock while the train moves: two
    samples lie 2 (d1 - d0) / (v0 + v1) apart in time, whatever the link did to their arrivals
    (StepWatch._count_resid). A count 0.5 m and a speed 0.1 m/s noisy per reading, at 20 m/s:
    steps the arrivals alone missed or placed 0.3-0.5 s off (-0.3 s and a whole period at 1 Hz
    inside the jitter's bar, +0.5 s refused as future stamps on the 200 ms link) are declared
    after min_judged (9) readings and measured exactly (the count the whole periods, the
    stamps' phase the rest); a step below one chain's resolution (-0.1 s here, 2 m against
    0.7 m of noise per pair of counts) is the count's level test's (the test below)."""
    r = _count_link(rate, jitter, step)
    assert r["decided_readings"] == 9 and r["refused"] == 0, r
    assert abs(r["shift_err_ms"]) < 1e-3 and r["time_err_all_ms"] < 1e-3, r
    # and a clean link with the same noise: no step, nothing refused (one run for the steps
    # that share the rate and the jitter)
    clean = _count_link(rate, jitter, None)
    assert clean["false_steps_per_h"] == 0 and clean["refused"] == 0, clean
    assert clean["time_err_all_ms"] < 1e-3, clean


@pytest.mark.parametrize("rate, jitter, step, scale, noise", [
    (10.0, 0.2, -0.3, 0.95, (0.5, 0.1)), (1.0, 0.05, -1.0, 0.95, (0.5, 0.1)),
    (1.0, 0.2, -1.0, 1.1, (0.05, 0.05))])
def test_a_speed_off_its_count_keeps_the_count_a_clock(rate, jitter, step, scale, noise):
    """A speed field that is not its count's rate (a radar, a second axle: 5-10 % off) adds
    that share of the time between samples to every link of the count's chain. The count's
    rate is learnt from the fused pairs beside the train clock's (clocks._count_fit), so the
    steps of the test above are still declared after min_judged readings and measured exactly;
    taking the speed as the count's rate, its scatter swamped the count (a whole period at 1
    Hz missed, 1 s off) or its bias held the readings (-0.3 s missed at 10 Hz, two refused)."""
    def run(step):
        return run_link(STEP_AT + 100.0 if rate == 10.0 else 900.0, rate, False, jitter, 0.05,
                        step, seed=0, noise=noise, speed_scale=scale)
    r = run(step)
    assert r["decided_readings"] == 9 and r["refused"] == 0, r
    assert abs(r["shift_err_ms"]) < 1e-3 and r["time_err_all_ms"] < 1e-3, r
    clean = run(None)
    assert clean["false_steps_per_h"] == 0 and clean["refused"] == 0, clean
    assert clean["time_err_all_ms"] < 1e-3, clean


@pytest.mark.parametrize("seed", [1, 2])
def test_a_smoothed_count_is_judged_at_its_chains_span(seed):
    """A producer that smooths its count (its noise correlated 0.9 from one reading to the next,
    0.5 m of spread, 10 Hz): neighbours' counts differ by a third of what two ends of a chain
    of held readings do. The count's scale is learnt over both spans (clocks._count_fit), so a
    clean link refuses nothing and declares no step, and a -0.3 s step is declared after
    min_judged readings and measured exactly; learnt from neighbours alone, one good reading
    was refused in each of these seeds."""
    def run(step):
        return run_link(STEP_AT + 100.0, 10.0, False, 0.05, 0.05, step, seed=seed,
                        noise=(0.5, 0.1), noise_corr=0.9)
    clean = run(None)
    assert clean["false_steps_per_h"] == 0 and clean["refused"] == 0, clean
    assert clean["time_err_all_ms"] < 1e-3, clean
    r = run(-0.3)
    assert r["decided_readings"] == 9 and r["refused"] == 0, r
    assert abs(r["shift_err_ms"]) < 1e-3 and r["time_err_all_ms"] < 1e-3, r


def test_a_reading_stamped_as_the_last_fused_one_after_a_backward_step_is_no_corrupt_one():
    """After a -1 s step at 10 Hz and 20 m/s, the reading sampled 1 s after the last one fused
    on the old clock carries its stamp and a count 21 m further on: more than any train runs
    in a period. Without counters the count's own time (at most COUNT_SPAN) bounds the time
    between two samples, as the counters do where there are some (StepWatch._plausible), so
    the chain's count measures the step exactly; taken for a corrupted reading, it left the
    chain unresolved and the arrivals measured the step a period (100 ms) off."""
    r = run_link(STEP_AT + 300.0, 10.0, False, 0.2, 0.05, -1.0, seed=0, noise=(0.5, 0.1))
    assert r["decided_readings"] == 9 and r["refused"] == 0, r
    assert abs(r["shift_err_ms"]) < 1e-3 and r["time_err_all_ms"] < 1e-3, r


@pytest.mark.parametrize("jitter, step, seed", [(0.05, -0.1, 0), (0.05, -0.1, 1),
                                               (0.2, 0.1, 1), (0.2, -0.2, 0)])
def test_a_step_within_the_counts_noise_is_found_by_its_level_and_re_stamped(jitter, step,
                                                                             seed):
    """A step of one or two periods at 10 Hz without a counter, the count 0.5 m and the speed
    0.1 m/s noisy a reading, at 20 m/s: 2-4 m of count against 0.7 m of noise between a
    chain's two ends, within the count's tolerance, on the sampling's own phase, and inside
    the arrivals' bar, so every reading after it was fused as it came, 0.1-0.2 s off its time
    for the rest of the run (the step missed in 9 of these 12 runs and these seeds, two of the
    others a period off). The count's level moves by the step and stays: the generalised
    likelihood ratio of one level move among the last 2 s of readings (StepWatch._level_test)
    finds it a few readings on, the stamps' phase makes it whole periods, and the readings
    fused since are re-stamped and fused again at their times (EstimatorRunner._late_step): the
    shift exact, every reading fused at its sampling time."""
    r = run_link(STEP_AT + 100.0, 10.0, False, jitter, 0.05, step, seed=seed,
                 noise=(0.5, 0.1))
    assert r["refused"] == 0 and r["decided_readings"] <= 20, r
    assert abs(r["shift_err_ms"]) < 1e-3 and r["time_err_all_ms"] < 1e-3, r


@pytest.mark.parametrize("jitter, jump, seed", [(0.05, 4.0, 1), (0.05, 2.0, 1),
                                               (0.005, -4.0, 0)])
def test_a_count_re_based_by_its_producer_is_no_clock_step(jitter, jump, seed):
    """A producer that re-bases its count by 2-4 m at a cruise (the stamps stay), the count 0.5 m
    noisy: the count's level moves as a step of 0.1-0.2 s of the stamps would, but the arrivals
    stayed where they were. The log-likelihood ratio of their move (clocks.arrivals_llr, for the
    count's level test and for held readings alike) makes it the count's: logged as count_slip,
    no step, every reading fused at its time. With bars of 3 and 6 of the arrivals' precision,
    4 m on the 50 ms link (arrivals 27 ms off, 3.2 precisions, against 0.26 s) was a step of
    -0.3 s, the filter's time 0.3 s off."""
    r = run_link(STEP_AT + 100.0, 10.0, False, jitter, 0.05, None, seed=seed, noise=(0.5, 0.1),
                 count_jump=jump)
    assert r["false_steps_per_h"] == 0 and r["refused"] == 0 and r["count_slips"] == 1, r
    assert r["time_err_all_ms"] < 1e-3, r


def _braking_run(lag: float, seed: int, duration: float = 900.0, rate: float = 10.0,
                 slide: tuple | None = None, fault=None, rounding: tuple = (0.0, 0.0),
                 ripple: float = 0.0, stamps: tuple = (0.0, 0.0), counter: bool = False,
                 count_clock: bool = True, count_noise: float = 0.0):
    """A stream without a counter from a train that cruises at 20 m/s, brakes at 0.8 m/s^2 to
    4 m/s, runs on and accelerates back at 0.4 m/s^2 every 120 s, its acceleration following
    its set point at 1 m/s^3 (COUNT_JERK); the speed field lags the count by ``lag`` s (a rate
    over a window of pulses). ``slide`` ``(ratio, from s, for s)``: in every cycle the wheel
    that is counted slides (ratio > 0: counts that share less than the train runs) or spins (<
    0) while the speed field is the train's (a radar's). Through the campaign's 50 ms link, 5 %
    lost, with the campaign's ``fault`` (faults.Fault) if given. ``rounding`` ``(m, m/s)``: the
    grids the producer rounds its count and speed to (0: none); ``ripple`` m/s^2, a sine of
    17 s on the acceleration (a cruise's speed is never one number); ``stamps`` ``(s, s)``: the
    sampling loop's Gaussian jitter on the stamps and the grid they are rounded to; ``counter``:
    ``seq`` the sample counter (else 0); ``count_clock``: the runner's; ``count_noise`` m, the
    count's Gaussian noise a reading. The runner and its estimates."""
    from train_estimation.core.online.replay import replay
    from train_estimation.core.online.runner import EstimatorRunner
    from train_estimation.tools import faults as F
    from train_estimation.tools.clock_runs import Recorder
    dt = 1e-3
    t = np.arange(0.0, duration + 5.0, dt)
    ph = t % 120.0
    want = np.where((ph >= 40) & (ph < 60), -0.8, np.where(ph >= 80, 0.4, 0.0)) + \
        ripple * np.sin(2.0 * np.pi * t / 17.0)
    # the set point followed at COUNT_JERK: a[k] = a[k-1] + clip(want[k] - a[k-1], -dt, dt),
    # on Python floats (the same comparisons and sums as np.clip's on numpy scalars, at a
    # twentieth of their cost: 900,000 steps a run)
    acc, prev = [0.0] * t.size, 0.0
    for k, w in enumerate(want.tolist()[1:], 1):
        d = w - prev
        prev += dt if d > dt else -dt if d < -dt else d
        acc[k] = prev
    a = np.array(acc)
    v = 20.0 + np.cumsum(a) * dt
    wheel = v
    if slide is not None:
        ratio, t0, span = slide
        wheel = v * (1.0 - np.where((ph >= t0) & (ph < t0 + span), ratio, 0.0))
    x = np.cumsum(wheel) * dt
    rng = np.random.default_rng(seed)
    dq, vq = rounding

    def rounded(y, q):
        return float(round(y / q) * q) if q else float(y)

    sj, sq = stamps

    def stamped(k):
        t = k / rate + (rng.normal(0.0, sj) if sj else 0.0)
        return round(t / sq) * sq if sq else t

    ev = [("odometer", stamped(k), {"seq": k if counter else 0,
                                  "distance": rounded(x[int(round(k / rate / dt))] + (
                                      rng.normal(0.0, count_noise) if count_noise else 0.0),
                                                      dq),
                                  "speed": rounded(v[max(int(round((k / rate - lag) / dt)), 0)],
                                                   vq),
                                  "speed_variance": 0.01})
          for k in range(int(duration * rate)) if rng.random() >= 0.05]
    ev += [("control", float(s), {"target_acceleration": 0.0}) for s in range(int(duration) + 1)]
    ev.sort(key=lambda e: (e[1], e[0] != "control"))
    faulted = F.inject(ev, fault or F.Fault("none", jitter=0.05), rng)
    rec = Recorder()
    runner = EstimatorRunner(rec, 1.0 / rate, count_clock=count_clock)
    outs, _ = replay(iter(faulted.events), rec, 1.0 / rate, runner=runner)
    return runner, outs


def _braking_cycles(lag: float, seed: int, duration: float = 900.0, rate: float = 10.0,
                    slide: tuple | None = None):
    """:func:`_braking_run`'s clock_reset events, refusals and estimates in doubt."""
    runner, outs = _braking_run(lag, seed, duration, rate, slide)
    return (runner.events.get("odometer:clock_reset", 0), sum(runner.rejected.values()),
            sum("clock" in o.integrity_reason for o in outs))


@pytest.mark.parametrize("lag", [0.3, 1.0])
@pytest.mark.parametrize("seed", [0, 1])
def test_a_speed_that_lags_its_count_through_braking_is_no_step(seed, lag):
    """A speed 0.3 s or 1 s behind its count through braking and acceleration: a lag adds
    -tau ln(v1 / v0) to the count's residual between two readings, which a rate alone learnt
    from the fused pairs took in while the train braked and carried on after (0.3 s: 6 and 2
    false steps; 1 s: 33-37 false steps, the clock 0.9 s off). The count's fit carries the lag
    beside the rate, learnt over the run's brakings (clocks._count_fit, StepWatch._lag_prior),
    and the chain's residual is taken less it: no step, nothing refused, no estimate in
    doubt."""
    assert _braking_cycles(lag, seed) == (0, 0, 0)


@pytest.mark.parametrize("slide", [(0.15, 42.0, 3.0), (0.05, 42.0, 8.0), (-0.2, 82.0, 3.0)])
def test_a_wheel_that_slides_or_spins_is_no_clock_step(slide):
    """The counted wheel slides 15 % for 3 s or 5 % for 8 s in every braking, or spins 20 % for
    3 s in every acceleration, exact counts, while the speed field is the train's (a radar):
    each link of the slide adds its share to the count's residual, which stays where the
    slide left it. The stamps and their arrivals stay on their clock. Taken for the stamps',
    every slide made a false step of +0.1 to +0.4 s and 130-200 readings were refused as
    stamped ahead in 10 min. The count's reach of a slip (StepWatch._slip_room: COUNT_SLIP of
    the stamps' time, where the train brakes or accelerates by COUNT_SLIP_ACCEL) and the
    arrivals that stayed (StepWatch._count_moved) make it the count's: no clock step, nothing
    refused, and the count_slip event says so."""
    runner, _ = _braking_run(0.0, 0, 600.0, slide=slide)
    assert runner.events.get("odometer:clock_reset", 0) == 0
    assert sum(runner.rejected.values()) == 0
    assert runner.events.get("odometer:count_slip", 0) >= 1


@pytest.mark.parametrize("step", [-0.3, 0.5])
def test_a_clock_step_in_braking_is_still_one(step):
    """A clock step while the train brakes (0.8 m/s^2, exact counts, no slide): a slide puts at
    most COUNT_SLIP of the stamps' time into the count's residual of a link, and only forward
    (counts less) while braking; -0.3 s puts a reading on the stamp of the one before it, +0.5 s
    is 0.5 of 0.6 s. One clock_reset, at the step's size, nothing refused."""
    from train_estimation.tools import faults as F
    runner, _ = _braking_run(0.0, 0, 200.0, fault=F.Fault("step", step, 163.0, jitter=0.05))
    assert runner.events.get("odometer:clock_reset", 0) == 1
    assert runner.events.get("odometer:count_slip", 0) == 0
    assert sum(runner.rejected.values()) == 0
    text = next(e[2] for e in runner.last_events if "clock_reset" in e[2])
    assert f"{step:+.3f} s" in text


@pytest.mark.parametrize("rate", [10.0, 1.0])
@pytest.mark.parametrize("rounding", [(1.0, 1.0 / 3.6), (1.0, 0.1 / 3.6), (0.1, 1.0 / 3.6)])
@pytest.mark.parametrize("ripple", [0.0, 0.05])
def test_a_count_and_speed_rounded_by_their_producer_are_read_right(rounding, rate, ripple):
    """A recorder that logs the count in whole metres (or decimetres) and the speed in whole
    (or tenths of) km/h, no counter, through the braking cycles: no step, nothing refused. At
    4 m/s and 10 Hz a whole-metre count stays put for two or three samples, and with the speed
    rounded the readings were refused as copies of a fused one (half of them, 900 in 10 min);
    the count's rounding, bounded and seen only when the speed carries a count across a grid
    line, was refused as stamps off the count's clock (the count's noise learnt as 0 between
    the crossings), and so was the speed's (whole km/h: 1.4 ms a link at 20 m/s). The
    producer's grids are learnt from its values (clocks.Grid); a count that cannot have moved
    by a grid step between the two stamps is no copy (runner._count_moves), and a chain's
    tolerance holds both roundings (StepWatch._count_resid)."""
    runner, _ = _braking_run(0.0, 0, 600.0, rate, rounding=rounding, ripple=ripple)
    assert runner.events.get("odometer:clock_reset", 0) == 0
    assert dict(runner.rejected) == {}


@pytest.mark.parametrize("counter", [False, True])
@pytest.mark.parametrize("rate", [10.0, 1.0])
def test_stamps_rounded_by_their_producer_are_read_right(rate, counter):
    """A log that stamps to hundredths of a second a sampling loop 3 ms jittery, through the
    braking cycles, with and without a sample counter: nine stamps in ten land on the nominal
    slot and the tenth a whole hundredth off, so the robust scale of the count's (or the
    grid's) residuals learns nothing of the rounding and each crossing was refused as a stamp
    off its clock (10 Hz: 280-600 readings in 10 min). The stamps' grid is learnt from them
    (StepWatch.stamp_grid: finer than a tenth of the period, which the sampling's own grid is
    not) and, once a held reading that no later one continued showed it, every tolerance holds
    it: no step, nothing refused."""
    runner, _ = _braking_run(0.0, 0, 600.0, rate, ripple=0.05, stamps=(0.003, 0.01),
                             counter=counter)
    assert runner.events.get("odometer:clock_reset", 0) == 0
    assert dict(runner.rejected) == {}


@pytest.mark.parametrize("rate", [10.0, 1.0])
def test_stamps_rounded_by_their_producer_are_read_right_by_their_phase_alone(rate):
    """The same log judged by its arrivals and its sampling phase alone (``count_clock``
    off, as for a train too slow for its count): nothing places a held reading on its clock
    but the phase, whose robust scale learns nothing of the rounding either, so every
    crossing was held in doubt until the next reading (38-58 estimates in 10 min, nothing
    refused). A held reading that no later one continued, off the phase by at most one step
    of the stamps' grid, shows the rounding as a count's residual does (StepWatch._release):
    at most the crossing that shows it is in doubt."""
    runner, outs = _braking_run(0.0, 0, 600.0, rate, ripple=0.05, stamps=(0.003, 0.01),
                                count_clock=False)
    assert runner.events.get("odometer:clock_reset", 0) == 0
    assert dict(runner.rejected) == {}
    assert sum("clock" in o.integrity_reason for o in outs) <= 2


@pytest.mark.parametrize("seed, ripple", [(0, 0.0), (4, 0.0), (3, 0.05), (4, 0.05)])
def test_a_noisy_count_through_braking_cycles_makes_no_level_step(seed, ripple):
    """The braking cycles with the count 0.1 m noisy a reading, with and without a cruise
    ripple: the train cruises at 20 and at 4 m/s, where the same metres of count noise are five
    times the time. The count's level test learns the noise in metres and takes it at the
    window's speed (StepWatch._learn_noise); learnt in seconds it made false steps of 0.05 s at
    the slow cruise, and their reversals (2-9 in ten minutes in these runs)."""
    runner, outs = _braking_run(0.0, seed, 600.0, ripple=ripple, count_noise=0.1)
    assert runner.events.get("odometer:clock_reset", 0) == 0
    assert dict(runner.rejected) == {}


def test_a_producers_grid_is_the_coarsest_its_values_lie_on():
    """clocks.Grid: whole metres, then a half: 0.5; 0.5 and 0.4: 0.1 (not 0.2, which 0.5 is
    not on); km/h as m/s (k / 3.6) and tenths of m/s; values that are not rounded: none; one
    that lies on a grid by chance (2 m) leaves it at the next."""
    from train_estimation.core.numerics.clocks import COUNT_GRIDS, SPEED_GRIDS, Grid

    def grid(values, grids=COUNT_GRIDS):
        g = Grid(grids)
        for x in values:
            g.add(x)
        return g.q

    assert grid([1234.0, 1236.0, 1237.0]) == 1.0
    assert grid([1234.0, 1234.5]) == 0.5
    assert grid([0.5, 0.4]) == pytest.approx(0.1)
    assert grid([12345.6, 12346.1]) == pytest.approx(0.1)
    assert grid([k / 3.6 for k in (72, 71, 40)], SPEED_GRIDS) == pytest.approx(1 / 3.6)
    assert grid([20.1, 19.7, 3.3], SPEED_GRIDS) == pytest.approx(0.1)
    assert grid(list(np.random.default_rng(0).uniform(0, 1e4, 5))) == 0.0
    assert grid([2.0, 4.0, 6.0, 7.93]) == 0.01


def _braking_links(seed: int, rate: float, lag: float, noise: float, accel: float = -0.8):
    """64 links (clocks._count_link) of a train braking at ``accel`` from 20 m/s sampled at
    10 Hz: white count noise ``noise`` m, a speed ``lag`` s behind its count, stamps on a clock
    of rate ``1 + rate``."""
    from train_estimation.core.numerics.clocks import _count_link
    rng = np.random.default_rng(seed)
    t = np.arange(65) / 10.0
    x = 20.0 * t + 0.5 * accel * t * t + rng.normal(0.0, noise, t.size)
    v = 20.0 + accel * (t - lag)
    s = (1.0 + rate) * t
    links = []
    for i in range(1, t.size):
        r, vbar = _count_link(s[i - 1], x[i - 1], v[i - 1], s[i], x[i], v[i])
        links.append((r, s[i] - s[i - 1] - r, vbar, v[i]))
    return links


def test_the_counts_fit_states_its_rate_and_lag_errors():
    """The count's fit against its own model: 300 windows braked at 0.8 m/s^2 (64 links, 0.3 m
    of count noise, a clock 2 % fast, a speed 0.7 s behind), fitted without a prior. Each
    estimate over its stated standard error is a standard normal if the fit is unbiased and
    states its error: the mean within 3 standard errors of the mean (3 / sqrt 300 = 0.17), the
    mean square within 3 of its (1 + 3 sqrt(2 / 300) = 1.25; the stated error may be wider,
    not narrower). The count's time as the regressor, which shares the count's noise, gave a
    lag of 1.9 +- 0.7 here (z 1.8 on average)."""
    from train_estimation.core.numerics.clocks import _count_fit
    z = []
    for seed in range(300):
        rate, lag, (c_rr, _, c_ll), _ = _count_fit(_braking_links(seed, 0.02, 0.7, 0.3), None)
        z.append(((rate - 0.02) / math.sqrt(c_rr), (lag - 0.7) / math.sqrt(c_ll)))
    z = np.array(z)
    assert np.all(np.abs(z.mean(axis=0)) < 3.0 / math.sqrt(300)), z.mean(axis=0)
    assert np.all((z ** 2).mean(axis=0) < 1.0 + 3.0 * math.sqrt(2.0 / 300)), (z ** 2).mean(axis=0)


def test_a_cruise_does_not_tell_the_lag():
    """At one speed the lag has no data: fitted alone its error is infinite (the window adds no
    information to the lag's long memory), and with a prior the fit keeps the prior's mean and
    variance while it measures the rate (the prior holds the lag in the stamps' seconds, which
    differs from the count's by the rate: 0.1 % here at most, a few % for a speed off its
    count)."""
    from train_estimation.core.numerics.clocks import _count_fit
    links = _braking_links(0, 0.001, 0.0, 0.3, accel=0.0)
    rate, lag, (c_rr, _, c_ll), _ = _count_fit(links, None)
    assert c_ll == math.inf and lag == 0.0
    assert abs(rate - 0.001) < 4.0 * math.sqrt(c_rr)
    rate, lag, (_, _, c_ll), _ = _count_fit(links, (0.4, 0.09))
    assert lag == pytest.approx(0.4, rel=1e-3) and c_ll == pytest.approx(0.09, rel=3e-3)
