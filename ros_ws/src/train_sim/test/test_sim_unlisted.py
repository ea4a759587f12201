"""The test effects outside the causes list (train_sim.unlisted) against closed forms, on a
frictionless train on a flat line (test_sim_drive_effects.py's set-up)."""

import numpy as np
from train_core.effects import Effects
from train_core.model import Brake, Davis, Line, TrainParams

from train_sim.scenario import load_scenario
from train_sim.unlisted import (
    BrakeFade,
    BrakePowerLimit,
    ClockSlew,
    ClockStep,
    CoastDrag,
    HuntingDrag,
    LoadChange,
    OdometerBias,
    OdometerSpeedScale,
    ResistanceWarmup,
    TractionGain,
    TractionTrip,
    TunnelDrag,
    Unlisted,
    Wind,
)
from train_sim.world import open_loop, simulate

TAU, T = 0.4, 1.2  # s
TRAIN = TrainParams(mass=200000.0, rotary_allowance=0.1, davis=Davis(0.0, 0.0, 0.0),
                    brake=Brake(TAU, T, 1.0))
M_EFF = TRAIN.effective_mass
FLAT = Line("flat", 1e5)
SETTLED = T + 40 * TAU  # s


def run(commands, unlisted=None, duration=60.0, v0=0.0, x0=0.0):
    t, a = (np.asarray(c, float) for c in commands)
    return open_loop(FLAT, TRAIN, (t, a), effects=Effects(), duration=duration, x0=x0, v0=v0,
                     unlisted=unlisted).truth


def test_traction_gain_scales_traction_only():
    u = Unlisted(traction_gain=TractionGain(0.75))
    pull = run(([0.0], [0.8]), u)
    settled = pull["t"] > SETTLED
    assert np.allclose(pull["acceleration"][settled], 0.75 * 0.8, rtol=0, atol=1e-12)
    brake = ([-40.0], [-0.6])
    for k in ("position", "velocity", "acceleration"):
        assert np.array_equal(run(brake, u, v0=25.0)[k], run(brake, v0=25.0)[k]), k


def test_brake_fade_below_v_fade_only():
    u = Unlisted(brake_fade=BrakeFade(8.0, 0.6))
    tr = run(([-40.0], [-0.8]), u, v0=25.0)
    v, acc = tr["velocity"], tr["acceleration"]
    fast, slow = v >= 8.0, (v < 8.0) & (v > 0.0)
    assert fast.sum() > 50 and slow.sum() > 50
    assert np.allclose(acc[fast], -0.8, rtol=0, atol=1e-12)
    assert np.allclose(acc[slow], -0.48, rtol=0, atol=1e-12)


def test_tunnel_drag_in_the_tunnel_only():
    c = 30.0  # N/(m/s)^2
    u = Unlisted(tunnel_drag=TunnelDrag(200.0, 500.0, c))
    tr = run(([-40.0], [0.0]), u, v0=20.0)  # coasting, frictionless
    t, x, v = tr["t"], tr["position"], tr["velocity"]
    before, inside, after = x < 200.0, (x >= 200.0) & (x < 500.0), x >= 500.0
    assert inside.sum() > 50 and after.sum() > 50
    assert np.all(v[before] == 20.0)
    # v' = -c v^2 / M_eff: 1 / v grows linearly at c / M_eff
    k = np.flatnonzero(inside)[1:]
    slope = np.diff(1.0 / v[k]) / np.diff(t[k])
    assert np.allclose(slope, c / M_EFF, rtol=1e-6)
    assert np.ptp(v[after]) < 1e-12 and v[after][0] < 20.0


def test_wind_in_its_time_window_only():
    f = 8000.0  # N
    u = Unlisted(wind=Wind(10.0, 20.0, f))
    tr = run(([-40.0], [0.0]), u, v0=15.0)
    t, v = tr["t"], tr["velocity"]
    assert np.all(v[t <= 10.0] == 15.0)
    inside = (t > 10.05) & (t < 19.95)
    slope = np.diff(v[inside]) / np.diff(t[inside])
    assert np.allclose(slope, -f / M_EFF, rtol=1e-9)
    after = t >= 20.0
    assert np.ptp(v[after]) < 1e-12
    # exactly 10 s of it: the 10 ms integration steps start and end on the window's edges
    assert abs(v[after][0] - (15.0 - 10.0 * f / M_EFF)) < 1e-9


def test_load_change_scales_traction_from_its_time_on():
    u = Unlisted(load_change=LoadChange(30.0, 0.8))
    tr = run(([0.0], [0.5]), u)
    t, acc = tr["t"], tr["acceleration"]
    before, after = (t > SETTLED) & (t < 29.95), t > 30.05
    assert before.sum() > 50 and after.sum() > 50
    assert np.allclose(acc[before], 0.5, rtol=0, atol=1e-12)
    assert np.allclose(acc[after], 0.4, rtol=0, atol=1e-12)
    brake = ([-40.0], [-0.6])  # a load-weighed brake: braking untouched
    for k in ("position", "velocity", "acceleration"):
        assert np.array_equal(run(brake, u, v0=25.0)[k], run(brake, v0=25.0)[k]), k


def test_coast_drag_while_coasting_only():
    u = Unlisted(coast_drag=CoastDrag(0.05))
    coast = run(([-40.0], [0.0]), u, v0=10.0)
    v, acc = coast["velocity"], coast["acceleration"]
    moving = v > 0.6
    assert moving.sum() > 50
    assert np.allclose(acc[moving], -0.05, rtol=0, atol=1e-12)
    for cmd in (([0.0], [0.5]), ([-40.0], [-0.6])):  # traction or braking delivered: untouched
        ref, got = run(cmd, v0=25.0), run(cmd, u, v0=25.0)
        settled = (ref["t"] > SETTLED) & (ref["velocity"] > 0.6)
        assert settled.sum() > 50
        assert np.array_equal(got["acceleration"][settled], ref["acceleration"][settled])


def test_hunting_drag_above_its_critical_speed_only():
    f = 30000.0  # N: 0.14 m/s^2, from 25 to 20 m/s in 37 s
    u = Unlisted(hunting_drag=HuntingDrag(20.0, f))
    tr = run(([-40.0], [0.0]), u, v0=25.0)  # coasting, frictionless: slows to 20 m/s, then holds
    t, v = tr["t"], tr["velocity"]
    fast = np.flatnonzero(v > 20.05)
    assert fast.size > 50
    slope = np.diff(v[fast]) / np.diff(t[fast])
    assert np.allclose(slope[:-1], -f / M_EFF, rtol=1e-6)
    assert v.min() > 19.9 and np.ptp(v[-50:]) < 1e-9


def test_resistance_warmup_decays_from_its_start():
    f, tau = 20000.0, 15.0  # N, s
    u = Unlisted(resistance_warmup=ResistanceWarmup(5.0, tau, f))
    tr = run(([-40.0], [0.0]), u, v0=20.0)  # coasting, frictionless
    t, v = tr["t"], tr["velocity"]
    assert np.all(v[t <= 5.0] == 20.0)
    # v(t) = 20 - f tau / M_eff (1 - exp(-(t - 5) / tau)) after its start
    after = t > 5.0
    want = 20.0 - f * tau / M_EFF * (1.0 - np.exp(-(t[after] - 5.0) / tau))
    assert np.allclose(v[after], want, rtol=0, atol=1e-6)


def test_brake_power_limit_above_its_knee_only():
    p = 10.0  # m^2/s^3: the braking -0.8 m/s^2 is limited above 12.5 m/s
    u = Unlisted(brake_power_limit=BrakePowerLimit(p))
    tr = run(([-40.0], [-0.8]), u, v0=25.0)
    v, acc = tr["velocity"], tr["acceleration"]
    fast, slow = v > 12.6, (v < 12.4) & (v > 0.0)
    assert fast.sum() > 50 and slow.sum() > 50
    assert np.allclose(acc[fast], -p / v[fast], rtol=1e-3)
    assert np.allclose(acc[slow], -0.8, rtol=0, atol=1e-12)


def test_traction_trip_in_its_time_window_only():
    u = Unlisted(traction_trip=TractionTrip(30.0, 45.0, 0.5))
    tr = run(([0.0], [0.5]), u)
    t, acc = tr["t"], tr["acceleration"]
    before, inside, after = (t > SETTLED) & (t < 29.95), (t > 30.05) & (t < 44.95), t > 45.05
    assert before.sum() > 50 and inside.sum() > 50 and after.sum() > 50
    assert np.allclose(acc[before], 0.5, rtol=0, atol=1e-12)
    assert np.allclose(acc[inside], 0.25, rtol=0, atol=1e-12)
    assert np.allclose(acc[after], 0.5, rtol=0, atol=1e-12)


def test_odometer_bias_and_clock_step_change_the_readings_only():
    sc = load_scenario("metro_demo")
    r0 = simulate(sc, duration=150.0)
    u = Unlisted(odometer_bias=OdometerBias(0.07), clock_step=ClockStep(60.0, -2.5))
    r1 = simulate(sc.with_changes(unlisted=u), duration=150.0)
    for k in ("position", "velocity"):
        assert np.array_equal(r1.truth[k], r0.truth[k]), k
    o0, o1 = r0.odometer, r1.odometer
    moving = r0.truth["velocity"] > 0.5
    assert moving.sum() > 500 and (~moving).sum() > 50
    dv = o1["speed"] - o0["speed"]
    assert np.allclose(dv[moving], 0.07, rtol=0, atol=1e-9)
    assert np.allclose(dv[~moving], 0.0, rtol=0, atol=1e-9)
    # the distance counts the bias over the time moving: 0.07 m/s x (time moving so far)
    dd = o1["distance"] - o0["distance"]
    assert abs(dd[-1] - 0.07 * 0.1 * moving[:-1].sum()) < 0.07 * 1.0, dd[-1]
    for r1_, r0_ in ((o1, o0), (r1.balise, r0.balise)):
        step = np.where(r0_["t"] >= 60.0, -2.5, 0.0)
        assert np.allclose(r1_["stamp"] - r0_["stamp"], step, rtol=0, atol=1e-9)


def test_odometer_speed_scale_and_clock_slew_change_the_readings_only():
    sc = load_scenario("metro_demo")
    r0 = simulate(sc, duration=150.0)
    u = Unlisted(odometer_speed_scale=OdometerSpeedScale(0.02, 20.0),
                 clock_slew=ClockSlew(60.0, 1e-3))
    r1 = simulate(sc.with_changes(unlisted=u), duration=150.0)
    assert np.array_equal(r1.truth["velocity"], r0.truth["velocity"])
    v = r0.truth["velocity"]
    assert v.max() > 10.0
    assert np.allclose(r1.odometer["speed"] - r0.odometer["speed"], 0.02 * v * v / 20.0,
                       rtol=0, atol=1e-9)
    for r1_, r0_ in ((r1.odometer, r0.odometer), (r1.balise, r0.balise)):
        slew = np.where(r0_["t"] >= 60.0, 1e-3 * (r0_["t"] - 60.0), 0.0)
        assert np.allclose(r1_["stamp"] - r0_["stamp"], slew, rtol=0, atol=1e-6)


def test_closed_loop_with_all_four_and_sensors_untouched():
    sc = load_scenario("metro_demo")
    r0 = simulate(sc, duration=150.0)
    u = Unlisted(TunnelDrag(300.0, 900.0, 20.0), BrakeFade(5.0, 0.7), TractionGain(0.8),
                 Wind(30.0, 60.0, 5000.0))
    r1 = simulate(sc.with_changes(unlisted=u), duration=150.0)
    assert np.abs(r1.truth["velocity"] - r0.truth["velocity"]).max() > 0.1
    for k in ("t", "seq", "received"):
        assert np.array_equal(r1.odometer[k], r0.odometer[k]), k
    assert np.allclose(r1.odometer["speed"] - r1.truth["velocity"],
                       r0.odometer["speed"] - r0.truth["velocity"], rtol=0, atol=1e-9)
