"""``Motion._integrate_plain`` (the nominal drive's loop, written out for speed) against the loop
it replaces, bit for bit: ``Actuator.segment`` and ``Dynamics.step`` called per step; and
``warm_actuator``, which skips the commands long before whose effect a later one overwrites,
against the walk over every earlier command."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from train_core.actuator import Actuator
from train_core.model import load_line, load_train
from train_core.motion import Motion, warm_actuator

CONFIG = Path(__file__).resolve().parents[1] / "config"


def _reference(mot: Motion, t_next: float, visits: list) -> None:
    """:meth:`Motion.integrate` as it was before the plain loop: the generic calls per step."""
    act, dyn, st = mot.act, mot.dyn, mot.state
    span = t_next - mot.t
    n = max(1, math.ceil(span / mot.max_step - 1e-9))
    h = span / n
    act.track_br = False
    for i in range(n):
        t0 = mot.t + i * h
        f = mot.braking_rate_const if mot.braking_rate_const is not None else \
            mot.braking_rate_of_t(t0 + 0.5 * h)
        ue = act.effective(f)
        a0, a_mid, a_end = act.segment(h, f)
        x0 = st.x
        dyn.step(st, h, a0, a_mid, a_end, ue, act.tau)
        if st.x > x0:
            visits.append((t0, h, x0, st.x))
    mot.t = t_next
    act.t = t_next
    act._activate()


def _drive(mot: Motion, plain: bool) -> tuple[list, list]:
    """Commands through traction, a cruise, braking to a stop, a dwell and a start again on
    the line's gradients, cut at every switch of the actuator's input as the simulator
    does: every (t, x, v, stopped) and every visit."""
    cmds = [(0.0, 1.0), (40.0, 0.0), (70.0, -0.8), (120.0, -1.0), (150.0, 0.6), (200.0, -1.2)]
    out, visits = [], []
    t, k = 0.0, 0
    while t < 260.0 - 1e-9:
        if k < len(cmds) and cmds[k][0] <= t + 1e-9:
            mot.act.command(t, cmds[k][1])
            k += 1
        t_next = min(260.0, mot.act.next_switch(), cmds[k][0] if k < len(cmds) else math.inf,
                     t + 0.7)
        if plain:
            mot.integrate(t_next, lambda *a: visits.append(a))
        else:
            _reference(mot, t_next, visits)
        t = t_next
        st = mot.state
        out.append((t, st.x, st.v, st.stopped, mot.act.a))
    return out, visits


@pytest.mark.parametrize("line, train", [("metro_demo", "metro_b6"), ("crh3_line", "crh3")])
@pytest.mark.parametrize("varying", [False, True])
def test_the_plain_loop_is_the_generic_one_bit_for_bit(line, train, varying):
    tr = load_train(CONFIG / "trains" / f"{train}.yaml")
    ln = load_line(CONFIG / "lines" / f"{line}.yaml")
    f_of = (lambda t: 1.0 - 0.001 * t) if varying else None  # a braking rate that degrades

    def motion():
        act = Actuator(tr.brake.time_constant, tr.brake.delay)
        return Motion(tr, ln, tr, act, ln.stations[0].position, 0.0,
                      braking_rate_of_t=f_of)

    fast, ref = motion(), motion()
    assert not fast.dyn.split
    got, got_visits = _drive(fast, True)
    want, want_visits = _drive(ref, False)
    assert any(s for *_, s, _ in got[5:]) and max(v for _, _, v, _, _ in got) > 10.0
    assert got == want  # every float, exactly
    assert got_visits == want_visits


def _warm_reference(train, t_cmd, a_cmd, t0: float, warmup: float = 30.0) -> Actuator:
    """``warm_actuator`` as it was: every command before ``t0`` visited in turn."""
    act = Actuator(train.brake.time_constant, train.brake.delay, t0=-warmup)
    act.track_br = True
    f = train.brake.braking_rate
    for t_i, a_i in zip(t_cmd[t_cmd < t0] - t0, a_cmd[t_cmd < t0]):
        if t_i >= -warmup:
            act.advance(t_i, f)
            act.command(t_i, a_i)
        else:
            act.u_tr, act.u_br = max(a_i, 0.0), min(a_i, 0.0)
    act.advance(0.0, f)
    act.t = 0.0
    return act


@pytest.mark.parametrize("t0", [0.0, 20.0, 31.0, 95.3, 400.0])
def test_warm_actuator_skips_only_commands_whose_effect_is_overwritten(t0):
    tr = load_train(CONFIG / "trains" / "metro_b6.yaml")
    rng = np.random.default_rng(5)
    t_cmd = np.round(np.arange(0.0, 500.0, 0.1), 6)  # a recorder's 10 Hz commands
    a_cmd = np.where(rng.random(t_cmd.size) < 0.5, rng.uniform(-1.2, 1.0, t_cmd.size), 0.0)
    got, want = warm_actuator(tr, t_cmd, a_cmd, t0), _warm_reference(tr, t_cmd, a_cmd, t0)
    assert vars(got).keys() == vars(want).keys()
    for k, v in vars(want).items():
        assert getattr(got, k) == v, k  # every float, exactly (the delay lines too)
