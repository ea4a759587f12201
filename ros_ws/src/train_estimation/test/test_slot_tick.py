"""A lost reading's slot is published when it is due by the arrival clock (``runner.tick``),
not when the next message happens to arrive; never twice, never out of order."""

import os
import sys

import numpy as np
import pytest

from train_estimation.core.online.replay import TimerTicks
from train_estimation.core.online.replay import replay as core_replay
from train_estimation.tools import faults as F

sys.path.insert(0, os.path.dirname(__file__))
from clocks import adapter, run  # noqa: E402

GRACE, TICK = 0.5, 0.05


def stream(scenario, duration, seed=1):
    """The clean received stream (arrival = sample time + 50 ms) and the simulated run."""
    sc, res = run(scenario, seed, duration)
    return sc, res, F.inject(res.events(), F.Fault("none"), np.random.default_rng(0)).events


def lose_one(events, near):
    """The stream without one odometer reading sampled near ``near`` s whose two neighbours
    arrived (a lone loss: the slot's prediction is OK by the monitor), and its stamp."""
    odo = [k for k, e in enumerate(events) if e[0] == "odometer"]
    stamps = [events[k][1] for k in odo]
    period = np.median(np.diff(stamps))
    for j in range(1, len(odo) - 1):
        s = stamps[j]
        if s - F.EPOCH >= near and abs(stamps[j - 1] - (s - period)) < 1e-6 and \
                abs(stamps[j + 1] - (s + period)) < 1e-6:
            return events[:odo[j]] + events[odo[j] + 1:], events[odo[j]], s
    raise AssertionError("no lone reading to lose")


def replay(sc, events, kind, tick_period=TICK):
    outs, emitted, runner = F.run(events, adapter(sc, kind), 1 / sc.odometer_rate,
                                  tick_period=tick_period, slot_grace=GRACE)
    return outs, emitted, runner


def assert_one_per_slot_in_order(outs):
    stamps = np.array([o.stamp for o in outs])
    assert np.all(np.diff(stamps) > 0), "an estimate out of order or twice"


@pytest.mark.parametrize("kind", ["robust", "kf"])
def test_a_lost_1hz_reading_leaves_within_the_grace(kind):
    sc, _res, ev = stream("crh3_high_speed", 90.0)
    assert sc.odometer_rate == 1.0
    lost, reading, s = lose_one(ev, 40.0)
    outs, emitted, runner = replay(sc, lost, kind)
    assert_one_per_slot_in_order(outs)
    at = [i for i, o in enumerate(outs) if abs(o.stamp - s) < 1e-6]
    assert len(at) == 1, "the lost slot: one estimate"
    o, e = outs[at[0]], emitted[at[0]]
    assert not o.measurement_used and o.integrity != 2 and not o.integrity_reason, o
    # due at the reading's arrival (stamp + 50 ms on this clean link), out by the next tick
    # after the grace -- not a second later with the next message
    assert e - reading[3] <= GRACE + TICK + 1e-6, e - reading[3]
    # the same prediction the inputs' watermarks publish (the same commands before it), only
    # earlier: without the timer it leaves with the next message, a second after its reading
    ref, ref_emitted, _ = replay(sc, lost, kind, tick_period=None)
    k = next(i for i, r in enumerate(ref) if abs(r.stamp - s) < 1e-6)
    assert ref_emitted[k] - reading[3] > 0.9
    assert (ref[k].position, ref[k].velocity) == (o.position, o.velocity)
    assert [r.stamp for r in ref] == [r.stamp for r in outs]


@pytest.mark.parametrize("near", [40.0, 5.0])
def test_a_lost_1hz_reading_in_the_first_seconds_leaves_within_the_grace(near):
    """Also before the train clock has its nine readings (nine seconds at 1 Hz): three that
    agree place it (a reading lost at 6 s waited for the next one, a second late)."""
    sc, _res, ev = stream("wen2017_subway", 40.0, seed=0)
    assert sc.odometer_rate == 1.0
    lost, reading, s = lose_one(ev, near if near < 40.0 else 20.0)
    outs, emitted, _ = replay(sc, lost, "robust")
    k = next(i for i, o in enumerate(outs) if abs(o.stamp - s) < 1e-6)
    assert outs[k].integrity != 2 and not outs[k].integrity_reason
    assert emitted[k] - reading[3] <= GRACE + TICK + 1e-6


@pytest.mark.parametrize("kind", ["robust", "kf"])
@pytest.mark.parametrize("delay", [0.8, 1.3])
def test_a_reading_after_its_predicted_slot_is_fused_and_not_published_again(kind, delay):
    """0.8 s: after the grace, before the next reading (fused in order); 1.3 s: after the next
    reading was fused (fused by rewinding)."""
    sc, _res, ev = stream("crh3_high_speed", 90.0)
    lost, reading, s = lose_one(ev, 40.0)
    late = reading[:3] + (reading[3] + delay,)
    ev_late = sorted(lost + [late], key=lambda e: e[3])
    outs, emitted, runner = replay(sc, ev_late, kind)
    assert_one_per_slot_in_order(outs)
    at = [i for i, o in enumerate(outs) if abs(o.stamp - s) < 1e-6]
    assert len(at) == 1 and not outs[at[0]].measurement_used
    assert emitted[at[0]] < late[3]  # predicted before the reading came
    assert not runner.rejected, dict(runner.rejected)
    ref, _, r0 = replay(sc, ev, kind)
    assert runner.accepted == r0.accepted  # the late reading was fused
    rewound = runner.events.get("odometer:fused_late", 0)
    assert rewound == (1 if delay > 1.0 else 0), dict(runner.events)
    # the first estimate published after it arrived carries it: as without the delay
    i = next(i for i, e in enumerate(emitted) if e > late[3])
    want = next(o for o in ref if abs(o.stamp - outs[i].stamp) < 1e-6)
    assert outs[i].measurement_used
    assert outs[i].position == pytest.approx(want.position, abs=1e-6)
    assert outs[i].velocity == pytest.approx(want.velocity, abs=1e-6)


@pytest.mark.parametrize("kind", ["robust", "kf"])
def test_a_backlog_burst_is_not_taken_for_lost_readings(kind):
    """After a node stall the backlog arrives in one burst: by the arrival clock each of its
    readings is seconds overdue, but it is in the burst; no slot is predicted ahead of it."""
    sc, res = run("crh3_high_speed", 1, 90.0)
    fl = F.inject(res.events(), F.Fault("node_stall", 8.0, 40.0), np.random.default_rng(0))
    outs, emitted, _ = replay(sc, fl.events, kind)
    assert_one_per_slot_in_order(outs)
    burst = [s for k, s, _f, r in fl.events
             if k == "odometer" and r == pytest.approx(F.EPOCH + 48.0) and s > F.EPOCH + 41.0]
    assert len(burst) >= 4
    by_stamp = {round(o.stamp, 6): o for o in outs}
    for s in burst:
        assert by_stamp[round(s, 6)].measurement_used, s - F.EPOCH


def test_10hz_lost_readings_leave_as_before():
    """At 10 Hz the commands' watermark publishes a lost slot within 0.25 s, before the grace:
    the timer changes nothing, estimates or publication times."""
    sc, _res, ev = stream("metro_demo", 60.0)
    lost, _, _ = lose_one(ev, 30.0)
    outs, emitted, _ = replay(sc, lost, "kf")
    ref, ref_emitted, _ = replay(sc, lost, "kf", tick_period=None)
    assert [(o.stamp, o.position, o.integrity) for o in outs] == \
        [(o.stamp, o.position, o.integrity) for o in ref]
    np.testing.assert_array_equal(emitted, ref_emitted)


def test_timer_ticks_fall_between_messages_and_stop_in_a_long_silence():
    ticks = TimerTicks(0.05)
    assert ticks.until(100.01) == []  # the first message starts the timer
    assert ticks.until(100.16) == pytest.approx([100.05, 100.10, 100.15])
    assert ticks.until(100.16) == []
    got = ticks.until(1e9)  # a log time far ahead: bounded
    assert len(got) == TimerTicks.cap
    assert ticks.until(1e9 + 0.07) == pytest.approx([1e9 + 0.05], abs=1e-6)
    assert TimerTicks(None).until(5.0) == [] and TimerTicks(0.05).until(None) == []


def test_a_stalled_node_does_not_tick():
    """faults.run with a node stall: the timer fires on both sides of it, never inside (a node
    whose callbacks are blocked runs no timer either; every message of the stall arrives at its
    end)."""
    sc, res, _ = stream("crh3_high_speed", 40.0)
    fl = F.inject(res.events(), F.Fault("node_stall", 8.0, at=10.0), np.random.default_rng(0))
    assert fl.stalled == ((10.0, 18.0),)
    seen = {}
    for stalled in ((), fl.stalled):
        t = seen[stalled] = []
        core_replay(fl.events, adapter(sc, "kf"), 1.0, tick_period=TICK, on_time=t.append,
                    blocked=(lambda u, st=stalled: any(a <= u - F.EPOCH < b for a, b in st))
                    if stalled else None)
    inside = [[u for u in seen[k] if 10.0 < u - F.EPOCH < 18.0] for k in ((), fl.stalled)]
    assert inside[0] and not inside[1]
    assert any(u - F.EPOCH >= 18.0 for u in seen[fl.stalled])


@pytest.mark.parametrize("kind", ["robust", "kf"])
def test_a_slow_odometer_link_is_no_loss(kind):
    """Every odometer reading 0.7 s on its link, the commands on time: the commands lead the
    readings by that much, and a slot is given up as lost only ``fallback`` beyond the lead
    they usually have (EstimatorRunner._odometer_lag). With ``fallback`` alone (0.2 s) every
    slot was predicted before its reading came, each reading fused late, and every estimate
    published without a measurement (DEGRADED by no_measurement all run)."""
    sc, res = run("metro_demo", 1, 120.0)
    fl = F.inject(res.events(), F.Fault("route", 0.65, 0.0), np.random.default_rng(0))
    outs, _emitted, runner = replay(sc, fl.events, kind)
    assert_one_per_slot_in_order(outs)
    late = [o.stamp for o in outs if "no_measurement" in o.integrity_reason]
    assert not late, late[:5]
    assert "odometer:fused_late" not in runner.events, runner.counts


@pytest.mark.parametrize("kind", ["robust", "kf"])
def test_readings_after_the_commands_stopped_leave_on_a_clock_that_stood_still(kind):
    """The commands stop and the arrival clock stands still after the last readings (a
    simulation's end: no /clock comes any more), while the node's steady clock runs on past
    the command timeout: every reading received is estimated. The node's clock (its last
    arrival less output_delay, through the odometer's offset) lies below the last readings'
    stamps, and they waited for it for ever."""
    from train_estimation.core.online.runner import EstimatorRunner

    sc, _res, ev = stream("metro_demo", 60.0)
    stop = F.EPOCH + 50.0
    ev = [e for e in ev if not (e[0] == "control" and e[1] > stop)]
    runner = EstimatorRunner(adapter(sc, kind), 1 / sc.odometer_rate)
    outs, delay = [], 0.05
    for topic, stamp, fields, recv in ev:
        runner.push(topic, stamp, fields, recv, wall=recv)
        outs += runner.advance_to(runner.ready_time(recv, delay, 4 * delay, wall=recv))
    last = max(e[1] for e in ev if e[0] == "odometer")
    assert last > stop + 5.0
    now = ev[-1][3]  # the arrival clock stands here; the steady clock runs on
    for wall in np.arange(now, now + 3.0 * runner.command_timeout, TICK):
        outs += runner.advance_to(runner.ready_time(now, delay, 4 * delay, wall=wall))
        outs += runner.tick(now)
    assert_one_per_slot_in_order(outs)
    assert outs[-1].stamp == last, (outs[-1].stamp, last)
