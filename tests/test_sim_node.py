"""Simulator and zone-controller nodes on a live (localhost-only) ROS graph."""

import math
from pathlib import Path

import numpy as np
import pytest
from train_core.link import bernoulli_received_probability

from train_sim.scenario import load_scenario

pytestmark = pytest.mark.ros

NS = "/train"
DURATION = 60.0  # s of simulated time
RATE = 20.0  # x real time


def binomial_interval(n: int, p: float, z: float = 4.5) -> tuple[float, float]:
    sd = math.sqrt(n * p * (1 - p))
    return n * p - z * sd, n * p + z * sd


def test_simulator_with_zone_controller(launch, ros_node):
    from train_interfaces.msg import (
        BaliseReading,
        ControlCommand,
        MovementAuthority,
        OdometerReading,
        TrainState,
    )

    sc = load_scenario("metro_demo")
    red_signal = sc.start_position + 700.0  # a danger point the train must stop before
    odo = ros_node.collect(OdometerReading, f"{NS}/odometer")
    ros_node.collect(ControlCommand, f"{NS}/control")
    ros_node.collect(BaliseReading, f"{NS}/balise")  # the simulator waits for every input
    truth = ros_node.collect(TrainState, f"{NS}/ground_truth")
    mas = ros_node.collect(MovementAuthority, f"{NS}/movement_authority")
    launch.node("train_sim", "zone_controller", "--ros-args", "-r", f"__ns:={NS}",
                "-p", "use_sim_time:=true", "-p", "state_topic:=ground_truth",
                "-p", f"danger_points:=[{red_signal}]", "-p", "rate:=2.0")
    ros_node.wait_for_subscribers(f"{NS}/ground_truth", 2)  # this probe and the controller
    sim = launch.node("train_sim", "simulator", "--ros-args", "-r", f"__ns:={NS}",
                      "-p", "scenario:=metro_demo", "-p", f"rate_factor:={RATE}",
                      "-p", f"duration:={DURATION}", "-p", "wait_for_subscribers:=1",
                      "-p", "wait_for_truth_subscribers:=2")
    ros_node.wait_until(lambda: sim.poll() is not None, timeout=DURATION / RATE + 60,
                        what="the simulator to finish its run")
    ros_node.spin_for(1.0)
    assert sim.returncode == 0, launch.logs()

    # counts: rate x duration samples offered, each received with the link's probability
    n = int(round(sc.odometer_rate * DURATION)) + 1  # samples at t = 0, 0.1, ..., DURATION
    p = bernoulli_received_probability(sc.link.p, sc.link.r)
    lo, hi = binomial_interval(n, p)
    assert lo <= len(odo) <= hi, f"{len(odo)} odometer messages, expected [{lo:.0f}, {hi:.0f}]"
    seqs = [m.seq for m in odo]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)

    # ground truth is published at the odometer rate (every period, from the first sample to
    # the end of the run: the world went on past its first messages once this probe and the
    # controller had acknowledged them) and is monotone in position
    assert "the first messages acknowledged by every reader" in launch.logs()
    tt = np.array([m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in truth])
    assert tt[0] == 0.0 and abs(tt[-1] - DURATION) < 1e-6, (tt[0], tt[-1])
    np.testing.assert_allclose(np.diff(tt), 1.0 / sc.odometer_rate, atol=1e-6)
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
        msg.braking_rate = math.nan  # not estimated
        msg.covariance = [1.0 if i in (0, 5) else 0.0 for i in range(16)]
        pub.publish(msg)

    timer = ros_node.node.create_timer(0.1, report)
    ros_node.wait_until(lambda: any(not m.emergency_brake for m in mas), timeout=20,
                        what="an authority without emergency brake while estimates flow")
    timer.cancel()
    n_before = len(mas)
    ros_node.wait_until(lambda: any(m.emergency_brake for m in mas[n_before:]), timeout=20,
                        what="the emergency brake after the estimates stopped")


def test_zone_controller_refuses_bad_reports_without_crashing_or_locking(launch, ros_node):
    """A live zone controller fed bad TrainStates between good ones (a negative braking-rate
    variance, NaN variances, a stamp 1e6 s ahead, integrity 9) keeps running, keeps granting
    authority from the good ones, logs each kind once per log_interval, and brakes at once on
    integrity ALARM."""
    from train_interfaces.msg import MovementAuthority, TrainState

    ns = "/bad_reports"
    mas = ros_node.collect(MovementAuthority, f"{ns}/movement_authority")
    pub = ros_node.node.create_publisher(TrainState, f"{ns}/estimate/robust", 100)
    zc = launch.node("train_sim", "zone_controller", "--ros-args", "-r", f"__ns:={ns}",
                     "-p", "stale_timeout:=2.0", "-p", "rate:=10.0",
                     "-p", "danger_points:=[5000.0]", "-p", "log_interval:=60.0")
    ros_node.wait_for_subscribers(f"{ns}/estimate/robust", 1)
    ros_node.wait_for_publishers(f"{ns}/movement_authority", 1)
    bad = [{"braking_rate": 0.9, 15: -0.01}, {0: math.nan}, {"braking_rate": 0.9, 15: math.nan},
           {"ahead": 1e6}, {"integrity": 9}]
    state = {"integrity": 0}

    def report(change=None):
        change = dict(change or {})
        msg = TrainState()
        now = ros_node.node.get_clock().now().nanoseconds * 1e-9 + change.pop("ahead", 0.0)
        msg.header.stamp.sec, msg.header.stamp.nanosec = int(now), int(now % 1 * 1e9)
        msg.source = "test"
        msg.position, msg.velocity = 100.0, 0.0
        msg.braking_rate = change.pop("braking_rate", math.nan)
        msg.integrity = change.pop("integrity", state["integrity"])
        cov = [math.nan] * 16
        cov[0], cov[1], cov[4], cov[5] = 1.0, 0.0, 0.0, 0.01
        for i, v in change.items():
            cov[i] = v
        msg.covariance = cov
        pub.publish(msg)

    def good_and_bad():
        report()
        for b in bad:
            report(b)

    timer = ros_node.node.create_timer(0.1, good_and_bad)
    ros_node.spin_for(4.0)  # 40 rounds: 200 bad reports, 40 good ones
    n = len(mas)
    ros_node.wait_until(lambda: len(mas) > n + 5, timeout=20, what="authorities after the garbage")
    assert zc.poll() is None, launch.logs()
    assert not any(m.emergency_brake for m in mas[n:]), "bad reports locked the authority"
    state["integrity"] = 2  # ALARM: the next authority brakes
    n = len(mas)
    ros_node.wait_until(lambda: any(m.emergency_brake for m in mas[n:]), timeout=20,
                        what="the emergency brake on integrity ALARM")
    timer.cancel()
    launch.stop(zc)  # the whole log is on disk
    log = Path(zc.log_path).read_text()
    for kind in ("non-positive variance", "non-finite value", "future stamp",
                 "unknown integrity"):
        assert log.count(f"refused ({kind})") == 1, (kind, log)
    assert "emergency brake SET (alarm)" in log


@pytest.mark.parametrize("with_model", [False, True])
def test_node_publishes_exactly_what_the_offline_generator_produces(launch, ros_node, tmp_path,
                                                                    with_model):
    """Same scenario and seed: the live node's messages equal simulate()'s, field for field;
    also when it runs a model directory as diagnose writes it (`model` parameter)."""
    import shutil

    import yaml
    from train_core.files import config_file
    from train_core.ros import msg_to_dict, stamp_to_sec

    from train_interfaces.msg import BaliseReading, ControlCommand, OdometerReading, TrainState
    from train_sim.scenario import with_model as run_model
    from train_sim.world import simulate

    ns, seed, duration = f"/det{int(with_model)}", 11, 40.0
    extra, sc = [], load_scenario("metro_demo")
    if with_model:
        shutil.copy(config_file("lines", "metro_demo"), tmp_path / "line.yaml")
        shutil.copy(config_file("trains", "metro_b6"), tmp_path / "train.yaml")
        (tmp_path / "effects.yaml").write_text(yaml.safe_dump(
            {"gradient": {"start": 120.0, "end": 400.0, "permille": 6.0},
             "mass": {"mass": 300000.0}}))
        extra = ["-p", f"model:={tmp_path}"]
        sc = run_model(sc, tmp_path)
        assert sc.effects.active() == ["gradient", "mass"]
    types = {"odometer": OdometerReading, "balise": BaliseReading, "control": ControlCommand,
             "ground_truth": TrainState}
    boxes = {t: ros_node.collect(cls, f"{ns}/{t}") for t, cls in types.items()}
    sim = launch.node("train_sim", "simulator", "--ros-args", "-r", f"__ns:={ns}",
                      "-p", "scenario:=metro_demo", "-p", f"seed:={seed}",
                      "-p", "rate_factor:=40.0", "-p", f"duration:={duration}",
                      "-p", "wait_for_subscribers:=1", "-p", "wait_for_truth_subscribers:=1",
                      *extra)
    ros_node.wait_until(lambda: sim.poll() is not None, timeout=60, what="the simulator run")
    ros_node.spin_for(1.0)
    assert sim.returncode == 0, launch.logs()

    res = simulate(sc, seed=seed, duration=duration)
    expected = {t: [] for t in types}
    for topic, stamp, fields in res.events():
        expected[topic].append((stamp, fields))
    for topic, box in boxes.items():
        assert len(box) == len(expected[topic]), topic
        for msg, (stamp, fields) in zip(box, expected[topic]):
            assert abs(stamp_to_sec(msg.header.stamp) - stamp) < 1e-9
            got = msg_to_dict(msg)
            for key, value in fields.items():
                if isinstance(value, str):
                    assert got[key] == value, (topic, key)
                    continue
                assert np.array_equal(np.asarray(got[key], dtype=float),
                                      np.asarray(value, dtype=float), equal_nan=True), \
                    (topic, key, got[key], value)


def test_bad_scenario_is_refused_with_one_line_and_exit_code_2(launch, tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: bad\nline: metro_demo\ntrain: metro_b6\nduration: -5\n")
    sim = launch.node("train_sim", "simulator", "--ros-args", "-p", f"scenario:={bad}")
    assert sim.wait(30) == 2
    text = sim.log_path.read_text().strip().splitlines()
    assert text and text[-1].startswith("error: ") and "bad.yaml" in text[-1], text
    assert "Traceback" not in "\n".join(text)


def test_clock_before_each_delivery_and_not_every_step(launch, ros_node):
    """/clock (clock_period 0.1 s at 1x): said with the messages of each step, so that each
    ground-truth sample finds a /clock at or after its stamp soon after it (within 1 s: a
    loaded machine stretches a step); otherwise at most every clock_period of wall time, so
    far fewer than one per 10 ms step (350 in this run); and the run's last instant is said."""
    from rosgraph_msgs.msg import Clock

    from train_interfaces.msg import ControlCommand, OdometerReading, TrainState

    ns, duration = "/clocked", 3.0
    clock = ros_node.collect(Clock, "/clock")
    ros_node.collect(OdometerReading, f"{ns}/odometer")
    ros_node.collect(ControlCommand, f"{ns}/control")
    truth = ros_node.collect(TrainState, f"{ns}/ground_truth")
    sim = launch.node("train_sim", "simulator", "--ros-args", "-r", f"__ns:={ns}",
                      "-p", "rate_factor:=1.0", "-p", f"duration:={duration}",
                      "-p", "end_linger:=0.5", "-p", "clock_period:=0.1",
                      "-p", "wait_for_truth_subscribers:=1")
    ros_node.wait_until(lambda: sim.poll() is not None, timeout=duration + 60,
                        what="the simulator to finish its run")
    ros_node.spin_for(0.5)
    assert sim.returncode == 0, launch.logs()
    said = np.array(sorted(m.clock.sec + 1e-9 * m.clock.nanosec for m in clock))
    stamps = [m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in truth]
    assert len(stamps) >= 25, len(stamps)
    for s in stamps:  # a /clock at or after each sample, with the step that delivered it
        i = np.searchsorted(said, s - 1e-9)
        assert i < len(said) and said[i] - s < 1.0, (s, said[max(0, i - 1):i + 2])
    # the deliveries (ground truth, control, odometer at 10 Hz; balises) and once per
    # clock_period between them: at most 2 x 10 per s of the run and its linger, not 100
    assert len(said) <= 2 * 10 * (duration + 0.5) + 2, len(said)
    assert said[-1] == pytest.approx(duration + 0.5, abs=1e-9)  # the run's last instant


def test_a_world_that_waits_says_for_what(launch, ros_node):
    """A simulator whose readers are not there stands still and says, once per
    wait_log_period, which input lacks subscribers; paced, it names the topic it waits for.
    The main job's progress reader keeps that line, so a run that does not finish reports
    its cause instead of only 'did not finish in time'."""
    from train_bringup.main_job import SimProgress

    from train_interfaces.msg import BaliseReading, ControlCommand, OdometerReading

    ns = "/waiting_world"
    sim = launch.node("train_sim", "simulator", "--ros-args", "-r", f"__ns:={ns}",
                      "-p", "scenario:=metro_demo", "-p", "rate_factor:=20.0",
                      "-p", "duration:=30.0", "-p", "wait_for_subscribers:=1",
                      "-p", "wait_log_period:=0.5", "-p", "max_lead:=1.0",
                      "-p", "pace_topics:=[estimate/robust]")
    watch = SimProgress(Path(sim.log_path), 30.0)
    try:
        ros_node.wait_until(lambda: (watch.update(), watch.waiting)[1], timeout=30,
                            what="the simulator's log line on what it waits for")
        assert watch.waiting.startswith(
            "waiting for subscribers: odometer 0 of 1, balise 0 of 1, control 0 of 1, "
            "ground_truth 0 of 0 ("), watch.waiting
        assert watch.bar.n == 0  # it did not start
        # the readers come: the world starts, runs 1 s ahead of estimate/robust (never
        # published here) and says that it waits for it
        for msg_type, topic in ((OdometerReading, "odometer"), (BaliseReading, "balise"),
                                (ControlCommand, "control")):
            ros_node.collect(msg_type, f"{ns}/{topic}")
        ros_node.wait_until(lambda: (watch.update(), "paced at" in watch.waiting)[1],
                            timeout=30, what="the paced world's log line")
    finally:
        watch.close()
    assert watch.waiting.startswith("paced at t = 1.00 s, waiting for estimate/robust "
                                    "(newest stamp 0.00 s, 0 received)"), watch.waiting
