"""`Recorder`: every message of the chosen topics written, raw, into a rosbag2 (MCAP) bag with its
arrival time, flushed every `flush_period`, closed on shutdown. `recorder.py` holds its
parameters (`RecorderConfig`) and command line and imports this module, and rclpy, only to start
it."""

from __future__ import annotations

import math

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from train_core import diagnostics as D
from train_core.bagio import BagError, BagWriter
from train_core.ros import (
    Diagnostics,
    ParameterError,
    declare_config,
)

from train_estimation.nodes.recorder import SPARSE, RecorderConfig, topic_type, type_class


class Recorder(Node):
    def __init__(self):
        super().__init__("recorder")

        try:
            cfg = declare_config(self, RecorderConfig)
        except ValueError as exc:
            raise ParameterError(str(exc)) from None
        topics, bag, flush = list(cfg.topics), cfg.bag, cfg.flush_period
        given: dict[str, str] = {}  # resolved name -> the name given
        for topic in topics:
            full = self.resolve_topic_name(topic)
            if full in given:  # two names of one topic: every message would be written twice
                raise ParameterError(f"parameter topics: {given[full]!r} and {topic!r} are "
                                     f"one topic, {full}: give it once")
            given[full] = topic
        # every parameter judged before the bag's directory is made
        self.diag = Diagnostics(self, "bag recorder", D.StaleThresholds, self.diagnostics)
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
        for full, topic in given.items():
            msgtype = topic_type(topic)
            self.received[full], self.last_arrival[full] = 0, math.nan
            self.create_subscription(
                type_class(msgtype), topic,
                lambda data, full=full, msgtype=msgtype: self.on_msg(full, msgtype, data),
                1000, raw=True)
        # steady time, as the parameter says: on simulated time /clock may stop or race
        self.timer = self.create_timer(flush, self.writer.flush, clock=self.steady)
        self.get_logger().info(f"recording {topics} in {ns} to {bag}")

    @property
    def taken(self) -> int:
        """Messages taken so far (``run_node`` drains the queues at a stop until it stays)."""
        return sum(self.received.values())

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
