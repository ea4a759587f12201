"""Out-of-sequence readings within the history are fused by rewinding."""

import os
import re
import sys

import numpy as np
import pytest

from train_estimation.core.online.replay import replay
from train_estimation.core.online.runner import EstimatorRunner, _Replayed

sys.path.insert(0, os.path.dirname(__file__))
from clocks import adapter, errors, restamp, run, wobbled  # noqa: E402


def jittered(events, rng, max_latency=0.4):
    """Arrival order after a link with latency uniform in [0, max_latency] on odometer and
    balise (control is not on the radio link): readings overtake each other."""
    out = []
    for topic, stamp, fields, recv in events:
        lat = rng.uniform(0, max_latency) if topic in ("odometer", "balise") else 0.0
        out.append((recv + lat, topic, stamp, fields))
    out.sort(key=lambda e: e[0])
    return [(t, s, f, a) for a, t, s, f in out]


@pytest.mark.parametrize("kind", ["robust", "gsma"])
def test_reordered_readings_are_fused_not_dropped(kind):
    sc, res = run(duration=60.0)
    clean = restamp(res.events())
    ref, r0 = replay(clean, adapter(sc, kind), 0.1)
    ev = jittered(clean, np.random.default_rng(7))
    odo = [e[1] for e in ev if e[0] == "odometer"]
    assert sum(np.diff(odo) < 0) > 50  # the link does reorder
    outs, r = replay(ev, adapter(sc, kind), 0.1)
    assert not r.rejected, dict(r.rejected)
    assert r.accepted == r0.accepted
    late = sum(v for k, v in r.events.items() if k.endswith("fused_late"))
    assert late > 50, dict(r.events)
    e0, _ = errors(ref, res)
    e, _ = errors(outs, res)
    assert len(e) == len(e0)
    rmse0, rmse = np.sqrt(np.mean(e0 ** 2)), np.sqrt(np.mean(e ** 2))
    assert rmse <= 1.1 * rmse0 + 0.02, (rmse, rmse0)
    # the same arrival order gives the same estimates, bit for bit (node = replay)
    again, _ = replay(ev, adapter(sc, kind), 0.1)
    assert [(o.stamp, o.position, o.velocity) for o in again] == \
        [(o.stamp, o.position, o.velocity) for o in outs]


def test_readings_older_than_the_history_are_refused_with_a_reason():
    sc, res = run(duration=30.0)
    ev = restamp(res.events())
    i = [k for k, e in enumerate(ev) if e[0] == "odometer"][100]
    late = ev.pop(i)
    ev.insert(i + 80, late)  # arrives 80 messages (about 4 s) late: beyond the 3 s history
    _, r = replay(ev, adapter(sc), 0.1)
    assert r.rejected == {"odometer:out_of_order": 1}
    # the reason says how late: beyond the history, by no more than the newest stamp that
    # arrived before it (the runner fuses what its watermarks release)
    newest = max(e[1] for e in ev[:i + 80])
    (kind, stamp, why), = r.last_reasons
    assert (kind, stamp) == ("odometer", late[1]), r.last_reasons
    m = re.fullmatch(r"out_of_order: ([\d.]+) s older than the newest input fused "
                     r"\(history 3 s\)", why)
    assert m and r.history < float(m.group(1)) <= newest - late[1], (why, newest)


def test_an_adapter_without_snapshots_keeps_no_history():
    """Nothing rewinds an adapter that cannot copy its state, so the runner keeps only the last
    item it fused (what a later one is judged late against), not every item of the run: the
    history stays one item long however long the run, and each reading is fused as it came."""
    from train_estimation.tools.clock_runs import Recorder

    class NoCopy:  # the clock runs' Recorder without its copies
        def __init__(self):
            self._rec = Recorder()
            self.fused = self._rec.fused
            for name in ("start", "control", "odometer", "balise", "output"):
                setattr(self, name, getattr(self._rec, name))

    sc, res = run(duration=30.0)
    ev = restamp(res.events())
    rec = NoCopy()
    runner = EstimatorRunner(rec, 0.1)
    outs, r = replay(ev, rec, 0.1, runner=runner)
    n_odo = sum(e[0] == "odometer" for e in ev)
    assert runner.history > 0 and not runner._can_rewind
    assert len(runner._hist) == 1
    assert r.accepted["odometer"] == n_odo == len(rec.fused) and not r.rejected
    assert len(outs) >= n_odo


class _Unsettled(EstimatorRunner):
    """A runner whose state for each reading is copied just before the reading (settle does
    nothing): the rewind points as they were before settle existed."""

    def settle(self) -> None:
        pass


def _bits(outs) -> list:
    return [tuple(v.hex() if isinstance(v, float) else repr(v) for v in vars(o).values())
            for o in outs]


@pytest.mark.parametrize("kind", ["robust", "kf", "rbpf"])
def test_the_state_copied_after_publishing_rewinds_to_the_same_bits(kind):
    """settle() copies the state once the estimates are out and a reading after it keeps that
    copy and the commands given since; a late reading that rewinds there makes the commands'
    calls again. Every field of every estimate, and the counts, are those of a runner that
    copies the state just before each reading."""
    sc, res = run(duration=40.0)
    ev = jittered(restamp(res.events()), np.random.default_rng(3))
    restores = []
    ref, r0 = replay(ev, None, 0.1, runner=_Unsettled(adapter(sc, kind), 0.1))
    runner = EstimatorRunner(adapter(sc, kind), 0.1)
    restore = runner._restore
    runner._restore = lambda snap: (restores.append(snap), restore(snap))
    outs, r = replay(ev, None, 0.1, runner=runner)
    # the rewinds met settled copies with a command to make again (the path under test)
    assert sum(isinstance(s, _Replayed) and len(s.controls) > 0 for s in restores) > 20
    assert _bits(outs) == _bits(ref)
    assert r.counts == r0.counts and r.events == r0.events


@pytest.mark.parametrize("kind", ["robust", "kf"])
def test_a_step_found_by_the_counts_level_is_fused_again_as_without_it(kind):
    """A real filter through a late step: metro_demo, 300 s, a stream without a counter whose
    count is 0.5 m noisy, on a link of 50 ms + Exp(50 ms), the train clock stepped back by one
    period (0.1 s) at 200 s. Inside the count's noise and the arrivals' bar, the step is found
    by the count's level among readings already fused (clocks.StepWatch._level_test), and
    those are re-stamped and fused again from the copy before them (EstimatorRunner.
    _late_step). From then on the filter is where it is without the step: every estimate after
    the step equals, bit for bit, the one at the same true time of the same run without it,
    but those published before the step was found (at most its 2 s); the first reading after
    the step, stamped as the last one before it, was refused by the filter as its duplicate
    and is fused at its time by the re-stamp, and counted as fused, not as refused."""
    sc, res = run(duration=300.0)

    def events(step):
        rng = np.random.default_rng(3)
        ev = []
        for topic, t, fields, recv in restamp(res.events()):
            f = dict(fields)
            stamp = t
            if topic in ("odometer", "balise"):
                if topic == "odometer":
                    f["seq"] = 0
                    f["distance"] = f["distance"] + rng.normal(0.0, 0.5)
                stamp = t + (step if t >= 200.0 else 0.0)
                recv = recv + 0.05 + rng.exponential(0.05)
            ev.append((topic, stamp, f, recv))
        ev.sort(key=lambda e: e[3])
        return ev

    ref, r0 = replay(events(0.0), adapter(sc, kind), 0.1)
    outs, r = replay(events(-0.1), adapter(sc, kind), 0.1)
    assert r.events.get("odometer:clock_reset") == 1 and not r0.events.get("odometer:clock_reset")
    at = {round(o.stamp, 6): o for o in ref}
    same = differ = 0
    for o in outs:
        if o.stamp >= 200.0 - 1e-6:  # a sample after the step: stamped (as sent) 0.1 s back
            o0 = at[round(o.stamp + 0.1, 6)]
            if (o.position, o.velocity) == (o0.position, o0.velocity):
                same += 1
            else:
                differ += 1
    assert differ <= 20 and same >= 900, (same, differ)
    # the duplicate refused before the step was found is counted by what it became: fused
    assert r.rejected == r0.rejected and r.accepted == r0.accepted, (
        dict(r.rejected), dict(r0.rejected), dict(r.accepted), dict(r0.accepted))


@pytest.mark.parametrize("kind", ["kf", "gsma"])
def test_a_reading_sampled_before_its_predicted_slot_is_fused_late_not_refused(kind):
    """metro_demo 300 s, every odometer sample taken up to 10 ms off its 10 Hz slot (the stamp
    the true sampling instant, the values the truth there), a 50 ms + Exp(50 ms) link. A
    reading late enough for its slot to be published as a prediction has a braking filter
    stepped to the slot's nominal time (their outputs are time updates of the filter), and
    the copies taken after it hold that time: rewound to one of them, a reading sampled a few
    ms before its slot was refused as out of order (9 of 2,622). The rewind now goes back to
    a copy taken before any output after the reading's stamp: every reading fused, late ones
    by rewinding."""
    from train_estimation.tools import faults as F

    sc, res = run(duration=300.0)
    tr = res.truth
    ev = wobbled(sc, res, 0.01, np.random.default_rng(5))
    fl = F.inject(ev, F.Fault("none", jitter=0.05), np.random.default_rng(1))
    outs, emitted, runner = F.run(fl.events, adapter(sc, kind), 0.1)
    assert not runner.rejected, dict(runner.rejected)
    assert runner.events.get("odometer:fused_late", 0) > 50, dict(runner.events)
    s = F.score(outs, emitted, fl, tr, 10.0, 300.0 + F.LATENCY)
    assert s["wrong_side"] == 0 and s["misleading"] == 0, s


@pytest.mark.parametrize("kind", ["kf", "gsma"])
def test_a_reading_beyond_the_history_leaves_the_history_for_those_within_it(kind,
                                                                            monkeypatch):
    """metro_demo 300 s, the link holds the readings sampled in [100, 104) s and delivers them
    together at 104.05 s (a modem flushing its backlog). Those more than `history` (3 s) late
    reach no copy; those within it are fused by rewinding. The first of them, processed
    without a rewind, was appended after the history's newest items with a copy taken after
    the outputs since: it became the first copy kept, the copies before it were let go, and
    the braking filters refused 24 of the 25 readings the history still reached."""
    from train_estimation.tools import faults as F

    sc, res = run(duration=300.0)
    fl = F.inject(res.events(), F.Fault("none"), np.random.default_rng(0))
    held = [(k, s, f, F.EPOCH + 104.0 + F.LATENCY if k != "control" and
             100.0 <= s - F.EPOCH < 104.0 else r) for k, s, f, r in fl.events]
    fl.events = sorted(held, key=lambda e: e[3])
    lags = {}
    apply = EstimatorRunner._apply

    def watched(self, stamp, order, n, kind_, fields):
        lag = self._high_done - stamp
        reason = apply(self, stamp, order, n, kind_, fields)
        if kind_ == "odometer" and 100.0 <= stamp - F.EPOCH < 104.0:
            lags[stamp] = (lag, reason)
        return reason

    monkeypatch.setattr(EstimatorRunner, "_apply", watched)
    F.run(fl.events, adapter(sc, kind), 0.1)
    within = [r for lag, r in lags.values() if lag <= 3.0]
    assert len(within) >= 20 and not any(within), within


@pytest.mark.parametrize("kind", ["robust", "kf"])
@pytest.mark.parametrize("first", [True, False])
def test_a_corrupted_copy_of_a_sample_never_costs_the_true_one(kind, first):
    """Two messages with one seq and stamp whose counts differ are a sample and a corruption of
    it, not copies: whichever comes first, the corrupted one (5 km off) is refused and the true
    one fused. Keyed by seq and stamp alone, a corrupted copy that came first and was refused by
    the gate made the true sample after it a duplicate, and it was lost."""
    sc, res = run(duration=60.0)
    ev = restamp(res.events())
    ref, r0 = replay(ev, adapter(sc, kind), 0.1)
    i = [k for k, e in enumerate(ev) if e[0] == "odometer"][300]
    t, s, f, rc = ev[i]
    bad = (t, s, {**f, "distance": f["distance"] + 5000.0}, rc)
    outs, r = replay(ev[:i] + [bad] + ev[i:] if first else ev[:i + 1] + [bad] + ev[i + 1:],
                     adapter(sc, kind), 0.1)
    assert r.accepted == r0.accepted
    assert dict(r.rejected) == ({"odometer:outside_gate": 1} if first
                                else {"odometer:duplicate": 1})
    # every estimate as without the corruption, bit for bit; the true sample's own slot was
    # published when the corrupted one was refused (one estimate per slot), a prediction of it
    got = {o.stamp: (o.position, o.velocity) for o in outs}
    want = {o.stamp: (o.position, o.velocity) for o in ref}
    assert got.keys() == want.keys()
    assert [k for k in want if got[k] != want[k]] == ([s] if first else [])


@pytest.mark.parametrize("kind", ["robust", "gsma"])
def test_a_commands_copy_is_a_duplicate_at_the_door_not_a_rewind(kind):
    """Every command sent again, the same stamp and target, after the next odometer reading:
    each copy is refused as a duplicate as it comes (nothing is fused late for it) and the
    estimates are those of the run without the copies, bit for bit. A command of the same
    target at another stamp is no copy (a driver holding a notch sends it every cycle)."""
    sc, res = run(duration=40.0)
    clean = restamp(res.events())
    ref, r0 = replay(clean, adapter(sc, kind), 0.1)
    ev, copies = [], 0
    pending = None
    for e in clean:
        ev.append(e)
        if pending is not None and e[0] == "odometer":
            ev.append(pending)  # the copy arrives after a later reading
            copies += 1
            pending = None
        if e[0] == "control":
            pending = e
    assert copies > 100
    outs, r = replay(ev, adapter(sc, kind), 0.1)
    assert r.rejected == {"control:duplicate": copies}, dict(r.rejected)
    assert r.accepted == r0.accepted
    assert r.events.get("control:fused_late", 0) == r0.events.get("control:fused_late", 0)
    assert [(o.stamp, repr(o.position), repr(o.velocity)) for o in outs] == \
        [(o.stamp, repr(o.position), repr(o.velocity)) for o in ref]
