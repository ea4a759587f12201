"""nav_msgs/Odometry covariances from an estimate's 4x4 (REP-103: unknown = large, never NaN)."""

import math

import numpy as np
import pytest

from train_estimation.core.online.odometry import UNKNOWN_VARIANCE, odometry_covariances


def test_position_and_speed_variances_go_to_x_and_the_rest_is_unknown():
    cov = np.diag([0.25, 0.01, 0.3, 0.02]).ravel()
    cov[1] = cov[4] = 0.04  # position-velocity correlation: not expressible in Odometry
    pose, twist = odometry_covariances(list(cov))
    p, t = np.reshape(pose, (6, 6)), np.reshape(twist, (6, 6))
    assert p[0, 0] == 0.25 and t[0, 0] == 0.01
    for m in (p, t):
        assert np.all(np.diag(m)[1:] == UNKNOWN_VARIANCE)
        assert np.all(m[~np.eye(6, dtype=bool)] == 0.0)
        assert np.all(np.linalg.eigvalsh(m) > 0)  # a valid covariance for any consumer


@pytest.mark.parametrize("bad", [math.nan, math.inf, -1.0, 0.0])
def test_not_estimated_or_invalid_variances_are_unknown_never_nan(bad):
    cov = [math.nan] * 16
    cov[0], cov[5] = bad, 0.04
    pose, twist = odometry_covariances(cov)
    assert pose[0] == UNKNOWN_VARIANCE and twist[0] == 0.04
    assert all(math.isfinite(v) for v in pose + twist)


def test_wrong_size_is_an_error():
    with pytest.raises(ValueError, match="16"):
        odometry_covariances([0.0] * 4)


def test_the_position_variance_overbounds_the_protection_levels():
    """K sd at the stated risk reach the larger protection level (never below the estimator's
    own variance); ALARM (levels +inf) is unknown."""
    from statistics import NormalDist

    cov = list(np.diag([0.25, 0.01, 0.3, 0.02]).ravel())
    k = NormalDist().inv_cdf(1.0 - 1e-7 / 2.0)
    pose, _ = odometry_covariances(cov, (12.0, 20.0, 1e-7))
    assert math.isclose(k * math.sqrt(pose[0]), 20.0, rel_tol=1e-12)
    assert odometry_covariances(cov, (1.0, 2.0, 1e-7))[0][0] == 0.25  # its own is wider
    assert odometry_covariances(cov, (math.inf, math.inf, 1e-7))[0][0] == UNKNOWN_VARIANCE
