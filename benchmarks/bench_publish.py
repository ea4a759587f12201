"""Publishing an estimate: the messages filled and published, or written from templates.

An estimator node publishes each estimate as a TrainState and a nav_msgs/Odometry. Filled as
Python messages, rclpy converts them to C structs and serialises them in ``publish``; written
from per-node templates (``train_estimation/nodes/estimate_cdr.py``, what the nodes do) they
are CDR bytes that ``publish`` hands on as they are. Both ways, estimate by estimate in turn,
in one process (a publisher with no subscriber on a private localhost-only ROS domain: the DDS
write is in, no network or reader): CPU time of this thread per estimate, both messages.

    ./run bench publish            # 20,000 estimates (a few seconds)
    ./run bench publish --quick    # 2,000
"""

import argparse
import math
import os
import random
import time

# a private domain on loopback before rclpy is imported (rules: no DDS traffic off the host)
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
# 91-101: above the test sessions' domains (conftest.py: 1-90 + the worker's index) and within
# the 0-101 whose DDS ports stay below Linux's ephemeral range (ROS 2 docs, "About Domain ID")
os.environ["ROS_DOMAIN_ID"] = str(random.randint(91, 101))

import numpy as np  # noqa: E402
import rclpy  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402

from train_estimation.core.online.runner import Output  # noqa: E402
from train_estimation.nodes.estimate_cdr import EstimateCdr, node_messages  # noqa: E402
from train_estimation.nodes.estimator_node import fill_odometry, fill_state  # noqa: E402
from train_interfaces.msg import TrainState  # noqa: E402


def estimates(n: int, rng: np.random.Generator) -> list[Output]:
    """Estimates as a braking filter publishes them (a NaN-free covariance, levels finite)."""
    return [Output(stamp=100.0 + 0.1 * i, position=1000.0 + 2.0 * i,
                   velocity=float(20.0 + rng.normal()), acceleration=float(rng.normal()),
                   braking_rate=float(1.0 + 0.01 * rng.normal()),
                   covariance=tuple(float(v) for v in rng.normal(size=16)),
                   measurement_used=bool(i % 8), integrity=0,
                   protection_level_ahead=float(12.0 + rng.random()),
                   protection_level_behind=float(11.0 + rng.random())) for i in range(n)]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--n", type=int, default=20000, help="estimates published each way")
    p.add_argument("--quick", action="store_true", help="2,000 estimates")
    args = p.parse_args()
    n = 2000 if args.quick else args.n
    rclpy.init()
    node = rclpy.create_node("bench_publish")
    try:
        pub = node.create_publisher(TrainState, "estimate/bench", 1000)
        opub = node.create_publisher(Odometry, "odom/bench", 1000)
        state, odom = node_messages("gsma")
        cdr = EstimateCdr("gsma")
        risk = 1e-7

        def filled(out):  # the messages path (EstimatorNode before the templates)
            fill_state(state, out)
            pub.publish(state)
            fill_odometry(odom, state, risk)
            opub.publish(odom)

        def written(out):  # the nodes' path
            raw = cdr.encode(out, risk)
            pub.publish(raw[0])
            opub.publish(raw[1])

        ways = {"filled and published (rclpy converts, serialises)": filled,
                "written from templates, published as bytes": written}
        cpu = {k: [] for k in ways}
        clock = time.thread_time
        for i, out in enumerate(estimates(n, np.random.default_rng(0))):
            for name in (list(ways) if i % 2 else list(ways)[::-1]):  # in turn, both orders
                t0 = clock()
                ways[name](out)
                cpu[name].append(clock() - t0)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    print(f"Publishing an estimate (TrainState + Odometry), {n} estimates each way, "
          f"thread CPU per estimate (us), first 5 % left out:")
    print("| way | p50 | p90 | p99 | mean |")
    print("|---|---:|---:|---:|---:|")
    for name, v in cpu.items():
        a = 1e6 * np.asarray(v[math.ceil(0.05 * n):])
        print(f"| {name} | {np.percentile(a, 50):.1f} | {np.percentile(a, 90):.1f} | "
              f"{np.percentile(a, 99):.1f} | {a.mean():.1f} |")


if __name__ == "__main__":
    main()
