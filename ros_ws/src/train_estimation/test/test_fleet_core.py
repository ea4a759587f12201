"""Fleet consensus core (train_estimation.core.offline.fleet) on exact inputs.

- inverse-variance combination, Cochran's Q, DerSimonian-Laird tau^2 and the weighted trend
  against numbers worked out by hand;
- sections: grouped by overlap; a section found by several trains with agreeing values is a map
  error, by one train only (however often) or by trains that disagree it is not;
- trains: a departing train is flagged and no other; a trending train is flagged; on fleets
  without any fault the family-wise false-alarm rate stays at or below the stated alpha.
"""

import math

import numpy as np
import pytest
from scipy import stats

from train_estimation.core.offline import fleet as F


def test_combine_by_hand():
    # w = 1, 1/4: mean = (1 * 1 + 0.25 * 4) / 1.25 = 1.6, se = 1.25^-1/2,
    # Q = 1 * 0.6^2 + 0.25 * 2.4^2 = 1.8 on 1 df
    c = F.combine([1.0, 4.0], [1.0, 2.0])
    assert c["mean"] == pytest.approx(1.6)
    assert c["se"] == pytest.approx(1 / math.sqrt(1.25))
    assert c["q"] == pytest.approx(1.8)
    assert c["df"] == 1
    assert c["p_consistency"] == pytest.approx(stats.chi2.sf(1.8, 1))
    assert c["z"] == pytest.approx(1.6 * math.sqrt(1.25))
    one = F.combine([3.0], [0.5])
    assert one["mean"] == 3.0 and one["se"] == 0.5 and one["p_consistency"] == 1.0


def test_tau2_and_random_effects_by_hand():
    # x = 0, 2, 4, se = 1: mean 2, Q = 8 on 2 df, S1 = 3, S2 = 3 -> tau^2 = 6 / (3 - 1) = 3
    assert F.tau2_dl([0.0, 2.0, 4.0], [1.0, 1.0, 1.0]) == pytest.approx(3.0)
    assert F.tau2_dl([1.0, 1.1], [1.0, 1.0]) == 0.0  # less scatter than the errors: 0
    r = F.combine_random([0.0, 2.0, 4.0], [1.0, 1.0, 1.0])
    assert r["tau"] == pytest.approx(math.sqrt(3.0))
    assert r["se"] == pytest.approx(math.sqrt(4.0 / 3.0))  # (1 + 3) / 3
    assert r["q"] == pytest.approx(8.0)


def test_weighted_trend_by_hand():
    t = np.array([0.0, 1.0, 2.0, 3.0])
    x = 5.0 - 0.5 * t
    tr = F.weighted_trend(t, x, np.full(4, 0.1))
    assert tr["slope"] == pytest.approx(-0.5)
    # se = 1 / sqrt(sum w (t - t_bar)^2) = 1 / sqrt(100 * 5)
    assert tr["se"] == pytest.approx(1 / math.sqrt(500.0))
    assert F.z_critical(0.01, 1) == pytest.approx(stats.norm.isf(0.005))


def test_group_sections():
    dets = [{"start": 1000, "end": 1400}, {"start": 1050, "end": 1400},
            {"start": 3000, "end": 3300}, {"start": 975, "end": 1425},
            {"start": 1350, "end": 1700}]  # overlaps the first by 50 of 350 m: its own
    groups = F.group_sections(dets, 0.5)
    assert sorted(sorted(g) for g in groups) == [[0, 1, 3], [2], [4]]


def _row(train, line, gradient=None, **params):
    r = {"train": train, "line": line, "time": 0.0, "bag": f"{train}-{line}"}
    if gradient:
        r["gradient"] = dict(zip(("start", "end", "permille", "se"), gradient))
    r.update({k: {"value": v[0], "se": v[1]} for k, v in params.items()})
    return r


def test_map_error_needs_several_agreeing_trains():
    rows = [_row(f"T{i}", "north", (1000 + 10 * i, 1400, 5.0 + 0.3 * (i % 2), 0.6))
            for i in range(4)]
    rows += [_row(f"T{i}", "north") for i in range(4, 8)]  # passed without finding it
    # one train finds the same section on every run of the south line: its fault, not the map's
    rows += [_row("T9", "south", (2000, 2300, -6.0, 0.5)) for _ in range(3)]
    rows += [_row(f"T{i}", "south") for i in range(5)]
    res = F.consensus(rows)
    assert [(m["line"], m["start"], m["end"]) for m in res.map_errors] == \
        [("north", 1015.0, 1400.0)]
    m = res.map_errors[0]
    # 4 detections, se 0.6 each: combined se = 0.3; values 5.0, 5.3, 5.0, 5.3 -> 5.15
    assert m["permille"] == pytest.approx(5.15) and m["se"] == pytest.approx(0.3)
    assert m["trains_found"] == ["T0", "T1", "T2", "T3"] and m["runs_passed"] == 8
    assert m["p_binomial"] == pytest.approx(stats.binom.sf(3, 8, 0.05))
    south = res.lines["south"]["sections"]
    assert len(south) == 1 and south[0]["verdict"] == "single-train or spurious"


def test_disagreeing_trains_are_disputed():
    vals = (5.0, -5.0, 5.0, -5.0)
    rows = [_row(f"T{i}", "north", (1000, 1400, v, 0.5)) for i, v in enumerate(vals)]
    res = F.consensus(rows)
    assert res.map_errors == []
    assert res.lines["north"]["sections"][0]["verdict"] == "disputed"


def _fleet(rng, n_trains=8, runs=4, f_bad=None, trend=None, tau=0.01):
    rows = []
    for i in range(n_trains):
        for k in range(runs):
            f = 1.0 + tau * rng.normal()
            if f_bad is not None and i == 0:
                f = f_bad + tau * rng.normal()
            if trend is not None and i == 1:
                f += trend * k
            se = 0.02
            r = _row(f"T{i}", "north" if k % 2 else "south",
                     braking_rate=(f + se * rng.normal(), se),
                     mass=(288000 * (1 + 0.01 * rng.normal()), 1000.0),
                     odometer_scale=(1 + 3e-4 * rng.normal(), 3e-4))
            r["time"] = 24.0 * k + float(rng.uniform(6, 20))
            rows.append(r)
    return rows


def test_departing_train_flagged_and_no_other():
    res = F.consensus(_fleet(np.random.default_rng(3), f_bad=0.8))
    alerts = {(a["train"], a["parameter"], a["kind"]) for a in res.train_alerts}
    assert alerts == {("T0", "braking_rate", "departs from the fleet")}
    t0 = res.trains["parameters"]["braking_rate"]["trains"]["T0"]
    assert t0["mean"] == pytest.approx(0.8, abs=0.03) and t0["fleet"] == pytest.approx(1.0,
                                                                                        abs=0.02)


def test_trending_train_flagged():
    res = F.consensus(_fleet(np.random.default_rng(4), trend=-0.06, tau=0.005))
    kinds = {(a["train"], a["kind"]) for a in res.train_alerts if a["parameter"] ==
             "braking_rate"}
    assert ("T1", "trends in time") in kinds
    assert {a["train"] for a in res.train_alerts} == {"T1"}


def test_false_alarm_rate_at_most_alpha():
    """200 fleets without any fault: fleets with an alert (any train, parameter or kind)."""
    rng = np.random.default_rng(11)
    n = 200
    hits = sum(bool(F.consensus(_fleet(rng)).train_alerts) for _ in range(n))
    # two families (departure, trend) at alpha = 0.01 each: expected <= 2 %; P(X > 10) for
    # Binomial(200, 0.02) is 0.3 %
    assert hits <= 10, hits


# ------------------------------------------------------------------------------------------------
# Several days, reliability
# ------------------------------------------------------------------------------------------------

def _days(rng, days, trains, runs, found, spurious=0.05, artefact_day=None):
    """Runs on ``north`` over ``days`` days: each finds the section [1000, 1400) +5 per mille
    with probability ``found`` (on ``artefact_day`` only, when given), else a spurious 300 m
    section anywhere with probability ``spurious``."""
    rows = []
    for d in range(days):
        for i in range(trains):
            for k in range(runs):
                r = _row(f"T{i:02d}", "north")
                r.update(day=f"2026-11-{d + 1:02d}", time=24.0 * d + 6 + k,
                         coverage=[100.0, 4300.0])
                p = found if artefact_day in (None, d) else 0.0
                if rng.random() < p:
                    r["gradient"] = {"start": 1000 + 20 * rng.normal(),
                                     "end": 1400 + 20 * rng.normal(),
                                     "permille": 5 + 0.8 * rng.normal(), "se": 0.8}
                elif rng.random() < spurious:
                    s = rng.uniform(0, 4000)
                    r["gradient"] = {"start": s, "end": s + 300, "permille": 3 * rng.normal(),
                                     "se": 1.0}
                rows.append(r)
    return rows


def test_map_error_confirmed_over_days_and_kept_among_spurious_detections():
    # two weeks of 30 trains x 4 runs: the spurious detections that overlap the section
    # would make the values disagree (Cochran's Q) if none were left out
    rows = _days(np.random.default_rng(5), 14, 30, 4, found=0.7)
    # six spurious detections that overlap the section, far from its value
    quiet = [r for r in rows if not r.get("gradient")][::97][:6]
    for r in quiet:
        r["gradient"] = {"start": 1100.0, "end": 1400.0, "permille": -4.0, "se": 0.5}
    found = [r["gradient"] for r in rows if r.get("gradient")
             and F._overlap(r["gradient"]["start"], r["gradient"]["end"], 1000, 1400) >= 0.5]
    assert F.combine([g["permille"] for g in found],
                     [g["se"] for g in found])["p_consistency"] < 0.01  # untrimmed: disputed
    res = F.consensus(rows)
    assert len(res.map_errors) == 1
    m = res.map_errors[0]
    assert abs(m["start"] - 1000) < 30 and abs(m["end"] - 1400) < 30
    assert m["day_status"] == "confirmed on 14 days" and len(m["days"]) == 14
    assert m["ci95"][0] < 5.0 < m["ci95"][1]
    assert 1 <= m["left_out"] <= stats.binom.isf(0.01, m["runs_passed"], 0.05)
    assert res.reliability["lines"]["north"]["reliable"]


def test_one_days_artefact_is_withdrawn_and_one_day_alone_unconfirmed():
    rng = np.random.default_rng(6)
    # found by every train on day 1 only; the next two days' runs pass it and do not find it
    rows = _days(rng, 3, 6, 2, found=0.8, artefact_day=0)
    res = F.consensus(rows)
    assert res.map_errors == []
    sec = max(res.lines["north"]["sections"], key=lambda s: s["runs_found"])
    assert sec["verdict"] == "one day's artefact" and sec["day_status"] == "withdrawn"
    assert sec["top_day"] == "2026-11-01" and sec["p_fewer"] < 0.01
    # day 1 alone: a map error (nothing yet says otherwise)
    day1 = [r for r in rows if r["day"] == "2026-11-01"]
    res1 = F.consensus(day1)
    assert len(res1.map_errors) == 1 and "day_status" not in res1.map_errors[0]


def test_runs_needed_and_unreliable_consensus():
    cfg = F.FleetConfig()
    n = F.runs_needed(cfg)
    # the rule by hand: the binomial test's critical count k at n runs, and the power to reach
    # it when a map error is found in half of the runs
    k = next(k for k in range(n + 1) if stats.binom.sf(k - 1, n, 0.05) < 0.01)
    assert stats.binom.sf(k - 1, n, 0.5) >= 0.9
    km = next(k for k in range(n) if stats.binom.sf(k - 1, n - 1, 0.05) < 0.01)
    assert stats.binom.sf(km - 1, n - 1, 0.5) < 0.9
    # every bag but two failed: "no map error" must not read as a clean line
    rows = [dict(_row(f"T{i}", "north"), error="ModuleNotFoundError: x") for i in range(20)]
    rows += [_row("T0", "north", braking_rate=(1.0, 0.02)),
             _row("T1", "north", braking_rate=(1.0, 0.02))]
    res = F.consensus(rows)
    rel = res.reliability
    assert not rel["reliable"] and rel["lines"]["north"] == {
        "runs": 22, "analysed": 2, "failed": 20, "trains": 2, "reliable": False}
    assert any(r.startswith("line north: 2 of 22 runs analysed") for r in rel["reasons"])
    assert any(r.startswith("braking_rate: values of 2 trains") for r in rel["reasons"])


def test_speed_test_by_hand():
    """x = a (a map error at any speed) against x = b v2 (a drag growing as v^2): each model's
    weighted residual sum of squares on k - 1 degrees of freedom."""
    x, se, v2 = [2.0, 4.0, 6.0], [0.5, 0.5, 0.5], [100.0, 200.0, 300.0]
    t = F.speed_test(x, se, v2, 0.01)
    w = 4.0  # 1 / 0.5^2
    b = sum(w * xi * ui for xi, ui in zip(x, v2)) / sum(w * ui * ui for ui in v2)  # 0.02
    assert t["permille_per_v2"] == pytest.approx(b) and t["permille_at_any_speed"] == 4.0
    assert t["p_place"] == pytest.approx(stats.chi2.sf(w * (4 + 0 + 4), 2))
    assert t["p_speed"] == pytest.approx(1.0) and t["decided"] == "speed"
    # the passes that decided it: the fewest whose misfit under the model rejected reaches the
    # bar chi2(2).isf(0.01) = 9.21 on its own: here the slowest pass's (w (2 - 4)^2 = 16; the
    # fastest's is as large, and the first of equals is taken)
    assert t["decided_by"] == [0]
    t = F.speed_test([4.0, 4.2, 3.9], se, v2, 0.01)
    assert t["decided"] == "place"
    # under x = b v2 (b = 2410 / 140000) the misfits are w (x - b v2)^2 = 20.8, 2.3 and 6.3:
    # the slowest pass, where a drag would be a third of the fastest's, reaches the bar alone
    assert t["decided_by"] == [0]
    x4, u4 = np.array([4.0, 4.2, 3.9, 4.1]), np.array([1.0, 100.0, 200.0, 300.0])
    r = 4.0 * (x4 - np.sum(x4 * u4) / np.sum(u4 * u4) * u4) ** 2  # 63.4, 24.2, 0.7, 5.0
    t = F.speed_test(x4, [0.5] * 4, u4, stats.chi2.sf(75.0, 3))  # the bar at 75
    assert t["decided"] == "place" and r.max() < 75.0 < r[0] + r[1]
    # no pass alone reaches that bar: the largest misfits, the least speed first, until they do
    assert t["decided_by"] == [0, 1]
    assert "decided_by" not in F.speed_test([4.0, 4.1, 3.9], se, [400.0, 401.0, 399.0], 0.01)
    # passes at one speed: both fit; the speeds that would tell part the models by 3 se
    t = F.speed_test([4.0, 4.1, 3.9], se, [400.0, 401.0, 399.0], 0.01)
    assert t["decided"] == "either"
    lo, hi = sorted(((4.0 - 1.5) / t["permille_per_v2"], (4.0 + 1.5) / t["permille_per_v2"]))
    assert t["would_tell"]["below_m_s"] == pytest.approx(math.sqrt(lo))
    assert t["would_tell"]["above_m_s"] == pytest.approx(math.sqrt(hi))
    assert F.speed_test([4.0], [0.5], [100.0], 0.01) is None  # one pass cannot tell
    assert F.speed_test(x, se, [math.nan] * 3, 0.01) is None  # no speeds (an older row)


def test_a_section_whose_gradient_grows_as_the_passes_speed_squared_is_no_map_error():
    """Four trains find a section at 30-80 km/h; its gradient grows with the pass's speed
    squared (a tunnel's drag, 0.03 per mille per m^2/s^2): not a map error. The same section
    found at the same permille at every speed is one, and says it is the same at any speed."""
    speeds = np.array([8.3, 12.0, 16.7, 22.2])
    tunnel = [_row(f"T{i}", "north", (1000, 1400, 0.03 * v * v, 0.5))
              for i, v in enumerate(speeds)]
    flat = [_row(f"T{i}", "north", (1000, 1400, 9.0 + 0.2 * (i % 2), 0.5))
            for i, v in enumerate(speeds)]
    for rows, v in ((tunnel, speeds), (flat, speeds)):
        for r, vi in zip(rows, v):
            r["gradient"]["v2"] = vi * vi
    res = F.consensus(tunnel)
    s = res.lines["north"]["sections"][0]
    assert res.map_errors == [] and s["verdict"] == "drag growing with speed (a tunnel)"
    assert s["speed_test"]["decided"] == "speed"
    # and names the passes that decided it (the report prints them: tools/fleet_report.py)
    by = s["speed_test"]["decided_by"]
    assert by and all(d["train"] in {"T0", "T1", "T2", "T3"} for d in by)
    assert all(d["v_m_s"] == pytest.approx(speeds[int(d["train"][1])]) for d in by)
    res = F.consensus(flat)
    assert [m["verdict"] for m in res.map_errors] == ["map error"]
    assert res.map_errors[0]["speed_test"]["decided"] == "place"
    assert res.map_errors[0]["speed_test"]["decided_by"]
