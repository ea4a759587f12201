"""Physics of the world against closed forms: resistance, braking, gradient, actuator, rest."""

import math

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.optimize import brentq
from train_core.actuator import Actuator, effective_input, step_response
from train_core.dynamics import Dynamics, MotionState
from train_core.effects import Effects
from train_core.model import Brake, Davis, G, GradientSection, Line, TrainParams

from train_sim.scenario import load_scenario
from train_sim.world import simulate

DAVIS = Davis(3481.8036, 144.9154, 8.5212)  # N, Wen Table I


def make_train(davis=DAVIS, mass=288000.0, lam=0.16, tau=0.4, delay=1.2):
    return TrainParams(mass=mass, rotary_allowance=lam, davis=davis,
                       brake=Brake(time_constant=tau, delay=delay))


def run(dyn, state, act, t_end, h=0.01, f=1.0):
    """Integrate with the same stepping the world uses (split at actuator input changes)."""
    t = 0.0
    while t < t_end - 1e-12:
        t_next = min(t_end, act.next_switch())
        n = max(1, math.ceil((t_next - t) / h - 1e-9))
        hh = (t_next - t) / n
        for _ in range(n):
            ue = effective_input(act.u, f)
            a0, am, ae = act.segment(hh, f)
            dyn.step(state, hh, a0, am, ae, ue, act.tau)
        t = t_next
        act.t = t
        act._activate()
    return state


def test_coasting_follows_closed_form_of_davis_resistance():
    """Coasting on level track: m_eff dv/dt = -(a + b v + c v^2), solved exactly.

    With D = 4ac - b^2 > 0:  v(t) = (sqrt(D) tan(theta0 - sqrt(D) t / (2 m_eff)) - b) / (2c),
    theta0 = atan((2 c v0 + b) / sqrt(D)).
    """
    train = make_train()
    m = train.effective_mass
    a, b, c = DAVIS.a, DAVIS.b, DAVIS.c
    D = 4 * a * c - b * b
    assert D > 0
    v0 = 20.0
    th0 = math.atan((2 * c * v0 + b) / math.sqrt(D))

    def v_exact(t):
        return (math.sqrt(D) * math.tan(th0 - math.sqrt(D) * t / (2 * m)) - b) / (2 * c)

    dyn = Dynamics(train, Line("flat", 1e5))
    # Initial deceleration = resistance / effective mass.
    assert dyn.accel(0.0, v0, 0.0) == pytest.approx(-DAVIS.force(v0) / m, rel=1e-12)
    st = MotionState(0.0, v0, False)
    act = Actuator(0.4, 1.2)
    run(dyn, st, act, 60.0)
    assert st.v == pytest.approx(v_exact(60.0), abs=1e-9)
    x_exact = quad(v_exact, 0.0, 60.0, epsabs=1e-12)[0]
    assert st.x == pytest.approx(x_exact, abs=1e-7)


def test_constant_braking_stops_in_v0_squared_over_2a_and_stays():
    """No resistance, actuator already at a_hat = -a (delay line full): x_stop = v0^2 / (2a)."""
    train = make_train(davis=Davis(0.0, 0.0, 0.0))
    dyn = Dynamics(train, Line("flat", 1e5))
    for v0, a in [(20.0, 1.0), (13.7, 0.83), (3.0, 1.1)]:
        st = MotionState(0.0, v0, False)
        act = Actuator(0.4, 1.2, a0=-a, u0=-a)
        run(dyn, st, act, v0 / a + 5.0)
        assert st.stopped and st.v == 0.0
        assert st.x == pytest.approx(v0 * v0 / (2 * a), abs=1e-9)
        x_stop = st.x
        run(dyn, st, act, 30.0)  # held: no creeping, no roll-back
        assert st.x == x_stop and st.v == 0.0


def test_braking_with_delay_and_lag_matches_closed_form_in_world():
    """World run, a_Tar = -1 from t = 0 with exact delay T and lag tau, no resistance.

    a_hat = -(1 - e^{-(t-T)/tau}) for t >= T, so with s = t - T:
    v = v0 - (s - tau (1 - e^{-s/tau})),
    x = v0 t - (s^2/2 - tau s + tau^2 (1 - e^{-s/tau})).
    """
    sc = load_scenario("zheng2015_braking")
    sc = sc.with_changes(start_acceleration=0.0, start_target_acceleration=0.0,
                         effects=Effects(), odometer_rate=10.0)
    T, tau, v0 = sc.train.brake.delay, sc.train.brake.time_constant, sc.start_speed
    res = simulate(sc, duration=40.0)

    def v_exact(t):
        s = max(t - T, 0.0)
        return v0 - (s - tau * (1 - math.exp(-s / tau)))

    def x_exact(t):
        s = max(t - T, 0.0)
        return v0 * t - (s * s / 2 - tau * s + tau * tau * (1 - math.exp(-s / tau)))

    t_stop = brentq(v_exact, T, 60.0, xtol=1e-14)
    tr = res.truth
    assert tr["position"][-1] == pytest.approx(x_exact(t_stop), abs=1e-8)
    moving = tr["t"] < t_stop
    assert np.allclose(tr["velocity"][moving], [v_exact(t) for t in tr["t"][moving]], atol=1e-9)
    assert np.allclose(tr["acceleration"], step_response(tr["t"], -1.0, tau, T), atol=1e-12)
    # The delay is exact (no Pade undershoot): nothing happens before T.
    assert np.all(tr["acceleration"][tr["t"] < T] == 0.0)


@pytest.mark.parametrize("permille", [12.0, -9.0])
def test_gradient_sign_and_size(permille):
    """Inside a section dv/dt = -g sin(atan(permille/1000)) / (1 + lambda): uphill decelerates."""
    train = make_train(davis=Davis(0.0, 0.0, 0.0))
    line = Line("hill", 1e4, gradients=(GradientSection(100.0, 5000.0, permille),))
    dyn = Dynamics(train, line)
    p = permille / 1000
    expected = -G * p / math.sqrt(1 + p * p) / (1 + train.rotary_allowance)
    assert expected * permille < 0  # uphill (positive) slows the train down
    st = MotionState(200.0, 15.0, False)
    run(dyn, st, Actuator(0.4, 1.2), 10.0)
    assert (st.v - 15.0) / 10.0 == pytest.approx(expected, rel=1e-12)
    assert st.x == pytest.approx(200.0 + 15.0 * 10.0 + 0.5 * expected * 100.0, abs=1e-9)
    # Outside the section nothing acts.
    st = MotionState(5100.0, 15.0, False)
    run(dyn, st, Actuator(0.4, 1.2), 10.0)
    assert st.v == 15.0


def test_actuator_step_response_lag_and_delay():
    tau, T = 0.4, 1.2
    for amp, f in [(-1.0, 1.0), (-0.8, 0.6), (0.5, 0.6)]:
        act = Actuator(tau, T)
        act.command(0.0, amp)
        ts = np.arange(0.0, 6.0, 0.05)
        out = [act.advance(t, f) for t in ts]
        exact = step_response(ts, amp, tau, T, f)
        assert np.allclose(out, exact, atol=1e-13)
        assert np.all(np.array(out)[ts < T] == 0.0)
        # One time constant after the delay: 1 - 1/e of the final value.
        ue = amp * (f if amp < 0 else 1.0)  # f scales braking only
        assert act.advance(T + tau + 6.0, f) == pytest.approx(ue, abs=1e-6)
        a = Actuator(tau, T)
        a.command(0.0, amp)
        assert a.advance(T + tau, f) == pytest.approx(ue * (1 - math.exp(-1)), rel=1e-12)


def test_coasting_to_rest_uphill_does_not_roll_back():
    """Documented choice: a train at rest never moves backwards (held), even without braking."""
    train = make_train()
    line = Line("hill", 1e4, gradients=(GradientSection(0.0, 1e4, 20.0),))
    dyn = Dynamics(train, line)
    st = MotionState(100.0, 2.0, False)
    run(dyn, st, Actuator(0.4, 1.2), 20.0)
    assert st.stopped and st.v == 0.0
    x = st.x
    run(dyn, st, Actuator(0.4, 1.2), 20.0)
    assert st.x == x
    # It starts again only when traction beats gradient + static resistance.
    grade = 9.80665 * 0.02 / math.sqrt(1 + 0.02**2) / (1 + train.rotary_allowance)
    static = DAVIS.a / train.effective_mass  # static resistance per effective mass
    assert not dyn.can_start(x, grade + static - 1e-6)
    assert dyn.can_start(x, grade + static + 1e-6)


@pytest.mark.parametrize("brake_delay", [None, 1.5])
def test_grid_output_is_the_event_actuator_on_a_common_grid(brake_delay):
    """The two implementations of Zheng eq. (1) (train_core.actuator docstring): with commands
    and delays on the 0.1 s grid, traction + f * braking of the grid form is the event-based
    output at every grid point."""
    from train_core.actuator import grid_output

    rng = np.random.default_rng(3)
    ctrl_t = 0.1 * np.arange(1, 600, 7)
    ctrl_a = rng.uniform(-1.2, 1.0, ctrl_t.size)
    tg = 0.1 * np.arange(700)
    f = 0.8
    tr, br = grid_output(tg, ctrl_t, ctrl_a, 0.4, 1.2, brake_delay)
    act = Actuator(0.4, 1.2, brake_delay=brake_delay)
    got = []
    i = 0
    for t in tg:
        while i < ctrl_t.size and ctrl_t[i] <= t + 1e-9:
            act.advance(ctrl_t[i], f)
            act.command(ctrl_t[i], ctrl_a[i])
            i += 1
        got.append(act.advance(t, f))
    np.testing.assert_allclose(tr + f * br, got, rtol=0, atol=1e-12)
