"""Replay the reference bags (bags/) into the estimator nodes, record and check the outputs.

- thresholds through ``check_bag`` on the recorded output bag;
- the estimator core fed straight from the bag (no ROS) gives the same estimates as the node,
  sample for sample and bit for bit; the core is a function of the bag alone, so this is also
  the determinism check (a replay's estimates do not depend on the executor's timing).
"""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from train_core.bagio import read_bag

from train_estimation.core.online.estimators import (
    BrakingAdapter,
    BrakingConfig,
    RobustAdapter,
    RobustConfig,
    StartState,
)
from train_estimation.core.online.replay import replay
from train_sim.scenario import load_scenario

pytestmark = pytest.mark.ros
REPO = Path(__file__).resolve().parents[1]
BAGS = REPO / "bags"
# 5x: at 10x on two cores a particle filter node falls behind its input by seconds of stamps,
# and a sparse balise then reaches it far ahead of the odometer clock it is judged on
RATE = 5.0
PLAYER = [sys.executable, "-m", "train_sim.nodes.player"]


def live_replay(launch, ros_node, tmp_path, bag, scenario, estimators, tag):
    sc = load_scenario(scenario)
    ns = f"/replay_{tag}"
    out = tmp_path / f"out_{tag}"
    common = ["-p", "use_sim_time:=true", "-p", "control_clock:=same",
              "-p", f"line_file:={sc.line_path}",
              "-p", f"train_file:={sc.train_path}", "-p", f"initial_position:={sc.start_position}",
              "-p", f"odometer_rate:={sc.odometer_rate}", "-p", f"output_delay:={0.05 * RATE}"]
    rec = launch.node("train_estimation", "recorder", "--ros-args", "-r", f"__ns:={ns}",
                      "-p", f"bag:={out}", "-p", "use_sim_time:=true",
                      "-p", "topics:=[ground_truth, estimate/robust, estimate/gsma]")
    for exe in estimators:
        launch.node("train_estimation", exe, "--ros-args", "-r", f"__ns:={ns}", *common)
    ros_node.wait_for_subscribers(f"{ns}/odometer", len(estimators))
    ros_node.wait_for_subscribers(f"{ns}/ground_truth", 1)
    # the recorder and the estimators discover each other on their own: this narrows the time
    # in which the first estimates go unrecorded, it cannot close it (see `recorded`)
    for topic in ("estimate/robust", "estimate/gsma"):
        ros_node.wait_for_subscribers(f"{ns}/{topic}", 1)
    player = launch.start([*PLAYER, "--ros-args", "-r", f"__ns:={ns}", "-p", f"bag:={bag}",
                           "-p", f"rate_factor:={RATE}",
                           "-p", f"wait_for_subscribers:={len(estimators)}"], name="player")
    duration = read_bag(bag).stamps("odometer").max()
    ros_node.wait_until(lambda: player.poll() is not None, timeout=duration / RATE + 60,
                        what="the player to finish")
    assert player.returncode == 0, launch.logs()
    ros_node.spin_for(1.0)
    assert launch.stop(rec) == 0, launch.logs()
    return read_bag(out), out, sc


def estimates(bag, topic, source):
    rows = [(s, f) for _, s, f in bag.topics.get(topic, []) if f["source"] == source]
    return np.array([[s, f["position"], f["velocity"], f["braking_rate"]] for s, f in rows])


def offline(bag_path, sc, adapter):
    """The core fed in the node's arrival order: the player publishes in stamp order (stable
    over its topic list) at bag time = stamp, so that is the arrival order and time."""
    bag = read_bag(bag_path)
    events = sorted(((s, t, f) for t in ("control", "odometer", "balise")
                     for _, s, f in bag.topics[t]), key=lambda e: e[0])
    out, _ = replay([(t, s, f, s) for s, t, f in events], adapter,
                    1.0 / sc.odometer_rate, control_clock="same")  # the nodes' default
    return np.array([[o.stamp, o.position, o.velocity, o.braking_rate] for o in out])


def recorded(node, core):
    """The rows of ``core`` that the recording holds, and the recording up to the core's end.

    The recorder subscribes reliably (depth 1000) but matches each estimator's publisher when
    DDS discovery gets there: on a loaded machine that can be after the player's first seconds.
    What it misses is therefore a prefix, and from its first estimate on it has every one.
    """
    assert len(node), "nothing recorded"
    first = int(np.searchsorted(core[:, 0], node[0, 0] - 1e-9))
    assert first < len(core), (node[0, 0], core[-1, 0])
    n = len(core) - first
    assert len(node) >= n, ("an estimate lost after the recording's first", len(node), n)
    return core[first:], node[:n]


def assert_same(node, core):
    """Stamps to the header's nanosecond; the estimates bit for bit."""
    np.testing.assert_allclose(node[:, 0], core[:, 0], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(node[:, 1:], core[:, 1:])


def check(out_bag, thresholds):
    # the output bag holds the estimates and the truth only (the inputs are in the played bag)
    args = [sys.executable, "-m", "train_estimation.tools.check_bag", str(out_bag), "--no-plots",
            "--allow-missing", "odometer,balise,control"]
    for t in thresholds:
        args += ["--threshold", t]
    res = subprocess.run(args, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr


def test_metro_demo_bag_replay(launch, ros_node, tmp_path):
    bag = BAGS / "metro_demo_short"
    b1, out1, sc = live_replay(launch, ros_node, tmp_path, bag, "metro_demo",
                               ["robust_filter", "gsma_estimator"], "m")
    # 1.5 m, not the 1 m of an estimator that took the odometer's scale as exact (and was
    # wrong-side when it is not): the scale (prior sd 1 %) is learnt from balises read to 1 m;
    # this bag's first one, 1.1 m off at 350 m counted, moves the scale by a third of that over
    # 350 m, 2-3 m at the next balise. RMSE 1.11-1.13 m here (0.63-0.65 m with a scale known to
    # 0.2 %: odometer_scale_std, docs/benchmarks.md); the stated interval must hold throughout
    check(out1, ["estimators.robust_filter.position.rmse<=1.5",
                 "estimators.robust_filter.position_within_3sigma>=0.99",
                 "estimators.gsma.position.rmse<=1.5",  # gsma_estimator's default: gsma
                 "estimators.gsma.position_within_3sigma>=0.99",
                 "estimators.gsma.velocity.rmse<=0.3"])
    st = StartState(sc.start_position)
    robust = offline(bag, sc, RobustAdapter(sc.train, sc.line, st,
                                            RobustConfig(period=1.0 / sc.odometer_rate)))
    gsma = offline(bag, sc, BrakingAdapter(sc.train, sc.line, st, BrakingConfig()))
    for topic, source, core in (("estimate/robust", "robust_filter", robust),
                                ("estimate/gsma", "gsma", gsma)):
        # the nodes go on predicting while the player's clock runs past the last message
        c1, e1 = recorded(estimates(b1, topic, source), core)
        # the core fed from the bag equals the node, sample for sample: any replay of this bag
        # publishes these estimates wherever it was recorded (determinism)
        assert_same(e1, c1)


def test_wen2017_bag_replay(launch, ros_node, tmp_path):
    bag = BAGS / "wen2017_subway"
    b, out, sc = live_replay(launch, ros_node, tmp_path, bag, "wen2017_subway",
                             ["robust_filter"], "w")
    check(out, ["estimators.robust_filter.position.rmse<=2.0",
                "estimators.robust_filter.velocity.rmse<=0.3"])
    core = offline(bag, sc, RobustAdapter(sc.train, sc.line, StartState(sc.start_position),
                                          RobustConfig(period=1.0 / sc.odometer_rate)))
    c, e = recorded(estimates(b, "estimate/robust", "robust_filter"), core)
    assert_same(e, c)
