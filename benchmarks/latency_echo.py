#!/usr/bin/env python3
"""A bare rclpy echo node: the floor of ``bench_latency``'s receive -> publish latency.

It subscribes to ``odometer`` as the estimator nodes do (same executor loop,
``train_core.ros.run_node``), and for every reading publishes at once what an estimator
publishes for it -- a TrainState on ``estimate/echo`` and a nav_msgs/Odometry on ``odom/echo``,
stamped with the reading's stamp -- with no estimation at all. Its latency is measured as the
estimators measure theirs (steady clock, from the callback's start to the second publish's
return) and logged at SIGINT in the same form, so one run of ``bench_latency`` gives the
estimators' latencies next to the part of them that is rclpy's own (message conversion,
publishing, serialisation into DDS). It also logs how long each reading waited in its queue
before the callback (from the DDS layer's reception stamp, rclpy's MessageInfo): the executor's
own work before a callback, which the latency from the callback's start leaves out.

    python3 benchmarks/latency_echo.py --ros-args -r __ns:=/lat
"""

from __future__ import annotations

import math
import sys
import time

import numpy as np


def main(argv=None) -> int:
    from train_core.ros import parse_cli, run_node

    _, ros_args = parse_cli(__doc__.splitlines()[0], argv)

    def factory():
        from nav_msgs.msg import Odometry
        from rclpy.clock import Clock, ClockType
        from rclpy.node import Node

        from train_interfaces.msg import OdometerReading, TrainState

        class Echo(Node):
            def __init__(self):
                super().__init__("latency_echo")
                self.steady = Clock(clock_type=ClockType.STEADY_TIME)
                self.pub = self.create_publisher(TrainState, "estimate/echo", 1000)
                self.odom_pub = self.create_publisher(Odometry, "odom/echo", 1000)
                self.latency: list[float] = []
                self.queued: list[float] = []  # s, DDS reception -> the callback's start
                self.whole: list[float] = []  # s, DDS reception -> the Odometry published
                self.create_subscription(OdometerReading, "odometer", self.on_odometer, 2000)

            def on_odometer(self, msg, info) -> None:
                recv = self.steady.now().nanoseconds * 1e-9
                received = info.get("received_timestamp")  # the DDS layer's, system clock
                if received:
                    self.queued.append((time.time_ns() - received) * 1e-9)
                out = TrainState()
                out.header.stamp = msg.header.stamp
                out.header.frame_id = "track"
                out.source = "echo"
                out.position, out.velocity = msg.distance, msg.speed
                out.acceleration = out.braking_rate = math.nan
                out.covariance = [math.nan] * 16
                self.pub.publish(out)
                odom = Odometry()
                odom.header = out.header
                odom.child_frame_id = "base_link"
                odom.pose.pose.position.x = out.position
                odom.pose.pose.orientation.w = 1.0
                odom.twist.twist.linear.x = out.velocity
                self.odom_pub.publish(odom)
                self.latency.append(self.steady.now().nanoseconds * 1e-9 - recv)
                if received:
                    self.whole.append((time.time_ns() - received) * 1e-9)

            def close(self) -> None:
                lat = np.array(self.latency[3:])  # the estimators' start-up samples aside
                if lat.size:
                    p50, p99, top = np.percentile(lat, 50), np.percentile(lat, 99), lat.max()
                    self.get_logger().info(
                        f"latency odometer received -> echo published: p50 {1e3 * p50:.2f} ms,"
                        f" p99 {1e3 * p99:.2f} ms, max {1e3 * top:.2f} ms over {lat.size} "
                        "samples")
                q, w = 1e3 * np.array(self.queued[3:]), 1e3 * np.array(self.whole[3:])
                if q.size and w.size:
                    self.get_logger().info(
                        f"queue wait (DDS reception -> callback start): p50 "
                        f"{np.percentile(q, 50):.2f} ms, p99 {np.percentile(q, 99):.2f} ms; "
                        f"DDS reception -> echo published: p50 {np.percentile(w, 50):.2f} ms, "
                        f"p99 {np.percentile(w, 99):.2f} ms")

        return Echo()

    return run_node(factory, ros_args)


if __name__ == "__main__":
    sys.exit(main())
