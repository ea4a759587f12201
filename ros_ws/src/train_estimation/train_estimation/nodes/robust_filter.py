"""`robust_filter`: position and velocity under packet dropouts (Wen et al. 2017).

Subscribes ``odometer``, ``balise``, ``control``; publishes ``estimate/robust`` (source
``robust_filter``) at the odometer rate whether or not a measurement arrived, with the filter's
upper bound Sigma of the error covariance in ``covariance`` (position/velocity block).
"""

from __future__ import annotations

import sys

from train_core.ros import declare_config, parse_cli, run_node

DESCRIPTION = __doc__.splitlines()[0]


def make_adapter(node, train, line, start, common):

    from train_estimation.core.online.estimators import RobustAdapter, RobustConfig

    cfg = declare_config(node, RobustConfig, period=1.0 / common["odometer_rate"])
    return RobustAdapter(train, line, start, cfg)


def main(argv=None) -> int:
    from train_estimation.core.online.estimators import RobustConfig
    from train_estimation.nodes.estimator_params import node_params

    _, ros_args = parse_cli(DESCRIPTION + " Parameters: see config/robust_filter.yaml.", argv,
                            params=node_params(RobustConfig))

    def build():  # rclpy and the node's module only now: --help needs neither
        from train_estimation.nodes.estimator_node import EstimatorNode

        return EstimatorNode("robust_filter", "estimate/robust", make_adapter)

    return run_node(build, ros_args)


if __name__ == "__main__":
    sys.exit(main())
