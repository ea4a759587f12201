"""The integrity campaign's zone controller in the loop (benchmarks/bench_integrity.zone_in_loop):
a run's estimates as a leader's reports, the follower's authority against the leader's true
rear."""

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_integrity as B  # noqa: E402

from train_estimation.core.online.runner import Output  # noqa: E402
from train_estimation.tools import faults as F  # noqa: E402

COV = tuple((np.eye(4) * 0.01).ravel())


def leader(offset: float, behind: float, integrity: int = 0, n: int = 300, speed: float = 10.0,
           start: float = 200.0, dwell: float = 0.0):
    """A leader at ``start`` + 10 t m (standing there for the first ``dwell`` s) reported at
    10 Hz ``offset`` m from the truth with the level ``behind`` (and 5 m ahead), at the speed
    ``speed`` (sd 0.1 m/s); the truth and the emission times."""
    t = 0.1 * np.arange(n)
    x = start + 10.0 * np.maximum(t - dwell, 0.0)
    outs = [Output(F.EPOCH + s, xs + offset, speed, 0.0, math.nan, COV, True,
                   integrity=integrity, protection_level_ahead=5.0 if integrity < 2 else math.inf,
                   protection_level_behind=behind if integrity < 2 else math.inf)
            for s, xs in zip(t, x)]
    truth = {"t": t, "position": x, "velocity": np.full(t.size, 10.0)}
    return outs, F.EPOCH + t + 0.05, truth


def test_an_honest_leader_grants_no_authority_past_its_rear():
    outs, em, truth = leader(offset=3.0, behind=5.0)
    r = B.zone_in_loop(outs, em, truth)
    assert r["past_rear"] == 0 and r["granted"] == len(outs)


@pytest.mark.parametrize("start", [0.0, 0.5, 50.0])
def test_a_leader_starting_at_the_line_origin_is_still_ahead_of_the_follower(start):
    """A real line's first station is its origin: the leader stands at 0 m for its dwell, its
    rear 120 m before it. The follower still stands behind that rear (the leader's coordinates
    lifted), not ahead of the leader, where the zone takes it for the first train: the leader
    then passes it (refused, trains out of order), goes stale behind it, and every authority
    of the follower runs past the leader's rear."""
    outs, em, truth = leader(offset=0.0, behind=5.0, start=start, dwell=2.0)
    r = B.zone_in_loop(outs, em, truth)
    assert r["past_rear"] == 0 and r["granted"] == len(outs)
    outs, em, truth = leader(offset=3.0, behind=1.0, start=start, dwell=2.0)
    assert B.zone_in_loop(outs, em, truth)["past_rear"] == len(outs)


@pytest.mark.parametrize("behind", [1.0, 2.4])
def test_a_level_that_does_not_cover_the_error_grants_authority_past_the_rear(behind):
    """3 m ahead of the truth with a level behind of less than the 2.5 m that remain when the
    report is judged (published 0.05 s after its stamp, the train 0.5 m further on): the
    follower's end of authority (the leader's min safe rear, margin 0) lies past the true rear
    at every report."""
    outs, em, truth = leader(offset=3.0, behind=behind)
    r = B.zone_in_loop(outs, em, truth)
    assert r["granted"] == len(outs) and r["past_rear"] == len(outs)


def test_an_alarm_brakes_the_follower():
    outs, em, truth = leader(offset=30.0, behind=1.0, integrity=2)
    r = B.zone_in_loop(outs, em, truth)
    assert r["granted"] == 0 and r["past_rear"] == 0


def test_a_speed_stated_too_low_stops_short_of_the_truth():
    """The leader's own supervision: its worst-case stopping point (max safe front, carried to
    the present, plus the stop from the speed + K sigma at 1.2 m/s^2) against the true one
    (the true front plus 41.7 m from 10 m/s). Stated at 10 m/s with a sigma of 0.1 m/s: 5 m of
    level and 46.2 m of stop, beyond it. Stated at 8 m/s: 8.53 m/s, 30.3 m of stop, 6 m short
    of the truth once the level's 5 m are added."""
    outs, em, truth = leader(offset=0.0, behind=5.0)
    assert B.zone_in_loop(outs, em, truth)["stop_short"] == 0
    outs, em, truth = leader(offset=0.0, behind=5.0, speed=8.0)
    assert B.zone_in_loop(outs, em, truth)["stop_short"] == len(outs)
