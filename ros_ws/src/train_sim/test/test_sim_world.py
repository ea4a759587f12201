"""World / simulate: determinism, node-equals-offline, messages, sensors, the ATO's stops."""

import math
from dataclasses import replace

import numpy as np
import pytest
from train_core.effects import BrakingRateEffect, Effects

from train_sim.scenario import load_scenario
from train_sim.world import World, simulate

SCENARIOS = ("metro_demo", "wen2017_subway", "zheng2015_braking", "crh3_high_speed")


@pytest.fixture(scope="module")
def metro():
    sc = load_scenario("metro_demo")
    return sc, simulate(sc)


def test_same_seed_same_result_other_seed_other_noise(metro):
    sc, r0 = metro
    r1 = simulate(sc)
    for topic in ("truth", "odometer", "balise", "control"):
        a, b = getattr(r0, topic), getattr(r1, topic)
        assert all(np.array_equal(a[k], b[k], equal_nan=a[k].dtype.kind == "f") for k in a)
    assert r0.events() == r1.events() and r0.stops == r1.stops
    r2 = simulate(sc, seed=sc.seed + 1)
    assert not np.array_equal(r0.odometer["speed"], r2.odometer["speed"])
    assert np.array_equal(r0.truth["position"], r2.truth["position"])  # ATO sees the truth only


def test_world_in_chunks_equals_simulate(metro):
    sc, r0 = metro
    w = World(sc)
    rng = np.random.default_rng(0)
    events, t = [], 0.0
    while t < sc.duration:
        t = min(sc.duration, t + float(rng.uniform(0.013, 3.7)))
        events += w.advance(t)
    assert events == r0.events()


def test_events_topics_fields_and_order(metro):
    sc, r = metro
    ev = r.events()
    topics = {e[0] for e in ev}
    assert topics == {"odometer", "balise", "control", "ground_truth"}
    n = len(r.truth["t"])
    assert n == round(sc.duration * sc.odometer_rate) + 1
    assert sum(e[0] == "ground_truth" for e in ev) == n == sum(e[0] == "control" for e in ev)
    assert sum(e[0] == "odometer" for e in ev) == int(r.odometer["received"].sum())
    assert sum(e[0] == "balise" for e in ev) == int(r.balise["received"].sum())
    assert r.dropped["odometer"] == n - int(r.odometer["received"].sum())
    stamps = [e[1] for e in ev]
    assert stamps == sorted(stamps)
    fields = {e[0]: set(e[2]) for e in ev}
    assert fields["odometer"] == {"seq", "distance", "speed", "speed_variance"}
    assert fields["balise"] == {"seq", "balise_id", "position", "position_variance"}
    assert fields["control"] == {"target_acceleration"}
    assert fields["ground_truth"] == {"source", "position", "velocity", "acceleration",
                                      "braking_rate", "covariance", "measurement_used",
                                      "integrity", "protection_level_ahead",
                                      "protection_level_behind"}
    gt = next(e[2] for e in ev if e[0] == "ground_truth")
    assert gt["source"] == "truth" and len(gt["covariance"]) == 16
    assert np.array_equal(r.odometer["seq"], np.arange(n))  # +1 per sample before the link
    assert np.array_equal(r.balise["seq"], np.arange(len(r.balise["t"])))
    assert np.all(np.diff(r.truth["position"]) >= 0.0) and np.all(r.truth["velocity"] >= 0.0)


def test_received_fraction_matches_link(metro):
    sc, r = metro
    P = sc.true_link.received_probability
    n = len(r.odometer["received"])
    assert abs(r.odometer["received"].mean() - P) < 4.5 * math.sqrt(P * (1 - P) / n)


def test_odometer_noise_statistics(metro):
    """speed - v ~ N(0, speed_std^2): mean within 4.5 se, variance within 4.5 sd(s^2)."""
    sc, r = metro
    e = r.odometer["speed"] - r.truth["velocity"]
    d = r.odometer["distance"] - (r.truth["position"] - sc.start_position)
    n = len(e)
    for res, sd in ((e, sc.train.odometer_speed_std), (d, sc.train.odometer_distance_std)):
        assert abs(res.mean()) < 4.5 * sd / math.sqrt(n)
        assert abs(res.var(ddof=1) - sd**2) < 4.5 * sd**2 * math.sqrt(2 / (n - 1))
    assert np.all(r.odometer["speed_variance"] == sc.train.odometer_speed_std ** 2)


def test_balise_read_at_the_reference_mark():
    sc = load_scenario("metro_demo")
    sc = sc.with_changes(train=replace(sc.train, balise_position_std=1e-9))
    r = simulate(sc, duration=300.0)
    x_at = np.interp(r.balise["t"], r.truth["t"], r.truth["position"])
    # 10 Hz truth interpolated linearly: error <= a dt^2 / 8 ~ 1 mm.
    assert np.max(np.abs(x_at - r.balise["position"])) < 5e-3
    x_end = r.truth["position"][-1]
    ahead = [b for b in sc.line.balises if sc.start_position < b.position <= x_end]
    assert list(r.balise["balise_id"]) == [b.id for b in ahead]
    assert np.all(r.balise["position_variance"] == pytest.approx(1e-18))


def test_ato_stops_accurately_with_nominal_braking(metro):
    sc, r = metro
    assert [s["station"] for s in r.stops] == [t.station for t in sc.timetable]
    assert all(abs(s["stopping_error"]) < 0.5 for s in r.stops)


@pytest.mark.parametrize("f", [0.8, 0.7])
def test_degraded_braking_overshoots_unless_the_ato_knows_it(f):
    sc = load_scenario("metro_demo").with_effects(Effects(braking_rate=BrakingRateEffect(f, f)))
    r = simulate(sc)
    assert all(s["stopping_error"] > 5.0 for s in r.stops)
    sc_b = sc.with_changes(driver=replace(sc.driver, braking_rate_belief=f))
    rb = simulate(sc_b)
    assert len(rb.stops) == 3 and all(abs(s["stopping_error"]) < 0.5 for s in rb.stops)
    w = World(sc)
    w.set_braking_rate_belief(f)  # the hook a benchmark uses to feed an estimate
    w.advance(sc.duration)
    assert all(abs(s["stopping_error"]) < 0.5 for s in w.result().stops)


def test_movement_authority_and_emergency_brake():
    sc = load_scenario("metro_demo")
    w = World(sc)
    w.set_movement_authority(1500.0, 30.0, False)
    w.advance(200.0)
    assert w.state.v == 0.0 and 1500.0 - sc.driver.ma_margin - 1.0 < w.state.x <= 1500.0
    assert w.result().stops == []  # an authority stop is not a station stop
    w.set_movement_authority(1e9, 30.0, False)
    w.advance(300.0)
    assert [s["station"] for s in w.result().stops] == ["B"]
    # Emergency brake: counted once per rising edge; the train stops and stays.
    w = World(sc)
    w.advance(60.0)
    assert w.state.v > 10.0
    w.set_movement_authority(1e9, 30.0, True)
    w.set_movement_authority(1e9, 30.0, True)
    w.advance(100.0)
    assert w.state.v == 0.0 and w.result().emergency_brakes == 1
    ctrl = w.result().control
    assert ctrl["target_acceleration"][-1] == -sc.train.performance.emergency_brake


@pytest.mark.parametrize("name", SCENARIOS)
def test_shipped_scenarios_run(name):
    sc = load_scenario(name)
    r = simulate(sc)
    assert r.truth["t"][-1] == pytest.approx(sc.duration)
    assert np.all(np.isfinite(r.truth["position"]))
    if sc.driver.mode == "ato":
        assert len(r.stops) == len(sc.timetable)
        assert all(abs(s["stopping_error"]) < 0.5 for s in r.stops)


def test_zheng_truth_follows_eq_23():
    sc = load_scenario("zheng2015_braking")
    r = simulate(sc)
    t = r.truth["t"]
    assert np.allclose(r.truth["braking_rate"], 1.0 - 0.005 * t, atol=1e-12)
    assert r.truth["velocity"][0] == 20.0 and r.truth["acceleration"][0] == -1.0
