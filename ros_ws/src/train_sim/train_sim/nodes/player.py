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
from dataclasses import dataclass

from train_core.config import param, require
from train_core.ros import (
    parse_cli,
    run_node,
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
                                      "has this many subscribers, and go on past the first "
                                      "messages once every reader acknowledged them", lo=0)
    clock_period: float = param(0.1, "s", "wall time between two /clock messages at most; "
                                "/clock is also said before every step that publishes "
                                "messages. <= 0.005 (the stepping timer's period): every "
                                "step", lo=0.0)

    def __post_init__(self):
        require(bool(self.bag), "bag", self.bag, "is empty: give the bag to play")
        require(math.isfinite(self.clock_period) and self.clock_period >= 0, "clock_period",
                self.clock_period, "must be >= 0")


def build_node():
    """The node: rclpy and the node's module are imported only now (--help needs neither)."""
    from train_sim.nodes.player_node import Player

    return Player()


def main(argv=None) -> int:
    _, ros_args = parse_cli(DESCRIPTION, argv, params=(PlayerConfig,))
    return run_node(build_node, ros_args)


if __name__ == "__main__":
    sys.exit(main())
