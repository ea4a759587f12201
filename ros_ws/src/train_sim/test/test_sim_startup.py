"""Start-up under a zone controller: braked until the first authority, whenever it arrives."""

import math

import numpy as np
import pytest

from train_sim.scenario import load_scenario
from train_sim.world import World

LINE_END = 6980.0  # m, an authority that restricts nothing on metro_demo


def _run(release_at: list[float], duration: float = 60.0) -> World:
    """metro_demo started braked (no authority) and released at the given times, as the
    simulator node does with start_with_emergency_brake and a zone controller."""
    w = World(load_scenario("metro_demo"))
    w.set_movement_authority(-math.inf, 0.0, True)
    for t in release_at:
        w.advance(t)
        w.set_movement_authority(LINE_END, 22.23, False)
    w.advance(duration)
    return w


def test_release_time_during_the_dwell_changes_nothing():
    """However late the first authority arrives within the initial dwell (10 s), the train
    departs at the end of the dwell and every message is the same: what the live run does
    cannot depend on when a radio message happened to arrive."""
    runs = [_run([t]) for t in (0.35, 1.2, 4.75, 9.9)]
    ref = runs[0].result()
    ctl = ref.control["target_acceleration"]
    t = ref.control["t"]
    eb = load_scenario("metro_demo").train.performance.emergency_brake
    assert np.all(ctl[t < 10.0 - 1e-9] == -eb)  # braked for the whole dwell
    assert ctl[np.searchsorted(t, 10.0)] > 0.0  # departs on time
    for w in runs[1:]:
        r = w.result()
        for topic in ("truth", "odometer", "balise", "control"):
            a, b = getattr(ref, topic), getattr(r, topic)
            assert all(np.array_equal(a[k], b[k], equal_nan=a[k].dtype.kind == "f")
                       for k in a), topic
    for w in runs:
        assert (w.driver.emergency_brakes, w.driver.startup_emergency_brakes) == (1, 1)


def test_zone_controllers_own_startup_brake_is_not_an_incident():
    """The controller's 'no estimate received yet' brake before its first authority is the
    same start-up state: no new rising edge, no incident."""
    w = World(load_scenario("metro_demo"))
    w.set_movement_authority(-math.inf, 0.0, True)
    w.advance(1.0)
    w.set_movement_authority(-math.inf, 0.0, True)  # the controller: no report yet
    w.advance(2.0)
    w.set_movement_authority(LINE_END, 22.23, False)
    w.advance(30.0)
    assert (w.driver.emergency_brakes, w.driver.startup_emergency_brakes) == (1, 1)
    assert w.state.v > 0.0


def test_brake_after_an_authority_is_an_incident_and_late_release_departs_late():
    w = _run([2.0], duration=60.0)
    assert w.state.v > 5.0
    w.set_movement_authority(LINE_END, 22.23, True)  # e.g. stale estimates
    w.advance(120.0)
    assert w.state.v == 0.0
    assert (w.driver.emergency_brakes, w.driver.startup_emergency_brakes) == (2, 1)
    # released away from a dwell: applied no longer than the flag is set
    w.set_movement_authority(LINE_END, 22.23, False)
    w.advance(140.0)
    assert w.state.v > 0.0
    # a first authority after the dwell: the train departs when it arrives, not before
    def first_motion(r):
        return r.truth["t"][r.truth["velocity"] > 0][0]

    on_time = first_motion(_run([2.0], duration=30.0).result())  # departs at 10 s
    late = first_motion(_run([14.95], duration=30.0).result())  # next ATO cycle: 15 s
    assert late - 15.0 == pytest.approx(on_time - 10.0, abs=1e-9)


def test_ground_truth_covariance_is_nan():
    """docs/interfaces.md: covariance is NaN where not estimated; the truth estimates nothing."""
    w = World(load_scenario("metro_demo"))
    truth = [f for topic, _, f in w.advance(1.0) if topic == "ground_truth"]
    assert truth and all(len(f["covariance"]) == 16 and all(math.isnan(c)
                                                              for c in f["covariance"])
                         for f in truth)


@pytest.mark.parametrize("eoa,speed,why", [
    (math.nan, 22.23, "non_finite: end_of_authority is NaN"),
    (LINE_END, math.nan, "bad_speed: permitted_speed nan is not >= 0"),
    (LINE_END, -1.0, "bad_speed: permitted_speed -1.0 is not >= 0"),
])
def test_an_authority_that_says_nothing_is_refused_and_the_one_in_force_kept(eoa, speed, why):
    """One authority with a NaN end or speed stopped the train where it was, for good; refused
    with its reason, the run is the one without it. An emergency brake in such a message is
    still applied (the safe side), its end and speed not taken."""
    ref = _run([2.0], duration=60.0)
    w = World(load_scenario("metro_demo"))
    w.set_movement_authority(-math.inf, 0.0, True)
    w.advance(2.0)
    w.set_movement_authority(LINE_END, 22.23, False)
    w.advance(30.0)
    assert w.set_movement_authority(eoa, speed, False) == why
    w.advance(60.0)
    a, b = ref.result().truth, w.result().truth
    assert all(np.array_equal(a[k], b[k]) for k in a)
    assert w.set_movement_authority(eoa, speed, True) == why
    assert w.driver.emergency and w.driver.eoa == LINE_END
    assert w.set_movement_authority(math.inf, 22.23, False) == ""  # the open line
