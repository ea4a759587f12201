"""Keys of line.yaml/train.yaml: extra keys are allowed and named in a warning with their near
misses; a typo is an error only where it would silently change the model (the key meant is
absent and the value has that key's kind), naming the key meant; every shipped file loads
without either."""

import warnings
from pathlib import Path

import pytest
import yaml
from train_core.config import ConfigError, ConfigWarning
from train_core.model import load_line, load_train

SRC = Path(__file__).resolve().parents[2]
LINES = sorted((SRC / "train_core" / "config" / "lines").glob("*.yaml"))
TRAINS = sorted((SRC / "train_core" / "config" / "trains").glob("*.yaml"))
SCENARIOS = sorted((SRC / "train_sim" / "scenarios").glob("*.yaml"))


def edited(tmp_path, src, **changes):
    data = yaml.safe_load(src.read_text())
    for old, new in changes.items():
        if new is None:
            data[old] = "anything"
        else:
            data[new] = data.pop(old)
    path = tmp_path / src.name
    path.write_text(yaml.safe_dump(data))
    return path


def test_misspelt_line_key_is_an_error_naming_the_key_meant(tmp_path):
    path = edited(tmp_path, LINES[0], gradients="gradeints")
    assert isinstance(yaml.safe_load(path.read_text())["gradeints"], list)
    with pytest.raises(ConfigError, match="'gradeints'.*did you mean 'gradients'"):
        load_line(path)


def test_a_producers_line_wide_speed_limit_beside_the_map_loads_with_a_warning(tmp_path):
    data = yaml.safe_load(LINES[0].read_text())
    data["speed_limits"] = [{"start": 0.0, "end": 100.0, "speed": 10.0}]
    data["speed_limit"] = 22.2  # a producer's own key, near 'speed_limits', which is given
    path = tmp_path / "line.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.warns(ConfigWarning, match="'speed_limit' is ignored.*'speed_limits' \\(given\\)"):
        line = load_line(path)
    assert line.speed_limits[0].speed == 10.0
    # without speed_limits a number still is not a list of sections: allowed, named
    del data["speed_limits"]
    path.write_text(yaml.safe_dump(data))
    with pytest.warns(ConfigWarning, match="'speed_limit' is ignored.*'speed_limits'"):
        assert load_line(path).speed_limits == ()


def test_a_near_key_of_another_kind_is_a_warning_not_an_error(tmp_path):
    data = yaml.safe_load(LINES[0].read_text())
    data["gradient"] = "as surveyed in 2019"  # a string, not a list of sections
    path = tmp_path / "line.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.warns(ConfigWarning, match="'gradient' is ignored"):
        load_line(path)


def test_extra_and_misspelt_keys_inside_the_lines_entries(tmp_path):
    data = yaml.safe_load(LINES[0].read_text())
    data["gradients"][0]["radius"] = 300.0  # a curve radius kept beside the gradient
    path = tmp_path / "line.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.warns(ConfigWarning, match=r"gradients\[0\]: unknown key 'radius'"):
        load_line(path)
    data["stations"] = [{"name": "A", "position": 0.0, "dwel": 60.0}]  # dwell stays 30 s
    path.write_text(yaml.safe_dump(data))
    with pytest.warns(ConfigWarning, match="'radius'"), \
            pytest.raises(ConfigError, match="'dwel'.*did you mean 'dwell'"):
        load_line(path)


def test_misspelt_train_key_is_an_error_naming_the_key_meant(tmp_path):
    path = edited(tmp_path, TRAINS[0], performance="perfomance")
    with pytest.raises(ConfigError, match="'perfomance'.*did you mean 'performance'"):
        load_train(path)


def test_unknown_key_is_named_in_a_warning_and_the_file_loads(tmp_path):
    path = edited(tmp_path, LINES[0], operator=None)
    with pytest.warns(ConfigWarning, match="unknown key 'operator' is ignored"):
        line = load_line(path)
    assert line.length > 0
    path = edited(tmp_path, TRAINS[0], fleet_number=None)
    with pytest.warns(ConfigWarning, match="'fleet_number'"):
        load_train(path)


@pytest.mark.parametrize("path", LINES + TRAINS, ids=lambda p: p.name)
def test_shipped_files_load_without_warnings(path):
    assert path.is_file()
    with warnings.catch_warnings():
        warnings.simplefilter("error", ConfigWarning)
        (load_line if path.parent.name == "lines" else load_train)(path)


@pytest.mark.parametrize("path", SCENARIOS, ids=lambda p: p.name)
def test_shipped_scenarios_load_without_warnings(path):
    from train_sim.real_lines import REAL_SCENARIOS, available
    from train_sim.scenario import load_scenario

    if path.stem in REAL_SCENARIOS:  # a real line's file is not in the repository
        missing = available([path.stem])[1]
        if missing:
            pytest.skip(missing[path.stem])
    with warnings.catch_warnings():
        warnings.simplefilter("error", ConfigWarning)
        load_scenario(path)


def test_the_trains_sections_allow_extra_keys_but_not_typos(tmp_path):
    data = yaml.safe_load(TRAINS[0].read_text())
    data["brake"]["kind"] = "disc"  # a producer's note beside the brake's parameters
    path = tmp_path / "train.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.warns(ConfigWarning, match="brake: unknown key 'kind' is ignored"):
        load_train(path)
    data["odometer"] = {"speed_sd": 0.3}  # speed_std would silently stay 0.1 m/s
    path.write_text(yaml.safe_dump(data))
    with pytest.warns(ConfigWarning), \
            pytest.raises(ConfigError, match="'speed_sd'.*did you mean 'speed_std'"):
        load_train(path)
    del data["odometer"]
    data["davis"] = {"A": 1.0, "b": 1.0, "c": 1.0}  # a required key is still required
    path.write_text(yaml.safe_dump(data))
    with pytest.warns(ConfigWarning), pytest.raises(ConfigError, match="missing key 'a'"):
        load_train(path)


def test_a_line_may_state_its_alert_limit(tmp_path):
    """``alert_limit`` (m): the operation's on this line; NaN where the line states none, and
    refused where it is no length (the estimators label by it)."""
    import math

    assert math.isnan(load_line(LINES[0]).alert_limit)
    data = yaml.safe_load(LINES[0].read_text())
    path = tmp_path / "line.yaml"
    path.write_text(yaml.safe_dump(dict(data, alert_limit=25.0)))
    assert load_line(path).alert_limit == 25.0
    path.write_text(yaml.safe_dump(dict(data, alert_limit=-1.0)))
    with pytest.raises(ConfigError, match="alert_limit"):
        load_line(path)


def test_load_yaml_reads_every_shipped_file_as_the_pure_python_parser_does(tmp_path):
    """load_yaml parses with libyaml where PyYAML has it: the same values as yaml.safe_load
    (every shipped line, train, scenario and config file), and a broken file is a one-line
    ConfigError naming its line (and the parser's problem) either way."""
    from train_core.config import load_yaml

    files = sorted(SRC.glob("*/config/**/*.yaml")) + SCENARIOS
    assert len(files) >= 12
    for f in files:
        assert repr(load_yaml(f)) == repr(yaml.safe_load(f.read_text())), f
    bad = tmp_path / "bad.yaml"
    bad.write_text("mass: [1, 2\n davis: {")
    with pytest.raises(ConfigError, match=r"bad.yaml: not valid YAML \(line 2\): [^\n]+$"):
        load_yaml(bad)


def _line_text(tmp_path, text: str, data: bytes | None = None):
    path = tmp_path / "line.yaml"
    if data is not None:
        path.write_bytes(data)
    else:
        path.write_text(text)
    return path


def test_a_key_given_twice_is_refused_not_silently_replaced(tmp_path):
    text = ("name: t\nlength: 7000.0\ngradients:\n  - {start: 0, end: 500, permille: 2}\n"
            "gradients:\n  - {start: 4000, end: 4500, permille: 9}\n")
    with pytest.raises(ConfigError, match=r"key 'gradients' given twice .*lines 3 and 5"):
        load_line(_line_text(tmp_path, text))


def test_a_decimal_comma_in_a_flow_mapping_is_refused(tmp_path):
    text = "name: t\nlength: 5000.0\ngradients:\n  - {start: 0.0, end: 2000.0, permille: -3,5}\n"
    with pytest.raises(ConfigError, match=r"'permille: -3,5' .* write -3.5"):
        load_line(_line_text(tmp_path, text))


def test_another_encoding_is_refused_with_what_to_do(tmp_path):
    path = _line_text(tmp_path, "", "name: Zürich\nlength: 5000.0\n".encode("cp1252"))
    with pytest.raises(ConfigError, match=r"not UTF-8 text \(byte 0xfc on line 1\).*iconv"):
        load_line(path)


def test_yaml_1_2_exponents_are_numbers_and_tabs_are_named(tmp_path):
    assert load_line(_line_text(tmp_path, "name: t\nlength: 5e3\n")).length == 5000.0
    with pytest.raises(ConfigError, match=r"line 3.*a tab on that line"):
        load_line(_line_text(tmp_path, "name: t\nlength:\n\t5000\n"))


@pytest.mark.parametrize("extra, what", [
    ("balises:\n  - {id: 1, position: 5200.0}\n", r"balises\[0\].position"),
    ("balises:\n  - {id: 1, position: -3.0}\n", r"balises\[0\].position"),
    ("gradients:\n  - {start: 4000.0, end: 5500.0, permille: 2}\n", r"gradients\[0\].end"),
    ("speed_limits:\n  - {start: 300.0, end: 100.0, speed: 10}\n",
     r"speed_limits\[0\]: end \(100\) must be greater than start \(300\)"),
])
def test_places_off_the_line_are_refused(tmp_path, extra, what):
    """A balise or a section beyond the line's end is a unit slip (km for m) or another line's
    map; a speed limit that ends before it starts is a typo: refused, not read."""
    with pytest.raises(ConfigError, match=what):
        load_line(_line_text(tmp_path, "name: t\nlength: 5000.0\n" + extra))
