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


def _with_seq(ev, value=0):
    """The stream with every odometer and balise seq at ``value`` (a producer that leaves the
    field at its default: no sample counter)."""
    return [(t, s, dict(f, seq=value) if t in ("odometer", "balise") else f, recv)
            for t, s, f, recv in ev]


def _table(outs):  # NaN where not estimated: compared as equal
    return np.array([(o.stamp, o.position, o.velocity, o.integrity, *o.covariance)
                     for o in outs], float)


@pytest.mark.parametrize("kind", ["robust", "kf"])
def test_a_stream_without_a_sample_counter_is_judged_by_its_stamps(kind):
    """Every seq 0 (the field left at its default): before, every reading after the first was
    refused as a copy of it and no estimate was ever published. Now the stream is found to
    have no counter (one event per stream, every reading counted), its readings are judged by
    their stamps and values, and the estimates are those of the same stream with its counter
    (on a lossy link: the lost samples are counted from the stamps at the configured rate)."""
    sc, res = run(duration=150.0)
    ev = restamp(res.events(), epoch=1.7e9, control_epoch=1.7e9)
    counted, r0 = replay(ev, adapter(sc, kind), 0.1)
    bare, r1 = replay(_with_seq(ev), adapter(sc, kind), 0.1)
    n_odo = sum(e[0] == "odometer" for e in ev)
    n_bal = sum(e[0] == "balise" for e in ev)
    assert n_bal >= 2 and r0.rejected == r1.rejected
    np.testing.assert_array_equal(_table(bare), _table(counted))
    assert r1.events[f"odometer:{R.SEQ_UNSTATED}"] == 1
    assert r1.events[f"balise:{R.SEQ_UNSTATED}"] == 1
    # (the first balise was taken before the second showed that its seq stands still; the
    # odometer's first readings wait for their clock anyway)
    assert r1.uncounted == {"odometer": n_odo, "balise": n_bal - 1}
    assert not r0.uncounted and not r0.events[f"odometer:{R.SEQ_UNSTATED}"]
    # the sensor's period for the odometer_rate check: from the stamps alone without a counter
    # (stamps at epoch 1.7e9 are spaced by 2.4e-7 s in double precision)
    assert r1.sample_period() == pytest.approx(r0.sample_period(), abs=1e-6)
    assert r1.sample_period() == pytest.approx(1.0 / sc.odometer_rate, abs=1e-6)


def test_copies_of_a_first_reading_do_not_make_a_counter_of_none():
    """Three copies of the first odometer reading at other stamps, arriving with it (the fuzz
    mix's): one seq at distinct stamps, but not over the stream's pace; the counter is kept."""
    sc, res = run(duration=20.0)
    ev = restamp(res.events(), epoch=1.7e9, control_epoch=1.7e9)
    i = next(k for k, e in enumerate(ev) if e[0] == "odometer")
    t, s, f, recv = ev[i]
    copies = [(t, s + d, dict(f), recv) for d in (0.5, 5.0, 60.0)]
    outs, r = replay(ev[:i + 1] + copies + ev[i + 1:], adapter(sc, "kf"), 0.1)
    assert not r.uncounted and not r.events[f"odometer:{R.SEQ_UNSTATED}"]
    assert r.accepted["odometer"] > 150 and outs


def test_a_backward_clock_step_without_a_counter_is_held_not_fused_at_the_old_clock():
    """Without a counter a backward step's readings come at stamps already taken: refused as
    copies of those (by their stamp alone), they left the kf estimating on the old clock, 61 m
    off with a sigma of 7 m (4 estimates OK). A copy is now a stamp with its values: the step's
    readings are held, the estimate is in doubt at once and the clock is re-anchored."""
    from train_estimation.tools import faults as F
    sc, res = run("metro_demo", 3, 90.0)
    fl = F.inject(res.events(), F.Fault("step", -3.0, 46.8), np.random.default_rng(0))
    fl.events = _with_seq(fl.events)
    outs, emitted, runner = F.run(fl.events, adapter(sc, "kf"), 0.1)
    s = F.score(outs, emitted, fl, res.truth, 10.0, 90.0 + F.LATENCY)
    assert runner.events[f"odometer:{R.SEQ_UNSTATED}"] == 1
    assert runner.events[f"odometer:{R.CLOCK_RESET}"] == 1
    # 60 m off on the old clock while the step is judged: inside the widened interval
    assert s["wrong_side"] == 0 and s["max_err"] > 30.0 and s["availability"] < 1.0, s


def test_commands_stamped_zero_are_taken_at_their_arrival():
    """A producer that leaves the commands' header empty (stamp 0): the contract stamps
    commands on the reference clock, the receive time, which stands in (one event, every
    command counted). Before, each command lay an epoch before the readings and three
    estimates in four were not published on time."""
    sc, res = run(duration=60.0)
    ev = restamp(res.events(), epoch=1.7e9, control_epoch=1.7e9)
    stated, _ = replay(ev, adapter(sc, "kf"), 0.1)
    zeros = [(t, 0.0 if t == "control" else s, f, recv) for t, s, f, recv in ev]
    outs, r = replay(zeros, adapter(sc, "kf"), 0.1)
    np.testing.assert_array_equal(_table(outs), _table(stated))  # restamp: arrival = stamp
    assert r.events[f"control:{R.STAMP_UNSTATED}"] == 1
    # the first decides nothing (its 0 may be a clock's own), the second does, and the first
    # is still held for its clock: both at their arrival
    assert r.unstamped == sum(e[0] == "control" for e in ev)
    # a clock that starts at 0 stamps one command 0, the node's clock elsewhere (a replayed bag)
    late = [(t, s, f, recv + 5e4) for t, s, f, recv in ev]
    _, r0 = replay(late, adapter(sc, "kf"), 0.1)
    assert not r0.unstamped and not r0.events[f"control:{R.STAMP_UNSTATED}"]


def test_a_command_hours_ahead_of_the_estimate_is_refused_as_a_reading_is():
    """A command mapped further ahead of the filter than ``max_horizon`` (commands that arrive
    14 h after the readings): refused as ``future_stamp``, as a reading would be; predicting
    over it overflowed the process noise's matrix exponential."""
    sc, res = run(duration=20.0)
    ev = restamp(res.events())
    ad = adapter(sc, "kf")
    outs, _ = replay(ev, ad, 0.1)
    before = ad.output(ad.filt.t)
    assert ad.control(ad.filt.t + 5e4, {"target_acceleration": 0.5}) == R.FUTURE_STAMP
    after = ad.output(ad.filt.t)
    assert after.position == before.position and after.covariance == before.covariance
