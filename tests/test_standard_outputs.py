"""The standard ROS outputs of a running estimator: nav_msgs/Odometry and /diagnostics."""

import re
import time

import numpy as np
import pytest

from train_sim.scenario import load_scenario

pytestmark = pytest.mark.ros


def _stamp(m) -> float:
    return m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec


def _mine(arrays, ns, name):
    """The DiagnosticStatus entries of one node of this test's namespace, in arrival order."""
    return [s for a in arrays for s in a.status
            if s.hardware_id == ns and s.name.startswith(f"{name}:")]


def test_estimator_publishes_odometry_and_diagnostics(launch, ros_node):
    """simulator + robust_filter: one Odometry per TrainState with the same stamp, position,
    speed and variances (REP-103 layout, unknown = large, never NaN); every node's status on
    /diagnostics about once a second, naming its inputs' rates, counts and integrity."""
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry

    from train_interfaces.msg import TrainState

    ns = "/std_out"
    sc = load_scenario("metro_demo")
    odom = ros_node.collect(Odometry, f"{ns}/odom/robust")
    est = ros_node.collect(TrainState, f"{ns}/estimate/robust")
    diags = ros_node.collect(DiagnosticArray, "/diagnostics")
    t_start = time.monotonic()
    launch.node("train_estimation", "robust_filter", "--ros-args", "-r", f"__ns:={ns}",
                "-p", "use_sim_time:=true", "-p", f"line_file:={sc.line_path}",
                "-p", f"train_file:={sc.train_path}",
                "-p", f"initial_position:={sc.start_position}", "-p", "output_delay:=0.5",
                "-p", "control_clock:=same")  # the simulator's launch: one clock
    ros_node.wait_for_subscribers(f"{ns}/odometer", 1)
    ros_node.wait_for_publishers(f"{ns}/odom/robust", 1)
    ros_node.spin_for(3.0)  # the estimator alone: its odometer input is missing
    idle = _mine(diags, ns, "robust_filter")
    assert idle, launch.logs()
    # WARN from stale_warn (2 s), ERROR from stale_error (5 s) after the node's start
    assert idle[-1].level in (bytes([1]), bytes([2])), idle[-1]
    assert idle[-1].message.startswith("odometer: nothing received since start"), idle[-1]
    sim = launch.node("train_sim", "simulator", "--ros-args", "-r", f"__ns:={ns}",
                      "-p", "scenario:=metro_demo", "-p", "rate_factor:=10.0",
                      "-p", "duration:=40.0", "-p", "wait_for_subscribers:=1")
    ros_node.wait_until(lambda: sim.poll() is not None, timeout=90, what="the simulator run")
    ros_node.spin_for(1.5)
    elapsed = time.monotonic() - t_start
    assert sim.returncode == 0, launch.logs()

    assert len(est) >= 0.98 * 40.0 * sc.odometer_rate, launch.logs()
    assert len(odom) == len(est)
    for o, e in zip(odom, est):
        assert _stamp(o) == _stamp(e)
        assert o.header.frame_id == "track" and o.child_frame_id == "base_link"
        assert o.pose.pose.position.x == e.position and o.twist.twist.linear.x == e.velocity
        assert o.pose.pose.orientation.w == 1.0
        pose, twist = np.reshape(o.pose.covariance, (6, 6)), np.reshape(o.twist.covariance,
                                                                         (6, 6))
        # the position variance overbounds the protection levels (5.33 sd at 1e-7 reach
        # the larger; docs/ros.md), never below the estimator's own
        assert twist[0, 0] == e.covariance[5] and pose[0, 0] >= e.covariance[0]
        level = max(e.protection_level_ahead, e.protection_level_behind)
        if np.isfinite(level):
            assert pose[0, 0] == pytest.approx(max(e.covariance[0], (level / 5.3267) ** 2),
                                               rel=1e-4)
        else:
            assert pose[0, 0] == 1e6
        assert np.all(np.isfinite(pose)) and np.all(np.isfinite(twist))
        assert np.all(np.diag(pose)[1:] >= 1e6) and np.all(np.diag(twist)[1:] >= 1e6)

    running = [s for s in _mine(diags, ns, "robust_filter")
               if dict((kv.key, kv.value) for kv in s.values).get("odometer.received", "0")
               != "0"]
    assert len(running) >= 3, launch.logs()
    values = {kv.key: kv.value for kv in running[-1].values}
    assert values["source"] == "robust_filter" and values["integrity"] in ("OK", "DEGRADED",
                                                                          "ALARM")
    for key in ("odometer.rate_hz", "odometer.accepted", "control.rate_hz", "balise.received",
                "latency_p99_ms", "integrity_reason", "odometer.age_s", "odometer_scale",
                "odometer_scale_std"):
        assert key in values, (key, values)
    # the odometer's own period from its stamps and counter: odometer_rate is right, no WARN
    assert float(values["odometer_period_s"]) == pytest.approx(1.0 / sc.odometer_rate,
                                                               rel=1e-3), values
    assert "odometer_rate" not in running[-1].message, running[-1].message
    # the scale learnt so far, in the parameter's terms (a next run can start from it)
    assert abs(float(values["odometer_scale"]) - 1.0) < 0.03, values["odometer_scale"]
    assert 0.0 < float(values["odometer_scale_std"]) <= 0.01, values["odometer_scale_std"]
    # 10 Hz odometer at 10x: about 100 per wall second, less the link's drops (12.5 %), in a
    # period spent wholly in the run (the first and last ones hold part of it)
    rates = [float(dict((kv.key, kv.value) for kv in s.values)["odometer.rate_hz"])
             for s in running]
    assert 50 <= max(rates) <= 150, rates
    # healthy while the run goes on: OK, or WARN for nothing but a protection level beyond
    # the alert limit (integrity DEGRADED: bounded, unavailable to the operation;
    # docs/integrity.md measures how often on clean runs); after the run the inputs fall silent
    assert any(st.level == bytes([0]) or (st.level == bytes([1]) and all(
        part.startswith("integrity DEGRADED") for part in st.message.split("; ")))
        for st in running), [(st.level, st.message) for st in running]
    # the simulator's status names its state and what it published
    world = _mine(diags, ns, "simulator")
    assert world and {kv.key for kv in world[-1].values} >= {"state", "sim_time_s",
                                                             "odometer.published"}
    # one status per second per node (steady clock, whatever /clock does), from its start
    n = len(_mine(diags, ns, "robust_filter"))
    assert elapsed - 8.0 <= n <= elapsed + 1.0, (n, elapsed)


def test_zone_controller_diagnostics_count_refused_reports_by_reason(launch, ros_node):
    """Reports with a negative variance are refused and counted under their reason; the share
    refused in the period grades the status (here all of them: ERROR, the reason named)."""
    from diagnostic_msgs.msg import DiagnosticArray

    from train_interfaces.msg import TrainState

    ns = "/zone_diag"
    diags = ros_node.collect(DiagnosticArray, "/diagnostics")
    pub = ros_node.node.create_publisher(TrainState, f"{ns}/estimate/robust", 10)
    launch.node("train_sim", "zone_controller", "--ros-args", "-r", f"__ns:={ns}")
    ros_node.wait_for_subscribers(f"{ns}/estimate/robust", 1, timeout=30)
    for k in range(5):
        msg = TrainState()
        msg.header.stamp.sec = k
        msg.source = "test"
        msg.position, msg.velocity = 100.0, 0.0
        msg.covariance = [1.0] * 16
        msg.covariance[0] = -0.01
        pub.publish(msg)
    ros_node.wait_until(lambda: any(
        dict((kv.key, kv.value) for kv in s.values).get(f"{ns}.rejected.non_positive_variance")
        == "5" for s in _mine(diags, ns, "zone_controller")), timeout=20,
        what="the zone's status counting 5 refused reports")
    last = [s for s in _mine(diags, ns, "zone_controller")
            if dict((kv.key, kv.value) for kv in s.values).get(f"{ns}.received") == "5"]
    first = last[0]  # the period in which the five arrived
    assert first.level == bytes([2]), (first.level, first.message)
    # all refused in that period (the five may straddle two periods: n of n)
    assert re.search(rf"{ns}: (\d) of \1 rejected in the last 1 s \(mostly "
                     r"non_positive_variance\)", first.message), first.message
    assert dict((kv.key, kv.value) for kv in first.values)[f"{ns}.accepted"] == "0"
