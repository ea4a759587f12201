"""The main job (`./run demo`): its report says what happened, and a run is reproducible."""

import sys
from pathlib import Path

import numpy as np
import pytest

from train_sim.bagio import read_bag

pytestmark = [pytest.mark.ros, pytest.mark.slow]

DURATION = 50.0  # s: the start-up (braked, initial dwell of 10 s), departure, a balise
SAME = ("ground_truth", "control", "odometer", "balise", "estimate/robust", "estimate/gsma")


def _demo(launch, out: Path) -> str:
    proc = launch.start([sys.executable, "-m", "train_estimation.tools.main_job",
                         "--duration", str(DURATION), "--out", str(out)], name=out.name)
    proc.wait(timeout=240)
    report = Path(proc.log_path).read_text()
    assert proc.returncode == 0, report
    return report


def test_demo_is_reproducible_and_its_report_explains_itself(launch, tmp_path):
    """Two runs of one scenario and seed give the same bag, message for message and bit for
    bit (only the zone controller's wall-timed authority stamps differ), whatever the load:
    the world starts braked, not when a first authority happens to arrive, and is paced by the
    estimates, so a stalled process cannot be judged stale in simulated time."""
    reports = [_demo(launch, tmp_path / name) for name in ("run1", "run2")]
    bags = [read_bag(tmp_path / name / "bag") for name in ("run1", "run2")]
    for topic in SAME:
        a, b = ([(s, f) for _, s, f in bag.topics[topic]] for bag in bags)
        assert len(a) == len(b) > 0, topic
        for (sa, fa), (sb, fb) in zip(a, b):
            assert sa == sb and fa.keys() == fb.keys(), (topic, sa, sb)
            assert all(np.array_equal(fa[k], fb[k], equal_nan=not isinstance(fa[k], str))
                       for k in fa), (topic, sa, fa, fb)
    for bag in bags:  # every sample has its estimate: none lost at the start or at the end
        assert len(bag.topics["estimate/gsma"]) == len(bag.topics["ground_truth"])
        assert len(bag.topics["estimate/robust"]) == len(bag.topics["ground_truth"])
    for rep in reports:
        assert "emergency brakes: 0 during the run (incidents)" in rep
        assert "start-up: the train starts braked until the zone controller's first" in rep
        assert "latency p50/p99 (ms, wall)" in rep and "/ 20 = wall time" in rep
        assert "errors by position on line metro_demo" in rep
    check = tmp_path / "run1" / "check"
    assert (check / "estimates_vs_truth.png").stat().st_size > 10_000
    assert (check / "error_over_position.png").stat().st_size > 10_000
