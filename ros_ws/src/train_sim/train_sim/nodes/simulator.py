"""`simulator`: the train world (ROS layer of train_sim.world).

Steps the pure :class:`train_sim.world.World` at ``rate_factor`` times real time and publishes
what it emits: ``odometer`` and ``balise`` after the lossy radio link, ``control`` (the ATO's
command) and ``ground_truth``, each stamped with its sample time, plus ``/clock`` (the world's
time) so every other node can run with ``use_sim_time``: before each step's messages, at the
run's last instant, and otherwise every ``clock_period`` of wall time (not every step: each
/clock costs every node on simulated time a wake-up). Subscribes ``movement_authority`` and
hands it to the ATO. Same scenario and seed, same message contents as the offline generator.
Its health (state, simulated time, messages published, the authorities and paced topics it
receives) goes to ``/diagnostics`` once per ``diagnostics_period``.
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


PROGRESS = "simulated"  # the progress log line: "simulated T of D s"


@dataclass(frozen=True)
class SimulatorConfig:
    """The simulator node's parameters (declared from this metadata; config/simulator.yaml
    documents them)."""

    scenario: str = param("metro_demo", "", "scenario name or path to its YAML")
    model: str = param("", "", "a model directory written by diagnose (DIR/model: line.yaml, "
                       "train.yaml, effects.yaml) to run instead of the scenario's line, train "
                       "and effects; empty = the scenario's")
    seed: int = param(-1, "", "random seed; -1 = the scenario's own seed", lo=-1)
    rate_factor: float = param(1.0, "-", "simulated seconds per wall-clock second", lo=0.0)
    duration: float = param(-1.0, "s", "simulated time; -1 = the scenario's")
    wall_step: float = param(0.01, "s", "wall-clock period of the stepping timer", lo=0.0)
    clock_period: float = param(0.1, "s", "wall time between two /clock messages at most; "
                                "/clock is also said before every step that delivers "
                                "messages. <= wall_step: every step", lo=0.0)
    wait_for_subscribers: int = param(0, "", "start only when control, odometer and balise "
                                      "have this many subscribers each, and go on past the "
                                      "first messages once every reader acknowledged them",
                                      lo=0)
    wait_for_truth_subscribers: int = param(0, "", "and ground_truth has this many "
                                            "subscribers", lo=0)
    publish_clock: bool = param(True, "", "publish /clock (one simulator per ROS graph should)")
    start_at: float = param(0.0, "s", "wall time (since the epoch) to start at; 0 = at once. "
                            "Several simulators given one start_at share a time base", lo=0.0)
    summary_file: str = param("", "", "write the run's summary (JSON) here at the end; '' = no")
    start_with_emergency_brake: bool = param(False, "", "the train starts braked, as one no "
                                             "zone controller has localised yet, until an "
                                             "authority without the brake arrives")
    end_linger: float = param(0.0, "s", "of simulated time /clock keeps running after the run "
                              "ends, so estimators release their last estimates", lo=0.0)
    max_lead: float = param(0.0, "s", "> 0: simulated time runs at most this far ahead of the "
                            "newest message stamp on every pace_topics topic; 0 = off", lo=0.0)
    pace_topics: tuple[str, ...] = param(("estimate/robust",), "", "topics whose progress "
                                         "paces the world when max_lead > 0")
    exit_at_end: bool = param(True, "", "stop the node when the run ends")
    wait_log_period: float = param(10.0, "s", "wall time between two log lines that say what a "
                                   "world standing still waits for (subscribers not matched, "
                                   "paced topics behind)", lo=0.0)

    def __post_init__(self):
        require(self.rate_factor > 0, "rate_factor", self.rate_factor, "must be > 0")
        require(self.wall_step > 0, "wall_step", self.wall_step, "must be > 0")
        require(math.isfinite(self.clock_period) and self.clock_period >= 0, "clock_period",
                self.clock_period, "must be >= 0")
        require(math.isfinite(self.wait_log_period) and self.wait_log_period > 0,
                "wait_log_period", self.wait_log_period, "must be > 0")
        require(math.isfinite(self.end_linger) and self.end_linger >= 0, "end_linger",
                self.end_linger, "must be >= 0")
        require(math.isfinite(self.max_lead) and self.max_lead >= 0, "max_lead", self.max_lead,
                "must be >= 0")
        unknown = [t for t in self.pace_topics if t not in TOPIC_TYPES]
        require(self.max_lead == 0 or not unknown, "pace_topics", unknown,
                f"unknown (allowed: {sorted(TOPIC_TYPES)})")


def build_node():
    """The node: rclpy and the node's module are imported only now (--help needs neither)."""
    from train_sim.nodes.simulator_node import SimulatorNode

    return SimulatorNode()


def main(argv=None) -> int:
    from train_core.diagnostics import StaleThresholds

    _, ros_args = parse_cli(DESCRIPTION + " Parameters: see config/simulator.yaml.", argv,
                            params=(SimulatorConfig, StaleThresholds))
    return run_node(build_node, ros_args)


if __name__ == "__main__":
    sys.exit(main())
