"""Zone-controller logic against hand-computed authorities."""

import math

from train_sim.zone import TrainReport, ZoneController, ZoneParams


def rep(t, x, v, var_x=1.0, var_v=0.01, f=math.nan, var_f=math.nan):
    return TrainReport(t_received=t, stamp=t, position=x, velocity=v, var_position=var_x,
                       var_velocity=var_v, braking_rate=f, var_braking_rate=var_f)


P = ZoneParams(k_sigma=3.0, stale_timeout=2.0, emergency_decel=1.0, train_length=100.0,
               margin=10.0, danger_points=(5000.0,))


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
