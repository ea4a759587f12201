"""`robust_filter`: position and velocity under packet dropouts (Wen et al. 2017).

Subscribes ``odometer``, ``balise``, ``control``; publishes ``estimate/robust`` (source
``robust_filter``) at the odometer rate whether or not a measurement arrived, with the filter's
upper bound Sigma of the error covariance in ``covariance`` (position/velocity block).
"""

from __future__ import annotations

import math
import sys

from train_core.ros import declarer, parse_cli, run_node

DESCRIPTION = __doc__.splitlines()[0]


def make_adapter(node, train, line, start, common):

    from train_estimation.core.estimators import RobustAdapter, RobustConfig

    declare = declarer(node)

    d = RobustConfig()
    eps = declare("epsilon", -1.0, "eq. (21) epsilon > 0; -1 = per-step minimiser")
    cfg = RobustConfig(
        q=declare("q", d.q, "N^2, bound on the squared wind force (Wen eq. (7))"),
        epsilon=None if eps <= 0 else eps,
        alpha_bar=declare("alpha_bar", d.alpha_bar, "Prob(odometer packet received)"),
        gate=declare("gate", d.gate, "innovation gate in standard deviations"),
        use_distance=declare("use_distance", d.use_distance, "odometer distance as position"),
        distance_variance=declare("distance_variance", d.distance_variance, "m^2"),
        period=1.0 / common["odometer_rate"])
    if not (0.0 < cfg.alpha_bar <= 1.0 and cfg.q >= 0 and cfg.gate > 0
            and cfg.distance_variance > 0 and math.isfinite(cfg.q)):
        raise ValueError("robust_filter parameters: need 0 < alpha_bar <= 1, q >= 0, gate > 0, "
                         "distance_variance > 0")
    return RobustAdapter(train, line, start, cfg)


def main(argv=None) -> int:
    from train_estimation.nodes.estimator_node import build_estimator_node

    _, ros_args = parse_cli(DESCRIPTION + " Parameters: see config/robust_filter.yaml.", argv)
    return run_node(lambda: build_estimator_node("robust_filter", "estimate/robust",
                                                 make_adapter), ros_args)


if __name__ == "__main__":
    sys.exit(main())
