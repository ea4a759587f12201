"""check_bag against bags whose errors are known by construction."""

import json
import math

import numpy as np
import pytest
from train_core.bagio import BagWriter, msgdef, read_bag

from train_estimation.tools import check_bag
from train_sim.generate import generate
from train_sim.scenario import load_scenario

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
