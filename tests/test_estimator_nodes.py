"""Estimator nodes on the live simulator (localhost-only ROS graph)."""

import math
import os
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from train_sim.scenario import load_scenario

pytestmark = pytest.mark.ros
REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "ros_ws" / "src" / "train_estimation" / "config"


def run_live(launch, ros_node, ns, scenario, duration, rate, nodes, topics, sim_extra=(),
             truth_readers=0):
    """Start the given estimator nodes and a simulator; collect ``topics`` until it ends."""
    from train_interfaces.msg import TrainState

    sc = load_scenario(scenario)
    boxes = {t: ros_node.collect(TrainState, f"{ns}/{t}") for t in topics}
    common = ["-p", "use_sim_time:=true", "-p", "control_clock:=same",
              "-p", f"line_file:={sc.line_path}",
              "-p", f"train_file:={sc.train_path}", "-p", f"initial_position:={sc.start_position}",
              "-p", f"odometer_rate:={sc.odometer_rate}",
              "-p", f"output_delay:={max(0.05, 0.05 * rate)}"]
    for exe, extra in nodes:
        # a params file first: the -p overrides after it win (later arguments override)
        launch.node("train_estimation", exe, "--ros-args", "-r", f"__ns:={ns}", *extra, *common)
    ros_node.wait_for_subscribers(f"{ns}/odometer", len(nodes))
    sim = launch.node("train_sim", "simulator", "--ros-args", "-r", f"__ns:={ns}",
                      "-p", f"scenario:={scenario}", "-p", f"rate_factor:={rate}",
                      "-p", f"duration:={duration}", "-p", f"wait_for_subscribers:={len(nodes)}",
                      "-p", f"wait_for_truth_subscribers:={truth_readers}", *sim_extra)
    ros_node.wait_until(lambda: sim.poll() is not None, timeout=duration / rate + 90,
                        what="the simulator run")
    ros_node.spin_for(2.0)
    assert sim.returncode == 0, launch.logs()

    wait_for_last_slot(ros_node, boxes, duration, sc.odometer_rate)
    return sc, boxes


def wait_for_last_slot(ros_node, boxes: dict, duration: float, rate: float,
                       odometer=None) -> None:
    """Wait until every estimator has published the run's last slot. A node on a loaded
    machine lags a fast simulator by seconds of wall time (its inputs stay queued), so what it
    managed by a fixed time is a count that depends on scheduling (GSMA at 10x under CPU hogs
    had published 312 of 600 two seconds after the simulator stopped); the caller's
    assertions say what is missing if it never does. ``odometer`` (the readings the test
    received, the simulator stopped): the last slot is its last reading's, since the radio
    may lose the run's final readings and no message after them releases their slots (the
    wait then lasted its whole timeout)."""
    def last(msgs):
        return max((m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in msgs),
                   default=-1.0)

    end = duration - 2.0 / rate
    if odometer:
        end = min(end, last(odometer) - 0.5 / rate)
    try:
        ros_node.wait_until(lambda: all(last(b) >= end for b in boxes.values()),
                            timeout=120.0,
                            what="the estimators to publish the run's last slot")
    except TimeoutError:
        pass


def test_robust_filter_tracks_truth_within_its_bound(launch, ros_node):
    """simulator + robust_filter + zone controller on metro_demo: |error| <= 3 sqrt(Sigma_xx)."""
    from train_interfaces.msg import TrainState

    ns = "/rf"
    truth = ros_node.collect(TrainState, f"{ns}/ground_truth")
    launch.node("train_sim", "zone_controller", "--ros-args", "-r", f"__ns:={ns}",
                "-p", "use_sim_time:=true", "-p", "state_topic:=estimate/robust")
    sc, boxes = run_live(
        launch, ros_node, ns, "metro_demo", 240.0, 20.0,
        [("robust_filter", ["--params-file", str(CONFIG / "robust_filter.yaml")])],
        ["estimate/robust"], truth_readers=1)
    est = boxes["estimate/robust"]
    assert len(est) >= 0.98 * 240.0 * sc.odometer_rate, launch.logs()
    assert all(m.source == "robust_filter" for m in est)
    t_truth = np.array([m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in truth])
    x_truth = np.array([m.position for m in truth])
    t = np.array([m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in est])
    x = np.array([m.position for m in est])
    sx = np.sqrt([m.covariance[0] for m in est])
    # compare only where this probe has ground truth: under load its ground_truth subscription
    # can be matched after the run started, and np.interp would extrapolate a constant there
    covered = (t >= t_truth[0]) & (t <= t_truth[-1])
    assert covered.mean() >= 0.9, (t_truth[0], t_truth[-1])
    err = (x - np.interp(t, t_truth, x_truth))[covered]
    inside = np.abs(err) <= 3 * sx[covered]
    assert inside.mean() >= 0.99, f"{inside.mean():.4f} of steps within 3 sigma"
    assert all(math.isnan(m.braking_rate) for m in est)
    assert np.all(np.diff(t) > 0)


def test_gsma_estimator_converges_to_the_degraded_braking_rate(launch, ros_node):
    """Live simulator, brakes at f = 0.7: after three braking phases |f_hat - 0.7| < 0.05.
    (The node's default algorithm is GSMA, so `source` is "gsma".)"""
    from train_sim.world import simulate

    ns = "/gsma"
    sc, boxes = run_live(
        launch, ros_node, ns, "metro_degraded", 480.0, 20.0,
        [("gsma_estimator", ["--params-file", str(CONFIG / "gsma_estimator.yaml")])],
        ["estimate/gsma"])
    est = boxes["estimate/gsma"]
    assert est and all(m.source == "gsma" for m in est)
    # the third braking phase ends when the train stops at the third station
    stops = simulate(sc, duration=480.0).stops
    assert len(stops) == 3, stops
    t_third = stops[2]["t"]
    after = [m for m in est if m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec > t_third]
    assert after, "no estimate after the third stop"
    f_true = sc.true_train.brake.braking_rate if sc.effects.braking_rate is None else \
        sc.effects.braking_rate.value(t_third)
    assert abs(after[0].braking_rate - f_true) < 0.05, (after[0].braking_rate, f_true)
    assert all(np.isfinite(m.covariance[15]) and m.covariance[15] >= 0 for m in est)


@pytest.mark.parametrize("rate,hogs", [(1.0, 0), (1.0, os.cpu_count() or 1), (10.0, 0),
                                       (10.0, os.cpu_count() or 1)])
def test_the_by_hand_recipe_with_default_parameters(launch, ros_node, rate, hogs):
    """docs/nodes.md's nodes by hand, in its order: the simulator at ``rate`` x real time with
    its defaults (it starts at once, waiting for nobody), then the estimators with
    use_sim_time and nothing else but the line and train. They join a run already going, at
    10x tens of seconds in, the train moving, while their start state says standing at the
    start: from its first estimate on each publishes every slot to the run's end, refuses no
    command but one that reached it later than its history (out of order), takes the
    commands on the odometer's clock, every estimate holds the truth within its protection
    levels, and each has found the train again by the end (its last estimates fuse readings
    and are not ALARM). At 10x the stamps run ten times faster than the nodes' (steady)
    arrival clock: the runner finds that pace from the commands (clocks.ArrivalPace). With
    ``hogs`` busy loops at normal
    priority (one per core, started before the nodes and ended with them), on a loaded
    machine: the nodes then get part of a core each, their arrivals stretch and bunch, and
    the defaults must still be right."""
    from train_interfaces.msg import OdometerReading, TrainState

    for i in range(hogs):
        # (SIGINT at its default: a shell's background job inherits it ignored, and the
        # launcher's stop then waited its 10 s for SIGTERM)
        launch.start([sys.executable, "-c", "import signal\n"
                      "signal.signal(signal.SIGINT, signal.SIG_DFL)\nwhile True: pass"],
                     name=f"cpu_hog{i}")
    ns = f"/byhand{int(rate)}{'hog' if hogs else ''}"
    # at 10x: long enough that a balise follows any plausible join (the monitor holds ALARM
    # after a reacquisition until a balise agrees with the odometer; the nodes come up 20-40 s
    # of simulated time in, and metro_demo's balises come at about 42, 72, 100, 201, 233 and 264 s)
    duration = 300.0 if rate > 1 else 20.0
    sc = load_scenario("metro_demo")
    truth = ros_node.collect(TrainState, f"{ns}/ground_truth")
    boxes = {t: ros_node.collect(TrainState, f"{ns}/estimate/{t}") for t in ("robust", "gsma")}
    odometer = ros_node.collect(OdometerReading, f"{ns}/odometer")
    files = ["-p", f"line_file:={sc.line_path}", "-p", f"train_file:={sc.train_path}"]
    # the truth's reader only, so that the test sees the run from its start (the recipe's
    # simulator waits for nobody)
    sim = launch.node("train_sim", "simulator", "--ros-args", "-r", f"__ns:={ns}",
                      "-p", f"rate_factor:={rate}", "-p", f"duration:={duration}",
                      "-p", "wait_for_truth_subscribers:=1")
    estimators = [launch.node("train_estimation", exe, "--ros-args", "-r", f"__ns:={ns}",
                              "-p", "use_sim_time:=true", *files)
                  for exe in ("robust_filter", "gsma_estimator")]
    ros_node.wait_until(lambda: sim.poll() is not None, timeout=duration / rate + 90,
                        what="the simulator run")
    ros_node.spin_for(2.0)
    assert sim.returncode == 0, launch.logs()
    wait_for_last_slot(ros_node, boxes, duration, sc.odometer_rate, odometer)
    for proc in estimators:  # their closing counts (a node writes them as it stops)
        launch.stop(proc)
    logs = launch.logs()
    # (the counts of refused input only: the events beside them, a command fused late, are
    # no refusals)
    rejected = re.findall(r"; rejected (\{[^}]*\}|none);", logs)
    assert len(rejected) == len(estimators), logs[-3000:]
    # each node's closing count ("rejected {'control:future_stamp': 11, ...}"): no command
    # refused as anything but out of order, and the commands on the odometer's clock, as the
    # simulator stamps them. (A node that joins times what it received before its first
    # /clock at that /clock, a backlog at one instant: if its older stamps voted, they set
    # the control clock's centre low, and at 10x the next 11-28 commands were refused as
    # ahead of it; decided from a backlog's first commands, "another clock" stayed for the
    # run. Out of order is a command that reached the node later than the history after its
    # stamp, which it cannot use: a reliable reader that joins may wait seconds of wall time,
    # tens of simulated seconds at 10x, for the writer to repair its first gap)
    refused = [(what, int(n)) for r in rejected
               for what, n in re.findall(r"'control:([a-z_]+)': (\d+)", r)]
    assert {what for what, _ in refused} <= {"out_of_order"}, (refused, logs[-3000:])
    # and each logged one says how late it came: beyond the runner's history (3 s; one within
    # it would be a rewind that failed)
    lags = [float(x) for x in re.findall(r"out_of_order: ([\d.]+) s older than the newest "
                                         r"input fused", logs)]
    assert bool(lags) == bool(refused) and all(x > 3.0 for x in lags), (lags, refused)
    assert "stamped on another clock" not in logs, \
        [line for line in logs.splitlines() if "another clock" in line]
    t_truth = np.array([m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in truth])
    x_truth = np.array([m.position for m in truth])
    period = 1.0 / sc.odometer_rate
    for name, est in boxes.items():
        t = np.array([m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in est])
        # to the last reading the link delivered (the radio may lose the run's final ones, and
        # no message after them releases their slots). After the simulator stops, the command
        # silence releases the last ones: the readings admitted lead, whatever the node's
        # simulated clock, which stands still then
        last = max(m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in odometer)
        assert len(t) > 1 and t[-1] >= last - 0.5 * period, (name, len(t), last, logs[-3000:])
        # every slot from the first estimate on, in order (the start depends on when the node
        # came up: on scheduling)
        assert np.all(np.diff(t) > 0) and np.diff(t).max() < 1.5 * period, name
        covered = (t >= t_truth[0]) & (t <= t_truth[-1])
        err = np.array([m.position for m in est])[covered] - np.interp(t[covered], t_truth,
                                                                        x_truth)
        ahead = np.array([m.protection_level_ahead for m in est])[covered]
        behind = np.array([m.protection_level_behind for m in est])[covered]
        assert np.all((err >= -ahead) & (err <= behind)), name
        # found again: the last 5 s of the run (minutes after the node came up at 10x); 2 =
        # ALARM (TrainState.msg)
        last = [m for m, tm in zip(est, t) if tm >= duration - 5.0]
        assert last and all(m.integrity != 2 for m in last), \
            (name, t[0], [m.integrity for m in last])
        assert np.mean([m.measurement_used for m in last]) > 0.5, name


def test_messages_that_wait_together_are_taken_in_the_order_they_were_sent(launch, tmp_path):
    """A balise read 30 ms before a slot and sent just before that slot's reading and command,
    all three waiting when the node wakes: rclpy's executor takes them one per subscription in
    the order the subscriptions were made (command, odometer, balise), and the balise was fused
    late, after the slot it precedes had left without it; a replay of the same messages in
    their order puts it into that slot. The node takes them in the order sent."""
    import json

    sc = load_scenario("metro_demo")
    out = tmp_path / "order.json"
    proc = launch.start([sys.executable, str(REPO / "tests" / "helpers" / "arrival_order.py"),
                         str(sc.line_path), str(sc.train_path), str(out)], name="arrival_order")
    assert proc.wait(timeout=120) == 0, proc.log_path.read_text()[-3000:]
    got = json.loads(out.read_text())
    assert got["accepted"] == {"control": 80, "odometer": 80, "balise": 1}, got
    assert "balise:fused_late" not in got["events"], got
