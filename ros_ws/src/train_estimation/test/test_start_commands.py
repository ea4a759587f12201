"""At start-up the readings wait for the command stream: a node that takes its first messages in
any order, or stalls while its clock runs on, publishes what the replay of the same messages
publishes (EstimatorRunner._awaiting_commands)."""

import os
import sys

import numpy as np
import pytest

from train_estimation.core.online.runner import EstimatorRunner

sys.path.insert(0, os.path.dirname(__file__))
from clocks import adapter, run  # noqa: E402

DELAY = 1.0  # s, the node's output_delay at 20x (the main job's)


def feed(sc, kind, arrivals):
    """The estimates of a runner driven as a node on simulated time drives it:
    ``arrivals`` = (topic, stamp, fields, recv); after each push, advance to the ready time at
    ``recv`` and settle; a topic of None is a timer tick at ``recv``. Then drain."""
    r = EstimatorRunner(adapter(sc, kind), 1 / sc.odometer_rate, control_clock="same")
    outs = []
    for topic, stamp, fields, recv in arrivals:
        if topic is not None:
            r.push(topic, stamp, fields, recv)
        outs += r.advance_to(r.ready_time(recv, DELAY, 4 * DELAY))
        r.settle()
    return outs + r.drain(), r


def by_stamp(outs):
    stamps = [o.stamp for o in outs]
    assert stamps == sorted(set(stamps)), "an estimate twice or out of order"
    return {o.stamp: o for o in outs}


def same(a, b):
    assert a.keys() == b.keys()
    for st in a:
        x, y = a[st], b[st]
        assert (x.position, x.velocity, x.integrity) == (y.position, y.velocity, y.integrity), st
        assert np.array_equal(x.covariance, y.covariance, equal_nan=True), st


@pytest.mark.parametrize("kind", ["gsma", "kf", "robust"])
def test_the_first_estimates_do_not_depend_on_when_the_node_took_its_messages(kind):
    sc, res = run("metro_demo", 1, 20.0)
    ev = [e for e in res.events() if e[0] in ("control", "odometer", "balise")]
    # in time: each message when it was sent (commands first in a cycle, as sent)
    in_time = [(tp, t, f, t + 0.01) for tp, t, f in ev]
    # a stall after the first four messages: the node's clock 2.2 s on when it resumes (the
    # paced simulator ran to its limit meanwhile), the messages of those 2.2 s taken at once
    stalled = [(tp, t, f, 0.2 if k < 4 else max(2.2, t + 0.01))
               for k, (tp, t, f) in enumerate(ev)]
    # the odometer's first 1.6 s taken before any command (the control subscription's data
    # came later), the node's clock moving meanwhile
    early = [e for e in ev if e[0] != "control" and e[1] < 1.6]
    rest = [e for e in ev if not (e[0] != "control" and e[1] < 1.6)]
    odometer_first = [(tp, t, f, 1.64) for tp, t, f in early] + \
        [(None, None, None, t) for t in (1.864, 2.037)] + \
        [(tp, t, f, max(2.2, t + 0.01)) for tp, t, f in rest]
    ref, r = feed(sc, kind, in_time)
    ref = by_stamp(ref)
    # every reading's estimate, and the lost ones' slots (predicted) between them
    assert {t for tp, t, _ in ev if tp == "odometer"} <= ref.keys()
    assert r.accepted["control"] == sum(e[0] == "control" for e in ev)
    for arrivals in (stalled, odometer_first):
        same(by_stamp(feed(sc, kind, arrivals)[0]), ref)


def test_without_commands_the_readings_wait_command_timeout_once():
    """A stream that sends no command: no estimate until its readings span command_timeout
    of their own stamps, then every slot, in order."""
    sc, res = run("metro_demo", 1, 20.0)
    odo = [(tp, t, f, t + 0.01) for tp, t, f in res.events() if tp == "odometer"]
    r = EstimatorRunner(adapter(sc, "kf"), 1 / sc.odometer_rate, control_clock="same")
    first = None
    outs = []
    for tp, t, f, recv in odo:
        r.push(tp, t, f, recv)
        got = r.advance_to(r.ready_time(recv, DELAY, 4 * DELAY))
        if got and first is None:
            first = t
        outs += got
    timeout = r.command_timeout
    assert first is not None and first >= odo[0][1] + timeout - 1e-9
    assert first <= odo[0][1] + timeout + 2 * DELAY
    by_stamp(outs + r.drain())
