"""The ATO's prediction (``Driver._predict``) runs its believed actuator forward on local copies
of the actuator's state, ``Actuator.advance`` written out for speed: it must stay the actuator's
own arithmetic. The oracle steps a copy of the actuator, as the prediction once did."""

from __future__ import annotations

import math

import numpy as np
import pytest

from train_sim.driver import Driver, DriverParams
from train_sim.scenario import load_scenario


def stepped(drv: Driver, x: float, v: float) -> tuple[float, float]:
    """The prediction through ``Actuator.copy`` and ``advance`` (the oracle)."""
    act = drv._act.copy()
    n = max(3, math.ceil(drv.horizon / 0.1))
    h = drv.horizon / n
    for _ in range(n):
        a_start = act.a
        a_end = act.advance(act.t + h, drv.braking_rate_belief)
        dv = h * (0.5 * (a_start + a_end) - drv._resist(x, v))
        v_new = v + dv
        if v_new <= 0.0:
            frac = v / (v - v_new) if v > v_new else 0.0
            return x + 0.5 * v * frac * h, 0.0
        x += 0.5 * h * (v + v_new)
        v = v_new
    return x, v


@pytest.mark.parametrize("scenario", ["metro_demo", "crh3_high_speed"])
def test_the_prediction_is_the_actuators_own_to_the_bit(scenario):
    """Over 400 control cycles of random commands (traction, coasting, braking; at the cycle's
    instants, so that pipe heads fall on sub-step ends, and between them), a braking-rate
    belief that changes, positions over the whole line and speeds from rest to 40 m/s: the
    same (x, v) bit for bit, and the actuator itself left as it was."""
    sc = load_scenario(scenario)
    drv = Driver(sc.line, sc.train, DriverParams(), (), 0.0)
    rng = np.random.default_rng(3)
    t = 0.0
    for k in range(400):
        t += drv.p.control_period if k % 3 else float(rng.uniform(0.01, 0.3))
        drv._act.advance(t, drv.braking_rate_belief)
        drv._act.command(t, float(rng.choice([rng.uniform(-1.2, 1.0), 0.0, -0.3])))
        if k % 50 == 0:
            drv.set_braking_rate_belief(float(rng.uniform(0.6, 1.2)))
        x, v = float(rng.uniform(0.0, sc.line.length)), float(rng.choice([0.0, 0.4,
                                                                          rng.uniform(0, 40)]))
        before = (drv._act.t, drv._act.a, drv._act.u_tr, drv._act.u_br,
                  list(drv._act._pipe), list(drv._act._bpipe))
        assert drv._predict(x, v) == stepped(drv, x, v), (k, x, v)
        assert (drv._act.t, drv._act.a, drv._act.u_tr, drv._act.u_br, list(drv._act._pipe),
                list(drv._act._bpipe)) == before
