"""`identify` on generated bags: recovers a changed Davis c; refuses data that cannot fit."""

import dataclasses

import pytest
import yaml
from train_core.bagio import BagWriter
from train_core.effects import ResistanceEffect
from train_core.model import load_train

from train_estimation.tools import identify as tool
from train_sim.generate import generate
from train_sim.scenario import load_scenario


@pytest.fixture(scope="module")
def crh3():
    return load_scenario("crh3_high_speed")


def run_tool(sc, bag, out):
    return tool.main(["--bag", str(bag), "--line", sc.line_path, "--train", sc.train_path,
                      "--out", str(out), "--quiet"])


def test_identify_recovers_c_plus_30_percent(crh3, tmp_path, capsys):
    d = crh3.train.davis
    sc = crh3.with_effects(dataclasses.replace(
        crh3.effects, resistance=ResistanceEffect(a=d.a, b=d.b, c=1.3 * d.c)))
    generate(sc, tmp_path / "bag", measured=True)
    assert run_tool(sc, tmp_path / "bag", tmp_path / "fitted.yaml") == 0
    fitted = load_train(tmp_path / "fitted.yaml")
    assert abs(fitted.davis.c - 1.3 * d.c) <= 0.10 * 1.3 * d.c, fitted.davis
    assert (tmp_path / "fitted.png").stat().st_size > 5000
    assert "standard error" in (tmp_path / "fitted.yaml").read_text()
    # the summary and the yaml carry the force at the reference speed, the correlations of the
    # free parameters and the rule applied
    out = capsys.readouterr().out
    assert "resistance force at" in out and "correlations of the fitted parameters" in out
    assert "rule: identifiable = tight AND separable" in out
    ident = yaml.safe_load((tmp_path / "fitted.yaml").read_text())["identification"]
    force = ident["force_at_reference_speed"]
    assert force["std_error"] > 0 and force["speed"] > 0
    assert "gamma" in ident["correlations"]
    vif = ident["variance_inflation"]
    assert all(ident["identifiable"][k] == (v <= 30.0) for k, v in vif.items())


def test_identify_refuses_a_bag_without_control(crh3, tmp_path, capsys):
    res = generate(crh3, tmp_path / "full", measured=True, duration=300.0)
    with BagWriter(tmp_path / "nocontrol") as w:
        for topic, stamp, fields in res.events():
            if topic in ("odometer", "balise"):
                w.write(topic, stamp, fields)
    assert run_tool(crh3, tmp_path / "nocontrol", tmp_path / "x.yaml") == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "control" in err and "cannot identify" in err
    assert not (tmp_path / "x.yaml").exists()


@pytest.mark.parametrize("duration,expect", [(30.0, "too short")])
def test_identify_refuses_too_short_a_run(crh3, tmp_path, capsys, duration, expect):
    generate(crh3, tmp_path / "short", measured=True, duration=duration)
    assert run_tool(crh3, tmp_path / "short", tmp_path / "x.yaml") == 2
    assert expect in capsys.readouterr().err
    assert not (tmp_path / "x.yaml").exists()


def test_identify_refuses_a_train_that_never_moves(crh3, tmp_path, capsys):
    # the driver dwells for the whole run: 300 s of odometer samples at standstill
    still = crh3.with_changes(duration=300.0,
                              driver=dataclasses.replace(crh3.driver, initial_dwell=1000.0))
    generate(still, tmp_path / "still", measured=True)
    assert run_tool(crh3, tmp_path / "still", tmp_path / "x.yaml") == 2
    err = capsys.readouterr().err
    assert "never moves" in err and "cannot identify" in err, err
    assert not (tmp_path / "x.yaml").exists()


def test_fitted_yaml_says_which_prior_an_unidentifiable_davis_term_kept(crh3, tmp_path):
    """b not identifiable, mass fitted 20 % heavier: b is the prior per unit of effective mass
    (so 1.2 x train.yaml's in N), and the comment must not claim train.yaml's b was kept."""
    from types import SimpleNamespace

    prior = crh3.train
    d = prior.davis
    fitted = dataclasses.replace(prior, mass=1.2 * prior.mass,
                                 davis=dataclasses.replace(d, b=1.2 * d.b, c=1.1 * d.c))
    ok = {"mass": True, "rotary_allowance": True, "davis.a": False, "davis.b": False,
          "davis.c": True, "braking_rate": True}
    res = SimpleNamespace(std_errors={k: 0.01 for k in ok}, identifiable=ok,
                          reasons={k: "x" for k in ok}, mass_if_davis_nominal=(1.0, 0.1),
                          rule="r", free_names=(), correlation=None, variance_inflation={},
                          fixed_by_rule=(), force_at_reference_speed={})
    text = tool.train_to_yaml(fitted, res, prior, "bag")
    line = {ln.split(":")[0].strip(): ln for ln in text.splitlines()}
    assert "per unit of effective mass" in line["b"] and f"prior {d.b:.6g}" in line["b"]
    assert line["a"].endswith("not identifiable from this run: prior kept")  # a unchanged
    assert "fitted, standard error" in line["c"]
    path = tmp_path / "fitted.yaml"
    path.write_text(text)
    assert load_train(path).davis.b == pytest.approx(1.2 * d.b, rel=1e-5)


def test_an_out_that_would_overwrite_itself_or_is_a_directory_is_refused(tmp_path, capsys):
    """--out fit.png named the plot and the fitted train.yaml the same file: refused first."""
    from train_estimation.tools import identify as tool

    for out in (tmp_path / "fit.png", tmp_path):
        assert tool.main(["--bag", str(tmp_path / "nobag"), "--line", "l.yaml", "--train",
                          "t.yaml", "--out", str(out), "--quiet"]) == 2
        err = capsys.readouterr().err
        assert "name the fitted train.yaml" in err and len(err.splitlines()) == 1
