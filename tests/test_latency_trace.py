"""The live latency's per-stage split (``bench_latency --trace``): a node's callback trace
(``train_core.realtime.CallbackTrace``) cut into stages and into what /clock costs, checked
exactly on traces written by hand, and the trace's callback wrappers as rclpy sees them."""

from __future__ import annotations

import inspect
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from bench_latency import clock_costs, trace_breakdown  # noqa: E402
from train_core.realtime import CallbackTrace  # noqa: E402

US = 1_000  # ns


def _m(label, wall_us, cpu_us, value=None):
    return (label, wall_us * US, cpu_us * US, value)


def _trace():
    """Two cycles. The first: the reading (stamp 1.0) arrives with its command in one wait;
    its callback releases nothing, the command's does. The second: the command came in an
    earlier wait, the reading's own callback releases its estimate (stamp 1.1)."""
    return [
        _m("wait", 0, 0), _m("woken", 9000, 1),
        _m("B:sub /odometer", 9100, 101), _m("reading", 9300, 301, 1.0),
        _m("pushed", 9310, 311), _m("tick", 9320, 321), _m("advanced", 9330, 331),
        _m("E:sub /odometer", 9340, 341),
        _m("B:sub /control", 9400, 401), _m("pushed", 9450, 451), _m("tick", 9460, 461),
        _m("advanced", 10060, 961),  # 600 us of wall, 500 of CPU: it waited 100 for a core
        _m("published", 10220, 1121, 1.0),
        _m("E:sub /control", 10240, 1141),
        _m("wait", 10500, 1400), _m("woken", 19000, 1401),
        _m("B:sub /control", 19050, 1451), _m("pushed", 19100, 1501), _m("tick", 19110, 1511),
        _m("advanced", 19120, 1521), _m("E:sub /control", 19130, 1531),
        _m("wait", 19200, 1600), _m("woken", 19300, 1601),
        _m("B:sub /odometer", 19400, 1701), _m("reading", 19600, 1901, 1.1),
        _m("pushed", 19610, 1911), _m("tick", 19620, 1921), _m("advanced", 20020, 2321),
        _m("published", 20180, 2481, 1.1),
        _m("E:sub /odometer", 20200, 2501),
    ]


def test_stages_of_each_estimate_exactly():
    b = trace_breakdown(_trace(), skip=0)

    def d(us):  # us -> s, as the trace's ns are
        return us * US * 1e-9
    # (wall, CPU) per estimate: the first released by the command, the second by the reading
    assert b["reading's push"] == [(d(210), d(210)), (d(210), d(210))]
    assert b["to the release"] == [(d(150), d(150)), (d(10), d(10))]
    assert b["advance"] == [(d(600), d(500)), (d(400), d(400))]
    assert b["messages"] == [(d(160), d(160)), (d(160), d(160))]
    assert b["total"] == [(d(1120), d(1020)), (d(780), d(780))]
    assert b["released_by"] == {"sub /control": 1, "sub /odometer": 1}
    # the executor: callback end -> wait, wake-up -> callback (CPU)
    assert b["before_wait"] == [d(259), d(69)]
    assert b["after_wait"] == [d(100), d(50), d(100)]
    span = d(20200)
    in_cbs = d(240 + 740 + 80 + 800)
    between = d(60 + 310 + 170)
    assert b["cpu_per_s"] == pytest.approx((in_cbs / span, between / span), rel=1e-12)


def test_start_up_estimates_left_out():
    b = trace_breakdown(_trace(), skip=1)
    assert len(b["total"]) == 1 and b["released_by"] == {"sub /odometer": 1}


def test_wrapper_keeps_the_arity_rclpy_reads_and_marks_an_exception():
    trace = CallbackTrace("/nonexistent")

    def on_msg(msg):
        raise ValueError(msg)

    wrapped = trace._wrapped("sub /x", on_msg)
    inspect.signature(wrapped).bind(object())  # rclpy: one argument, the message only
    with pytest.raises(TypeError):
        inspect.signature(wrapped).bind(object(), object())
    with pytest.raises(ValueError):
        wrapped("boom")
    assert [m[0] for m in trace.marks] == ["B:sub /x", "E:sub /x"]
    assert trace.marks[0][1] <= trace.marks[1][1] and trace.marks[0][2] <= trace.marks[1][2]


def test_subscription_wrapper_takes_the_message_info_and_keeps_its_stamps():
    """rclpy hands a two-argument callback the MessageInfo: the wrapper takes it, marks its
    start with the DDS stamps, and calls a one-argument callback with the message only (and a
    two-argument one with both)."""
    trace = CallbackTrace("/nonexistent")
    got = []
    one = trace._wrapped_sub("sub /x", lambda msg: got.append(msg))
    two = trace._wrapped_sub("sub /y", lambda msg, info: got.append((msg, info)))
    for wrapped in (one, two):
        inspect.signature(wrapped).bind(object(), object())
        with pytest.raises(TypeError):
            inspect.signature(wrapped).bind(object())
    info = {"source_timestamp": 5, "received_timestamp": 7}
    one("a", info)
    two("b", info)
    assert got == ["a", ("b", info)]
    assert [m[0] for m in trace.marks] == ["B:sub /x", "E:sub /x", "B:sub /y", "E:sub /y"]
    published, received, now = trace.marks[0][3]
    assert (published, received) == (5, 7) and now > 7


def _clock_trace():
    """Three wake-ups: /clock alone; /clock, then a reading that was received (system clock,
    the trace's steady clock + 1000 s) while that wake-up was under way; a reading alone,
    received after the wake-up for /clock had ended."""
    sys_off = 1_000_000 * 1_000 * US  # the system clock's lead on the steady clock, ns

    def info(recv_us, start_us):
        return (0, recv_us * US + sys_off, start_us * US + sys_off)
    return [
        _m("wait", 0, 0), _m("woken", 1000, 10),
        _m("B:sub /clock", 1100, 110, info(990, 1100)), _m("E:sub /clock", 1130, 140),
        _m("wait", 1700, 700),  # 690 us of CPU for /clock alone
        _m("woken", 2000, 701),
        _m("B:sub /clock", 2300, 1001, info(1995, 2300)), _m("E:sub /clock", 2340, 1041),
        _m("B:sub /lat/odometer", 2600, 1301, info(2100, 2600)),
        _m("E:sub /lat/odometer", 3600, 2301),
        _m("wait", 3900, 2600),
        _m("woken", 5000, 2601),
        _m("B:sub /lat/odometer", 5200, 2801, info(4900, 5200)),
        _m("E:sub /lat/odometer", 6000, 3601), _m("wait", 6100, 3700),
    ]


def test_clock_costs_exactly():
    c = clock_costs(_clock_trace())

    def d(us):
        return us * US * 1e-9
    assert c["alone"] == [d(690)]
    assert c["callback"] == [d(30), d(40)]
    assert c["per_s"] == pytest.approx(2 / d(6100), rel=1e-12)
    assert c["cpu_per_s"] == pytest.approx((d(690) + d(40)) / d(6100), rel=1e-12)
    assert c["queue"] == pytest.approx([d(500), d(300)], abs=1e-15)
    assert c["behind"] == [True, False]


def test_clock_costs_without_clock():
    marks = [m for m in _clock_trace() if "clock" not in m[0]]
    c = clock_costs(marks)
    assert c["alone"] == [] and c["callback"] == [] and c["per_s"] == 0.0
    assert c["behind"] == [False, False]
