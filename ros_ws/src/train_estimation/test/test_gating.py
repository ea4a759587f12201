"""Every estimator gates gross outliers with a reason, and counts them."""

import os
import sys

import numpy as np
import pytest

from train_estimation.core import reasons as R
from train_estimation.core.online.replay import replay

sys.path.insert(0, os.path.dirname(__file__))
from clocks import adapter, errors, restamp, run  # noqa: E402

OUTLIERS = {
    "distance+1e6": ("odometer", {"distance": 1e6}, R.OUTSIDE_GATE),
    "distance-1e6": ("odometer", {"distance": -1e6}, R.OUTSIDE_GATE),
    "speed+1e6": ("odometer", {"speed": 1e6}, R.OUTSIDE_GATE),
    "speed-1e6": ("odometer", {"speed": -1e6}, R.OUTSIDE_GATE),
    "variance0": ("odometer", {"speed_variance": 0.0}, R.NON_POSITIVE_VARIANCE),
    "nan": ("odometer", {"speed": float("nan")}, R.NON_FINITE),
    "balise_id": ("balise", {"balise_id": 999}, R.UNKNOWN_BALISE),
    "balise_map": ("balise", {"position": 1e6}, R.BALISE_MAP_MISMATCH),
}


@pytest.mark.parametrize("kind", ["robust", "gsma", "sma", "rbpf", "qgrbpf"])
def test_gross_outliers_are_gated_with_a_reason(kind):
    sc, res = run(duration=60.0)
    ev = restamp(res.events())
    clean, _ = replay(ev, adapter(sc, kind), 0.1)
    e0, _ = errors(clean, res)
    odo = [i for i, e in enumerate(ev) if e[0] == "odometer"]
    bal = [i for i, e in enumerate(ev) if e[0] == "balise"]
    assert bal, "the scenario passes a balise in 60 s"
    for name, (topic, change, reason) in OUTLIERS.items():
        targets = odo[100::37] if topic == "odometer" else bal
        bad = list(ev)
        for i in targets:
            t, s, f, recv = bad[i]
            bad[i] = (t, s, dict(f, **change), recv)
        outs, r = replay(bad, adapter(sc, kind), 0.1)
        assert r.rejected[f"{topic}:{reason}"] == len(targets), (name, dict(r.rejected))
        assert sum(r.rejected.values()) == len(targets), (name, dict(r.rejected))
        e, _ = errors(outs, res)
        assert len(e) == len(e0)
        # the estimate stays what it was without those readings, give or take their absence
        assert np.abs(e).max() < np.abs(e0).max() + 1.0, (name, np.abs(e).max())
        assert all(np.isfinite(o.position) and np.isfinite(o.velocity) for o in outs)
