"""The `diagnose` executable as a user runs it: bad input gives one line and exit 2, the report
has docs/interfaces.md's shape, ground truth is never read, the model directory runs in the
simulator, and hidden effects on generated bags (train_sim.cases) are found."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml
from train_core.bagio import BagWriter, read_bag
from train_core.config import Section
from train_core.effects import parse_effects

from train_estimation.core.offline.diagnose import CAUSES, CauseFit, Diagnosis
from train_estimation.tools import diagnose as tool
from train_estimation.tools import diagnose_unexplained as unexplained
from train_estimation.tools.diagnose_plots import write_plots
from train_sim.cases import main_error, make_case
from train_sim.generate import generate
from train_sim.scenario import load_scenario, with_model
from train_sim.world import simulate

REPORT_KEYS = ["cause", "parameters", "ranking", "unexplained", "untestable", "evidence",
               "gain"]


def run_tool(bag, line, train, out):
    return tool.main(["--bag", str(bag), "--line", str(line), "--train", str(train),
                      "--out", str(out), "--quiet"])


@pytest.fixture(scope="module")
def metro():
    return load_scenario("metro_demo")


@pytest.fixture(scope="module")
def metro_run(metro):
    """One simulated metro_demo run (300 s), written into bags as the tests need."""
    return simulate(metro.with_changes(duration=300.0))


def write_bag(path, res, topics=("odometer", "balise", "control"), gt=None):
    with BagWriter(path) as w:
        for t_recv, topic, stamp, fields in res.received_events():
            if topic == "ground_truth":
                if gt is not None:
                    gt(w, t_recv, stamp, fields)
                continue
            if topic in topics:
                w.write(topic, stamp, fields, t_ns=int(round(t_recv * 1e9)))
    return path


def one_error_line(capsys) -> str:
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1, err
    return err[0]


# ------------------------------------------------------------------------------------------------
# Help and bad input
# ------------------------------------------------------------------------------------------------

def test_help_says_how_to_read_the_report(capsys):
    with pytest.raises(SystemExit) as e:
        tool.main(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    for word in ("--bag", "--line", "--train", "--out", "report.json", "ranking", "score",
                 "log-likelihood", "untestable", "gain", "model/", "exit status"):
        assert word.lower() in out.lower(), word
    # every cause the tool tests is named (argparse may wrap a line at any space)
    flat = " ".join(out.split())
    for cause in CAUSES:
        assert cause in flat, cause


@pytest.mark.parametrize("missing,words", [
    ("control", ("control",)), ("odometer", ("odometer",)), ("balise", ("balise",))])
def test_a_missing_topic_gives_one_line_and_exit_2(metro, metro_run, tmp_path, capsys, missing,
                                                   words):
    keep = tuple(t for t in ("odometer", "balise", "control") if t != missing)
    bag = write_bag(tmp_path / "bag", metro_run, keep)
    assert run_tool(bag, metro.line_path, metro.train_path, tmp_path / "out") == 2
    line = one_error_line(capsys)
    assert line.startswith("diagnose:") and all(w in line for w in words), line
    assert not (tmp_path / "out" / "report.json").exists()


def test_too_short_and_never_moving_give_one_line_and_exit_2(metro, tmp_path, capsys):
    short = simulate(metro.with_changes(duration=60.0))
    assert run_tool(write_bag(tmp_path / "short", short), metro.line_path, metro.train_path,
                    tmp_path / "o1") == 2
    assert "short" in one_error_line(capsys)
    still = simulate(metro.with_changes(
        duration=300.0, driver=dataclasses.replace(metro.driver, initial_dwell=1000.0)))
    assert run_tool(write_bag(tmp_path / "still", still), metro.line_path, metro.train_path,
                    tmp_path / "o2") == 2
    assert "balise" in one_error_line(capsys)  # standing: no balise passed
    # the same standstill with two balise readings in it (so only the motion is missing)
    with BagWriter(tmp_path / "still_b") as w:
        for t_recv, topic, stamp, fields in still.received_events():
            if topic in ("odometer", "control"):
                w.write(topic, stamp, fields, t_ns=int(round(t_recv * 1e9)))
        t_epoch = still.odometer["stamp"][0]
        for k, b in enumerate(metro.line.balises[1:3]):
            fields = {"seq": k, "balise_id": b.id, "position": b.position,
                      "position_variance": 1.0}
            w.write("balise", t_epoch + 100.0 + k, fields, t_ns=int((100.0 + k) * 1e9))
    assert run_tool(tmp_path / "still_b", metro.line_path, metro.train_path, tmp_path / "o3") == 2
    assert "never moves" in one_error_line(capsys)
    assert not any((tmp_path / f"o{i}").exists() for i in (1, 2, 3))


def test_unreadable_bag_and_bad_yaml_give_one_line_and_exit_2(metro, metro_run, tmp_path,
                                                               capsys):
    good = write_bag(tmp_path / "good", metro_run)
    corrupt = tmp_path / "corrupt"
    shutil.copytree(good, corrupt)
    for f in corrupt.glob("*.mcap"):
        f.write_bytes(b"\x89MCAP0\r\n" + b"garbage" * 1000)
    cases = [
        (corrupt, metro.line_path, metro.train_path, "unreadable"),
        (tmp_path / "nope", metro.line_path, metro.train_path, "no such bag"),
        (good, tmp_path / "missing_line.yaml", metro.train_path, "not found"),
    ]
    bad_yaml = tmp_path / "bad.yaml"
    bad_yaml.write_text("mass: [1, 2\n davis: {")
    cases.append((good, metro.line_path, bad_yaml, "not valid YAML"))
    no_davis = tmp_path / "no_davis.yaml"
    t = yaml.safe_load(Path(metro.train_path).read_text())
    del t["davis"]
    no_davis.write_text(yaml.safe_dump(t))
    cases.append((good, metro.line_path, no_davis, "missing key 'davis'"))
    for i, (bag, line, train, words) in enumerate(cases):
        assert run_tool(bag, line, train, tmp_path / f"out{i}") == 2, words
        msg = one_error_line(capsys)
        assert words in msg, (words, msg)
        assert not (tmp_path / f"out{i}").exists()


def test_the_installed_executable_exits_2_with_one_line(metro, tmp_path, ros_env):
    from conftest import executable

    out = subprocess.run([executable("train_estimation", "diagnose"), "--bag",
                          str(tmp_path / "nope"), "--line", metro.line_path, "--train",
                          metro.train_path, "--out", str(tmp_path / "o")],
                         capture_output=True, text=True, timeout=120, env=ros_env)
    assert out.returncode == 2
    assert len(out.stderr.strip().splitlines()) == 1 and "no such bag" in out.stderr


def test_a_run_with_its_plots_writes_svg_figures_without_loading_matplotlib(metro, metro_run,
                                                                            tmp_path, ros_env):
    """The installed executable, plots included: no matplotlib module is imported (python's
    -X importtime lists every import), each figure is a well-formed SVG document and
    report.html embeds each one."""
    import xml.etree.ElementTree as ET

    from conftest import executable

    bag = write_bag(tmp_path / "bag", metro_run)
    out = tmp_path / "out"
    res = subprocess.run([sys.executable, "-X", "importtime",
                          executable("train_estimation", "diagnose"), "--bag", str(bag),
                          "--line", metro.line_path, "--train", metro.train_path,
                          "--out", str(out), "--quiet"],
                         capture_output=True, text=True, timeout=300, env=ros_env)
    assert res.returncode == 0, res.stderr[-2000:]
    imported = [ln.rsplit("|", 1)[-1].strip() for ln in res.stderr.splitlines()
                if ln.startswith("import time:")]
    assert "numpy" in imported  # the listing is there
    assert not [m for m in imported if m.split(".")[0] in ("matplotlib", "PIL")]
    svgs = sorted(out.glob("*.svg"))
    assert {"residual_position.svg", "speed_trace.svg"} <= {p.name for p in svgs}
    for p in svgs:
        root = ET.parse(p).getroot()
        assert root.tag == "{http://www.w3.org/2000/svg}svg", p.name
        assert len(list(root.iter("{http://www.w3.org/2000/svg}path"))) >= 4, p.name
    texts = {t.text for t in ET.parse(out / "residual_position.svg").getroot().iter(
        "{http://www.w3.org/2000/svg}text")}
    assert {"residual (believed model)", "believed model: mean per 100 m, +-2 SE",
            "track position (m)", "residual accel. (m/s^2)"} <= texts
    page = (out / "report.html").read_text()
    assert page.count('src="data:image/svg+xml;base64,') == len(svgs)
    assert not list(out.glob("*.png"))


# ------------------------------------------------------------------------------------------------
# The model directory (no core needed: a Diagnosis with every cause accepted)
# ------------------------------------------------------------------------------------------------

def _motion_over(tmp_path, sc, cfg, start: float, end: float):
    """The scenario's run, written as a bag and read back as diagnose reads it: its Motion and
    the position bins ``i..j`` that hold the stretch ``[start, end)``."""
    from train_estimation.core.offline.diagnose import Motion, prepare

    bag = write_bag(tmp_path / "bag", simulate(sc))
    mo = Motion(prepare(tool.read_measured(bag), sc.line, cfg), sc.line, sc.train, cfg)
    return (mo, int(np.searchsorted(mo.bin_edges, start, "right") - 1),
            int(np.searchsorted(mo.bin_edges, end, "left")))


def _report(paths: dict, tmp_path) -> dict:
    """diagnose on ``tmp_path/bag`` with the case's believed line and train, as a user runs it
    (no plots: they have tests of their own): report.json."""
    assert tool.main(["--bag", str(tmp_path / "bag"), "--line", str(paths["line"]), "--train",
                      str(paths["train"]), "--out", str(tmp_path / "out"), "--quiet",
                      "--no-plots"]) == 0
    return json.loads((tmp_path / "out" / "report.json").read_text())


def _unlisted_bag(kind: str, seed, tmp_path):
    """An unlisted case (train_sim.unlisted_cases) of ``kind`` at ``seed``, written and
    simulated into ``tmp_path/bag``: (the case, its files). The case's pilot runs are shared
    within the worker (conftest.simulations_shared): each seed draws its nominal case again for
    every kind."""
    from conftest import simulations_shared
    from train_sim.unlisted_cases import unlisted_case

    with simulations_shared():
        uc = unlisted_case(np.random.default_rng(seed), kind)
    paths = uc.write(tmp_path / "case")
    generate(uc.scenario, tmp_path / "bag", measured=True)
    return uc, paths


def _unexplained(paths: dict, tmp_path) -> dict:
    """diagnose on ``tmp_path/bag`` with the case's believed line and train: the report, checked
    to confirm no listed cause and to say ``unexplained``."""
    rep = _report(paths, tmp_path)
    confirmed = [r["cause"] for r in rep["ranking"]
                 if r["status"] == "confirmed" and r["cause"] != "none"]
    assert confirmed == [], rep["ranking"][:3]
    assert rep["cause"] == "unexplained", rep["unexplained"]
    return rep


def _fits(entries: list[dict]) -> list[CauseFit]:
    return [CauseFit(e["cause"], e.get("score", 1.0), e["parameters"]) for e in entries]


def full_diagnosis() -> Diagnosis:
    acc = [
        {"cause": "gradient", "parameters": {"start": 2400.0, "end": 2800.0, "permille": 4.0}},
        {"cause": "resistance", "parameters": {"a": 4000.0, "b": 160.0, "c": 9.5}},
        {"cause": "braking_rate", "parameters": {"f_start": 0.95, "f_end": 0.85}},
        {"cause": "odometer_scale", "parameters": {"scale": 1.01}},
        {"cause": "wheel_slip", "parameters": {"intervals": [[50.0, 52.0], [120.0, 122.5]]}},
        {"cause": "bursty_link", "parameters": {"p_good_bad": 0.03, "p_bad_good": 0.2}},
        {"cause": "brake_delay", "parameters": {"delay": 1.6}},
        {"cause": "mass", "parameters": {"mass": 310000.0}},
        {"cause": "clock_drift", "parameters": {"drift": 0.001}},
        {"cause": "power_limit", "parameters": {"p_spec": 9.5}},
        {"cause": "adhesion_section", "parameters": {"start": 3100.0, "end": 3400.0,
                                                     "factor": 0.7}},
        {"cause": "traction_delay", "parameters": {"delay": 1.5}},
    ]
    ranking = [{"cause": a["cause"], "score": 10.0 - i, "parameters": a["parameters"]}
               for i, a in enumerate(acc)] + [{"cause": "none", "score": 0.0, "parameters": {}}]
    return Diagnosis(cause="gradient", parameters=acc[0]["parameters"], ranking=_fits(ranking),
                     untestable=[], gain={}, accepted=_fits(acc), series={},
                     # where the core reports the fitted slip fraction of each episode
                     evidence={"wheel_slip": {"details": {"slip_fraction": [0.1, 0.12]}}})


def fake_data(duration=600.0, rate=10.0):
    """What write_model reads of the data: odometer stamps (train clock) and speeds."""
    t = np.arange(0.0, duration + 1e-9, 1.0 / rate) + 1.5e9
    return SimpleNamespace(odo_stamp=t, odo_speed=np.full_like(t, 10.0),
                           balise_stamp=np.array([]))


def test_model_dir_holds_every_accepted_cause_and_loads(metro, tmp_path):
    dg = full_diagnosis()
    tool.write_model(tmp_path, dg, metro.line_path, metro.train_path, fake_data())
    d = tmp_path / "model"
    sc = with_model(metro, d)
    eff = sc.effects
    assert sorted(eff.active()) == sorted(set(CAUSES) - {"gradient", "resistance"})
    # gradient in line.yaml: mapped + 4 per mille on [2400, 2800) (metro_demo: 18 there)
    assert sc.line.gradient_permille(2500.0) == pytest.approx(22.0)
    assert sc.line.gradient_permille(2350.0) == pytest.approx(18.0)
    assert sc.line.gradient_permille(2850.0) == pytest.approx(18.0)
    assert sc.line.gradient_permille(2950.0) == pytest.approx(-15.0)
    assert eff.gradient is None  # it is in the line itself
    assert (sc.train.davis.a, sc.train.davis.b, sc.train.davis.c) == (4000.0, 160.0, 9.5)
    assert sc.train.mass == metro.train.mass and sc.true_train.mass == 310000.0
    assert eff.braking_rate.value(0.0) == pytest.approx(0.95)
    assert eff.braking_rate.value(600.0 / 1.001) == pytest.approx(0.85)
    assert eff.brake_delay.delay == 1.6 and eff.odometer_scale.scale == 1.01
    assert eff.wheel_slip.slip_fraction == pytest.approx(0.11)
    assert eff.wheel_slip.intervals[0] == pytest.approx((50.0 / 1.001, 52.0 / 1.001), abs=1e-3)
    assert (eff.bursty_link.p_good_bad, eff.bursty_link.p_bad_good) == (0.03, 0.2)
    assert eff.clock_drift.drift == 0.001
    assert eff.power_limit.p_spec == 9.5 and eff.traction_delay.delay == 1.5
    assert eff.adhesion_section.as_tuple() == (3100.0, 3400.0, 0.7)
    # believed extras (balises, stations, performance) survive
    assert sc.line.balises == metro.line.balises and sc.line.stations == metro.line.stations
    assert sc.train.performance == metro.train.performance


def test_model_dir_of_none_is_the_believed_model(metro, tmp_path):
    dg = Diagnosis(cause="none", parameters={}, ranking=[CauseFit("none", 0.0, {})],
                   untestable=[], evidence={}, gain={}, accepted=[])
    tool.write_model(tmp_path, dg, metro.line_path, metro.train_path, fake_data())
    sc = with_model(metro, tmp_path / "model")
    assert sc.line == metro.line and sc.train == metro.train and sc.effects.active() == []
    raw = yaml.safe_load((tmp_path / "model" / "effects.yaml").read_text())
    assert raw == {}
    parse_effects(Section(raw, "effects.yaml"), 600.0)


def test_model_dir_runs_in_the_generator(metro, tmp_path, ros_env):
    tool.write_model(tmp_path, full_diagnosis(), metro.line_path, metro.train_path, fake_data())
    out = subprocess.run([sys.executable, "-m", "train_sim.generate", "--scenario",
                          "metro_demo", "--model", str(tmp_path / "model"), "--duration",
                          "120", "--measured", "--out", str(tmp_path / "bag")],
                         capture_output=True, text=True, timeout=180, env=ros_env)
    assert out.returncode == 0, out.stderr[-2000:]
    bag = read_bag(tmp_path / "bag")
    assert bag.topics["odometer"] and "ground_truth" not in bag.topics


# ------------------------------------------------------------------------------------------------
# With the core: report shape, ground truth never read, the model runs
# ------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def diagnosed(metro, tmp_path_factory):
    """metro_demo (300 s) with ground truth in the bag: garbage values and raw garbage."""
    d = tmp_path_factory.mktemp("diag")
    res = simulate(metro.with_changes(duration=300.0))
    write_bag(d / "measured", res)

    def garbage(w, t_recv, stamp, fields):
        bad = dict(fields, position=fields["position"] + 1234.5, velocity=-99.0,
                   acceleration=42.0, braking_rate=0.1)
        w.write("ground_truth", stamp + 7.0, bad, t_ns=int(round(t_recv * 1e9)))

    write_bag(d / "with_gt", res, gt=garbage)
    with BagWriter(d / "raw_gt") as w:
        for t_recv, topic, stamp, fields in res.received_events():
            t_ns = int(round(t_recv * 1e9))
            if topic == "ground_truth":
                w.write_raw(topic, "train_interfaces/msg/TrainState", t_ns, b"\x00\x01garbage")
            else:
                w.write(topic, stamp, fields, t_ns=t_ns)
    out = {}
    for name in ("measured", "with_gt", "raw_gt"):
        rc = tool.main(["--bag", str(d / name), "--line", metro.line_path, "--train",
                        metro.train_path, "--out", str(d / f"out_{name}"), "--quiet"])
        out[name] = (rc, d / f"out_{name}")
    return out


@pytest.mark.slow
def test_report_has_the_contract_shape(diagnosed, capsys):
    rc, out = diagnosed["measured"]
    assert rc == 0
    rep = json.loads((out / "report.json").read_text())
    assert list(rep) == REPORT_KEYS
    # cause: the first confirmed entry (none when it is none itself), else unexplained
    first = next(r for r in rep["ranking"] if r["status"] == "confirmed") \
        if rep["cause"] != "unexplained" else None
    assert rep["cause"] == ("unexplained" if first is None else first["cause"])
    assert rep["parameters"] == ({} if first is None else first["parameters"])
    assert all(r["status"] in ("confirmed", "not confirmed", "rejected")
               for r in rep["ranking"])
    # the contract: "not confirmed" (with why) or "rejected" (a why where one is known: a fit
    # outside its physical range, a section that claims nothing more than a braking rate)
    assert all("why" in r for r in rep["ranking"] if r["status"] == "not confirmed")
    assert all("why" not in r for r in rep["ranking"] if r["status"] == "confirmed")
    assert (rep["cause"] == "unexplained") == (
        bool(rep["unexplained"]) and not any(r["status"] == "confirmed" and r["cause"] != "none"
                                             for r in rep["ranking"]))
    for u in rep["unexplained"]:
        assert set(u) == {"phase", "where", "when", "speed", "size", "best_listed"}
        assert u["phase"] in ("traction", "coasting", "braking", "standstill", "all")
    names = [r["cause"] for r in rep["ranking"]]
    assert "none" in names and len(set(names)) == len(names)
    assert set(names) | {u["cause"] for u in rep["untestable"]} == set(CAUSES) | {"none"}
    assert all(isinstance(r["score"], float) for r in rep["ranking"])
    assert {"metric", "before", "after"} <= set(rep["gain"])
    assert all(set(u) == {"cause", "why"} for u in rep["untestable"])
    assert list(out.glob("*.svg")), "no plot written"
    for f in ("line.yaml", "train.yaml", "effects.yaml"):
        assert (out / "model" / f).is_file()


@pytest.mark.slow
def test_stated_score_formula_is_the_one_applied(diagnosed, capsys):
    """--help and report.json state 2 (ll_cause - ll_null) - k ln n - 2 ln K; every first-stage
    score in the report is that formula of the report's own log-likelihood gain, k and n."""
    _, out = diagnosed["measured"]
    rep = json.loads((out / "report.json").read_text())
    assert rep["evidence"]["_model"]["score"] == tool.SCORE_FORMULA
    assert "- k ln n - 2 ln K" in tool.SCORE_FORMULA
    with pytest.raises(SystemExit):
        tool.main(["--help"])
    assert "- k ln n - 2 ln K" in " ".join(capsys.readouterr().out.split())
    ev = {c: e for c, e in rep["evidence"].items() if not c.startswith("_")}
    k_causes = len(ev)
    assert k_causes >= 9
    for cause, e in ev.items():
        stated = (2 * e["loglik_gain"] - e["n_params"] * math.log(e["n"])
                  - 2 * math.log(k_causes))
        # the report rounds to 3 decimals: 2 x 0.0005 + 0.0005
        assert e["score_alone"] == pytest.approx(stated, abs=2e-3), cause


@pytest.mark.slow
def test_ground_truth_is_never_read(diagnosed):
    reports = {k: json.loads((o / "report.json").read_text()) for k, (rc, o) in
               diagnosed.items()}
    assert all(rc == 0 for rc, _ in diagnosed.values())
    assert reports["with_gt"] == reports["measured"]
    assert reports["raw_gt"] == reports["measured"]


@pytest.mark.slow
def test_summary_last_line_is_the_cause(metro, tmp_path, capsys, diagnosed):
    _, out = diagnosed["measured"]
    rep = json.loads((out / "report.json").read_text())
    bag = out.parent / "measured"
    assert tool.main(["--bag", str(bag), "--line", metro.line_path, "--train",
                      metro.train_path, "--out", str(tmp_path / "o"), "--quiet"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[-1] == f"cause: {rep['cause']}"


# ------------------------------------------------------------------------------------------------
# Hide an effect and find it (train_sim.cases: varied lines, trains, links, drivers)
# ------------------------------------------------------------------------------------------------

# (cause(s), size, seed): seeds fixed in advance, not picked for passing. Known failures of the
# core are marked xfail(strict): the mark must go when the core is fixed.
KNOWN: dict = {}  # (cause, seed) -> reason
SPECS = [(c, "plain", 200 + i) for i, c in enumerate(CAUSES)] + [
    (None, "plain", 230), (("gradient", "mass"), "plain", 231),
    (("traction_delay", "power_limit"), "plain", 232),
    (("power_limit", "traction_delay"), "plain", 234), ("gradient", "subtle", 240),
    ("brake_delay", "subtle", 241), ("power_limit", "subtle", 242),
    ("adhesion_section", "subtle", 243), ("traction_delay", "subtle", 244)]
HIDDEN = [pytest.param(c, s, n, marks=[pytest.mark.xfail(reason=KNOWN[(c, n)], strict=True)]
                       if (c, n) in KNOWN else []) for c, s, n in SPECS]
# (cause, seed) -> why one run cannot tell the hidden effect from a rival (docs/diagnose.md,
# check 3): found where it is and of its size, not confirmed with a reason that says so, and
# its effect the report's entry on its stretch
UNTOLD = {("gradient", 240): "a downhill gradient of -2.29 per mille run wholly in braking at "
                             "35-42 m/s, the braking asked for 0.90-1.24 of its mean there: "
                             "the braking law gives -0.2, the same force as braking x 0.96"}


def _id(p):
    c, s, n = p.values if hasattr(p, "values") else p
    return f"{'+'.join(c) if isinstance(c, tuple) else c}-{s}-{n}"

# main parameter of each cause and the tolerance when the fit gives no standard error for it
MAIN = {"gradient": "permille", "resistance": None, "braking_rate": None,
        "odometer_scale": "scale", "wheel_slip": None, "bursty_link": "p_bad_good",
        "brake_delay": "delay", "mass": "mass", "clock_drift": "drift", "power_limit": "p_spec",
        "adhesion_section": "factor", "traction_delay": "delay"}
Z = 4.0  # an estimate further than 4 standard errors from the truth fails


def _se(evidence: dict, cause: str, key: str) -> float:
    se = (evidence.get(cause) or {}).get("std_errors", {}).get(key)
    if isinstance(se, list):
        se = max((s for s in se if s is not None), default=None)
    return float(se) if se is not None and math.isfinite(se) else math.nan


def check_parameters(cause: str, est: dict, truth: dict, evidence: dict, v_ref: float) -> None:
    """|estimate - true| within Z standard errors (as the fit reports them); section ends and
    slip edges, which have no standard error, within the search resolution."""
    if cause == "gradient":  # permille first (below), then the ends
        se = _se(evidence, cause, "permille")
        assert abs(est["permille"] - truth["permille"]) <= Z * se, (est, truth, se)
        assert abs(est["start"] - truth["start"]) <= 100.0, (est, truth)
        assert abs(est["end"] - truth["end"]) <= 100.0, (est, truth)
        return
    if cause == "adhesion_section":  # factor (below), then the ends
        se = _se(evidence, cause, "factor")
        assert abs(est["factor"] - truth["factor"]) <= Z * se, (est, truth, se)
        assert abs(est["start"] - truth["start"]) <= 100.0, (est, truth)
        assert abs(est["end"] - truth["end"]) <= 100.0, (est, truth)
        return
    if cause == "wheel_slip":
        assert len(est["intervals"]) == len(truth["intervals"]), (est, truth)
        assert len(est["depths"]) == len(est["intervals"]), est
        for (a0, a1), (b0, b1) in zip(est["intervals"], truth["intervals"]):
            assert abs(a0 - b0) <= 0.5 and abs(a1 - b1) <= 0.5, (est, truth)
        return
    if cause == "resistance":  # the force at v_ref; SE bound without the covariances
        se = (_se(evidence, cause, "a") + v_ref * _se(evidence, cause, "b")
              + v_ref**2 * _se(evidence, cause, "c"))
        err = abs(sum(est[k] * v_ref**i for i, k in enumerate("abc"))
                  - sum(truth[k] * v_ref**i for i, k in enumerate("abc")))
        assert err <= Z * se, (err, se, est, truth)
        return
    if cause == "braking_rate":
        for k in ("f_start", "f_end"):
            se = _se(evidence, cause, k)
            assert abs(est[k] - truth[k]) <= Z * se, (k, est, truth, se)
        return
    k = MAIN[cause]
    se = _se(evidence, cause, k)
    if cause in ("brake_delay", "traction_delay") and not math.isfinite(se):
        se = 0.05  # the delay grid's step
    assert math.isfinite(se) and se > 0, (cause, k, evidence.get(cause))
    assert abs(est[k] - truth[k]) <= Z * se, (k, est[k], truth[k], se)


def _search(case, case_dir, bag):
    """diagnose's greedy search (``search._Search``) set up on ``bag``, the line and train of
    ``case`` written to ``case_dir``, the default config: for tests of its stages."""
    from train_core.model import load_line, load_train

    from train_estimation.core.offline.diagnose import search as S
    from train_estimation.core.offline.diagnose.causes import REGISTRY
    from train_estimation.core.offline.diagnose.motion import Motion
    from train_estimation.core.offline.diagnose.run import DiagConfig, prepare

    paths = case.write(case_dir)
    cfg = DiagConfig()
    line, train = load_line(paths["line"]), load_train(paths["train"])
    run = prepare(tool.read_measured(bag), line, cfg, train)
    own = {c.name: r for c in REGISTRY if (r := c.own_test(run)) is not None}
    return S._Search(Motion(run, line, train, cfg), cfg, own, set())


def _diagnosed(case, tmp_path) -> tuple[dict, dict]:
    """The case (train_sim.cases) written, simulated into a measured bag and diagnosed as a
    user runs the tool (no plots: they have tests of their own): (report.json, the truth over
    the bag's odometer stamps)."""
    paths = case.write(tmp_path / "case")
    generate(case.scenario, tmp_path / "bag", measured=True)
    bag = read_bag(tmp_path / "bag")
    stamps = np.array([s for _, s, _ in bag.topics["odometer"]])
    truth = case.truth_in_bag(float(stamps.min()), float(stamps.max()))
    return _report(paths, tmp_path), truth


@pytest.mark.slow
@pytest.mark.parametrize("cause,size,seed", HIDDEN, ids=[_id(p) for p in HIDDEN])
def test_hidden_effect_is_found(cause, size, seed, tmp_path, capsys):
    case = make_case(np.random.default_rng(seed), cause, size)
    rep, truth = _diagnosed(case, tmp_path)
    assert capsys.readouterr().out.strip().splitlines()[-1] == f"cause: {rep['cause']}"
    assert (tmp_path / "out" / "report.html").is_file()
    assert not list((tmp_path / "out").glob("*.svg"))  # --no-plots
    names = [r["cause"] for r in rep["ranking"]]
    if not case.causes:
        assert rep["cause"] == "none", rep["ranking"][:3]
        return
    if (case.expected, seed) in UNTOLD:
        from train_estimation.core.offline.diagnose.confirm import UNDECIDED

        fit = next(r for r in rep["ranking"] if r["cause"] == case.expected)
        assert rep["cause"] == "unexplained", (case.truth, rep["ranking"][:3])
        assert fit["status"] == "not confirmed" and fit["why"].startswith(UNDECIDED), fit
        assert rep["unexplained"][0]["best_listed"]["cause"] == case.expected, rep["unexplained"]
        check_parameters(case.expected, fit["parameters"], truth[case.expected],
                         rep["evidence"], case.v_ref)
        return
    if len(case.causes) == 1:
        assert rep["cause"] == case.expected, (case.truth, rep["ranking"][:3])
    else:
        assert set(names[:2]) == set(case.causes), (case.truth, rep["ranking"][:3])
        assert all(r["status"] == "confirmed" for r in rep["ranking"][:2]), rep["ranking"][:3]
    for c in case.causes:
        est = next(r["parameters"] for r in rep["ranking"] if r["cause"] == c)
        check_parameters(c, est, truth[c], rep["evidence"], case.v_ref)
        # and the issue's target measure, recorded for the benchmark's table
        err = main_error(c, est, truth[c], case.nominal[c], case.v_ref)
        print(f"{c}: main-parameter error {err:.2f} of the effect's size")
    # the extended model holds the causes found and loads in the simulator
    sc = with_model(case.scenario, tmp_path / "out" / "model")
    in_model = set(sc.effects.active())
    if sc.line.gradients != case.scenario.line.gradients:
        in_model.add("gradient")
    if sc.train.davis != case.scenario.train.davis:
        in_model.add("resistance")
    assert set(case.causes) <= in_model, in_model


def _gradient_over_an_approach(tmp_path, through: bool) -> tuple[dict, tuple, float]:
    """A downhill gradient the map lacks, -5 per mille, on the stretch of a braking-to-stop
    approach that ``train_sim.cases`` draws for a low-adhesion section (seed 8: a regional
    line, 7,679-8,600 m before the stop at 8,661 m, braked over at 10-32 m/s at a command
    within 10 % of its mean); with ``through``, on from there past the stop by as much again
    (the train leaves the station over it in traction). Diagnosed as a user runs the tool:
    (report.json, the gradient's stretch, its per mille)."""
    case = make_case(np.random.default_rng(8), "adhesion_section", "plain")
    sec = case.truth["adhesion_section"]
    stop = min(s.position for s in case.scenario.timetable if s.position >= sec["end"])
    start, end, pm = sec["start"], sec["end"], -5.0
    if through:
        end = stop + (end - start)
    eff = parse_effects(Section({"gradient": {"start": start, "end": end, "permille": pm}},
                                "test.effects"), case.scenario.duration)
    paths = case.write(tmp_path / "case")
    generate(case.scenario.with_effects(eff), tmp_path / "bag", measured=True)
    return _report(paths, tmp_path), (start, end), pm


@pytest.mark.slow
@pytest.mark.parametrize("searched", ["adhesion_section", "gradient"])
def test_a_gradient_braked_through_at_one_command_is_not_told_from_a_section(
        tmp_path, monkeypatch, searched):
    """Braked over at one command, a downhill gradient the map lacks and braking weaker there
    are the same force, and one run cannot tell them apart (docs/diagnose.md, check 3: the
    braking law). On these data the search takes the section; with the section left out of
    it, it takes the gradient (as it can on other data: the search's pick between them is
    noise). From either side the verdict is the same: not confirmed, the reason naming the
    rival and what would tell, the 2 ln LR within +-9, and the effect reported as left in
    braking on its stretch. (The gradient was confirmed, with a caveat, before the braking
    law judged it.)"""
    from train_estimation.core.offline.diagnose.causes.adhesion_section import AdhesionSection
    from train_estimation.core.offline.diagnose.confirm import UNDECIDED

    if searched == "gradient":
        monkeypatch.setattr(AdhesionSection, "untestable",
                            lambda self, run, cfg, own: "left out by the test")
    rep, (s0, s1), pm = _gradient_over_an_approach(tmp_path, through=False)
    assert rep["cause"] == "unexplained", rep["ranking"][:2]
    assert not [r for r in rep["ranking"] if r["status"] == "confirmed"], rep["ranking"][:2]
    fit = next(r for r in rep["ranking"] if r["cause"] == searched)
    assert fit["status"] == "not confirmed" and fit["why"].startswith(UNDECIDED), fit
    rival = "downhill gradient" if searched == "adhesion_section" else "low-adhesion section"
    assert rival in fit["why"] and "traction or coasting" in fit["why"], fit["why"]
    lr = rep["evidence"]["_model"]["confirmation"]["checks"][searched]["braking_law"]["lr"]
    assert abs(lr) <= 9.0, lr
    u = rep["unexplained"][0]
    assert u["phase"] == "braking" and u["best_listed"]["cause"] == searched, u
    overlap = min(u["where"][1], s1) - max(u["where"][0], s0)
    assert overlap > 0.8 * (s1 - s0), (u, s0, s1)
    # 5 per mille downhill is 0.049 m/s^2 less braking there (less the rotating masses' share)
    assert abs(u["size"] + 9.81 * pm / 1000.0) < 0.015, u
    assert "one run cannot tell" in unexplained.unexplained_line(u)


@pytest.mark.slow
def test_the_same_gradient_run_on_in_traction_is_confirmed(tmp_path):
    """The gradient of the test above, on from the approach past the stop by as much again: the
    train leaves the station over it in traction, where braking weaker explains nothing. The
    braking law favours the fixed force far beyond 9, and the gradient is confirmed where it
    is."""
    rep, (s0, s1), pm = _gradient_over_an_approach(tmp_path, through=True)
    assert rep["cause"] == "gradient", rep["ranking"][:2]
    assert rep["ranking"][0]["status"] == "confirmed", rep["ranking"][0]
    lr = rep["evidence"]["_model"]["confirmation"]["checks"]["gradient"]["braking_law"]["lr"]
    assert lr < -9.0, lr
    check_parameters("gradient", rep["parameters"], {"start": s0, "end": s1, "permille": pm},
                     rep["evidence"], 0.0)


def test_plots_draw_what_the_series_hold(tmp_path):
    assert write_plots({}, tmp_path) == []
    rng = np.random.default_rng(0)
    t = np.arange(0.0, 300.0, 0.5)
    x = 10.0 * t
    s = {"t": t, "position": x, "speed": np.full_like(t, 10.0),
         "residual_accel": rng.normal(0, 0.05, t.size), "odo_t": t, "odo_speed": 10 + 0 * t,
         "line_gradient": [(0.0, 1000.0, 5.0), (1000.0, 3000.0, -2.0)],
         "gradient_section": (1200.0, 1500.0, 4.0), "stations": [("A", 100.0)],
         "slip_intervals": [[50.0, 52.0]], "f_t": ([0.0, 300.0], [0.95, 0.9]),
         "loss_runs": np.array([1, 1, 2, 5, 1, 3]), "loss_fraction": 0.1,
         "phase": np.arange(t.size) % 3,
         "unexplained": [{"phase": "braking", "where": None, "when": None, "speed": [2, 8],
                          "size": 0.05, "best_listed": None}]}
    names = {p.name for p in write_plots(s, tmp_path)}
    assert names == {"residual_position.svg", "residual_speed.svg", "speed_trace.svg",
                     "loss_runs.svg", "residual_phases.svg"}
    import xml.etree.ElementTree as ET

    for n in names:  # each a drawn figure: a grid, ticks and its series
        assert len(list(ET.parse(tmp_path / n).iter("{http://www.w3.org/2000/svg}path"))) >= 4
    loss = ET.parse(tmp_path / "loss_runs.svg")
    assert len(list(loss.iter("{http://www.w3.org/2000/svg}rect"))) >= 4  # bars (k = 1, 2, 3, 5)


def test_a_negative_davis_fit_is_written_as_the_closest_nonnegative_curve(metro, tmp_path):
    acc = [{"cause": "resistance", "parameters": {"a": 5000.0, "b": -100.0, "c": 14.0}}]
    dg = Diagnosis(cause="resistance", parameters=acc[0]["parameters"],
                   ranking=[CauseFit("resistance", 5.0, acc[0]["parameters"])],
                   untestable=[], evidence={}, gain={}, accepted=_fits(acc))
    data = fake_data()
    data.odo_speed[:] = np.linspace(0.0, 20.0, data.odo_speed.size)
    tool.write_model(tmp_path, dg, metro.line_path, metro.train_path, data)
    d = with_model(metro, tmp_path / "model").train.davis
    assert min(d.a, d.b, d.c) >= 0.0
    v = np.linspace(0.0, 20.0, 50)
    fit = 5000.0 - 100.0 * v + 14.0 * v * v
    assert np.max(np.abs(d.force(v) - fit)) < 0.1 * np.max(fit)


def test_a_fit_the_files_cannot_hold_is_left_out_of_the_model_with_a_note(metro, tmp_path):
    acc = [{"cause": "gradient", "parameters": {"start": 2400.0, "end": 2800.0,
                                                "permille": -90.0}},
           {"cause": "odometer_scale", "parameters": {"scale": 3.0}},
           {"cause": "mass", "parameters": {"mass": 300000.0}}]
    dg = Diagnosis(cause="gradient", parameters=acc[0]["parameters"],
                   ranking=_fits(acc), untestable=[], evidence={}, gain={},
                   accepted=_fits(acc))
    model = tool.write_model(tmp_path, dg, metro.line_path, metro.train_path, fake_data())
    sc = with_model(metro, tmp_path / "model")
    assert sc.line == metro.line and sc.effects.active() == ["mass"]
    text = " ".join(model["notes"])
    assert "gradient not in the model" in text and "odometer_scale not in the model" in text
    assert "gradient not in the model" in (tmp_path / "model" / "line.yaml").read_text()


@pytest.mark.slow
def test_a_long_slip_episode_is_one_episode_and_a_spurious_one_is_dropped(metro, metro_run,
                                                                            tmp_path):
    """A 7 s slip episode (+10 %) given to the episode refinement in pieces (its onset and its
    end, where the null's innovations show it) and with a spurious episode where nothing
    happened: the pieces merge into one interval within one odometer period (0.2 s at the
    analysis' 5 Hz) plus 0.3 s of the boundary profile of each piece, and the spurious one does
    not pay its BIC penalty; the cause's own search returns the one episode with its depth."""
    from train_core.effects import Effects, WheelSlipEffect

    from train_estimation.core.offline.diagnose import DiagConfig, Motion, Null, Stage, prepare
    from train_estimation.core.offline.diagnose.causes.wheel_slip import (
        CAUSE,
        _fractions,
        refine_episodes,
    )

    t, v = metro_run.truth["t"], metro_run.truth["velocity"]
    fast = np.flatnonzero(np.convolve(v > 8.0, np.ones(120), "valid") == 120)
    t0 = float(t[fast[len(fast) // 3]]) + 1.0  # 12 s at > 8 m/s from here: the episode inside
    sc = metro.with_changes(duration=300.0,
                            effects=Effects(wheel_slip=WheelSlipEffect(((t0, t0 + 7.0),), 0.1)))
    bag = write_bag(tmp_path / "bag", simulate(sc))
    cfg = DiagConfig()
    run = prepare(tool.read_measured(bag), sc.line, cfg)
    st = Stage(Motion(run, sc.line, sc.train, cfg), Null(), cfg)
    shift = run.t_first - sc.stamp_epoch  # true time of the first odometer sample
    a, b = t0 - shift, t0 + 7.0 - shift
    quiet = float(run.odo_t[np.searchsorted(run.odo_t, b + 60.0)])
    pen = 3 * math.log(st.n_meas)
    ivs, th, se_th, _ = refine_episodes(st, [(a, a + 1.5), (b - 1.5, b), (quiet, quiet + 2.0)],
                                        pen)
    assert len(ivs) == 1, ivs
    assert abs(ivs[0][0] - a) <= 0.5 and abs(ivs[0][1] - b) <= 0.5, (ivs, a, b)
    eps, se = _fractions(th, se_th)
    assert abs(eps[0] - 0.1) <= 4 * se[0], (eps, se)
    _, _, params, ses, _ = CAUSE.fit(st)
    assert len(params["intervals"]) == 1, params
    assert abs(params["intervals"][0][0] - a) <= 0.5 and abs(params["intervals"][0][1] - b) <= 0.5
    # a slip: the odometer reads more than the train moves; its depth is the true -0.1 (the
    # columns are the odometer's own, slipped speed: their coefficient alone would be 0.1 / 1.1)
    assert abs(params["depths"][0] + 0.1) <= max(4 * ses["depths"][0], 0.003), (params, ses)


@pytest.mark.slow
def test_a_slip_that_builds_up_and_dies_away_is_found_with_its_peak(metro, metro_run, tmp_path):
    """A hidden slip episode of 6 s whose fraction rises and falls as a half sine (peak +15 %:
    adhesion lost and regained, not a step): the tool names wheel_slip, its found slip time
    overlaps the true one with 1 - IoU <= 0.3 and the overlapping episode's depth is the peak,
    -0.15, within 20 %. (A one-fraction step fitted to it comes out at about the mean, 2/pi of
    the peak, or split into several shallower pieces.)"""
    from train_core.effects import Effects, WheelSlipEffect

    t, v = metro_run.truth["t"], metro_run.truth["velocity"]
    fast = np.flatnonzero(np.convolve(v > 8.0, np.ones(120), "valid") == 120)
    t0 = float(t[fast[len(fast) // 3]]) + 1.0  # 12 s at > 8 m/s from here: the episode inside
    sc = metro.with_changes(duration=300.0, effects=Effects(
        wheel_slip=WheelSlipEffect(((t0, t0 + 6.0),), 0.15, shape="sine")))
    bag = write_bag(tmp_path / "bag", simulate(sc))
    assert run_tool(bag, metro.line_path, metro.train_path, tmp_path / "out") == 0
    rep = json.loads((tmp_path / "out" / "report.json").read_text())
    assert rep["cause"] == "wheel_slip", rep["ranking"][:3]
    est = rep["ranking"][0]["parameters"]
    first = min(s for _, s, _ in read_bag(bag).topics["odometer"])
    a, b = sc.stamp_epoch + t0 - first, sc.stamp_epoch + t0 + 6.0 - first  # no clock drift
    ivs = est["intervals"]
    inter = sum(max(0.0, min(b, y) - max(a, x)) for x, y in ivs)
    union = (b - a) + sum(y - x for x, y in ivs) - inter
    assert 1.0 - inter / union <= 0.3, (ivs, a, b)
    k = int(np.argmax([max(0.0, min(b, y) - max(a, x)) for x, y in ivs]))
    assert abs(est["depths"][k] + 0.15) <= 0.2 * 0.15, (est, a, b)


@pytest.mark.slow
def test_each_slip_episode_is_held_out_on_its_own(metro, metro_run, tmp_path):
    """A 7 s slip episode (+10 %) and a 2 s one where nothing happened, given as one confirmed
    wheel_slip: held out one by one (its fraction fitted on alternate odometer samples, scored
    on the others), the true episode is confirmed far beyond the score's 2 and the other is
    dropped, with its depth and column."""
    from train_core.effects import Effects, WheelSlipEffect

    from train_estimation.core.offline.diagnose import DiagConfig, Motion, Null, Stage, prepare
    from train_estimation.core.offline.diagnose.confirm import heldout_episodes

    t, v = metro_run.truth["t"], metro_run.truth["velocity"]
    fast = np.flatnonzero(np.convolve(v > 8.0, np.ones(120), "valid") == 120)
    t0 = float(t[fast[len(fast) // 3]]) + 1.0
    sc = metro.with_changes(duration=300.0,
                            effects=Effects(wheel_slip=WheelSlipEffect(((t0, t0 + 7.0),), 0.1)))
    bag = write_bag(tmp_path / "bag", simulate(sc))
    cfg = DiagConfig()
    run = prepare(tool.read_measured(bag), sc.line, cfg)
    mo = Motion(run, sc.line, sc.train, cfg)
    st = Stage(mo, Null(), cfg, big=False)
    shift = run.t_first - sc.stamp_epoch
    a, b = t0 - shift, t0 + 7.0 - shift
    quiet = float(run.odo_t[np.searchsorted(run.odo_t, b + 60.0)])
    th = [0.1 / 1.1, 0.02]  # columns: the slipped speed (motion.slip_cols); 2 % where none is
    fit = CauseFit("wheel_slip", 10.0, {"intervals": [[a, b], [quiet, quiet + 2.0]],
                                        "depths": [-0.1, -0.02]},
                   std_errors={"depths": [0.003, 0.003], "slip_fraction": [0.003, 0.003]},
                   extra={"column": th, "slip_fraction": [0.1, 0.02]})
    out = heldout_episodes(mo, Null(), fit, cfg, (st.q, st.r_s))
    assert [e["confirmed"] for e in out] == [True, False], out
    assert out[0]["z"] > 10.0, out
    assert fit.parameters == {"intervals": [[a, b]], "depths": [-0.1]}
    assert fit.extra["column"] == [th[0]] and fit.std_errors["depths"] == [0.003]


def test_a_slip_episode_must_step_in_the_odometer_readings():
    """contradict.slip_step on 10 Hz readings (speed noise 0.08 m/s) of a train whose traction
    command drops from 0.3 to 0.12 m/s^2 (through a 0.5 s lag) inside the episode, and which
    delivers 80 % of what is commanded: its speed bends there but does not step. An episode
    fitted at +2 % where the readings do not step is contradicted; readings that read 5 %
    more inside [t0, t1) show that step (within 3 SE) and are not, and support it; a step of
    0.1 % is below what the readings resolve: neither contradicted nor supported, so not the
    slip's (it was confirmed, as nothing could contradict it); another episode's readings
    nearby are left out."""
    from types import SimpleNamespace

    from train_estimation.core.offline.diagnose.contradict import slip_step

    rng = np.random.default_rng(5)
    g = np.arange(0.0, 30.0, 0.01)
    a_tr0 = 0.12 + 0.18 * np.exp(-np.clip(g - 14.0, 0.0, None) / 0.5)
    v_g = 14.0 + 0.8 * np.concatenate([[0.0], np.cumsum(0.5 * (a_tr0[1:] + a_tr0[:-1]) * 0.01)])
    t = np.arange(0.0, 30.0, 0.1)
    v = np.interp(t, g, v_g)
    t0, t1 = 13.0, 17.6
    inside = (t >= t0) & (t < t1)
    noise = 0.08 * rng.standard_normal(t.size)

    def mo(speed):
        return SimpleNamespace(run=SimpleNamespace(odo_t=t, odo_v=speed,
                                                   odo_rv=np.full(t.size, 0.08 ** 2)),
                               grid=SimpleNamespace(t=g), a_tr0=a_tr0, a_br0=np.zeros(g.size))

    smooth = slip_step(mo(v + noise), (t0, t1), 0.02)
    assert smooth["contradicted"] and not smooth["supported"], smooth
    eps = 0.05  # the odometer reads (1 + eps) v inside: column coefficient eps / (1 + eps)
    slipped = slip_step(mo(v * np.where(inside, 1.0 + eps, 1.0) + noise), (t0, t1),
                        eps / (1 + eps))
    assert not slipped["contradicted"] and slipped["supported"], slipped
    assert abs(slipped["step"] - eps / (1 + eps)) < 3 * slipped["se"], slipped
    small = slip_step(mo(v + noise), (t0, t1), 0.001)
    assert not small["contradicted"] and not small["supported"], small
    # a true 8 % slip on [19, 22) within the window: its readings are left out as another
    # episode's, and the smooth episode is still contradicted
    near = v * np.where((t >= 19.0) & (t < 22.0), 1.08, 1.0) + noise
    beside = slip_step(mo(near), (t0, t1), 0.02, others=[(19.0, 22.0)])
    assert beside["contradicted"], beside


# ------------------------------------------------------------------------------------------------
# Effects outside the list (train_sim.unlisted_cases): no listed cause confirmed, the remainder
# described with the right phase. Seeds fixed in advance (one per kind, varied lines/trains).
# ------------------------------------------------------------------------------------------------

UNLISTED_KNOWN = {
    "tunnel_drag": "drag in a tunnel run at a steady speed is a gradient over the tunnel in one "
                   "run's data (docs/diagnose.md)",
    "wind": "a constant force for a minute is a gradient over the track run in that minute in "
            "one run's data (docs/diagnose.md)",
}
UNLISTED = [pytest.param(k, s, marks=[pytest.mark.xfail(reason=UNLISTED_KNOWN[k], strict=True)]
                         if k in UNLISTED_KNOWN else [])
            for k, s in (("brake_fade", 3), ("traction_gain", 4), ("tunnel_drag", 5),
                         ("wind", 6))]


@pytest.mark.slow
@pytest.mark.parametrize("kind,seed", UNLISTED, ids=lambda p: str(p))
def test_an_effect_outside_the_list_is_unexplained(kind, seed, tmp_path, capsys):
    uc, paths = _unlisted_bag(kind, seed, tmp_path)
    rep = _unexplained(paths, tmp_path)
    out = capsys.readouterr().out
    assert rep["unexplained"][0]["phase"] == uc.phase, rep["unexplained"]
    assert "unexplained:" in out
    # nothing confirmed: the model directory is the believed model
    assert yaml.safe_load((tmp_path / "out" / "model" / "effects.yaml").read_text()) == {}


@pytest.mark.slow
def test_a_cause_found_beside_causes_not_confirmed_is_confirmed_again_without_them(
        tmp_path, monkeypatch):
    """A brake fade at every stop (metro_demo, the bench's seed [29, 125]): the greedy stages
    accept a low-adhesion section at the last stop and a gradient before it that fills the
    section's excess there. The section is then not confirmed (the phase split contradicts
    it); the gradient, confirmed against a model that held the section, falls once it is
    confirmed again without it. (The gradient is seen in braking only, and a third of it
    shows in braking elsewhere, so the one-phase rule of the place test withdraws it first, and
    a resistance accepted beside them needs a negative Davis term, so the Davis check
    withdraws that first, after which the flexible term takes the other two; and the section
    cancels the gradient on the gradient's stretch, which the cancelling check sees when a
    tenth of a cause's effect lies there: these checks are off here (the cancelling check at
    its earlier quarter), so that this test sees the re-confirmation; with them, the verdict
    is the same.)"""
    from dataclasses import replace

    from train_estimation.core.offline.diagnose import confirm, contradict

    _, paths = _unlisted_bag("brake_fade", [29, 125], tmp_path)
    rep = _unexplained(paths, tmp_path)
    assert rep["unexplained"][0]["phase"] == "braking", rep["unexplained"]
    monkeypatch.setattr(confirm, "CONFIRM", replace(confirm.CONFIRM, one_phase_elsewhere=False,
                                                    data_bounds=False))
    monkeypatch.setattr(contradict, "CANCEL_SHARE", 0.25)
    rep = _unexplained(paths, tmp_path)
    by = {r["cause"]: r for r in rep["ranking"]}
    # at the noise of the model with all three accepted causes the phase split contradicts
    # the gradient before the re-confirmation is reached (it fell there when the confirmation
    # ran at the noise of the model without the last accepted cause); the rule itself:
    # test_only_causes_the_checks_contradicted_are_left_out_of_the_re_confirmation
    assert by["gradient"]["status"] == "not confirmed", by["gradient"]
    assert rep["unexplained"][0]["phase"] == "braking", rep["unexplained"]


@pytest.mark.parametrize("why_b,left_out", [
    ("held-out check failed: score Z 0.24 <= 2", False),
    ("below resolution: f_end -0.01 from nominal", False),
    ("contradicted by the phase split: the fitted effect ...", True),
    ("not a running resistance: ...", True)])
def test_only_causes_the_checks_contradicted_are_left_out_of_the_re_confirmation(
        monkeypatch, why_b, left_out):
    """Each cause is confirmed given the others in the model: an accepted cause that is not
    confirmed for want of evidence (its held-out check or its resolution) stays in the model
    the confirmed ones are confirmed in again, so a true one beside it is not taken down with
    it; one the checks contradicted is left out, and a confirmed cause that falls without it
    is not confirmed, with the reason."""
    from train_estimation.core.offline.diagnose import verdict as V
    from train_estimation.core.offline.diagnose.stage import Null

    seen = []

    def fake_confirm(mo, shift, accepted, *args, **kw):
        seen.append([a.cause for a in accepted])
        for a in accepted:  # the gradient holds only with the resistance beside it
            ok = a.cause != "gradient" or any(b.cause == "resistance" for b in accepted)
            a.status, a.why = ("confirmed", None) if ok else ("not confirmed", "held-out check "
                                                              "failed: needs the resistance")
        return {a.cause: {} for a in accepted}

    monkeypatch.setattr(V, "confirm", fake_confirm)
    monkeypatch.setattr(V, "joint_refit", lambda *a, **k: None)
    monkeypatch.setattr(V, "_null_of", lambda mo, shift, fits: Null(shift=shift))
    grad = CauseFit("gradient", 50.0, {}, status="confirmed")
    res = CauseFit("resistance", 40.0, {}, status="not confirmed", why=why_b)
    sr = SimpleNamespace(accepted=[grad, res], mo=None, null=Null(), cfg=None, own={})
    checks = {"gradient": {}, "resistance": {}}
    V.reconfirm(sr, {}, (1e-4, 1e-2), None, checks)
    if left_out:
        assert seen == [["gradient"]], seen
        assert grad.status == "not confirmed" and grad.why.startswith("without resistance"), \
            grad.why
    else:
        assert seen == [], seen  # nothing contradicted: the first confirmation stands
        assert grad.status == "confirmed", grad.why


# Effects of kinds the bench does not use (train_sim.unlisted_cases.TEST_KINDS): a traction loss
# above a speed (not a power limit's p_spec / v), a traction loss on a stretch (not a gradient),
# a balise that lies metres from its map position, an odometer that counts 1-2 % more or
# less from a time on (neither an odometer scale nor slip), a traction that moves 12-20 % more
# or less load from a stop on (not mass: the brake is load-weighed), an extra deceleration
# while coasting (not resistance nor a gradient), an extra resistance above a critical speed
# (bogies hunting: a step in speed, not a Davis curve), an extra resistance that decays as the
# train warms up (in time, not a Davis curve), an odometer that reads a constant speed more or
# less while moving (not a scale), braking limited by power above a knee speed (not a braking
# rate), a traction that fails for a minute or two (in time, in traction), a train clock
# that jumps by 0.5-3 s and one whose rate changes mid-run (neither is a drift).
# Seeds 11-13 fixed in advance.
TEST_KIND_KNOWN = {
    ("traction_trip", 12): "the traction fails while the train holds 35 m/s in traction on one "
                           "stretch: at one steady speed and command, a traction x0.6 there is "
                           "the same force as a gradient, which is confirmed"}
TEST_KIND = [pytest.param(k, s, marks=[pytest.mark.xfail(reason=TEST_KIND_KNOWN[(k, s)],
                                                         strict=True)]
                          if (k, s) in TEST_KIND_KNOWN else [])
             for k in ("traction_fade", "neutral_section", "misplaced_balise", "odometer_rescale",
                       "load_change", "coast_drag", "hunting_drag", "resistance_warmup",
                       "odometer_bias", "brake_power_limit", "traction_trip", "clock_step",
                       "clock_slew")
             for s in (11, 12, 13)]


@pytest.mark.slow
@pytest.mark.parametrize("kind,seed", TEST_KIND, ids=lambda p: str(p))
def test_an_effect_of_a_kind_the_bench_does_not_use_is_unexplained(kind, seed, tmp_path):
    uc, paths = _unlisted_bag(kind, seed, tmp_path)
    rep = _unexplained(paths, tmp_path)
    # a traction loss at every place shows in traction only; a loss on a stretch run in
    # traction may be `all` (a place remainder is named by phase only where the same track
    # is run in other phases too: docs/diagnose.md)
    phases = {uc.phase} if kind in ("traction_fade", "coast_drag", "brake_power_limit",
                                    "traction_trip") else {uc.phase, "all"}
    assert rep["unexplained"][0]["phase"] in phases, rep["unexplained"]
    if kind == "hunting_drag":
        # the resistance fitted to it needs a negative Davis term, or a force free in speed
        # fits better than any Davis curve, or the data's halves fit it differently (a step in
        # speed is no Davis curve: each half's curve is another); what remains reaches above
        # the critical speed
        res = next(r for r in rep["ranking"] if r["cause"] == "resistance")
        assert res["why"].startswith(("not a running resistance",
                                      "the data's halves fit it differently")), res
        v_crit = uc.scenario.unlisted.hunting_drag.v_crit
        assert rep["unexplained"][0]["speed"][1] > v_crit, (rep["unexplained"], v_crit)
    if kind in ("odometer_rescale", "odometer_bias"):
        # the odometer family's entry: what the odometer counts differently, as an error in m
        # of the sign of the change (it counts more: ahead of the train)
        u = rep["unexplained"][0]
        assert unexplained.on_odometer(u), u
        un = uc.scenario.unlisted
        more = un.odometer_rescale.factor - 1.0 if kind == "odometer_rescale" \
            else un.odometer_bias.bias
        assert np.sign(u["size"]) == np.sign(more) and abs(u["size"]) > 5.0, (u, un)
    if kind == "clock_step":
        # the step itself, where it happened (stamp seconds since the first odometer stamp: the
        # first sample is at true time 0 and the clock drifts by < 0.2 %), of its size
        u = rep["unexplained"][0]
        st = uc.scenario.unlisted.clock_step
        assert unexplained.clock_step(u), u
        assert abs(u["when"][0] - st.t0) < 1.0 and abs(u["size"] - st.step) < 0.01, (u, st)
    if kind == "clock_slew":
        # the change of rate from where it happened, of the sign of the change (the clock
        # reads more by the end when it runs faster)
        u = rep["unexplained"][0]
        sl = uc.scenario.unlisted.clock_slew
        assert unexplained.clock_rate(u), u
        assert abs(u["when"][0] - sl.t0) < 20.0 and np.sign(u["size"]) == np.sign(sl.rate), (u, sl)
    if kind == "misplaced_balise":
        # the entry is at that balise, and its offset is the balise's (reading minus the
        # train's position by the odometer: minus where it lies from its map position)
        mb = uc.scenario.unlisted.misplaced_balise
        pos = next(b.position for b in uc.case.scenario.line.balises if b.id == mb.balise_id)
        u = rep["unexplained"][0]
        assert u["where"] == [pytest.approx(pos, abs=0.01)] * 2, (u, pos)
        rounds = rep["evidence"]["_model"]["structure"]["tests"]
        se = next(r["balise"]["std_error"] for r in rounds if r["balise"]["significant"])
        assert abs(u["size"] + mb.offset) <= 4 * se, (u["size"], mb.offset, se)


@pytest.mark.slow
def test_a_gradient_seen_in_one_phase_that_shows_elsewhere_in_that_phase_is_not_confirmed(
        tmp_path):
    """An extra deceleration while coasting (metro_demo, test kind coast_drag at seed 18, found
    while developing): the run coasts mostly on one stretch, where a gradient fits it, seen in
    coasting only. Continued beyond its stretch, the gradient is needed in coasting elsewhere at
    about a third of itself (beyond 3 SE, chi-square p < 1e-3): less than the half that
    contradicts a place effect, but evidence for an effect of the phase, which a cause seen in
    one phase cannot be told from. It was confirmed; now it is not, and the remainder is
    named in coasting."""
    _, paths = _unlisted_bag("coast_drag", 18, tmp_path)
    rep = _unexplained(paths, tmp_path)
    grad = next(r for r in rep["ranking"] if r["cause"] == "gradient")
    assert grad["why"].startswith("cannot be told from a force acting during that time: it "
                                  "shows in coasting only"), grad["why"]
    assert rep["unexplained"][0]["phase"] == "coasting", rep["unexplained"]


@pytest.mark.slow
def test_a_force_over_a_braking_approach_is_not_a_low_adhesion_section(tmp_path):
    """A tail wind of 40 kN from halfway down a braking approach to the stop after it (the
    bench's wind at seed [31, 9], highspeed): the braking there reads weaker, and a
    low-adhesion section (braking x 0.86 over the approach's last 300 m) was confirmed. The
    force does not follow the braking asked for (0.43 rising to 0.61 m/s^2 as the driver brakes
    harder against it); it ends where the train stops. Over the halves of the section's
    stretch (half its braking time each) it is a larger share of the lighter braking asked
    for in the first: x 0.839 and x 0.867 (z -5.3), not one factor, so the held-out check
    leaves it not confirmed (before that test, the braking law did: a force fixed there fitted
    better by 2 ln LR > 9), and the braking remainder is `unexplained` over the approach."""
    uc, paths = _unlisted_bag("wind", [31, 9], tmp_path)
    rep = _unexplained(paths, tmp_path)
    sec = next(r for r in rep["ranking"] if r["cause"] == "adhesion_section")
    assert sec["status"] == "not confirmed", sec
    assert sec["why"].startswith("the data's halves fit it differently: factor"), sec
    h = rep["evidence"]["_model"]["confirmation"]["checks"]["adhesion_section"]["held_out"][
        "halves"]
    q = h["quantities"]["factor"]
    assert q["disagree"] and q["z"] < -h["z_needed"], h
    assert q["folds"][0] < q["folds"][1] < 1.0, q
    u = rep["unexplained"][0]
    wind = uc.scenario.unlisted.wind
    assert u["phase"] in ("braking", "all") and u["when"] is not None, u
    # on the approach the wind acts on (the train stops before it ends)
    assert u["when"][0] < wind.t0 + 30.0 and u["when"][1] > wind.t0, (u, wind)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [11, 12, 13])
def test_an_odometer_that_rescales_mid_run_is_not_an_odometer_scale(seed, tmp_path):
    """One scale for the whole run fits an odometer that counts 1-2 % differently from a time
    on better than none (it was confirmed in all three); fitted over the first and the last
    half of the distance run, the scales differ beyond their standard errors (the halves
    test), or split by time, position and speed the fitted scale is needed about x0 before the
    rescale and x2 after: not confirmed. The scale after the rescale differs from the scale
    before it in the direction of the rescale."""
    uc, paths = _unlisted_bag("odometer_rescale", seed, tmp_path)
    rep = _report(paths, tmp_path)
    scale = next(r for r in rep["ranking"] if r["cause"] == "odometer_scale")
    assert scale["status"] == "not confirmed", scale
    assert scale["why"].startswith("not one scale") \
        or "effect on the odometer is needed" in scale["why"], scale["why"]
    halves = rep["evidence"]["_model"]["confirmation"]["checks"]["odometer_scale"][
        "held_out"]["halves"]["quantities"]["distance"]
    more = uc.scenario.unlisted.odometer_rescale.factor - 1.0
    assert np.sign(halves["scale"][1] - halves["scale"][0]) == np.sign(more), (halves, more)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [11, 12, 13])
def test_an_odometer_whose_error_grows_with_speed_is_not_an_odometer_scale(seed, tmp_path):
    """An odometer that reads (1 + k v / v_top) times the speed and counts it (a radar's
    error, k 1-2 %) was confirmed as one odometer scale in all three: most of the distance is
    run near the top speed. Against a count error that grows with speed (one parameter, as the
    scale), the balises and the odometer prefer the law: not confirmed, k fitted to a tenth,
    and the odometer's entry names the count's sign."""
    uc, paths = _unlisted_bag("odometer_speed_scale", seed, tmp_path)
    rep = _unexplained(paths, tmp_path)
    scale = next(r for r in rep["ranking"] if r["cause"] == "odometer_scale")
    assert scale["why"].startswith("a speed law fits better"), scale
    law = rep["evidence"]["_model"]["confirmation"]["checks"]["odometer_scale"]["count_law"]
    k = uc.scenario.unlisted.odometer_speed_scale.k
    assert law["lr"] > 9.0 and abs(law["k"] - k) < 0.1 * abs(k), (law, k)
    u = rep["unexplained"][0]
    assert unexplained.on_odometer(u) and np.sign(u["size"]) == np.sign(k), u


def test_a_power_limit_and_a_traction_delay_compose_in_either_order(metro, metro_run, tmp_path):
    """The limit caps the re-timed traction: the model of both is min(a_tr(t - s - d), p / v)
    whichever was accepted first (without it, one order added the delay's uncapped traction at
    a power-limited release, the other capped the traction as it was before the delay)."""
    from train_estimation.core.offline.diagnose import DiagConfig, Motion, Null, Stage, prepare
    from train_estimation.core.offline.diagnose.confirm import _null_of

    def traction_at(mo, timing):  # the believed traction with the commands re-timed
        return mo._part(timing, "traction")

    cfg = DiagConfig()
    run = prepare(tool.read_measured(write_bag(tmp_path / "bag", metro_run)), metro.line, cfg)
    mo = Motion(run, metro.line, metro.train, cfg)
    s = float(mo.shifts[mo.shifts > 0][0])
    d = float(mo.delays[mo.delays > 0.4][0])
    moving = mo.moving > 0
    p = 0.5 * float(np.max((mo.a_tr0 * mo.v_ref)[moving]))  # a limit the run meets
    pl = CauseFit("power_limit", 10.0, {"p_spec": p})
    td = CauseFit("traction_delay", 10.0, {"delay": metro.train.brake.delay + d},
                  extra={"offset": s, "extra": d})
    noise = (0.01, 0.01)  # the drift columns do not depend on it
    fv0 = Stage(mo, Null(shift=s), cfg, noise=noise, big=False).fv
    capped = np.minimum(traction_at(mo, s + d), p / np.maximum(mo.v_ref, 1e-3))
    want = mo.grid.integrate(((capped - traction_at(mo, s)) * mo.moving)[:, None],
                             mo.ev.t.size)[0][:, 0]
    assert np.max(np.abs(want)) > 0.05  # the limit and the delay both act in this run
    for order in ([pl, td], [td, pl]):
        got = Stage(mo, _null_of(mo, s, order), cfg, noise=noise, big=False).fv - fv0
        assert np.allclose(got, want, atol=1e-9), ([f.cause for f in order],
                                                   np.max(np.abs(got - want)))


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="the mass is accepted second and held out at its Z, but "
                   "the data's halves fit it 1.6 % apart (2.61e5 and 2.569e5 kg, z 8.7 beyond "
                   "3.3) since each fold's fit runs on the filter of every reading: with the "
                   "power limit fitted beside it, the two folds weigh its traction differently")
def test_a_power_limit_is_profiled_again_for_each_cause_scored_after_it(tmp_path):
    """A pair the benchmark missed (seed 29, pair 6: metro_demo, the train 8 % lighter than
    believed and a power limit). The power limit, accepted first, took most of the stronger
    traction, and against that null the stronger braking and faster coasting were fitted as a
    braking-rate change plus a resistance change; the mass change, scored with the limit
    profiled again with it free, is accepted second."""
    case = make_case(np.random.default_rng([29, 6]), ("mass", "power_limit"), "plain")
    rep, truth = _diagnosed(case, tmp_path)
    by = {r["cause"]: r for r in rep["ranking"]}
    assert [r["cause"] for r in rep["ranking"][:2]] == ["power_limit", "mass"], rep["ranking"][:3]
    assert by["mass"]["status"] == by["power_limit"]["status"] == "confirmed"
    assert by["braking_rate"]["status"] != "confirmed" and by["resistance"]["status"] != "confirmed"
    for c in ("mass", "power_limit"):
        check_parameters(c, by[c]["parameters"], truth[c], rep["evidence"], case.v_ref)


def _both_confirmed(seed: list, causes: tuple, tmp_path) -> None:
    """The pair case ``make_case(default_rng(seed), causes)`` diagnosed: its two causes ranked
    first and second, both confirmed, each with its parameters within check_parameters'
    bounds."""
    case = make_case(np.random.default_rng(seed), causes, "plain")
    rep, truth = _diagnosed(case, tmp_path)
    by = {r["cause"]: r for r in rep["ranking"]}
    assert {r["cause"] for r in rep["ranking"][:2]} == set(causes), rep["ranking"][:3]
    for c in causes:
        assert by[c]["status"] == "confirmed", (c, by[c].get("why"))
        check_parameters(c, by[c]["parameters"], truth[c], rep["evidence"], case.v_ref)


@pytest.mark.slow
def test_a_traction_delay_beside_a_power_limit_is_fitted_again_on_the_final_model(tmp_path):
    """A pair the benchmark missed (seed 0, bag 53: a metro line, a power limit of 6.30 m^2/s^3
    and a traction delay of 1.85 s). The delay, accepted at the second greedy stage, was
    fitted on the power limit's null at that stage's noise: 1.73 s, while the held-out folds'
    fits gave 1.86 and 1.91 s, and its effect, too small, was contradicted by its phase split.
    With no linear cause the joint refit had nothing to refit; each cause is now fitted again
    on the model of the others at the final noise, as the folds fit it: both confirmed."""
    _both_confirmed([0, 53], ("power_limit", "traction_delay"), tmp_path)


@pytest.mark.slow
def test_a_gradient_beside_a_drifting_braking_rate_are_both_confirmed(tmp_path):
    """A pair (seed 23, pair 8: a high-speed line, a gradient of 4.9 per mille run in braking
    and a braking rate drifting 0.81 -> 0.78). The heat law (brakes that fade as they heat)
    is compared with the braking rate fitted in its own two parameters on the law's stage:
    held at the joint refit's shape with one multiplier free, the rate lost to the law by
    2 ln LR +48.8 and was not confirmed. Fitted free, the drift is preferred to the heat by
    far, both causes are confirmed and nothing is left unexplained."""
    case = make_case(np.random.default_rng([23, 8]), ("gradient", "braking_rate"), "plain")
    rep, truth = _diagnosed(case, tmp_path)
    by = {r["cause"]: r for r in rep["ranking"]}
    assert {r["cause"] for r in rep["ranking"][:2]} == {"gradient", "braking_rate"}, \
        rep["ranking"][:3]
    for c in ("gradient", "braking_rate"):
        assert by[c]["status"] == "confirmed", by[c]
    check_parameters("gradient", by["gradient"]["parameters"], truth["gradient"],
                     rep["evidence"], case.v_ref)
    # the rate within 5 % of its change (its start 0.825 for 0.809: beyond its standard
    # error, the gradient fitted short of its stretch's ends leaves it some of the climb)
    assert main_error("braking_rate", by["braking_rate"]["parameters"], truth["braking_rate"],
                      case.nominal["braking_rate"], case.v_ref) <= 0.05, by["braking_rate"]
    law = rep["evidence"]["_model"]["confirmation"]["checks"]["braking_rate"]["heat_law"]
    assert law["lr"] < -9.0, law
    assert not rep["unexplained"], rep["unexplained"]


def test_a_cause_is_compared_in_its_own_parameters(metro, tmp_path):
    """``stage.cause_stat``, the statistic the heat law and the flexible term compare a cause
    by. Brakes that deliver 0.9 of the believed braking throughout; the braking rate's
    contribution held at a drift that is not the data's (f 1.0 -> 0.8) fits worse than the
    rate with its two parameters free, which contain that drift (nested least squares) and
    find the constant 0.9 (within 4 standard errors); the cause's statistic is the larger. A
    cause with a measurement column (an odometer scale) keeps its contribution's."""
    from train_core.effects import BrakingRateEffect, Effects

    from train_estimation.core.offline.diagnose import DiagConfig, Motion, Null, Stage, prepare
    from train_estimation.core.offline.diagnose.causes import BY_NAME
    from train_estimation.core.offline.diagnose.stage import cause_stat, fit_columns

    sc = metro.with_changes(duration=300.0, effects=Effects(
        braking_rate=BrakingRateEffect(0.9, 0.9)))
    cfg = DiagConfig()
    bag = write_bag(tmp_path / "bag", simulate(sc))
    mo = Motion(prepare(tool.read_measured(bag), sc.line, cfg), sc.line, sc.train, cfg)
    st = Stage(mo, Null(), cfg, big=False)
    br, brt = mo.col["br"], mo.col["brt"]
    d0, d1 = 1.0 - mo.f0, 0.8 - mo.f0  # the drift held: f - f0 at the start and the end
    dv = d0 * mo.Dv[:, br] + (d1 - d0) * mo.Dv[:, brt]
    ds = d0 * mo.Ds[:, br] + (d1 - d0) * mo.Ds[:, brt]
    held = fit_columns(st, dv[:, None], ds[:, None])[0]
    free, th, se = fit_columns(st, mo.Dv[:, [br, brt]], mo.Ds[:, [br, brt]])
    assert free > held + 9.0, (held, free)  # (the laws' bar, 2 ln LR 9)
    f_start, f_end = mo.f0 + th[0], mo.f0 + th[0] + th[1]
    assert abs(f_start - 0.9) <= 4 * se[0] and abs(f_end - 0.9) <= 4 * math.hypot(*se), th
    rate, scale = BY_NAME["braking_rate"], BY_NAME["odometer_scale"]
    got = cause_stat(st, dv, ds, lambda s: rate.free(s, {}))
    assert abs(got - free) <= 1e-9 * free, (got, free)  # (the same span in another basis)
    assert cause_stat(st, dv, ds) == held
    assert cause_stat(st, dv, ds, lambda s: scale.free(s, {})) == held


@pytest.mark.slow
def test_a_constant_braking_rate_beside_a_gradient_is_not_a_heat_law(tmp_path):
    """A pair (seed 29, pair 2: a high-speed line, braking x 0.92 throughout and a gradient of
    4.8 per mille). The joint refit gives the rate a drift (0.936 -> 0.921); held at that
    shape, it lost to the heat law by 2 ln LR +80 with the law's fade at 0.0006 (a constant
    factor that the rate's own two parameters contain). Fitted free on the law's stage, the
    rate does as well as the law, which pays for its cooling times: both causes confirmed."""
    case = make_case(np.random.default_rng([29, 2]), ("braking_rate", "gradient"), "plain")
    rep, truth = _diagnosed(case, tmp_path)
    by = {r["cause"]: r for r in rep["ranking"]}
    assert by["braking_rate"]["status"] == by["gradient"]["status"] == "confirmed", \
        rep["ranking"][:3]
    law = rep["evidence"]["_model"]["confirmation"]["checks"]["braking_rate"]["heat_law"]
    assert law["lr"] < 0.0 and abs(law["fade"]) < 0.01, law


@pytest.mark.slow
def test_a_brake_delay_and_a_low_adhesion_section_are_one_braking_chain(tmp_path):
    """A pair the benchmark missed (seed 31, pair 7: metro_demo, a brake delay of 1.21 s and
    braking x 0.52 on 1620-2041 m). The section was built on the braking at the believed
    timing, so the delay's re-timing was not scaled on its stretch: the delay was fitted
    1.04 s and its split needed it x0.39 over the braking that held the section (not
    confirmed). The section now scales the braking delayed by the brake delay, and the delay
    is profiled with the section's part delayed with it."""
    _both_confirmed([31, 7], ("brake_delay", "adhesion_section"), tmp_path)


def test_the_brake_delay_profile_with_a_section_is_the_likelihood_of_each_model(metro, tmp_path):
    """The brake delay's profile under a null with a low-adhesion section
    (``brake_delay._lls_with_sections``) against the exact oracle: each grid point's
    log-likelihood is that of the null re-timed to it (the section at the new timing), its
    own stage at the same noise; without sections, the elementary columns' ``fixed_lls``."""
    from train_core.effects import AdhesionSectionEffect, BrakeDelayEffect, Effects

    from train_estimation.core.offline.diagnose import DiagConfig, Motion, prepare
    from train_estimation.core.offline.diagnose.causes.brake_delay import _lls_with_sections
    from train_estimation.core.offline.diagnose.stage import Null, Stage

    sc = metro.with_changes(duration=200.0, effects=Effects(
        brake_delay=BrakeDelayEffect(metro.train.brake.delay + 0.4),
        adhesion_section=AdhesionSectionEffect(300.0, 1500.0, 0.6)))
    bag = write_bag(tmp_path / "bag", simulate(sc))
    cfg = DiagConfig()
    mo = Motion(prepare(tool.read_measured(bag), sc.line, cfg), sc.line, sc.train, cfg)
    plain = Null(shift=0.05)
    st = Stage(mo, plain, cfg)
    grid = [(0.05, 0.2), (0.0, 0.4), (0.1, 0.4), (-0.05, 0.6)]
    assert np.allclose(_lls_with_sections(st, grid),
                       st.fixed_lls([st.retime(s, d) for s, d in grid]), rtol=0, atol=1e-6)
    null = Null(shift=0.05, brake_extra=0.1, brake_sections=[(300.0, 1500.0, 0.6)])
    st = Stage(mo, null, cfg)
    noise = (st.q, st.r_s)
    got = _lls_with_sections(st, grid)
    for (s, d), ll in zip(grid, got):
        want = Stage(mo, Null(shift=s, brake_extra=d, brake_sections=null.brake_sections), cfg,
                     noise=noise, big=False).fixed_loglik()
        assert ll == pytest.approx(want, abs=1e-6 * abs(want) + 1e-6), (s, d)
    # the section changes the profile (the oracle above is not the plain one)
    assert not np.allclose(got, st.fixed_lls([st.retime(s, d) for s, d in grid]), atol=1e-3)


def test_two_accepted_causes_that_one_mass_change_explains_are_merged(metro, metro_run, tmp_path):
    """The merge step: a train 10 % heavier than believed, with the greedy stages made to accept
    a braking-rate change and then a resistance change (what a power limit accepted first left
    them in a benchmark bag), is one mass change: the model with it scores higher, the two are
    rejected with the reason, and nothing is merged where the two causes are what the data
    hold."""
    from train_core.effects import BrakingRateEffect, Effects, MassEffect, ResistanceEffect

    from train_estimation.core.offline.diagnose import DiagConfig, Motion, prepare
    from train_estimation.core.offline.diagnose.causes import REGISTRY, SCORING
    from train_estimation.core.offline.diagnose.refit import merge
    from train_estimation.core.offline.diagnose.search import _accept, _Search, _stage

    def greedy_with(sc, names):
        bag = write_bag(tmp_path / f"bag{len(list(tmp_path.iterdir()))}", simulate(sc))
        cfg = DiagConfig()
        mo = Motion(prepare(tool.read_measured(bag), sc.line, cfg), sc.line, sc.train, cfg)
        own = {c.name: r for c in REGISTRY if (r := c.own_test(mo.run)) is not None}
        sr = _Search(mo, cfg, own, {c.name for c in SCORING
                                    if c.untestable(mo.run, cfg, own.get(c.name))})
        for i, name in enumerate(names):
            st = _stage(sr, i, lambda *a: None)
            _accept(sr, sr.stages[-1]["scores"][name], i)
        st = _stage(sr, len(names), lambda *a: None)
        return sr, (st.q, st.r_s)

    sc = metro.with_changes(duration=300.0)
    heavier = sc.with_changes(effects=Effects(mass=MassEffect(1.1 * sc.train.mass)))
    sr, noise = greedy_with(heavier, ["braking_rate", "resistance"])
    assert merge(sr, noise)
    assert [a.cause for a in sr.accepted] == ["mass"]
    assert sr.accepted[0].parameters["mass"] == pytest.approx(1.1 * sc.train.mass, rel=0.02)
    assert [a.status for a in sr.merged] == ["rejected", "rejected"]
    assert sr.merged[0].why.startswith("one mass change explains it and resistance together")
    # a braking-rate change and a resistance change that are there stay
    d = sc.train.davis
    both = sc.with_changes(effects=Effects(braking_rate=BrakingRateEffect(0.8, 0.8),
                                           resistance=ResistanceEffect(1.5 * d.a, d.b,
                                                                       1.5 * d.c)))
    sr, noise = greedy_with(both, ["braking_rate", "resistance"])
    assert not merge(sr, noise)
    assert [a.cause for a in sr.accepted] == ["braking_rate", "resistance"]


def test_a_gradient_steeper_than_the_line_allows_is_not_a_map_error():
    """A map error of a few per mille is one; a change whose corrected gradient no part of the
    line's map holds is not, unless the map could have the section's profile wrong (a sign)."""
    from train_core.model import GradientSection, Line

    from train_estimation.core.offline.diagnose import BY_NAME

    line = Line(name="l", length=5000.0, gradients=(GradientSection(0.0, 2000.0, 0.0),
                                                   GradientSection(2000.0, 5000.0, -20.0)))
    mo = SimpleNamespace(line=line)

    def odd(start, end, permille):
        return BY_NAME["gradient"].plausible(CauseFit("gradient", 10.0, {
            "start": start, "end": end, "permille": permille}), mo)

    assert odd(500.0, 900.0, 4.5) is None
    assert odd(500.0, 900.0, -9.0) is None
    assert "not a map error" in odd(500.0, 900.0, 36.0)
    assert odd(2500.0, 2900.0, 36.0) is None  # corrected +16: a profile the line has
    assert "not a map error" in odd(2500.0, 2900.0, -12.0)  # corrected -32


def test_each_cause_states_its_resolution():
    """The issue's examples: 25 ms of brake delay at a 10 Hz odometer, f 0.999 and a mass
    0.5 % off are not changes; a plain effect is."""
    from train_core.model import load_train

    from train_estimation.core.offline.diagnose import BY_NAME

    train = load_train(Path(__file__).parents[1] / "ros_ws/src/train_core/config/trains"
                       / "metro_b6.yaml")
    t = np.arange(0.0, 100.0, 0.1)
    mo = SimpleNamespace(train=train, f0=train.brake.braking_rate,
                         ev=SimpleNamespace(t=t, odo=np.arange(t.size)))

    def res(cause, params, se, extra=None):
        return BY_NAME[cause].resolution(CauseFit(cause, 10.0, params, std_errors=se,
                                                  extra=extra or {}), mo)

    d0 = train.brake.delay
    assert "below resolution" in res("brake_delay", {"delay": d0 + 0.025}, {"delay": 0.005})
    assert res("brake_delay", {"delay": d0 + 0.5}, {"delay": 0.02}) is None
    assert "below resolution" in res("brake_delay", {"delay": d0 + 0.5}, {"delay": 0.2})
    assert "below resolution" in res("braking_rate", {"f_start": 0.999, "f_end": 0.999},
                                     {"f_start": 1e-4, "f_end": 1e-4})
    assert res("braking_rate", {"f_start": 0.9, "f_end": 0.85},
               {"f_start": 0.005, "f_end": 0.005}) is None
    assert "below resolution" in res("mass", {"mass": train.mass * 1.005}, {"mass": 10.0})
    assert res("mass", {"mass": train.mass * 1.1}, {"mass": 100.0}) is None
    assert res("gradient", {"permille": 4.0}, {"permille": 0.3}) is None
    assert "below resolution" in res("gradient", {"permille": 0.3}, {"permille": 0.01})
    assert "below resolution" in res("odometer_scale", {"scale": 1.0004}, {"scale": 1e-5})
    assert "below resolution" in res("clock_drift", {"drift": 2e-6}, {"drift": 1e-8})
    assert res("bursty_link", {"p_good_bad": 0.02, "p_bad_good": 0.25}, {}) is None
    assert "below resolution" in res("bursty_link", {"p_good_bad": 0.3, "p_bad_good": 0.65}, {})
    v = 15.0
    f0 = float(train.davis.force(v))
    assert res("resistance", {}, {"force_at_v_ref": 50.0},
               {"v_ref": v, "force_at_v_ref": 1.2 * f0}) is None
    assert "below resolution" in res("resistance", {}, {"force_at_v_ref": 50.0},
                                     {"v_ref": v, "force_at_v_ref": 1.01 * f0})
    ok = res("wheel_slip", {"intervals": [[10.0, 12.0]]}, {"slip_fraction": [0.002]},
             {"slip_fraction": [0.08]})
    assert ok is None
    assert "below resolution" in res("wheel_slip", {"intervals": [[10.0, 12.0]]},
                                     {"slip_fraction": [0.002]}, {"slip_fraction": [0.005]})


@pytest.mark.slow
@pytest.mark.parametrize("world", ["adhesion_section", "brake_fade"])
def test_a_stretch_of_weaker_braking_is_told_from_weaker_braking_at_every_stop(metro, world,
                                                                               tmp_path):
    """The place test: weaker braking on the approach to the first stop is a place effect when
    only that stretch has it, and is contradicted when every stop's low-speed braking is as
    weak (brakes that fade below a speed, an effect outside the list)."""
    from train_core.effects import AdhesionSectionEffect, Effects

    from train_estimation.core.offline.diagnose import DiagConfig, Null, Stage
    from train_estimation.core.offline.diagnose.causes.adhesion_section import CAUSE
    from train_estimation.core.offline.diagnose.confirm import CONFIRM
    from train_estimation.core.offline.diagnose.contradict import place_test
    from train_sim.unlisted import BrakeFade, Unlisted

    sc = metro.with_changes(duration=300.0)
    tr = simulate(sc).truth
    x, v = tr["position"], tr["velocity"]
    # the stretch: the first approach braked from above 6 m/s to a stop, from 6 m/s on
    stop = int(np.flatnonzero((v[1:] < 0.1) & (v[:-1] >= 0.1) & (x[1:] > x[0] + 100.0))[0])
    start = float(x[np.flatnonzero(v[:stop] > 6.0)[-1]])
    end = float(x[stop]) + 5.0
    if world == "adhesion_section":
        sc = sc.with_changes(effects=Effects(adhesion_section=AdhesionSectionEffect(
            start, end, 0.6)))
    else:
        sc = sc.with_changes(unlisted=Unlisted(brake_fade=BrakeFade(6.0, 0.6)))
    cfg = DiagConfig()
    mo, i, j = _motion_over(tmp_path, sc, cfg, start, end)
    fit = CauseFit("adhesion_section", 10.0, {"start": float(mo.bin_edges[i]),
                                              "end": float(mo.bin_edges[j]), "factor": 0.6},
                   extra={"bins": (i, j)})
    full = Null()
    CAUSE.extend_null(full, fit, mo)
    st = Stage(mo, full, cfg, big=False)
    res = place_test(mo, full, cfg, (st.q, st.r_s), *CAUSE.beyond(fit, mo), CONFIRM.split_alpha,
                     CONFIRM.split_min_share)
    assert "p" in res, res  # other stops were braked at the stretch's speeds
    assert res["contradicted"] is (world == "brake_fade"), res


@pytest.mark.slow
@pytest.mark.parametrize("world", ["gradient", "tunnel_drag"])
def test_drag_growing_with_speed_is_told_from_a_gradient_where_the_speed_changes(metro, world,
                                                                                  tmp_path):
    """The speed-law test: on a stretch the train accelerates over (3 to about 15 m/s), a
    force fixed at the place (a gradient) and drag growing as v^2 (a tunnel) of the same mean
    are told apart, each way round, by more than the confirmation's threshold."""
    from train_core.effects import Effects, GradientEffect
    from train_core.model import G

    from train_estimation.core.offline.diagnose import DiagConfig, Null, Stage
    from train_estimation.core.offline.diagnose.confirm import CONFIRM
    from train_estimation.core.offline.diagnose.laws import speed_law
    from train_sim.unlisted import TunnelDrag, Unlisted

    sc = metro.with_changes(duration=300.0)
    tr = simulate(sc).truth
    x, v = tr["position"], tr["velocity"]
    i0 = int(np.flatnonzero(v > 3.0)[0])
    start, end = float(x[i0]), float(x[i0]) + 600.0
    inside = (x >= start) & (x < end)
    assert v[inside].max() > 3.0 * v[inside].min(), (v[inside].min(), v[inside].max())
    a = 0.06  # m/s^2, the mean extra deceleration on the stretch
    train = sc.true_train
    if world == "gradient":
        permille = a * (1.0 + train.rotary_allowance) / G * 1000.0
        sc = sc.with_changes(effects=Effects(gradient=GradientEffect(start, end, permille)))
    else:
        c = a * train.effective_mass / float(np.mean(v[inside] ** 2))
        sc = sc.with_changes(unlisted=Unlisted(tunnel_drag=TunnelDrag(start, end, c)))
    cfg = DiagConfig()
    mo, i, j = _motion_over(tmp_path, sc, cfg, start, end)
    # at the noise of the model with the stretch's force (as the confirmation tests it: the
    # null's noise, inflated by the force it misses, would hide the shape)
    th = Stage(mo, Null(), cfg).fit({}, [{f"G{b}": 1.0 for b in range(i, j)}])[0]
    st = Stage(mo, Null(gradient=(i, j, float(th[0]))), cfg, big=False)
    res = speed_law(mo, Null(), cfg, (st.q, st.r_s), (i, j))
    if world == "gradient":
        assert res["lr"] < -CONFIRM.law_lr, res
        assert abs(res["b"]) < 3.0 * res["std_error"] + 0.1, res
    else:
        assert res["lr"] > CONFIRM.law_lr, res
        assert res["b"] > 0.5, res


@pytest.mark.slow
def test_a_tunnel_on_a_stretch_run_at_changing_speed_is_not_confirmed_as_a_gradient(tmp_path):
    """The tool end to end: drag growing as v^2 on a stretch the train accelerates over (drawn
    where the test kind ``neutral_section`` of seed 14 puts its stretch: metro_demo, 10-14 m/s)
    fits a gradient section well enough to be accepted, and the speed-law comparison withdraws
    it: no listed cause confirmed, the remainder `unexplained`."""
    from train_sim.unlisted import TunnelDrag, Unlisted
    from train_sim.unlisted_cases import unlisted_case

    uc = unlisted_case(np.random.default_rng(14), "neutral_section")
    ns, sc = uc.scenario.unlisted.neutral_section, uc.case.scenario
    tr = simulate(sc).truth
    inside = (tr["position"] >= ns.start) & (tr["position"] < ns.end)
    c = 0.06 * sc.true_train.effective_mass / float(np.mean(tr["velocity"][inside] ** 2))
    paths = uc.write(tmp_path / "case")
    generate(sc.with_changes(unlisted=Unlisted(tunnel_drag=TunnelDrag(ns.start, ns.end, c))),
             tmp_path / "bag", measured=True)
    rep = _unexplained(paths, tmp_path)
    grad = next(r for r in rep["ranking"] if r["cause"] == "gradient")
    assert grad["status"] == "not confirmed", grad
    assert grad["why"].startswith("a speed law fits better"), grad


def test_one_pass_finds_the_single_time_span_on_a_stretch():
    """A cause at a place is told from one acting in time only when the stretch is run twice:
    ``_one_pass`` gives the span of a single pass, and None for two passes or none."""
    from types import SimpleNamespace

    from train_estimation.core.offline.diagnose.confirm import _one_pass

    t = np.arange(0.0, 100.0, 1.0)
    there = np.minimum(t, 100.0 - t) * 20.0  # out to 1000 m and back
    mo = SimpleNamespace(x_ref=t * 20.0, grid=SimpleNamespace(t=t),
                         run=SimpleNamespace(clock={"beta": 1.0}))
    fit = CauseFit("gradient", 1.0, {"start": 400.0, "end": 600.0, "permille": 3.0})
    assert _one_pass(mo, fit) == (20.0, 29.0)
    mo.x_ref = there
    assert _one_pass(mo, fit) is None  # run out and back: two passes
    mo.x_ref = np.clip(t * 20.0, None, 400.0) + 0.1 * (-1.0) ** t  # stands at its start
    assert _one_pass(mo, fit) == (20.0, 98.0)  # crossing its edge by noise: still one pass
    x = np.where(t <= 30.0, t * 20.0, 590.0)
    for off, passes in ((9.0, (20.0, 99.0)), (11.0, None)):  # off its end and back on
        x[31] = 600.0 + off
        mo.x_ref = x
        assert _one_pass(mo, fit) == passes, off
    mo.x_ref = t * 2.0
    assert _one_pass(mo, fit) is None  # never there
    assert _one_pass(mo, CauseFit("resistance", 1.0, {"a": 1.0})) is None


def test_a_bag_whose_variances_are_all_zero_is_read_with_the_believed_ones(metro, metro_run,
                                                                            tmp_path):
    """A producer that leaves speed_variance and position_variance at 0 (not stated: zeros mean
    "unknown" in ROS's covariance fields): diagnose reads the run with train.yaml's variances,
    as it reads the same run stating them, and says so in the report's notes."""
    from train_estimation.core.offline.diagnose import DiagConfig, DiagnoseError, prepare

    train = metro.train
    believed = {"odometer": ("speed_variance", train.odometer_speed_variance),
                "balise": ("position_variance", train.balise_position_std ** 2)}

    def bag(path, zero: bool):
        with BagWriter(path) as w:
            for t_recv, topic, stamp, fields in metro_run.received_events():
                if topic not in ("odometer", "balise", "control"):
                    continue
                if topic in believed:
                    key, var = believed[topic]
                    fields = dict(fields, **{key: 0.0 if zero else var})
                w.write(topic, stamp, fields, t_ns=int(round(t_recv * 1e9)))
        return path

    cfg = DiagConfig()
    runs = [prepare(tool.read_measured(bag(tmp_path / name, zero)), metro.line, cfg, train)
            for name, zero in (("stated", False), ("zeros", True))]
    for k in ("odo_t", "odo_v", "odo_rv", "bal_t", "bal_r"):
        np.testing.assert_array_equal(getattr(runs[1], k), getattr(runs[0], k))
    assert sum("not stated" in n for n in runs[1].notes) == 2, runs[1].notes
    assert not any("not stated" in n for n in runs[0].notes)
    # without the believed train the zeros are dropped as before: nothing usable is left, and
    # that is said (it was an IndexError)
    with pytest.raises(DiagnoseError, match="no usable odometer reading"):
        prepare(tool.read_measured(tmp_path / "zeros"), metro.line, cfg)
    # identify likewise takes train.yaml's (None: not stated)
    assert tool.read_measured(tmp_path / "zeros").to_identify().odo_speed_variance is None
    assert tool.read_measured(tmp_path / "stated").to_identify().odo_speed_variance is not None
    # one rule for both: a NaN beside the zeros states nothing either
    from train_estimation.core.offline.measured import variances_unstated
    assert variances_unstated([0.0, math.nan, 0.0]) and not variances_unstated([0.0, 0.01])
    assert not variances_unstated([math.nan]) and not variances_unstated([0.01, 0.01])
    assert run_tool(tmp_path / "zeros", metro.line_path, metro.train_path, tmp_path / "out") == 0
    assert "not stated" in (tmp_path / "out" / "report.json").read_text()


def test_a_bag_without_a_sample_counter_or_command_stamps_is_read_by_what_it_has(
        metro, metro_run, tmp_path):
    """A producer that leaves every seq at 0 (no sample counter) or every command's stamp at 0
    (the header left empty): diagnose reads the run as the same bag with them, says so in the
    notes, and the link's losses, which only a counter can count, are untestable with that
    reason. (Commands stamped 0 lay an epoch before the odometer: exit 2 before.)"""
    def bag(path, seq0=False, ctl0=False):
        with BagWriter(path) as w:
            for t_recv, topic, stamp, fields in metro_run.received_events():
                if topic not in ("odometer", "balise", "control"):
                    continue
                if seq0 and topic != "control":
                    fields = dict(fields, seq=0)
                if ctl0 and topic == "control":
                    stamp = 0.0
                w.write(topic, stamp, fields, t_ns=int(round(t_recv * 1e9)))
        return path

    reports = {}
    for name, kw in (("plain", {}), ("seq0", {"seq0": True}), ("ctl0", {"ctl0": True})):
        assert run_tool(bag(tmp_path / name, **kw), metro.line_path, metro.train_path,
                        tmp_path / f"{name}_out") == 0
        reports[name] = json.loads((tmp_path / f"{name}_out" / "report.json").read_text())
    plain, seq0, ctl0 = (reports[k] for k in ("plain", "seq0", "ctl0"))
    assert ctl0["ranking"] == plain["ranking"]  # the log times are the commands' stamps here
    assert seq0["cause"] == plain["cause"]
    notes = {k: " ".join(r["evidence"]["_model"]["notes"]) for k, r in reports.items()}
    assert "no sample counter" in notes["seq0"] and "no sample counter" not in notes["plain"]
    assert "stamped 0" in notes["ctl0"] and "stamped 0" not in notes["plain"]
    link = {u["cause"]: u["why"] for u in seq0["untestable"]}
    assert "no sample counter" in link["bursty_link"]


# ------------------------------------------------------------------------------------------------
# The held-out check's power and what it compares
# ------------------------------------------------------------------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize("seed", [[7, 0], [7, 1], [7, 2]])
def test_a_cause_accepted_at_the_last_stage_is_held_out_at_the_noise_of_its_model(seed,
                                                                                 tmp_path):
    """A resistance change beside a drifting clock and a bursty link: every greedy stage
    accepts a cause, the resistance last. Confirmed at the noise of the model without it (its
    own effect inflated that noise, and the held-out filter followed the odometer through
    what the cause predicts), its held-out score Z was 8.0-9.0 for fits that scored 133-202
    (Z / sqrt(score) 0.62-0.78). For a true effect the held-out score test's Z^2 is about
    2 dll, which is more than the score (2 dll less its penalties): at the noise of the model
    with every accepted cause Z / sqrt(score) is 1.6-2.3 on these seeds."""
    case = make_case(np.random.default_rng(seed), ("clock_drift", "bursty_link", "resistance"),
                     "plain")
    rep, _ = _diagnosed(case, tmp_path)
    by = {r["cause"]: r for r in rep["ranking"]}
    held = rep["evidence"]["_model"]["confirmation"]["checks"]["resistance"]["held_out"]
    assert by["resistance"]["score"] > 100.0, by["resistance"]
    assert held["ok"] and held["z"] > math.sqrt(by["resistance"]["score"]), \
        (held["z"], by["resistance"]["score"])
    assert held["halves"]["consistent"], held["halves"]


def test_the_halves_test_compares_the_folds_fits_within_their_standard_errors():
    """The oracle: z = (x0 - x1) / sqrt(se0^2 + se1^2) against the two-sided quantile of
    halves_alpha shared out over the quantities, and a difference of more than
    halves_min_share of the cause's size (the mean fit's change from nominal)."""
    from scipy.stats import norm

    from train_estimation.core.offline.diagnose.confirm import CONFIRM, halves_test

    zc1 = norm.isf(CONFIRM.halves_alpha / 2)
    zc2 = norm.isf(CONFIRM.halves_alpha / 4)

    def folds(*pairs):
        return [{"fold": i, "halves": dict(p)} for i, p in enumerate(pairs)]

    # one quantity, just inside and just beyond its quantile (mass 10 % off nominal 100)
    se = 0.5
    x1 = 110.0 + 0.99 * zc1 * math.hypot(se, se)
    ok = halves_test(folds({"m": (110.0, se)}, {"m": (x1, se)}), nominal={"m": 100.0})
    assert ok["consistent"] and ok["tested"], ok
    x1 = 110.0 + 1.01 * zc1 * math.hypot(se, se)
    bad = halves_test(folds({"m": (110.0, se)}, {"m": (x1, se)}), nominal={"m": 100.0})
    assert not bad["consistent"] and "halves" in bad["why"], bad
    assert bad["quantities"]["m"]["z"] == pytest.approx(-1.01 * zc1)
    # two quantities: the quantile is shared out (Bonferroni)
    x1 = 110.0 + 1.01 * zc1 * math.hypot(se, se)
    two = halves_test(folds({"m": (110.0, se), "f": (0.8, 0.01)},
                            {"m": (x1, se), "f": (0.8, 0.01)}), nominal={"m": 100.0})
    assert two["consistent"] and two["z_needed"] == pytest.approx(zc2), two
    # beyond its SEs but within a tenth of the cause's size: not another cause
    tiny = halves_test(folds({"m": (110.0, 1e-3)}, {"m": (110.5, 1e-3)}), nominal={"m": 100.0})
    assert tiny["consistent"], tiny
    # a fold without the cause's data: nothing to compare
    assert halves_test([{"fold": 0, "error": "no data"}, {"fold": 1, "halves": {}}])["consistent"]


def test_the_clock_drift_held_out_score_is_standard_normal_without_a_drift():
    """On stamps with no drift and a skewed latency (exponential tail), the clock's held-out
    score is N(0, 1): P(Z > 2) ~ 2.3 %, where a lower held-out RMS alone (and a median offset
    against a least-squares fit) confirmed a drift on most nominal bags. With a drift of 100 ppm
    over 600 s (a tenth of the subtle case's) it is found every time."""
    from train_estimation.core.offline.diagnose.causes.clock_drift import clock_test

    rng = np.random.default_rng(5)
    zs, found = [], []
    for _ in range(400):
        s = np.arange(0.0, 600.0, 0.2)
        lat = 0.04 + rng.exponential(0.02, s.size)
        zs.append(clock_test(SimpleNamespace(odo_stamp=s, odo_recv=s + lat))["heldout_z"])
        found.append(clock_test(SimpleNamespace(odo_stamp=s, odo_recv=s * (1 + 1e-4) + lat))
                     ["heldout_z"])
    zs = np.array(zs)
    # binomial: 400 draws at 2.3 %, mean 9, SD 3: at most 9 + 4 SD
    assert np.sum(zs > 2.0) <= 21, np.sum(zs > 2.0)
    assert abs(np.mean(zs)) < 4 / math.sqrt(400) and 0.85 < np.std(zs) < 1.15, \
        (np.mean(zs), np.std(zs))
    assert np.all(np.array(found) > 2.0), min(found)


@pytest.mark.slow
@pytest.mark.parametrize("size", ["plain", "subtle"])
def test_a_section_fitted_outside_its_range_leaves_the_stage_to_the_next_cause(size, tmp_path):
    """A downhill gradient of -4.9 (plain) or -2.45 (subtle) per mille on a stretch run in
    light braking at 35 m/s (train_sim.cases seed 103; the braking asked for there is
    0.023-0.043 m/s^2). Plain: a low-adhesion section fits it best as braking x -0.14 there,
    a brake that drives the train; accepted at the first stage, it was refused by the
    confirmation, the gradient was never tried and the run was `unexplained`. Subtle: a
    section of braking x 0.14 there was confirmed, weakening a brake that asks for an
    adhesion of 0.004, which every rail gives. Out of the running at the greedy stage
    (search._refuse, AdhesionSection.plausible), the gradient is accepted and confirmed."""

    from train_estimation.core.offline.diagnose import search as S

    case = make_case(np.random.default_rng(103), "gradient", size)
    rep, truth = _diagnosed(case, tmp_path)
    by = {r["cause"]: r for r in rep["ranking"]}
    assert rep["cause"] == "gradient", rep["ranking"][:3]
    assert by["gradient"]["status"] == "confirmed", by["gradient"]
    assert by["adhesion_section"]["status"] == "rejected", by["adhesion_section"]
    assert not rep["unexplained"], rep["unexplained"]
    est, tru = by["gradient"]["parameters"], truth["gradient"]
    assert abs(est["start"] - tru["start"]) <= 100.0 and abs(est["end"] - tru["end"]) <= 100.0
    # one pass at one speed fixes the force over the stretch (per mille x metres) far better
    # than the per mille and the ends apiece (plain: -5.7 over 260 m for -4.9 over 312 m)
    force = est["permille"] * (est["end"] - est["start"])
    assert force == pytest.approx(tru["permille"] * (tru["end"] - tru["start"]), rel=0.1)
    # the first stage: the section scored, refused for its range, the gradient the best left
    sr = _search(case, tmp_path / "case2", tmp_path / "bag")
    S._stage(sr, 0, lambda *a: None)
    scores = sr.stages[0]["scores"]
    sec = scores["adhesion_section"]
    assert sec.why is not None and sec.why.startswith("refused"), (sec, sec.why)
    best = max((f for f in scores.values() if f.why is None), key=lambda f: f.score)
    assert best.cause == "gradient" and best.score > 0, best


@pytest.mark.slow
@pytest.mark.parametrize("index", [0, 9, 11])
def test_a_section_swapped_for_a_braking_rate_change_keeps_the_braking_deficit(index, tmp_path):
    """Every brake x 0.82-0.90 (a constant braking-rate change, train_sim.cases seeds [11, i]):
    a low-adhesion section over the stretch of every stop is accepted first, then a
    braking-rate change on top of it, which fits only the brakings outside the section (f
    0.99-1.00). The run brakes nowhere outside the section at its speeds, so the section is
    swapped for the braking-rate change (refit.unlocate): that change must carry the whole
    deficit, fitted without the section (it kept f 0.99-1.00, "below resolution", and the
    deficit was left unexplained)."""

    from train_estimation.core.offline.diagnose import search as S
    from train_estimation.core.offline.diagnose.refit import unlocate

    case = make_case(np.random.default_rng([11, index]), "braking_rate", "plain")
    truth = case.truth["braking_rate"]
    assert truth["f_start"] == truth["f_end"]  # the constant kind (30 % of the cases)
    generate(case.scenario, tmp_path / "bag", measured=True)
    sr = _search(case, tmp_path / "case", tmp_path / "bag")
    S._stage(sr, 0, lambda *a: None)
    S._accept(sr, sr.stages[0]["scores"]["adhesion_section"], 0)
    st = S._stage(sr, 1, lambda *a: None)
    beside = sr.stages[1]["scores"]["braking_rate"]
    assert min(beside.parameters.values()) > 0.98, beside.parameters  # what the section left
    S._accept(sr, beside, 1)
    assert unlocate(sr, (st.q, st.r_s))
    assert [a.cause for a in sr.accepted] == ["braking_rate"], sr.accepted
    fit = sr.accepted[0]
    for k in ("f_start", "f_end"):
        assert abs(fit.parameters[k] - truth[k]) <= max(Z * fit.std_errors[k], 0.01), \
            (k, fit.parameters, fit.std_errors, truth)


def test_outputs_go_to_dir_whole_replacing_an_earlier_run_and_only_diagnose_s(metro, metro_run,
                                                                              tmp_path, capsys):
    """A file in the way is one line (no analysis run); a second run into the same DIR without
    plots leaves none of the first run's plots beside its report, and a user's own file."""
    bag = write_bag(tmp_path / "bag", metro_run)
    (tmp_path / "afile").write_text("x")
    assert run_tool(bag, metro.line_path, metro.train_path, tmp_path / "afile") == 2
    assert "--out" in one_error_line(capsys) and (tmp_path / "afile").read_text() == "x"
    out = tmp_path / "out"
    assert run_tool(bag, metro.line_path, metro.train_path, out) == 0
    assert any(out.glob("*.svg"))
    (out / "earlier.png").write_text("x")  # a user's file of an image's name
    (out / "replay.png").write_text("x")  # a plot's name as earlier versions wrote it
    (out / "mine.txt").write_text("kept")
    assert tool.main(["--bag", str(bag), "--line", str(metro.line_path), "--train",
                      str(metro.train_path), "--out", str(out), "--quiet", "--no-plots"]) == 0
    capsys.readouterr()
    assert not any(out.glob("*.svg")) and (out / "mine.txt").read_text() == "kept"
    assert [p.name for p in out.glob("*.png")] == ["earlier.png"]
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no stage left
    assert {"report.json", "inputs.json", "report.html", "model"} <= {p.name for p in
                                                                      out.iterdir()}
