"""Scenario loading: shipped files are valid; bad files give one-line ConfigErrors naming the
file and the key."""

import shutil

import pytest
import yaml
from train_core.config import ConfigError
from train_core.effects import EFFECT_NAMES
from train_core.files import share_dir

from train_sim.scenario import data_root, load_scenario

SCEN = data_root() / "scenarios"
CONF = share_dir("train_core", "config") / "config"


@pytest.fixture()
def tmp_scenario(tmp_path):
    """A writable copy of metro_demo with its line and train next to it."""
    shutil.copy(CONF / "lines" / "metro_demo.yaml", tmp_path / "line.yaml")
    shutil.copy(CONF / "trains" / "metro_b6.yaml", tmp_path / "train.yaml")
    data = yaml.safe_load((SCEN / "metro_demo.yaml").read_text())
    data["line"], data["train"] = "./line.yaml", "./train.yaml"

    def write(mutate=None, train_mutate=None):
        d = yaml.safe_load(yaml.safe_dump(data))
        if mutate:
            mutate(d)
        path = tmp_path / "scenario.yaml"
        path.write_text(yaml.safe_dump(d))
        if train_mutate:
            t = yaml.safe_load((CONF / "trains" / "metro_b6.yaml").read_text())
            train_mutate(t)
            (tmp_path / "train.yaml").write_text(yaml.safe_dump(t))
        return path

    return write


def expect_error(path, *words):
    with pytest.raises(ConfigError) as exc:
        load_scenario(path)
    msg = str(exc.value)
    assert "\n" not in msg
    for w in words:
        assert w in msg, msg
    return msg


def test_valid_copy_loads(tmp_scenario):
    sc = load_scenario(tmp_scenario())
    assert sc.name == "metro_demo" and sc.effects.active() == []
    assert sc.true_train == sc.train and sc.true_line == sc.line


def test_missing_key(tmp_scenario):
    path = tmp_scenario(lambda d: d.pop("duration"))
    expect_error(path, str(path), "duration", "missing")


def test_negative_mass(tmp_scenario):
    path = tmp_scenario(train_mutate=lambda t: t.update(mass=-5.0))
    expect_error(path, "train.yaml", "mass", "out of range", "(0, inf)")


@pytest.mark.parametrize("key", ["p", "loss_bad"])
def test_probability_above_one(tmp_scenario, key):
    path = tmp_scenario(lambda d: d["link"].update({key: 1.5}))
    expect_error(path, str(path), f"link.{key}", "[0, 1]")


def test_probability_in_effect_out_of_range(tmp_scenario):
    path = tmp_scenario(lambda d: d.update(
        effects={"bursty_link": {"p_good_bad": -0.1, "p_bad_good": 0.5}}))
    expect_error(path, "effects.bursty_link.p_good_bad", "[0, 1]")


def test_unknown_effect(tmp_scenario):
    path = tmp_scenario(lambda d: d.update(effects={"gravity": {"g": 9.0}}))
    msg = expect_error(path, str(path), "gravity", "unknown effect")
    assert all(name in msg for name in EFFECT_NAMES)


@pytest.mark.parametrize("mutate,words", [
    (lambda d: d.update(foo=1), ("unknown key 'foo'",)),
    (lambda d: d["link"].update(pp=0.1), ("link", "unknown key 'pp'")),
    (lambda d: d.update(effects={"gradient": {"start": 1, "end": 2, "permille": 3, "x": 1}}),
     ("effects.gradient", "unknown key 'x'")),
])
def test_unknown_field(tmp_scenario, mutate, words):
    expect_error(tmp_scenario(mutate), *words)


def test_other_bad_values(tmp_scenario):
    expect_error(tmp_scenario(lambda d: d["timetable"].append({"station": "Z"})),
                 "timetable[3].station", "unknown station 'Z'", "A, B, C, D")
    expect_error(tmp_scenario(lambda d: d["integration"].update(max_step=0.05)),
                 "integration.max_step", "(0, 0.01]")
    expect_error(tmp_scenario(lambda d: d["link"].update(model="smoke")),
                 "link.model", "bernoulli, gilbert_elliott")
    expect_error(tmp_scenario(lambda d: d.update(effects={"mass": {}})),
                 "effects.mass", "missing key 'mass'")
    expect_error(tmp_scenario(lambda d: d.update(
        effects={"wheel_slip": {"intervals": [[5, 2]]}})), "effects.wheel_slip.intervals")
    expect_error(tmp_scenario(lambda d: d.update(effects={"wheel_slip": {
        "intervals": [[2, 5], [8, 9]], "fractions": [0.1]}})), "effects.wheel_slip.fractions",
        "one number in [-0.9, 1] per interval")
    expect_error(tmp_scenario(lambda d: d["start"].update(position=1e6)),
                 "start.position", "out of range")


def test_missing_file():
    expect_error("/nonexistent/scenario.yaml", "/nonexistent/scenario.yaml", "not found")


def test_effects_parse_and_build_true_models(tmp_scenario):
    eff = {
        "gradient": {"start": 1000.0, "end": 1300.0, "permille": 8.0},
        "resistance": {"a": 4000.0, "b": 150.0, "c": 9.0},
        "braking_rate": {"f_start": 1.0, "f_end": 0.7},
        "odometer_scale": {"scale": 1.01},
        "wheel_slip": {"intervals": [[30, 35], [10, 20]], "fractions": [-0.1, 0.2]},
        "bursty_link": {"p_good_bad": 0.02, "p_bad_good": 0.3},
        "brake_delay": {"delay": 1.6},
        "mass": {"mass": 320000.0},
        "clock_drift": {"drift": 1e-4},
        "power_limit": {"p_spec": 9.0},
        "adhesion_section": {"start": 1500.0, "end": 1700.0, "factor": 0.6},
        "traction_delay": {"delay": 1.5},
    }
    sc = load_scenario(tmp_scenario(lambda d: d.update(effects=eff)))
    assert sorted(sc.effects.active()) == sorted(EFFECT_NAMES)
    assert sc.train.mass == 288000.0 and sc.true_train.mass == 320000.0
    # brake_delay delays braking commands only: the world's actuator takes it from the effect,
    # the train's (traction) delay stays as train.yaml says
    assert sc.true_train.davis.a == 4000.0 and sc.true_train.brake.delay == 1.2
    assert sc.effects.brake_delay.delay == 1.6
    assert sc.effects.braking_rate.value(sc.duration) == 0.7
    assert sc.true_link.model == "gilbert_elliott" and sc.link.model == "bernoulli"
    assert sc.true_line.gradient_permille(1100.0) == 12.0 + 8.0
    # the fractions follow their intervals (which are sorted by start)
    assert sc.effects.wheel_slip.factor(15.0) == 1.2 and sc.effects.wheel_slip.factor(32.0) == 0.9
    assert sc.line.gradient_permille(1100.0) == 12.0


@pytest.mark.parametrize("name", ["metro_demo", "wen2017_subway", "zheng2015_braking",
                                  "crh3_high_speed"])
def test_shipped_scenarios_load(name):
    sc = load_scenario(name)
    assert sc.max_step <= 0.01


def test_wen_and_zheng_parameters():
    wen = load_scenario("wen2017_subway")
    assert wen.start_position == 1333.8031 and wen.start_speed == 0.0
    assert wen.odometer_rate == 1.0 and wen.link.received_probability == 0.875
    assert wen.train.odometer_distance_std ** 2 == 1.0
    assert wen.train.odometer_speed_std ** 2 == pytest.approx(0.01)
    assert [g.permille for g in wen.line.gradients] == [-3.0, 3.0, -3.0, -9.0]
    z = load_scenario("zheng2015_braking")
    assert z.train.brake.time_constant == 0.4
    assert 2.0 / z.train.brake.delay == pytest.approx(1.6667, abs=1e-4)
    assert z.effects.braking_rate.value(150.0) == pytest.approx(1.0 - 0.005 * 150)
