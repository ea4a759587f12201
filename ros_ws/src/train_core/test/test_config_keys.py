"""Top-level keys of line.yaml/train.yaml: unknown ones are named in a warning, a near miss of a
known key is an error naming the key meant, and every shipped file loads without either."""

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
    with pytest.raises(ConfigError, match="'gradeints'.*did you mean 'gradients'"):
        load_line(path)


def test_misspelt_train_key_is_an_error_naming_the_key_meant(tmp_path):
    path = edited(tmp_path, TRAINS[0], performance="perfomance")
    with pytest.raises(ConfigError, match="'perfomance'.*did you mean 'performance'"):
        load_train(path)


def test_unknown_key_is_named_in_a_warning_and_the_file_loads(tmp_path):
    path = edited(tmp_path, LINES[0], operator=None)
    with pytest.warns(ConfigWarning, match="unknown top-level key 'operator'"):
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
