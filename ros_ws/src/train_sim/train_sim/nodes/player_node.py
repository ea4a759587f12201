"""`Player`, the bag player's node: a bag's messages in stamp order at rate_factor times real time,
/clock before each step that publishes. Its parameters (`PlayerConfig`) and command line live in
`player.py`, which imports this module, and rclpy with it, only to start the node."""

from __future__ import annotations

import math
import time

from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from train_core.bagio import BagError, read_bag
from train_core.ros import (
    TOPIC_TYPES,
    ParameterError,
    declare_config,
    fields_to_msg,
    inputs_matched,
    msg_class,
    sec_to_stamp,
    unacknowledged,
)

from train_sim.nodes.player import PlayerConfig


class Player(Node):
    def __init__(self):
        super().__init__("player")

        try:
            cfg = declare_config(self, PlayerConfig)
        except ValueError as exc:
            raise ParameterError(str(exc)) from None
        bag, topics = cfg.bag, list(cfg.topics)
        self.rate, self.wait_subs = cfg.rate_factor, cfg.wait_for_subscribers
        self.clock_period, self.clock_said = cfg.clock_period, -math.inf
        try:
            data = read_bag(bag)
        except BagError as exc:
            raise ParameterError(str(exc)) from None
        missing = [t for t in topics if t not in data.topics]
        if missing:
            raise ParameterError(f"{bag}: the bag lacks topic(s) {missing} "
                                 f"(it has {sorted(data.topics)})")
        self.items = sorted(((s, t, f) for t in topics for _, s, f in data.topics[t]),
                            key=lambda i: i[0])
        self.pubs = {t: self.create_publisher(msg_class(TOPIC_TYPES[t]), t, 1000)
                     for t in topics}
        self.clock_pub = self.create_publisher(Clock, "/clock", 10)
        self.i = 0
        self.t0_bag = self.items[0][0] if self.items else 0.0
        self.wall0 = None
        # with readers waited for, the messages after the first ones follow once every reader
        # has acknowledged those (train_core.ros.unacknowledged)
        self.acked = not self.wait_subs
        self.finished = False
        self.timer = self.create_timer(0.005, self.tick)
        self.get_logger().info(f"playing {len(self.items)} messages of {bag} "
                               f"at {self.rate:g}x")

    def tick(self) -> None:
        if self.wall0 is None:
            if not inputs_matched(self.pubs, self.wait_subs):
                return
            self.wall0 = time.monotonic()
        now = time.monotonic()
        if not self.acked and self.i:
            if unacknowledged(self.pubs):
                return
            # the bag goes on from the last message sent: the wait is no bag time
            self.acked = True
            self.wall0 = now - (self.items[self.i - 1][0] - self.t0_bag) / self.rate
        t_bag = self.t0_bag + (now - self.wall0) * self.rate
        # the clock first, then what was logged by it: a node on simulated time receives
        # each message at or after its log time, never before. Without messages, every
        # clock_period: each /clock costs every node on simulated time a wake-up of its
        # executor (the simulator's clock_period, docs/benchmarks.md "Latency"); and the
        # last one (2 s past the last message), which the nodes wait for
        last = self.items[-1][0] if self.items else 0.0
        due = self.i < len(self.items) and self.items[self.i][0] <= t_bag
        if due or t_bag > last + 2.0 or now - self.clock_said >= self.clock_period:
            clock = Clock()
            sec_to_stamp(min(t_bag, last + 2.0), clock.clock)
            self.clock_pub.publish(clock)
            self.clock_said = now
        while self.i < len(self.items) and self.items[self.i][0] <= t_bag:
            stamp, topic, fields = self.items[self.i]
            self.pubs[topic].publish(fields_to_msg(TOPIC_TYPES[topic], stamp, fields))
            self.i += 1
        if self.i >= len(self.items) and t_bag > last + 2.0:
            self.get_logger().info("bag played")
            self.finished = True
