"""Any stamp epoch, phase and drift; one bad seq or stamp never blinds."""

import math
import os
import sys

import numpy as np
import pytest

from train_estimation.core.numerics.clocks import LATE
from train_estimation.core.online.replay import replay
from train_estimation.core.online.runner import EstimatorRunner
from train_estimation.tools.faults import wandered
from train_sim.scenario import load_scenario
from train_sim.world import simulate

sys.path.insert(0, os.path.dirname(__file__))
from clocks import adapter, errors, restamp, run, run_replay  # noqa: E402

CLOCKS = [dict(phase=0.02), dict(phase=0.049), dict(epoch=1.7e9, phase=0.013, drift=1e-4),
          dict(epoch=1.7e9, phase=0.03, drift=0.01),
          dict(epoch=1.7e9, phase=0.081, drift=-0.01, control_epoch=1.6e9),
          dict(epoch=12.345, drift=0.004, control_epoch=1.7e9)]


@pytest.mark.parametrize("kind", ["robust", "gsma"])
def test_any_epoch_phase_and_drift_accepts_clean_readings(kind):
    sc, res = run(duration=150.0)
    n_odo = sum(1 for e in res.events() if e[0] == "odometer")
    outs, r = run_replay(sc, res, kind)
    e_ref, _ = errors(outs, res)
    rmse_ref = float(np.sqrt(np.mean(e_ref ** 2)))
    for clk in CLOCKS:
        outs, r = run_replay(sc, res, kind, **clk)
        assert r.accepted["odometer"] >= 0.99 * n_odo, (clk, dict(r.rejected))
        e, t = errors(outs, res, clk.get("epoch", 0.0), clk.get("phase", 0.0),
                      clk.get("drift", 0.0))
        # one estimate per sample slot, over the whole run
        assert len(e) >= 0.99 * (res.truth["t"][-1] * sc.odometer_rate), clk
        rmse = float(np.sqrt(np.mean(e ** 2)))
        assert rmse <= 1.1 * rmse_ref + 0.01, (clk, rmse, rmse_ref)


def test_estimates_are_stamped_at_the_odometer_samples():
    sc, res = run(duration=30.0)
    clk = dict(epoch=1.7e9, phase=0.037, drift=0.002, control_epoch=5.0)
    ev = restamp(res.events(), **clk)
    outs, _ = replay(ev, adapter(sc), 0.1)
    odo = {s for k, s, _, _ in ev if k == "odometer"}
    stamps = [o.stamp for o in outs]
    assert odo <= set(stamps)
    assert np.all(np.diff(stamps) > 0)
    d = np.diff(stamps)
    assert np.all(d < 0.15 * 1.01) and np.all(d > 0.05), (d.min(), d.max())


def _tamper(ev, i, **changes):
    topic, stamp, fields = ev[i][:3]
    f = dict(fields)
    stamp = changes.pop("stamp", stamp)
    f.update(changes)
    out = list(ev)
    out[i] = (topic, stamp, f, *ev[i][3:])
    return out


@pytest.mark.parametrize("kind", ["robust", "gsma"])
@pytest.mark.parametrize("recv", [True, False])
def test_one_bad_seq_or_stamp_does_not_blind(kind, recv):
    sc, res = run(duration=60.0)
    ev = restamp(res.events())
    if not recv:
        ev = [e[:3] for e in ev]
    odo = [i for i, e in enumerate(ev) if e[0] == "odometer"]
    ctl = [i for i, e in enumerate(ev) if e[0] == "control"]
    n_odo = len(odo)
    i = odo[100]
    cases = {
        "seq_max": _tamper(ev, i, seq=2**32 - 1),
        "seq_reset": [e if k <= i or e[0] != "odometer" else
                      (e[0], e[1], dict(e[2], seq=e[2]["seq"] - 100), *e[3:])
                      for k, e in enumerate(ev)],
        "odo_future": _tamper(ev, i, stamp=ev[i][1] + 1e6),
        "ctl_future": _tamper(ev, ctl[100], stamp=ev[ctl[100]][1] + 1e6),
        "odo_future_1e9": _tamper(ev, i, stamp=ev[i][1] + 1e9),
    }
    for name, evs in cases.items():
        outs, r = replay(evs, adapter(sc, kind), 0.1)
        assert r.accepted["odometer"] >= n_odo - 2, (name, dict(r.rejected), r.last_reasons)
        assert outs[-1].stamp < 100.0, name  # never ran off to the future stamp
        if "future" in name:
            assert sum(v for k, v in r.rejected.items() if k.endswith("future_stamp")) == 1, \
                (name, dict(r.rejected))
        if name == "seq_reset":
            assert r.events["odometer:seq_reset"] == 1, dict(r.events)
        e, _ = errors(outs, res)
        assert np.abs(e).max() < 3.0, (name, np.abs(e).max())


def test_runner_refuses_garbage_at_the_door_with_reasons():
    sc, res = run(duration=5.0)
    r = EstimatorRunner(adapter(sc), 0.1)
    assert r.push("odometer", math.nan, {"seq": 1}) == "non_finite: stamp"
    assert r.push("lidar", 1.0, {}).startswith("unknown_kind")
    assert r.push("odometer", 1.0, {"seq": "x"}).startswith("invalid")
    odo = {"distance": 0.0, "speed": 0.0, "speed_variance": 0.01}
    for k in range(12):  # stamps are judged once the clock has min_judged arrivals
        assert r.push("odometer", 1.0 + 0.1 * k, dict(odo, seq=k), 1.0 + 0.1 * k) == ""
    assert r.push("odometer", 2.1, dict(odo, seq=11), 2.2) == "duplicate"
    assert r.push("odometer", 1e6, dict(odo, seq=12), 2.3).startswith("future_stamp")
    assert set(r.rejected) == {"odometer:non_finite", "lidar:unknown_kind", "odometer:invalid",
                               "odometer:duplicate", "odometer:future_stamp"}


def _stepped(ev, t_step, new_clock):
    """Odometer and balise stamped ``new_clock(t)`` from true time ``t_step`` on (a clock reset:
    reboot to a small count, or set to GPS time); ``ev`` from :func:`restamp` with epoch 1.7e9."""
    out = []
    for topic, stamp, fields, *recv in ev:
        t = stamp - 1.7e9
        if topic != "control" and t >= t_step - 1e-9:
            stamp = new_clock(t)
        out.append((topic, stamp, fields, *recv))
    return out


@pytest.mark.parametrize("kind", ["robust", "gsma"])
@pytest.mark.parametrize("recv", [True, False])
@pytest.mark.parametrize("step", ["reboot", "gps"])
def test_a_clock_reset_is_re_anchored_not_blinding(kind, recv, step):
    """A train clock that jumps and stays (reboot to 5 s, or a jump to GPS time 1e9 s ahead) is
    recognised (one ``clock_reset`` event), the filter goes on on its old timeline, the estimates
    carry the new clock's stamps, and its accuracy is that of the run without the reset."""
    sc, res = run(duration=120.0)
    t_step = 60.0
    new_clock = {"reboot": lambda t: 5.0 + (t - t_step),
                 "gps": lambda t: 1.7e9 + 1e9 + t}[step]
    ev = restamp(res.events(), epoch=1.7e9, control_epoch=1.7e9)
    ev_step = _stepped(ev, t_step, new_clock)
    if not recv:
        ev, ev_step = [e[:3] for e in ev], [e[:3] for e in ev_step]
    n_odo = sum(1 for e in ev if e[0] == "odometer")
    ref, _ = replay(ev, adapter(sc, kind), 0.1)
    outs, r = replay(ev_step, adapter(sc, kind), 0.1)
    assert r.events["odometer:clock_reset"] == 1, (dict(r.events), dict(r.rejected))
    # at most the readings of the step's detection window lost (min_judged), none blinded
    assert r.accepted["odometer"] >= n_odo - r.min_judged, (dict(r.accepted), dict(r.rejected))
    new = {e[1] for e in ev_step if e[0] == "odometer" and abs(e[1] - 1.7e9) > 1e8}
    stamps = [o.stamp for o in outs]
    assert len(new - set(stamps)) <= r.min_judged  # the new clock's sample stamps, as sent

    def to_true(s):
        return s - 1.7e9 if abs(s - 1.7e9) < 1e8 else (
            s - 5.0 + t_step if step == "reboot" else s - 2.7e9)

    t = np.array([to_true(s) for s in stamps])
    x = np.array([o.position for o in outs])
    e = x - np.interp(t, res.truth["t"], res.truth["position"])
    e_ref, _ = errors(ref, res, epoch=1.7e9)
    after = t > t_step + 2.0
    rmse = float(np.sqrt(np.mean(e[after] ** 2)))
    rmse_ref = float(np.sqrt(np.mean(e_ref[-after.sum():] ** 2)))
    assert rmse <= 1.2 * rmse_ref + 0.05, (rmse, rmse_ref)


def test_a_stalled_node_is_no_clock_reset():
    """Callbacks stalled 8 s, then a burst (all arrive at once): small stamp gaps whatever the
    arrivals, so no clock step is declared and every reading is used."""
    sc, res = run(duration=60.0)
    ev = restamp(res.events())
    ev = [(k, s, f, 38.0 if 30.0 <= r < 38.0 else r) for k, s, f, r in ev]
    n_odo = sum(1 for e in ev if e[0] == "odometer")
    outs, r = replay(ev, adapter(sc), 0.1)
    assert not r.events.get("odometer:clock_reset"), dict(r.events)
    assert r.accepted["odometer"] >= n_odo - 2, dict(r.rejected)


STALL_CLOCKS = {"one_clock": dict(),
                "train_and_reference": dict(epoch=1.7e9, phase=0.03, drift=0.004,
                                            control_epoch=1.6e9)}
STALL_CASES = [  # (scenario, kind, clocks, link latency on odometer/balise: 20 ms + Exp(50 ms))
    ("metro_demo", "robust", "one_clock", False), ("metro_demo", "kf", "one_clock", False),
    ("metro_demo", "robust", "train_and_reference", True),
    ("metro_demo", "kf", "train_and_reference", True),
    ("crh3_high_speed", "kf", "train_and_reference", True),  # other line, train, speeds
    ("wen2017_subway", "robust", "train_and_reference", True),  # (no brake delay: no KF)
]


@pytest.mark.parametrize("scenario,kind,clocks,latency", STALL_CASES)
def test_a_backlog_burst_does_not_move_the_clocks(scenario, kind, clocks, latency):
    """A recorder or node stalled 8 s / 20 s, then the backlog in one burst, replayed with
    control_clock "auto" (the offline default). The burst's offsets sweep from -stall to 0:
    they used to take over the offset windows, one stream before the other, so one clock was
    judged separate from itself and commands were mapped seconds off (0.7-6 m RMSE after the
    stall, 39 m at worst), and on truly separate clocks the burst tilted the drift fit. Now late
    items do not vote and the clocks stay put: the error is what it is without the stall."""
    clk = STALL_CLOCKS[clocks]
    sc, res = run(scenario, 1, 120.0)
    ev = restamp(res.events(), **clk)
    if latency:  # the radio's latency on the train's readings, then arrival order
        delay = 0.02 + np.random.default_rng(3).exponential(0.05, len(ev))
        ev = sorted(((k, s, f, rc + (d if k != "control" else 0.0))
                     for (k, s, f, rc), d in zip(ev, delay)), key=lambda e: e[3])
    t0 = clk.get("control_epoch", 0.0) + 30.0  # the stall starts 30 s in (reference clock)
    period = 1.0 / sc.odometer_rate
    ref, r_ref = replay(ev, adapter(sc, kind), period, control_clock="auto")
    e_ref, t_ref = errors(ref, res, clk.get("epoch", 0.0), clk.get("phase", 0.0),
                          clk.get("drift", 0.0))
    rmse_ref = float(np.sqrt(np.mean(e_ref[t_ref > 30.0] ** 2)))
    for stall in (8.0, 20.0):
        burst = [(k, s, f, t0 + stall if t0 <= rc < t0 + stall else rc) for k, s, f, rc in ev]
        outs, r = replay(burst, adapter(sc, kind), period, control_clock="auto")
        assert r.separate_clocks == r_ref.separate_clocks, stall
        assert not r.rejected, (stall, dict(r.rejected))
        e, t = errors(outs, res, clk.get("epoch", 0.0), clk.get("phase", 0.0),
                      clk.get("drift", 0.0))
        rmse = float(np.sqrt(np.mean(e[t > 30.0] ** 2)))
        assert rmse <= 1.1 * rmse_ref + 0.01, (stall, rmse, rmse_ref)  # as on aligned stamps


def test_wild_stamps_cannot_outvote_the_clock():
    """Stale copies (-500 s, all alike) mixed with good commands: even when they outnumber the
    good ones in the offset window (a run of bad luck in a long fuzz: the control clock's
    centre moved 500 s, the commands were mapped 500 s ahead and the braking filters went
    blind), they do not move the clock's centre; a clock that really steps (only far values,
    consecutively) does."""
    from train_estimation.core.numerics.clocks import StreamClock

    m = StreamClock()
    for k in range(40):
        m.add(0.001 * (k % 3))
    for k in range(60):  # two stale values for one good one
        m.add(-500.0 if k % 3 else 0.0)
    assert abs(m.value) < 0.01
    for _ in range(m.n // 2 + 1):  # the clock stepped by -500 s and stays there
        m.add(-500.0)
    assert m.value == -500.0


def test_stale_copies_do_not_blind_the_braking_filter():
    sc, res = run(duration=60.0)
    ev = restamp(res.events(), epoch=1.7e9, control_epoch=1.6e9)
    bad = []
    for k, e in enumerate(ev):
        bad.append(e)
        if e[0] == "control" and 300 <= k < 900:  # two stale copies per command for a while
            bad += [("control", e[1] - 500.0, e[2], e[3])] * 2
    outs, r = replay(bad, adapter(sc, "kf"), 0.1)
    n_odo = sum(1 for e in ev if e[0] == "odometer")
    assert r.accepted["odometer"] >= n_odo - 2, dict(r.rejected)
    e, _ = errors(outs, res, epoch=1.7e9)
    assert np.abs(e).max() < 3.0


def test_copies_of_the_first_readings_stamped_ahead_are_not_fused_at_their_stamps():
    """The fuzz mix's start of a 1 Hz run (wen2017_subway): each of the first readings and
    commands comes with copies stamped 5 s ahead (the sample's values, another stamp), arriving
    with it. The copies agree with one another as well as the genuine readings do, so the early
    hold released them with the genuine ones; a reading's copy fused 5 s after its sample left
    the robust filter 11 m behind with a sigma of 1.1 m, published OK. Copies of one message
    are one piece of evidence, and a sample fused once is not fused again at another stamp."""
    sc, res = run("wen2017_subway", seed=1, duration=40.0)
    ev = restamp(res.events(), epoch=100.0, control_epoch=100.0)
    bad = []
    for e in ev:
        bad.append(e)
        if e[3] < 103.0 and e[0] in ("odometer", "control"):
            bad += [(e[0], e[1] + 5.0, e[2], e[3])] * 2
    outs, r = replay(bad, adapter(sc, "robust"), 1 / sc.odometer_rate)
    assert r.rejected["odometer:duplicate"] >= 1, dict(r.rejected)
    err, _ = errors(outs, res, epoch=100.0)
    sd = np.sqrt([o.covariance[0] for o in outs if 100.0 <= o.stamp <= 140.0])
    sel = [o for o in outs if 100.0 <= o.stamp <= 140.0]
    # no doubt but, possibly, that the step back from the copies' clock to the readings' own
    # was a burst of wrong stamps (a rare fault: a solution beside the estimate, its
    # covariance the filter's own)
    ok = np.array([o.integrity != 2 and
                   not [w for w in o.integrity_reason.split("; ") if w and "burst" not in w]
                   for o in sel])
    bounded = np.array([o.integrity != 2 for o in sel])
    ahead = np.array([o.protection_level_ahead for o in sel])
    behind = np.array([o.protection_level_behind for o in sel])
    assert err.size == ok.size
    wrong = ok & (np.abs(err) > 1.0) & (np.abs(err) > 5 * sd)
    assert not wrong.any(), (err[wrong], sd[wrong])
    misleading = bounded & ((err < -ahead) | (err > behind))
    assert not misleading.any(), err[misleading]
    assert np.abs(err[ok]).max() < 3.0


def test_a_tie_of_offsets_in_the_first_message_does_not_set_a_clock():
    """The fuzz mix's first message of a 10 Hz run: the command comes with three identical
    copies stamped 1e9 s ahead, two copies at its own stamp with corrupted values and seven
    more at other wrong stamps. Nine offsets were in, so the early hold judged the control
    clock: two groups of three, the
    centre taken between them went 1e9 s ahead, the copies were queued as on time, and the
    runner processed up to them at once: every genuine command and reading after was out of
    order and no estimate was published for 600 s. With two groups as dense the hold waits."""
    sc, res = run("metro_demo", seed=1, duration=30.0)
    ev = restamp(res.events(), epoch=100.0, control_epoch=100.0)
    bad, first = [], True
    for e in ev:
        bad.append(e)
        if first and e[0] == "control":
            first = False
            bad += [("control", e[1] + 1e9, e[2], e[3])] * 3
            bad += [("control", e[1], {"target_acceleration": v}, e[3]) for v in (1e6, math.nan)]
            bad += [("control", e[1] + d, e[2], e[3]) for d in (1e6, 1e6, -500.0, -500.0, -5.0,
                                                                 -5.0, 5.0)]
    outs, r = replay(bad, adapter(sc, "kf"), 1 / sc.odometer_rate)
    n_odo = sum(1 for e in ev if e[0] == "odometer")
    assert r.accepted["odometer"] >= n_odo - 2, dict(r.rejected)
    err, t = errors(outs, res, epoch=100.0)
    assert t.size >= n_odo - 5 and np.abs(err).max() < 3.0


def test_an_early_latency_wander_at_1_hz_leaves_the_estimates_as_they_were():
    """wen2017_subway (1 Hz), 600 s, no sample counter, a 50 ms + Exp(50 ms) link whose latency
    rises by 0.4 s from 20 s and falls back over two minutes (a raised cosine). Before the rate
    fit has a line, arrivals cannot tell that rise from a train clock running slow; judged by
    the rate fit's error the clocks were two (4 of 4 seeds), by the error that allows a
    wandering latency (StreamClock.rate_apart) they are one. Were they judged two, the filter's
    time origin would shift by the rate believed meanwhile, but the readings' values and stamps
    are what they were, commands are mapped by the offsets as they are now, and each estimate
    is published at its reading's stamp: the errors against truth are those of the run without
    the wander (RMS within 2 cm, largest within 5 cm), nothing refused, none beyond its
    protection levels."""
    sc, res = run("wen2017_subway", seed=1, duration=600.0)

    def events(rise):
        rng = np.random.default_rng(3)
        ev = []
        for topic, t, fields, recv in restamp(res.events(), epoch=1.7e9, control_epoch=1.7e9):
            f = dict(fields)
            if topic in ("odometer", "balise"):
                if topic == "odometer":
                    f["seq"] = 0
                u = t - 1.7e9 - 20.0
                recv += 0.05 + rng.exponential(0.05) + (
                    0.5 * rise * (1.0 - math.cos(2.0 * math.pi * u / 120.0))
                    if 0.0 <= u <= 120.0 else 0.0)
            ev.append((topic, t, f, recv))
        ev.sort(key=lambda e: e[3])
        return ev

    stats = []
    for rise in (0.0, 0.4):
        outs, r = replay(events(rise), adapter(sc, "robust"), 1.0)
        assert not r.rejected, dict(r.rejected)
        assert not r.separate_clocks, (rise, r.separate_why)
        e, _ = errors(outs, res, epoch=1.7e9)
        ahead = np.array([o.protection_level_ahead for o in outs])[:len(e)]
        behind = np.array([o.protection_level_behind for o in outs])[:len(e)]
        assert np.all((e <= behind) & (-e <= ahead)), rise
        stats.append((len(outs), float(np.sqrt(np.mean(e ** 2))), float(np.max(np.abs(e)))))
    (n0, rms0, max0), (n1, rms1, max1) = stats
    assert n1 == n0 and abs(rms1 - rms0) < 0.02 and abs(max1 - max0) < 0.05, stats


@pytest.mark.parametrize("kind", ["robust", "kf"])
@pytest.mark.parametrize("clock", [{}, dict(epoch=1.7e9, phase=0.03, control_epoch=5.0)])
@pytest.mark.parametrize("wait", [1.2, 6.0])
def test_a_node_that_joins_a_running_world_takes_its_backlog_as_late(kind, clock, wait):
    """A node on simulated time that joins a run 30 s in, its first /clock ``wait`` s of
    simulated time after its inputs began to come (0.12 s of wall time at 10x: discovery),
    times what it received meanwhile at that /clock: a backlog at one instant, whose older
    stamps were only queued. They are late (more than LATE below the newest of their
    instant), so they do not vote on their clock; no command is refused, and every count
    and estimate stamp is that of the same messages pushed at their true arrivals. On one
    clock the estimates are those to the bit; with the commands on another clock they are
    mapped through the two clocks' centres, which the backlog's newest half-second still
    votes on for the first few seconds (a millisecond-level shift of the commands: within
    1 cm; 0.3 mm measured). (Voting, the backlog's offsets set the control clock's centre
    up to ``wait`` low, and the commands after it were refused as stamped ahead of it:
    10-11 of these runs' at 1.2 s, 65-66 at 6 s.)"""
    sc, res = run(duration=90.0)
    epoch = clock.get("control_epoch", 0.0)  # the arrivals' clock
    t0, first = 30.0, 30.0 + wait + epoch
    ev = [e for e in restamp(res.events(), **clock) if e[3] - epoch >= t0]
    late = [(k, s, f, max(rc, first)) for k, s, f, rc in ev]
    assert sum(rc < first for *_, rc in ev) > 10 * wait  # a backlog

    def estimates(events):
        outs, r = replay(events, adapter(sc, kind), 1 / sc.odometer_rate)
        return [(o.stamp, o.position, o.velocity, o.integrity, o.protection_level_ahead)
                for o in outs], dict(r.rejected), dict(r.accepted)

    on_time, joined = estimates(ev), estimates(late)
    assert not any(k.startswith("control") for k in on_time[1]), on_time[1]
    if not clock:
        assert joined == on_time
    assert joined[1:] == on_time[1:]
    assert [o[0] for o in joined[0]] == [o[0] for o in on_time[0]]
    assert max(abs(a[1] - b[1]) for a, b in zip(joined[0], on_time[0])) < 0.01


def _published(sc, kind: str, ev: list, now: float, backlog: bool) -> list:
    """The estimates' stamps a node publishes by ``now`` from ``ev`` (``(kind, stamp, fields,
    recv)``), each pushed at its arrival or, as a ``backlog``, all at ``now``."""
    runner = EstimatorRunner(adapter(sc, kind), 1 / sc.odometer_rate)
    outs = []
    for k, s, f, rc in ev:
        t = now if backlog else rc
        assert runner.push(k, s, f, t) == "", (k, s)
        outs += runner.advance_to(runner.ready_time(t, 0.05, 0.2, wall=t))
    outs += runner.tick(now)
    outs += runner.advance_to(runner.ready_time(now, 0.05, 0.2, wall=now))
    return [o.stamp for o in outs]


@pytest.mark.parametrize("kind", ["robust", "kf"])
def test_a_backlog_alone_judges_its_clocks(kind):
    """A paced world stands still once it is ahead of the estimates: a node that joins it
    receives a backlog at one instant and then nothing until it publishes. Only the
    backlog's newest half-second votes on each clock (the older stamps came late), and that
    is enough to judge the clocks: the node publishes, at that one arrival time, the slots
    it would have published had each message come on time, all but the newest half-second's
    at most, on the simulator's one clock and on two clocks apart. A node that published
    nothing here would hold a paced world for ever."""
    sc, res = run(duration=60.0)
    for clock in ({}, dict(epoch=1.7e9, phase=0.03, control_epoch=5.0)):
        ev = [e for e in restamp(res.events(), **clock)
              if 30.0 <= e[3] - clock.get("control_epoch", 0.0) < 32.0]
        now = 32.0 + clock.get("control_epoch", 0.0)
        got = _published(sc, kind, ev, now, backlog=True)
        on_time = _published(sc, kind, ev, now, backlog=False)
        # the same slots, but for the backlog's newest half-second at most (LATE: the votes):
        # commands that the early hold keeps until three of them agree or their clock has
        # min_judged votes (on two clocks, until both have), which the next message releases
        newest = max(s for k, s, _, _ in ev if k == "odometer")
        assert got == on_time[:len(got)], (clock, got, on_time)
        assert len(got) >= sum(t <= newest - LATE for t in on_time), (clock, got, on_time)


def _joined(sc, res, kind: str, late: float, clock: dict,
            wild: float | None = None) -> EstimatorRunner:
    """The runner of a node that joins a running world at 33.8 s (``restamp``'s ``clock``):
    what it received before its first /clock (the last 2 s) timed at that /clock, ``late`` s
    after the newest of it; what was sent meanwhile at the next /clock tick (0.1 s); from then
    on each message at the tick after its arrival. ``wild``: one more command, stamped that
    far ahead of the first command 0.5 s after the join and arriving with it (a corrupted
    copy). Replayed as a node's (``replay``)."""
    join, tick = 33.8 + clock.get("control_epoch", 0.0), 0.1  # (on the arrivals' clock)
    first = join + late
    ev = []
    for k, s, f, rc in restamp(res.events(), **clock):
        if rc < join - 2.0:
            continue
        arr = first if rc <= join else first + tick if rc <= first else \
            max(first + tick, math.ceil(round(rc / tick, 9)) * tick)
        ev.append((k, s, f, arr))
        if wild is not None and k == "control" and rc >= join + 0.5:
            ev.append(("control", s + wild, {"target_acceleration": 0.3}, arr))
            wild = None
    return replay(ev, adapter(sc, kind), 1 / sc.odometer_rate)[1]


@pytest.mark.parametrize("kind", ["robust", "gsma"])
@pytest.mark.parametrize("clock", [{}, dict(epoch=1.7e9, phase=0.03, control_epoch=5.0)])
@pytest.mark.parametrize("late", [0.0, 0.4, 0.8])
def test_a_node_that_joins_behind_a_backlog_refuses_no_command(kind, clock, late):
    """A node that joins a running world times everything it received before its first
    /clock at that /clock. When that /clock came ``late`` s after the newest of it (a node
    on a loaded machine), the commands' clock is first judged from items that waited: their
    offsets bound it from below only. The commands that then come on time lie above it; held,
    they are admitted once the commands after them move the clock to them. Refused as stamped
    ahead, a node that joined at 10x beside two busy loops lost 25 commands (the by-hand
    recipe's test); offline, a backlog 0.4 s late lost 5-7 and 0.8 s 9-15. On one clock and
    with the train's at an epoch of 1.7e9 s and the commands' on another."""
    sc, res = run(duration=60.0)
    r = _joined(sc, res, kind, late, clock)
    refused = {k: n for k, n in r.rejected.items() if k.startswith("control")}
    assert not refused, refused
    assert not r._ahead


@pytest.mark.parametrize("kind", ["robust", "gsma"])
@pytest.mark.parametrize("clock", [{}, dict(epoch=1.7e9, phase=0.03, control_epoch=5.0)])
def test_a_command_stamped_ahead_behind_a_backlog_is_still_refused(kind, clock):
    """The same join (0.8 s late) with one extra command stamped 3 s ahead of its clock
    right after it: held with the on-time ones, the commands after it do not move the clock
    to it, and once the clock no longer rests on the backlog it is refused as stamped ahead;
    the on-time commands around it are admitted."""
    sc, res = run(duration=60.0)
    r = _joined(sc, res, kind, 0.8, clock, wild=3.0)
    refused = {k: n for k, n in r.rejected.items() if k.startswith("control")}
    assert refused == {"control:future_stamp": 1}, refused


def test_a_copy_stamped_ahead_as_the_clock_is_first_judged_lifts_no_ceiling():
    """A 50 Hz odometer fuzzed at five corrupted messages per clean one: within 0.1 s the
    train clock has its settled votes, and the step watch judged the first readings while it
    had not (nothing is ahead of an unjudged clock). One copy stamped 5 s ahead came so and
    voted, and as the clock's ceiling (the largest offset, where latency is least) it hid
    every stamp below +4.95 s for the rest of the run: copies 0.5 and 5 s ahead were taken
    as on their clock, and the train was lost for 160 s (crh3_high_speed, the KF 653 m off
    under ALARM). Only an offset judged against its clock lifts the ceiling. (The campaign's
    draw of that case: the copy must come at the instant the clock is first judged; eight
    other draws never lifted it.)"""
    import zlib

    from train_estimation.tools import faults as F

    sc = load_scenario("crh3_high_speed").with_changes(odometer_rate=50.0)
    res = simulate(sc, 0, 20.0)
    fault = F.Fault("fuzz", 5.0, 0.0)
    case = zlib.crc32(f"crh3_high_speed|{fault.label}|{fault.at}".encode())
    fl = F.inject(res.events(), fault, np.random.default_rng([0, case]))
    outs, r = replay(fl.events, adapter(sc, "kf"), 1.0 / 50.0)
    clock = r._offsets["train"]
    assert clock.ceiling - clock.value < LATE, (clock.ceiling, clock.value)


def _as_node(sc, kind: str, ev: list):
    """``(outputs, runner)``: ``ev`` (``(kind, stamp, fields, recv)``, in arrival order) driven
    as a node on simulated time drives its runner: each message pushed at its arrival and the
    runner advanced to its ready time; the arrivals' resolution the largest of the last 64
    steps of the node's clock (``EstimatorNode._arrival``)."""
    runner = EstimatorRunner(adapter(sc, kind), 1 / sc.odometer_rate)
    outs, steps, last = [], [], None
    for k, s, f, rc in ev:
        if last is not None and rc != last:
            steps = (steps + [rc - last])[-64:]
            runner.arrival_resolution = max(steps)
        last = rc
        runner.push(k, s, f, rc, wall=rc)
        outs += runner.advance_to(runner.ready_time(rc, 0.05, 0.2, wall=rc))
        runner.settle()
    return outs + runner.drain(), runner


def _stalled(ev: list, kinds: tuple, start: float, first: float, end: float) -> list:
    """``ev`` with the messages of ``kinds`` that arrived in ``[start, end)`` delivered late:
    the odometer's arrived by ``first`` at ``first``, the rest at ``end``, that one instant in
    their stamps' order (a node's callback takes every queued input so). ``first == start``:
    one burst. The arrivals are on a clock of 0.1 s (a node times an input by its latest
    /clock: at 10x, every 10 ms of wall time)."""
    ev = [(k, s, f, math.ceil(round(rc / 0.1, 6)) * 0.1) for k, s, f, rc in ev]
    early = [e for e in ev if e[0] == "odometer" and "odometer" in kinds and start <= e[3] < first]
    burst = sorted((e for e in ev if e[0] in kinds and start <= e[3] < end and e not in early),
                   key=lambda e: e[1])
    out = [e for e in ev if e[3] < start or (e[3] < end and e[0] not in kinds)]
    out += [(k, s, f, first) for k, s, f, _ in early] + [(k, s, f, end) for k, s, f, _ in burst]
    return out + [e for e in ev if e[3] >= end]


@pytest.mark.parametrize("kind", ["robust", "gsma"])
def test_a_stall_at_one_instant_is_no_second_clock(kind):
    """Stalls that nodes met joining a simulation at 10x on a loaded machine (logged): a
    node whose first /clock came 2.9 s of simulated time late takes its queue at one instant
    (the world's first readings a moment before); one that stalled 4.4 s takes the readings
    at one instant and then the rest; the commands' topic delivers 32 s of them at one
    instant while the readings came on time (a reliable reader's first gap waits for the
    writer's repair). One clock (the simulator's): "auto" must not call the commands
    another clock. Decided from the first commands of a burst (their offsets seconds below
    the readings'), it did, for the whole run, and mapped the commands by the centres'
    wandering difference (8 to 28 refused, as ahead of it or out of order). A command that
    arrives later than the history (3 s) is out of order, whatever the clocks. With the
    commands on another clock the same stalls are still found to be two."""
    sc, res = run(duration=120.0)
    for clock in ({}, dict(epoch=1.7e9, phase=0.03, control_epoch=5.0)):
        ev = restamp(res.events(), **clock)
        b = clock.get("control_epoch", 0.0)
        every = ("odometer", "control", "balise")
        for stalled in (_stalled(ev, every, b + 0.4, b + 0.41, b + 3.2),
                        _stalled(ev, every, b + 5.7, b + 7.19, b + 10.13),
                        _stalled(ev, ("control",), b + 34.5, b + 34.5, b + 66.57)):
            outs, r = _as_node(sc, kind, stalled)
            assert r.separate_clocks == bool(clock), clock
            refused = {k: n for k, n in r.rejected.items() if k.startswith("control")}
            assert set(refused) <= {"control:out_of_order"}, (clock, refused)
            # (refused as out of order: stamped before the newest fused reading less the
            # history, and nothing is fused before it arrives)
            late = sum(1 for k, s, _, rc in stalled if k == "control" and rc - s > r.history)
            assert refused.get("control:out_of_order", 0) <= late, (clock, refused, late)
            assert len(outs) >= 0.99 * sc.odometer_rate * 120.0, (clock, len(outs))


def _wandering(ev: list, rng: np.random.Generator, sd: float = 0.01, tau: float = 20.0,
               jitter: float = 0.005) -> list:
    """``ev`` delivered over links whose latency wanders: each topic's own Ornstein-Uhlenbeck
    process (``sd`` s, correlation time ``tau`` s, folded to stay positive: faults.wandered)
    plus an exponential jitter of mean ``jitter`` s above a floor of 20 ms; in arrival order."""
    out, state = [], {}
    for k, s, f, rc in ev:
        x = wandered(state, k, rc, sd, rng, tau)
        out.append((k, s, f, rc + 0.02 + x + rng.exponential(jitter)))
    return sorted(out, key=lambda e: e[3])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_latencies_that_wander_are_no_second_clock(seed):
    """Each topic's latency wanders by 3 or 10 ms over about 20 s, on its own (a loaded
    host; a node behind on simulated time at 10x). One clock: "auto" must keep the commands
    on the odometer's. The rate fit splits such a wander into a score of short levels, whose
    shared slope is the wander's local one, and judged by that fit's error the two rates
    differed at 5 errors (the 10x by-hand recipe, once on a loaded CI machine: control
    taken as another clock); so did one line's under an AR(1) correction alone (two of ten
    runs at 3 ms). A train clock 3e-4 or 1e-3 fast beside a wander of 1 or 3 ms is still
    found to be another one within the 200 s."""
    sc, res = run(duration=200.0)
    for sd, drift in ((0.01, 0.0), (0.003, 0.0), (0.001, 3e-4), (0.003, 1e-3)):
        rng = np.random.default_rng([seed, int(1e4 * sd), int(1e4 * drift)])
        ev = _wandering(restamp(res.events(), drift=drift), rng, sd=sd)
        _, r = _as_node(sc, "robust", ev)
        assert r.separate_clocks == (drift > 0.0), (sd, drift, r.separate_why,
                                                    r.clock_summary())
