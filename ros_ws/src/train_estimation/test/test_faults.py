"""The fault injectors of ``tools/faults.py`` do what they say, and one case of each fault class
runs through an estimator and is scored (``./run bench integrity`` is the campaign)."""

import math
import os
import sys

import numpy as np
import pytest

from train_estimation.core.online.replay import replay
from train_estimation.core.online.runner import EstimatorRunner, Output
from train_estimation.tools import faults as F

sys.path.insert(0, os.path.dirname(__file__))
from clocks import adapter, run  # noqa: E402

ODO = {"distance": 0.0, "speed": 0.0, "speed_variance": 0.01}


def clean(duration=30.0):
    """Control and odometer at 10 Hz, a balise every 10 s: ``(topic, t, fields)``."""
    ev = []
    for k in range(int(duration * 10)):
        t = 0.1 * k
        ev.append(("control", t, {"target_acceleration": 0.0}))
        ev.append(("odometer", t, dict(ODO, seq=k)))
        if k % 100 == 50:
            ev.append(("balise", t, {"seq": k, "balise_id": 1, "position": 0.0,
                                     "position_variance": 1.0}))
    return ev


def by_topic(out, topic):
    return [(s, f, r) for k, s, f, r in out if k == topic]


def test_clean_stream_is_stamped_on_one_epoch_with_the_link_latency():
    out = F.inject(clean(), F.Fault("none"), np.random.default_rng(0)).events
    assert len(out) == len(clean())
    for _k, s, _f, r in out:
        assert r == pytest.approx(s + F.LATENCY)
    assert [r for *_, r in out] == sorted(r for *_, r in out)


def test_a_noisy_count_moves_only_the_odometers_distance_by_its_stated_scatter():
    out = F.inject(clean(300.0), F.Fault("none"), np.random.default_rng(0)).events
    got = F.noisy_count(out, 0.5, np.random.default_rng(1))
    assert [(k, s, r) for k, s, _f, r in got] == [(k, s, r) for k, s, _f, r in out]
    d = []
    for (k, _s, f0, _r), (_k, _s1, f1, _r1) in zip(out, got):
        if k == "odometer":
            assert {**f1, "distance": f0["distance"]} == f0
            d.append(f1["distance"] - f0["distance"])
        else:
            assert f1 == f0
    # 3,000 draws: the sample sd within 5 of its standard errors (0.5 / sqrt(2 n)) of 0.5
    assert len(d) == 3000 and abs(np.std(d) - 0.5) < 5 * 0.5 / math.sqrt(2 * len(d))
    assert F.noisy_count(out, 0.5, np.random.default_rng(1)) == got  # seeded


@pytest.mark.parametrize("count", [1, 3])
def test_a_stamp_fault_moves_only_the_stamps_of_count_readings(count):
    f = F.Fault("stamp", 60.0, 10.0, count=count)
    base = by_topic(F.inject(clean(), F.Fault("none"), np.random.default_rng(0)).events,
                    "odometer")
    got = by_topic(F.inject(clean(), f, np.random.default_rng(0)).events, "odometer")
    moved = [(b, g) for b, g in zip(base, got) if g[0] != b[0]]
    assert len(moved) == count
    for b, g in moved:
        assert g[0] - b[0] == pytest.approx(60.0)
        assert g[2] == b[2]  # arrives when it would have: only the stamp lies
        assert g[0] - 60.0 >= F.EPOCH + 10.0 - 1e-9


@pytest.mark.parametrize("size", [-10.0, -0.5, 3.0])
def test_a_step_shifts_train_stamps_from_its_time_on_and_not_commands(size):
    at = 12.0
    fl = F.inject(clean(), F.Fault("step", size, at), np.random.default_rng(0))
    for k, s, _f, r in fl.events:
        t = r - F.LATENCY - F.EPOCH
        want = F.EPOCH + t + (size if k != "control" and t >= at - 1e-9 else 0.0)
        assert s == pytest.approx(want, rel=0, abs=1e-5), (k, t)
    # the truth mapping undoes it: each stamp back to its own sample time
    for k, s, _f, r in fl.events:
        if k == "odometer":
            assert fl.clock.true_time(s, r - F.EPOCH) == pytest.approx(
                r - F.LATENCY - F.EPOCH, rel=0, abs=1e-5)


def test_drift_scales_train_stamps_only():
    d = 1e-2
    fl = F.inject(clean(), F.Fault("drift", d), np.random.default_rng(0))
    for k, s, _f, r in fl.events:
        t = r - F.LATENCY - F.EPOCH
        assert s - F.EPOCH == pytest.approx(t * (1 + d) if k != "control" else t, rel=0, abs=1e-5)


def test_outage_and_command_stop_drop_what_they_say():
    fl = F.inject(clean(), F.Fault("outage", 5.0, 10.0), np.random.default_rng(0))
    seq = [f["seq"] for s, f, r in by_topic(fl.events, "odometer")]
    assert seq == [k for k in range(300) if not 100 <= k < 150]
    assert len(by_topic(fl.events, "control")) == 300
    assert fl.end == 15.0
    fl = F.inject(clean(), F.Fault("command_stop", 0.0, 20.0), np.random.default_rng(0))
    t_ctl = [s - F.EPOCH for s, *_ in by_topic(fl.events, "control")]
    assert max(t_ctl) < 19.95 and len(t_ctl) == 200
    assert len(by_topic(fl.events, "odometer")) == 300


@pytest.mark.parametrize("size", [20.0, -20.0])
def test_a_misplaced_balise_is_read_when_the_train_has_run_that_much_more(size):
    """The first balise at or after ``at`` lies ``size`` m further on: at 10 m/s it is read
    size / 10 s later (stamp and arrival), with the fields it always had; the others stay."""
    ev = [(k, t, dict(f, distance=10.0 * t) if k == "odometer" else f) for k, t, f in clean()]
    base = by_topic(F.inject(ev, F.Fault("none"), np.random.default_rng(0)).events, "balise")
    got = by_topic(F.inject(ev, F.Fault("balise", size, 10.0), np.random.default_rng(0)).events,
                   "balise")
    assert [s - F.EPOCH for s, _f, _r in base] == pytest.approx([5.0, 15.0, 25.0])
    assert [s - F.EPOCH for s, _f, _r in got] == pytest.approx([5.0, 15.0 + size / 10.0, 25.0])
    assert [f for _s, f, _r in got] == [f for _s, f, _r in base]
    assert all(r == pytest.approx(s + F.LATENCY) for s, _f, r in got)


@pytest.mark.parametrize("kind", ["recorder_stall", "node_stall"])
def test_a_stall_delivers_its_backlog_in_one_burst(kind):
    fl = F.inject(clean(), F.Fault(kind, 8.0, 10.0), np.random.default_rng(0))
    for k, s, _f, r in fl.events:
        t = s - F.EPOCH
        late = 10.0 <= t + F.LATENCY < 18.0 and (kind == "node_stall" or k != "control")
        assert r - F.EPOCH == pytest.approx(18.0 if late else t + F.LATENCY, rel=0, abs=1e-5)
    assert [r for *_, r in fl.events] == sorted(r for *_, r in fl.events)


def test_a_route_change_delays_the_train_readings_from_then_on():
    """From ``at`` the odometer and balise readings come ``size`` s later and stay so; stamps,
    values and commands untouched."""
    fl = F.inject(clean(40.0), F.Fault("route", 1.5, 10.0), np.random.default_rng(0))
    for k, s, _f, rc in fl.events:
        t = s - F.EPOCH
        extra = 1.5 if k != "control" and t >= 10.0 else 0.0
        assert rc - F.EPOCH == pytest.approx(t + F.LATENCY + extra, rel=0, abs=1e-5)
    assert [r for *_, r in fl.events] == sorted(r for *_, r in fl.events)


def test_a_queue_holds_the_readings_then_delivers_them_faster():
    """Every QUEUE_EVERY s from ``at``: a train reading sampled u s into an episode comes
    QUEUE_BACKLOG - u (1 - 1/r) s late, until that is 0; stamps, values and commands untouched."""
    r, at = 2.0, 5.0
    fl = F.inject(clean(80.0), F.Fault("queue", r, at), np.random.default_rng(0))
    for k, s, _f, rc in fl.events:
        t = s - F.EPOCH
        u = (t - at) % F.QUEUE_EVERY
        extra = F.QUEUE_BACKLOG - u * (1.0 - 1.0 / r) if k != "control" and t >= at and \
            u * (1.0 - 1.0 / r) < F.QUEUE_BACKLOG else 0.0
        assert rc - F.EPOCH == pytest.approx(t + F.LATENCY + extra, rel=0, abs=1e-5)
    # the first reading of each episode is the latest, 1 s; each queue drains in 2 s
    lat = {round(s - F.EPOCH, 3): rc - s for k, s, _f, rc in fl.events if k == "odometer"}
    assert lat[5.0] == pytest.approx(F.LATENCY + 1.0) and lat[35.0] == pytest.approx(1.05)
    assert lat[7.0] == pytest.approx(F.LATENCY) and lat[6.0] == pytest.approx(0.55)
    assert [r for *_, r in fl.events] == sorted(r for *_, r in fl.events)


def test_a_wander_delays_each_topic_by_its_own_slowly_moving_latency():
    """``wander``: from ``at`` each topic's link adds |x| to its latency, x an Ornstein-Uhlenbeck
    process of ``size`` s and WANDER_TAU s: stamps, values and the order of each topic's own
    messages' stamps untouched; the mean square of the added latency is ``size``^2 (about 15
    correlation times of it in 600 s: within a factor 2.5 either way, 4 of its relative
    errors sqrt(2 / 15)); successive messages 0.1 s apart carry nearly the same latency (lag-one
    correlation exp(-0.1 / 20) = 0.995 for x); the topics' wanders are not one."""
    size, at = 0.05, 10.0
    ev = clean(600.0)
    base = F.inject(ev, F.Fault("none"), np.random.default_rng(0)).events
    fl = F.inject(ev, F.Fault("wander", size, at), np.random.default_rng(0)).events
    assert sorted((k, s, str(f)) for k, s, f, _ in fl) == \
        sorted((k, s, str(f)) for k, s, f, _ in base)
    assert [r for *_, r in fl] == sorted(r for *_, r in fl)
    extra = {}
    for k, s, _f, rc in fl:
        t = s - F.EPOCH
        x = rc - F.EPOCH - t - F.LATENCY
        assert x >= -1e-6 and (t >= at or abs(x) < 1e-6), (k, t, x)  # (stamps near 1.7e9 s)
        if t >= at:
            extra.setdefault(k, []).append(x)
    for k in ("odometer", "control"):
        x = np.array(extra[k])
        assert 0.4 * size ** 2 < float(np.mean(x * x)) < 2.5 * size ** 2, (k, np.mean(x * x))
        assert np.corrcoef(x[1:], x[:-1])[0, 1] > 0.9, k
    assert not np.allclose(extra["odometer"], extra["control"])


def test_latency_tail_is_capped_and_heavy():
    fl = F.inject(clean(300.0), F.Fault("latency", 5.0, 0.0), np.random.default_rng(1))
    lat = np.array([r - s for k, s, f, r in fl.events if k == "odometer"])
    assert lat.min() >= F.LATENCY - 1e-9 and lat.max() <= 5.0 + 1e-6
    # Pareto(1.5) times 50 ms: P(> 1 s) = 20^-1.5 = 1.1 %; 3000 readings: 34 expected
    n = int(np.sum(lat > 1.0))
    assert 34 - 4 * math.sqrt(34) < n < 34 + 4 * math.sqrt(34)
    assert [r for *_, r in fl.events] == sorted(r for *_, r in fl.events)


def test_fuzz_mixes_in_stamps_inside_max_future():
    fl = F.inject(clean(), F.Fault("fuzz", 5.0), np.random.default_rng(2))
    assert sum(fl.counts.values()) > 1000
    assert any(fl.counts[k] for k in F.INSIDE_FUTURE)


def _out(stamp, x, var, integrity=0):
    C = np.full((4, 4), np.nan)
    C[:2, :2] = [[var, 0.0], [0.0, 0.01]]
    return Output(stamp, x, 0.0, math.nan, math.nan, tuple(C.ravel()), True, integrity)


def test_score_counts_wrong_side_and_time_to_alarm():
    truth = {"t": 0.1 * np.arange(200), "position": np.zeros(200)}
    fl = F.Faulted([], F.TrainClock(), onset=5.0, end=5.0)
    t = 0.1 * np.arange(200)
    outs, emitted = [], F.EPOCH + t + F.LATENCY
    for k, ti in enumerate(t):
        bad = 50 <= k < 80  # 30 m off with a 1 m sigma: OK until 7 s, then ALARM
        outs.append(_out(F.EPOCH + ti, 30.0 if bad else 0.5, 1.0, 2 if 70 <= k < 80 else 0))
    outs.append(_out(F.EPOCH + 1e6, 0.0, 1.0))  # a stamp far outside the run, said OK
    emitted = np.append(emitted, emitted[-1])
    s = F.score(outs, emitted, fl, truth, 10.0, 20.0)
    assert s["wrong_side"] == 20 and s["off_run"] == 1 and s["hazards"] == 30
    assert s["tta"] == pytest.approx(2.0)
    assert s["clear"] == pytest.approx(140 / 150)  # the far stamp is of no use
    assert s["max_err"] == pytest.approx(30.0) and s["bad_cov"] == 0
    # a covariance claiming certainty of a hazard is no bound: wrong-side and not PD
    s = F.score([_out(F.EPOCH + 6.0, 3.0, -1.0)], np.array([F.EPOCH + 6.05]), fl, truth,
                10.0, 20.0)
    assert s["wrong_side"] == 1 and s["bad_cov"] == 1 and s["tta"] == math.inf


def test_an_estimate_past_the_truths_end_is_not_judged_by_its_last_place():
    """A train running at 10 m/s, its truth ending at 19.9 s, estimated right to 20.4 s: the
    five estimates stamped past the truth are not judged (held at its last place the truth
    read them 1-5 m off with a 0.1 m sigma: wrong-side, hazardous and misleading), and within
    a second of the run they are no off-run either."""
    t = 0.1 * np.arange(200)
    truth = {"t": t, "position": 10.0 * t}
    fl = F.Faulted([], F.TrainClock(), onset=0.0, end=0.0)
    ts = 0.1 * np.arange(205)
    outs = [_out(F.EPOCH + u, 10.0 * u, 0.01) for u in ts]
    s = F.score(outs, F.EPOCH + ts + F.LATENCY, fl, truth, 10.0, 20.5)
    assert (s["wrong_side"], s["hazards"], s["misleading"], s["off_run"]) == (0, 0, 0, 0), s


@pytest.mark.parametrize("ahead", [0.5, 2.0])
def test_the_replays_end_publishes_nothing_stamped_past_the_trains_present(ahead):
    """At the stream's end an odometer item stamped ``ahead`` s past the last reading is
    queued (a corrupted copy the door admitted: a fuzzed 50 Hz stream's copies 5 s ahead had
    voted the clock's ceiling there, so nothing below it was ahead of the clock). A live node
    would fuse it (or refuse it) only once its stamp came; the replay's drain at the last
    arrival published every slot up to it, predictions as if the train were there already
    (a zone controller then granted the train behind an authority past this one's rear). The
    clean run's estimates stand and none is stamped past the present."""
    sc, res = run("metro_demo", 1, 40.0)
    events = F.inject(res.events(), F.Fault("none"), np.random.default_rng(0)).events
    last = max((e for e in events if e[0] == "odometer"), key=lambda e: e[1])

    class Copied(EstimatorRunner):
        def drain(self):
            self._queue("odometer", last[1] + ahead, dict(last[2]))
            return super().drain()

    period = 1.0 / sc.odometer_rate
    outs0, _ = replay(events, adapter(sc, "kf"), period)
    outs, _ = replay(events, None, period, runner=Copied(adapter(sc, "kf"), period))
    assert max(o.stamp for o in outs) <= last[1] + 0.5 * period
    assert [o.stamp for o in outs] == [o.stamp for o in outs0]


@pytest.mark.parametrize("rate", [0.0, 0.5])
def test_a_count_rate_fault_moves_the_count_alone_from_its_onset(rate):
    """``count_rate``: from ``at`` the count advances ``rate`` times the distance run (0: it
    froze), continuous at the onset; the speed, stamps and everything else untouched."""
    ev = [(tp, t, dict(f, distance=10.0 * t, speed=10.0) if tp == "odometer" else f)
          for tp, t, f in clean()]
    out = F.inject(ev, F.Fault("count_rate", rate, 12.0), np.random.default_rng(0)).events
    ref = F.inject(ev, F.Fault("none"), np.random.default_rng(0)).events
    assert [(k, s, r) for k, s, _f, r in out] == [(k, s, r) for k, s, _f, r in ref]
    for (k, s, f, _), (_, _, f0, _) in zip(out, ref):
        t = s - F.EPOCH
        if k != "odometer" or t < 12.0 - 1e-9:
            assert f == f0
            continue
        assert f["distance"] == pytest.approx(120.0 + rate * (10.0 * t - 120.0))
        assert {**f, "distance": f0["distance"]} == f0


@pytest.mark.parametrize("fault", [
    F.Fault("none"), F.Fault("stamp", 60.0, 10.0), F.Fault("step", -3.0, 10.0),
    F.Fault("drift", -1e-2), F.Fault("outage", 5.0, 10.0), F.Fault("command_stop", 0.0, 10.0),
    F.Fault("latency", 5.0), F.Fault("queue", 1.5, 5.0, jitter=0.05),
    F.Fault("route", 1.5, 10.0),
    F.Fault("recorder_stall", 4.0, 10.0), F.Fault("node_stall", 4.0, 10.0),
    F.Fault("fuzz", 0.5), F.Fault("balise", 10.0, 5.0),
    F.Fault("reboot", 3.0, 10.0), F.Fault("count_rate", 0.5, 10.0),
    F.Fault("wander", 0.1, 5.0)],
    ids=lambda f: f.kind)
def test_one_case_of_each_fault_class_runs_through_an_estimator(fault):
    sc, res = run("metro_demo", 1, 20.0)
    fl = F.inject(res.events(), fault, np.random.default_rng(0))
    outs, emitted, runner = F.run(fl.events, adapter(sc), 0.1, control_clock="same")
    assert len(outs) == len(emitted) > 50
    assert np.all(np.diff(emitted) >= 0)
    s = F.score(outs, emitted, fl, res.truth, 10.0, 20.0 + F.LATENCY)
    assert s["outputs"] == len(outs)
    assert 0.0 <= s["clear"] <= 1.0 and math.isfinite(s["rms_err"])
    if fault.kind == "none":  # the clean run is inside its bound: the scoring has no false alarm
        assert s["wrong_side"] == 0 and s["hazards"] == 0 and s["clear"] > 0.95
    if fault.kind in ("none", "stamp"):  # faults.run is core.replay.replay, timed
        ref, _ = replay(fl.events, adapter(sc), 0.1, control_clock="same")
        assert [(o.stamp, o.position) for o in ref] == [(o.stamp, o.position) for o in outs]


def test_a_sample_counter_that_skips_is_logged_and_no_clock_step():
    """seq_skip moves only the odometer's counter; through the runner (node defaults) it is
    the event seq_skip, not a clock_reset, and no estimate leaves its bound."""
    base = by_topic(F.inject(clean(), F.Fault("none"), np.random.default_rng(0)).events,
                    "odometer")
    got = by_topic(F.inject(clean(), F.Fault("seq_skip", 2.0, 10.0),
                            np.random.default_rng(0)).events, "odometer")
    assert [(s, r) for s, _, r in got] == [(s, r) for s, _, r in base]
    assert all(g[1]["seq"] - b[1]["seq"] == (2 if b[0] >= F.EPOCH + 10.0 else 0)
               for b, g in zip(base, got))
    sc, res = run("metro_demo", 1, 30.0)
    fl = F.inject(res.events(), F.Fault("seq_skip", 1.0, 12.0), np.random.default_rng(0))
    outs, emitted, runner = F.run(fl.events, adapter(sc), 0.1)
    assert runner.events["odometer:seq_skip"] == 1, dict(runner.events)
    assert runner.events["odometer:clock_reset"] == 0, dict(runner.events)
    s = F.score(outs, emitted, fl, res.truth, 10.0, 30.0 + F.LATENCY)
    assert s["wrong_side"] == 0 and s["hazards"] == 0 and s["clear"] > 0.95, s


@pytest.mark.parametrize("jump", [0.2, -3.0])
def test_a_stamp_at_the_step_instant_means_the_old_clock(jump):
    """The slot after the old clock's last sample, predicted at the old clock's next stamp
    (the step's instant), is read there -- not 3 s later, nor 0.2 s earlier."""
    clock = F.TrainClock(steps=((41.0, jump),))
    assert clock.true_time(F.EPOCH + 41.0, near=41.2) == pytest.approx(41.0)
    assert clock.true_time(F.EPOCH + 41.1 + jump, near=41.2) == pytest.approx(41.1)


def test_a_step_is_read_from_its_first_reading_on():
    """A -0.1 s step at 618 s of a 1 Hz run whose readings at 618 and 619 s were lost: nothing
    tells of it until the reading at 620 s arrives (commands are on the reference clock), and
    the slot predicted at 619.00 is read on the clock in force until then, as a zone controller
    reading it at that time reads it -- on the stepped clock 619.00 is 619.1 s, 8 m further at
    80 m/s, which no estimator could have known."""
    events = [("odometer", float(t), {"seq": t}) for t in (616, 617, 620, 621)]
    fl = F.inject(events, F.Fault("step", -0.1, at=618.0), np.random.default_rng(0))
    assert fl.clock.seen == pytest.approx((620.0 + F.LATENCY,))
    before = fl.clock.known_at(619.55)
    assert before.steps == () and before.true_time(F.EPOCH + 619.0, 619.5) == pytest.approx(619.0)
    after = fl.clock.known_at(620.05)
    assert after.true_time(F.EPOCH + 619.9, 620.0) == pytest.approx(620.0)
    assert after.true_time(F.EPOCH + 619.0, 619.5) == pytest.approx(619.1)


def test_the_start_up_is_not_scored_as_unavailable():
    """A clean 1 Hz run: the runner starts on the third reading and publishes the first two
    slots with it (two seconds late, by design); availability counts from the third slot on,
    where every estimate is OK and on time."""
    sc, res = run("wen2017_subway", 0, 60.0)
    fl = F.inject(res.events(), F.Fault("none"), np.random.default_rng(0))
    outs, emitted, _ = F.run(fl.events, adapter(sc, "robust"), 1.0)
    first = emitted[0] - F.EPOCH
    assert first > 1.9  # the start-up: nothing before the third reading
    s = F.score(outs, emitted, fl, res.truth, 1.0, 60.0 + F.LATENCY)
    assert s["clear"] == 1.0, s


def test_the_tightness_figures_count_from_the_first_balise_and_take_alarm_as_unbounded():
    """``faults._tightness``: over the estimates published from the first balise's arrival on,
    the p95 |error|, the median and 99th percentile of the larger level (an ALARM is +inf, taken
    at an estimate, not interpolated) and ETCS's 1 m + 1 % of the true distance run since the
    last balise read."""
    from types import SimpleNamespace

    t = np.arange(30.0)
    tr_t, tr_x = t, 10.0 * t  # 10 m/s
    faulted = SimpleNamespace(events=[("balise", F.EPOCH + 10.0, {"position": 100.0},
                                       F.EPOCH + 10.0)])
    a = np.full(30, 1.0)
    a[-1] = 3.0
    ahead, behind = np.full(30, 4.0), np.full(30, 5.0)
    integ = np.zeros(30, int)
    integ[-1] = 2  # ALARM: unbounded
    got = F._tightness(t, t, a, ahead, behind, integ, faulted, tr_t, tr_x)
    assert got["pl_p50"] == 5.0 and got["al99"] == math.inf
    assert got["p95_err"] == pytest.approx(np.percentile(a[10:], 95))
    assert got["etcs_p50"] == pytest.approx(1.0 + 0.01 * 10.0 * np.median(t[10:] - 10.0))
