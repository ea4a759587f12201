"""Zone-controller logic against hand-computed authorities."""

import math
from statistics import NormalDist

from train_sim.zone import TrainReport, ZoneController, ZoneParams


def rep(t, x, v, var_x=1.0, var_v=0.01, f=math.nan, var_f=math.nan):
    """A report whose protection levels are 3 sigma of ``var_x`` (hand-computed figures)."""
    pl = 3.0 * math.sqrt(var_x)
    return TrainReport(t_received=t, stamp=t, position=x, velocity=v, var_position=var_x,
                       var_velocity=var_v, braking_rate=f, var_braking_rate=var_f,
                       pl_ahead=pl, pl_behind=pl)


THREE_SIGMA = 2.0 * (1.0 - NormalDist().cdf(3.0))  # the risk whose multiplier K is 3
P = ZoneParams(integrity_risk=THREE_SIGMA, stale_timeout=2.0, emergency_decel=1.0,
               train_length=100.0, margin=10.0, danger_points=(5000.0,))


def test_follower_authority_ends_behind_leader_worst_case_rear():
    zc = ZoneController(P)
    zc.report("A", rep(0.0, 2000.0, 10.0, var_x=4.0))  # sigma 2 m -> worst rear 2000-6-100
    zc.report("B", rep(0.0, 1000.0, 10.0))
    auth = {a.train_id: a for a in zc.authorities(0.5, ["A", "B"])}
    assert auth["B"].end_of_authority == 2000.0 - 6.0 - 100.0 - 10.0
    assert auth["A"].end_of_authority == 5000.0 - 10.0
    assert not auth["A"].emergency_brake and not auth["B"].emergency_brake


def test_emergency_brake_when_worst_case_stop_passes_eoa():
    zc = ZoneController(P)
    # front worst case 4900 + 3; speed worst case 20 + 0.3: d = 20.3^2 / 2 = 206 m > 4990 - 4903
    zc.report("A", rep(0.0, 4900.0, 20.0))
    (a,) = zc.authorities(0.1, ["A"])
    assert a.emergency_brake and "passes EoA" in a.reason
    zc2 = ZoneController(P)
    zc2.report("A", rep(0.0, 4000.0, 20.0))  # 4003 + 206 < 4990
    assert not zc2.authorities(0.1, ["A"])[0].emergency_brake


def test_estimated_braking_rate_lengthens_the_braking_distance():
    zc = ZoneController(P)
    zc.report("A", rep(0.0, 4700.0, 20.0))  # nominal: 4703 + 206 = 4909 < 4990
    assert not zc.authorities(0.1, ["A"])[0].emergency_brake
    zc.report("A", rep(0.1, 4700.0, 20.0, f=0.6, var_f=1e-4))  # f_low 0.57: 361 m
    assert zc.authorities(0.2, ["A"])[0].emergency_brake


def test_stale_train_and_the_train_behind_it_are_braked():
    zc = ZoneController(P)
    zc.report("A", rep(0.0, 3000.0, 10.0))
    zc.report("B", rep(0.0, 1000.0, 10.0))
    zc.report("B", rep(2.5, 1025.0, 10.0))
    auth = {a.train_id: a for a in zc.authorities(2.6, ["A", "B"])}
    assert auth["A"].emergency_brake and "stale" in auth["A"].reason
    assert auth["B"].emergency_brake and "train ahead" in auth["B"].reason


def test_bad_reports_are_rejected_and_counted():
    zc = ZoneController(P)
    assert zc.report("A", rep(0.0, math.nan, 1.0)) != ""
    assert zc.report("A", rep(1.0, 10.0, 1.0)) == ""
    assert zc.report("A", rep(0.5, 11.0, 1.0)) == "out-of-order stamp"
    assert zc.reports["A"].position == 10.0
    assert sum(zc.rejected.values()) == 2


def test_no_authority_while_another_train_is_not_localised():
    zc = ZoneController(P)
    zc.report("B", rep(0.0, 1000.0, 10.0))
    (a,) = zc.authorities(0.5, ["B"])
    assert not a.emergency_brake
    auth = {x.train_id: x for x in zc.authorities(0.5, ["A", "B"])}
    assert auth["B"].emergency_brake and "unknown" in auth["B"].reason
    assert auth["A"].emergency_brake


def test_predictions_without_measurements_become_stale_by_their_own_stamps():
    """An estimator that keeps publishing predictions (fresh arrivals) is stale all the same."""
    zc = ZoneController(P)  # stale_timeout 2 s, measurement_timeout 10 s (default)
    zc.report("A", rep(0.0, 1000.0, 10.0))
    t = 0.0
    for k in range(1, 120):  # 11.9 s of predictions, each arriving fresh
        t = 0.1 * k
        r = rep(t, 1000.0 + 10 * t, 10.0)
        r.measurement_used = False
        assert zc.report("A", r) == ""
        (a,) = zc.authorities(t, ["A"])
        assert a.emergency_brake == (t > 10.0 + 1e-9), t
    assert a.state == "stale" and "no measurement" in a.reason
    # a fresh measurement releases it
    zc.report("A", rep(t + 0.1, 1000.0 + 10 * t, 10.0))
    assert not zc.authorities(t + 0.1, ["A"])[0].emergency_brake


def test_old_stamp_is_stale_even_when_it_just_arrived():
    zc = ZoneController(P)
    r = TrainReport(t_received=5.0, stamp=2.5, position=1000.0, velocity=0.0, var_position=1.0,
                    var_velocity=0.01)
    zc.report("A", r)
    (a,) = zc.authorities(5.0, ["A"])
    assert a.emergency_brake and a.state == "stale" and "stamped" in a.reason


def test_state_is_stable_while_the_reason_text_changes():
    zc = ZoneController(P)
    zc.report("A", rep(0.0, 1000.0, 10.0))
    states, reasons = set(), set()
    for k in range(30, 60):
        (a,) = zc.authorities(0.1 * k, ["A"])
        states.add(a.state)
        reasons.add(a.reason)
    assert states == {"stale"} and len(reasons) > 10


def test_params_file_has_exactly_the_declared_fields_with_their_defaults():
    """zone_controller's parameters are declared once (ZoneParams, ZoneNodeConfig metadata);
    config/zone_controller.yaml documents exactly those, with their defaults."""
    from pathlib import Path

    import yaml
    from train_core.config import param_fields

    from train_sim.zone import ZoneNodeConfig

    path = Path(__file__).resolve().parents[1] / "config" / "zone_controller.yaml"
    params = yaml.safe_load(path.read_text())["/**"]["ros__parameters"]
    from train_core.diagnostics import InputThresholds

    fields = param_fields(ZoneParams) + param_fields(ZoneNodeConfig) + \
        param_fields(InputThresholds)
    assert set(params) == {f.name for f in fields}
    for f in fields:
        want = list(f.default) if isinstance(f.default, tuple) else f.default
        assert params[f.name] == want, f.name


def test_simulator_params_file_has_exactly_the_declared_fields_with_their_defaults():
    """The simulator's parameters are declared once (SimulatorConfig metadata);
    config/simulator.yaml documents exactly those, with their defaults."""
    from pathlib import Path

    import yaml
    from train_core.config import param_fields

    from train_sim.nodes.simulator import SimulatorConfig

    path = Path(__file__).resolve().parents[1] / "config" / "simulator.yaml"
    params = yaml.safe_load(path.read_text())["/**"]["ros__parameters"]
    from train_core.diagnostics import StaleThresholds

    fields = param_fields(SimulatorConfig) + param_fields(StaleThresholds)
    assert set(params) == {f.name for f in fields}
    for f in fields:
        want = list(f.default) if isinstance(f.default, tuple) else f.default
        assert params[f.name] == want, f.name


def test_an_alarm_position_does_not_take_the_leader_off_the_followers_track():
    """A leader in ALARM reporting a position behind its follower (a count that restarted at 0,
    mapped 1.2 km back): its position bounds nothing, so the trains stay in the order their
    bounded reports put them in and the follower brakes; its authority never ends beyond the
    leader's last bounded rear. (Taken as behind, the leader left the follower an open line.)"""
    from train_sim.zone import ALARM, ORDER
    zc = ZoneController(P)
    zc.report("A", rep(0.0, 2000.0, 10.0))
    zc.report("B", rep(0.0, 1000.0, 10.0))
    bad = rep(0.5, -1200.0, 10.0)
    bad = TrainReport(**{**bad.__dict__, "integrity": ALARM, "pl_ahead": math.inf,
                         "pl_behind": math.inf})
    assert zc.report("A", bad) == ""  # accepted: an ALARM bounds nothing, the brake is due
    zc.report("B", rep(0.5, 1005.0, 10.0))
    auth = {a.train_id: a for a in zc.authorities(0.6, ["A", "B"])}
    assert auth["A"].emergency_brake and auth["A"].state == "alarm"
    assert auth["B"].emergency_brake and auth["B"].state == "ahead_alarm", auth["B"]
    assert auth["B"].end_of_authority <= 2000.0 - 3.0 - 100.0 - 10.0
    # the follower's reports are judged against the leader's bounded position, not the ALARM one
    assert zc.report("B", rep(1.0, 1010.0, 10.0)) == ""
    # past the leader's last bounded place (and a plausible run from its last report)
    assert zc.report("B", rep(11.0, 2001.0, 10.0)) == ORDER


def test_a_train_in_alarm_from_its_first_report_may_be_anywhere():
    from train_sim.zone import ALARM
    zc = ZoneController(P)
    zc.report("B", rep(0.0, 1000.0, 10.0))
    first = TrainReport(**{**rep(0.0, 3000.0, 10.0).__dict__, "integrity": ALARM,
                           "pl_ahead": math.inf, "pl_behind": math.inf})
    assert zc.report("A", first) == ""
    auth = {a.train_id: a for a in zc.authorities(0.1, ["A", "B"])}
    assert auth["B"].emergency_brake and auth["B"].state in ("ahead_unknown", "ahead_alarm")


def test_the_max_safe_front_is_carried_to_the_present():
    """A report 1.9 s old (within the stale timeout) states where the train was: by now it may
    be 1.9 s further at its worst-case speed. 4750 m at 20 m/s: 4753 + 206 m of stop is within
    the 4990 m EoA at once, but 1.9 s later the front may be 38.6 m on: the brake is due."""
    zc = ZoneController(P)
    zc.report("A", rep(0.0, 4750.0, 20.0))
    assert not zc.authorities(0.1, ["A"])[0].emergency_brake
    a = zc.authorities(1.9, ["A"])[0]
    assert a.emergency_brake and a.state == "overrun", a
