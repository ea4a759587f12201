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

with ``theta = (x0, c)`` Gaussian, ``N((start, c0), diag(start_std^2, scale_std^2))`` at start
(``c0`` = 1, or the calibration an earlier run or the workshop found: the estimators'
``odometer_scale`` parameter, which is the reading over the true distance as ``diagnose``
reports it, so ``c0 = 1 / odometer_scale``).
A balise read at position ``b`` when the odometer had counted ``d_b`` is the linear measurement
``b = x0 + c d_b + e``, ``e ~ N(0, r_b + c^2 r_d)`` (``r_d``: the count at the balise's stamp,
carried from the last odometer reading), fused by the Kalman update of ``theta`` (exact: the
model is linear in ``theta`` given ``d_b``). Between balises ``theta`` walks with the distance
run: ``x0`` by :data:`COUNT_WALK` per metre (counts lost to slips too small to see), ``c`` by
:data:`SCALE_WALK` per metre (creep that changes with adhesion), with ``x0`` moving by ``-s``
times a step of ``c`` at the count ``s``, so that a change of scale acts on the distance run
after it only (integrated along the count: :func:`_walked`).

The estimators fuse the *mapped* readings ``x0^ + c^ d`` and ``c^ v_odo`` as if ``theta`` were
known (their covariance is then the error given the calibration), and the published
covariance adds what the calibration does not know (a Schmidt "consider" term)::

    [x; v] = [1, d; 0, v_odo] theta   ->   J Sigma_theta J^T,   J = [[1, d], [0, v_odo]]

When a balise moves ``theta``, the estimate is moved with the mapping (:meth:`shift_at`), so the
next reading continues it instead of looking like a jump the filter's gate refuses.

An odometer that reboots begins its count again from 0; the adapters splice the new count onto
the old one where their prediction puts the train
(``calibrated_odometry.DistanceAsPosition._restart``), and the prediction's variance enters
here as a concentrated walk of ``x0`` at the count of the splice
(:meth:`OdometerCalibration.splice`).

A balise reader can stamp late: a reading stamped when the telegram was decoded, not when the
antenna passed the balise's centre, says the train was at ``b`` at a time ``tau`` after it was.
The train is then ``v tau`` further on than the reading says (25 m at 50 m/s and 0.5 s), one
error per reading that grows with speed and that no number of readings averages away. The
calibration carries ``tau`` as a third parameter, ``theta = (x0, c, tau)``, with the prior
``N(0, latency_std^2)``: the balise read at the count ``d_b`` and counted speed ``v_b`` is::

    b = x0 + c (d_b - v_b tau) + e

linearised about the estimate (an extended Kalman update: ``h = [1, d_b - v_b tau^,
-c^ v_b]``; the product ``c tau`` is the only non-linearity, and a scale 1 % off changes the
latency's term by 1 %). Balises read at different speeds tell ``tau`` from ``x0``; balises read
at one speed cannot, and the prior is then what bounds it (``latency_std`` = 0: the reader is
trusted to stamp on time, and ``tau`` stays 0).

A reader far out of its prior (a second late where 0.1 s was assumed) is not learnt by the
calibration: its fixes lie many prior deviations off, the gate refuses them and two that agree
relocate the count onto them, late. So a second calibration runs beside it on the same fixes
with a wide prior (:data:`LATENCY_WIDE`), and :func:`latency_beyond_prior` tests the latency it
finds against the narrow prior: under the narrow prior the wide solution's ``tau^`` is
``N(0, latency_std^2 + sd_w^2)`` (``sd_w``: its own posterior sd), and beyond
:data:`LATENCY_Z` of that the reader is out of its prior and the wide calibration replaces the
narrow one (the adapters' event ``balise_latency``). The wide one is a valid model whatever
the reader's latency, only less sure: the test costs nothing but width when it is wrong.

A balise can lie: a survey error puts it metres from where its telegram says, and while the
scale is still uncertain (the first balises, or far from the last) it is fused like any other and
moves the calibration. Nothing tells until later balises disagree with it, so the published
covariance also covers the solution without each of the last three balises (solution
separation, as receiver autonomous integrity monitoring does for satellites:
:meth:`OdometerCalibration.consider`).

The start itself can be wrong: a position keyed in, or stored from the last mission before the
train was shunted, is not the train's until a balise confirms it (ETCS calls such a position
"unknown" and runs on sight until the first balise group). ``start_std`` is the start's
fault-free doubt; a start fault up to ``start_fault`` m beyond it (a bias bound, as ARAIM's
``b_nom``) is a hypothesis the solutions carry: before the first balise, the train at either end
of that bias; from the first balise on, the solution with no start at all (``x0`` uninformative,
fused with every balise the calibration fuses: :attr:`OdometerCalibration.free`), which agrees
with the main solution when the start was right and lies where the balises alone put the train
when it was not. The two are judged by Wald's sequential probability-ratio test on every balise
(the log of each one's predictive density of it, summed; :data:`EXCLUSION_RISK`): a start that
the balises contradict is excluded and the free solution becomes the calibration (event
``start_excluded``), one they confirm drops the free solution. A start that agrees within the
first balise's doubt is neither: the free solution is carried on, at little cost, since the two
then agree.

A balise more than ``gate`` standard deviations from where the calibration puts it is refused
and held: the odometer lost count (a slip or slide), its calibration went wrong, or the balise
is not where its telegram says, and one reading cannot tell. When the next balise is also
refused and the two agree with each other (their distance apart is what the count ran between
them at a scale the odometer can have), the count is found again from them: ``x0`` free, the
scale at its estimate with at least its prior's doubt, both fused
(:attr:`OdometerCalibration.relocated`, counted by the adapter as ``relocated``). A
balise is a surveyed reference and the count is not, but two agreeing balises are needed before
the count is moved by more than it claims. Before that, balises that fit the solution without
one of the recent balises, and with which that balise no longer fits, show that one to be the
liar: it is taken out (fault exclusion, event ``balise_excluded``): a refused balise (with the one
held before it, if any), or after each fusion any recent balise outside the gate of the
solution of two or more others without it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

COUNT_WALK = 1.0e-3  # m^2 per m run: x0's random walk (1 m std after 1 km)
SCALE_WALK = 1.0e-9  # 1 per m run: c's random walk (0.001 std after 1 km)
A_MAX = 1.5  # m/s^2, acceleration allowed in carrying the count to a balise's stamp
EXCLUDE = 2.0  # gates: a fused balise is taken out only this far outside the others' solution
#   (a noisy good balise next to a lying one must not be the one excluded)
RELOCATE_X0_VAR = 1.0e6  # m^2, x0's variance when the count is found again from two balises
LATENCY_WIDE = 2.0  # s, the latency prior of the calibration that checks the reader's (module
#   doc): a reader that stamps seconds late is not a reader that works
LATENCY_Z = 4.0  # sds of the narrow prior and the wide solution's own beyond which the reader
#   is taken to be out of its prior (tested after every balise: a strict threshold)
EXCLUSION_RISK = 1e-7  # probability that a sequential likelihood-ratio test between two
#   calibrations ever excludes the true one (Wald's bound: it stops at a ratio of 1 / this)
LATENCY_MIN_BALISES = 2  # the wide solution's balises before its latency is tested (two read
#   at different speeds tell the latency from the origin; the start's prior is the third datum)


@dataclass(frozen=True)
class BaliseFix:
    """A balise read against the count: ``position`` m (map), ``variance`` m^2 (the reading's
    and the count's at its stamp), ``distance`` m (the odometer's count at the stamp),
    ``speed`` m/s (the odometer's counted speed at the stamp: what a late stamp costs)."""

    position: float
    variance: float
    distance: float
    speed: float = 0.0


def _nanmax(a: float, b: float) -> float:
    """``np.maximum`` of two floats: the larger, NaN if either is."""
    return a if a >= b or a != a else b


def _walked(Sigma: np.ndarray, d0: float, d1: float, count_walk: float,
            scale_walk: float, jumps: tuple = ()) -> np.ndarray:
    """``Sigma`` with the random walk of the count run from ``d0`` to ``d1`` added (module
    doc): ``x0`` by ``count_walk`` per metre; ``c`` by ``scale_walk`` per metre, a step ``w`` of
    ``c`` at the count ``s`` moving ``x0`` by ``-w s``, integrated over ``s`` (so any path
    between the same counts adds the same); and ``x0`` by the variance of each of ``jumps``
    ``(count m, variance m^2)`` run over (a count spliced after the odometer restarted:
    :meth:`OdometerCalibration.splice`)."""
    a, b = sorted((float(d0), float(d1)))
    run = b - a
    if not run > 0:
        return Sigma
    s1, s2, s3 = run, (b * b - a * a) / 2.0, (b ** 3 - a ** 3) / 3.0
    # count_walk run [[1, 0], [0, 0]] + scale_walk [[s3, -s2], [-s2, s1]], entry by entry on
    # floats (the same operations as on 2x2 arrays, so the same bits: this runs for every
    # solution at every estimate, and two tiny arrays cost more than the sums)
    k = count_walk * run
    w00, w01, w11 = k * 1.0 + scale_walk * s3, k * 0.0 + scale_walk * -s2, \
        k * 0.0 + scale_walk * s1
    out = Sigma.copy()  # the latency (third parameter) does not walk: it is the reader's
    out[0, 0] += w00
    out[0, 1] += w01
    out[1, 0] += w01
    out[1, 1] += w11
    if jumps:
        out[0, 0] += sum(var for at, var in jumps if a < at <= b)
    return out


@dataclass(frozen=True)
class _Solution:
    """``theta = (x0, c)``, its covariance and the count up to which the walk is in it."""

    theta: np.ndarray
    Sigma: np.ndarray
    d: float
    n: int = 0  # balises in it
    worst: float = 0.0  # a solution without a recent balise: the largest |innovation| / sd of
    #   the later balises as it took them (its own consistency, OdometerCalibration._without)


class OdometerCalibration:
    """``theta = (x0 m, c -, tau s)`` and its covariance (module doc), and the solutions without
    each of the last :attr:`EXCLUDED` balises (solution separation, :meth:`consider`)."""

    EXCLUDED = 3  # the latest balises each of which may be the one that lies

    def __init__(self, start: float, start_std: float, scale_std: float, gate: float = 8.0,
                 count_walk: float = COUNT_WALK, scale_walk: float = SCALE_WALK,
                 scale: float = 1.0, latency_std: float = 0.0, start_fault: float = 0.0):
        if not (math.isfinite(start) and start_std > 0 and scale_std > 0 and gate > 0
                and count_walk >= 0 and scale_walk >= 0 and math.isfinite(scale) and scale > 0
                and math.isfinite(latency_std) and latency_std >= 0
                and math.isfinite(start_fault) and start_fault >= 0):
            raise ValueError("OdometerCalibration: start finite, start_std, scale_std, gate and "
                             "scale > 0, walks, latency_std and start_fault >= 0")
        # c's prior mean: 1, or what an earlier run or the workshop found (true / counted);
        # tau's: 0, the reader stamps when it passes the balise
        self.theta = np.array([float(start), float(scale), 0.0])
        self.Sigma = np.diag([start_std ** 2, scale_std ** 2, latency_std ** 2])
        self.scale_std = float(scale_std)
        self.gate = float(gate)
        self.count_walk, self.scale_walk = float(count_walk), float(scale_walk)
        self.d_walked = 0.0  # m, the furthest count up to which the walk has been added
        self.held: BaliseFix | None = None  # a refused balise, until the next one judges it
        self.relocated = 0
        self.excluded = 0  # recent balises found to lie by a later one and taken out
        self.n = 0  # balises in the solution
        # the last EXCLUDED fusions: (solution before, fixes fused)
        self.recent: list[tuple[_Solution, tuple[BaliseFix, ...]]] = []
        self.alternatives: list[_Solution] = []  # the solution without each of them
        self._stack: tuple | None = None  # what :meth:`doubt` reuses (:meth:`_stacked`)
        self.jumps: tuple = ()  # (count m, variance m^2) of each splice (:meth:`splice`)
        # the start-fault hypothesis (module doc): its bias bound before the first balise, then
        # the solution without the start (None: no start fault carried, or the count was
        # relocated and the main solution has no start in it either)
        self.start_fault = float(start_fault)
        self.llr_free = 0.0  # log-likelihood of the balises under the start minus without it
        self.start_excluded = 0
        self.free: _Solution | None = _Solution(
            self.theta, np.diag([RELOCATE_X0_VAR, scale_std ** 2, latency_std ** 2]), 0.0) \
            if start_fault > 0 else None

    def copy(self) -> OdometerCalibration:
        # every update makes new arrays and lists: a shallow copy shares nothing that changes
        c = object.__new__(OdometerCalibration)
        c.__dict__.update(self.__dict__)
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
        h = np.array([1.0, d, 0.0])
        return float(h @ self.Sigma @ h)

    def latency(self) -> tuple[float, float]:
        """The balise reader's latency as learnt so far: ``(tau s, its std s)``."""
        return float(self.theta[2]), math.sqrt(max(float(self.Sigma[2, 2]), 0.0))

    def consider(self, d: float, v_odo: float) -> np.ndarray:
        """2x2 covariance of (position, speed) that the calibration adds to an estimate that
        follows the mapped readings at count ``d`` and speed reading ``v_odo``.

        Solution separation (as receiver autonomous integrity monitoring does for satellites):
        any one of the last :attr:`EXCLUDED` balises may lie elsewhere than its telegram says
        (a survey error) by more than the stated accuracy, and nothing tells until later
        balises disagree with it. For each, the solution without it is at ``J theta_k`` with
        covariance ``C_k``; the diagonal grows (never shrinks) so that every variance is at
        least ``(C_k + Delta_k Delta_k^T)_ii``, ``Delta_k = J (theta_k - theta)``."""
        return self.doubt(d, v_odo)[0]

    def separation(self, d: float, v_odo: float) -> tuple:
        """The calibration's position doubt as solutions (``protection.py``): ``(variance m^2,
        ((shift m, variance m^2), ...))``, the fault-free solution's position variance at count
        ``d`` (``J Sigma J^T``) and, for each of the last balises, where the solution without
        it puts the train relative to this one and how sure that is (:meth:`consider` covers
        them all with one variance instead)."""
        return self.doubt(d, v_odo)[1]

    def doubt(self, d: float, v_odo: float) -> tuple[np.ndarray, tuple]:
        """``(consider(d, v_odo), separation(d, v_odo))`` from one pass over the solutions
        without each recent balise and the start's (an estimate publishes both)."""
        J = np.array([[1.0, d, 0.0], [0.0, v_odo, 0.0]])
        # the matrix products in numpy (on stacks: :meth:`_stacked`), the elementwise rest on
        # floats (the same IEEE operations as on the 2-vectors: this runs at every estimate)
        S, D = self._stacked()
        K = (J @ S @ J.T).tolist()
        (c00, c01), (c10, c11) = K[0]
        n0, n1 = c00, c11  # the diagonal needed: the largest over the solutions
        alts = []
        for ((k0, _), (_, k1)), ((d0,), (d1,)) in zip(K[1:], (J @ D).tolist() if K[1:] else ()):
            n0, n1 = _nanmax(n0, k0 + d0 * d0), _nanmax(n1, k1 + d1 * d1)
            alts.append((d0, k0))
        for shift, var in self.start_doubt(d, c00):
            n0 = max(n0, var + shift * shift)
            alts.append((shift, var))
        return np.array([[c00 + (n0 - c00), c01 + 0.0], [c10 + 0.0, c11 + (n1 - c11)]]), \
            (c00, tuple(alts))

    def _stacked(self) -> tuple:
        """``(S, D)`` of :meth:`doubt`: ``Sigma`` and each alternative's covariance walked to
        :attr:`d_walked`, stacked ``(n + 1, 3, 3)``, and the alternatives' ``theta`` less this
        one's ``(n, 3, 1)``. numpy makes the same BLAS call on each slice of a stack as on a lone
        array (the same numbers, a third of the calls); each part is kept while the objects it
        is made of stand (every update makes new ones: a standing train reuses both)."""
        alts, c = self.alternatives, self._stack
        if c is None or c[0] is not alts or c[1] is not self.theta:
            c = (alts, self.theta, np.array([a.theta - self.theta for a in alts])[:, :, None]
                 if alts else None, None, None, None, None)
        if c[3] is not self.Sigma or c[4] != self.d_walked or c[5] is not self.jumps:
            c = c[:3] + (self.Sigma, self.d_walked, self.jumps, np.array(
                [self.Sigma] + [_walked(a.Sigma, a.d, self.d_walked, self.count_walk,
                                        self.scale_walk, self.jumps) for a in alts]))
        self._stack = c
        return c[6], c[2]

    def start_doubt(self, d: float, var: float | None = None) -> tuple:
        """The start-fault hypothesis at the count ``d`` as solutions ``((shift m, variance
        m^2), ...)`` relative to this calibration's position (module doc): before the first
        balise the train at either end of the bias bound with ``var`` (the position's own
        variance, :meth:`position_variance` when None); then the solution without the start;
        ``()`` when no start fault is carried."""
        f = self.free
        if f is None:
            return ()
        if f.n == 0:
            v = self.position_variance(d) if var is None else float(var)
            return ((self.start_fault, v), (-self.start_fault, v))
        Sf = _walked(f.Sigma, f.d, self.d_walked, self.count_walk, self.scale_walk, self.jumps)
        h = np.array([1.0, d, 0.0])
        return ((float(h @ (f.theta - self.theta)), float(h @ Sf @ h)),)

    # -- time (distance) update ---------------------------------------------------------------
    def walk_to(self, d: float) -> None:
        """Add the random walk of the count run past the furthest count walked so far (module
        doc). A count that comes back below it is its readings' scatter, not metres run:
        walked along its path, a standing train's readings were charged as a train running
        0.5 m per reading (75 m per 15 s at 10 Hz on metro_demo), and its protection level
        grew by minutes of standing. A train that rolls back and on again over the same
        counts is charged for them once."""
        if not math.isfinite(d) or d <= self.d_walked:
            return
        self.Sigma = _walked(self.Sigma, self.d_walked, d, self.count_walk, self.scale_walk,
                             self.jumps)
        self.d_walked = float(d)

    def place(self, d: float, x: float, variance: float) -> None:
        """Before any balise: the count ``d`` (m) puts the train at ``x`` (m, ``variance``
        m^2), the scale and the latency at their priors: ``x0 = x - c d``, its variance and
        its covariance with ``c`` such that the position at ``d`` has ``variance`` (a count
        made of the speeds from where a track placed the train:
        ``calibrated_odometry.DistanceAsPosition._exclude_count``); the walk is charged from
        ``d`` on."""
        c, sc2 = float(self.theta[1]), float(self.Sigma[1, 1])
        self.theta = np.array([x - c * d, c, float(self.theta[2])])
        S = np.array(self.Sigma, dtype=float)
        S[0, 0] = variance + d * d * sc2
        S[0, 1] = S[1, 0] = -d * sc2
        S[0, 2] = S[2, 0] = 0.0
        self.Sigma = S
        self.d_walked = max(self.d_walked, float(d))

    def widen_origin(self, move: float, variance: float) -> None:
        """The origin moved by ``move`` (m) with ``variance`` (m^2) more doubt, before any
        balise (the first odometer reading's count far from the start:
        ``calibrated_odometry.DistanceAsPosition._origin``)."""
        if math.isfinite(move) and math.isfinite(variance) and variance >= 0:
            self.theta = self.theta + np.array([move, 0.0, 0.0])
            self.Sigma = self.Sigma + np.diag([variance, 0.0, 0.0])
            if self.free is not None:
                self.free = _Solution(self.free.theta + np.array([move, 0.0, 0.0]),
                                      self.free.Sigma, self.free.d, self.free.n)

    def splice(self, at: float, variance: float) -> None:
        """The odometer restarted its count, and the new count was spliced onto the old one at
        the count ``at`` (m) to within ``variance`` (m^2): that much more doubt of ``x0`` from
        there on, as a concentrated :data:`COUNT_WALK` (every solution walked over ``at``
        takes it, the solutions without a recent balise included)."""
        if math.isfinite(at) and math.isfinite(variance) and variance > 0:
            self.jumps = (self.jumps + ((float(at), float(variance)),))[-16:]

    # -- balises -----------------------------------------------------------------------------
    @staticmethod
    def _row(theta, fix: BaliseFix) -> tuple[float, np.ndarray]:
        """Where ``theta`` puts the balise (m) and the row of its linearisation (module doc):
        the train was over it ``tau`` before the stamp, ``v_b tau`` of count earlier."""
        d = fix.distance - fix.speed * float(theta[2])
        return (float(theta[0] + theta[1] * d),
                np.array([1.0, d, -float(theta[1]) * fix.speed]))

    @classmethod
    def _innovation_of(cls, theta, Sigma, fix: BaliseFix) -> tuple[float, float]:
        pred, h = cls._row(theta, fix)
        return fix.position - pred, float(h @ Sigma @ h) + fix.variance

    def _innovation(self, fix: BaliseFix) -> tuple[float, float]:
        return self._innovation_of(self.theta, self.Sigma, fix)

    @classmethod
    def _fused(cls, theta, Sigma, fix: BaliseFix) -> tuple[np.ndarray, np.ndarray]:
        """The (extended) Kalman update of ``(theta, Sigma)`` with one balise (new arrays)."""
        pred, h = cls._row(theta, fix)
        nu, s = fix.position - pred, float(h @ Sigma @ h) + fix.variance
        k = Sigma @ h / s
        # Joseph form: Sigma stays symmetric positive definite for any gain
        ikh = np.eye(len(h)) - np.outer(k, h)
        return theta + k * nu, ikh @ Sigma @ ikh.T + fix.variance * np.outer(k, k)

    def _apply(self, fixes: tuple[BaliseFix, ...]) -> None:
        """Fuse ``fixes``, noting the solution before them and recomputing the solutions
        without each recent fusion."""
        self.recent = (self.recent + [(_Solution(self.theta, self.Sigma, self.d_walked, self.n),
                                       fixes, self.free)])[-self.EXCLUDED:]
        self.theta, self.Sigma = self._step(self.theta, self.Sigma, fixes)
        if self.free is not None:  # the solution without the start takes the same balises
            f = self.free
            self.free = _Solution(*self._step(
                f.theta, _walked(f.Sigma, f.d, self.d_walked, self.count_walk, self.scale_walk,
                                 self.jumps), fixes), self.d_walked, f.n + len(fixes))
        self.n += len(fixes)
        self.alternatives = [self._without(j) for j in range(len(self.recent))]

    @classmethod
    def _step(cls, theta, Sigma, fixes):
        for fix in fixes:
            theta, Sigma = cls._fused(theta, Sigma, fix)
        return theta, Sigma

    def _without(self, j: int) -> _Solution:
        """The solution with every recent fusion but the ``j``-th, walked to the present, and
        how far the later balises lay from it as it took them (``worst``)."""
        sol = self.recent[j][0]
        theta, Sigma, d, n = sol.theta, sol.Sigma, sol.d, sol.n
        worst = 0.0
        for before, fixes, _ in self.recent[j + 1:]:
            Sigma = _walked(Sigma, d, before.d, self.count_walk, self.scale_walk, self.jumps)
            for fix in fixes:
                nu, s = self._innovation_of(theta, Sigma, fix)
                worst = max(worst, abs(nu) / math.sqrt(s))
                theta, Sigma = self._fused(theta, Sigma, fix)
            d, n = before.d, n + len(fixes)
        return _Solution(theta, _walked(Sigma, d, self.d_walked, self.count_walk,
                                        self.scale_walk, self.jumps), self.d_walked, n, worst)

    def _judge_start(self, fix: BaliseFix) -> bool:
        """The start-fault hypothesis's sequential test on ``fix`` (module doc): the start
        excluded or confirmed (the solution without it dropped) once the likelihood ratio
        passes ``1 / EXCLUSION_RISK``. Excluded, the solution without the start, with ``fix``
        fused, becomes the calibration (True: ``fix`` is fused). The test weighs the start
        against the balises read, not against one of them lying: the solution before ``fix``
        (with the start, without ``fix``) stays as the alternative of ``fix``, as the solution
        without any recent balise does, until later balises outvote one or the other."""
        f = self.free
        Sf = _walked(f.Sigma, f.d, self.d_walked, self.count_walk, self.scale_walk, self.jumps)
        self.llr_free += log_density(*self._innovation(fix)) \
            - log_density(*self._innovation_of(f.theta, Sf, fix))
        decided = wald(self.llr_free)
        if decided > 0:
            self.free = None
        elif decided < 0:
            before = _Solution(self.theta, self.Sigma, self.d_walked, self.n)
            self.theta, self.Sigma = self._fused(f.theta, Sf, fix)
            self.n = f.n + 1
            self.recent = [(before, (fix,), None)]
            self.free, self.held = None, None
            self.alternatives = [self._without(0)]
            self.start_excluded += 1
            return True
        return False

    def _outside(self, theta, Sigma, fixes, z: float) -> bool:
        """Whether any of ``fixes`` lies beyond ``z`` standard deviations of the solution
        ``(theta, Sigma)``."""
        for b in fixes:
            nu, s = self._innovation_of(theta, Sigma, b)
            if abs(nu) > z * math.sqrt(s):
                return True
        return False

    def _consistent(self, alt: _Solution) -> bool:
        """Whether a solution without a recent balise took each later balise within
        ``EXCLUDE`` gates of itself, the bar a liar must pass (:meth:`_exclude_for`): only
        such a subset solution may exclude the balise it leaves out."""
        return alt.worst <= EXCLUDE * self.gate

    def _exclude_for(self, fixes: tuple[BaliseFix, ...]) -> bool:
        """Fault exclusion: ``fixes`` (the new balise, after a held one) fit the solution
        without one of the recent balises, and with them in it that balise is outside the
        gate: it was the one that lied. Its exclusion, with ``fixes``, becomes the solution
        (True). At least two balises must outvote one: the prior alone is wide enough to take
        a balise that lies, and would exclude a good one. The solution without that balise
        must also have taken each later balise within ``EXCLUDE`` gates of itself, the bar a
        liar must pass to be excluded (fault exclusion takes a subset solution that is itself
        consistent, as RAIM's does): after a start excluded by one balise, the solution "the
        start was right and that balise lied" took the next balise 1,155 m off its prediction
        (a scale of 1.28 and a latency of -0.85 s, 28 prior deviations), the third fitted it,
        and the first balise was taken out: the wrong start back, every balise after refused,
        estimates 965 m off within 95 m levels (a node and its odometer restarted together
        mid-run). (With the gate itself as that bar, a liar 30 m off on wen2017_subway stayed
        in for longer: the solution without it, on the prior alone, had taken the next
        balise at 4-8 of its deviations.)"""
        best = None
        for j, alt in enumerate(self.alternatives):
            if alt.n + len(fixes) < 2:
                continue
            if not self._consistent(alt):
                continue
            theta, Sigma, worst = alt.theta, alt.Sigma, 0.0
            for b in fixes:
                nu, s = self._innovation_of(theta, Sigma, b)
                worst = max(worst, abs(nu) / math.sqrt(s))
                theta, Sigma = self._fused(theta, Sigma, b)
            if worst <= self.gate and self._outside(theta, Sigma, self.recent[j][1],
                                                    EXCLUDE * self.gate) \
                    and (best is None or worst < best[0]):
                best = (worst, j)
        if best is None:
            return False
        self._take(best[1], fixes)
        return True

    def _take(self, j: int, fixes: tuple[BaliseFix, ...] = ()) -> None:
        """The ``j``-th recent fusion taken out: the fusions after it applied again from the
        solution before it (each keeps its own alternative), then ``fixes``."""
        d_now = self.d_walked
        before, _, self.free = self.recent[j]
        rest = self.recent[j + 1:]
        self.recent = self.recent[:j]
        self.theta, self.Sigma, self.n, self.d_walked = before.theta, before.Sigma, before.n, \
            before.d
        for sol, fx, _ in rest:
            self.walk_to(sol.d)
            self._apply(fx)
        self.walk_to(d_now)
        self.alternatives = [self._without(i) for i in range(len(self.recent))]
        if fixes:
            self._apply(fixes)
        self.excluded += 1

    def _leave_one_out(self) -> None:
        """After a fusion: a recent balise beyond ``EXCLUDE`` gates of the solution without it,
        where that solution has two balises or more and took each within ``EXCLUDE`` gates
        (:meth:`_exclude_for`), lied; it is taken out (one per fusion)."""
        for j, alt in enumerate(self.alternatives):
            if alt.n >= 2 and self._consistent(alt) and \
                    self._outside(alt.theta, alt.Sigma, self.recent[j][1], EXCLUDE * self.gate):
                self._take(j)
                return

    def balise(self, fix: BaliseFix) -> bool:
        """Fuse one balise (True), or refuse and hold it (False); module doc."""
        if not (math.isfinite(fix.position) and math.isfinite(fix.distance)
                and math.isfinite(fix.variance) and fix.variance > 0):
            return False
        self.walk_to(fix.distance)
        if self.free is not None and self._judge_start(fix):
            return True
        if self.held is not None and self._exclude_for((self.held, fix)):
            self.held = None  # the held balise and this one outvote a fused one
            return True
        nu, s = self._innovation(fix)
        if abs(nu) <= self.gate * math.sqrt(s):
            self._apply((fix,))
            self._leave_one_out()
            self.held = None
            return True
        if self._exclude_for((fix,)):
            self.held = None
            return True
        held, self.held = self.held, fix
        if held is None:
            return False
        # two refused balises that agree with each other at a scale the odometer can have (its
        # prior's doubt at least: the scale may be what went wrong): the count is lost, and is
        # found again from the two, x0 free and the scale at its estimate with that doubt
        c, tau, stt = float(self.theta[1]), float(self.theta[2]), float(self.Sigma[2, 2])
        sc2 = max(float(self.Sigma[1, 1]), self.scale_std ** 2)
        gap = fix.distance - held.distance
        # a late reader moves both by their speeds: apart by the difference of those
        gap_t = gap - (fix.speed - held.speed) * tau
        agree = held.variance + fix.variance + sc2 * gap * gap + self.count_walk * abs(gap) \
            + stt * (c * (fix.speed - held.speed)) ** 2
        if abs((fix.position - held.position) - c * gap_t) > self.gate * math.sqrt(agree):
            return False
        self.theta = np.array([held.position - c * (held.distance - held.speed * tau), c, tau])
        self.Sigma = np.diag([RELOCATE_X0_VAR, sc2, stt])
        self.n, self.recent, self.alternatives = 0, [], []
        self._apply((held, fix))
        # the pair is the evidence: a solution without one of them (x0 unknown) is no
        # alternative to cover (two balises that lie alike are beyond a single fault)
        self.recent, self.alternatives = [], []
        self.free = None  # the relocated solution has no start in it: it is the free one
        self.held = None
        self.relocated += 1
        return True


def wald(llr: float, risk: float = EXCLUSION_RISK) -> int:
    """Wald's sequential test on ``llr``, the log-likelihood ratio summed so far of hypothesis
    A over B: +1 excludes B, -1 excludes A, 0 is undecided. The ratio of the wrong hypothesis
    over the true one is a martingale, so it ever reaches ``1 / risk`` with probability at most
    ``risk``, however many terms come."""
    bound = math.log(1.0 / risk)
    return 1 if llr >= bound else -1 if llr <= -bound else 0


def log_density(nu: float, s: float) -> float:
    """log N(nu; 0, s): a balise's predictive log-likelihood (innovation ``nu`` m, its
    variance ``s`` m^2)."""
    return -0.5 * (nu * nu / s + math.log(2.0 * math.pi * s))


def latency_beyond_prior(wide: OdometerCalibration, latency_std: float,
                         z: float = LATENCY_Z) -> bool:
    """Whether the wide-prior calibration ``wide`` finds the balise reader's latency beyond
    ``z`` standard deviations of what a reader within the prior ``N(0, latency_std^2)`` would
    give it (module doc): ``|tau^| > z sqrt(latency_std^2 + sd_w^2)``, with
    :data:`LATENCY_MIN_BALISES` balises in it at least."""
    if wide.n < LATENCY_MIN_BALISES:
        return False
    tau, sd = wide.latency()
    return abs(tau) > z * math.sqrt(latency_std ** 2 + sd * sd)
