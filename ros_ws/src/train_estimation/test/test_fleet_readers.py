"""The fleet's balise readers (core.offline.fleet_readers): a train's passes pooled.

Each run's innovations are drawn as diagnose leaves them (whitened by the stated SD, the
origin fitted: covariance I - c c^T / I_s0), 6-16 readings a run as on real bags. A reader whose
error varies slowly is found over its passes where no single pass finds it; readers as stated
are not; lag-1 products never cross two runs; and rows without usable innovations are left
out, not fatal.
"""

import numpy as np

from train_estimation.core.offline.fleet import FleetConfig, consensus
from train_estimation.core.offline.fleet_readers import MAX_READINGS, reader_consensus


def _run(rng, n, rho=0.0):
    """One run's innovations: a reader error AR(1) ``rho`` from one reading to the next (the
    stated SD as its marginal SD); the origin fitted."""
    c = rng.uniform(0.3, 1.0, n)
    info = float(c @ c) + rng.uniform(0.0, 2.0)
    e = np.empty(n)
    e[0] = rng.standard_normal()
    for k in range(1, n):
        e[k] = rho * e[k - 1] + np.sqrt(1 - rho * rho) * rng.standard_normal()
    z = e - c * (float(c @ e) + np.sqrt(info - float(c @ c)) * rng.standard_normal()) / info
    return {"z": z.tolist(), "c": c.tolist(), "info": info,
            "speed": rng.uniform(5.0, 25.0, n).tolist(),
            "position": np.sort(rng.uniform(0.0, 6000.0, n)).tolist()}


def _rows(rng, train, runs, rho):
    return [{"train": train, "line": "L", "time": float(k), "balise": _run(
        rng, int(rng.integers(6, 17)), rho)} for k in range(runs)]


def test_a_slowly_varying_reader_is_found_over_its_passes():
    """A reader with correlation 0.9 from one reading to the next: over its latest passes (up
    to MAX_READINGS readings of 30 passes) found as a correlation in time; two readers as stated
    beside it: no alert. (On simulated bags one pass finds no such reader:
    docs/benchmarks.md.)"""
    rng = np.random.default_rng(3)
    rows = _rows(rng, "T1", 30, 0.9) + _rows(rng, "T2", 30, 0.0) + _rows(rng, "T3", 30, 0.0)
    res = reader_consensus(rows, 0.01)
    assert [a["train"] for a in res["alerts"]] == ["T1"], res["alerts"]
    t1 = res["trains"]["T1"]
    assert t1["correlation"]["finding"] and t1["correlation"]["lag1"] > 0.2
    # the latest runs, as many as fit in MAX_READINGS
    sizes = [len(r["balise"]["z"]) for r in rows[:30]]
    assert t1["readings"] == sum(sizes[30 - t1["runs"]:]) <= MAX_READINGS
    assert t1["readings"] + sizes[29 - t1["runs"]] > MAX_READINGS
    assert "correlated from one reading to the next" in res["alerts"][0]["signature"]


def test_readers_as_stated_hold_the_fleets_false_alarm_rate():
    """40 fleets of three trains with 20 passes each, readers as stated, alpha 0.01 over the
    fleet: at most 3 fleets with an alert (binomial 99.9 % bound at 0.01 is 3)."""
    rng = np.random.default_rng(4)
    alarms = 0
    for _ in range(40):
        rows = [r for t in ("A", "B", "C") for r in _rows(rng, t, 20, 0.0)]
        alarms += bool(reader_consensus(rows, 0.01)["alerts"])
    assert alarms <= 3, alarms


def test_lag_products_do_not_cross_runs():
    """Runs of three readings [x_k, w_k, x_(k+1)]: each run's last reading is the next one's
    first, so the products across two runs are all positive squares, while those inside a run
    are of independent draws. Pooled with the runs' boundaries: no correlation; the same
    readings as one run: correlated."""
    rng = np.random.default_rng(5)
    x = rng.standard_normal(41)
    rows, z = [], []
    for k in range(40):
        zk = [x[k], rng.standard_normal(), x[k + 1]]
        z += zk
        rows.append({"train": "T", "line": "L", "time": float(k), "balise": {
            "z": zk, "c": [1e-9] * 3, "info": 1.0, "speed": [10.0, 12.0, 14.0],
            "position": [100.0 * k, 100.0 * k + 30, 100.0 * k + 60]}})
    res = reader_consensus(rows, 0.01)["trains"]["T"]
    assert res["readings"] == 120 and not res["correlation"]["finding"], res["correlation"]
    one = reader_consensus([{"train": "T", "line": "L", "time": 0.0, "balise": {
        "z": z, "c": [1e-9] * 120, "info": 1.0, "speed": [10.0, 12.0, 14.0] * 40,
        "position": list(np.arange(120.0))}}], 0.01)["trains"]["T"]
    assert one["correlation"]["finding"] and one["correlation"]["lag1"] > 0.2, one


def test_rows_without_usable_innovations_are_left_out():
    rng = np.random.default_rng(6)
    rows = _rows(rng, "T", 5, 0.0)
    rows.append({"train": "T", "line": "L", "time": 9.0, "balise": None})
    rows.append({"train": "T", "line": "L", "time": 10.0, "balise": {"z": [1.0]}})
    rows.append({"train": "T", "line": "L", "time": 11.0,
                 "balise": dict(_run(rng, 4), z=[float("nan")] * 4)})
    rows.append({"train": "U", "line": "L", "time": 1.0})
    res = reader_consensus(rows, 0.01)
    assert set(res["trains"]) == {"T"} and res["trains"]["T"]["runs"] == 5
    # the fleet's consensus carries them
    full = consensus([dict(r, error=None) for r in rows], FleetConfig())
    assert full.readers["trains"]["T"]["runs"] == 5
