"""Simulator and zone-controller nodes on a live (localhost-only) ROS graph."""

import math

import numpy as np
import pytest

from train_sim.link import bernoulli_received_probability
from train_sim.scenario import load_scenario

pytestmark = pytest.mark.ros

NS = "/train"
DURATION = 60.0  # s of simulated time
RATE = 20.0  # x real time


def binomial_interval(n: int, p: float, z: float = 4.5) -> tuple[float, float]:
    sd = math.sqrt(n * p * (1 - p))
    return n * p - z * sd, n * p + z * sd


def test_simulator_with_zone_controller(launch, ros_node):
    from train_interfaces.msg import MovementAuthority, OdometerReading, TrainState

    sc = load_scenario("metro_demo")
    red_signal = sc.start_position + 700.0  # a danger point the train must stop before
    odo = ros_node.collect(OdometerReading, f"{NS}/odometer")
    truth = ros_node.collect(TrainState, f"{NS}/ground_truth")
    mas = ros_node.collect(MovementAuthority, f"{NS}/movement_authority")
    launch.node("train_sim", "zone_controller", "--ros-args", "-r", f"__ns:={NS}",
                "-p", "use_sim_time:=true", "-p", "state_topic:=ground_truth",
                "-p", f"danger_points:=[{red_signal}]", "-p", "rate:=2.0")
    ros_node.wait_for_subscribers(f"{NS}/ground_truth", 1)
    sim = launch.node("train_sim", "simulator", "--ros-args", "-r", f"__ns:={NS}",
                      "-p", "scenario:=metro_demo", "-p", f"rate_factor:={RATE}",
                      "-p", f"duration:={DURATION}", "-p", "wait_for_subscribers:=1")
    ros_node.wait_until(lambda: sim.poll() is not None, timeout=DURATION / RATE + 60,
                        what="the simulator to finish its run")
    ros_node.spin_for(1.0)
    assert sim.returncode == 0, launch.logs()

    # counts: rate x duration samples offered, each received with the link's probability
    n = int(round(sc.odometer_rate * DURATION))
    p = bernoulli_received_probability(sc.link.p, sc.link.r)
    lo, hi = binomial_interval(n, p)
    assert lo <= len(odo) <= hi, f"{len(odo)} odometer messages, expected [{lo:.0f}, {hi:.0f}]"
    seqs = [m.seq for m in odo]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)

    # ground truth is published at the odometer rate and is monotone in position
    assert abs(len(truth) - n) <= 1
    x = np.array([m.position for m in truth])
    assert np.all(np.diff(x) >= 0.0)

    # the zone controller's authority is obeyed: never past the end of authority
    assert mas, "no movement authority received"
    eoa = min(m.end_of_authority for m in mas if math.isfinite(m.end_of_authority))
    assert eoa <= red_signal
    assert x.max() <= eoa, f"train reached {x.max():.1f} m past EoA {eoa:.1f} m"
    assert x.max() > sc.start_position + 100.0, "the train never moved"


def test_stale_estimates_trigger_the_emergency_brake(launch, ros_node):
    from train_interfaces.msg import MovementAuthority, TrainState

    ns = "/stale_train"
    mas = ros_node.collect(MovementAuthority, f"{ns}/movement_authority")
    pub = ros_node.node.create_publisher(TrainState, f"{ns}/estimate/robust", 10)
    launch.node("train_sim", "zone_controller", "--ros-args", "-r", f"__ns:={ns}",
                "-p", "stale_timeout:=1.0", "-p", "rate:=10.0", "-p", "danger_points:=[5000.0]")
    ros_node.wait_for_subscribers(f"{ns}/estimate/robust", 1)
    ros_node.wait_for_publishers(f"{ns}/movement_authority", 1)

    def report():
        msg = TrainState()
        msg.header.stamp = ros_node.node.get_clock().now().to_msg()
        msg.source = "test"
        msg.position, msg.velocity = 100.0, 0.0
        msg.covariance = [1.0 if i in (0, 5) else 0.0 for i in range(16)]
        pub.publish(msg)

    timer = ros_node.node.create_timer(0.1, report)
    ros_node.wait_until(lambda: any(not m.emergency_brake for m in mas), timeout=20,
                        what="an authority without emergency brake while estimates flow")
    timer.cancel()
    n_before = len(mas)
    ros_node.wait_until(lambda: any(m.emergency_brake for m in mas[n_before:]), timeout=20,
                        what="the emergency brake after the estimates stopped")
