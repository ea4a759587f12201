"""The open-loop entry point, the link's latency/outages and the train clock's epoch."""

import numpy as np
import pytest
from train_core.effects import BrakeDelayEffect, Effects, MassEffect
from train_core.link import LinkParams

from train_sim.scenario import load_scenario
from train_sim.world import World, open_loop, simulate


@pytest.fixture(scope="module")
def closed():
    sc = load_scenario("metro_demo")
    return sc, simulate(sc, duration=200.0)


@pytest.mark.parametrize("effects", [Effects(), Effects(mass=MassEffect(300000.0),
                                                         brake_delay=BrakeDelayEffect(1.5))])
def test_open_loop_replays_the_closed_loop_exactly(closed, effects):
    """The ATO's recorded commands, replayed open loop, give the closed loop's motion."""
    sc, _ = closed
    sc = sc.with_effects(effects)
    ref = simulate(sc, duration=200.0)
    c = ref.control
    res = open_loop(sc.line, sc.train, (c["t"], c["target_acceleration"]), effects=effects,
                    duration=200.0, x0=sc.start_position, v0=sc.start_speed)
    for k in ("t", "position", "velocity", "acceleration"):
        assert np.allclose(res.truth[k], ref.truth[k], rtol=0, atol=1e-9), k


def test_open_loop_from_the_middle(closed):
    """Started at t0 from the true state, with the commands before t0 only filling the delay
    line and the lag, the replay continues the closed loop (up to the lag's warm-up)."""
    sc, ref = closed
    c, tr = ref.control, ref.truth
    t0 = 60.0
    k0 = int(np.flatnonzero(np.isclose(tr["t"], t0))[0])
    res = open_loop(sc.line, sc.train, (c["t"], c["target_acceleration"]), t0=t0,
                    duration=60.0, x0=tr["position"][k0], v0=tr["velocity"][k0])
    sel = (tr["t"] >= t0) & (tr["t"] <= t0 + 60.0 + 1e-9)
    assert np.allclose(res.truth["t"], tr["t"][sel], atol=1e-9)
    assert np.max(np.abs(res.truth["velocity"] - tr["velocity"][sel])) < 1e-6
    assert np.max(np.abs(res.truth["position"] - tr["position"][sel])) < 1e-5


def test_latency_jitter_reorders_arrivals_and_keeps_losses(closed):
    sc, r0 = closed
    link = LinkParams(model=sc.link.model, p=sc.link.p, r=sc.link.r, latency=0.04, jitter=0.15)
    r1 = simulate(sc.with_changes(link=link), duration=200.0)
    o0, o1 = r0.odometer, r1.odometer
    assert np.array_equal(o0["received"], o1["received"])  # latency draws do not shift losses
    ok = o1["received"]
    delay = o1["t_recv"][ok] - o1["t"][ok]
    assert delay.min() >= 0.04 and abs(delay.mean() - 0.19) < 0.02
    arr = [s for tr, topic, s, _ in r1.received_events() if topic == "odometer"]
    assert np.any(np.diff(arr) < 0), "a jitter of 0.15 s at 10 Hz must reorder some samples"
    # the World delivers by arrival time, whatever the chunks it is advanced in
    w = World(sc.with_changes(link=link))
    got = []
    for t in np.arange(0.0, 200.0, 0.73):
        w.advance(t)
        got += [s for topic, s, _ in w.deliver(t) if topic == "odometer"]
    assert got == arr[:len(got)] and len(got) > 0.95 * len(arr)


def test_outage_and_epoch(closed):
    sc, r0 = closed
    link = LinkParams(model=sc.link.model, p=sc.link.p, r=sc.link.r, outages=((50.0, 110.0),))
    r1 = simulate(sc.with_changes(link=link, stamp_epoch=1.7e9), duration=200.0)
    o0, o1 = r0.odometer, r1.odometer
    inside = (o1["t"] >= 50.0) & (o1["t"] < 110.0)
    assert not o1["received"][inside].any()
    assert np.array_equal(o0["received"][~inside], o1["received"][~inside])
    assert np.allclose(o1["stamp"], 1.7e9 + o1["t"], rtol=0, atol=1e-6)
    assert np.array_equal(r1.control["stamp"], r1.control["t"])  # reference clock


def test_core_replay_equals_the_world(closed):
    """train_core.motion.replay (physics only, what diagnose predicts with) gives the World's
    motion for the same commands."""
    from train_core.motion import replay

    sc, ref = closed
    c, tr = ref.control, ref.truth
    t0 = 60.0
    k0 = int(np.flatnonzero(np.isclose(tr["t"], t0))[0])
    sel = (tr["t"] >= t0) & (tr["t"] <= t0 + 60.0 + 1e-9)
    x, v = replay(sc.line, sc.train, c["t"], c["target_acceleration"], t0, tr["t"][sel],
                  tr["position"][k0], tr["velocity"][k0])
    assert np.max(np.abs(v - tr["velocity"][sel])) < 1e-6
    assert np.max(np.abs(x - tr["position"][sel])) < 1e-5


def test_bursty_link_keeps_latency_and_outages():
    from train_core.effects import BurstyLinkEffect, true_link

    base = LinkParams(latency=0.05, jitter=0.01, outages=((10.0, 20.0),))
    tl = true_link(base, Effects(bursty_link=BurstyLinkEffect(0.02, 0.3)))
    assert tl.model == "gilbert_elliott" and (tl.p_good_bad, tl.p_bad_good) == (0.02, 0.3)
    assert (tl.latency, tl.jitter, tl.outages) == (base.latency, base.jitter, base.outages)


def test_driver_open_loop_mode_issues_the_profile(closed):
    """The driver's open_loop mode (a_Tar profile, looked up by bisection) issues the command
    in force at every cycle: on the closed loop's own 2000-command profile, the very same
    commands, and the same motion."""
    import dataclasses

    sc, ref = closed
    c = ref.control
    prof = tuple(zip(c["t"].tolist(), c["target_acceleration"].tolist()))
    sc_ol = dataclasses.replace(sc, driver=dataclasses.replace(sc.driver, mode="open_loop",
                                                               profile=prof))
    res = simulate(sc_ol, duration=200.0)
    assert np.array_equal(res.control["target_acceleration"], c["target_acceleration"])
    assert np.allclose(res.truth["position"], ref.truth["position"], rtol=0, atol=1e-9)
