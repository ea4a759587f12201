"""`recorder`: writes topics to a rosbag2 bag (MCAP storage), CDR bytes exactly as received.

Subscribes every topic of ``topics`` (relative names work in the node's namespace) with raw
(serialized) delivery and appends each message to the bag with the message definitions embedded.
Every ``flush_period`` seconds the pending chunk is closed and synced to disk, so a crash or
``kill -9`` loses at most that much (``read_bag``/``check_bag`` read such a bag, and
``python -m train_core.bagio repair BAG`` makes it a normal bag again for any reader);
SIGINT/SIGTERM close the bag properly. At the end it logs the
topics, message counts and bytes written.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

from train_core.config import param, require
from train_core.ros import (
    TOPIC_TYPES,
    ParameterError,
    declare_config,
    msg_class,
    parse_cli,
    run_node,
)

DESCRIPTION = __doc__.splitlines()[0]
DEFAULT_TOPICS = ["odometer", "balise", "control", "ground_truth", "estimate/robust",
                  "estimate/gsma", "movement_authority"]


@dataclass(frozen=True)
class RecorderConfig:
    """The recorder's parameters (declared from this metadata; config/recorder.yaml)."""

    topics: tuple[str, ...] = param(tuple(DEFAULT_TOPICS), "", "topics to record "
                                    "(docs/interfaces.md names)")
    bag: str = param("", "", "bag directory to create (must not exist)")
    flush_period: float = param(1.0, "s", "of wall time between chunk flushes")

    def __post_init__(self):
        require(bool(self.bag), "bag", self.bag, "is empty: give the bag directory to write")
        unknown = [t for t in self.topics if t.split("/")[-1] not in
                   {k.split("/")[-1] for k in TOPIC_TYPES}]
        require(not unknown, "topics", unknown, f"unknown (allowed: {sorted(TOPIC_TYPES)})")


def build_node():
    from rclpy.node import Node
    from train_core.bagio import BagError, BagWriter

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
            for topic in topics:
                rel = topic.lstrip("/")
                key = rel if rel in TOPIC_TYPES else rel.split("/", 1)[-1]
                type_name = TOPIC_TYPES[key]
                msgtype = f"train_interfaces/msg/{type_name}"
                full = self.resolve_topic_name(topic)
                self.create_subscription(
                    msg_class(type_name), topic,
                    lambda data, full=full, msgtype=msgtype: self.on_msg(full, msgtype, data),
                    1000, raw=True)
            self.timer = self.create_timer(flush, self.writer.flush)
            self.get_logger().info(f"recording {topics} in {ns} to {bag}")

        def on_msg(self, topic: str, msgtype: str, data: bytes) -> None:
            t_ns = self.get_clock().now().nanoseconds
            self.writer.write_raw(topic, msgtype, t_ns, data)
            self.bytes += len(data)

        def close(self) -> None:
            self.writer.close()
            counts = ", ".join(f"{t}: {n}" for t, n in sorted(self.writer.counts.items()))
            self.get_logger().info(f"bag {self.writer.path} closed; {counts or 'no messages'}; "
                                   f"{self.bytes} bytes of messages")

    return Recorder()


def main(argv=None) -> int:
    _, ros_args = parse_cli(DESCRIPTION + " Parameters: see config/recorder.yaml.", argv)
    return run_node(build_node, ros_args)


if __name__ == "__main__":
    sys.exit(main())
