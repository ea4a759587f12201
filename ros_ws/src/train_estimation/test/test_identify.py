"""Tests of the SI front end (identify.py) on synthetic runs of the same model (si_synth)."""

import os
import sys

import numpy as np
import pytest
from train_core.model import Davis, Line

from train_estimation.core.offline.identify import IdentificationError, SIData, identify

sys.path.insert(0, os.path.dirname(__file__))
from si_synth import METRO, hilly_line, simulate_run  # noqa: E402

LINE = hilly_line()


def _data(run, **drop):
    kw = {k: v for k, v in run.items() if k != "truth_v"}
    kw.update(drop)
    return SIData(**kw)


@pytest.fixture(scope="module")
def c_plus_30():
    true = METRO.with_changes(davis=Davis(METRO.davis.a, METRO.davis.b, 1.3 * METRO.davis.c))
    run = simulate_run(true, LINE, np.random.default_rng(11), 2400.0)
    return true, identify(_data(run), LINE, METRO)


def test_identify_recovers_c_plus_30_percent_within_10_percent(c_plus_30):
    true, res = c_plus_30
    assert "gamma" in res.free_names  # fitted (identifiable only if also separable)
    assert res.identifiable["davis.c"] == (res.variance_inflation["gamma"] <= 30.0)
    assert abs(res.values["davis.c"] / true.davis.c - 1) < 0.10
    # the reported SE is honest: the error is within 3 SE
    assert abs(res.values["davis.c"] - true.davis.c) < 3 * res.std_errors["davis.c"]


def test_identify_other_parameters_and_mass_flags(c_plus_30):
    true, res = c_plus_30
    assert abs(res.values["mass"] / true.mass - 1) < 0.02
    assert abs(res.values["braking_rate"] - 1.0) < 0.02
    assert abs(res.values["rotary_allowance"] - true.rotary_allowance) < 0.03
    assert res.train.davis.c == pytest.approx(res.values["davis.c"])
    assert "assuming" in res.reasons["mass"]


def test_mass_not_identifiable_without_force_calibration():
    from train_estimation.core.offline.identify import SIConfig

    run = simulate_run(METRO, LINE, np.random.default_rng(12), 900.0)
    res = identify(_data(run), LINE, METRO, SIConfig(fit_traction_gain=False))
    assert not res.identifiable["mass"] and res.values["mass"] == METRO.mass
    assert np.isnan(res.std_errors["mass"])


def test_flat_line_rotary_allowance_not_identifiable():
    flat = Line(name="flat", length=60000.0, balises=LINE.balises)
    run = simulate_run(METRO, flat, np.random.default_rng(13), 900.0)
    res = identify(_data(run), flat, METRO)
    assert not res.identifiable["rotary_allowance"]
    assert "gradient" in res.reasons["rotary_allowance"]
    assert res.values["rotary_allowance"] == pytest.approx(METRO.rotary_allowance)


def test_missing_series():
    run = simulate_run(METRO, LINE, np.random.default_rng(14), 300.0)
    with pytest.raises(IdentificationError) as e:
        identify(_data(run, ctrl_t=np.array([]), ctrl_a_tar=np.array([])), LINE, METRO)
    assert "control" in e.value.missing and "davis.c" in e.value.unidentifiable
    with pytest.raises(IdentificationError) as e:
        identify(_data(run, balise_t=None, balise_position=None), LINE, METRO)
    assert any("balise" in m for m in e.value.missing)


def test_too_short():
    run = simulate_run(METRO, LINE, np.random.default_rng(15), 60.0)
    with pytest.raises(IdentificationError, match="too short"):
        identify(_data(run), LINE, METRO)


def test_never_moves():
    run = simulate_run(METRO, LINE, np.random.default_rng(16), 400.0, never_moves=True)
    with pytest.raises(IdentificationError, match="never moves") as e:
        identify(_data(run), LINE, METRO)
    assert "mass" in e.value.unidentifiable


def test_only_cruises():
    run = simulate_run(METRO, LINE, np.random.default_rng(17), 600.0, cruise_only=True)
    with pytest.raises(IdentificationError, match="only cruises"):
        identify(_data(run), LINE, METRO)


def test_bad_stamps_and_nan():
    run = simulate_run(METRO, LINE, np.random.default_rng(18), 300.0)
    t = run["odo_t"].copy()
    t[5] = t[4]
    with pytest.raises(IdentificationError, match="strictly increasing"):
        identify(_data(run, odo_t=t), LINE, METRO)
    sp = run["odo_speed"].copy()
    sp[3] = np.nan
    with pytest.raises(IdentificationError, match="NaN"):
        identify(_data(run, odo_speed=sp), LINE, METRO)


@pytest.fixture(scope="module")
def nominal():
    run = simulate_run(METRO, LINE, np.random.default_rng(12), 900.0)
    return identify(_data(run), LINE, METRO)


def test_correlated_davis_terms_are_reported_and_not_all_flagged(nominal):
    """Over a run's speeds 1, v and v^2 are nearly collinear: the Davis terms' estimates are
    correlated near -1. They are reported with their correlations, keep the joint fit's values,
    and are flagged identifiable only if separable (variance inflation <= vif_max)."""
    from train_estimation.core.offline.identify import SIConfig

    res, cfg = nominal, SIConfig()
    names = list(res.free_names)
    assert {"alpha", "beta", "gamma"} <= set(names)  # all three fitted on this run
    R = res.correlation
    assert R.shape == (len(names), len(names))
    np.testing.assert_allclose(np.diag(R), 1.0)
    ib, ig = names.index("beta"), names.index("gamma")
    r_max = np.sqrt(1.0 - 1.0 / cfg.vif_max)  # the largest |r| two separable parameters have
    assert abs(R[ib, ig]) > r_max  # the correlated pair ...
    assert not (res.identifiable["beta"] and res.identifiable["gamma"])  # ... not both flagged
    for i, a in enumerate(names):
        vif = res.variance_inflation[a]
        assert res.identifiable[a] == (vif <= cfg.vif_max)
        if vif > cfg.vif_max:
            # the reason names the inflation and the strongest correlation; the value is the
            # joint fit's (with its SE), not the prior
            j = max((j for j in range(len(names)) if j != i), key=lambda j: abs(R[i, j]))
            assert "not separable" in res.reasons[a]
            assert f"{R[i, j]:+.2f} with {names[j]}" in res.reasons[a]
            assert np.isfinite(res.std_errors[a])
        for j in range(i):
            if res.identifiable[a] and res.identifiable[names[j]]:
                assert abs(R[i, j]) <= r_max
    assert "variance inflation" in res.rule and "relative standard error" in res.rule


def test_force_at_reference_speed_is_within_its_standard_error(nominal):
    f = nominal.force_at_reference_speed
    d = METRO.davis
    true = d.a + d.b * f["speed"] + d.c * f["speed"] ** 2
    assert 9.0 < f["speed"] < 22.0  # the median moving speed of the run
    assert f["prior"] == pytest.approx(true)
    assert 0 < f["std_error"] < 0.05 * true
    # 3 SE: a 0.27 % two-sided chance of failing with an honest SE (one fixed seed)
    assert abs(f["fitted"] - true) < 3 * f["std_error"]


def test_commands_that_act_later_than_stamped_are_found_and_doubted(c_plus_30):
    """The same run with every command stamped 0.06 s early (another producer's commands act
    after their stamps): identify profiles the commands' time offset and finds it within 3 of
    its standard errors, the values within 3 SE of the truth as on the run stamped right
    (where the offset found is 0 within 3 SE), and every standard error holds the offset's
    doubt (none below the fit's at the offset alone). Taken as stamped, c, the mass and f
    were 5.6, -7.9 and -9.0 SE off the truth."""
    from dataclasses import replace

    from train_estimation.core.offline.identify import SIConfig

    true, right = c_plus_30
    run = simulate_run(true, LINE, np.random.default_rng(11), 2400.0)
    early = replace(_data(run), ctrl_t=run["ctrl_t"] - 0.06)
    res = identify(early, LINE, METRO)
    dg = res.diagnostics
    assert abs(dg["command_offset_s"] - 0.06) < 3 * dg["command_offset_se"], dg
    assert abs(right.diagnostics["command_offset_s"]) < 3 * right.diagnostics["command_offset_se"]
    for name, want in (("davis.c", true.davis.c), ("mass", true.mass), ("braking_rate", 1.0)):
        assert abs(res.values[name] - want) < 3 * res.std_errors[name], name
    alone = identify(replace(early, ctrl_t=early.ctrl_t + dg["command_offset_s"]), LINE, METRO,
                     SIConfig(command_offsets=None))
    for name, se in alone.std_errors.items():
        if np.isfinite(se):
            assert res.std_errors[name] >= se * (1 - 1e-9), name


def test_a_brake_delay_longer_than_believed_is_found_beyond_the_range():
    """A train whose actuator answers 0.6 s later than train.yaml says: the best offset lies
    past the profile's +0.5 s, so the range goes on, and the offset found is the 0.6 s within
    3 of its standard errors, f and the mass within 3 of theirs; the fitted train's delay
    carries it. (Taken as stamped, f came 3.6 of its standard errors off the truth.)"""
    from dataclasses import replace

    true = METRO.with_changes(brake=replace(METRO.brake, delay=METRO.brake.delay + 0.6))
    run = simulate_run(true, LINE, np.random.default_rng(14), 1200.0)
    res = identify(_data(run), LINE, METRO)
    dg = res.diagnostics
    assert abs(dg["command_offset_s"] - 0.6) < 3 * dg["command_offset_se"], dg
    assert "command_offset" not in res.reasons
    for name, want in (("mass", true.mass), ("braking_rate", 1.0)):
        assert abs(res.values[name] - want) < 3 * res.std_errors[name], name
    assert res.train.brake.delay == pytest.approx(METRO.brake.delay + dg["command_offset_s"])


def test_the_runs_place_on_the_line_is_in_the_standard_errors():
    """The run is placed on the line by the median of its balises' offsets; taken as exact, its
    doubt was in no standard error (on metro_demo the mass, the rotary allowance and f spread
    1.15-1.38 of their SEs over 20 seeds of one trajectory; 0.94-1.03 with it). The place's
    variance is (pi / 2) var / n, var the larger of train.yaml's and the offsets' own robust
    spread; moving every balise by its standard deviation either way moves the values the
    gradients carry by about what the doubt added (the fit refits its noise and offset, the
    doubt's sigma points do not: within a factor of 2), and on a line without gradients the
    place moves nothing."""
    from dataclasses import replace

    from train_estimation.core.offline.identify import SIConfig

    run = simulate_run(METRO, LINE, np.random.default_rng(12), 900.0)
    data = _data(run)
    data = replace(data, balise_position=data.balise_position
                   + np.random.default_rng(5).normal(0.0, 3.0, data.balise_position.size))
    cfg = SIConfig(command_offsets=None)
    bare_cfg = SIConfig(command_offsets=None, placement_doubt=False)
    res, bare = identify(data, LINE, METRO, cfg), identify(data, LINE, METRO, bare_cfg)
    offs = data.balise_position - np.interp(data.balise_t, data.odo_t, data.odo_distance)
    spread = (1.4826 * np.median(np.abs(offs - np.median(offs)))) ** 2
    stated = METRO.balise_position_variance + METRO.odometer_distance_variance
    assert spread > stated  # the balises scatter more than train.yaml says: their spread counts
    var = res.diagnostics["position_offset_var"]
    assert var == pytest.approx(0.5 * np.pi * spread / offs.size, rel=1e-12)
    assert res.diagnostics["position_offset_m"] == pytest.approx(np.median(offs), rel=1e-12)
    moved = [identify(replace(data, balise_position=data.balise_position + s * np.sqrt(var)),
                      LINE, METRO, bare_cfg) for s in (1.0, -1.0)]
    for name in ("mass", "rotary_allowance", "braking_rate"):
        added = np.sqrt(res.std_errors[name] ** 2 - bare.std_errors[name] ** 2)
        rms = np.sqrt(np.mean([(m.values[name] - bare.values[name]) ** 2 for m in moved]))
        assert 0.5 * added < rms < 2.0 * added, (name, added, rms)
        assert res.values[name] == bare.values[name]  # the doubt moves no value

    flat = Line(name="flat", length=60000.0, balises=LINE.balises)
    run = simulate_run(METRO, flat, np.random.default_rng(13), 900.0)
    res, bare = (identify(_data(run), flat, METRO, c) for c in (cfg, bare_cfg))
    assert res.std_errors.keys() == bare.std_errors.keys()
    for name, se in res.std_errors.items():  # bit for bit (nan where held at the prior)
        assert se == bare.std_errors[name] or np.isnan(se) and np.isnan(bare.std_errors[name])
