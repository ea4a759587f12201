"""`zone_controller`: movement authorities for one or more trains (ROS layer of train_sim.zone).

Subscribes ``<train>/<state_topic>`` (TrainState) for every entry of ``trains`` and publishes
``<train>/movement_authority`` (MovementAuthority) at ``rate`` Hz, and at once when a train's
estimator reports integrity ALARM. An entry of ``trains`` is a namespace: "" means the node's own
namespace (relative names), "/train2" an absolute one. Refused reports are logged once per train
and kind per ``log_interval`` with their count; a followed clock reset is logged when it happens.
Its health (per train: reports received, accepted and rejected by reason, their silence, the
emergency brake and why) goes to ``/diagnostics`` once per ``diagnostics_period``.
"""

from __future__ import annotations

import sys

from train_core.ros import parse_cli, run_node

DESCRIPTION = __doc__.splitlines()[0]


def build_node():
    """The node: rclpy and the node's module are imported only now (--help needs neither)."""
    from train_sim.nodes.zone_controller_node import ZoneControllerNode

    return ZoneControllerNode()


def main(argv=None) -> int:
    from train_core.diagnostics import InputThresholds

    from train_sim.zone import ZoneNodeConfig, ZoneParams

    _, ros_args = parse_cli(DESCRIPTION + " Parameters: see config/zone_controller.yaml.", argv,
                            params=(ZoneParams, ZoneNodeConfig, InputThresholds))
    return run_node(build_node, ros_args)


if __name__ == "__main__":
    sys.exit(main())
