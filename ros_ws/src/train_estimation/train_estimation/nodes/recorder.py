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
    parse_cli,
    run_node,
)

DESCRIPTION = __doc__.splitlines()[0]
DEFAULT_TOPICS = ["odometer", "balise", "control", "ground_truth", "estimate/robust",
                  "estimate/gsma", "movement_authority"]
MIN_FLUSH = 0.01  # s, the shortest flush_period
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
    flush_period: float = param(1.0, "s", "of steady (wall) time between chunk flushes, at "
                                "least 0.01 (a flush is a write to disk: at 0 the recorder "
                                "flushed without pause and fell behind its topics)",
                                lo=MIN_FLUSH)

    def __post_init__(self):
        require(bool(self.bag), "bag", self.bag, "is empty: give the bag directory to write")
        require(math.isfinite(self.flush_period) and self.flush_period >= MIN_FLUSH,
                "flush_period", self.flush_period, f"must be finite and >= {MIN_FLUSH:g}")
        require(len(self.topics) > 0, "topics", list(self.topics), "is empty: give the "
                "topics to record")
        twice = sorted({t for t in self.topics if self.topics.count(t) > 1})
        require(not twice, "topics", twice, "given twice: each message would be written "
                "twice")
        unknown = [t for t in self.topics if topic_type(t) is None]
        require(not unknown, "topics", unknown, f"unknown (allowed: {sorted(TOPIC_TYPES)}, "
                "estimate/NAME, odom/NAME, /diagnostics)")


def build_node():
    """The node: rclpy and the node's module are imported only now (--help needs neither)."""
    from train_estimation.nodes.recorder_node import Recorder

    return Recorder()


def main(argv=None) -> int:
    from train_core.diagnostics import StaleThresholds

    _, ros_args = parse_cli(DESCRIPTION + " Parameters: see config/recorder.yaml.", argv,
                            params=(RecorderConfig, StaleThresholds))
    return run_node(build_node, ros_args)


if __name__ == "__main__":
    sys.exit(main())
