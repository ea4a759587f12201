"""ROS-layer helpers shared by every node of the project (this module imports rclpy).

- message <-> plain dict conversion (the core speaks dicts with docs/interfaces.md's field names);
- stamps: seconds (float) <-> builtin_interfaces/Time;
- argument handling so every executable answers ``--help`` without starting ROS;
- a ``run_node`` wrapper that spins until SIGINT/SIGTERM and shuts down cleanly;
- parameters declared from config dataclasses, validated at start-up and at run time;
- ``/diagnostics``: a node's :class:`train_core.diagnostics.Status` as a DiagnosticArray.
"""

from __future__ import annotations

import argparse
import re
import signal
import sys
from collections.abc import Callable

import numpy as np

from train_core import bagio

# short message name -> Python class path; docs/interfaces.md topic -> short message name (a table,
# bagio's, serves the bag tools and the nodes)
TYPES = {n: f"train_interfaces.msg.{n}" for n in bagio.MSG_NAMES}
TOPIC_TYPES = {t: full.rsplit("/", 1)[-1] for t, full in bagio.TOPIC_TYPES.items()}


def msg_class(name: str):
    """The message class for a short name ('TrainState') or a full 'pkg/msg/Name'."""
    short = name.rsplit("/", 1)[-1]
    module, cls = TYPES[short].rsplit(".", 1)
    return getattr(__import__(module, fromlist=[cls]), cls)


def stamp_to_sec(stamp) -> float:
    return stamp.sec + stamp.nanosec * 1e-9


def sec_to_stamp(t: float, stamp=None):
    """Fill a builtin_interfaces/Time from seconds (rounded to the nanosecond)."""
    from builtin_interfaces.msg import Time

    stamp = stamp if stamp is not None else Time()
    ns = int(round(t * 1e9))
    stamp.sec, stamp.nanosec = divmod(ns, 1_000_000_000)
    return stamp


def msg_to_dict(msg) -> dict:
    """Recursively turn a ROS message into a dict (arrays become lists)."""
    out = {}
    for field in msg.get_fields_and_field_types():
        value = getattr(msg, field)
        if hasattr(value, "get_fields_and_field_types"):
            value = msg_to_dict(value)
        elif isinstance(value, np.ndarray):
            value = value.tolist()
        elif isinstance(value, (list, tuple)):
            value = list(value)
        out[field] = value
    return out


def dict_to_msg(data: dict, msg):
    """Fill ``msg`` from a dict with the message's field names (nested dicts for sub-messages)."""
    for field, value in data.items():
        current = getattr(msg, field)
        if hasattr(current, "get_fields_and_field_types"):
            dict_to_msg(value, current)
        elif isinstance(current, np.ndarray):
            setattr(msg, field, np.asarray(value, dtype=current.dtype))
        else:
            setattr(msg, field, value)
    return msg


def fields_to_msg(type_name: str, stamp: float, fields: dict, frame_id: str = "track"):
    """A message of ``type_name`` with header stamped at ``stamp`` (s) and the core's fields."""
    msg = msg_class(type_name)()
    sec_to_stamp(stamp, msg.header.stamp)
    msg.header.frame_id = frame_id
    for key, value in fields.items():
        current = getattr(msg, key)
        if isinstance(current, np.ndarray):
            setattr(msg, key, np.asarray(value, dtype=current.dtype))
        elif isinstance(current, bool):
            setattr(msg, key, bool(value))
        elif isinstance(current, int):
            setattr(msg, key, int(value))
        elif isinstance(current, float):
            setattr(msg, key, float(value))
        else:
            setattr(msg, key, value)
    return msg


ESTIMATOR_INPUTS = ("control", "odometer", "balise")


def inputs_matched(pubs: dict, n: int) -> bool:
    """True when each estimator input topic published (``pubs``: topic -> publisher) has at
    least ``n`` subscribers. A sender waits for this before its first message: DDS does not
    keep volatile messages for readers matched later, so a reader discovered on one topic but
    not yet on another would miss, say, the first command (and compute something else than the
    offline replay of the same bag)."""
    return all(pubs[t].get_subscription_count() >= n for t in ESTIMATOR_INPUTS if t in pubs)


def unacknowledged(pubs: dict) -> list[str]:
    """The topics (of ``pubs``: topic -> publisher) whose reliable readers have not all
    acknowledged every message yet (a publisher that sent nothing has nothing unacknowledged).

    A matched subscription count is the writer's side of discovery only: the reader may
    discover the writer later, and until it does it drops the writer's data, which the
    writer then sends again. One reader can thus get a topic's first messages a moment after
    another topic's (at 20x real time, 100 ms of wall time are 2 s of stamps): a fresh-clone
    CI run had the GSMA's first command reach it after 2.2 s of odometer readings, fused late,
    and its estimate at 0.1 s differed from the same run's in the 8th digit. A sender that
    waits for its first messages to be acknowledged before sending more knows every reader
    has each topic from its first message on; after that, a reliable topic is delivered in
    order. (Non-blocking: rmw's wait with a zero timeout; a best-effort reader acknowledges
    nothing and is not waited for.)"""
    from rclpy.duration import Duration

    now = Duration(seconds=0)
    return [t for t, p in pubs.items() if not p.wait_for_all_acked(now)]


def declarer(node):
    """``declare(name, default, text, lo=None, hi=None) -> value``: declare_parameter with a
    descriptor (the description; ``lo``/``hi``: a FloatingPointRange or IntegerRange).

    A float parameter accepts an integer (``-p rate:=10``, ``rate: 10`` in a params file): the
    override is converted at start-up, a ``set_parameters`` through a pre-set callback. A
    value of another type (``-p q:=abc``) or out of range raises :class:`ParameterError` with
    one line naming the parameter, the type or range wanted and the value given, instead of
    rclpy's traceback.
    """
    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException

    _accept_integers_for_floats(node)
    _hold_use_sim_time(node)

    def declare(name, default, text, lo=None, hi=None):
        desc = ParameterDescriptor(description=text)
        _set_range(desc, default, lo, hi)
        over = node._parameter_overrides.get(name)
        if (isinstance(default, float) and over is not None and isinstance(over.value, int)
                and not isinstance(over.value, bool)):
            from rclpy.parameter import Parameter

            node._parameter_overrides[name] = Parameter(name, value=float(over.value))
        try:
            return node.declare_parameter(name, default, desc).value
        except InvalidParameterTypeException as exc:
            m = re.search(r"to '(.*)' of type '(\w+)'", str(exc))
            given = f"{m.group(1)!r} ({m.group(2).lower()})" if m else "another type"
            raise ParameterError(f"parameter {name}: expected {_type_name(default)}, got "
                                 f"{given}") from None
        except InvalidParameterValueException as exc:
            over = node._parameter_overrides.get(name)
            if over is not None and (lo is not None or hi is not None):
                from train_core.config import _range_text

                raise ParameterError(f"parameter {name}: {over.value!r} is out of range, "
                                     f"allowed {_range_text(lo, hi)}") from None
            raise ParameterError(f"parameter {name}: {getattr(exc, 'reason', exc)}") from None

    return declare


DRAIN_BUDGET = 2.0  # s, the longest a node that records drains its queues at a stop
INT_BOUND = 2 ** 63 - 1  # IntegerRange is int64: "unbounded" on one side


def _set_range(desc, default, lo, hi) -> None:
    """The descriptor's range for a numeric parameter with a declared ``lo`` and/or ``hi``."""
    if lo is None and hi is None or isinstance(default, bool):
        return
    from rcl_interfaces.msg import FloatingPointRange, IntegerRange

    if isinstance(default, float):
        desc.floating_point_range = [FloatingPointRange(
            from_value=float(-np.inf if lo is None else lo),
            to_value=float(np.inf if hi is None else hi), step=0.0)]
    elif isinstance(default, int):
        desc.integer_range = [IntegerRange(
            from_value=int(-INT_BOUND if lo is None else lo),
            to_value=int(INT_BOUND if hi is None else hi), step=1)]


def _accept_integers_for_floats(node) -> None:
    """Once per node: a ``set_parameters`` giving an integer to a float parameter sets the
    float (rclpy would refuse it: "Wrong parameter type")."""
    if getattr(node, "_train_int_to_float", False) or not hasattr(
            node, "add_pre_set_parameters_callback"):
        return
    from rclpy.parameter import Parameter

    def pre_set(params):
        out = []
        for p in params:
            if (p.type_ == Parameter.Type.INTEGER and node.has_parameter(p.name)
                    and node.get_parameter(p.name).type_ == Parameter.Type.DOUBLE):
                p = Parameter(p.name, value=float(p.value))
            out.append(p)
        return out

    node.add_pre_set_parameters_callback(pre_set)
    node._train_int_to_float = True


def _hold_use_sim_time(node) -> None:
    """Once per node: ``use_sim_time`` is read at start-up only. A node's stamps, arrival times,
    timers and the estimators' stream clocks are all on the time base it started on; switched at
    run time (rclpy's own parameter, which its TimeSource applies at once), an estimator on
    /clock's 18 s found its clock at the system's 1.7e9 s, published 6,125 predictions in ten
    seconds and refused every reading after them. Refused with a reason, as any start-up
    parameter. (This callback is added after the TimeSource's, so rclpy asks it first.)"""
    if getattr(node, "_train_clock_held", False):
        return
    from rcl_interfaces.msg import SetParametersResult

    def callback(params):
        for p in params:
            if p.name == "use_sim_time" and node.has_parameter(p.name) \
                    and p.value != node.get_parameter(p.name).value:
                return SetParametersResult(
                    successful=False, reason="parameter use_sim_time: read at start-up only; "
                                             "restart the node to change it")
        return SetParametersResult(successful=True)

    node.add_on_set_parameters_callback(callback)
    node._train_clock_held = True


def _type_name(default) -> str:
    if isinstance(default, bool):
        return "a boolean (true/false)"
    if isinstance(default, int):
        return "an integer"
    if isinstance(default, float):
        return "a number (write 5.0, not 5)"
    if isinstance(default, str):
        return "a string"
    if isinstance(default, (list, tuple)):
        return f"a list like {list(default)!r}"
    return type(default).__name__


def refuse_runtime_changes(node, cls, values: dict, live: tuple[str, ...] = (),
                           on_change: Callable | None = None) -> None:
    """Validate ``set_parameters`` on ``cls``'s parameters at run time.

    The proposed values with the current ones go through ``cls``'s own checks
    (``__post_init__``): an invalid set is refused with that reason. A valid change of a
    parameter in ``live`` is accepted and ``on_change(cls(**new))`` applies it; a valid change
    of any other (read once at start-up) is refused, saying so, rather than accepted and ignored.
    ``values``: the current constructor arguments (``given`` ones included).
    """
    from rcl_interfaces.msg import SetParametersResult

    from train_core.config import param_fields

    names = {f.name: f for f in param_fields(cls)}
    current = dict(values)

    def proposal(params) -> tuple[list, dict]:
        mine = [p for p in params if p.name in names]
        proposed = dict(current)
        for p in mine:
            f = names[p.name]
            from_ros = f.metadata.get("ros", (None, None))[1]
            v = _list_value(f, p.value)
            proposed[p.name] = from_ros(v) if from_ros else (
                tuple(v) if isinstance(f.default, tuple) else v)
        return mine, proposed

    def callback(params):
        # judges only: another config's callback on the same node may still refuse the set
        # (set_parameters_atomically), and then nothing of it may be in force
        mine, proposed = proposal(params)
        if not mine:
            return SetParametersResult(successful=True)
        try:
            cls(**proposed)
        except (ValueError, TypeError) as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        fixed = [p.name for p in mine if p.name not in live]
        if fixed:
            return SetParametersResult(
                successful=False, reason=f"parameter {fixed[0]}: read at start-up only; "
                                         "restart the node to change it")
        return SetParametersResult(successful=True)

    def applied(params):
        # rclpy calls this only once every callback accepted the whole set
        mine, proposed = proposal(params)
        if not mine:
            return
        current.update(proposed)
        if on_change is not None:
            on_change(cls(**proposed))

    node.add_on_set_parameters_callback(callback)
    node.add_post_set_parameters_callback(applied)


def _list_value(f, v):
    """A list parameter set to an empty list arrives from rclpy as None (PARAMETER_NOT_SET):
    it is the empty list, for the dataclass's own check to judge."""
    return [] if v is None and isinstance(f.default, tuple) else v


def declare_config(node, cls, live: tuple[str, ...] = (), on_change: Callable | None = None,
                   **given):
    """Declare every parameter field of config dataclass ``cls`` on ``node`` (name, default,
    "unit, meaning" from the field's metadata: ``train_core.config.param``) and return
    ``cls(**values, **given)``; ``given`` fields are set by the caller, not declared. Tuples
    travel as ROS lists; a field's ``ros`` converters map values ROS cannot carry (None).
    Validation is the dataclass's own (``__post_init__``): a ValueError names the parameter,
    at start-up and for a ``set_parameters`` at run time (:func:`refuse_runtime_changes`:
    ``live`` parameters are applied through ``on_change``, the others refused).
    """
    from train_core.config import describe, param_fields, param_range

    if _NODE_PARAMS:  # every parameter of the node is known: check its overrides first
        check_overrides(node, {**_NODE_PARAMS,
                               **{f.name: _ros_default(f) for f in param_fields(cls)}})
    declare = declarer(node)
    values = dict(given)
    for f in param_fields(cls):
        if f.name in given:
            continue
        to_ros, from_ros = f.metadata.get("ros", (None, None))
        default = f.default
        is_tuple = isinstance(default, tuple)
        ros_default = to_ros(default) if to_ros else (list(default) if is_tuple else default)
        v = _list_value(f, declare(f.name, ros_default, describe(f), *param_range(f)))
        values[f.name] = from_ros(v) if from_ros else (tuple(v) if is_tuple else v)
    cfg = cls(**values)
    refuse_runtime_changes(node, cls, values, live, on_change)
    return cfg


class Diagnostics:
    """Publishes ``/diagnostics`` (diagnostic_msgs/DiagnosticArray) for ``node``.

    ``thresholds`` is the node's threshold dataclass (``train_core.diagnostics``: it has
    ``diagnostics_period``); every field is declared as a parameter that may change at run time
    (the period included) and the one in force is ``self.cfg``. ``status()`` returns the node's
    :class:`train_core.diagnostics.Status` (built by the pure core from the node's counters); it
    is called every ``diagnostics_period`` s of steady (wall) time, so the rate holds under
    ``use_sim_time`` whatever /clock does. The status is named ``<node name>: <what>`` with the
    node's namespace as ``hardware_id`` (the train).
    """

    def __init__(self, node, what: str, thresholds: type, status: Callable):
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.clock import Clock, ClockType

        from train_core.config import param_fields

        self.node, self.what, self.status = node, what, status
        self._previous: dict = {}  # input name -> its InputCounts one period ago
        try:
            self.cfg = declare_config(node, thresholds,
                                      live=tuple(f.name for f in param_fields(thresholds)),
                                      on_change=self._on_change)
        except ValueError as exc:
            raise ParameterError(str(exc)) from None
        self.pub = node.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.timer = node.create_timer(self.cfg.diagnostics_period, self.publish,
                                       clock=Clock(clock_type=ClockType.STEADY_TIME))

    def _on_change(self, cfg) -> None:
        self.cfg = cfg
        self.set_period(cfg.diagnostics_period)

    def input_checks(self, now: float, started: float, inputs: list):
        """``train_core.diagnostics.input_checks`` of ``inputs`` (InputCounts) against the
        counts one period ago, with the thresholds in force; returns (checks, values)."""
        from train_core.diagnostics import input_checks

        checks, values = input_checks(now, started, inputs, self._previous,
                                      self.cfg.diagnostics_period, self.cfg)
        self._previous = {c.name: c for c in inputs}
        return checks, values

    def set_period(self, period: float) -> None:
        self.timer.timer_period_ns = int(period * 1e9)
        self.timer.reset()

    def publish(self) -> None:
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

        st = self.status()
        msg = DiagnosticArray()
        msg.header.stamp = self.node.get_clock().now().to_msg()
        item = DiagnosticStatus()
        item.level = bytes([st.level])
        item.name = f"{self.node.get_name()}: {self.what}"
        item.message = st.message
        item.hardware_id = self.node.get_namespace()
        item.values = [KeyValue(key=k, value=v) for k, v in st.values]
        msg.status = [item]
        self.pub.publish(msg)


def parse_cli(description: str, argv: list[str] | None = None,
              extra: Callable[[argparse.ArgumentParser], None] | None = None,
              params: tuple = ()):
    """Parse our own options; everything after --ros-args is left for rclpy.

    ``--help`` is answered here, before rclpy starts, so it works without a ROS graph; it
    lists the parameters of the config dataclasses ``params`` (name, unit, default, range,
    meaning: ``train_core.config.param_help``).
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    ros_args: list[str] = []
    if "--ros-args" in argv:
        i = argv.index("--ros-args")
        argv, ros_args = argv[:i], argv[i:]
    epilog = ("ROS arguments follow --ros-args, e.g. --ros-args -r __ns:=/train "
              "-p use_sim_time:=true --params-file FILE")
    if params:
        from train_core.config import param_fields, param_help

        epilog += ("\n\nparameters (-p NAME:=VALUE; unit, default, allowed range, meaning; "
                   "a float parameter accepts an integer):\n" + param_help(params))
    parser = argparse.ArgumentParser(
        description=description, epilog=epilog,
        formatter_class=argparse.RawDescriptionHelpFormatter if params
        else argparse.HelpFormatter,
    )
    if extra is not None:
        extra(parser)
    args = parser.parse_args(argv)
    if params:  # the node this process runs declares these (check_overrides)
        _NODE_PARAMS.clear()
        _NODE_PARAMS.update({f.name: _ros_default(f) for cls in params
                             for f in param_fields(cls)})
    return args, ros_args


FLUSH_TIMEOUT = 3.0  # s: at most this long at exit for subscribers to acknowledge the last data


def flush_publishers(node, timeout: float = FLUSH_TIMEOUT) -> list[str]:
    """Wait until every message published by ``node`` is acknowledged by its matched reliable
    subscribers, at most ``timeout`` s in all; returns the topics still unacknowledged.

    A node that exits right after its last publish would otherwise lose those messages: the
    RMW sends them from its own thread (asynchronous publication) and repairs a lost datagram
    only while the writer exists, so destroying the node drops what is still on its way."""
    import time

    from rclpy.duration import Duration

    end = time.monotonic() + timeout
    late = []
    for pub in list(node.publishers):
        left = max(0.0, end - time.monotonic())
        if not pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))):
            late.append(pub.topic_name)
    return late


def run_node(factory: Callable, ros_args: list[str]) -> int:
    """Create the node with ``factory(context_args)``, spin until SIGINT/SIGTERM, clean up.

    Returns the process exit code: 0 on a clean stop, 2 if the node refused its parameters.
    """
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

    # Our own SIGINT/SIGTERM handlers stop the loop, so close() can flush before shutdown.
    rclpy.init(args=["node", *ros_args],
               signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
    stop = {"flag": False}

    def _on_signal(signum, frame):
        stop["flag"] = True

    signal.signal(signal.SIGINT, _on_signal)
    signal.signal(signal.SIGTERM, _on_signal)
    node = None
    code = 0
    try:
        node = factory()
        check_overrides(node)
        # One executor with the node added once: rclpy.spin_once(node) adds and removes the
        # node on every call, rebuilding the executor's entities each time (milliseconds per
        # message: most of an estimator's receive -> publish latency)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        while rclpy.ok() and not stop["flag"]:
            executor.spin_once(timeout_sec=0.05)
            if getattr(node, "finished", False):
                break
        if stop["flag"] and rclpy.ok() and hasattr(node, "taken"):
            _drain(executor, node)
    except ParameterError as exc:
        print(f"error: {exc}", file=sys.stderr)
        code = 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            close = getattr(node, "close", None)
            if close is not None:
                close()
            if rclpy.ok():
                late = flush_publishers(node)
                if late:
                    node.get_logger().warning(f"exit: messages on {late} not acknowledged by "
                                              f"every subscriber within {FLUSH_TIMEOUT:g} s")
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    return code


def _drain(executor, node, budget: float = DRAIN_BUDGET) -> None:
    """Take what the node's subscriptions hold when it is told to stop: a recorder that lags
    its topics has messages delivered to it but not yet taken, and they belong in the bag.
    Spins without waiting until ``node.taken`` (messages taken) stays put over a few turns,
    for at most ``budget`` s (a publisher that goes on must not hold the stop)."""
    import time

    end, still = time.monotonic() + budget, 0
    while still < 3 and time.monotonic() < end:
        before = node.taken
        executor.spin_once(timeout_sec=0.0)
        still = still + 1 if node.taken == before else 0


def _kind(value) -> str:
    """The kind of a parameter value (train_core.config._KIND_TESTS's names)."""
    if isinstance(value, bool):
        return "boolean"
    if isinstance(value, (int, float)):
        return "number"  # a float parameter accepts an integer (declarer)
    if isinstance(value, str):
        return "string"
    if isinstance(value, (list, tuple)) or hasattr(value, "__len__"):
        return "list"
    return "any"


def unknown_overrides(declared: dict, overrides: dict, where: str) -> list[str]:
    """The shared rule of every reader (train_core.config.unknown_key) for a node's parameter
    overrides (a --params-file, ``-p``): ``declared`` name -> value, ``overrides`` name ->
    value given. A parameter the node does not declare is allowed (a params file may serve
    several nodes) and the returned warnings name its near misses; a typo of a declared
    parameter that is not given, with a value of its kind (``integrity_rsk: 1e-6``, the risk
    silently left at its default), raises :class:`ParameterError`."""
    from train_core.config import ConfigError, unknown_key

    known = {k: _kind(v) for k, v in declared.items()
             if "." not in k}  # qos_overrides.* and the like are rclpy's own
    out = []
    for name, value in overrides.items():
        if name in declared or "." in name:
            continue
        try:
            msg = unknown_key(name, value, known, overrides.keys(), where, what="parameter")
        except ConfigError as exc:
            raise ParameterError(str(exc)) from None
        if msg is not None:
            out.append(msg)
    return out


# name -> ROS default of every parameter of the config classes given to parse_cli: what this
# process's node declares, known before it declares them (so that a typo is refused before the
# node starts)
_NODE_PARAMS: dict = {}


def check_overrides(node, declared: dict | None = None) -> None:
    """:func:`unknown_overrides` on a node, once: warnings in its log, a typo refused with
    :class:`ParameterError` (exit 2, like any invalid parameter). ``declared``: every
    parameter the node will declare (default: those declared so far)."""
    if getattr(node, "_train_overrides_checked", False):
        return
    node._train_overrides_checked = True
    overrides = {k: p.value for k, p in getattr(node, "_parameter_overrides", {}).items()}
    if not overrides:
        return
    known = {k: p.value for k, p in node._parameters.items()}
    known.update(declared or {})
    for msg in unknown_overrides(known, overrides, f"node {node.get_name()}"):
        node.get_logger().warning(msg)


def _ros_default(f):
    to_ros = f.metadata.get("ros", (None, None))[0]
    return to_ros(f.default) if to_ros else f.default


class ParameterError(ValueError):
    """A node parameter is invalid: the node refuses to start (exit code 2, one-line reason)."""
