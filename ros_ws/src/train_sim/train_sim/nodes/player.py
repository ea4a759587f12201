"""`player`: replays a bag's messages with /clock (there is no `ros2 bag play` on the pip set-up).

    python -m train_sim.nodes.player --ros-args -r __ns:=/train -p bag:=bags/metro_demo_short \
        -p rate_factor:=10.0 -p wait_for_subscribers:=1

Publishes the chosen topics of the bag in stamp order at ``rate_factor`` times real time, each
message exactly as recorded (decoded and re-encoded: the same field values), and ``/clock``
before the messages of each step (a node on simulated time receives each message at or after
its stamp on its clock), and otherwise every ``clock_period`` of wall time, so that nodes with
``use_sim_time`` see bag time. The clock follows the messages' header stamps (the sample
times).
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass

from train_core.config import param, require
from train_core.ros import (
    TOPIC_TYPES,
    ParameterError,
    declare_config,
    fields_to_msg,
    inputs_matched,
    msg_class,
    parse_cli,
    run_node,
    sec_to_stamp,
)

DESCRIPTION = __doc__.splitlines()[0]


@dataclass(frozen=True)
class PlayerConfig:
    """The player's parameters (declared from this metadata)."""

    bag: str = param("", "", "bag directory (rosbag2, MCAP) to play")
    topics: tuple[str, ...] = param(("control", "odometer", "balise", "ground_truth"), "",
                                    "topics of the bag to publish (relative names)")
    rate_factor: float = param(1.0, "-", "bag seconds per wall second", lo=0.0)
    wait_for_subscribers: int = param(0, "", "start when each of control, odometer and balise "
                                      "has this many subscribers", lo=0)
    clock_period: float = param(0.1, "s", "wall time between two /clock messages at most; "
                                "/clock is also said before every step that publishes "
                                "messages. <= 0.005 (the stepping timer's period): every "
                                "step", lo=0.0)

    def __post_init__(self):
        require(bool(self.bag), "bag", self.bag, "is empty: give the bag to play")
        require(math.isfinite(self.clock_period) and self.clock_period >= 0, "clock_period",
                self.clock_period, "must be >= 0")


def build_node():
    from rclpy.node import Node
    from rosgraph_msgs.msg import Clock
    from train_core.bagio import BagError, read_bag

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

    return Player()


def main(argv=None) -> int:
    _, ros_args = parse_cli(DESCRIPTION, argv, params=(PlayerConfig,))
    return run_node(build_node, ros_args)


if __name__ == "__main__":
    sys.exit(main())
