"""The odometer's halves test and its speed-offset rival (diagnose/halves.py): the partition is
exact, a true constant scale passes, a scale that changes mid-run and an odometer that reads a
speed more while moving do not pass as one scale."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
from train_core.effects import OdometerScaleEffect

from train_estimation.core.offline.diagnose.causes import BY_NAME
from train_estimation.core.offline.diagnose.confirm import CONFIRM
from train_estimation.core.offline.diagnose.halves import (
    MIN_READINGS,
    bias_law,
    odometer_halves,
    odometer_partitions,
)
from train_sim.scenario import load_scenario
from train_sim.unlisted import OdometerBias, OdometerRescale, Unlisted


def test_the_partition_halves_the_distance_and_holds_only_odometer_readings():
    rng = np.random.default_rng(3)
    n = 400
    kind = (rng.random(n) < 0.1).astype(int)  # 1: a balise event
    v = np.where(np.arange(n) % 100 < 10, 0.0, rng.uniform(2.0, 20.0, n))  # stops
    t = np.cumsum(np.full(n, 0.2))
    odo = np.flatnonzero(kind == 0)
    sc_d = np.zeros(n)
    sc_v = np.zeros(n)
    sc_v[odo] = v[odo]
    sc_d[odo] = np.cumsum(v[odo] * 0.2)
    mo = SimpleNamespace(ev=SimpleNamespace(t=t, odo=odo), sc_d=sc_d, sc_v=sc_v)
    a, b, words = odometer_partitions(mo, 1.0)["distance"]
    assert not np.any(a & b) and np.array_equal(a | b, kind == 0)
    inc = np.diff(sc_d[odo], prepend=0.0)
    first = float(np.sum(inc[a[odo]]))
    total = float(sc_d[odo][-1])
    # the first half ends at the last reading within half the distance
    assert total / 2 - inc.max() < first <= total / 2, (first, total)
    assert words[0] == f"over the first {total / 2:.0f} m"
    # too few readings while moving in a half: no partition
    still = SimpleNamespace(ev=mo.ev, sc_d=sc_d, sc_v=np.where(np.arange(n) < n - 3 * MIN_READINGS,
                                                                  0.5, sc_v))
    assert odometer_partitions(still, 1.0) == {}


@pytest.fixture(scope="module")
def metro():
    return load_scenario("metro_demo").with_changes(duration=300.0)


def _analysed(scenario, tmp_path):
    """(Motion, DiagConfig, null with the command-time offset, noise of the model with the
    odometer scale fitted) of a simulated measured bag of ``scenario``, as ``diagnose`` runs."""
    from train_estimation.core.offline.diagnose.motion import Motion
    from train_estimation.core.offline.diagnose.run import DiagConfig, prepare
    from train_estimation.core.offline.diagnose.search import refit_at_own_noise
    from train_estimation.core.offline.diagnose.stage import Null, Stage
    from train_estimation.tools.diagnose import read_measured
    from train_sim.generate import generate

    generate(scenario, tmp_path / "bag", measured=True)
    cfg = DiagConfig()
    run = prepare(read_measured(tmp_path / "bag"), scenario.line, cfg, scenario.train)
    mo = Motion(run, scenario.line, scenario.train, cfg)
    null = Null(shift=Stage(mo, Null(), cfg).nuisance_shift()[0])
    cause = BY_NAME["odometer_scale"]
    st = Stage(mo, null, cfg)
    fit = cause.score(st, None, st.null_ll())
    fit.noise = (st.q, st.r_s)
    refit_at_own_noise(mo, null, cause, fit, cfg)
    return mo, cfg, null, fit.noise


def _halves(scenario, tmp_path):
    mo, cfg, null, noise = _analysed(scenario, tmp_path)
    return (odometer_halves(mo, null, cfg, noise, CONFIRM.halves_alpha,
                            CONFIRM.halves_min_share), bias_law(mo, null, cfg, noise))


@pytest.mark.slow
def test_a_constant_scale_passes_and_is_no_speed_offset(metro, tmp_path):
    scenario = metro.with_effects(dataclasses.replace(
        metro.effects, odometer_scale=OdometerScaleEffect(1.015)))
    h, law = _halves(scenario, tmp_path)
    q = h["quantities"]["distance"]
    assert h["consistent"], h
    # both halves fit the true scale within 4 SE
    for s, e in zip(q["scale"], q["std_errors"]):
        assert abs(s - 1.015) < 4 * e, q
    assert law["lr"] < -CONFIRM.law_lr, law


@pytest.mark.slow
def test_a_scale_that_changes_mid_run_fails_the_halves(metro, tmp_path):
    scenario = metro.with_changes(unlisted=Unlisted(odometer_rescale=OdometerRescale(100.0,
                                                                                    0.985)))
    h, _ = _halves(scenario, tmp_path)
    q = h["quantities"]["distance"]
    assert not h["consistent"] and h["why"].startswith("not one scale"), h
    assert q["scale"][1] < q["scale"][0], q  # counts less after the change


@pytest.mark.slow
def test_a_speed_offset_is_the_rival_law_and_fitted(metro, tmp_path):
    """The offset is fitted to its size and the law fits better than one scale. On this metro
    line (top speed 22 m/s) it is not decisive: 2 ln LR 6.1 over ten minutes (8.4
    in the first five), below the 9 that overrules the scale; on a high-speed line (the
    unlisted test kind odometer_bias, seed 13: 0.095 m/s at 4-58 m/s) it was 105."""
    scenario = metro.with_changes(duration=600.0,
                                  unlisted=Unlisted(odometer_bias=OdometerBias(0.08)))
    _, law = _halves(scenario, tmp_path)
    assert abs(law["b"] - 0.08) < 4 * law["std_error"], law
    assert law["lr"] > 0.0, law
