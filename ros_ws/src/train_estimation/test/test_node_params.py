"""Each node parameter is declared once, as a field of a config dataclass with its unit and
meaning (``train_core.config.param``); the params files document exactly those fields."""

import math
from pathlib import Path

import pytest
import yaml
from train_core.config import ConfigError, param_fields

from train_estimation.core.estimators import BrakingConfig, NodeConfig, RobustConfig
from train_estimation.core.integrity import IntegrityParams

CONFIG = Path(__file__).resolve().parents[1] / "config"
NODES = {"robust_filter.yaml": RobustConfig, "gsma_estimator.yaml": BrakingConfig}


def _same(a, b):
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    if isinstance(b, tuple):
        return list(b) == list(a)
    return a == b


@pytest.mark.parametrize("name", sorted(NODES))
def test_params_file_has_exactly_the_declared_fields_with_their_defaults(name):
    params = yaml.safe_load((CONFIG / name).read_text())["/**"]["ros__parameters"]
    fields = param_fields(NodeConfig) + param_fields(NODES[name]) + param_fields(IntegrityParams)
    declared = {f.name for f in fields}
    assert set(params) == declared, (set(params) - declared, declared - set(params))
    for f in fields:
        default = f.default
        to_ros = f.metadata.get("ros", (None, None))[0]
        if to_ros:
            default = to_ros(default)
        assert _same(params[f.name], default), (f.name, params[f.name], default)
        assert f.metadata["doc"], f.name


def test_every_parameter_field_has_a_unit_and_a_meaning():
    for cls in (NodeConfig, RobustConfig, BrakingConfig, IntegrityParams):
        for f in param_fields(cls):
            assert isinstance(f.metadata["unit"], str) and len(f.metadata["doc"]) > 5, f.name


@pytest.mark.parametrize("cls,bad", [
    (RobustConfig, {"alpha_bar": 0.0}), (RobustConfig, {"gate": -1.0}),
    (RobustConfig, {"distance_variance": 0.0}), (RobustConfig, {"q": math.inf}),
    (BrakingConfig, {"algorithm": "nope"}), (BrakingConfig, {"braking_rate_prior_std": 0.0}),
    (NodeConfig, {"odometer_rate": 0.0}), (NodeConfig, {"output_delay": -1.0}),
    (NodeConfig, {"initial_position_std": math.nan}),
])
def test_validation_in_the_config_names_the_parameter(cls, bad):
    with pytest.raises(ConfigError, match=f"parameter {next(iter(bad))}:"):
        cls(**bad)


def test_recorder_params_file_has_exactly_the_declared_fields():
    from train_estimation.nodes.recorder import RecorderConfig

    params = yaml.safe_load((CONFIG / "recorder.yaml").read_text())["/**"]["ros__parameters"]
    fields = param_fields(RecorderConfig)
    assert set(params) == {f.name for f in fields}
    for f in fields:
        assert _same(params[f.name], f.default), f.name
