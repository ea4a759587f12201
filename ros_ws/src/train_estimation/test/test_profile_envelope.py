"""The delay profiles' vertex and standard error (``causes.drive.envelope``)."""

import math

import numpy as np
import pytest

from train_estimation.core.offline.diagnose.causes.drive import envelope, parabola


def _quadratic(x, x0, se):
    return -0.5 * ((x - x0) / se) ** 2


def test_a_quadratic_profile_gives_the_three_point_parabola():
    xs = np.arange(0.0, 1.5, 0.025)
    ll = _quadratic(xs, 0.4613, 0.05)
    i = int(np.argmax(ll))
    v, se = envelope(xs, ll, i)
    v3, se3 = parabola(xs, ll, i)
    assert v == pytest.approx(0.4613, abs=1e-9) and v3 == pytest.approx(0.4613, abs=1e-9)
    assert se == pytest.approx(0.05, rel=1e-9) and se3 == pytest.approx(0.05, rel=1e-9)


def test_a_rough_profile_gives_its_envelope_not_its_local_curvature():
    # a quadratic of SE 0.04 with a ripple 2 units deep every 0.1 s (a delay passing the
    # instants of commands and readings), sampled on the 0.025 s grid of the delay causes
    xs = np.arange(0.0, 1.5, 0.025)
    ll = _quadratic(xs, 0.47, 0.04) + 1.0 * np.cos(2 * math.pi * (xs - 0.45) / 0.1)
    i = int(np.argmax(ll))
    v, se = envelope(xs, ll, i)
    _, se3 = parabola(xs, ll, i)
    assert se == pytest.approx(0.04, rel=0.25)
    assert se3 < 0.5 * 0.04  # the ripple's curvature: half the envelope's SE or less
    assert abs(v - 0.47) < 0.04


def test_few_points_or_the_grid_end_fall_back_to_three_points():
    xs = np.arange(0.0, 1.0, 0.025)
    ll = _quadratic(xs, 0.05, 0.2)  # the window reaches the grid's start
    i = int(np.argmax(ll))
    assert envelope(xs, ll, i) == parabola(xs, ll, i)
    ll = _quadratic(xs, 0.5, 0.005)  # a peak narrower than the grid: three points above -8
    i = int(np.argmax(ll))
    assert envelope(xs, ll, i) == parabola(xs, ll, i)
