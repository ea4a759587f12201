"""The odometer's calibration against the balises (pure): where its count puts the train, and
how sure that is.

A wheel odometer counts wheel turns: its distance ``d`` and speed are the true ones times a
scale that a worn or mis-set wheel diameter puts 1-3 % off, and nothing between two balises
sees it. A filter that reads ``start + d`` as a position with a fixed variance of a metre is
then sure of a position that drifts by 1-2 % of the distance run: 20 m after a kilometre, with a
sigma under a metre (a wrong-side estimate). The error is one number for the whole run, not
noise, so fusing ten readings a second does not average it away; it has to be a state.

This module carries it as one. The odometer's count maps to the position along the track as::

    x = x0 + c d                     (x0: the odometer's origin, m; c: true / counted, -)
    v = c v_odo                      (the speed, by the same wheel)

with ``theta = (x0, c)`` Gaussian, ``N((start, 1), diag(start_std^2, scale_std^2))`` at start.
A balise read at position ``b`` when the odometer had counted ``d_b`` is the linear measurement
``b = x0 + c d_b + e``, ``e ~ N(0, r_b + c^2 r_d)`` (``r_d``: the count at the balise's stamp,
carried from the last odometer reading), fused by the Kalman update of ``theta`` (exact: the
model is linear in ``theta`` given ``d_b``). Between balises ``theta`` walks with the distance
run: ``x0`` by :data:`COUNT_WALK` per metre (counts lost to slips too small to see), ``c`` by
:data:`SCALE_WALK` per metre (creep that changes with adhesion), with ``x0`` moving by ``-d``
times ``c``'s step so that a change of scale acts on the distance run after it only.

The estimators fuse the *mapped* readings ``x0^ + c^ d`` and ``c^ v_odo`` as if ``theta`` were
known (their covariance is then the error given the calibration), and the published
covariance adds what the calibration does not know (a Schmidt "consider" term)::

    [x; v] = [1, d; 0, v_odo] theta   ->   J Sigma_theta J^T,   J = [[1, d], [0, v_odo]]

When a balise moves ``theta``, the estimate is moved with the mapping (:meth:`shift_at`), so the
next reading continues it instead of looking like a jump the filter's gate refuses.

A balise more than ``gate`` standard deviations from where the calibration puts it is refused
and held: the odometer lost count (a slip or slide) or the balise is not where its telegram
says, and one reading cannot tell. When the next balise is also refused and the two agree with
each other (the same offset from the count, within what the scale allows between them), the
count is relocated onto them: ``x0``'s variance grows by the larger offset squared and both are
fused (:attr:`OdometerCalibration.relocated`, counted by the adapter as ``relocated``). A
balise is a surveyed reference and the count is not, but two agreeing balises are needed before
the count is moved by more than it claims.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

COUNT_WALK = 1.0e-3  # m^2 per m run: x0's random walk (1 m std after 1 km)
SCALE_WALK = 1.0e-9  # 1 per m run: c's random walk (0.001 std after 1 km)
A_MAX = 1.5  # m/s^2, acceleration allowed in carrying the count to a balise's stamp


@dataclass(frozen=True)
class BaliseFix:
    """A balise read against the count: ``position`` m (map), ``variance`` m^2 (the reading's
    and the count's at its stamp), ``distance`` m (the odometer's count at the stamp)."""

    position: float
    variance: float
    distance: float


class OdometerCalibration:
    """``theta = (x0 m, c -)`` and its covariance (module doc)."""

    def __init__(self, start: float, start_std: float, scale_std: float, gate: float = 8.0,
                 count_walk: float = COUNT_WALK, scale_walk: float = SCALE_WALK):
        if not (math.isfinite(start) and start_std > 0 and scale_std > 0 and gate > 0
                and count_walk >= 0 and scale_walk >= 0):
            raise ValueError("OdometerCalibration: start finite, start_std, scale_std and gate "
                             "> 0, walks >= 0")
        self.theta = np.array([float(start), 1.0])
        self.Sigma = np.diag([start_std ** 2, scale_std ** 2])
        self.gate = float(gate)
        self.count_walk, self.scale_walk = float(count_walk), float(scale_walk)
        self.d_walked = 0.0  # m, the count up to which the walk has been added
        self.held: BaliseFix | None = None  # a refused balise, until the next one judges it
        self.relocated = 0

    def copy(self) -> OdometerCalibration:
        c = object.__new__(OdometerCalibration)
        c.__dict__.update(self.__dict__)
        c.theta, c.Sigma = self.theta.copy(), self.Sigma.copy()
        return c

    # -- the mapping ------------------------------------------------------------------------
    def position(self, d: float) -> float:
        """m, where the count ``d`` puts the train."""
        return float(self.theta[0] + self.theta[1] * d)

    def speed(self, v_odo: float) -> float:
        """m/s, the speed a reading ``v_odo`` stands for."""
        return float(self.theta[1] * v_odo)

    def position_variance(self, d: float) -> float:
        """m^2, of :meth:`position` from the calibration alone."""
        h = np.array([1.0, d])
        return float(h @ self.Sigma @ h)

    def consider(self, d: float, v_odo: float) -> np.ndarray:
        """2x2 covariance of (position, speed) that the calibration adds to an estimate that
        follows the mapped readings at count ``d`` and speed reading ``v_odo``."""
        J = np.array([[1.0, d], [0.0, v_odo]])
        return J @ self.Sigma @ J.T

    # -- time (distance) update ---------------------------------------------------------------
    def walk_to(self, d: float) -> None:
        """Add the random walk of the distance run since the last call (module doc)."""
        if not math.isfinite(d):
            return
        run = abs(d - self.d_walked)
        # a change of scale here acts on the distance run from here on, not on the count so
        # far: c moves by w and x0 by -w d (the position at the count d stays put)
        g = np.array([-float(d), 1.0])
        self.Sigma = self.Sigma + np.diag([self.count_walk * run, 0.0]) \
            + self.scale_walk * run * np.outer(g, g)
        self.d_walked = float(d)

    # -- balises -----------------------------------------------------------------------------
    def _innovation(self, fix: BaliseFix) -> tuple[float, float]:
        h = np.array([1.0, fix.distance])
        return (fix.position - float(h @ self.theta),
                float(h @ self.Sigma @ h) + fix.variance)

    def _fuse(self, fix: BaliseFix) -> tuple[np.ndarray, np.ndarray]:
        """(change of theta, old theta): the Kalman update with one balise."""
        h = np.array([1.0, fix.distance])
        nu, s = self._innovation(fix)
        k = self.Sigma @ h / s
        old = self.theta.copy()
        self.theta = self.theta + k * nu
        # Joseph form: Sigma stays symmetric positive definite for any gain
        ikh = np.eye(2) - np.outer(k, h)
        self.Sigma = ikh @ self.Sigma @ ikh.T + fix.variance * np.outer(k, k)
        return self.theta - old, old

    def balise(self, fix: BaliseFix) -> bool:
        """Fuse one balise (True), or refuse and hold it (False); module doc."""
        if not (math.isfinite(fix.position) and math.isfinite(fix.distance)
                and math.isfinite(fix.variance) and fix.variance > 0):
            return False
        self.walk_to(fix.distance)
        nu, s = self._innovation(fix)
        if abs(nu) <= self.gate * math.sqrt(s):
            self._fuse(fix)
            self.held = None
            return True
        held, self.held = self.held, fix
        if held is None:
            return False
        nu0, _ = self._innovation(held)
        gap = abs(fix.distance - held.distance)
        agree = held.variance + fix.variance + self.Sigma[1, 1] * gap * gap \
            + self.count_walk * gap
        if abs(nu - nu0) > self.gate * math.sqrt(agree):
            return False
        # two balises that agree with each other and not with the count: the count moved
        self.Sigma[0, 0] += max(nu * nu, nu0 * nu0)
        self._fuse(held)
        self._fuse(fix)
        self.held = None
        self.relocated += 1
        return True
