"""A 60 s odometer outage while braking (metro_demo, the integrity campaign's case, node defaults):
every braking-rate estimator keeps its error within 10 m, and no estimate is wrong-side.

Without a reading, the filters only predict with the braking rate they had (the transition is
applied with readings; SMA's children prior drifts to neighbours and jumps only rarely). When
SMA spread f evenly over every value each second of the gap and Q-GRBPF redrew its particles
each second, their predicted stop moved 147 m and 80 m.
"""

import math

import numpy as np
import pytest

from train_estimation.core.online.estimators import (
    BrakingAdapter,
    BrakingConfig,
    NodeConfig,
    StartState,
)
from train_estimation.tools import faults as F
from train_sim.scenario import load_scenario
from train_sim.world import simulate

GAP = 60.0  # s
AFTER = 60.0  # s of the run kept after the gap (the campaign's)


@pytest.fixture(scope="module")
def demo():
    sc = load_scenario("metro_demo")
    res = simulate(sc, 0, sc.duration)
    t, v, a = (np.asarray(res.truth[k], float) for k in ("t", "velocity", "acceleration"))
    # the first brake application from speed (the campaign's "braking" onset: 102.3 s)
    brake = float(t[np.flatnonzero((t > 40.0) & (a < -0.25) & (v > 0.5 * v.max()))[0]])
    return sc, res, round(brake, 1)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["sma", "qgrbpf", "gsma", "rbpf", "kf"])
def test_a_60_s_outage_while_braking_keeps_the_error_within_10_m(demo, kind):
    sc, res, at = demo
    end = at + GAP + AFTER
    events = [e for e in res.events() if e[1] <= end]
    fl = F.inject(events, F.Fault("outage", GAP, at), np.random.default_rng(0))
    ad = BrakingAdapter(sc.train, sc.line, StartState(sc.start_position),
                        BrakingConfig(algorithm=kind))
    cfg = NodeConfig()
    outs, emitted, _ = F.run(fl.events, ad, 1 / sc.odometer_rate, delay=cfg.output_delay,
                             control_clock=cfg.control_clock, max_future=cfg.max_future)
    truth = {k: np.asarray(v)[np.asarray(res.truth["t"]) <= end] for k, v in res.truth.items()}
    s = F.score(outs, emitted, fl, truth, sc.odometer_rate, end + F.LATENCY)
    # the train brakes to a stop inside the gap (its stopping distance is ~235 m: a braking
    # rate off by 0.04 is 10 m), so the prediction is what is tested
    v_end = np.interp(at + GAP, truth["t"], truth["velocity"])
    assert v_end < 0.1
    assert s["wrong_side"] == 0 and s["bad_cov"] == 0
    assert math.isfinite(s["window_err"]) and s["window_err"] <= 10.0, s["window_err"]
