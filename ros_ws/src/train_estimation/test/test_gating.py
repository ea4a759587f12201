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


@pytest.mark.parametrize("kind", ["robust", "kf"])
def test_a_stream_that_never_states_its_variance_is_read_with_the_believed_one(kind):
    """A producer that leaves speed_variance and position_variance at 0 (zeros mean "unknown"
    in ROS's covariance fields): the believed train's variances stand in, and the estimates are
    those of the same stream stating them; one event per stream, every such reading counted.
    A stream that has stated a variance and then sends 0 is corrupted: refused as before."""
    sc, res = run(duration=60.0)
    ev = restamp(res.events())
    sv, bv = sc.train.odometer_speed_variance, sc.train.balise_position_std ** 2

    def with_var(odo, bal, first=0):
        out = []
        for i, (t, s, f, recv) in enumerate(ev):
            if i >= first and t == "odometer":
                f = dict(f, speed_variance=odo)
            elif i >= first and t == "balise":
                f = dict(f, position_variance=bal)
            out.append((t, s, f, recv))
        return out

    stated, r0 = replay(with_var(sv, bv), adapter(sc, kind), 0.1)
    zeros, r1 = replay(with_var(0.0, 0.0), adapter(sc, kind), 0.1)
    n_odo = sum(e[0] == "odometer" for e in ev)
    n_bal = sum(e[0] == "balise" for e in ev)
    assert n_bal > 0
    def table(outs):  # NaN where not estimated: compared as equal
        return np.array([(o.stamp, o.position, o.velocity, o.integrity, *o.covariance)
                         for o in outs], float)

    np.testing.assert_array_equal(table(zeros), table(stated))
    assert r1.events[f"odometer:{R.VARIANCE_UNSTATED}"] == 1
    assert r1.events[f"balise:{R.VARIANCE_UNSTATED}"] == 1
    assert r1.unstated == {"odometer": n_odo, "balise": n_bal}
    assert not r0.unstated and not r1.rejected, dict(r1.rejected)
    # stated first, zeros later: a corrupted reading, refused
    odo = [i for i, e in enumerate(ev) if e[0] == "odometer"]
    _, r2 = replay(with_var(0.0, 0.0, first=odo[100]), adapter(sc, kind), 0.1)
    assert r2.rejected[f"odometer:{R.NON_POSITIVE_VARIANCE}"] == \
        sum(e[0] == "odometer" for e in ev[odo[100]:])
    assert "odometer" not in r2.unstated  # (per stream: the balises' had stated nothing yet)
