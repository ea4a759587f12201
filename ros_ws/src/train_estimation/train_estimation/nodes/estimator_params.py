"""The parameters and models of the estimator nodes, without rclpy (their ``--help`` and tests
read these; :mod:`train_estimation.nodes.estimator_node` is the node)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from train_core.config import param
from train_core.ros import ParameterError, declare_config


@dataclass(frozen=True)
class LineChoice:
    """Whether an estimator may run on the demo's line when no line file is given."""

    use_demo_line: bool = param(False, "", "with line_file or train_file empty, run on the "
                                "demo's line and train (metro_demo, metro_b6); false: an empty "
                                "line_file or train_file is refused")


def node_params(adapter_config) -> tuple:
    """The config dataclasses an estimator node declares (for its ``--help``): the common ones,
    the algorithm's ``adapter_config``, the integrity's and the diagnostics' thresholds."""
    from train_core.diagnostics import EstimatorThresholds

    from train_estimation.core.online.estimators import NodeConfig
    from train_estimation.core.online.integrity import IntegrityParams

    return (NodeConfig, LineChoice, adapter_config, IntegrityParams, EstimatorThresholds)


def declare_common(node) -> dict:
    """Parameters every estimator node has (``core.online.estimators.NodeConfig``;
    config/*.yaml)."""
    from dataclasses import asdict

    from train_estimation.core.online.estimators import NodeConfig

    try:
        common = asdict(declare_config(node, NodeConfig))
        common.update(asdict(declare_config(node, LineChoice)))
    except ValueError as exc:
        raise ParameterError(str(exc)) from None
    return common


def load_models(common: dict):
    """(train, line, StartState) from the file parameters; ParameterError with one line if bad."""
    from train_core.config import ConfigError
    from train_core.files import config_file
    from train_core.model import load_line, load_train

    from train_estimation.core.online.estimators import StartState

    if not common["line_file"] and not common.get("use_demo_line", False):
        # an estimator on the wrong line map is wrong everywhere: never guess it silently
        raise ParameterError("parameter line_file: empty: give the line.yaml the train runs on "
                             "(or use_demo_line:=true to run on the demo's line, metro_demo)")
    if not common["train_file"] and not common.get("use_demo_line", False):
        # nor on another train's mass, resistance and brake: the braking-rate and the
        # predictions through a gap would be off with no sign of it
        raise ParameterError("parameter train_file: empty: give the train.yaml of the train "
                             "(mass, resistance, brake, odometer noise) (or "
                             "use_demo_line:=true to run on the demo's train, metro_b6)")
    line_file = common["line_file"] or str(config_file("lines", "metro_demo"))
    train_file = common["train_file"] or str(config_file("trains", "metro_b6"))
    try:
        line, train = load_line(line_file), load_train(train_file)
    except ConfigError as exc:
        raise ParameterError(str(exc)) from None
    x0 = common["initial_position"]
    if math.isnan(x0):
        x0 = line.stations[0].position if line.stations else 0.0
    elif not 0.0 <= x0 <= line.length:  # +-inf included: NaN alone means the first station
        raise ParameterError(f"parameter initial_position: {x0:g} m is off the line "
                             f"({line.name}: 0 to {line.length:g} m); NaN starts at its "
                             "first station")
    return train, line, StartState(position=x0, position_std=common["initial_position_std"],
                                    position_fault=common["initial_position_fault"])
