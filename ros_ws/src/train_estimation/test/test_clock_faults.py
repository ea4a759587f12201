"""Clock faults through the runner with the node defaults (``control_clock: auto``): a forward
step is re-anchored, a drifting train clock is tracked, one wrong stamp never moves a clock.
The figures are those of ``./run bench integrity`` (tools/faults.py), on a short metro_demo run
with the kf (the estimator that was wrong-side on both)."""

import dataclasses
import math
import os
import sys

import numpy as np
import pytest

from train_estimation.core.numerics.clocks import LINE_SPREAD, StreamClock, is_step, t_spread
from train_estimation.core.online.integrity import IntegrityParams, burst_readings
from train_estimation.tools import faults as F
from train_sim.scenario import load_scenario
from train_sim.world import simulate

sys.path.insert(0, os.path.dirname(__file__))
from clocks import adapter, run, wobbled  # noqa: E402

BURST = burst_readings(IntegrityParams())  # readings on a declared step's new clock by which
#   the hypothesis that it was a burst of wrong stamps is dropped (37 at the defaults)


def clock_doubt_ends(outs, emitted, events, at: float, period: float) -> float:
    """s after ``at`` (true time) of the last estimate published with a clock doubt: the
    readings held while they decide a step, then the step's burst hypothesis. No later than
    the ``BURST``-th odometer reading to arrive after ``at`` (``events``, the faulted stream;
    the link loses some) and a period."""
    last = max(e - F.EPOCH for o, e in zip(outs, emitted) if "clock:" in o.integrity_reason)
    arrivals = sorted(e[3] - F.EPOCH for e in events if e[0] == "odometer"
                      and e[3] - F.EPOCH >= at)
    assert last <= arrivals[BURST - 1] + period, (last - at, BURST)
    return last - at


def clear_after(outs, emitted, t: float) -> float:
    """The share of the estimates published after true time ``t`` that no check doubts."""
    after = [not o.integrity_reason for o, e in zip(outs, emitted) if e - F.EPOCH > t]
    assert after
    return float(np.mean(after))


def _campaign_case(fault, duration=40.0):
    sc, res = run("metro_demo", 3, duration)
    fl = F.inject(res.events(), fault, np.random.default_rng(0))
    outs, emitted, runner = F.run(fl.events, adapter(sc, "kf"), 0.1)  # node default: auto
    return F.score(outs, emitted, fl, res.truth, 10.0, duration + F.LATENCY), runner


@pytest.mark.parametrize("size", [3.0, 0.5])
def test_forward_clock_step_is_re_anchored(size):
    s, runner = _campaign_case(F.Fault("step", size, at=20.0))
    assert runner.events.get("odometer:clock_reset") == 1, runner.counts
    assert runner._steps.shift == pytest.approx(size, abs=0.02)
    assert s["wrong_side"] == 0 and s["hazards"] == 0, s  # the bound holds throughout


@pytest.mark.parametrize("link_seed", [0, 2])
def test_a_forward_step_on_a_fast_jittery_link_is_no_latency_move(link_seed):
    """A 50 Hz odometer over a link with 0.1 s of exponential jitter (five samples reordered),
    its train clock stepped 2 s forward while braking (metro_demo, 120 s): the step is declared
    and measured. A late reading of the old clock was among the held ones, so their first stamp
    lay before the old clock's newest and they read as a latency that rose while the stamps ran
    on (a route change), though their offsets had risen by the step: the clock's offset moved
    2 s as a latency, every later reading was 2 s ahead of its slot, 405-428 were refused by the
    filter's gate and the estimate was blind, then reacquired, for 80 s (link seeds 0 and 2 of
    four). A latency that rose lowers the offsets; it is no answer to offsets that rose."""
    sc = dataclasses.replace(load_scenario("metro_demo"), odometer_rate=50.0)
    res = simulate(sc, 1, 160.0)
    fl = F.inject(res.events(), F.Fault("step", 2.0, at=120.0, jitter=0.1),
                  np.random.default_rng(link_seed))
    outs, emitted, runner = F.run(fl.events, adapter(sc, "kf"), 1 / 50.0)
    assert runner.events.get("odometer:clock_reset") == 1, runner.events
    assert "odometer:link_latency" not in runner.events, runner.events
    assert runner._steps.shift == pytest.approx(2.0, abs=0.02)
    assert "odometer:outside_gate" not in runner.rejected, runner.rejected
    s = F.score(outs, emitted, fl, res.truth, 50.0, 160.0 + F.LATENCY)
    assert s["misleading"] == 0 and s["wrong_side"] == 0, s


def test_one_stamp_ahead_is_refused_and_moves_no_clock():
    s, runner = _campaign_case(F.Fault("stamp", 1.0, at=20.0))
    assert "odometer:clock_reset" not in runner.events and runner._steps.shift == 0.0
    assert runner.rejected.get("odometer:future_stamp") == 1, runner.counts
    assert s["wrong_side"] == 0, s


def test_drift_is_tracked_by_default():
    s, runner = _campaign_case(F.Fault("drift", -1e-2), duration=60.0)
    assert runner.separate_clocks
    assert runner.drift == pytest.approx(-1e-2, abs=1e-4)
    assert s["wrong_side"] == 0 and s["hazards"] == 0, s  # the bound holds throughout


def test_stream_clock_rate_and_step_test():
    c = StreamClock()
    rng = np.random.default_rng(0)
    for k in range(4000):  # 1e-3 slow clock, 10 Hz, latency 20 ms + Exp(50 ms)
        a = 0.1 * k + 0.02 + rng.exponential(0.05)
        s = 0.1 * k * (1 - 1e-3)
        c.add(s - a, a)
        c.rate_point(s, a)
    d, se = c.rate()
    assert abs(d + 1e-3) < 5 * se and se < 2e-5
    chain = [(100.0 + 0.1 * k, 97.0 + 0.1 * k) for k in range(9)]
    assert is_step(chain, 9, 0.1) and not is_step(chain[:8], 9, 0.1)
    burst = [(100.0 + 0.1 * k, 97.0) for k in range(9)]  # one stall's backlog, at once
    assert not is_step(burst, 9, 0.1)


def test_a_rate_fit_over_two_levels_of_the_offset_is_not_a_drift():
    """A clock that stepped +3 s 4 s into a 1 Hz stream, before its rate was known (no sample
    counter to see it): the fit's points lie on two levels, about no line within the link's
    jitter, and give no drift (it read 0.09: slots 1.09 s apart, estimates stamped after the
    run). Either the fit sees the two levels and gives no rate, or its points (each block's
    envelope) lie on the new level and it gives the true drift, 0, within its standard error.
    The same stream without the step gives its true drift. Its standard error is the normal
    one (below 5e-4 for these 12 points) widened by Student's t for their degrees of freedom
    (clocks.t_spread)."""
    rng = np.random.default_rng(1)
    for step, drift in ((3.0, 0.0), (0.0, 1e-3)):
        c = StreamClock()
        for k in range(60):
            a = float(k) + 0.02 + rng.exponential(0.05)
            s = k * (1.0 + drift) + (step if k >= 4 else 0.0)
            c.add(s - a, a)
            c.rate_point(s, a)
        d, se = c.rate()
        bound = 5e-4 * t_spread(c._pooled()[4]) / LINE_SPREAD
        if step:
            assert (d == 0.0 and math.isinf(se)) or (abs(d) < 5 * se and se < bound), (d, se)
        else:
            assert abs(d - drift) < 5 * se and se < bound


def test_backward_step_at_1_hz_is_in_doubt_from_its_first_reading():
    """At 1 Hz the first reading after a -3 s step lands on a slot already fused: no lateness
    explains it, so the estimate is DEGRADED at once (not one period later, wrong-side)."""
    sc, res = run("wen2017_subway", 3, 60.0)
    assert sc.odometer_rate == 1.0
    fl = F.inject(res.events(), F.Fault("step", -3.0, at=26.0), np.random.default_rng(0))
    outs, emitted, runner = F.run(fl.events, adapter(sc), 1.0)
    s = F.score(outs, emitted, fl, res.truth, 1.0, 60.0 + F.LATENCY)
    assert runner.events.get("odometer:clock_reset") == 1, runner.counts
    first = next(o for o, e in zip(outs, emitted) if e - F.EPOCH > 26.0)
    assert first.integrity == 1 and first.integrity_reason.startswith("clock"), first
    assert s["wrong_side"] == 0 and s["hazards"] == 0, s



def test_a_backward_step_without_a_counter_stays_in_doubt_when_its_readings_run_on():
    """Without a counter, at 1 Hz, a -10 s step while braking (crh3_high_speed, 618 s, kf):
    the new clock's first ten readings land on slots already fused and are held; the eleventh
    is stamped on the old grid past its newest slot, the held ones are refused as stale, and it
    alone is held, 10 s later than the clock's lateness bar allows. The slot published then
    claims, on the stepped clock, a time 10 s after its content: it must stay in doubt (one
    estimate was 790 m behind the train inside its levels)."""
    sc, res = run("crh3_high_speed", 0, 700.0)
    fl = F.inject(res.events(), F.Fault("step", -10.0, at=618.0), np.random.default_rng(0))
    outs, emitted, runner = F.run(F.uncounted(fl.events), adapter(sc, "kf"), 1.0)
    s = F.score(outs, emitted, fl, res.truth, 1.0, 700.0 + F.LATENCY)
    assert runner.events.get("odometer:clock_reset") == 1, dict(runner.events)
    assert s["misleading"] == 0 and s["wrong_side"] == 0, s


def test_a_node_catching_up_is_not_above_its_clock():
    """Offsets drift down while a node falls 3 s behind (each reading a little later: the
    centre follows); when it catches up they return to where the clock is: above the centre by
    3 s, but not above the ceiling, so not taken for a forward step (a real one is)."""
    c = StreamClock()
    for k in range(100):
        c.add(-0.05, 0.1 * k)
    for k in range(100):  # lag grows by 30 ms per reading to 3 s
        c.add(-0.05 - 0.03 * k, 10.0 + 0.13 * k)
    assert c.value < -2.5 and c.ceiling == pytest.approx(-0.05)
    assert c.above(-0.05) == pytest.approx(0.0, abs=1e-9)
    assert c.above(-0.05 + 3.0) == pytest.approx(3.0)


def test_one_wild_offset_among_the_first_does_not_lift_the_ceiling():
    """The ceiling (where the clock is when the latency is least) is fed once the clock has a
    centre: a wild stamp among the first readings votes unjudged, but is no clock."""
    c = StreamClock()
    c.add(-0.05, 0.0)
    c.add(1e9, 0.0)  # among the first: voted before any centre existed
    for k in range(1, 40):
        c.add(-0.05, 0.1 * k)
    assert c.value == pytest.approx(-0.05) and c.ceiling == pytest.approx(-0.05)
    assert c.above(-0.05 + 5.0) == pytest.approx(5.0)


def _with_copies(events, copies, before=False):
    """``events`` (faults.inject's stream) with copies of odometer readings stamped wrong:
    ``copies`` = {true sampling time: stamp error}, each copy arriving with its original (just
    after it, or ``before`` it)."""
    out = []
    for topic, stamp, fields, recv in events:
        t = round(stamp - F.EPOCH, 6)
        copy = (topic, stamp + copies[t], dict(fields), recv) \
            if topic == "odometer" and t in copies else None
        out += [e for e in ((copy, (topic, stamp, fields, recv)) if before else
                            ((topic, stamp, fields, recv), copy)) if e is not None]
    return out


def test_a_wild_first_stamp_does_not_let_a_later_one_take_a_slot():
    """1 Hz odometer (crh3_high_speed), kf: a copy of the second reading stamped 1e9 s ahead,
    then a copy of the 8th stamped 5 s ahead. The first must not raise the clock's ceiling (it
    did, for 600 readings: the second then passed as on time, was fused at its wrong stamp,
    took the genuine reading's slot and left the kf up to 6 m off with sigma 0.4 m, integrity
    OK); the second is refused as stamped ahead of its clock."""
    sc, res = run("crh3_high_speed", 0, 40.0)
    assert sc.odometer_rate == 1.0
    fl = F.inject(res.events(), F.Fault("none"), np.random.default_rng(0))
    # (copies before their originals: a copy after a fused original is refused as such, below)
    events = _with_copies(fl.events, {1.0: 1e9, 8.0: 5.0}, before=True)
    outs, emitted, runner = F.run(events, adapter(sc, "kf"), 1.0)
    s = F.score(outs, emitted, fl, res.truth, 1.0, 40.0 + F.LATENCY)
    # the 5 s copy, before its original, only the clock can refuse; the 1e9 s one arrives
    # among the first readings, held until the clock is judged, and meets its original there
    assert runner.rejected.get("odometer:future_stamp", 0) >= 1, runner.counts
    assert runner.rejected.get("odometer:future_stamp", 0) + \
        runner.rejected.get("odometer:duplicate", 0) == 2, runner.counts
    assert s["wrong_side"] == 0 and s["hazards"] == 0, s


@pytest.mark.parametrize("size", [0.2, -0.1])
def test_a_small_clock_step_is_re_anchored(size):
    """Steps below step_back (0.3 s at 10 Hz) on a link with little jitter: every offset of the
    new clock moves alike, which jitter cannot do, so the step is watched and re-anchored
    (left alone, 0.2 s left the kf 4 m off at 20 m/s with sigma 0.1 m, integrity OK)."""
    s, runner = _campaign_case(F.Fault("step", size, at=20.0))
    assert runner.events.get("odometer:clock_reset") == 1, runner.counts
    assert runner._steps.shift == pytest.approx(size, abs=0.02)
    assert s["wrong_side"] == 0 and s["hazards"] == 0, s


def test_a_node_falling_behind_is_no_small_step():
    """Arrivals later by 30 ms more per reading for 2 s (a node falling 0.6 s behind its
    input), then on time again: readings below the centre, each later than the one before --
    late readings, no clock step, nothing wrong-side."""
    sc, res = run("metro_demo", 3, 40.0)
    fl = F.inject(res.events(), F.Fault("none"), np.random.default_rng(0))
    lag = [(tp, st, f, rc + min(max(rc - F.EPOCH - 20.0, 0.0), 2.0) * 0.3
            * (rc - F.EPOCH < 24.0)) for tp, st, f, rc in fl.events]
    lag.sort(key=lambda e: e[3])
    outs, emitted, runner = F.run(lag, adapter(sc, "kf"), 0.1)
    s = F.score(outs, emitted, fl, res.truth, 10.0, 40.0 + F.LATENCY)
    assert "odometer:clock_reset" not in runner.events and runner._steps.shift == 0.0
    assert s["wrong_side"] == 0, s


@pytest.mark.parametrize("how", ["lag", "stall"])
def test_a_balise_is_judged_on_the_odometer_clock_when_the_node_falls_behind(how):
    """metro_demo's first balise (41.8 s) reaches a node that fell behind: arrivals 0.3 s
    later per second from 38 s (1.2 s behind at the balise), or every arrival of 38-46 s taken
    at 46 s in one burst. The balise shares the train clock with the odometer (one
    StreamClock, fed at 10 Hz), so it meets the centre the odometer readings around it set, is
    fused, and no estimate is wrong-side."""
    sc, res = run("metro_demo", 3, 60.0)
    if how == "stall":
        fl = F.inject(res.events(), F.Fault("node_stall", 8.0, at=38.0),
                      np.random.default_rng(0))
        events = fl.events
    else:
        fl = F.inject(res.events(), F.Fault("none"), np.random.default_rng(0))
        events = sorted(((tp, st, f, rc + 0.3 * min(max(rc - F.EPOCH - 38.0, 0.0), 4.0)
                          * (rc - F.EPOCH < 44.0)) for tp, st, f, rc in fl.events),
                        key=lambda e: e[3])
    assert sum(e[0] == "balise" for e in events) == 1
    outs, emitted, runner = F.run(events, adapter(sc, "kf"), 0.1)
    s = F.score(outs, emitted, fl, res.truth, 10.0, 60.0 + F.LATENCY)
    assert runner.accepted.get("balise") == 1, runner.counts
    assert not any(k.startswith("balise:") for k in runner.rejected), runner.counts
    assert "odometer:clock_reset" not in runner.events, runner.counts
    assert s["wrong_side"] == 0, s


def test_one_command_stamped_ahead_is_refused_and_blinds_nothing():
    """A command copy stamped 300 s ahead (inside max_future): it made the control watermark,
    and with it the runner, jump 300 s ahead -- every slot up to it predicted at once, then
    every genuine reading refused as out of order. Refused now: estimates go on, all OK."""
    sc, res = run("metro_demo", 3, 40.0)
    fl = F.inject(res.events(), F.Fault("none"), np.random.default_rng(0))
    events = []
    for e in fl.events:
        events.append(e)
        if e[0] == "control" and abs(e[1] - F.EPOCH - 20.0) < 1e-6:
            events.append((e[0], e[1] + 300.0, dict(e[2]), e[3]))
    outs, emitted, runner = F.run(events, adapter(sc, "kf"), 0.1)
    s = F.score(outs, emitted, fl, res.truth, 10.0, 40.0 + F.LATENCY)
    assert runner.rejected.get("control:future_stamp") == 1, runner.counts
    assert not any(k.startswith("odometer:") for k in runner.rejected), runner.counts
    assert s["wrong_side"] == 0 and s["off_run"] == 0 and s["clear"] > 0.99, s


def test_a_clock_faster_than_its_arrivals_is_not_ahead_of_itself():
    """Sim time at 20x, arrivals on the steady clock: each offset 0.095 s above the one before.
    The centre (a median) lags the newest by over a second; the next reading is judged against
    the latest offset that voted, so it is not taken for a forward step."""
    c = StreamClock()
    for k in range(100):
        c.add(0.095 * k, 0.005 * k)
    assert c.value < 0.095 * 99 - 1.0
    assert c.above(0.095 * 100) == pytest.approx(0.095)


def test_the_offset_of_a_drifting_clock_is_carried_to_now():
    """A window's centre is the offset of its middle: half a window (15 s at 1 Hz) behind a
    clock 1 % fast, 0.15 s. Carried along the drift it is where the clock is now."""
    c = StreamClock()
    for k in range(60):
        c.add(0.01 * k - 0.05, float(k))
    assert c.value == pytest.approx(0.01 * 44 - 0.05)  # the middle of the last 31
    assert c.value_at(59.0, 0.01) == pytest.approx(0.01 * 59 - 0.05)
    assert c.value_at(59.0, 0.0) == c.value


@pytest.mark.parametrize("drift", [1e-3, 1e-2])
def test_a_fast_train_clock_at_1_hz_is_published_on_arrival(drift):
    """Reading and command sampled together at 1 Hz, the train clock fast: each reading's
    estimate is published when the reading arrives (it waited for the command after it, one
    second late, when the commands were mapped onto the clock's centre of 15 s ago), and a
    lost reading's slot is stamped where its sample would have been."""
    sc, res = run("wen2017_subway", 3, 120.0)
    fl = F.inject(res.events(), F.Fault("drift", drift), np.random.default_rng(0))
    outs, emitted, runner = F.run(fl.events, adapter(sc), 1.0)  # node default: auto
    assert runner.separate_clocks and runner.drift == pytest.approx(drift, rel=1e-3)
    arrived = {s: r for k, s, _, r in fl.events if k == "odometer"}
    late, slots = [], []
    for o, e in zip(outs, emitted):
        t = fl.clock.true_time(o.stamp, e - F.EPOCH)
        if t < 40.0:  # the drift is found from 20 readings on
            continue
        if o.stamp in arrived:
            late.append(e - arrived[o.stamp])
        else:  # a lost reading's slot: at the true second the sample was due
            slots.append(t - round(t))
    assert len(late) > 60 and max(late) == 0.0, late
    assert slots and max(map(abs, slots)) < 1e-3, slots
    s = F.score(outs, emitted, fl, res.truth, 1.0, 120.0 + F.LATENCY)
    assert s["wrong_side"] == 0 and s["hazards"] == 0, s


def _jittery(events, rng):
    """Odometer and balise arrivals later by a further Exp(50 ms) (a radio link's jitter)."""
    ev = [(k, s, f, r + (rng.exponential(0.05) if k != "control" else 0.0))
          for k, s, f, r in events]
    return sorted(ev, key=lambda e: e[3])


@pytest.mark.parametrize("size", [-3.0, 3.0])
def test_a_step_is_measured_from_the_offsets_not_two_arrivals(size):
    """On a jittery link the step is the median offset of the readings that decided it
    against the clock's centre: within 80 ms, 4 standard errors (the medians of 9 and 31
    offsets with Exp(50 ms) jitter: about 20 ms together); from the arrivals of the last old
    reading and the first new one alone it was 0.14 s off for seed 0."""
    sc, res = run("metro_demo", 3, 60.0)
    for seed in range(4):
        rng = np.random.default_rng(seed)
        fl = F.inject(res.events(), F.Fault("step", size, at=30.0), rng)
        fl.events = _jittery(fl.events, rng)
        outs, emitted, runner = F.run(fl.events, adapter(sc, "kf"), 0.1)
        s = F.score(outs, emitted, fl, res.truth, 10.0, 60.0 + F.LATENCY)
        assert runner.events.get("odometer:clock_reset") == 1, (seed, runner.counts)
        assert runner._steps.shift == pytest.approx(size, abs=0.08), seed
        assert s["wrong_side"] == 0, (seed, s)


def test_a_measured_step_is_ok_once_re_anchored():
    """A step measured from the arrivals is a live hypothesis (``clock`` among the doubts)
    while the readings decide it (9 at 10 Hz: 0.9 s) and then, as a burst of wrong stamps
    that may end, until its prior is retired (BURST readings of the new clock: 3.7 s), not
    for a further reanchor_hold; after that every estimate is clear."""
    sc, res = run("metro_demo", 3, 90.0)
    fl = F.inject(res.events(), F.Fault("step", -3.0, at=30.0), np.random.default_rng(0))
    outs, emitted, runner = F.run(fl.events, adapter(sc, "kf"), 0.1)
    s = F.score(outs, emitted, fl, res.truth, 10.0, 90.0 + F.LATENCY)
    assert runner.events.get("odometer:clock_reset") == 1, runner.counts
    held = [e - F.EPOCH for o, e in zip(outs, emitted)
            if "readings held" in o.integrity_reason and e > F.EPOCH + 30]
    assert held and max(held) < 31.1, held
    end = clock_doubt_ends(outs, emitted, fl.events, 30.0, 0.1)
    assert clear_after(outs, emitted, 30.0 + end) == 1.0
    assert s["wrong_side"] == 0 and s["misleading"] == 0 and s["hazards"] == 0, s


def test_a_late_reading_at_1_hz_is_no_doubt():
    """At 1 Hz a reading late by a latency tail (50 ms x Pareto(1.5), cap 1 s) lands on the
    stream's grid at a slot not yet filled: a late reading, not a step, and the estimate stays
    OK (every held reading was in doubt: 91 % available). A backward step lands off the grid
    or on a slot already fused and is still in doubt at once (the -3 s test above)."""
    sc, res = run("wen2017_subway", 3, 150.0)
    fl = F.inject(res.events(), F.Fault("latency", 1.0), np.random.default_rng(1))
    outs, emitted, runner = F.run(fl.events, adapter(sc), 1.0)
    s = F.score(outs, emitted, fl, res.truth, 1.0, 150.0 + F.LATENCY)
    assert "odometer:clock_reset" not in runner.events, runner.counts
    assert not [o for o in outs if o.integrity_reason.startswith("clock")]
    assert s["wrong_side"] == 0 and s["hazards"] == 0, s


def _jittery_step(size, seed, jitter=0.05, kind="kf"):
    """metro_demo (seed) with a step at 46.8 s on a link with Exp(jitter) extra latency on every
    train reading (arrivals then out of order), through the runner with node defaults."""
    sc, res = run("metro_demo", seed, 110.0)
    fault = F.Fault("step", size, at=46.8, jitter=jitter)
    fl = F.inject(res.events(), fault, np.random.default_rng([seed, 1]))
    outs, emitted, runner = F.run(fl.events, adapter(sc, kind), 0.1)
    return F.score(outs, emitted, fl, res.truth, 10.0, 110.0 + F.LATENCY), runner


@pytest.mark.parametrize("size", [-0.5, -0.1, 0.1])
@pytest.mark.parametrize("seed", [1, 2])
def test_a_step_on_a_jittery_link_is_re_anchored_exactly(size, seed):
    # a -0.5 s step among readings that arrive out of order: one reading off the pace of its
    # neighbour released the held ones as late readings of the old clock, the offsets' centre
    # then took the new level as the clock's and no step was declared (the kf up to 10 m off
    # with a sigma of 0.1 m, 42 wrong-side); a 0.1 s step hid inside the jitter (2 m off, 60-75)
    s, runner = _jittery_step(size, seed)
    assert runner.events.get("odometer:clock_reset") == 1, (runner.counts, runner.last_events)
    # measured on the sample grid: the link's jitter does not enter
    assert runner._steps.shift == pytest.approx(size, abs=0.005)
    assert s["wrong_side"] == 0 and s["off_run"] == 0, s


def test_the_sample_grid():
    from train_estimation.core.numerics.clocks import SampleGrid
    g = SampleGrid(0.1, n_min=9)
    rng = np.random.default_rng(0)
    for q in range(20):  # stamps on the train clock with 1 ms of sampling jitter, 1e-3 fast
        g.add(q, 100.0 + 0.1 * (1 + 1e-3) * q + rng.normal(0, 1e-3))
    assert g.tol < 0.02
    assert abs(g.residual(25, 100.0 + 0.1 * (1 + 1e-3) * 25)) < g.tol  # lost packets: no matter
    assert g.residual(21, 100.0 + 0.1 * 21 - 0.1) == pytest.approx(-0.1, abs=0.005)  # a step
    assert abs(g.residual(15, 100.0 + 0.1 * 1.001 * 15)) < g.tol  # a late reading is on it
    g.add(20, 100.0 + 0.1 * 1.001 * 20 - 0.07)  # one corrupted stamp admitted: not learnt
    assert abs(g.residual(21, 100.0 + 0.1 * 1.001 * 21)) < g.tol
    g.add(21, 100.0 + 0.1 * 1.001 * 21)
    assert g.residual(3, 200.0) is None  # the seq back, the stamp on: a sender restarted
    for q in range(3, 3 + 8):
        g.add(q, 200.0 + 0.1 * (q - 3))
    assert g.residual(11, 200.8) is None  # not yet: eight readings off the line
    g.add(11, 200.8)  # the ninth in a row: the restarted sender's grid replaces the old one
    assert abs(g.residual(12, 200.9)) < g.tol and g.residual(12, 200.8) == pytest.approx(-0.1)
    h = SampleGrid(0.1)
    for q in range(20):  # irregular sampling (no grid): never trusted
        h.add(q, 100.0 + 0.1 * q + rng.uniform(0, 0.05))
    assert h.residual(20, 102.0) is None


def test_a_recorder_stall_early_in_a_1_hz_run_does_not_move_the_clock():
    # an 8 s stall at 26 s of a 1 Hz run (26 readings, the offsets' window not yet full): the
    # burst voted into the centre, which moved 4 s, and the rest of the run was published 4 s
    # late (availability 50 %)
    sc, res = run("wen2017_subway", 0, 100.0)
    fl = F.inject(res.events(), F.Fault("recorder_stall", 8.0, at=26.0), np.random.default_rng(0))
    outs, emitted, runner = F.run(fl.events, adapter(sc, "robust"), 1.0)
    s = F.score(outs, emitted, fl, res.truth, 1.0, 100.0 + F.LATENCY)
    assert abs(runner._offsets["train"].value + F.LATENCY) < 0.1, runner._offsets["train"].value
    assert s["wrong_side"] == 0 and s["clear"] > 0.85, s


@pytest.mark.parametrize("err", [0.5, 5.0, -5.0, 60.0])
def test_a_copy_of_a_fused_sample_with_another_stamp_is_refused_and_doubts_nothing(err):
    # fuzzed copies of genuine readings with their stamps moved were held as possible clock
    # steps, each putting the next estimate in doubt: the quick fuzz row of metro_demo was OK
    # in a third of its estimates; a sample fused once cannot be sampled again at another time
    sc, res = run("metro_demo", 3, 60.0)
    fl = F.inject(res.events(), F.Fault("none"), np.random.default_rng(0))
    copies = {round(20.0 + 0.1 * k, 6): err for k in range(0, 200, 3)}  # every third reading
    events = _with_copies(fl.events, copies)
    n_copies = len(events) - len(fl.events)  # (the link lost some originals)
    outs, emitted, runner = F.run(events, adapter(sc, "kf"), 0.1)
    s = F.score(outs, emitted, fl, res.truth, 10.0, 60.0 + F.LATENCY)
    assert runner.rejected.get("odometer:duplicate") == n_copies > 40, runner.counts
    assert s["wrong_side"] == 0 and s["clear"] > 0.99, s


@pytest.mark.parametrize("size", [-10.0, -3.0, 3.0, 10.0])
def test_a_step_in_the_first_seconds_of_a_1_hz_run_is_seen_by_the_seqs(size):
    """A train clock that steps 4 s into a 1 Hz run, before the clock has its nine readings: the
    seqs place the new readings off the provisional sample grid, and the step is re-anchored.
    Without it the readings after a -10 s step, stamped where the old clock had been, were
    taken as its late ones (the robust filter 70 m behind, integrity OK); after a +3 s step the
    step's offsets voted into the clock's centre before the watch judged them, and every slot
    to the end of the run came 3 s early (availability 0 %)."""
    sc, res = run("wen2017_subway", 0, 70.0)
    fl = F.inject(res.events(), F.Fault("step", size, at=4.0), np.random.default_rng(0))
    outs, emitted, runner = F.run(fl.events, adapter(sc, "robust"), 1.0)
    s = F.score(outs, emitted, fl, res.truth, 1.0, 70.0 + F.LATENCY)
    assert runner.events.get("odometer:clock_reset") == 1, runner.counts
    assert runner._steps.shift == pytest.approx(size, abs=0.02)
    assert s["wrong_side"] == 0 and s["off_run"] == 0 and s["misleading"] == 0, s
    # held while the nine readings that decide the step come, then carried as a possible
    # burst for its prior's BURST readings; clear after that
    end = clock_doubt_ends(outs, emitted, fl.events, 4.0, 1.0)
    assert clear_after(outs, emitted, 4.0 + end) > 0.9


def test_the_provisional_sample_grid():
    from train_estimation.core.numerics.clocks import SampleGrid
    g = SampleGrid(1.0, n_min=9)
    for q in range(2):
        g.add(q, 50.0 + q)
    assert g.residual(2, 52.0) is None  # two samples: no line yet
    g.add(2, 52.0)
    # 3 samples beyond the learnt ones: the floor, plus per sample the clock's rate (0.02 of
    # the period) and the period's own doubt (4 floors over the learnt span of 2 samples)
    assert g.residual(5, 55.0) == pytest.approx(0.0) and g.tol_at(5) == pytest.approx(0.13)
    assert g.residual(14, 54.0) == pytest.approx(-10.0)  # a -10 s step, 11 samples on
    assert g.tol_at(1) == pytest.approx(0.01)  # inside the learnt span: the floor
    h = SampleGrid(1.0, n_min=9)
    for q, st in ((0, 50.0), (1, 51.0), (7, 52.0)):  # a corrupted seq among three: no line
        h.add(q, st)
    assert h.residual(3, 53.0) is None and h.tol_at(3) == float("inf")


def test_the_provisional_grid_holds_the_period_its_few_samples_allow():
    """Three samples of a 0.1 s grid, each sampled within the floor (10 ms) of its slot, can lie
    on a line of period 0.090 s; the samples after them, on the true grid, must lie within the
    provisional grid's tolerance, which grows by what the period of so few samples may be off
    (4 floors over their span per sample). At 0.02 periods per sample alone they were refused
    as ahead of their stream, and never learnt from."""
    from train_estimation.core.numerics.clocks import SampleGrid
    g = SampleGrid(0.1, n_min=9)
    for q, st in ((0, 0.010), (1, 0.100), (2, 0.190)):  # period 0.090 s, on the true grid +-10 ms
        g.add(q, st)
    for q in range(3, 9):
        for jitter in (-0.01, 0.0, 0.01):  # the true grid, within the floor
            assert abs(g.residual(q, 0.1 * q + jitter)) <= g.tol_at(q), (q, jitter)


@pytest.mark.parametrize("jitter_seed", [5, 6, 11])
def test_a_sampling_loop_that_wobbles_is_no_stream_ahead_of_itself(jitter_seed):
    """metro_demo 300 s, every odometer sample taken up to 15 ms off its 10 Hz slot (uniform;
    the stamp is the true sampling instant, the values the truth there), a constant link: every
    reading is good. Its first three samples fitted a provisional grid of period 0.094 s, whose
    tolerance grew by 2 ms a sample while the stamps left it by 6-9: 3-17 readings refused as
    ahead of their stream in the first seconds. Now none."""
    sc, res = run("metro_demo", seed=0, duration=300.0)
    tr = res.truth
    ev = wobbled(sc, res, 0.015, np.random.default_rng(jitter_seed))
    fl = F.inject(ev, F.Fault("none"), np.random.default_rng(1))
    outs, emitted, runner = F.run(fl.events, adapter(sc, "robust"), 0.1)
    assert not runner.rejected, dict(runner.rejected)
    s = F.score(outs, emitted, fl, tr, 10.0, 300.0 + F.LATENCY)
    assert s["wrong_side"] == 0 and s["misleading"] == 0, s


def test_a_balise_during_a_step_waits_with_the_odometer_and_is_fused_on_the_new_clock():
    """wen2017_subway (1 Hz), the train clock 3 s back at 55 s, a balise among the nine
    readings that decide it: held with them and mapped with the step. Taken at once, it was
    placed 3 s (60 m) off, refused by the gate, and its doubt held the estimate DEGRADED to the
    next balise (availability 0 %)."""
    sc, res = run("wen2017_subway", 1, 115.0)
    fl = F.inject(res.events(), F.Fault("step", -3.0, at=55.0), np.random.default_rng(0))
    outs, emitted, runner = F.run(fl.events, adapter(sc, "robust"), 1.0)
    s = F.score(outs, emitted, fl, res.truth, 1.0, 115.0 + F.LATENCY)
    assert runner.events.get("odometer:clock_reset") == 1, runner.counts
    assert "balise:outside_gate" not in runner.rejected, runner.counts
    assert s["wrong_side"] == 0 and s["misleading"] == 0, s
    end = clock_doubt_ends(outs, emitted, fl.events, 55.0, 1.0)
    assert clear_after(outs, emitted, 55.0 + end) > 0.9


def test_a_counter_that_restarts_counts_on_past_its_old_highest_seq_on_its_own_line():
    """A 1 Hz odometer sampled seqs 0..9 at stamps 1..10, then rebooted and counts 0, 1, ...
    from stamp 11: its samples are off the learnt line (restarted: no residual) until the new
    count passes 9, where the old line would put them 11 s late. Two admitted in a row already
    make their own line, on which they lie; they are never learnt into the old one, and nine
    of them replace it."""
    from train_estimation.core.numerics.clocks import SampleGrid

    g = SampleGrid(1.0)
    for q in range(10):
        g.add(q, 1.0 + q)
    assert g.residual(5, 6.0) == 0.0
    for q in range(9):
        assert g.residual(q, 11.0 + q) is None
        g.add(q, 11.0 + q)
    # the ninth replaced the line: the new count's own
    assert g.residual(9, 20.0) == 0.0 and g.residual(10, 21.0) == 0.0
    # two in a row are enough to place the one that passes the old highest seq
    g = SampleGrid(1.0)
    for q in range(10):
        g.add(q, 1.0 + q)
    for q in (7, 8):
        g.add(q, 11.0 + q)  # admitted (off the line: no residual)
    assert g.residual(9, 20.0) == 0.0 and g.residual(10, 21.0) == 0.0
    g.add(9, 20.0)
    assert g.residual(5, 6.0) == 0.0  # the old line kept what it had learnt
    # one alone is no line (a corrupted seq): off the old line as before
    g = SampleGrid(1.0)
    for q in range(10):
        g.add(q, 1.0 + q)
    g.add(8, 19.0)
    assert g.residual(10, 21.0) == 10.0
