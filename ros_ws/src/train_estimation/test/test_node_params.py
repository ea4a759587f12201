"""Each node parameter is declared once, as a field of a config dataclass with its unit and
meaning (``train_core.config.param``); the params files document exactly those fields."""

import math
from pathlib import Path

import pytest
import yaml
from train_core.config import ConfigError, param_fields
from train_core.diagnostics import EstimatorThresholds, StaleThresholds

from train_estimation.core.online.estimators import BrakingConfig, NodeConfig, RobustConfig
from train_estimation.core.online.integrity import IntegrityParams

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
    from train_estimation.nodes.estimator_params import LineChoice

    fields = (param_fields(NodeConfig) + param_fields(LineChoice) + param_fields(NODES[name])
              + param_fields(EstimatorThresholds) + param_fields(IntegrityParams))
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
    (NodeConfig, {"initial_position_std": math.nan}), (NodeConfig, {"tick_period": 0.0}),
    (NodeConfig, {"slot_grace": -1.0}),
])
def test_validation_in_the_config_names_the_parameter(cls, bad):
    with pytest.raises(ConfigError, match=f"parameter {next(iter(bad))}:"):
        cls(**bad)


def test_recorder_params_file_has_exactly_the_declared_fields():
    from train_estimation.nodes.recorder import RecorderConfig

    params = yaml.safe_load((CONFIG / "recorder.yaml").read_text())["/**"]["ros__parameters"]
    fields = param_fields(RecorderConfig) + param_fields(StaleThresholds)
    assert set(params) == {f.name for f in fields}
    for f in fields:
        assert _same(params[f.name], f.default), f.name


# --- the running node: start-up refusals in one line, runtime changes validated ------------

def _node_output(launch, *args, name, node="robust_filter"):
    proc = launch.node("train_estimation", node, "--ros-args", *args, name=name)
    proc.wait(timeout=60)
    return proc.returncode, Path(proc.log_path).read_text()


@pytest.mark.ros
@pytest.mark.parametrize("arg,want", [
    ("q:=abc", "error: parameter q: expected a number (write 5.0, not 5), got 'abc' (string)"),
    ("use_distance:=3.5", "error: parameter use_distance: expected a boolean (true/false), "
                          "got '3.5' (double)"),
    # the descriptor's range (FloatingPointRange) refuses it first, in the same words
    ("q:=-1.0", "error: parameter q: -1.0 is out of range, allowed [0, inf)"),
    ("q:=-1", "error: parameter q: -1.0 is out of range, allowed [0, inf)"),  # int -> float
    ("alpha_bar:=1.5", "error: parameter alpha_bar: 1.5 is out of range, allowed [0, 1]"),
    ("outage_slots:=-2", "error: parameter outage_slots: -2 is out of range, allowed [0, inf)"),
    ("tick_period:=0.0", "error: parameter tick_period: 0.0 must be finite and > 0"),
    ("slot_grace:=-0.5", "error: parameter slot_grace: -0.5 is out of range, allowed [0, inf)"),
    # a typo of a parameter not given, with a value of its kind: refused (the rule of every
    # reader, train_core.config.unknown_key); the gate would silently stay at its default
    ("balise_gat:=3.0", "error: node robust_filter: unknown parameter 'balise_gat': did you "
                        "mean 'balise_gate'? (it holds a number, as 'balise_gate' would, and "
                        "'balise_gate' is absent: rename it, or the model goes without it)"),
    # a start off the line (+-inf was read as NaN, the first station); a status busy loop
    ("initial_position:=-100000.0", "error: parameter initial_position: -100000 m is off the "
                                    "line (metro_demo: 0 to 7000 m); NaN starts at its first "
                                    "station"),
    ("initial_position:=.inf", "error: parameter initial_position: inf m is off the line "
                               "(metro_demo: 0 to 7000 m); NaN starts at its first station"),
    ("diagnostics_period:=1e-9", "error: parameter diagnostics_period: 1e-09 is out of range, "
                                 "allowed [0.05, inf)"),
])
def test_a_bad_parameter_at_start_up_is_one_line_not_a_traceback(launch, arg, want):
    code, out = _node_output(launch, "-p", "use_demo_line:=true", "-p", arg,
                             name=f"bad_{arg.split(':')[0]}")
    assert code == 2, out
    assert "Traceback" not in out, out
    lines = [ln for ln in out.splitlines() if ln.strip()]
    assert lines == [want], out


@pytest.mark.ros
@pytest.mark.parametrize("arg,want", [
    # an empty list arrives from rclpy as "not set": it was a TypeError's traceback
    ("values:=[]", "error: parameter values: [] must be one or more braking rates in [0, 2], "
                   "distinct and in order (rising or falling)"),
    # a negative braking rate, and a set out of order (the priors move by index), were taken
    ("values:=[-1.0,1.0]", "error: parameter values: [-1.0, 1.0] must be one or more braking "
                           "rates in [0, 2], distinct and in order (rising or falling)"),
    ("values:=[1.0,0.5,0.7]", "error: parameter values: [1.0, 0.5, 0.7] must be one or more "
                              "braking rates in [0, 2], distinct and in order (rising or "
                              "falling)"),
    # the kernel's own words ("every value needs an allowed child") named no parameter
    ("branch_p_move:=2.0", "error: parameter branch_p_move: 2.0 is out of range, allowed "
                           "[-1, 1]"),
    ("seed:=-5", "error: parameter seed: -5 is out of range, allowed [0, inf)"),  # numpy's words
])
def test_a_bad_braking_parameter_at_start_up_names_itself(launch, arg, want):
    code, out = _node_output(launch, "-p", "use_demo_line:=true", "-p", arg,
                             name=f"bad_{arg.split(':')[0]}", node="gsma_estimator")
    assert code == 2, out
    assert [ln for ln in out.splitlines() if ln.strip()] == [want], out


@pytest.mark.ros
def test_an_integer_for_a_float_and_an_unknown_parameter_start_the_node(launch, ros_node):
    """``q:=1`` is 1.0; a parameter the node does not know (a params file shared by several
    nodes) is named in a warning with its near misses, and the node runs."""
    from rcl_interfaces.srv import GetParameters

    ns = "/params_int"
    proc = launch.node("train_estimation", "robust_filter", "--ros-args", "-r", f"__ns:={ns}",
                       "-p", "use_demo_line:=true", "-p", "q:=1", "-p", "gates:=true",
                       "-p", "operator:=north", name="int_params")
    get_cli = ros_node.node.create_client(GetParameters, f"{ns}/robust_filter/get_parameters")
    ros_node.wait_until(get_cli.service_is_ready, timeout=30, what="the parameter service")
    # answered once the node's construction is done (the first answer waits for its start-up)
    (v,) = ros_node.call(get_cli, GetParameters.Request(names=["q"]), timeout=60,
                         what="the node's first parameter answer").values
    assert v.double_value == 1.0
    assert proc.poll() is None
    log = Path(proc.log_path).read_text()
    assert "unknown parameter 'operator' is ignored (known: " in log, log
    # 'gates' is near 'gate', but a boolean is not a gate's kind of value: allowed, named
    assert "unknown parameter 'gates' is ignored; near: 'gate' (holds a number)" in log, log


def test_unknown_overrides_follow_the_rule_of_every_reader():
    from train_core.ros import ParameterError, unknown_overrides

    declared = {"gate": 8.0, "balise_gate": 4.0, "seed": 0, "use_distance": True}
    # a parameter of another node (a shared params file): named, allowed
    (msg,) = unknown_overrides(declared, {"rate_factor": 2.0}, "node x")
    assert msg.startswith("node x: unknown parameter 'rate_factor' is ignored (known: ")
    # near a parameter that is given too: a second spelling, allowed
    (msg,) = unknown_overrides(declared, {"gate": 5.0, "gates": 5.0}, "node x")
    assert "'gates' is ignored; near: 'gate' (given)" in msg
    # near one that is not given, of its kind: the typo would leave the gate at its default
    with pytest.raises(ParameterError, match="'gates': did you mean 'gate'"):
        unknown_overrides(declared, {"gates": 5.0}, "node x")
    # an integer is a number's kind too (a float parameter accepts it)
    with pytest.raises(ParameterError, match="'balise_gat': did you mean 'balise_gate'"):
        unknown_overrides(declared, {"balise_gat": 3}, "node x")
    assert unknown_overrides(declared, {"gate": 1.0, "qos_overrides./a.depth": 5}, "x") == []


def test_help_lists_the_parameters_with_units_defaults_and_ranges(capsys):
    from train_estimation.nodes import gsma_estimator

    with pytest.raises(SystemExit) as exc:
        gsma_estimator.main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    from train_estimation.nodes.estimator_params import node_params

    for cls in node_params(BrakingConfig):
        for f in param_fields(cls):
            assert f"  {f.name} (" in out, f.name
    assert "  odometer_rate (Hz) = 10.0 [0, inf): odometer sample rate" in out
    assert "  odometer_scale (-) = 1.0 [0.5, 2]:" in out
    assert "  algorithm (no unit) = 'gsma':" in out


@pytest.mark.ros
def test_an_estimator_without_a_line_file_refuses_to_start(launch):
    code, out = _node_output(launch, name="no_line")
    assert code == 2 and "Traceback" not in out, out
    assert out.strip() == ("error: parameter line_file: empty: give the line.yaml the train "
                           "runs on (or use_demo_line:=true to run on the demo's line, "
                           "metro_demo)")


@pytest.mark.ros
def test_runtime_set_parameters_is_validated_and_refused_with_a_reason(launch, ros_node):
    """q = -1 is refused with the dataclass's reason; a valid q is refused too (read at start-up:
    accepting it would be a silent no-op); diagnostics thresholds change live, checked."""
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import GetParameters, SetParameters

    ns = "/params"
    proc = launch.node("train_estimation", "robust_filter", "--ros-args", "-r", f"__ns:={ns}",
                       "-p", "use_demo_line:=true", name="live_params")
    node = ros_node.node
    set_cli = node.create_client(SetParameters, f"{ns}/robust_filter/set_parameters")
    get_cli = node.create_client(GetParameters, f"{ns}/robust_filter/get_parameters")
    ros_node.wait_until(lambda: set_cli.service_is_ready() and get_cli.service_is_ready(),
                        timeout=30, what="the node's parameter services")

    def call(client, request, timeout=10.0, what="a parameter service answer"):
        return ros_node.call(client, request, timeout=timeout, what=what)

    # the services are discovered as soon as rclpy's Node is made, and answered once the node's
    # construction (models, filter, kernels) is done and it spins: the first answer waits for
    # that start-up, which a loaded machine stretches past the 10 s given to one answer; the
    # checks below are about the answers, not the start-up
    call(get_cli, GetParameters.Request(names=["q"]), timeout=60.0,
         what="the node's first parameter answer (its start-up)")

    def set_double(name, value):
        p = Parameter(name=name, value=ParameterValue(type=ParameterType.PARAMETER_DOUBLE,
                                                      double_value=value))
        (result,) = call(set_cli, SetParameters.Request(parameters=[p])).results
        return result

    def get(name):
        (v,) = call(get_cli, GetParameters.Request(names=[name])).values
        return v.double_value

    r = set_double("q", -1.0)  # outside the descriptor's range: rclpy's own words
    assert not r.successful and "out of range" in r.reason, r.reason
    r = set_double("stale_warn", math.inf)  # in range, refused by the dataclass's check
    assert not r.successful and r.reason.startswith("parameter stale_warn:"), r.reason
    # a wrong type is refused with a reason (rclpy's type check), and the node keeps running
    p = Parameter(name="q", value=ParameterValue(type=ParameterType.PARAMETER_STRING,
                                                 string_value="abc"))
    (r,) = call(set_cli, SetParameters.Request(parameters=[p])).results
    assert not r.successful and "type" in r.reason.lower(), r.reason
    assert proc.poll() is None
    r = set_double("q", 0.5)
    assert not r.successful
    assert r.reason == "parameter q: read at start-up only; restart the node to change it"
    assert get("q") == 0.49  # unchanged
    r = set_double("stale_warn", 6.0)  # above stale_error (5.0): the pair's check
    assert not r.successful and r.reason.startswith("parameter stale_error:"), r.reason
    r = set_double("stale_warn", 3.0)
    assert r.successful, r.reason
    assert get("stale_warn") == 3.0
    # a float parameter accepts an integer at run time too
    p = Parameter(name="stale_warn", value=ParameterValue(type=ParameterType.PARAMETER_INTEGER,
                                                          integer_value=4))
    (r,) = call(set_cli, SetParameters.Request(parameters=[p])).results
    assert r.successful, r.reason
    assert get("stale_warn") == 4.0
    # a live change takes effect: four statuses a second after diagnostics_period := 0.25
    from diagnostic_msgs.msg import DiagnosticArray

    assert set_double("diagnostics_period", 0.25).successful
    box = ros_node.collect(DiagnosticArray, "/diagnostics")
    ros_node.spin_for(2.0)
    mine = [s for a in box for s in a.status if s.hardware_id == ns]
    assert 6 <= len(mine) <= 9, len(mine)
    # a set refused as a whole changes nothing: the period (live) with q (start-up only) in one
    # atomic set; the period was applied before q's refusal, 40 statuses in 2 s instead of 8
    from rcl_interfaces.srv import SetParametersAtomically

    atomic = node.create_client(SetParametersAtomically,
                                f"{ns}/robust_filter/set_parameters_atomically")
    ros_node.wait_until(atomic.service_is_ready, timeout=30, what="the atomic set service")
    both = [Parameter(name=n, value=ParameterValue(type=ParameterType.PARAMETER_DOUBLE,
                                                  double_value=v))
            for n, v in (("diagnostics_period", 0.05), ("q", 0.5))]
    r = call(atomic, SetParametersAtomically.Request(parameters=both)).result
    assert not r.successful and r.reason.startswith("parameter q: read at start-up only"), r
    assert get("diagnostics_period") == 0.25
    box.clear()
    ros_node.spin_for(2.0)
    mine = [s for a in box for s in a.status if s.hardware_id == ns]
    assert 6 <= len(mine) <= 9, len(mine)
    # use_sim_time is read at start-up too: switched at run time, the node's clock jumped to
    # another time base under estimates already out
    p = Parameter(name="use_sim_time", value=ParameterValue(type=ParameterType.PARAMETER_BOOL,
                                                            bool_value=True))
    (r,) = call(set_cli, SetParameters.Request(parameters=[p])).results
    assert not r.successful, r
    assert r.reason == ("parameter use_sim_time: read at start-up only; restart the node to "
                        "change it")
    assert proc.poll() is None


def test_an_empty_train_file_is_refused_unless_the_demo_is_asked_for():
    # an estimator on another train's mass, resistance and brake is off with no sign of it
    from train_core.files import config_file

    from train_estimation.nodes.estimator_params import ParameterError, load_models

    line = str(config_file("lines", "metro_demo"))
    common = dict(line_file=line, train_file="", initial_position=math.nan,
                  initial_position_std=5.0, initial_position_fault=50.0)
    with pytest.raises(ParameterError, match="parameter train_file: empty"):
        load_models(common)
    train, _, _ = load_models(dict(common, use_demo_line=True))
    assert train.mass > 0


@pytest.mark.ros
def test_the_node_timer_publishes_a_lost_1hz_slot_before_the_next_message(launch, ros_node):
    """odometer_rate 1 Hz, slot_grace 0.2 s: the estimate of a reading that never comes leaves
    by the node's timer (tick_period), with no later message to push it out (without the timer
    it waits for the next cycle's messages)."""
    import time

    from train_core.ros import sec_to_stamp, stamp_to_sec

    from train_interfaces.msg import ControlCommand, OdometerReading, TrainState

    ns = "/slot_tick"
    launch.node("train_estimation", "robust_filter", "--ros-args", "-r", f"__ns:={ns}",
                "-p", "use_demo_line:=true", "-p", "odometer_rate:=1.0",
                "-p", "slot_grace:=0.2", "-p", "tick_period:=0.05", name="slot_tick")
    node = ros_node.node
    est = ros_node.collect(TrainState, f"{ns}/estimate/robust")
    odo = node.create_publisher(OdometerReading, f"{ns}/odometer", 100)
    ctl = node.create_publisher(ControlCommand, f"{ns}/control", 100)
    ros_node.wait_for_subscribers(f"{ns}/odometer")
    ros_node.wait_for_subscribers(f"{ns}/control")
    ros_node.wait_for_publishers(f"{ns}/estimate/robust")
    start, lost = time.time() + 1.0, 12  # the clock is judged after 9 readings

    def wait_until_time(t):
        ros_node.spin_for(max(0.0, t - time.time()))

    for k in range(lost + 1):
        wait_until_time(start + k)
        c, o = ControlCommand(), OdometerReading()
        sec_to_stamp(start + k, c.header.stamp)
        sec_to_stamp(start + k, o.header.stamp)
        c.target_acceleration = 0.0
        o.seq, o.distance, o.speed, o.speed_variance = k, 0.0, 0.0, 0.01
        ctl.publish(c)
        if k != lost:  # that reading is lost, its cycle's command is not
            odo.publish(o)
    # no message is sent after that cycle: only the node's timer can release the lost slot's
    # estimate (without it the slot waits for the next message, which never comes). How soon
    # it leaves is a latency, measured by `./run bench latency`, not timed here: a CI host
    # that stalls a process for seconds must not fail this test
    ros_node.wait_until(
        lambda: any(abs(stamp_to_sec(m.header.stamp) - (start + lost)) < 1e-3 for m in est),
        timeout=10.0, what="the lost slot's estimate")
    stamps = [stamp_to_sec(m.header.stamp) for m in est]
    assert any(abs(s - (start + lost - 1)) < 1e-3 for s in stamps), (launch.logs(), stamps)
    mine = [m for m, s in zip(est, stamps) if abs(s - (start + lost)) < 1e-3]
    assert len(mine) == 1, ([s - start for s in stamps], launch.logs())
    assert not mine[0].measurement_used and mine[0].integrity != 2, mine[0]  # bounded


def test_an_event_and_a_refusal_log_through_one_method_without_killing_the_node():
    """``EstimatorNode._log_event`` logs events at INFO and refusals at WARN. rclpy's logger
    refuses a call site whose severity changes between calls (ValueError): written as one
    call with the severity chosen, the first refusal after an event killed the estimator in
    its callback (the by-hand recipe at 10x under load)."""
    from types import SimpleNamespace

    from rclpy.logging import get_logger

    from train_estimation.nodes.estimator_node import EstimatorNode

    log = get_logger("log_event_test")  # one logger, as a node's get_logger() returns
    me = SimpleNamespace(event_log={}, get_logger=lambda: log)
    for k in range(3):
        EstimatorNode._log_event(me, "odometer", 1.0 + k, "seq_reset: 3 -> 0", 100.0 * k)
        EstimatorNode._log_event(me, "odometer", 1.5 + k, "rejected: duplicate", 100.0 * k,
                                 warn=True, what="rejected duplicate")
    assert set(me.event_log) == {("odometer", "seq_reset"), ("odometer", "rejected duplicate")}
