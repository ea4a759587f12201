"""An ``odometer_rate`` that is not the sensor's: every reading is still fused, and the node
says which rate to set (``/diagnostics``)."""

import os
import sys

import pytest
from train_core import diagnostics as D

from train_estimation.core.online.estimators import RobustAdapter, RobustConfig, StartState
from train_estimation.core.online.replay import replay

sys.path.insert(0, os.path.dirname(__file__))
from clocks import restamp, run  # noqa: E402


def test_a_rate_set_above_the_sensors_loses_no_reading():
    """A 1 Hz odometer run with odometer_rate 2 Hz: the stamps alone put a lost slot between
    every two samples, and the robust filter used to refuse every second reading as a
    duplicate of that slot (62 of 150 on seed 2). The counter says no sample was lost: every
    reading is fused, the estimates at the readings' stamps are those of the right rate to
    the filter's round-off (the bound differs: it is propagated over the half-period slots),
    and the runner measures the sensor's period."""
    sc, res = run("wen2017_subway", 1, 120.0)
    assert sc.odometer_rate == 1.0
    ev = restamp(res.events())
    outs, runners = {}, {}
    for period in (1.0, 0.5):
        ad = RobustAdapter(sc.train, sc.line, StartState(sc.start_position),
                           RobustConfig(period=period))
        o, runners[period] = replay(ev, ad, period)
        outs[period] = {round(x.stamp, 6): x.position for x in o}
    right, fast = runners[1.0], runners[0.5]
    assert not fast.rejected, dict(fast.rejected)
    assert fast.accepted == right.accepted
    common = set(outs[1.0]) & set(outs[0.5])
    assert len(common) == len(outs[1.0])
    assert max(abs(outs[1.0][k] - outs[0.5][k]) for k in common) < 1e-3
    assert fast.sample_period() == pytest.approx(1.0, abs=1e-6)


def test_the_rate_check_names_the_rate_to_set():
    checks, values = D.rate_check(1.0, 0.5)
    assert checks == [(D.WARN, "odometer samples every 1 s where odometer_rate 2 Hz expects "
                               "0.5 s: set odometer_rate: 1")]
    assert values == [("odometer_period_s", "1")]
    assert D.rate_check(0.105, 0.1) == ([], [("odometer_period_s", "0.105")])  # within 20 %
    assert D.rate_check(None, 0.1) == ([], [("odometer_period_s", "-")])
