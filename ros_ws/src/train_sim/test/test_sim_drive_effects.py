"""Power limit, adhesion section and traction delay against physics.

A frictionless train (Davis 0) on a flat line gives closed forms: under constant power per kg p,
v dv/dt = p, so v^2 grows by exactly 2 p per second; a settled command a is delivered as a.
"""

import numpy as np
import pytest
from train_core.config import ConfigError, Section
from train_core.effects import (
    AdhesionSectionEffect,
    Effects,
    PowerLimitEffect,
    TractionDelayEffect,
    parse_effects,
)
from train_core.model import Brake, Davis, Line, TrainParams

from train_sim.scenario import load_scenario
from train_sim.world import open_loop, simulate

TAU, T = 0.4, 1.2  # s
TRAIN = TrainParams(mass=200000.0, rotary_allowance=0.1, davis=Davis(0.0, 0.0, 0.0),
                    brake=Brake(TAU, T, 1.0))
FLAT = Line("flat", 1e5)
SETTLED = T + 40 * TAU  # s after a command: the lag's transient is below e^-40 of the step


NONE = Effects()


def run(commands, effects=NONE, duration=80.0, v0=0.0, x0=0.0):
    t, a = (np.asarray(c, float) for c in commands)
    return open_loop(FLAT, TRAIN, (t, a), effects=effects, duration=duration, x0=x0, v0=v0).truth


def test_power_limit_caps_traction_at_p_over_v_and_changes_nothing_below_the_knee():
    a_cmd, p = 0.8, 8.0  # knee speed p / a = 10 m/s
    nominal = run(([0.0], [a_cmd]))
    limited = run(([0.0], [a_cmd]), Effects(power_limit=PowerLimitEffect(p)))
    t, v, acc = limited["t"], limited["velocity"], limited["acceleration"]
    # Below the knee: bit for bit the nominal motion.
    below = nominal["acceleration"] * nominal["velocity"] < p
    first_above = int(np.argmin(below))
    assert first_above > 50 and not below[first_above:].any()
    for k in ("position", "velocity", "acceleration"):
        assert np.array_equal(limited[k][:first_above], nominal[k][:first_above]), k
    # Above the knee: the delivered traction is p / v exactly ...
    above = t > t[first_above]
    assert np.allclose(acc[above], p / v[above], rtol=1e-12, atol=0)
    # ... and the motion is constant power: v^2 grows by 2 p per second (RK4 on v' = p / v).
    k0 = first_above + 1
    assert np.allclose(v[k0:] ** 2 - v[k0] ** 2, 2 * p * (t[k0:] - t[k0]), rtol=1e-9, atol=1e-9)
    # The nominal train keeps accelerating at a_cmd (the effect is not the model's doing).
    settled = nominal["t"] > SETTLED
    assert np.allclose(nominal["acceleration"][settled], a_cmd, rtol=0, atol=1e-12)
    # A command met below the knee is met in full: a = 0.2 keeps p / a = 40 m/s above v here.
    slow = run(([0.0], [0.2]), Effects(power_limit=PowerLimitEffect(p)), duration=60.0)
    assert slow["velocity"].max() < p / 0.2
    assert np.array_equal(slow["velocity"], run(([0.0], [0.2]), duration=60.0)["velocity"])


def test_power_limit_leaves_braking_alone():
    cmd = ([-40.0], [-0.6])  # braking since long before t0
    eff = Effects(power_limit=PowerLimitEffect(1.0))  # knee far below the speeds here
    a, b = run(cmd, duration=40.0, v0=30.0), run(cmd, eff, duration=40.0, v0=30.0)
    for k in ("position", "velocity", "acceleration"):
        assert np.array_equal(a[k], b[k]), k


def test_adhesion_section_changes_braking_only_inside_the_section():
    start, end, factor = 200.0, 320.0, 0.55
    cmd = ([-40.0], [-0.8])  # settled braking from 30 m/s: stops after ~560 m
    eff = Effects(adhesion_section=AdhesionSectionEffect(start, end, factor))
    nominal = run(cmd, duration=60.0, v0=30.0)
    wet = run(cmd, eff, duration=60.0, v0=30.0)
    x, acc, v = wet["position"], wet["acceleration"], wet["velocity"]
    before = nominal["position"] < start
    n0 = int(before.sum())
    for k in ("position", "velocity", "acceleration"):
        assert np.array_equal(wet[k][:n0], nominal[k][:n0]), k
    moving = v > 0.0
    inside = (x >= start) & (x < end) & moving
    outside = ~((x >= start) & (x < end)) & moving
    assert inside.sum() > 20 and (outside & (x >= end)).sum() > 20
    # The braking delivered is factor x the command inside, the command outside: at once at
    # the section's ends (a rail effect, no lag).
    assert np.allclose(acc[inside], factor * -0.8, rtol=0, atol=1e-12)
    assert np.allclose(acc[outside], -0.8, rtol=0, atol=1e-12)
    # The motion follows: v^2 falls by 2 b per metre, b = factor 0.8 inside, 0.8 after.
    for sel, b in ((inside, factor * 0.8), (outside & (x >= end), 0.8)):
        energy = v[sel] ** 2 + 2 * b * x[sel]
        assert np.ptp(energy) < 1e-6 * energy.mean()
    # Traction through the section is untouched.
    pull = ([-40.0], [0.5])
    assert np.array_equal(run(pull, eff, duration=60.0, v0=10.0, x0=150.0)["velocity"],
                          run(pull, duration=60.0, v0=10.0, x0=150.0)["velocity"])


def test_traction_delay_shifts_traction_onsets_and_leaves_braking_onsets():
    d = T + 0.7  # true traction transport delay; 0.7 s later than modelled = 7 samples
    shift = 7
    cmd = ([0.0, 5.0, 20.0, 40.0], [0.0, 0.6, 0.0, -0.5])
    nominal = run(cmd, duration=60.0)
    late = run(cmd, Effects(traction_delay=TractionDelayEffect(d)), duration=60.0)
    t, a0, a1 = nominal["t"], nominal["acceleration"], late["acceleration"]
    assert t[np.argmax(a0 > 1e-12)] == pytest.approx(5.0 + T + 0.1)
    assert t[np.argmax(a1 > 1e-12)] == pytest.approx(5.0 + d + 0.1)
    # The traction phase (onset and release) is the nominal one, 0.7 s later.
    trac = (t >= 5.0) & (t < 39.0)
    k = np.flatnonzero(trac)
    assert np.allclose(a1[k + shift], a0[k], rtol=0, atol=1e-12)
    # Braking begins at 40 + T in both: the braking chain keeps its delay.
    brake0, brake1 = t[np.argmax((t > 39) & (a0 < -1e-9))], t[np.argmax((t > 39) & (a1 < -1e-9))]
    assert brake0 == brake1 == pytest.approx(40.0 + T + 0.1)
    after = t >= 40.0
    assert np.allclose(a1[after], a0[after], rtol=0, atol=1e-12)


def test_new_effects_parse_strictly():
    eff = parse_effects(Section({"power_limit": {"p_spec": 9.0},
                                 "adhesion_section": {"start": 10, "end": 20, "factor": 0.6},
                                 "traction_delay": {"delay": 1.8}}, "effects"), 100.0)
    assert eff.power_limit.p_spec == 9.0 and eff.traction_delay.delay == 1.8
    assert eff.adhesion_section.as_tuple() == (10.0, 20.0, 0.6)
    for bad, words in ((({"power_limit": {"p_spec": 0.0}}), "p_spec"),
                       ({"adhesion_section": {"start": 20, "end": 10, "factor": 0.5}}, "end"),
                       ({"adhesion_section": {"start": 0, "end": 10}}, "factor"),
                       ({"traction_delay": {"delay": -1}}, "delay")):
        with pytest.raises(ConfigError, match=words):
            parse_effects(Section(bad, "effects"), 100.0)


@pytest.fixture(scope="module")
def demo():
    sc = load_scenario("metro_demo")
    return sc, simulate(sc, duration=200.0)


@pytest.mark.parametrize("name", ["power_limit", "adhesion_section", "traction_delay"])
def test_closed_loop_runs_with_each_effect_and_only_the_motion_changes(demo, name):
    sc, r0 = demo
    eff = {"power_limit": PowerLimitEffect(6.0),
           "adhesion_section": AdhesionSectionEffect(1500.0, 1950.0, 0.5),
           "traction_delay": TractionDelayEffect(sc.train.brake.delay + 0.5)}[name]
    r1 = simulate(sc.with_effects(Effects(**{name: eff})), duration=200.0)
    assert np.abs(r1.truth["velocity"] - r0.truth["velocity"]).max() > 0.05
    # Sensors' noise and the link's draws are untouched: same seq/received, same noise.
    for k in ("t", "seq", "received"):
        assert np.array_equal(r1.odometer[k], r0.odometer[k]), k
    noise0 = r0.odometer["speed"] - r0.truth["velocity"]
    noise1 = r1.odometer["speed"] - r1.truth["velocity"]
    assert np.allclose(noise0, noise1, rtol=0, atol=1e-9)
