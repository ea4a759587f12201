"""Issue 11, items 1-2: any stamp epoch, phase and drift; one bad seq or stamp never blinds."""

import math
import os
import sys

import numpy as np
import pytest

from train_estimation.core.replay import replay
from train_estimation.core.runner import EstimatorRunner

sys.path.insert(0, os.path.dirname(__file__))
from clocks import adapter, errors, restamp, run, run_replay  # noqa: E402

CLOCKS = [dict(phase=0.02), dict(phase=0.049), dict(epoch=1.7e9, phase=0.013, drift=1e-4),
          dict(epoch=1.7e9, phase=0.03, drift=0.01),
          dict(epoch=1.7e9, phase=0.081, drift=-0.01, control_epoch=1.6e9),
          dict(epoch=12.345, drift=0.004, control_epoch=1.7e9)]


@pytest.mark.parametrize("kind", ["robust", "gsma"])
def test_any_epoch_phase_and_drift_accepts_clean_readings(kind):
    sc, res = run(duration=150.0)
    n_odo = sum(1 for e in res.events() if e[0] == "odometer")
    outs, r = run_replay(sc, res, kind)
    e_ref, _ = errors(outs, res)
    rmse_ref = float(np.sqrt(np.mean(e_ref ** 2)))
    for clk in CLOCKS:
        outs, r = run_replay(sc, res, kind, **clk)
        assert r.accepted["odometer"] >= 0.99 * n_odo, (clk, dict(r.rejected))
        e, t = errors(outs, res, clk.get("epoch", 0.0), clk.get("phase", 0.0),
                      clk.get("drift", 0.0))
        # one estimate per sample slot, over the whole run
        assert len(e) >= 0.99 * (res.truth["t"][-1] * sc.odometer_rate), clk
        rmse = float(np.sqrt(np.mean(e ** 2)))
        assert rmse <= 1.1 * rmse_ref + 0.01, (clk, rmse, rmse_ref)


def test_estimates_are_stamped_at_the_odometer_samples():
    sc, res = run(duration=30.0)
    clk = dict(epoch=1.7e9, phase=0.037, drift=0.002, control_epoch=5.0)
    ev = restamp(res.events(), **clk)
    outs, _ = replay(ev, adapter(sc), 0.1)
    odo = {s for k, s, _, _ in ev if k == "odometer"}
    stamps = [o.stamp for o in outs]
    assert odo <= set(stamps)
    assert np.all(np.diff(stamps) > 0)
    d = np.diff(stamps)
    assert np.all(d < 0.15 * 1.01) and np.all(d > 0.05), (d.min(), d.max())


def _tamper(ev, i, **changes):
    topic, stamp, fields = ev[i][:3]
    f = dict(fields)
    stamp = changes.pop("stamp", stamp)
    f.update(changes)
    out = list(ev)
    out[i] = (topic, stamp, f, *ev[i][3:])
    return out


@pytest.mark.parametrize("kind", ["robust", "gsma"])
@pytest.mark.parametrize("recv", [True, False])
def test_one_bad_seq_or_stamp_does_not_blind(kind, recv):
    sc, res = run(duration=60.0)
    ev = restamp(res.events())
    if not recv:
        ev = [e[:3] for e in ev]
    odo = [i for i, e in enumerate(ev) if e[0] == "odometer"]
    ctl = [i for i, e in enumerate(ev) if e[0] == "control"]
    n_odo = len(odo)
    i = odo[100]
    cases = {
        "seq_max": _tamper(ev, i, seq=2**32 - 1),
        "seq_reset": [e if k <= i or e[0] != "odometer" else
                      (e[0], e[1], dict(e[2], seq=e[2]["seq"] - 100), *e[3:])
                      for k, e in enumerate(ev)],
        "odo_future": _tamper(ev, i, stamp=ev[i][1] + 1e6),
        "ctl_future": _tamper(ev, ctl[100], stamp=ev[ctl[100]][1] + 1e6),
        "odo_future_1e9": _tamper(ev, i, stamp=ev[i][1] + 1e9),
    }
    for name, evs in cases.items():
        outs, r = replay(evs, adapter(sc, kind), 0.1)
        assert r.accepted["odometer"] >= n_odo - 2, (name, dict(r.rejected), r.last_reasons)
        assert outs[-1].stamp < 100.0, name  # never ran off to the future stamp
        if "future" in name:
            assert sum(v for k, v in r.rejected.items() if k.endswith("future_stamp")) == 1, \
                (name, dict(r.rejected))
        if name == "seq_reset":
            assert r.events["odometer:seq_reset"] == 1, dict(r.events)
        e, _ = errors(outs, res)
        assert np.abs(e).max() < 3.0, (name, np.abs(e).max())


def test_runner_refuses_garbage_at_the_door_with_reasons():
    sc, res = run(duration=5.0)
    r = EstimatorRunner(adapter(sc), 0.1)
    assert r.push("odometer", math.nan, {"seq": 1}) == "non_finite: stamp"
    assert r.push("lidar", 1.0, {}).startswith("unknown_kind")
    assert r.push("odometer", 1.0, {"seq": "x"}).startswith("invalid")
    odo = {"distance": 0.0, "speed": 0.0, "speed_variance": 0.01}
    for k in range(12):  # stamps are judged once the clock has min_judged arrivals
        assert r.push("odometer", 1.0 + 0.1 * k, dict(odo, seq=k), 1.0 + 0.1 * k) == ""
    assert r.push("odometer", 2.1, dict(odo, seq=11), 2.2) == "duplicate"
    assert r.push("odometer", 1e6, dict(odo, seq=12), 2.3).startswith("future_stamp")
    assert set(r.rejected) == {"odometer:non_finite", "lidar:unknown_kind", "odometer:invalid",
                               "odometer:duplicate", "odometer:future_stamp"}
