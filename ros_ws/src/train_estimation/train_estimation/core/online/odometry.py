"""An estimate as ``nav_msgs/Odometry`` covariances (REP-103/REP-105 conventions; pure).

The estimate lives on one axis: x is the position along the track from the line's origin
(``header.frame_id = "track"``, world-fixed), and the train's body axis (``child_frame_id =
"base_link"``, x forward in the running direction) moves along it, so the twist's ``linear.x``
is the speed. Both covariances are row-major 6x6 over (x, y, z, rotation about x, y, z).

What the estimator does not estimate (y, z, the three rotations, and anything it reports as
NaN) gets :data:`UNKNOWN_VARIANCE` on the diagonal and zero correlation: the convention of
robot_localization and the ROS drivers for "not measured" is a very large variance, never NaN
(NaN poisons every consumer's fusion). The position-velocity correlation cannot be carried:
Odometry keeps pose and twist apart (TrainState's covariance has it).

Odometry has no field for the protection levels, and a consumer that reads only Odometry bounds
the position with its variance. So the position variance is an *overbound* of them: at least
``(PL / K)^2``, ``PL`` the larger level and ``K = Phi^-1(1 - risk / 2)`` at the estimator's
integrity risk, so that ``K`` standard deviations at the stated risk reach the protection level
(5.33 sd at 1e-7); an estimate in ALARM (levels +inf) has :data:`UNKNOWN_VARIANCE`. A consumer
that fuses the variance as a Gaussian (robot_localization) is then conservative, never
overconfident, and the TrainState keeps the estimator's own covariance.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from .protection import k_factor

UNKNOWN_VARIANCE = 1.0e6  # m^2, (m/s)^2 or rad^2: "not estimated" (the ROS drivers' value)


def _variance(v: float) -> float:
    v = float(v)
    return v if math.isfinite(v) and v > 0 else UNKNOWN_VARIANCE


def odometry_covariances(covariance: Sequence[float], protection: tuple | None = None
                         ) -> tuple[list[float], list[float]]:
    """(pose 6x6, twist 6x6), row-major, from TrainState's 4x4 over (position, velocity,
    acceleration, braking rate): position variance at pose[0], velocity variance at twist[0];
    every other diagonal entry :data:`UNKNOWN_VARIANCE`, off-diagonals 0. A variance that is
    NaN, infinite or not positive (not estimated, or not to be trusted) is also unknown.
    ``protection``: ``(ahead m, behind m, integrity risk)``; the position variance is then at
    least the protection levels' overbound (module doc)."""
    if len(covariance) != 16:
        raise ValueError(f"covariance: expected 16 values (4x4), got {len(covariance)}")
    pose = [0.0] * 36
    twist = [0.0] * 36
    for i in range(6):
        pose[7 * i] = twist[7 * i] = UNKNOWN_VARIANCE
    pose[0] = _variance(covariance[0])
    twist[0] = _variance(covariance[5])
    if protection is not None:
        ahead, behind, risk = (float(v) for v in protection)
        level = max(ahead, behind)
        if not math.isfinite(level):  # ALARM: nothing bounds it
            pose[0] = UNKNOWN_VARIANCE
        elif level > 0.0 and 0.0 < risk < 1.0:
            k = k_factor(risk)
            pose[0] = min(UNKNOWN_VARIANCE, max(pose[0], (level / k) ** 2))
    return pose, twist
