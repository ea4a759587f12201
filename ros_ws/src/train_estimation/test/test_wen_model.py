"""Discretisation helpers and the Wen et al. (2017) discrete model against closed forms."""

import math

import numpy as np
import pytest
from train_core.model import Brake, Davis, GradientSection, Line, TrainParams

from train_estimation.core.numerics.discretize import van_loan, zoh
from train_estimation.core.robust.wen_model import Actuator, WenModel

TRAIN = TrainParams(mass=288e3, rotary_allowance=0.16, davis=Davis(3481.8036, 144.9154, 8.5212),
                    brake=Brake(0.4, 1.2))
LINE = Line(name="t", length=3000.0, gradients=(GradientSection(0.0, 1706.0, -3.0),
                                                GradientSection(1706.0, 2372.0, 3.0)))


@pytest.mark.parametrize("dt", [0.0, 0.1, 1.0, 2.5])
def test_zoh_double_integrator_closed_form(dt):
    Ad, Bd = zoh([[0, 1], [0, 0]], [0, 2.0], dt)
    np.testing.assert_allclose(Ad, [[1, dt], [0, 1]], atol=1e-14)
    np.testing.assert_allclose(Bd, [dt**2, 2 * dt], atol=1e-14)  # 2 * (dt^2/2, dt)


def test_zoh_and_van_loan_scalar_closed_form():
    a, b, s, dt = -0.7, 1.3, 0.4, 0.9
    Ad, Bd = zoh([[a]], [[b]], dt)
    assert Ad[0, 0] == pytest.approx(math.exp(a * dt), rel=1e-13)
    assert Bd[0, 0] == pytest.approx(b * (math.exp(a * dt) - 1) / a, rel=1e-13)
    Qd = van_loan([[a]], [[s]], dt)
    assert Qd[0, 0] == pytest.approx(s * (math.exp(2 * a * dt) - 1) / (2 * a), rel=1e-12)


def test_van_loan_double_integrator_closed_form():
    dt, s = 0.3, 2.0
    Qd = van_loan([[0, 1], [0, 0]], np.diag([0, s]), dt)
    np.testing.assert_allclose(Qd, s * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]]),
                               rtol=1e-12, atol=1e-16)


def test_discretisation_rejects_bad_dt():
    with pytest.raises(ValueError):
        zoh([[0.0]], [1.0], -1.0)
    with pytest.raises(ValueError):
        van_loan([[0.0]], [[1.0]], math.nan)


@pytest.mark.parametrize("dt", [0.1, 1.0])
def test_wen_matrices_closed_form(dt):
    m = WenModel.from_params(TRAIN, LINE, q=0.49, v_max=22.23)
    dm = m.discrete(dt)
    meff = 1.16 * 288e3
    np.testing.assert_allclose(dm.A1, [[1, dt], [0, 1]], atol=1e-14)
    np.testing.assert_allclose(dm.B, [dt**2 / 2 / meff, dt / meff], rtol=1e-12)
    np.testing.assert_allclose(dm.E, -dm.B, rtol=0, atol=0)
    k1 = 144.9154 + 8.5212 * 22.23 / 2  # eq. (9), Davis in N (no factor M)
    np.testing.assert_allclose(dm.A, dm.A1 + np.outer(dm.E, [0, k1]), rtol=1e-14)
    assert dm.F == pytest.approx(8.5212 * 22.23 / 2)
    np.testing.assert_allclose(dm.H[:, 0], dm.E * dm.F, rtol=1e-14)


@pytest.mark.parametrize("uncertainty", ["paper", "velocity"])
def test_uncertain_form_10_reproduces_v2_resistance(uncertainty):
    """x+ of eq. (6) with a + b v + c v^2 equals eq. (10) with Delta = dv / (v_max / 2)."""
    m = WenModel.from_params(TRAIN, LINE, v_max=22.23, uncertainty=uncertainty)
    dm = m.discrete(0.5)
    for v in (0.0, 3.0, 11.115, 22.23):
        x = np.array([1800.0, v])
        delta = (v - 22.23 / 2) / (22.23 / 2)
        Delta = np.array([[0.0, delta]]) if uncertainty == "paper" else np.array([[delta]])
        assert np.all(np.abs(Delta) <= 1 + 1e-12)
        lhs = m.step_exact(dm, x, 0.3, wind=0.5)
        rhs = (dm.A + dm.H @ Delta @ dm.Eu) @ x + m.known_input(dm, x[0], 0.3) + dm.E * 0.5
        np.testing.assert_allclose(lhs, rhs, rtol=1e-13, atol=1e-12)


def test_gradient_sign_and_size():
    m = WenModel.from_params(TRAIN, LINE)
    dm = m.discrete(1.0)
    up = m.known_input(dm, 2000.0, 0.0)  # +3 per mille: uphill decelerates
    down = m.known_input(dm, 1000.0, 0.0)  # -3 per mille: downhill accelerates
    g = 9.80665 * 0.003 / math.sqrt(1 + 0.003**2) / 1.16  # M g sin / ((1 + lambda) M)
    res = 3481.8036 / (1.16 * 288e3)
    assert up[1] == pytest.approx(-(res + g), rel=1e-12)
    assert down[1] == pytest.approx(-(res - g), rel=1e-12)


def _lag_integral(t, A, T, tau):
    """int_0^t of A (1 - exp(-(s - T)/tau)) 1{s >= T} ds (closed form of the step response)."""
    if t <= T:
        return 0.0
    r = t - T
    return A * (r - tau * (1 - math.exp(-r / tau)))


@pytest.mark.parametrize("amp,f", [(0.8, 1.0), (-0.6, 0.7)])
def test_actuator_mean_matches_step_response(amp, f):
    T, tau = 1.2, 0.4
    act = Actuator(tau, T, braking_rate=f)
    act.command(0.0, amp)
    ue = amp if amp >= 0 else f * amp
    grid = np.arange(0.0, 4.0001, 0.1)
    for t0, t1 in zip(grid[:-1], grid[1:]):
        expect = (_lag_integral(t1, ue, T, tau) - _lag_integral(t0, ue, T, tau)) / (t1 - t0)
        assert act.mean(t0, t1) == pytest.approx(expect, abs=1e-12)


def test_standstill_stops_instead_of_reversing():
    m = WenModel.from_params(TRAIN, LINE)
    dm = m.discrete(1.0)
    x = np.array([100.0, 0.3])
    xp = m.predict_mean(dm, x, -1.0)  # brakes harder than needed to stop within the step
    assert xp[1] < 0
    a = (xp[1] - x[1]) / 1.0
    np.testing.assert_allclose(m.standstill(x, xp, 1.0), [100.0 + 0.09 / (2 * -a), 0.0])
    rest = np.array([100.0, 0.0])
    np.testing.assert_array_equal(m.standstill(rest, m.predict_mean(dm, rest, -0.3), 1.0),
                                  [100.0, 0.0])
    moving = m.predict_mean(dm, np.array([100.0, 5.0]), -1.0)
    assert m.standstill(x, moving, 1.0) is moving


def test_zoh_of_a_stack_is_the_stack_of_single_discretisations():
    """One ZOH: a stack of models (the braking particles' per-f matrices) in one call."""
    rng = np.random.default_rng(4)
    A = rng.normal(size=(5, 3, 3))
    B = rng.normal(size=(5, 3, 2))
    Ad, Bd = zoh(A, B, 0.3)
    for k in range(5):
        a, b = zoh(A[k], B[k], 0.3)
        np.testing.assert_allclose(Ad[k], a, rtol=1e-13, atol=1e-15)
        np.testing.assert_allclose(Bd[k], b, rtol=1e-13, atol=1e-15)


def test_believed_actuator_state_is_the_event_actuator():
    """wen_model.Actuator (step means for the filter) and train_core.actuator.Actuator (the
    world's, event based) are the same eq. (1): the lag state agrees at every step end."""
    from train_core.actuator import Actuator as EventActuator

    rng = np.random.default_rng(5)
    f = 0.7
    believed = Actuator(0.4, 1.2, braking_rate=f)
    event = EventActuator(0.4, 1.2)
    cmds = [(0.1 * k, float(rng.uniform(-1.0, 1.0))) for k in range(0, 300, 9)]
    grid = 0.1 * np.arange(320)
    i = 0
    for t0, t1 in zip(grid[:-1], grid[1:]):
        while i < len(cmds) and cmds[i][0] <= t0 + 1e-9:
            believed.command(*cmds[i])
            event.advance(cmds[i][0], f)
            event.command(*cmds[i])
            i += 1
        believed.mean(t0, t1)
        assert believed._a == pytest.approx(event.advance(t1, f), abs=1e-12)


class _ScanActuator(Actuator):
    """The oracle: the definition written out. The step splits at every command's effect time
    inside it, each segment under the command in force at its start, found by a linear scan
    of the commands in stamp order; no index kept beside them."""

    def _delayed(self, s):
        c = 0.0
        for ts, val in self._cmds:
            if ts + self.delay <= s:
                c = val
            else:
                break
        return self._g(c)

    def mean(self, t0, t1):
        if not self.enabled:
            return super().mean(t0, t1)
        if not math.isfinite(self._t):
            self._t, self._a = t0, self._delayed(t0)
        t0 = self._t
        if t1 <= t0:
            return self._a
        knots = [t0] + [ts + self.delay for ts, _ in self._cmds if t0 < ts + self.delay < t1]
        knots.append(t1)
        integral, a = 0.0, self._a
        for s0, s1 in zip(knots[:-1], knots[1:]):
            c = self._delayed(s0)
            d = s1 - s0
            if self.tau > 0:
                decay = math.exp(-d / self.tau)
                integral += c * d + (a - c) * self.tau * (1.0 - decay)
                a = c + (a - c) * decay
            else:
                integral += c * d
                a = c
        self._a, self._t = a, t1
        self._prune(t1)
        return integral / (t1 - t0)

    def _prune(self, t):
        keep_from = 0
        for i, (ts, _) in enumerate(self._cmds):
            if ts + self.delay <= t:
                keep_from = i
            else:
                break
        if keep_from:
            del self._cmds[:keep_from]
        self._acts = [ts + self.delay for ts, _ in self._cmds]


@pytest.mark.parametrize("enabled", [True, False])
@pytest.mark.parametrize("seed", range(4))
def test_the_indexed_command_lookup_is_the_scan_to_the_bit(seed, enabled):
    """The actuator finds the command in force by bisecting the commands' effect times: its
    step means, lag state and kept commands equal a scan's to the bit, with commands waiting
    seconds ahead of the filter (as at 50 Hz), repeated stamps, late commands clamped to the
    latest stamp, effect times falling exactly on a step's ends, and copies."""
    rng = np.random.default_rng(seed)
    fast = Actuator(0.4, 0.7, braking_rate=0.8, enabled=enabled)
    slow = _ScanActuator(0.4, 0.7, braking_rate=0.8, enabled=enabled)
    # the commands start 8 s ahead of the filter's time, off its 20 ms grid; a step of up to
    # a second spans dozens of them, several sharing an effect time
    t, stamp, held, inside, shared = 0.0, 8.0071, 0, 0, 0
    for k in range(2000):
        stamp += 0.02  # a cycle's commands: none, one, or repeats; some late (clamped)
        for _ in range(int(rng.integers(0, 3))):
            a = float(rng.uniform(-1.2, 1.0))
            late = stamp - 0.05 * (rng.uniform() < 0.1)
            fast.command(late, a)
            slow.command(late, a)
        # steps of 20 ms; some end exactly where a held command takes effect, some are empty
        near = [s for s in fast._acts if t < s <= t + 0.05]
        r = rng.uniform()
        t1 = t if r < 0.05 else near[int(rng.integers(len(near)))] if near and r < 0.3 else \
            t + float(rng.uniform(0.05, 1.0)) if r > 0.85 and stamp - t > 2.5 else t + 0.02
        if rng.uniform() < 0.1:
            fast, slow = fast.copy(), slow.copy()
        k = [s for s in fast._acts if max(t, fast._t) < s < t1]  # effect times inside the step
        inside, shared = inside + len(k), shared + len(k) - len(set(k))
        assert repr(fast.mean(t, t1)) == repr(slow.mean(t, t1)), k
        assert (repr(fast._a), fast._t) == (repr(slow._a), slow._t)
        assert fast._cmds == slow._cmds
        assert fast._acts == [ts + fast.delay for ts, _ in fast._cmds]
        held = max(held, len(fast._cmds))
        t = max(t, t1)
    assert held > 50  # the lookups ran over long lists of commands waiting ahead
    assert inside > 100 and shared > 20, (inside, shared)  # steps spanned effect times
