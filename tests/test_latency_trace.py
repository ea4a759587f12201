"""The live latency's per-stage split (``bench_latency --trace``): a node's callback trace
(``train_core.realtime.CallbackTrace``) cut into stages, checked exactly on a trace written by
hand, and the trace's callback wrapper as rclpy sees it."""

from __future__ import annotations

import inspect
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from bench_latency import trace_breakdown  # noqa: E402
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
