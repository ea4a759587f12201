"""Each effect changes the data in its documented way and only that way (same seed, with and
without the effect)."""

import numpy as np
import pytest
from train_core.effects import (
    BrakeDelayEffect,
    BrakingRateEffect,
    BurstyLinkEffect,
    ClockDriftEffect,
    Effects,
    GradientEffect,
    MassEffect,
    OdometerScaleEffect,
    ResistanceEffect,
    WheelSlipEffect,
)

from train_sim.scenario import load_scenario
from train_sim.world import simulate

DURATION = 250.0  # s: departure from A at 10 s, stop at B (~135 s), departure towards C


@pytest.fixture(scope="module")
def base():
    sc = load_scenario("metro_demo")
    return sc, simulate(sc, duration=DURATION)


def run(sc, **effects):
    return simulate(sc.with_effects(Effects(**effects)), duration=DURATION)


def same(a: dict, b: dict, keys=None):
    keys = keys or a.keys()
    # t_recv is NaN for the messages the link lost
    return all(np.array_equal(a[k], b[k], equal_nan=a[k].dtype.kind == "f") for k in keys)


def odo_noise(res, x0):
    """Odometer minus axle-free truth: the sensor noise sequence (no scale/slip effects)."""
    o, tr = res.odometer, res.truth
    return o["distance"] - (tr["position"] - x0), o["speed"] - tr["velocity"]


def test_odometer_scale_changes_only_odometer_values(base):
    sc, r0 = base
    s = 1.02
    r1 = run(sc, odometer_scale=OdometerScaleEffect(s))
    assert same(r0.truth, r1.truth) and same(r0.balise, r1.balise)
    assert same(r0.control, r1.control)
    assert same(r0.odometer, r1.odometer, ("t", "stamp", "seq", "received", "speed_variance"))
    travelled = r0.truth["position"] - sc.start_position
    assert np.allclose(r1.odometer["distance"] - r0.odometer["distance"], (s - 1) * travelled,
                       atol=1e-9)
    assert np.allclose(r1.odometer["speed"] - r0.odometer["speed"], (s - 1) * r0.truth["velocity"],
                       atol=1e-12)
    assert r1.stops == r0.stops


def test_wheel_slip_changes_odometer_only_inside_and_carries_distance(base):
    sc, r0 = base
    t0, t1, k = 50.0, 60.0, 0.2
    r1 = run(sc, wheel_slip=WheelSlipEffect(((t0, t1),), slip_fraction=k))
    assert same(r0.truth, r1.truth) and same(r0.balise, r1.balise) and same(r0.control, r1.control)
    t, x, v = r0.truth["t"], r0.truth["position"], r0.truth["velocity"]
    inside = (t >= t0) & (t < t1)
    dv = r1.odometer["speed"] - r0.odometer["speed"]
    assert np.allclose(dv[inside], k * v[inside], atol=1e-12)
    assert np.all(dv[~inside] == 0.0)
    x_at = np.interp([t0, t1], t, x)
    extra = k * (np.clip(x, x_at[0], x_at[1]) - x_at[0])
    assert np.allclose(r1.odometer["distance"] - r0.odometer["distance"], extra, atol=1e-8)
    assert extra[-1] > 1.0  # the episode really happened while moving


def test_wheel_slip_fractions_per_episode(base):
    """``fractions``: each episode its own slip fraction (a slide in one, a slip in the other),
    in the order of the intervals."""
    sc, r0 = base
    ivs, fr = ((40.0, 45.0), (70.0, 80.0)), (-0.15, 0.08)
    r1 = run(sc, wheel_slip=WheelSlipEffect(ivs, slip_fraction=0.5, fractions=fr))
    t, v = r0.truth["t"], r0.truth["velocity"]
    dv = r1.odometer["speed"] - r0.odometer["speed"]
    for (a, b), k in zip(ivs, fr):
        inside = (t >= a) & (t < b)
        assert v[inside].min() > 1.0
        assert np.allclose(dv[inside], k * v[inside], atol=1e-12)
    out = np.ones(t.size, bool)
    for a, b in ivs:
        out &= (t < a) | (t >= b)
    assert np.all(dv[out] == 0.0)


def test_wheel_slip_of_sine_shape_builds_up_and_dies_away(base):
    """``shape: sine``: the odometer's speed reads (1 + k sin(pi (t - t0) / (t1 - t0))) v inside
    the episode (k at its middle), and nothing changes outside it."""
    sc, r0 = base
    t0, t1, k = 50.0, 60.0, 0.2
    r1 = run(sc, wheel_slip=WheelSlipEffect(((t0, t1),), slip_fraction=k, shape="sine"))
    t, v = r0.truth["t"], r0.truth["velocity"]
    inside = (t >= t0) & (t < t1)
    dv = r1.odometer["speed"] - r0.odometer["speed"]
    assert np.allclose(dv[inside], k * np.sin(np.pi * (t[inside] - t0) / (t1 - t0)) * v[inside],
                       atol=1e-12)
    assert np.all(dv[~inside] == 0.0)
    with pytest.raises(ValueError, match="shape"):
        WheelSlipEffect(((t0, t1),), shape="square")


def test_clock_drift_changes_only_train_stamps(base):
    sc, r0 = base
    d = 2e-4
    r1 = run(sc, clock_drift=ClockDriftEffect(d))
    assert same(r0.truth, r1.truth)
    for topic in ("odometer", "balise", "control"):
        a, b = getattr(r0, topic), getattr(r1, topic)
        assert same(a, b, [k for k in a if k != "stamp"])
        assert np.array_equal(a["stamp"], a["t"])
        # docs/interfaces.md: control stays on the reference clock; the sensors' stamps drift
        expect = b["t"] if topic == "control" else b["t"] * (1 + d)
        assert np.allclose(b["stamp"], expect, rtol=0, atol=1e-12)
    gt = [s for topic, s, _ in r1.events() if topic == "ground_truth"]
    assert np.array_equal(gt, r1.truth["t"])


def test_bursty_link_changes_only_which_messages_arrive(base):
    sc, r0 = base
    r1 = run(sc, bursty_link=BurstyLinkEffect(p_good_bad=0.05, p_bad_good=0.2))
    assert same(r0.truth, r1.truth) and same(r0.control, r1.control)
    for topic in ("odometer", "balise"):
        a, b = getattr(r0, topic), getattr(r1, topic)
        assert same(a, b, [k for k in a if k not in ("received", "t_recv")])
    assert not np.array_equal(r0.odometer["received"], r1.odometer["received"])
    # Bursty: the mean loss-burst length is near 1/p_bad_good = 5, not Bernoulli's 1/0.875.
    rec = r1.odometer["received"]
    lost = np.concatenate(([0], (~rec).astype(int), [0]))
    bursts = np.flatnonzero(np.diff(lost) == -1) - np.flatnonzero(np.diff(lost) == 1)
    assert bursts.mean() > 2.5


def dynamics_effect_checks(sc, r0, r1):
    """A motion effect leaves every sensor's noise, seq and link draws untouched."""
    n0, v0 = odo_noise(r0, sc.start_position)
    n1, v1 = odo_noise(r1, sc.start_position)
    assert np.allclose(n0, n1, atol=1e-9) and np.allclose(v0, v1, atol=1e-12)
    assert same(r0.odometer, r1.odometer, ("t", "stamp", "seq", "received", "speed_variance"))
    k = min(len(r0.balise["t"]), len(r1.balise["t"]))
    assert np.array_equal(r0.balise["received"][:k], r1.balise["received"][:k])
    assert np.array_equal(r0.balise["balise_id"][:k], r1.balise["balise_id"][:k])
    assert not np.array_equal(r0.truth["position"], r1.truth["position"])


def test_gradient_effect_changes_motion_only_from_the_section_on(base):
    sc, r0 = base
    g = GradientEffect(800.0, 1200.0, 10.0)
    sc1 = sc.with_effects(Effects(gradient=g))
    assert sc1.true_line.gradient_permille(1000.0) == sc.line.gradient_permille(1000.0) + 10.0
    assert sc1.true_line.gradient_permille(700.0) == sc.line.gradient_permille(700.0)
    assert sc1.true_line.gradient_permille(1300.0) == sc.line.gradient_permille(1300.0)
    assert sc1.line == sc.line  # the believed map is untouched
    r1 = simulate(sc1, duration=DURATION)
    dynamics_effect_checks(sc, r0, r1)
    before = r0.truth["position"] < g.start
    first = np.argmax(~before)
    assert same({k: v[:first] for k, v in r0.truth.items()},
                {k: v[:first] for k, v in r1.truth.items()})


def test_resistance_effect(base):
    sc, r0 = base
    r1 = run(sc, resistance=ResistanceEffect(5000.0, 200.0, 12.0))
    dynamics_effect_checks(sc, r0, r1)
    # At rest (before departure at 10 s + delay) nothing differs.
    rest = r0.truth["t"] < 10.0
    assert np.array_equal(r0.truth["position"][rest], r1.truth["position"][rest])


def test_mass_effect_scales_drive_acceleration(base):
    sc, r0 = base
    m_true = 1.2 * sc.train.mass
    r1 = run(sc, mass=MassEffect(m_true))
    dynamics_effect_checks(sc, r0, r1)
    # Drive force is made for the believed mass: a_drive = a_hat * M_believed / M_true.
    rest = r0.truth["t"] < 10.0
    assert np.allclose(r1.truth["acceleration"][rest],
                       r0.truth["acceleration"][rest] * sc.train.mass / m_true, rtol=1e-12)


def test_brake_delay_effect_delays_braking_commands_only(base):
    sc, r0 = base
    T, T1 = sc.train.brake.delay, 1.8
    r1 = run(sc, brake_delay=BrakeDelayEffect(T1))
    dynamics_effect_checks(sc, r0, r1)
    t, a0, a1 = r0.truth["t"], r0.truth["acceleration"], r1.truth["acceleration"]
    # At 10 s the ATO replaces the holding brake (-0.3) by traction. Traction acts after T in
    # both runs; the brake's release is a braking-chain change, so it comes after T1 in r1: in
    # between r1 pulls against the still applied holding brake.
    # (the holding brake applied at 0 s also acts 0.6 s later in r1; from 5 s on that lag
    # transient is below 0.3 exp(-(5 - 1.8) / 0.4) = 1e-4 m/s^2)
    same_part = (t >= 5.0) & (t <= 10.0 + T)
    assert np.allclose(a0[same_part], a1[same_part], rtol=0, atol=1.1e-4)
    window = (t > 10.0 + T + 0.05) & (t < 10.0 + T1 - 1e-9)
    diff = a0[window] - a1[window]
    assert np.all(diff > 0.0) and diff.max() > 0.1
    # Traction alone is not delayed: a command series without braking gives identical output.
    from train_core.actuator import Actuator
    x, y = Actuator(0.4, T), Actuator(0.4, T, brake_delay=T1)
    for k in range(100):
        for act in (x, y):
            act.advance(0.1 * k)
            act.command(0.1 * k, 0.5 * (k > 10))
    assert x.advance(12.0) == y.advance(12.0)


def test_braking_rate_effect_drift_and_step(base):
    sc, r0 = base
    t0 = 20.0  # drift starts after departure (the holding brake at rest is scaled by f too)
    eff = BrakingRateEffect(1.0, 0.8, "linear", t0, DURATION)
    r1 = run(sc, braking_rate=eff)
    dynamics_effect_checks(sc, r0, r1)
    t = r1.truth["t"]
    expected = np.where(t <= t0, 1.0, 1.0 - 0.2 * (t - t0) / (DURATION - t0))
    assert np.allclose(r1.truth["braking_rate"], expected, atol=1e-12)
    assert np.all(r0.truth["braking_rate"] == 1.0)
    # Traction is unaffected by f: identical motion until the first braking after departure.
    ctrl, v = r0.control["target_acceleration"], r0.truth["velocity"]
    t_brake = t[np.argmax((ctrl < 0) & (v > 0))]
    early = t <= t_brake + sc.train.brake.delay
    assert np.array_equal(r0.truth["position"][early], r1.truth["position"][early])
    step = BrakingRateEffect(1.0, 0.6, "step", t_step=100.0)
    assert step.value(99.99) == 1.0 and step.value(100.0) == 0.6
    # Weaker brakes than believed: the ATO overshoots B.
    assert r1.stops[0]["stopping_error"] > 0.5
