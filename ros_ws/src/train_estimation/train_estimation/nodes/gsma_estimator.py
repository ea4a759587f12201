"""`gsma_estimator`: braking rate, position and velocity (GSMA, SMA, RBPF, Q-GRBPF or the KF).

Subscribes ``control``, ``odometer``, ``balise``; publishes ``estimate/gsma`` (source = the
algorithm) with position, velocity, control acceleration (a-hat), braking rate and the 4x4
covariance including the braking-rate variance, at the odometer rate.
"""

from __future__ import annotations

import sys

from train_core.ros import declare_config, parse_cli, run_node

DESCRIPTION = __doc__.splitlines()[0]


def make_adapter(node, train, line, start, common):

    from train_estimation.core.online.estimators import BrakingAdapter, BrakingConfig

    return BrakingAdapter(train, line, start, declare_config(node, BrakingConfig))


def main(argv=None) -> int:
    from train_estimation.core.online.estimators import BrakingConfig
    from train_estimation.nodes.estimator_params import node_params

    _, ros_args = parse_cli(DESCRIPTION + " Parameters: see config/gsma_estimator.yaml.", argv,
                            params=node_params(BrakingConfig))

    def build():  # rclpy and the node's module only now: --help needs neither
        from train_estimation.nodes.estimator_node import EstimatorNode

        return EstimatorNode("gsma_estimator", "estimate/gsma", make_adapter)

    return run_node(build, ros_args)


if __name__ == "__main__":
    sys.exit(main())
