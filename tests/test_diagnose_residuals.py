"""The odometer's residual checks (diagnose/residuals.py): each statistic against its exact
null distribution on synthetic readings, its false-alarm rate on nominal simulated bags of
several line families within the binomial bound, and its power on hidden sensor effects."""

from __future__ import annotations

import dataclasses
import os
import sys

import numpy as np
import pytest
from scipy.stats import binom

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))
import bench_balise_scatter as BS  # noqa: E402
import odometer_checks as OC  # noqa: E402

from train_estimation.core.offline.diagnose.residuals import (
    MAX_PERIOD,
    balise_checks,
    count_consistency,
    dependence_test,
    ljung_box,
    positive_sf,
    scatter_test,
    sensor_checks,
    spline_residuals,
    stretches,
)


def _readings(rng, n=1500, dt=0.1, sd=0.1, gap_at=700):
    """A smooth speed (accelerate, cruise, brake: a cubic between 2 s knots is not exact)
    with white noise of the stated SD, and one gap of 3 s (a link's burst)."""
    t = np.arange(n) * dt
    t[gap_at:] += 3.0
    v = 15.0 * (1 - np.cos(2 * np.pi * t / t[-1])) / 2 + 0.5 * np.sin(t / 7.0)
    rv = np.full(n, sd * sd)
    return t, v, v + sd * rng.standard_normal(n), rv


def test_the_stretches_split_at_gaps_of_the_link():
    t = np.r_[np.arange(10) * 0.1, 4.0 + np.arange(5) * 0.1]
    assert stretches(t).tolist() == [0] * 10 + [1] * 5


def test_the_statistics_hold_their_false_alarm_rate_on_white_noise():
    """At alpha 0.01 each, 300 synthetic runs: alarms within the binomial 99.9 % bound."""
    rng = np.random.default_rng(5)
    alpha, runs = 0.01, 300
    alarms = {"scatter": 0, "correlation": 0, "dependence": 0}
    ratios = []
    for _ in range(runs):
        t, v, y, rv = _readings(rng)
        r, dof, sums = spline_residuals(t, y, rv, lags=10)
        sc = scatter_test(r, dof, rv, alpha)
        alarms["scatter"] += sc["finding"]
        ratios.append(sc["ratio"])
        alarms["correlation"] += ljung_box(r / np.sqrt(rv), stretches(t), 10, alpha, sums,
                                           dof)["finding"]
        alarms["dependence"] += dependence_test(r / np.sqrt(rv), {"speed": v, "distance": t},
                                                alpha)["finding"]
    bound = binom.ppf(0.999, runs, alpha)
    assert all(k <= bound for k in alarms.values()), (alarms, bound)
    # the scatter's ratio is 1 on average (chi-square over its degrees of freedom: SD
    # sqrt(2 / dof) per run), so the spline neither follows the noise nor misses the motion
    sd = np.sqrt(2.0 / dof) / np.sqrt(runs)
    assert abs(np.mean(ratios) - 1.0) < 4 * sd, (np.mean(ratios), sd)


def test_the_spline_leaves_exactly_its_degrees_of_freedom():
    rng = np.random.default_rng(1)
    t, v, y, rv = _readings(rng, sd=0.0)  # no noise: the spline misfit alone
    r, dof, _ = spline_residuals(t, v + 1e-12, np.full(t.size, 0.01))
    # two stretches, each a cubic spline with knots every 2 s: n - (knots + 3) per stretch
    seg = stretches(t)
    p = sum(int((t[seg == s][-1] - t[seg == s][0]) // 2.0) + 3 for s in (0, 1))
    assert dof == t.size - p
    # the smooth motion is followed within a tenth of the noise it is tested against
    assert np.nanmax(np.abs(r)) < 0.01, np.nanmax(np.abs(r))
    # readings sparser than MAX_PERIOD are not fitted
    r, dof, _ = spline_residuals(t * (2 * MAX_PERIOD / 0.1), y, rv)
    assert dof == 0 and np.isnan(r).all()


def test_each_statistic_finds_what_it_is_for():
    rng = np.random.default_rng(2)
    t, v, y, rv = _readings(rng)
    n = t.size
    # scatter 1.3 times the stated SD
    noisy = v + 0.13 * rng.standard_normal(n)
    r, dof, _ = spline_residuals(t, noisy, rv)
    sc = scatter_test(r, dof, rv, 1e-3)
    assert sc["finding"] and abs(np.sqrt(sc["ratio"]) - 1.3) < 0.1, sc
    # an AR(1) error of the stated SD (phi 0.5)
    e = np.zeros(n)
    for k in range(1, n):
        e[k] = 0.5 * e[k - 1] + np.sqrt(1 - 0.25) * rng.standard_normal()
    r, dof, sums = spline_residuals(t, v + 0.1 * e, rv, lags=10)
    lb = ljung_box(r / np.sqrt(rv), stretches(t), 10, 1e-3, sums, dof)
    assert lb["finding"] and lb["rho"][0] > 0.3, lb
    # white noise: the fit's own correlation is what the autocorrelations show
    r, dof, sums = spline_residuals(t, y, rv, lags=10)
    lb = ljung_box(r / np.sqrt(rv), stretches(t), 10, 1e-3, sums, dof)
    assert abs(lb["rho"][0] - lb["rho_fit"][0]) < 4 / np.sqrt(n) and lb["rho_fit"][0] < -0.02, lb
    # noise whose SD doubles from standstill to the top speed
    grows = v + 0.1 * (1 + v / v.max()) * rng.standard_normal(n)
    r, _, _ = spline_residuals(t, grows, rv)
    dp = dependence_test(r / np.sqrt(rv), {"speed": v, "distance": t}, 1e-3)
    assert dp["finding"] and dp["ratio"]["speed"][1] > 2 * dp["ratio"]["speed"][0], dp
    out = sensor_checks(t, grows, rv, v, t)
    assert out["finding"] and "changes with speed" in out["signature"], out


def _count(t, v, rng, sd=0.02):
    """The odometer's count of the speed ``v``: its exact integral (trapezoid on a 10 ms
    grid) plus white noise of ``sd`` m; the reference speed: ``v`` averaged over 1 s."""
    g = np.arange(t[0], t[-1] + 0.01, 0.001)
    vg = np.interp(g, t, v)
    dist = np.concatenate([[0.0], np.cumsum(0.5 * (vg[1:] + vg[:-1]) * np.diff(g))])
    vs = np.convolve(v, np.ones(10) / 10, mode="same")
    return np.interp(t, g, dist) + sd * rng.standard_normal(t.size), vs


def test_the_speed_against_the_count_holds_its_false_alarm_rate_and_finds_a_lag():
    """The count's increase over 1 s less the speed readings' trapezoid, regressed on the
    speed's change: at alpha 0.01, 300 runs of white noise (0.1 m/s on the speed, 2 cm on
    the count) alarm within the binomial 99.9 % bound; a speed channel 0.3 s behind its count
    is found in each of 20 runs with the lag within 3 of its standard errors, and both
    channels 0.3 s late alike (the whole message) hold the rate (they agree with each
    other)."""
    rng = np.random.default_rng(7)
    alpha, runs = 0.01, 300
    alarms = late_alarms = 0
    z = []
    for _ in range(runs):
        t, v, y, _ = _readings(rng)
        d, vs = _count(t, v, rng)
        cc = count_consistency(t, d, y, vs, alpha)
        assert cc["tested"] and cc["windows"] > 100, cc
        alarms += cc["finding"]
        z.append(cc["z"])
        late = t - 0.3  # both channels sampled 0.3 s before their stamps
        vl = np.interp(late, t, v)
        dl, _ = _count(t, v, rng)
        dl = np.interp(late, t, dl)
        late_alarms += count_consistency(t, dl, vl + 0.1 * rng.standard_normal(t.size), vs,
                                         alpha)["finding"]
    bound = binom.ppf(0.999, runs, alpha)
    assert alarms <= bound and late_alarms <= bound, (alarms, late_alarms, bound)
    assert abs(np.mean(z)) < 4 / np.sqrt(runs) and abs(np.std(z) - 1) < 0.15, (np.mean(z),
                                                                              np.std(z))
    for _ in range(20):
        t, v, _, _ = _readings(rng)
        d, vs = _count(t, v, rng)
        y = np.interp(t - 0.3, t, v) + 0.1 * rng.standard_normal(t.size)
        cc = count_consistency(t, d, y, vs, 1e-3)
        assert cc["finding"] and abs(cc["lag"] - 0.3) < 3 * cc["std_error"], cc
        out = sensor_checks(t, y, np.full(t.size, 0.01), v, d, raw=(t, d, y, vs))
        assert "behind its own count" in out["signature"], out


# ------------------------------------------------------------------------------------------
# Simulated bags: the model's innovations as diagnose has them
# ------------------------------------------------------------------------------------------

def _bag_checks(seed: int, effect=None, alpha: float = 1e-3) -> dict:
    """The checks on a nominal bag of ``train_sim.cases`` (seeded; its family drawn), with
    ``effect(speeds, rng, stamps)`` added to the odometer's speed readings
    (benchmarks/odometer_checks, which ``./run bench diagnose`` reports too)."""
    out = OC.checks_on_case(seed, effect, alpha)
    # the figures of docs/benchmarks.md's table (shown with pytest -s)
    print(f"seed {seed} {out['family']} {getattr(effect, '__name__', 'nominal')}: scatter "
          f"{out['scatter'].get('ratio', float('nan')):.3f}, p scatter "
          f"{out['scatter'].get('p', 1):.2g}, correlation {out['correlation'].get('p', 1):.2g},"
          f" dependence {out['dependence'].get('p', 1):.2g}, count {out['count'].get('p', 1):.2g}"
          f" (lag {out['count'].get('lag', float('nan')):+.3f} s), finding {out['finding']}")
    return out


@pytest.mark.slow
def test_nominal_bags_of_several_families_hold_the_false_alarm_rate():
    """12 nominal bags (metro, metro_demo, regional, high-speed families): at alpha 1e-3 for
    the four tests together, at most 1 alarm (P(X >= 2) = 6.6e-5 at that rate)."""
    res = [_bag_checks(seed) for seed in range(12)]
    assert len({r["family"] for r in res}) >= 3, [r["family"] for r in res]
    alarms = [(r["family"], r["signature"]) for r in res if r["finding"]]
    assert len(alarms) <= 1, alarms
    assert all(r["scatter"]["tested"] for r in res), [r["scatter"] for r in res]


@pytest.mark.slow
@pytest.mark.parametrize("effect,words", list(OC.EFFECTS.values()))
def test_a_hidden_odometer_noise_is_found(effect, words):
    """An AR(1) error (phi 0.9, SD 0.1 m/s: 1-2 times the stated SD of these bags) and noise
    that grows with speed (to 0.1 m/s at the top speed) on nominal bags: found on each of
    three, each by what it is for (the AR(1) also by its scatter, the noise growing with
    speed by its dependence). A speed that lags its count: tests/test_foreign_sim.py."""
    for seed in (0, 1, 2):
        r = _bag_checks(seed, effect)
        assert r["finding"] and words in r["signature"], (seed, r["family"], r)


@pytest.mark.slow
def test_diagnose_names_an_odometer_with_correlated_errors_unexplained(tmp_path):
    """End to end: a metro_demo run whose odometer speed readings carry an AR(1) error
    (phi 0.9, SD 0.1 m/s) beside their stated noise is `unexplained`, the entry phase `all`
    with its signature, not `none`; the same run without it is `none`."""
    import json

    from train_core.bagio import BagWriter

    from train_estimation.tools import diagnose as tool
    from train_estimation.tools.diagnose_unexplained import sensor_noise, unexplained_size
    from train_sim.scenario import load_scenario
    from train_sim.world import simulate

    sc = load_scenario("metro_demo").with_changes(duration=300.0)
    res = simulate(sc)
    rng = np.random.default_rng(4)
    err = {"x": 0.0}

    def write(path, ar1):
        with BagWriter(path) as w:
            for t_recv, topic, stamp, fields in res.received_events():
                if topic not in ("odometer", "balise", "control"):
                    continue
                if topic == "odometer" and ar1:
                    err["x"] = 0.9 * err["x"] + 0.1 * np.sqrt(1 - 0.81) * rng.standard_normal()
                    fields = dict(fields, speed=fields["speed"] + err["x"])
                w.write(topic, stamp, fields, t_ns=int(round(t_recv * 1e9)))

    for name, ar1 in (("nominal", False), ("ar1", True)):
        write(tmp_path / name, ar1)
        assert tool.main(["--bag", str(tmp_path / name), "--line", str(sc.line_path),
                          "--train", str(sc.train_path), "--out", str(tmp_path / f"o_{name}"),
                          "--quiet", "--no-plots"]) == 0
    nominal = json.loads((tmp_path / "o_nominal" / "report.json").read_text())
    assert nominal["cause"] == "none" and not nominal["evidence"]["_model"]["sensors"][
        "finding"], nominal["unexplained"]
    rep = json.loads((tmp_path / "o_ar1" / "report.json").read_text())
    assert rep["cause"] == "unexplained", rep["ranking"][:3]
    u = next(u for u in rep["unexplained"] if sensor_noise(u))
    assert u["phase"] == "all" and "correlated in time" in u["best_listed"]["why"], u
    assert unexplained_size(u).endswith("of the stated SD")


# -- the balise readings' scatter (diagnose/balise_rounds.scatter_round) ----------------

def _scatter(seed: int, k: float = 1.0) -> dict:
    """The balise scatter test (round 1, at alpha 1e-3) on case ``seed``'s bag whose balise
    reader's errors are ``k`` times the SD its readings state (benchmarks/bench_balise_scatter,
    whose table is these figures over more seeds)."""
    out = BS.scatter_on_case(seed, k, alpha=1e-3)
    print(f"seed {seed} {out['family']} k {k}: {out['readings']} readings, ratio "
          f"{out.get('ratio', float('nan')):.2f}, p {out.get('p', float('nan')):.2g}")
    return out


@pytest.mark.slow
def test_the_balise_scatter_holds_its_false_alarm_rate_on_nominal_bags():
    """12 nominal bags of several families at alpha 1e-3: at most 1 alarm (P(X >= 2) =
    6.6e-5 at that rate); the sum of squares is tested on every bag (3 readings or more)."""
    res = [_scatter(seed) for seed in range(12)]
    assert all("chi2" in r for r in res), [r.get("note") for r in res]
    assert sum(r["significant"] for r in res) <= 1, [r["p"] for r in res]


@pytest.mark.slow
def test_a_balise_reader_three_times_noisier_than_stated_is_found():
    """Readings whose errors are 3 times the stated SD (seeds whose 10-16 readings are each
    about 7-10 times the stated variance in all): found, the scale within a factor of 2."""
    for seed in (20, 22, 23):
        r = _scatter(seed, 3.0)
        assert r["significant"] and 9.0 / 2 < r["ratio"] < 9.0 * 2, (seed, r)
        assert r["entry"]["family"] == "balise_scatter"


@pytest.mark.slow
def test_diagnose_names_a_noisy_balise_reader_not_a_misplaced_balise(tmp_path):
    """End to end on metro_demo (600 s, seed 1): its balise reader's errors 3 times the SD the
    readings state. Tested one reading at a time the largest had been named a balise lying
    5.0 m from its map position; now one entry for every reading, their SD over the stated
    one, and no balise named. The same run with the reader as stated is `none`."""
    import json

    from train_core.bagio import BagWriter

    from train_estimation.tools import diagnose as tool
    from train_estimation.tools.diagnose_unexplained import (
        at_balise,
        balise_scatter,
        unexplained_line,
        unexplained_size,
    )
    from train_sim.scenario import load_scenario
    from train_sim.world import simulate

    sc = load_scenario("metro_demo")
    stated = sc.train.balise_position_variance
    reports = {}
    for k in (1.0, 3.0):
        res = simulate(sc.with_changes(train=dataclasses.replace(
            sc.train, balise_position_std=k * sc.train.balise_position_std)), 1)
        bag = tmp_path / f"bag{k:g}"
        with BagWriter(bag) as w:
            for t_recv, topic, stamp, fields in res.received_events():
                if topic == "balise":
                    fields = dict(fields, position_variance=stated)
                if topic in ("odometer", "balise", "control"):
                    w.write(topic, stamp, fields, t_ns=int(round(t_recv * 1e9)))
        out = tmp_path / f"out{k:g}"
        assert tool.main(["--bag", str(bag), "--line", str(sc.line_path), "--train",
                          str(sc.train_path), "--out", str(out), "--quiet",
                          "--no-plots"]) == 0
        reports[k] = json.loads((out / "report.json").read_text())
    assert reports[1.0]["cause"] == "none", reports[1.0]["unexplained"]
    rep = reports[3.0]
    assert rep["cause"] == "unexplained", rep["ranking"][:3]
    (u,) = [u for u in rep["unexplained"] if balise_scatter(u)]
    assert not any(at_balise(v) for v in rep["unexplained"]), rep["unexplained"]
    assert u["phase"] == "all" and 1.5 < u["size"] < 6.0, u
    assert unexplained_size(u).endswith("of the stated SD")
    assert "scatter about the odometer's track" in unexplained_line(u)


# -- the balise readings' correlation in time and dependence on speed and distance -------

def test_the_weighted_chi_square_tail_is_exact():
    """positive_sf against closed forms: two weights (g1^2 / g2^2 is F(1, 1): 1 - 2/pi
    arctan sqrt(b / a)), one positive against fourteen equal negative ones (F(1, 14)), down to
    tail probabilities of 4e-5; and the all-one-sign and the empty cases."""
    from scipy.stats import f as fdist

    for a, b in ((1.0, 1.0), (1.0, 4.0), (1.0, 100.0), (3.0, 0.01)):
        exact = 1.0 - 2.0 / np.pi * np.arctan(np.sqrt(b / a))
        assert positive_sf(np.array([a, -b])) == pytest.approx(exact, rel=1e-9, abs=1e-12)
    for w in (60.0, 8.0, 1.0, 0.4):
        exact = fdist.sf(14.0 / w, 1, 14)
        got = positive_sf(np.r_[np.full(14, -1.0), w] * 3.7)  # the scale does not matter
        assert got == pytest.approx(exact, rel=1e-6), (w, got, exact)
    assert positive_sf(np.array([1.0, 2.0, 0.0])) == 1.0
    assert positive_sf(np.array([-1.0, -2.0])) == 0.0
    assert positive_sf(np.zeros(3)) == 0.5


def _origin_cov(rng, n):
    """(C, c, I_s0): the covariance a fitted origin leaves n whitened innovations, I - c c^T /
    I_s0, the origin's column c over the balises carrying part of its information I_s0 (the
    odometer's innovations the rest)."""
    c = rng.uniform(0.3, 1.0, n)
    info = float(c @ c) + rng.uniform(0.0, 2.0)
    return np.eye(n) - np.outer(c, c) / info, c, info


def _fitted(rng, err, c, info):
    """The whitened innovations at the fitted origin of readings whose errors are ``err``
    (whitened by the stated SD): the origin's error is (c^T err + the odometer's share) /
    I_s0, and its covariance is C for white ``err``."""
    other = np.sqrt(info - float(c @ c)) * rng.standard_normal()
    return err - c * (float(c @ err) + other) / info


def test_the_balise_checks_hold_their_false_alarm_rate_at_every_size():
    """Under the stated readings (z ~ N(0, C), C what the fitted origin leaves), each of the
    three exact tests at 10 to 40 readings: the p-values uniform (alarms at 0.05 and 0.2 within
    the binomial 99.9 % bounds over 600 runs per size)."""
    rng = np.random.default_rng(11)
    runs = 600
    for n in (10, 20, 40):
        ps = {"correlation": [], "speed": [], "distance": []}
        for _ in range(runs):
            C, c, info = _origin_cov(rng, n)
            z = _fitted(rng, rng.standard_normal(n), c, info)
            v = rng.uniform(5.0, 25.0, n)
            x = np.sort(rng.uniform(0.0, 8000.0, n))
            out = balise_checks(z, C, v, x, alpha=1e-3)
            for k in ps:
                ps[k].append(out[k]["p"])
        for k, p in ps.items():
            p = np.array(p)
            for a in (0.05, 0.2):
                lo, hi = binom.ppf([0.0005, 0.9995], runs, a)
                assert lo <= np.sum(p < a) <= hi, (n, k, a, np.sum(p < a))


def test_the_balise_checks_find_what_each_is_for():
    """Ten runs of 120 readings (a fleet's passes, or hours of one train; a 10-minute bag has
    7-16 and the tests there have little power: docs/benchmarks.md): an error that varies
    slowly (AR(1), correlation 0.8 from one reading to the next) is found as a correlation in
    time in every run (100 of 100 in a longer draw); errors whose SD grows fivefold with the
    speed (power 0.96 at 120 readings: 96 of 100 runs) as a dependence on speed in at least 8
    of 10 (P(fewer) = 6e-3 at that power), on distance in at most 1; white noise of the
    stated SD as neither in at least 9."""
    rng = np.random.default_rng(12)
    n = 120
    found = {"correlation": 0, "speed": 0, "distance": 0, "white": 0}
    for _ in range(10):
        C, c, info = _origin_cov(rng, n)
        v = rng.uniform(5.0, 25.0, n)
        x = np.sort(rng.uniform(0.0, 8000.0, n))

        def whitened(err, c=c, info=info):  # the innovations with the origin fitted
            return _fitted(rng, err, c, info)

        e = np.empty(n)
        e[0] = rng.standard_normal()
        for k in range(1, n):
            e[k] = 0.8 * e[k - 1] + 0.6 * rng.standard_normal()
        out = balise_checks(whitened(e), C, v, x)
        found["correlation"] += out["correlation"]["finding"] and out["correlation"]["lag1"] > 0.4
        if out["correlation"]["finding"]:
            assert "correlated from one reading to the next" in out["signature"]
        jit = v * rng.standard_normal(n) / np.sqrt(np.mean(v * v))
        out = balise_checks(whitened(jit), C, v, x)
        found["speed"] += out["speed"]["finding"] and out["speed"]["ratio"][1] > \
            2 * out["speed"]["ratio"][0]
        found["distance"] += out["distance"]["finding"]
        found["white"] += balise_checks(whitened(rng.standard_normal(n)), C, v, x)["finding"]
    assert found["correlation"] == 10 and found["speed"] >= 8, found
    assert found["distance"] <= 1 and found["white"] <= 1, found
    # too few readings: not tested, said so
    out = balise_checks(np.ones(5), np.eye(5), v[:5], x[:5])
    assert out["tested"] is False and "fewer than" in out["note"]


@pytest.mark.slow
def test_the_balise_checks_hold_their_false_alarm_rate_on_nominal_bags():
    """12 nominal case bags (several families) under the believed model at alpha 1e-3: at most
    one alarm (P(X >= 2) = 6.6e-5 at that rate); tested wherever a bag has 8 readings."""
    res = [BS.checks_on_case(seed) for seed in range(12)]
    for seed, r in enumerate(res):
        print(f"seed {seed} {r['family']}: {r['readings']} readings, tested {r['tested']}, "
              + ", ".join(f"{k} p {r[k]['p']:.2g}" for k in ("correlation", "speed", "distance")
                          if k in r and "p" in r[k]))
    assert sum(r["tested"] for r in res) >= 6, [r["readings"] for r in res]
    assert sum(r["finding"] for r in res) <= 1, [r.get("signature") for r in res]
