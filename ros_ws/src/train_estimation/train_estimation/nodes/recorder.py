"""`recorder`: writes topics to a rosbag2 bag (MCAP storage), CDR bytes exactly as received.

Subscribes every topic of ``topics`` (relative names work in the node's namespace) with raw
(serialized) delivery and appends each message to the bag with the message definitions embedded.
metadata.yaml is written at the start, and every ``flush_period`` seconds the pending chunk is
closed and synced to disk with a provisional MCAP footer and an updated metadata.yaml, so a crash
or ``kill -9`` loses at most that much and leaves a bag that opens as it is (``read_bag``,
``check_bag``, rosbags' AnyReader; ``python -m train_core.bagio repair BAG`` adds the index);
SIGINT/SIGTERM close the bag properly. At the end it logs the topics, message counts and bytes
written.

Besides the topics of docs/interfaces.md it records any ``estimate/<name>`` (TrainState),
``odom/<name>`` (nav_msgs/Odometry) and ``/diagnostics`` (diagnostic_msgs/DiagnosticArray), so
that a bag shows in Foxglove what the nodes published. Its own health (per topic: rate, count,
silence; bytes written) goes to ``/diagnostics``.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass

from train_core.config import param, require
from train_core.ros import (
    TOPIC_TYPES,
    ParameterError,
    declare_config,
    parse_cli,
    run_node,
)

DESCRIPTION = __doc__.splitlines()[0]
DEFAULT_TOPICS = ["odometer", "balise", "control", "ground_truth", "estimate/robust",
                  "estimate/gsma", "movement_authority"]
SPARSE = ("balise",)  # minutes apart by design: never judged stale


def topic_type(topic: str) -> str | None:
    """The full message type recorded on ``topic`` (relative, or absolute with a namespace):
    the topics of docs/interfaces.md, ``estimate/<name>``, ``odom/<name>``, ``/diagnostics``;
    else None."""
    parts = topic.strip("/").split("/")
    for i in range(len(parts)):  # drop leading namespace components
        rel, rest = "/".join(parts[i:]), len(parts) - i
        if rel in TOPIC_TYPES:
            return f"train_interfaces/msg/{TOPIC_TYPES[rel]}"
        if rest == 2 and parts[i] == "estimate":
            return "train_interfaces/msg/TrainState"
        if rest == 2 and parts[i] == "odom":
            return "nav_msgs/msg/Odometry"
        if rel == "diagnostics" and topic.startswith("/") and i == 0:
            return "diagnostic_msgs/msg/DiagnosticArray"
    return None


def type_class(full: str):
    pkg, _, name = full.split("/")
    return getattr(__import__(f"{pkg}.msg", fromlist=[name]), name)


@dataclass(frozen=True)
class RecorderConfig:
    """The recorder's parameters (declared from this metadata; config/recorder.yaml)."""

    topics: tuple[str, ...] = param(tuple(DEFAULT_TOPICS), "", "topics to record "
                                    "(docs/interfaces.md names, estimate/NAME, odom/NAME, "
                                    "/diagnostics)")
    bag: str = param("", "", "bag directory to create (must not exist)")
    flush_period: float = param(1.0, "s", "of wall time between chunk flushes", lo=0.0)

    def __post_init__(self):
        require(bool(self.bag), "bag", self.bag, "is empty: give the bag directory to write")
        unknown = [t for t in self.topics if topic_type(t) is None]
        require(not unknown, "topics", unknown, f"unknown (allowed: {sorted(TOPIC_TYPES)}, "
                "estimate/NAME, odom/NAME, /diagnostics)")


def build_node():
    from rclpy.clock import Clock, ClockType
    from rclpy.node import Node
    from train_core import diagnostics as D
    from train_core.bagio import BagError, BagWriter
    from train_core.ros import Diagnostics

    class Recorder(Node):
        def __init__(self):
            super().__init__("recorder")

            try:
                cfg = declare_config(self, RecorderConfig)
            except ValueError as exc:
                raise ParameterError(str(exc)) from None
            topics, bag, flush = list(cfg.topics), cfg.bag, cfg.flush_period
            ns = self.get_namespace()
            try:
                self.writer = BagWriter(bag, namespace=ns if ns != "/" else "")
            except (BagError, OSError) as exc:
                raise ParameterError(f"parameter bag: {exc}") from None
            self.bytes = 0
            self.steady = Clock(clock_type=ClockType.STEADY_TIME)
            self.started = self.steady.now().nanoseconds * 1e-9
            self.received: dict[str, int] = {}
            self.last_arrival: dict[str, float] = {}
            for topic in topics:
                msgtype = topic_type(topic)
                full = self.resolve_topic_name(topic)
                self.received[full], self.last_arrival[full] = 0, math.nan
                self.create_subscription(
                    type_class(msgtype), topic,
                    lambda data, full=full, msgtype=msgtype: self.on_msg(full, msgtype, data),
                    1000, raw=True)
            self.timer = self.create_timer(flush, self.writer.flush)
            self.diag = Diagnostics(self, "bag recorder", D.StaleThresholds, self.diagnostics)
            self.get_logger().info(f"recording {topics} in {ns} to {bag}")

        def on_msg(self, topic: str, msgtype: str, data: bytes) -> None:
            t_ns = self.get_clock().now().nanoseconds
            self.writer.write_raw(topic, msgtype, t_ns, data)
            self.bytes += len(data)
            self.received[topic] += 1
            self.last_arrival[topic] = self.steady.now().nanoseconds * 1e-9

        def diagnostics(self):
            """Per topic: rate, count and silence (a topic is watched once it has delivered:
            a recorder may be told to record a topic nobody publishes in this run)."""
            now = self.steady.now().nanoseconds * 1e-9
            inputs = [D.InputCounts(t, n, n, {}, self.last_arrival[t],
                                    watch_stale=n > 0 and t.rsplit("/", 1)[-1] not in SPARSE)
                      for t, n in self.received.items()]
            checks, values = self.diag.input_checks(now, self.started, inputs)
            return D.combine(checks, [("bag", str(self.writer.path)),
                                      ("bytes_written", str(self.bytes)), *values])

        def close(self) -> None:
            self.writer.close()
            counts = ", ".join(f"{t}: {n}" for t, n in sorted(self.writer.counts.items()))
            self.get_logger().info(f"bag {self.writer.path} closed; {counts or 'no messages'}; "
                                   f"{self.bytes} bytes of messages")

    return Recorder()


def main(argv=None) -> int:
    from train_core.diagnostics import StaleThresholds

    _, ros_args = parse_cli(DESCRIPTION + " Parameters: see config/recorder.yaml.", argv,
                            params=(RecorderConfig, StaleThresholds))
    return run_node(build_node, ros_args)


if __name__ == "__main__":
    sys.exit(main())
