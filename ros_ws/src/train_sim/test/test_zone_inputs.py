"""Zone controller: bad input refused and counted (never a crash, never a lock), clock resets
followed on evidence, integrity obeyed, and a seeded fuzz of corrupted reports."""

import math
from collections import Counter
from dataclasses import replace

import numpy as np
import pytest

from train_sim import zone as Z
from train_sim.zone import RefusalLog, TrainReport, ZoneController, ZoneParams
from train_sim.zone_fuzz import EXPECTED, corrupt_reports

P = ZoneParams(stale_timeout=2.0, emergency_decel=1.0, train_length=100.0,
               margin=10.0, danger_points=(50000.0,), max_future=1.0, line_length=100000.0)
LATENCY = 0.05  # s, stamp to arrival


def rep(t, x=1000.0, v=10.0, clock=0.0, **kw):
    """A good report sampled at zone time t, stamped on a clock ``clock`` s ahead of the
    zone's, arriving LATENCY later."""
    kw = {"var_position": 1.0, "var_velocity": 0.01, "pl_ahead": 5.3, "pl_behind": 5.3, **kw}
    return TrainReport(t_received=t + LATENCY, stamp=t + clock, position=x + v * t, velocity=v,
                       **kw)


def granted(zc, now, tid="A"):
    (a,) = zc.authorities(now, [tid])
    return not a.emergency_brake, a


def test_negative_braking_rate_variance_is_refused_not_a_crash():
    zc = ZoneController(P)
    assert zc.report("A", rep(0.0)) == ""
    assert zc.report("A", rep(0.1, braking_rate=0.9, var_braking_rate=-0.01)) == \
        Z.NON_POSITIVE_VARIANCE
    assert zc.rejected == {Z.NON_POSITIVE_VARIANCE: 1}
    assert zc.report("A", rep(0.2)) == ""
    assert granted(zc, 0.3)[0]


@pytest.mark.parametrize("field", ["var_position", "var_velocity", "var_braking_rate"])
def test_nan_variance_is_refused_never_read_as_certainty(field):
    zc = ZoneController(P)
    # the last good report stays in force: the NaN one is not stored with a variance of 0
    good = replace(rep(0.0, x=4000.0), braking_rate=0.9, var_braking_rate=1e-4)
    assert zc.report("A", good) == ""
    bad = replace(rep(0.1, x=4000.0), **{"braking_rate": 0.9, "var_braking_rate": 1e-4,
                                          field: math.nan})
    assert zc.report("A", bad) == Z.NON_FINITE
    assert zc.reports["A"] is good


def test_covariance_must_be_symmetric_positive_definite():
    zc = ZoneController(P)
    assert zc.report("A", rep(0.0, cov_position_velocity=0.05, cov_velocity_position=0.05)) == ""
    assert zc.report("A", rep(0.1, cov_position_velocity=0.05)) == Z.NOT_POSITIVE_DEFINITE
    assert zc.report("A", rep(0.2, cov_position_velocity=0.2, cov_velocity_position=0.2)) == \
        Z.NOT_POSITIVE_DEFINITE  # 0.04 > 1.0 * 0.01
    assert zc.report("A", rep(0.3, integrity=3)) == Z.UNKNOWN_INTEGRITY
    assert zc.report("A", rep(0.4, var_velocity=0.0)) == Z.NON_POSITIVE_VARIANCE
    # ground truth (exact) may state zero variances
    assert zc.report("A", rep(0.5, var_velocity=0.0, var_position=0.0, exact=True)) == ""


@pytest.mark.parametrize("v", [1e9, -1e9, -151.0])
def test_a_speed_no_train_runs_is_refused(v):
    """A large negative speed would be a train at rest in the worst-case stop (max(v, 0)):
    refused, and the last good report stays in force."""
    zc = ZoneController(P)
    good = rep(0.0, v=20.0)
    assert zc.report("A", good) == ""
    assert zc.report("A", rep(0.1, v=v)) == Z.IMPLAUSIBLE_SPEED
    assert zc.reports["A"] is good
    assert zc.report("A", rep(0.2, v=Z.MAX_SPEED)) == ""  # the fastest plausible is accepted


@pytest.mark.parametrize("check_stamp_age", [True, False])
@pytest.mark.parametrize("ahead", [1.5, 60.0, 1e6, 1e9])
def test_far_future_stamp_is_refused_without_poisoning_later_reports(check_stamp_age, ahead):
    zc = ZoneController(replace(P, check_stamp_age=check_stamp_age))
    assert zc.report("A", rep(0.0)) == ""
    bad = rep(0.1)
    bad.stamp += ahead
    assert zc.report("A", bad) == Z.FUTURE_STAMP
    for k in range(2, 100):
        assert zc.report("A", rep(0.1 * k)) == "", k
        assert granted(zc, 0.1 * k + LATENCY)[0]
    assert zc.rejected == {Z.FUTURE_STAMP: 1}


def test_future_stamp_on_separate_clocks_is_judged_against_the_drifting_timeline():
    """A train clock slow by the stated max_clock_drift for an hour: its timeline moves 3.6 s
    back, and the zone's follows it; a report stamped 3.5 s ahead of it is refused (the
    timeline is not the all-time maximum), one on it accepted."""
    d = P.max_clock_drift
    zc = ZoneController(replace(P, check_stamp_age=False))
    for k in range(36000):
        t = 0.1 * k
        assert zc.report("A", rep(t, clock=-d * t)) == ""
    bad = rep(3600.0, clock=-d * 3600.0 + 3.5)
    assert zc.report("A", bad) == Z.FUTURE_STAMP
    assert zc.report("A", rep(3600.1, clock=-d * 3600.1)) == ""


def test_a_latency_that_rises_and_stays_is_carried_into_the_age_on_separate_clocks():
    """The link's latency rises by 3 s and stays (a slower route), the train's clock separate
    from the zone's: the two read alike, and the zone keeps the latency. Five minutes later a
    report's worst-case stop is still carried over those 3 s of running (a 60 s window of
    least latency took them for the clock's offset after a minute: fronts 3 s x v short)."""
    zc = ZoneController(replace(P, check_stamp_age=False))
    v = 10.0
    for k in range(3000):  # 300 s at 10 Hz, the last 240 s 3 s later
        t = 0.1 * k
        late = 3.0 if t >= 60.0 else 0.0
        r = rep(t, v=v)
        r.t_received += late
        assert zc.report("A", r) == ""
    now = r.t_received
    front, _, speed, _, _ = zc._bounds(r)
    # the report's sample was 3 s more than the least latency before its arrival: carried at
    # least that far, less the drift the zone allows the clocks since the last report on the
    # quick route (243 s); the 60 s window carried 0 s
    allowed = P.max_clock_drift * (now - (60.0 + LATENCY - 0.1))
    assert zc._age("A", r, now) >= 3.0 - allowed - 1e-9
    assert zc.worst_stop("A", r, now) >= front + speed * (3.0 - allowed) - 1e-9


def test_a_stream_of_future_stamps_is_never_followed_on_one_clock():
    zc = ZoneController(P)  # check_stamp_age: zone and estimates on one clock
    assert zc.report("A", rep(0.0)) == ""
    for k in range(1, 50):
        assert zc.report("A", rep(0.1 * k, clock=60.0)) == Z.FUTURE_STAMP
    assert zc.clock_resets == {}
    assert zc.report("A", rep(5.0)) == ""


def run_reset(zc, jump, n=400, dt=0.1):
    """n reports, the estimator's clock jumping by ``jump`` s after the first quarter; returns
    (refused, braked) counted over the reports after the jump."""
    refused = braked = 0
    for k in range(n):
        t = dt * k
        clock = jump if k >= n // 4 else 0.0
        r = rep(t, clock=clock)
        kind = zc.report("A", r)
        ok, _ = granted(zc, t + LATENCY)
        if k >= n // 4:
            refused += bool(kind)
            braked += not ok
    return refused, braked


@pytest.mark.parametrize("jump", [-3600.0, -60.0, -2.0, 3600.0])
def test_clock_reset_is_followed_on_separate_clocks(jump):
    """Estimates on the estimator's own clock (check_stamp_age false): a reset is followed after
    reset_reports consistent reports; the authority is kept meanwhile (the last accepted report
    is fresh by its arrival for stale_timeout)."""
    zc = ZoneController(replace(P, check_stamp_age=False))
    refused, braked = run_reset(zc, jump)
    assert refused == P.reset_reports - 1
    assert braked == 0
    assert zc.clock_resets == {"A": 1}


@pytest.mark.parametrize("jump", [-1.0, -60.0, -1000.0])
def test_clock_reset_is_followed_on_one_clock(jump):
    """On one clock a reset back is followed after reset_reports reports, and the stamps of the
    new timeline are then judged on it: no brake while its reports keep coming (an estimator's
    legitimate reset braked the train for good), stale once they stop."""
    zc = ZoneController(P)
    refused, braked = run_reset(zc, jump)
    assert refused == P.reset_reports - 1 and zc.clock_resets == {"A": 1}
    assert braked <= P.reset_reports  # the reports refused meanwhile (brake only while judged)
    ok, a = granted(zc, 39.9 + LATENCY)
    assert ok and a.state == "ok"
    ok, a = granted(zc, 39.9 + P.stale_timeout + 1.0)
    assert not ok and a.state == "stale"


def test_interleaved_outliers_do_not_make_a_new_timeline():
    """Reports 60 s behind, each followed by a good one: never a run, never followed."""
    zc = ZoneController(replace(P, check_stamp_age=False))
    for k in range(200):
        assert zc.report("A", rep(0.1 * k)) == ""
        assert zc.report("A", rep(0.1 * k + 0.05, clock=-60.0)) == Z.OUT_OF_ORDER
    assert zc.clock_resets == {}


def test_integrity_alarm_brakes_at_once_and_the_train_behind():
    zc = ZoneController(P)
    zc.report("A", rep(0.0, x=3000.0))
    zc.report("B", rep(0.0, x=1000.0))
    zc.report("A", rep(0.1, x=3000.0, integrity=Z.ALARM))
    auth = {a.train_id: a for a in zc.authorities(0.1 + LATENCY, ["A", "B"])}
    assert auth["A"].emergency_brake and auth["A"].state == "alarm"
    assert auth["B"].emergency_brake and auth["B"].state == "ahead_alarm"
    zc.report("A", rep(0.2, x=3000.0))
    auth = {a.train_id: a for a in zc.authorities(0.2 + LATENCY, ["A", "B"])}
    assert not auth["A"].emergency_brake and not auth["B"].emergency_brake


def test_degraded_is_bounded_by_its_protection_levels_and_never_brakes_by_itself():
    """DEGRADED is bounded (its protection levels exceed the alert limit): the authority uses the
    interval as it is, for as long as it lasts; a wide interval of the leader shortens the
    follower's authority by exactly its width."""
    zc = ZoneController(P)
    zc.report("A", rep(0.0, x=3000.0))
    zc.report("B", rep(0.0, x=1000.0))
    for k in range(100):  # 10 s DEGRADED with a 60 m interval behind
        t = 1.0 + 0.1 * k
        zc.report("A", rep(t, x=3000.0, integrity=Z.DEGRADED, pl_behind=60.0, pl_ahead=60.0))
        zc.report("B", rep(t, x=1000.0))
        auth = {a.train_id: a for a in zc.authorities(t + LATENCY, ["A", "B"])}
        assert not auth["A"].emergency_brake, auth["A"].reason
    lead = zc.reports["A"]
    assert auth["B"].end_of_authority == lead.position - 60.0 - P.train_length - P.margin


def test_implausible_reports_are_refused_and_the_train_keeps_its_last_plausible_one():
    """A report off the line, one that jumps further than a train can run, one that puts the
    follower past the leader, a braking rate of 1e6 and a speed of -149 m/s are refused by
    name; the follower's authority never passes the leader's last plausible rear."""
    zc = ZoneController(replace(P, line_length=10000.0))
    assert zc.report("A", rep(0.0, x=3000.0, v=0.0)) == ""
    assert zc.report("B", rep(0.0, x=1000.0, v=0.0)) == ""
    bad = {
        Z.OFF_LINE: rep(0.1, x=1e12, v=0.0),
        Z.JUMP: rep(0.1, x=3200.0, v=0.0),  # 200 m in 0.1 s
        Z.IMPLAUSIBLE_BRAKING: rep(0.1, x=3000.0, v=0.0, braking_rate=1e6,
                                   var_braking_rate=1e-4),
        Z.IMPLAUSIBLE_SPEED: rep(0.1, x=3000.0, v=-149.0),
    }
    for kind, r in bad.items():
        assert zc.report("A", r) == kind, zc.last_refusal
    assert zc.report("A", rep(0.1, x=-1e9, v=0.0)) == Z.OFF_LINE
    # the follower reported just past the leader (within what it could run: not a jump)
    assert zc.report("B", rep(30.0, x=3010.0, v=0.0)) == Z.ORDER
    assert zc.reports["A"].position == 3000.0 and zc.reports["B"].position == 1000.0
    auth = {a.train_id: a for a in zc.authorities(0.1 + LATENCY, ["A", "B"])}
    assert auth["B"].end_of_authority <= 3000.0 - 5.3 - P.train_length - P.margin
    assert zc.rejected[Z.OFF_LINE] == 2 and zc.rejected[Z.ORDER] == 1


def test_refusals_are_logged_once_per_kind_per_interval():
    log = RefusalLog(interval=5.0)
    logged = [(t, log.note("A", Z.NON_FINITE, t)) for t in np.arange(0.0, 12.0, 0.01)]
    logged = [(t, n) for t, n in logged if n]
    assert [n for _, n in logged] == [1, 500, 500]
    assert log.note("A", Z.FUTURE_STAMP, 12.0) == 1  # another kind: its own interval
    assert log.note("B", Z.NON_FINITE, 12.0) == 1  # another train too


@pytest.mark.parametrize("check_stamp_age", [True, False])
@pytest.mark.parametrize("seed", [0, 1])
def test_fuzz_no_exception_no_lock_refusals_counted_by_kind(check_stamp_age, seed):
    rng = np.random.default_rng(seed)
    clean = []
    x, v = 100.0, 0.0
    for k in range(600):  # 60 s at 10 Hz: accelerating, then cruising
        t = 0.1 * k
        v = min(v + 0.05, 15.0)
        x += 0.1 * v
        clean.append(TrainReport(t_received=t + LATENCY, stamp=t, position=x, velocity=v,
                                 var_position=1.0 + 0.01 * k, var_velocity=0.01,
                                 cov_position_velocity=0.02, cov_velocity_position=0.02,
                                 pl_ahead=5.3 * math.sqrt(1.0 + 0.01 * k),
                                 pl_behind=5.3 * math.sqrt(1.0 + 0.01 * k)))
    stream, counts = corrupt_reports(clean, rng, per_report=5.0)
    assert sum(counts.values()) > 2500 and set(counts) == set(EXPECTED)
    zc = ZoneController(replace(P, check_stamp_age=check_stamp_age))
    refused = Counter()
    for kind, r in stream:
        got = zc.report("A", r)
        if kind:
            refused[kind] += 1
            assert got == EXPECTED[kind], (kind, got, r)
        else:
            assert got == "", (got, zc.last_refusal)  # no corruption poisoned a good report
            assert granted(zc, r.t_received)[0]
    want = Counter()
    for kind, n in counts.items():
        want[EXPECTED[kind]] += n
    assert zc.rejected == dict(want)
    assert zc.clock_resets == {}
    # after the garbage, a good report is granted authority
    last = clean[-1]
    assert zc.report("A", replace(last, stamp=last.stamp + 0.1,
                                  t_received=last.t_received + 0.1)) == ""
    assert granted(zc, last.t_received + 0.1)[0]


def test_main_job_summary_reads_the_brake_reasons_the_node_logs(tmp_path):
    """The demo's summary lists the reasons from the zone controller's log lines as the node
    writes them ("emergency brake SET (state): reason")."""
    from train_bringup.main_job import brake_reasons

    log = tmp_path / "zone_controller.log"
    log.write_text("[WARN] [1.5] [zone_controller]: /train: emergency brake SET (stale): "
                   "estimates stale: none received for 3.2 s (> 3.0 s)\n"
                   "[WARN] [9.0] [zone_controller]: /train: emergency brake SET (alarm): "
                   "estimator integrity ALARM (it cannot bound its error)\n")
    assert brake_reasons(log) == ["estimates stale: none received for # s (> # s)",
                                  "estimator integrity ALARM (it cannot bound its error)"]


@pytest.mark.parametrize("age", [0.5, 1.9])
def test_the_worst_stop_covers_a_train_that_accelerated_since_its_report(age):
    """A report of a train at 5 m/s, ``age`` s old on the zone's clock (within stale_timeout),
    while the train pulled away at max_acceleration since: its true stop (at the nominal
    emergency braking) lies within the zone's worst stop. Carried at the stated speed alone,
    the stop fell short by the speed gained (a route 3 s slower on metro_demo: 1-7 m)."""
    zc = ZoneController(P)
    r = rep(0.0, x=1000.0, v=5.0)
    assert zc.report("A", r) == ""
    a = P.max_acceleration
    x_true = r.position + r.pl_ahead + 5.0 * age + 0.5 * a * age * age
    v_true = 5.0 + a * age
    true_stop = x_true + v_true * v_true / (2.0 * P.emergency_decel)
    assert zc.worst_stop("A", zc.reports["A"], age) >= true_stop


def _r(stamp, x, v=0.0, arrive=None, pl=5.0, **kw):
    kw = {"var_position": 1.0, "var_velocity": 0.01, **kw}
    return TrainReport(t_received=stamp + LATENCY if arrive is None else arrive, stamp=stamp,
                       position=x, velocity=v, pl_ahead=pl, pl_behind=pl, **kw)


def test_a_danger_point_within_the_margin_still_bounds_the_authority():
    """A train 4 m short of the line's end (margin 10 m here): the end is still ahead of it and
    its worst stop passes the end less the margin: braked. The end was dropped once the train
    came within the margin of it, and the train got the open line."""
    zc = ZoneController(P)
    assert zc.report("A", _r(0.0, 49996.0, v=15.0)) == ""
    (a,) = zc.authorities(0.1, ["A"])
    assert a.end_of_authority == 50000.0 - P.margin and a.emergency_brake
    assert a.state == "overrun"


@pytest.mark.parametrize("lead_at, follow_at", [(940.0, 950.0), (940.0, 940.0)])
def test_trains_whose_intervals_allow_either_order_each_keep_behind_the_other(lead_at,
                                                                             follow_at):
    """The leader's front truly at 1000 m, the follower's at 895 m (5 m behind the leader's
    rear), both DEGRADED with levels of 100 m that hold the truth, the follower's estimate at
    or ahead of the leader's. Ordered by the point estimates, the follower was taken for the
    leader and given the open line. While the intervals allow either order, each train's
    authority ends at the other's min safe rear: neither is granted past the other."""
    zc = ZoneController(P)
    assert zc.report("lead", _r(10.0, lead_at, pl=100.0, integrity=Z.DEGRADED)) == ""
    assert zc.report("follow", _r(10.0, follow_at, pl=100.0, integrity=Z.DEGRADED)) == ""
    auth = {a.train_id: a for a in zc.authorities(10.1, ["lead", "follow"])}
    true_rear = 1000.0 - P.train_length
    assert auth["follow"].emergency_brake or auth["follow"].end_of_authority <= true_rear
    assert auth["follow"].end_of_authority <= lead_at - 100.0 - P.train_length - P.margin
    assert auth["lead"].end_of_authority <= follow_at - 100.0 - P.train_length - P.margin


def test_trains_apart_by_more_than_their_intervals_keep_their_order():
    """Tight intervals 500 m apart: the train behind is no hazard to the one ahead."""
    zc = ZoneController(P)
    zc.report("A", _r(0.0, 3000.0))
    zc.report("B", _r(0.0, 2500.0))
    auth = {a.train_id: a for a in zc.authorities(0.1, ["A", "B"])}
    assert auth["A"].end_of_authority == 50000.0 - P.margin and not auth["A"].emergency_brake
    assert auth["B"].end_of_authority < 3000.0 - P.train_length


def test_a_zone_clock_that_goes_back_makes_every_report_stale():
    """The zone's clock steps back 100 s 0.5 s after a train's last report (a /clock that
    restarted, a bag played again): the report's age cannot be known on it, so the train is
    braked at once; it was braked only after 103 s, its age negative meanwhile."""
    for csa in (True, False):
        zc = ZoneController(replace(P, check_stamp_age=csa))
        for i in range(100):
            t = 1000.0 + 0.1 * i
            assert zc.report("A", _r(t, 1000.0 + 20.0 * t, v=20.0)) == ""
        assert granted(zc, 1010.0)[0]
        ok, a = granted(zc, 910.5)
        assert not ok and a.state == "stale" and "went back" in a.reason


def test_a_followed_clock_reset_keeps_the_age_of_the_last_measurement():
    """An estimator that predicts without measurements from 5 s on, its clock reset by -3,600 s
    at 8 s (separate clocks, followed after reset_reports reports): still braked
    measurement_timeout after its last measurement (never, when the reset forgot it)."""
    zc = ZoneController(replace(P, check_stamp_age=False, stale_timeout=3.0))
    first = None
    for i in range(300):
        t = 0.1 * i
        stamp = t - (3600.0 if t >= 8.0 else 0.0)
        zc.report("A", _r(stamp, 1000.0 + 10.0 * t, v=10.0, arrive=t + LATENCY,
                          measurement_used=t < 5.0))
        ok, _ = granted(zc, t + LATENCY)
        if not ok and first is None and t >= 5.0:
            first = t
    assert zc.clock_resets == {"A": 1}
    assert first is not None and first <= 4.9 + P.measurement_timeout + 0.3, first


def test_a_replayed_burst_of_old_reports_is_no_clock_reset():
    """A follower at 20 m/s, then five of its reports of a minute before delivered at once (each
    stamped behind the last: out of order). They put the train 1.2 km behind where it was a
    moment ago, farther than a train reverses in that time: refused as implausible, never
    followed as the estimator's clock reset (it was, and the old position stood as fresh)."""
    for csa in (True, False):
        zc = ZoneController(replace(P, check_stamp_age=csa, stale_timeout=3.0))
        for i in range(1000):
            t = 0.1 * i
            assert zc.report("F", _r(t, 750.0 + 20.0 * t, v=20.0)) == ""
        for j in range(5):
            s = 40.0 + 0.1 * j
            assert zc.report("F", _r(s, 750.0 + 20.0 * s, v=20.0, arrive=99.96 + 0.001 * j)) \
                == Z.JUMP
        assert zc.clock_resets == {} and zc.reports["F"].stamp == pytest.approx(99.9)


def test_a_reversing_leaders_rear_is_carried_back_over_its_age():
    """A leader backing at 1 m/s, stating it (-1 +- 0.1 m/s), checked 2.9 s after its report,
    margin 0: the follower's authority ends at its min safe rear carried back over those 2.9 s
    at the report's worst reverse speed (K of its standard deviations past it); uncarried, it
    lay 2.4 m past the leader's true rear."""
    zc = ZoneController(replace(P, margin=0.0, stale_timeout=3.0))
    assert zc.report("L", _r(10.0, 3000.0, v=-1.0, pl=1.0)) == ""
    assert zc.report("F", _r(10.0, 2000.0)) == ""
    auth = {a.train_id: a for a in zc.authorities(12.9, ["L", "F"])}
    true_rear = 3000.0 - 1.0 * (12.9 - 10.0) - P.train_length
    assert auth["F"].end_of_authority < true_rear


@pytest.mark.parametrize("where", ["_plausible", "worst_stop"])
def test_a_zone_that_fails_brakes_every_train_and_reads_nothing_more(where):
    """The node's setting (fail_safe): an exception inside the zone controller (a defect)
    never ends the node; every train is braked from then on, every report refused by name.
    Without it (offline, tests) the exception propagates."""
    def broken(*_a, **_k):
        raise ZeroDivisionError("injected defect")

    for safe in (False, True):
        zc = ZoneController(P, fail_safe=safe)
        assert zc.report("A", rep(0.0)) == "" and zc.report("B", rep(0.0, x=3000.0)) == ""
        assert granted(zc, 0.1, "A")[0] and zc.failure is None
        setattr(zc, where, broken)
        if not safe:
            with pytest.raises(ZeroDivisionError):
                zc.report("A", rep(0.2)) if where == "_plausible" else \
                    zc.authorities(0.2, ["A", "B"])
            continue
        first = zc.report("A", rep(0.2))
        auths = zc.authorities(0.3, ["A", "B"])
        call = "report" if where == "_plausible" else "authorities"
        assert zc.failure == f"{call}: ZeroDivisionError: injected defect"
        assert "injected defect" in zc.failure_trace
        assert first == (Z.FAILED if where == "_plausible" else "")
        assert [(a.train_id, a.emergency_brake, a.end_of_authority, a.permitted_speed,
                 a.state) for a in auths] == [("A", True, -math.inf, 0.0, "failed"),
                                              ("B", True, -math.inf, 0.0, "failed")]
        # latched: a good report is refused, the brakes stay set
        assert zc.report("B", rep(0.4, x=3000.0)) == Z.FAILED
        assert all(a.emergency_brake for a in zc.authorities(0.5, ["A", "B"]))
        assert zc.rejected[Z.FAILED] == (2 if where == "_plausible" else 1)
