"""check_bag against bags whose errors are known by construction."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
from train_core.bagio import BagWriter, msgdef, read_bag

from train_estimation.tools import check_bag
from train_sim.generate import generate
from train_sim.scenario import load_scenario

REPO = Path(__file__).resolve().parents[1]
SIGMA_X, SIGMA_V = 2.0, 0.1


@pytest.fixture(scope="module")
def bag_with_estimate(tmp_path_factory):
    """A 60 s metro_demo bag plus an 'estimator' = truth + N(0, diag(SIGMA^2)), stating it."""
    root = tmp_path_factory.mktemp("bag")
    res = generate(load_scenario("metro_demo"), root / "src", seed=5, duration=60.0)
    rng = np.random.default_rng(0)
    out = root / "bag"
    with BagWriter(out) as w:
        for topic, stamp, fields in res.events():
            w.write(topic, stamp, fields)
            if topic == "ground_truth":
                cov = np.diag([SIGMA_X**2, SIGMA_V**2, math.nan, math.nan]).ravel()
                est = dict(fields, source="fake", covariance=cov, measurement_used=True,
                           position=fields["position"] + rng.normal(0, SIGMA_X),
                           velocity=fields["velocity"] + rng.normal(0, SIGMA_V),
                           braking_rate=math.nan)
                w.write("estimate/robust", stamp, est, t_ns=int(round((stamp + 0.002) * 1e9)))
    return out, res


def test_errors_and_consistency_match_the_construction(bag_with_estimate, tmp_path):
    bag, res = bag_with_estimate
    s = check_bag.check(str(bag), tmp_path, expected_received=0.875)
    r = s["estimators"]["fake"]
    n = r["position"]["n"]
    # RMSE^2 * n / sigma^2 ~ chi2(n): 4.5-sigma band on the RMSE from that distribution
    for key, sigma in (("position", SIGMA_X), ("velocity", SIGMA_V)):
        tol = 4.5 * sigma * math.sqrt(1 / (2 * n))
        assert abs(r[key]["rmse"] - sigma) < tol, (key, r[key])
    # NEES ~ chi2(2): mean 2 with sd 2/sqrt(n)
    assert abs(r["nees"]["mean"] - 2.0) < 4.5 * 2.0 / math.sqrt(n)
    assert abs(r["latency_s"]["median"] - 0.002) < 1e-6
    odo = s["topics"]["odometer"]
    assert odo["received_fraction"] == pytest.approx(
        1 - res.dropped["odometer"] / res.sent["odometer"], abs=2 / res.sent["odometer"])
    assert (tmp_path / "summary.json").exists()
    assert (tmp_path / "estimates_vs_truth.png").stat().st_size > 10_000


def test_exit_codes(bag_with_estimate, tmp_path, capsys):
    bag, _ = bag_with_estimate
    ok = ["--threshold", "estimators.fake.position.rmse<=3", "--no-plots"]
    assert check_bag.main([str(bag), *ok]) == 0
    bad = ["--threshold", "estimators.fake.position.rmse<=0.5", "--no-plots"]
    assert check_bag.main([str(bag), *bad]) == 1
    missing = ["--threshold", "estimators.nobody.position.rmse<=1", "--no-plots"]
    assert check_bag.main([str(bag), *missing]) == 2
    assert check_bag.main([str(tmp_path / "nope")]) == 2
    corrupt = tmp_path / "corrupt"
    corrupt.mkdir()
    (corrupt / "corrupt.mcap").write_bytes(b"not an mcap file at all")
    (corrupt / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    assert check_bag.main([str(corrupt)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err and all(line.startswith("check_bag:") for line in err)


@pytest.mark.parametrize("text, code, what", [
    ("estimators.fake.position.rmse: {max: 3}\n", 0, None),
    ("estimators.fake.position.rmse: {max: 0.5}\n", 1, None),
    ("- estimators.fake.position.rmse<=3\n", 2, "expected a mapping at the top level"),
    ("estimators.fake.position.rmse:\n\t{max: 3}\n", 2, "a tab on that line"),
    ("estimators.fake.position.rmse: {max: three}\n", 2, "max must be a number"),
    ("estimators.fake.position.rmse: {}\n", 2, "expected {max: V}"),
])
def test_a_thresholds_file_is_read_or_refused_in_one_line(bag_with_estimate, tmp_path, capsys,
                                                          text, code, what):
    bag, _ = bag_with_estimate
    (tmp_path / "t.yaml").write_text(text)
    assert check_bag.main([str(bag), "--no-plots", "--thresholds", str(tmp_path / "t.yaml")]) \
        == code
    err = capsys.readouterr().err
    if what:
        assert what in err and err.startswith("check_bag:")


def test_reads_bags_written_by_the_mcap_writer(tmp_path):
    from mcap_ros2.writer import Writer

    path = tmp_path / "other.mcap"
    with open(path, "wb") as fh:
        w = Writer(fh)
        schema = w.register_msgdef("train_interfaces/msg/OdometerReading",
                                   msgdef("train_interfaces/msg/OdometerReading"))
        other = w.register_msgdef("example/msg/Thing", "float64 value\n")
        for i in range(5):
            w.write_message("/train/odometer", schema, {
                "header": {"stamp": {"sec": i, "nanosec": 0}, "frame_id": "track"},
                "seq": i, "distance": float(i), "speed": 1.0, "speed_variance": 0.01},
                log_time=i * 10**9, publish_time=i * 10**9)
            w.write_message("/train/thing", other, {"value": 1.0}, log_time=i * 10**9)
        w.finish()
    bag = read_bag(path)
    assert [f["seq"] for _, _, f in bag.topics["odometer"]] == list(range(5))
    assert "/train/thing" in bag.skipped
    s = check_bag.check(str(path))
    assert s["topics"]["odometer"]["received_fraction"] == 1.0
    json.dumps(s, default=float)


def test_line_reports_errors_by_position(bag_with_estimate, tmp_path, capsys):
    """--line makes a difference: errors by section, at each station stop, around balises."""
    from train_core.model import load_line

    bag, res = bag_with_estimate
    sc = load_scenario("metro_demo")
    s = check_bag.check(str(bag), tmp_path, line=load_line(sc.line_path))
    bp = s["by_position"]["fake"]
    a_b = bp["sections"][0]
    assert (a_b["from"], a_b["to"]) == ("A", "B") and a_b["n"] > 300  # running from 10 s
    n = a_b["n"]
    assert abs(a_b["position_rmse"] - SIGMA_X) < 4.5 * SIGMA_X * math.sqrt(1 / (2 * n))
    assert [st["station"] for st in bp["stops"]] == ["A"]  # the 60 s run waits at A only
    passed = [b for b in sc.line.balises
              if sc.start_position < b.position < res.truth["position"][-1]]
    assert len(bp["balises"]) == len(passed) > 0
    assert (tmp_path / "error_over_position.png").stat().st_size > 10_000
    assert check_bag.main([str(bag), "--no-plots"]) == 0
    without = capsys.readouterr().out
    assert check_bag.main([str(bag), "--no-plots", "--line", str(sc.line_path)]) == 0
    with_line = capsys.readouterr().out
    assert "errors by position" not in without
    assert "errors by position on line metro_demo" in with_line and "A -> B" in with_line


def test_latency_is_labelled_and_converted_to_wall_time(bag_with_estimate, capsys):
    bag, _ = bag_with_estimate
    assert check_bag.main([str(bag), "--no-plots"]) == 0
    out = capsys.readouterr().out
    assert "latency p50/p99 (ms, bag time)" in out and " 2.0/2.0" in out
    assert check_bag.main([str(bag), "--no-plots", "--rate-factor", "20"]) == 0
    out = capsys.readouterr().out
    assert "latency p50/p99 (ms, wall)" in out and " 0.1/0.1" in out and "/ 20 = wall" in out
    assert check_bag.main([str(bag), "--no-plots", "--rate-factor", "0"]) == 2


def test_plot_bands_are_clipped_and_startup_is_separated():
    from train_estimation.tools.bag_plots import F_RANGE, band, startup_end

    t = np.arange(0.0, 100.0, 0.1)
    cov = np.zeros((t.size, 4, 4))
    cov[:, 0, 0] = (0.2 + 5.0 * np.exp(-t)) ** 2  # 5 m at start, 0.2 m after a few seconds
    cov[:, 3, 3] = 0.3**2
    s = {"stamp": t, "cov": cov, "braking_rate": np.where(t < 50, 0.5, 1.9), "x": t, "xt": t,
         "v": t, "vt": t}
    f, lo, hi = band(s, "braking_rate")
    assert lo.min() == F_RANGE[0] and hi.max() == F_RANGE[1]  # 0.5 - 0.9 and 1.9 + 0.9
    assert np.all(lo <= f) and np.all(f <= hi)
    t_ss = startup_end({"e": s}, 0.0, 100.0)
    sx = np.sqrt(cov[:, 0, 0])
    assert np.all(sx[t >= t_ss] <= 2 * np.median(sx)) and t_ss < 25.0


def test_not_estimated_nan_is_not_non_finite(bag_with_estimate, tmp_path):
    """NaN acceleration, braking_rate and covariance entries of a TrainState mean "not
    estimated" (docs/interfaces.md): not counted; a NaN position or an infinite entry is."""
    bag, _ = bag_with_estimate
    s = check_bag.check(str(bag), tmp_path / "a", expected_received=0.875)
    est = s["topics"]["estimate/robust"]
    assert est["count"] > 100 and est["non_finite"] == 0
    fields = read_bag(bag).topics["estimate/robust"][0][2]
    out = tmp_path / "bad"
    cov = np.full(16, math.nan)
    cov[5] = math.inf
    bad = [dict(fields, position=math.nan), dict(fields, covariance=cov),
           dict(fields, braking_rate=math.inf), dict(fields, acceleration=-math.inf),
           dict(fields, braking_rate=math.nan), dict(fields, acceleration=math.nan)]
    with BagWriter(out) as w:
        for i, f in enumerate(bad):
            w.write("estimate/robust", 1.0 + i, f)
        w.write("odometer", 5.0, {"seq": 1, "distance": math.nan, "speed": 1.0,
                                   "speed_variance": 0.01})
    b = read_bag(out)
    assert check_bag.topic_health(b, "estimate/robust")["non_finite"] == 4
    assert check_bag.topic_health(b, "odometer")["non_finite"] == 1


def test_the_shipped_bag_of_the_live_nodes_has_no_non_finite_value():
    """The reference bag recorded from the live nodes: the robust filter publishes NaN
    acceleration and braking rate by design (not estimated); nothing in it is non-finite."""
    b = read_bag(REPO / "bags" / "metro_demo_short")
    robust = [f for _, _, f in b.topics["estimate/robust"]]
    assert robust and all(math.isnan(f["acceleration"]) for f in robust)  # what is exempted
    for topic in b.topics:
        h = check_bag.topic_health(b, topic)
        assert h["count"] > 0 and h["non_finite"] == 0, (topic, h)


# --- a bag without the measured data's topics, or never closed ------------------------------

def _inputs_bag(path, topics=("odometer", "balise", "control"), n=30, killed=False):
    """A small bag with the given input topics; ``killed``: as ``kill -9`` leaves it after a
    flush that held the commands and balises only (the odometer's chunk never written)."""
    import shutil

    w = BagWriter(path)
    for i in range(n):
        t = 100.0 + 0.1 * i
        if "control" in topics:
            w.write("control", t, {"target_acceleration": 0.3})
        if "balise" in topics and i % 10 == 0:
            w.write("balise", t, {"seq": i // 10, "balise_id": 1, "position": 10.0 * i,
                                  "position_variance": 1.0})
    if killed:
        w.flush()
        snap = path.parent / (path.name + ".snap")
        shutil.copytree(path, snap)
    for i in range(n):
        if "odometer" in topics:
            w.write("odometer", 100.0 + 0.1 * i, {"seq": i, "distance": 1.0 * i, "speed": 10.0,
                                                   "speed_variance": 0.01})
    w.close()
    if killed:
        shutil.rmtree(path)
        snap.rename(path)
    return path


@pytest.mark.parametrize("missing", ["odometer", "balise", "control", "odometer,control"])
def test_a_missing_input_topic_is_named_and_exits_2_unless_allowed(tmp_path, capsys, missing):
    keep = [t for t in ("odometer", "balise", "control") if t not in missing.split(",")]
    bag = _inputs_bag(tmp_path / "bag", keep)
    assert check_bag.main([str(bag), "--no-plots"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("check_bag:"), err
    assert f"no {' and no '.join(missing.split(','))} messages" in err[0], err
    assert f"--allow-missing {missing}" in err[0], err
    assert check_bag.main([str(bag), "--no-plots", "--allow-missing", missing]) == 0
    assert check_bag.main(["--bag", str(bag), "--no-plots", "--allow-missing", missing]) == 0
    assert check_bag.main([str(bag), "--no-plots", "--allow-missing", "gps"]) == 2


def test_the_bag_as_an_option_and_once(tmp_path, capsys):
    bag = _inputs_bag(tmp_path / "bag")
    assert check_bag.main(["--bag", str(bag), "--no-plots"]) == 0
    assert "odometer" in capsys.readouterr().out
    with pytest.raises(SystemExit) as exc:
        check_bag.main([str(bag), "--bag", str(bag)])
    assert exc.value.code == 2
    with pytest.raises(SystemExit):
        check_bag.main(["--no-plots"])


def test_a_truncated_bag_is_named_with_its_repair_by_every_tool(tmp_path, capsys):
    """The recorder was killed before the odometer's chunk reached the disk: check_bag, identify
    and diagnose all say the bag was not closed and how to repair it, not only what is
    missing."""
    from train_estimation.tools import diagnose, identify

    bag = _inputs_bag(tmp_path / "bag", killed=True)
    cfg = REPO / "ros_ws" / "src" / "train_core" / "config"
    files = ["--line", str(cfg / "lines" / "metro_demo.yaml"),
             "--train", str(cfg / "trains" / "metro_b6.yaml")]
    runs = {"check_bag": lambda: check_bag.main([str(bag), "--no-plots"]),
            "identify": lambda: identify.main(["--bag", str(bag), *files, "--quiet",
                                               "--out", str(tmp_path / "t.yaml")]),
            "diagnose": lambda: diagnose.main(["--bag", str(bag), *files, "--quiet",
                                               "--out", str(tmp_path / "diag")])}
    for tool, run in runs.items():
        assert run() == 2, tool
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"{tool}:"), err
        assert "no odometer" in err[0], err
        assert "bag was not closed" in err[0], err
        assert f"python -m train_core.bagio repair {bag}" in err[0], err


def test_a_counter_that_wraps_or_restarts_is_read_by_its_runs(tmp_path):
    """The received fraction from the sample counter, per run of it: unwrapped past 2^32 - 1
    (a wrap lost nothing: it read 1.4e-7 on a lossless bag), and restarted where the counter
    goes back while the stamps go on (both runs' seqs over one span, a fifth of the samples
    lost read as none); a reading the link delivered late is neither."""
    from train_estimation.core.offline.measured import counter_gaps, counter_runs

    def write(path, seqs):
        with BagWriter(path) as w:
            for k, q in enumerate(seqs):
                if q is not None:
                    w.write("odometer", 100.0 + 0.1 * k, {"seq": q, "distance": float(k),
                                                          "speed": 10.0, "speed_variance": 0.01})
        return check_bag.check(str(path))["topics"]["odometer"]

    wrap = [(2 ** 32 - 300 + k) % 2 ** 32 for k in range(600)]
    odo = write(tmp_path / "wrap", wrap)
    assert odo["received_fraction"] == 1.0 and odo["seq_span"] == 600 and odo["seq_gaps"] == 0
    # every fifth sample lost, the counter from 0 again halfway through
    lost = [None if k % 5 == 4 else (k if k < 300 else k - 300) for k in range(600)]
    odo = write(tmp_path / "restart", lost)
    assert odo["seq_restarts"] == 1 and odo["seq_span"] == 598 and odo["seq_gaps"] == 118
    assert odo["received_fraction"] == 480 / 598
    # a late reading (its seq and stamp behind the highest) is no restart; a run's own late
    # reading after the restart goes to its run
    q, runs = counter_runs([5, 6, 8, 7, 9, 0, 4, 1], [0.5, 0.6, 0.8, 0.7, 0.9, 1.0, 0.4, 1.1])
    assert list(runs) == [0, 0, 0, 0, 0, 1, 0, 1]
    assert counter_gaps(q, runs) == [(6, 6, 0), (2, 2, 0)]


def test_a_foreign_topic_with_a_contract_name_does_not_move_the_namespace(tmp_path, capsys):
    """A vehicle's own /vehicle/odometer (std_msgs/String) written before /train/*: the
    namespace is the one whose topics carry the contract's types."""
    from train_core.bagio import typestore

    ts, s = typestore(), "std_msgs/msg/String"
    with BagWriter(tmp_path / "bag") as w:
        w.write_raw("/vehicle/odometer", s, 10**9, bytes(ts.serialize_cdr(ts.types[s](data="x"),
                                                                         s)))
        for i in range(50):
            t = 1.0 + 0.1 * i
            w.write("odometer", t, {"seq": i + 1, "distance": 1.0 * i, "speed": 10.0,
                                    "speed_variance": 0.01})
            w.write("control", t, {"target_acceleration": 0.1})
            if i % 10 == 0:
                w.write("balise", t, {"seq": i // 10 + 1, "balise_id": 1, "position": 100.0,
                                      "position_variance": 1.0})
    bag = read_bag(tmp_path / "bag")
    assert bag.namespace == "/train" and len(bag.topics["odometer"]) == 50
    assert check_bag.main([str(tmp_path / "bag"), "--no-plots"]) == 0
    assert "not checked: /vehicle/odometer (std_msgs/String)" in capsys.readouterr().out
