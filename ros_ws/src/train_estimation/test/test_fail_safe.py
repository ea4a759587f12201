"""The runner as the nodes run it (``fail_safe``): an exception inside the estimator never
stops the node and never publishes a state it left half-updated; it latches ALARM."""

from __future__ import annotations

import math
import os
import sys

import pytest

from train_estimation.core import reasons as R
from train_estimation.core.online.integrity import ALARM
from train_estimation.core.online.replay import replay

sys.path.insert(0, os.path.dirname(__file__))
from clocks import adapter, run  # noqa: E402

LAT = 0.05  # s, arrival = stamp + LAT


def _events(res):
    return [(topic, t, f, t + LAT) for topic, t, f in res.events()
            if topic in ("odometer", "balise", "control")]


def _breaking(a, method: str, after: int):
    """``a`` whose ``method`` raises on its call number ``after`` and every later one."""
    calls = [0]
    real = getattr(a, method)

    def broken(*args, **kw):
        calls[0] += 1
        if calls[0] >= after:
            raise FloatingPointError("injected defect")
        return real(*args, **kw)

    setattr(a, method, broken)
    return a


@pytest.fixture(scope="module")
def demo():
    return run("metro_demo", 2, 60.0)


def test_without_fail_safe_the_exception_is_seen(demo):
    """Offline analysis, tests and the campaign run without it: a defect must not hide."""
    sc, res = demo
    with pytest.raises(FloatingPointError):
        replay(_events(res), _breaking(adapter(sc, "kf"), "odometer", 300), 0.1,
               control_clock="same")


@pytest.mark.parametrize("kind, method", [("kf", "odometer"), ("robust", "output"),
                                          ("gsma", "balise")])
def test_a_failure_latches_alarm_after_the_estimates_before_it(demo, kind, method):
    sc, res = demo
    ev = _events(res)
    clean, _ = replay(ev, adapter(sc, kind), 0.1, control_clock="same")
    after = {"odometer": 300, "output": 300, "balise": 1}[method]
    outs, r = replay(ev, _breaking(adapter(sc, kind), method, after), 0.1,
                     control_clock="same", fail_safe=True)
    assert r.failure is not None and r.failure.startswith(("advance_to:", "tick:"))
    assert "FloatingPointError: injected defect" in r.failure
    assert "injected defect" in r.failure_trace
    k = next(i for i, o in enumerate(outs) if o.integrity_reason.startswith(R.ESTIMATOR_FAILED))
    assert 0 < k < len(clean)
    # before it: what the estimator published without the defect, to the bit (repr: NaN is
    # not equal to itself, and the robust filter publishes no acceleration)
    assert repr(outs[:k]) == repr(clean[:k])
    failed = outs[k:]
    assert all(o.integrity == ALARM and o.protection_level_ahead == math.inf
               and o.protection_level_behind == math.inf for o in failed)
    assert all(o.integrity_reason == f"{R.ESTIMATOR_FAILED}: {r.failure}" for o in failed)
    # where the train was last known, with no bound a consumer could take for one
    assert all(o.position == outs[k - 1].position and o.velocity == outs[k - 1].velocity
               for o in failed)
    assert all(all(math.isfinite(o.covariance[i]) for i in (0, 1, 4, 5))
               and o.covariance[0] >= 1e12 and o.covariance[5] >= 1e12 for o in failed)
    stamps = [o.stamp for o in outs]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))  # one stream, in order
    # every message after the failure is refused by name; each odometer reading stamped after
    # the last estimate is one ALARM estimate at its stamp
    odo_after = [s for topic, s, _, _ in ev if topic == "odometer" and s > outs[k - 1].stamp]
    assert [o.stamp for o in failed] == odo_after[-len(failed):]
    assert r.rejected[f"odometer:{R.ESTIMATOR_FAILED}"] >= len(failed)
    assert r.rejected[f"control:{R.ESTIMATOR_FAILED}"] > 0
    assert R.ESTIMATOR_FAILED in R.REJECTIONS


def test_a_failure_before_any_estimate_publishes_nothing(demo):
    """Nothing was ever published: no position to put an ALARM at (a consumer that has never
    heard of the train does not let it move), the failure still latched and counted."""
    sc, res = demo
    outs, r = replay(_events(res), _breaking(adapter(sc, "kf"), "start", 1), 0.1,
                     control_clock="same", fail_safe=True)
    assert outs == [] and r.failure.startswith("advance_to: FloatingPointError")
    assert r.rejected[f"odometer:{R.ESTIMATOR_FAILED}"] > 500
