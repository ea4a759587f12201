"""`gsma_estimator`: braking rate, position and velocity (GSMA, SMA, RBPF, Q-GRBPF or the KF).

Subscribes ``control``, ``odometer``, ``balise``; publishes ``estimate/gsma`` (source = the
algorithm) with position, velocity, control acceleration (a-hat), braking rate and the 4x4
covariance including the braking-rate variance, at the odometer rate.
"""

from __future__ import annotations

import sys

from train_core.ros import declarer, parse_cli, run_node

DESCRIPTION = __doc__.splitlines()[0]


def make_adapter(node, train, line, start, common):

    from train_estimation.core.estimators import ALGORITHMS, BrakingAdapter, BrakingConfig

    declare = declarer(node)

    d = BrakingConfig()
    algorithm = declare("algorithm", d.algorithm, f"one of {', '.join(ALGORITHMS)}")
    if algorithm not in ALGORITHMS:
        raise ValueError(f"parameter algorithm: '{algorithm}' (allowed: {', '.join(ALGORITHMS)})")
    cfg = BrakingConfig(
        algorithm=algorithm,
        values=tuple(declare("values", list(d.values), "discrete braking-rate set")),
        f_prior_std=declare("f_prior_std", d.f_prior_std,
                            "std of the f prior (centred on train.yaml's braking_rate)"),
        merge=declare("merge", d.merge, "GSMA/SMA: merge particles per value, no pruning"),
        n_init=declare("n_init", d.n_init, "N0, initial particles"),
        n_keep=declare("n_keep", d.n_keep, "N, particles kept after pruning"),
        q_max=declare("q_max", d.q_max, "Q, prune when the count exceeds it"),
        branch_p_move=declare("branch_p_move", d.branch_p_move,
                              "GSMA/SMA: prior P(child = a neighbour value); -1 = uniform"),
        rbpf_particles=declare("rbpf_particles", d.rbpf_particles, "RBPF particle count"),
        rbpf_p_move=declare("rbpf_p_move", d.rbpf_p_move, "RBPF: P(move to a neighbour)"),
        qgrbpf_particles=declare("qgrbpf_particles", d.qgrbpf_particles, "Q-GRBPF particles"),
        qgrbpf_q_theta=declare("qgrbpf_q_theta", d.qgrbpf_q_theta, "1/s, f random walk"),
        kf_q_theta=declare("kf_q_theta", d.kf_q_theta, "1/s, f random walk while braking (KF)"),
        transition_interval=declare("transition_interval", d.transition_interval,
                                    "s between f transitions"),
        accel_var=declare("accel_var", d.accel_var, "m^2/s^3, acceleration noise PSD"),
        ahat_var=declare("ahat_var", d.ahat_var, "m^2/s^5, a-hat noise PSD"),
        distance_variance=declare("distance_variance", d.distance_variance, "m^2"),
        standstill_speed=declare("standstill_speed", d.standstill_speed, "m/s"),
        min_brake=declare("min_brake", d.min_brake, "m/s^2"),
        seed=declare("seed", d.seed, "particle random stream"),
    )
    return BrakingAdapter(train, line, start, cfg)


def main(argv=None) -> int:
    from train_estimation.nodes.estimator_node import build_estimator_node

    _, ros_args = parse_cli(DESCRIPTION + " Parameters: see config/gsma_estimator.yaml.", argv)
    return run_node(lambda: build_estimator_node("gsma_estimator", "estimate/gsma",
                                                 make_adapter), ros_args)


if __name__ == "__main__":
    sys.exit(main())
