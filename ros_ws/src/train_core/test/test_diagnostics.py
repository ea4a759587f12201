"""The /diagnostics rules (train_core.diagnostics): levels from counts, without rclpy."""

import math

import pytest
from train_core import diagnostics as D
from train_core.config import ConfigError

CFG = D.EstimatorThresholds()  # stale 2/5 s, rejected 0.05/0.5, latency 0.2/1.0 s


def _status(now, inputs, previous=None, latencies=(), integrity=None, reason=""):
    checks, values = D.input_checks(now, 0.0, inputs, previous or {}, 1.0, CFG)
    lc, lv = D.latency_check(list(latencies), CFG)
    ic, iv = D.integrity_check(integrity, reason)
    return D.combine(checks + lc + ic, values + lv + iv)


def test_grade_at_and_between_thresholds():
    assert D.grade(0.0, 1.0, 2.0) == D.OK
    assert D.grade(0.999, 1.0, 2.0) == D.OK
    assert D.grade(1.0, 1.0, 2.0) == D.WARN
    assert D.grade(2.0, 1.0, 2.0) == D.ERROR
    assert D.grade(math.nan, 1.0, 2.0) == D.ERROR


def test_fresh_inputs_without_rejections_are_ok_and_values_say_why():
    prev = {"odometer": D.InputCounts("odometer", 90, 90, {}, 9.0)}
    st = _status(10.0, [D.InputCounts("odometer", 100, 100, {}, 9.95)], prev,
                 latencies=[0.002] * 10, integrity=0)
    assert st.level == D.OK and st.message == "OK"
    values = dict(st.values)
    assert values["odometer.rate_hz"] == "10"
    assert values["odometer.received"] == "100" and values["integrity"] == "OK"
    assert values["latency_p99_ms"] == "2.00"


@pytest.mark.parametrize("age,level", [(1.9, D.OK), (2.0, D.WARN), (4.9, D.WARN),
                                       (5.0, D.ERROR)])
def test_staleness_levels(age, level):
    st = _status(100.0, [D.InputCounts("control", 5, 5, {}, 100.0 - age)])
    assert st.level == level
    if level:
        assert "control: silent for" in st.message


def test_never_received_counts_from_the_start_and_sparse_inputs_are_not_stale():
    st = _status(6.0, [D.InputCounts("odometer"), D.InputCounts("balise", watch_stale=False)])
    assert st.level == D.ERROR
    assert st.message == "odometer: nothing received since start for 6.0 s"
    assert dict(st.values)["balise.age_s"] == "never received"


def test_rejected_fraction_over_the_last_period_with_the_main_reason():
    prev = {"odometer": D.InputCounts("odometer", 100, 98, {"outside_gate": 2}, 9.9)}
    cur = D.InputCounts("odometer", 110, 100, {"outside_gate": 9, "non_finite": 3}, 10.9)
    st = _status(11.0, [cur], prev)
    # 10 received in the period, 10 newly rejected (7 gate, 3 non-finite): ERROR at >= 0.5
    assert st.level == D.ERROR
    assert st.message == "odometer: 10 of 10 rejected in the last 1 s (mostly outside_gate)"
    assert dict(st.values)["odometer.rejected.non_finite"] == "3"
    # old rejections do not count again: the next clean period is OK
    nxt = D.InputCounts("odometer", 120, 110, {"outside_gate": 9, "non_finite": 3}, 11.9)
    assert _status(12.0, [nxt], {"odometer": cur}).level == D.OK
    # one in twenty: WARN
    warn = D.InputCounts("odometer", 140, 129, {"outside_gate": 10, "non_finite": 3}, 12.9)
    assert _status(13.0, [warn], {"odometer": nxt}).level == D.WARN


@pytest.mark.parametrize("p99,level", [(0.19, D.OK), (0.2, D.WARN), (1.0, D.ERROR)])
def test_latency_graded_on_its_p99(p99, level):
    lat = [0.001] * 99 + [p99]
    st = _status(1.0, [], latencies=lat)
    assert st.level == level


def test_integrity_maps_to_levels_with_its_reason_and_the_worst_check_wins():
    fresh = [D.InputCounts("odometer", 10, 10, {}, 0.9)]
    assert _status(1.0, fresh, integrity=1, reason="innovations").level == D.WARN
    st = _status(1.0, fresh, integrity=2, reason="no measurement for 60 s")
    assert st.level == D.ERROR
    assert st.message == "integrity ALARM: no measurement for 60 s"
    assert dict(st.values)["integrity_reason"] == "no measurement for 60 s"
    # WARN and ERROR together: the message names the ERROR checks only
    both = _status(3.0, [D.InputCounts("odometer", 10, 10, {}, 0.9)], integrity=2, reason="x")
    assert both.level == D.ERROR and "odometer" not in both.message
    assert _status(0.5, [], integrity=None).level == D.OK


@pytest.mark.parametrize("bad,named", [
    ({"stale_warn": 0.0}, "stale_warn"), ({"stale_warn": 6.0}, "stale_error"),  # the pair
    ({"rejected_error": 1.5}, "rejected_error"), ({"latency_error": 0.1}, "latency_error"),
    ({"diagnostics_period": math.nan}, "diagnostics_period"),
    ({"diagnostics_period": 1e-9}, "diagnostics_period")])  # a busy loop, not a status
def test_thresholds_are_checked_with_the_parameter_named(bad, named):
    with pytest.raises(ConfigError, match=f"parameter {named}:"):
        D.EstimatorThresholds(**bad)
