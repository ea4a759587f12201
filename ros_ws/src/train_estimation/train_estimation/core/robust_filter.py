r"""Recursive robust filter under packet dropouts (Wen et al. 2017) and its baselines.

Model (``wen_model``, eq. (10))::

    x(k+1) = (A + H Delta(k) Eu) x(k) + u_k + E w(k),   Delta Delta^T <= I,  w^2 <= q,
    y(k)   = C x(k) + nu(k),   ybar(k) = Lambda(k) y(k),   Lambda = diag(alpha_i(k)),   (5), (11)

with ``u_k`` the known input (drive force, a0, gradient) and ``alpha_i(k)`` Bernoulli with mean
``abar_i`` (eq. (12)); the filter knows the realised ``alpha(k)`` (Remark 3: from the message
sequence numbers). Filter (13)::

    x^(k+1|k)   = A x^(k|k) + u_k
    x^(k+1|k+1) = x^(k+1|k) + K(k+1) Lambda(k+1) (y(k+1) - C x^(k+1|k))

Upper bound of the error second moment, Theorem 2, eq. (21)-(22) (Lemma 1 with general ``Eu``;
the paper has ``Eu = I``)::

    Sigma(k+1|k) = q E E^T + (1 + eps) (A (Sigma^{-1} - gamma Eu^T Eu)^{-1} A^T + H H^T / gamma)
                   + (1 + 1/eps) lambda_bar H H^T,   lambda_bar = |Eu x^(k|k)|^2           (21)
    Sigma(k+1|k+1) = (I - K Abar C) Sigma (I - K Abar C)^T
                     + K [ (Pi - abar abar^T) o (C Sigma C^T) + Pi o R ] K^T                (22)

``Abar = diag(abar)``, ``Pi = E[alpha alpha^T]`` (``Pi_ij = abar_i`` for two channels of one
packet, ``abar_i abar_j`` otherwise) and ``o`` the elementwise product. For one packet
(``Pi = abar 1 1^T``) this is exactly eq. (22); several sensors at different rates and missing
samples are the same update with a different channel list and mask.

**Paper slip in the gain.** Eq. (22) expands to ``Sigma - abar (K C Sigma + Sigma C^T K^T) +
abar K (C Sigma C^T + R) K^T``; its trace is minimised by ``K = Sigma C^T (R + C Sigma
C^T)^{-1}``, *without* the factor ``abar`` of eq. (24)/(33): the derivative (32) drops the
``abar`` of the quadratic term. Both gains give a valid bound (22 holds for any K), but only the
corrected one minimises it, as the theorem claims. ``gain="corrected"`` (default) uses
``K = Sigma C^T Abar (Pi o S)^{-1}``, ``S = C Sigma C^T + R``, the minimiser of tr (22) in the
multi-channel form; ``gain="paper"`` uses eq. (24) literally, ``K = Sigma C^T Abar S^{-1}``.

**Rule for gamma_k** (constraint (23): ``gamma^{-1} I - Eu Sigma Eu^T > 0``). Only the bracket
``A (Sigma^{-1} - gamma Eu^T Eu)^{-1} A^T + H H^T / gamma`` of (21) depends on gamma. We take
the gamma in the open interval ``(0, 1 / lambda_max(Eu Sigma Eu^T))`` that minimises its trace:
with ``Eu Sigma Eu^T = V diag(s) V^T`` and ``g_i = |A Sigma Eu^T V_i|^2`` (Woodbury)
``tr = tr(A Sigma A^T) + sum_i g_i gamma / (1 - gamma s_i) + tr(H H^T) / gamma``, strictly convex
on the interval and infinite at both ends, so the minimiser is the unique root of the increasing
function ``sum_i g_i gamma^2 / (1 - gamma s_i)^2 - tr(H H^T)`` (bracketed Newton). Why: (23)
then holds by construction (strictly inside the interval); Sigma(k+1|k+1) of (22) is monotone in
Sigma(k+1|k) (proof of Thm 2), so the smallest prior bound gives the smallest posterior bound
that a choice of gamma can give -- the same greedy criterion the paper uses for K.
A fixed gamma would violate (23) as soon as Sigma grows, and Remark 6 asks for a per-step choice.

**epsilon.** A parameter (``epsilon > 0``). ``epsilon=None`` picks it per step as
``sqrt(b / a)``, the minimiser of ``(1 + eps) a + (1 + 1/eps) b`` with ``a`` the trace of the
gamma-bracket and ``b = lambda_bar tr(H H^T)``; the proof of Theorem 2 holds for any positive
eps at each step, so this is allowed (for ``b = 0`` the cross terms of (28) vanish and eps -> 0).

**Caveats of Theorem 2 as printed** (kept, but stated): ``lambda_bar`` uses the random estimate
``x^(k|k)`` where the proof needs a deterministic one, and ``Delta(k)`` depends on the random true
speed; the bound is therefore checked by Monte Carlo in the tests and the benchmark.

Measurements (one :class:`Measurement` = channel list + mask):

* odometer: speed (``C = [0 1]``, the message's ``speed_variance``) and, if
  ``use_distance``, position ``= odometer_origin + distance`` (``C = [1 0]``,
  ``distance_variance``): the paper's measurement (5) with ``C = I``. The odometer's counted
  distance is the paper's position sensor. It is used as an absolute position with white noise of
  the stated variance, which is what the sensor model (``train.yaml: odometer.distance_std``)
  says; a drifting odometer (wheel wear, slip) breaks that assumption and is ``diagnose``'s job.
  A lost odometer packet is a :class:`OdometerReading` with ``received=False``: both channels
  with ``alpha = 0``. The bound still shrinks (the expectation over alpha, eq. (22)).
* balise: position (``C = [1 0]``) at the surveyed map position, ``position_variance``. A balise
  read is position-triggered, not a periodic slot, so the filter cannot know of a lost one: it
  enters when received with ``abar = 1`` (the bound is conditional on the balise arrivals).

Input and standstill (not in the paper, shared by all model-based filters): the control input
of a step is the mean over the step of the achieved control acceleration that ``a_Tar`` gives
through the believed actuator (delay + lag + braking rate of ``train.yaml``,
``wen_model.Actuator``), and a prediction that would end with ``v < 0`` stops the train inside the
step instead (``WenModel.standstill``): a braked train at rest does not roll backwards.

Bad input is rejected with a reason (``Decision``), counted in ``counters`` and leaves the state
untouched: ``non_finite``, ``non_positive_variance``, ``out_of_order``, ``duplicate``,
``unknown_balise``, ``balise_map_mismatch``, ``outside_gate`` (normalised innovation
``|nu_i| / sqrt(S_ii) > gate`` on any channel, S from the filter's own covariance / bound),
``future_stamp`` (more than ``max_horizon`` ahead), ``numerical_failure`` -- the names of
``core/reasons.py``. Order is by stamp; ``seq`` marks duplicates only, and a ``seq`` that goes
back while the stamp goes on (a sensor reset, a wrap-around) is accepted and counted as
``seq_reset``.

Lost packets are not bad input: an odometer slot with ``received=False`` is accepted with
reason ``missing``. Accepted ``predict_to``/``set_control`` calls are not counted.

Baselines: :class:`FOHFilter` (the paper's "direct measurements with first-order hold",
odometer only),
:class:`IntermittentKF` (KF with the same nominal model, update skipped for missing channels;
Sinopoli et al. 2004) and the oracle (:class:`IntermittentKF` with ``ekf=True`` on the true
model with the true actuator output as input).

Pure: numpy/scipy only.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, replace

import numpy as np

from . import reasons as R
from .wen_model import Actuator, DiscreteWen, WenModel

__all__ = [
    "Measurement", "Decision", "OdometerReading", "BaliseReading", "FilterParams",
    "choose_gamma", "robust_predict_cov", "robust_predict", "robust_update", "packet_moments",
    "kf_predict", "kf_update", "RobustFilter", "IntermittentKF", "FOHFilter", "REASONS",
    "make_robust_filter", "covariance16",
]

# the filters' share of the one vocabulary (core/reasons.py)
REASONS = (R.OK, R.MISSING, R.IGNORED,  # accepted
           R.NON_FINITE, R.NON_POSITIVE_VARIANCE, R.OUT_OF_ORDER, R.DUPLICATE,  # rejected
           R.UNKNOWN_BALISE, R.BALISE_MAP_MISMATCH, R.OUTSIDE_GATE)


# ---------------------------------------------------------------------------------------------
# Data types
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Measurement:
    """Channels that could arrive at one instant. ``mask[i]`` is the realised ``alpha_i``."""

    y: np.ndarray  # (m,) values (anything where mask is False)
    C: np.ndarray  # (m, n) measurement matrix
    R: np.ndarray  # (m, m) noise covariance (SI units squared)
    abar: np.ndarray  # (m,) Prob(channel received), eq. (12)
    group: np.ndarray  # (m,) int: channels of one packet share alpha
    mask: np.ndarray  # (m,) bool, alpha_i(k)


@dataclass(frozen=True)
class Decision:
    accepted: bool
    reason: str  # one of REASONS


@dataclass(frozen=True)
class OdometerReading:
    stamp: float  # s, sampling time on the train
    seq: int  # sample counter before the radio link
    distance: float = math.nan  # m, counted since the run started
    speed: float = math.nan  # m/s
    speed_variance: float = math.nan  # (m/s)^2
    received: bool = True  # False: the slot of sample ``seq`` was lost (values ignored)


@dataclass(frozen=True)
class BaliseReading:
    stamp: float  # s, time the antenna passed the reference mark
    seq: int
    balise_id: int
    position: float  # m, surveyed position as sent
    position_variance: float  # m^2


@dataclass(frozen=True)
class FilterParams:
    """Settings shared by the filters (SI units)."""

    alpha_bar: float = 0.875  # -, Prob(odometer packet received), eq. (12)
    alpha_bar_balise: float = 1.0  # -, balise readings enter on arrival (see module doc)
    epsilon: float | None = None  # -, eq. (21); None = per-step minimiser of the trace
    gain: str = "corrected"  # "corrected" (minimises tr (22)) or "paper" (eq. (24) literally)
    gate: float = 8.0  # -, reject if |innovation| > gate * sqrt(S_ii); math.inf disables
    use_distance: bool = True  # odometer distance as a position measurement
    distance_variance: float = 1.0  # m^2, variance of origin + distance as a position reading
    speed_variance: float = 0.01  # (m/s)^2, odometer speed variance until a packet states it
    odometer_origin: float = 0.0  # m, track position where the odometer distance is zero
    balise_map_tolerance: float = 1.0  # m, max |sent position - map position|
    actuator: bool = True  # pass a_Tar through the believed delay + lag (wen_model.Actuator)
    clamp_standstill: bool = True  # project v^ onto v >= 0 (the world never rolls back)
    kf_q: float | None = None  # N^2, IntermittentKF's wind-force variance (None: model.q)
    max_dt: float = 1.0  # s, longer predictions are split (ZOH of gradient and resistance)
    max_horizon: float = 3600.0  # s, a reading further ahead of the estimate is future_stamp


# ---------------------------------------------------------------------------------------------
# Pure step functions
# ---------------------------------------------------------------------------------------------

def choose_gamma(Sigma: np.ndarray, A: np.ndarray, H: np.ndarray, Eu: np.ndarray) -> float:
    """gamma_k minimising tr[A (Sigma^{-1} - gamma Eu^T Eu)^{-1} A^T] + tr(H H^T) / gamma on
    (0, 1/lambda_max(Eu Sigma Eu^T)) (constraint (23)); see the module docstring.

    The stationarity condition is ``r(gamma) = sum_i g_i t_i^2 - h = 0`` with
    ``t_i = gamma / (1 - gamma s_i)``; ``r`` is increasing and convex on the interval and
    infinite at its right end. Replacing every ``s_i`` by ``s_max`` (``s_min``) gives functions
    above (below) ``r`` with closed-form roots ``sqrt(h) / (sqrt(sum g) + s sqrt(h))``, so the
    root lies in ``[gamma_lo, min(gamma_hi, 1/s_max))``; safeguarded Newton (bisection whenever
    a Newton step leaves the bracket) converges in a few iterations.
    Returns 0.0 when ``H = 0`` (no uncertainty: the bracket is ``A Sigma A^T`` in the limit).
    """
    h = float(np.sum(H * H))
    if h == 0.0:
        return 0.0
    s, V = np.linalg.eigh(Eu @ Sigma @ Eu.T)
    G = A @ Sigma @ Eu.T @ V
    g = [float(v) for v in np.sum(G * G, axis=0)]
    s = [float(v) for v in s]
    sh, sg = math.sqrt(h), math.sqrt(sum(g))
    lo = sh / (sg + s[-1] * sh)
    pole = 1.0 / s[-1]
    ghi = sh / (sg + max(s[0], 0.0) * sh)  # guard: s_min >= 0 in exact arithmetic
    hi = min(ghi, pole)
    gam = ghi if ghi < pole else 0.5 * (lo + hi)
    for _ in range(200):
        r, dr = -h, 0.0
        for gi, si in zip(g, s):
            d = 1.0 - gam * si
            t = gam / d
            r += gi * t * t
            dr += 2.0 * gi * t / (d * d)
        if r > 0.0:
            hi = gam
        else:
            lo = gam
        if abs(r) <= 1e-14 * h or hi - lo <= 1e-15 * hi:
            break
        new = gam - r / dr if dr > 0.0 else 0.5 * (lo + hi)
        if not lo < new < hi:
            new = 0.5 * (lo + hi)
        if abs(new - gam) <= 1e-15 * gam:
            break
        gam = new
    return gam


def robust_predict_cov(Sigma: np.ndarray, dm: DiscreteWen, q: float, lam_bar: float,
                       gamma: float | None = None, epsilon: float | None = None
                       ) -> tuple[np.ndarray, float, float]:
    """Eq. (21). Returns ``(Sigma(k+1|k), gamma, epsilon)`` actually used.

    ``gamma=None``: :func:`choose_gamma`. ``epsilon=None``: per-step minimiser ``sqrt(b/a)``.
    Raises ValueError when a given gamma violates (23).
    """
    A, H, Eu, E = dm.A, dm.H, dm.Eu, dm.E
    check = gamma is not None
    if gamma is None:
        gamma = choose_gamma(Sigma, A, H, Eu)
    HH = H @ H.T
    if gamma > 0.0:
        S_u = Eu @ Sigma @ Eu.T
        W = np.eye(S_u.shape[0]) / gamma - S_u
        if check and np.linalg.eigvalsh(W)[0] <= 0.0:  # choose_gamma's is inside by construction
            raise ValueError("gamma violates constraint (23): 1/gamma I - Eu Sigma Eu^T not > 0")
        SE = Sigma @ Eu.T
        M = Sigma + SE @ np.linalg.solve(W, SE.T)  # (Sigma^{-1} - gamma Eu^T Eu)^{-1}, Woodbury
        bracket = A @ M @ A.T + HH / gamma
    else:
        bracket = A @ Sigma @ A.T
    b_term = lam_bar * HH
    if epsilon is None:
        a_tr, b_tr = float(np.trace(bracket)), float(np.trace(b_term))
        epsilon = math.sqrt(b_tr / a_tr) if b_tr > 0.0 else 0.0
    if epsilon > 0.0:
        out = (1.0 + epsilon) * bracket + (1.0 + 1.0 / epsilon) * b_term
    elif np.any(b_term != 0.0):
        raise ValueError("epsilon must be > 0 when lambda_bar H H^T != 0")
    else:
        out = bracket
    out = out + q * np.outer(E, E)
    return 0.5 * (out + out.T), float(gamma), float(epsilon)


def robust_predict(x: np.ndarray, Sigma: np.ndarray, model: WenModel, dm: DiscreteWen,
                   control_accel: float, epsilon: float | None = None,
                   clamp_standstill: bool = True) -> tuple[np.ndarray, np.ndarray, float, float]:
    """First line of (13) and eq. (21): ``(x^(k+1|k), Sigma(k+1|k), gamma, epsilon)``."""
    Eux = dm.Eu @ x
    lam_bar = float(Eux @ Eux)  # lambda_max(Eu x x^T Eu^T) = |Eu x|^2
    Sp, gamma, eps = robust_predict_cov(Sigma, dm, model.q, lam_bar, None, epsilon)
    xp = model.predict_mean(dm, x, control_accel)
    if clamp_standstill:
        # The world never rolls back (true v >= 0): stop instead of reversing. For the
        # velocity this is a projection onto v >= 0, which cannot increase its error.
        xp = model.standstill(x, xp, dm.dt)
    return xp, Sp, gamma, eps


def packet_moments(meas: Measurement) -> np.ndarray:
    """``Pi = E[alpha alpha^T]``: ``abar_i`` within one packet, ``abar_i abar_j`` across."""
    ab = meas.abar
    same = meas.group[:, None] == meas.group[None, :]
    return np.where(same, np.minimum(ab[:, None], ab[None, :]), np.outer(ab, ab))


def robust_update(x_pred: np.ndarray, Sigma_pred: np.ndarray, meas: Measurement,
                  gain: str = "corrected") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Second line of (13) with the gain (24) (or its correction) and eq. (22).

    Returns ``(x^(k+1|k+1), Sigma(k+1|k+1), K)``. Channels with ``abar = 0`` are dropped.
    """
    keep = meas.abar > 0.0
    if not keep.all():
        if not keep.any():
            return x_pred, Sigma_pred, np.zeros((x_pred.size, 0))
        meas = replace(meas, C=meas.C[keep], R=meas.R[np.ix_(keep, keep)],
                       abar=meas.abar[keep], group=meas.group[keep], mask=meas.mask[keep],
                       y=meas.y[keep])
    C, R, ab, mask = meas.C, meas.R, meas.abar, meas.mask
    Pi = packet_moments(meas)
    CS = C @ Sigma_pred
    S = CS @ C.T + R
    PiS = Pi * S
    if gain == "corrected":
        K = np.linalg.solve(PiS.T, (Sigma_pred @ C.T * ab).T).T  # Sigma C^T Abar (Pi o S)^{-1}
    elif gain == "paper":
        K = np.linalg.solve(S.T, (Sigma_pred @ C.T * ab).T).T  # eq. (24): abar Sigma C^T S^{-1}
    else:
        raise ValueError(f"gain must be 'corrected' or 'paper', got {gain!r}")
    IKC = np.eye(x_pred.size) - K @ (ab[:, None] * C)
    inner = (Pi - np.outer(ab, ab)) * (CS @ C.T) + Pi * R
    Sig = IKC @ Sigma_pred @ IKC.T + K @ inner @ K.T  # eq. (22) in a sum-of-PSD form
    innov = np.where(mask, meas.y - C @ x_pred, 0.0)  # eq. (13): ybar - alpha C x^
    x_new = x_pred + K @ innov
    return x_new, 0.5 * (Sig + Sig.T), K


def kf_predict(x: np.ndarray, P: np.ndarray, model: WenModel, dm: DiscreteWen,
               control_accel: float, Q: np.ndarray, ekf: bool = False,
               clamp_standstill: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Kalman prediction on the nominal model (A~ of eq. (10)) or, with ``ekf``, the exact
    Davis resistance linearised at x^ (the oracle)."""
    if ekf:
        xp, J = model.ekf_step(dm, x, control_accel)
    else:
        xp, J = model.predict_mean(dm, x, control_accel), dm.A
    if clamp_standstill:
        xp = model.standstill(x, xp, dm.dt)
    Pp = J @ P @ J.T + Q
    return xp, 0.5 * (Pp + Pp.T)


def kf_update(x: np.ndarray, P: np.ndarray, meas: Measurement) -> tuple[np.ndarray, np.ndarray]:
    """Kalman update with the received channels only (intermittent observations); Joseph form.
    Nothing received: returned unchanged."""
    m = meas.mask
    if not np.any(m):
        return x, P
    C, R, y = meas.C[m], meas.R[np.ix_(m, m)], meas.y[m]
    S = C @ P @ C.T + R
    K = np.linalg.solve(S.T, (P @ C.T).T).T
    IKC = np.eye(x.size) - K @ C
    Pn = IKC @ P @ IKC.T + K @ R @ K.T
    return x + K @ (y - C @ x), 0.5 * (Pn + Pn.T)


# ---------------------------------------------------------------------------------------------
# Stateful filters (explicit time; the ROS node calls them in time order)
# ---------------------------------------------------------------------------------------------

_POS = np.array([[1.0, 0.0]])
_VEL = np.array([[0.0, 1.0]])


def _finite(*vals) -> bool:
    return all(isinstance(v, (int, float, np.floating, np.integer)) and math.isfinite(v)
               for v in vals)


class _FilterBase:
    """Validation, counters, time keeping and the actuator, shared by every filter.

    Usage (the node)::

        f.set_control(stamp, a_tar)            # on every ControlCommand
        f.predict_to(t)                        # move the estimate to time t
        f.update(OdometerReading(...))         # received reading, or received=False for a lost one
        f.update(BaliseReading(...))
        x, Sigma = f.estimate()

    ``update`` predicts to the reading's stamp itself when needed, so the node only has to feed
    readings in stamp order. Every call returns a :class:`Decision`; rejected input leaves the
    state (time included) untouched.
    """

    name = "base"

    def __init__(self, model: WenModel, params: FilterParams, x0, P0, t0: float,
                 brake=None):
        self.model = model
        self.params = params
        self.x = np.asarray(x0, dtype=float).copy()
        self.P = np.asarray(P0, dtype=float).copy()
        self.t = float(t0)
        self.counters: Counter = Counter()
        self._last_seq: dict[str, int] = {}
        self._last_stamp: dict[str, float] = {}
        # Control history -> input of each step. Without a brake model (or actuator=False) the
        # step [t0, t1) uses the last command issued at or before t0 (Wen's ZOH u(kT)), so the
        # result does not depend on whether a command stamped t1 is fed before the reading at t1.
        if brake is not None and params.actuator:
            self.actuator = Actuator(brake.time_constant, brake.delay, brake.braking_rate)
        else:
            self.actuator = Actuator(0.0, 0.0, 1.0, enabled=False)
        self._used = False
        self._speed_var = params.speed_variance  # (m/s)^2, for lost odometer packets
        self._balise_pos = {b.id: b.position for b in model.line.balises}

    # -- bookkeeping ---------------------------------------------------------------------------
    def _decide(self, accepted: bool, reason: str) -> Decision:
        self.counters[reason] += 1
        return Decision(accepted, reason)

    def estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """``(x^, Sigma)``: position (m), velocity (m/s) and the filter's covariance (the upper
        bound for the robust filter, NaN for FOH)."""
        return self.x.copy(), self.P.copy()

    def pop_measurement_used(self) -> bool:
        """True if a received reading entered the estimate since the last call."""
        used, self._used = self._used, False
        return used

    # -- control -------------------------------------------------------------------------------
    def set_control(self, stamp: float, target_acceleration: float) -> Decision:
        if not _finite(stamp, target_acceleration):
            return self._decide(False, R.NON_FINITE)
        last = self._last_stamp.get("control", -math.inf)
        if stamp < last:
            return self._decide(False, R.OUT_OF_ORDER)
        self._last_stamp["control"] = float(stamp)
        self.actuator.command(stamp, target_acceleration)
        return Decision(True, R.OK)  # accepted commands are not counted (rejections are)

    # -- time update ---------------------------------------------------------------------------
    def predict_to(self, t: float, control: float | None = None) -> Decision:
        """Move the estimate to time ``t`` (s). ``control`` (a_Tar, m/s^2), if given, is recorded
        as a command issued at the current filter time first."""
        if not _finite(t) or (control is not None and not _finite(control)):
            return self._decide(False, R.NON_FINITE)
        if t < self.t:
            return self._decide(False, R.OUT_OF_ORDER)
        if t - self.t > self.params.max_horizon:
            return self._decide(False, R.FUTURE_STAMP)
        if control is not None:
            self.set_control(self.t, control)
        self.x, self.P, self.actuator = self._propagate(t)
        self.t = float(t)
        return Decision(True, R.OK)

    def _propagate(self, t: float):
        """Prediction to ``t`` on copies; returns (x, P, actuator)."""
        act = self.actuator.copy()
        x, P, tc = self.x, self.P, self.t
        while t - tc > 0.0:
            dt = min(t - tc, self.params.max_dt)
            if t - (tc + dt) < 1e-9:  # avoid a sliver of a step from round-off
                dt = t - tc
            u = act.mean(tc, tc + dt)  # mean achieved control acceleration over the step
            x, P = self._predict(x, P, dt, u)
            tc += dt
        return x, P, act

    def _predict(self, x, P, dt, u):  # pragma: no cover - abstract
        raise NotImplementedError

    def _apply(self, x, P, meas: Measurement):  # pragma: no cover - abstract
        raise NotImplementedError

    # -- measurement update --------------------------------------------------------------------
    def _validate_order(self, kind: str, stamp: float, seq: int) -> str | None:
        """Order by stamp; ``seq`` only marks duplicates. A seq that goes back while the stamp
        goes on is a sensor reset or a wrap-around: accepted, counted as ``seq_reset``."""
        if stamp < self.t:
            return R.OUT_OF_ORDER
        if stamp - self.t > self.params.max_horizon:  # a clock error, not a long outage
            return R.FUTURE_STAMP
        last_seq = self._last_seq.get(kind)
        last_stamp = self._last_stamp.get(kind)
        if last_seq is not None and (seq == last_seq or stamp == last_stamp):
            return R.DUPLICATE
        if last_stamp is not None and stamp < last_stamp:
            return R.OUT_OF_ORDER
        return None

    def _measurement(self, reading) -> tuple[str, Measurement | str]:
        """Validate a reading and turn it into channels, or return the rejection reason."""
        p = self.params
        if isinstance(reading, OdometerReading):
            kind = "odometer"
            if not _finite(reading.stamp) or not isinstance(reading.seq, (int, np.integer)):
                return kind, R.NON_FINITE
            if reading.received:
                if not _finite(reading.distance, reading.speed, reading.speed_variance):
                    return kind, R.NON_FINITE
                if reading.speed_variance <= 0.0:
                    return kind, R.NON_POSITIVE_VARIANCE
            bad = self._validate_order(kind, reading.stamp, int(reading.seq))
            if bad:
                return kind, bad
            rows, ys, rs = [_VEL], [reading.speed], [reading.speed_variance]
            if p.use_distance:
                rows.append(_POS)
                ys.append(p.odometer_origin + reading.distance)
                rs.append(p.distance_variance)
            m = len(rows)
            recv = bool(reading.received)
            if not recv:
                # A lost packet still enters the bound (22) through E[alpha] = abar: it would
                # have carried the sensor's usual variance (the last one received).
                ys = [0.0] * m
                rs[0] = self._speed_var
            return kind, Measurement(
                y=np.array(ys, float), C=np.vstack(rows), R=np.diag(np.array(rs, float)),
                abar=np.full(m, p.alpha_bar), group=np.zeros(m, int),
                mask=np.full(m, recv))
        if isinstance(reading, BaliseReading):
            kind = "balise"
            if not _finite(reading.stamp, reading.position, reading.position_variance) or \
                    not isinstance(reading.seq, (int, np.integer)):
                return kind, R.NON_FINITE
            if reading.position_variance <= 0.0:
                return kind, R.NON_POSITIVE_VARIANCE
            bad = self._validate_order(kind, reading.stamp, int(reading.seq))
            if bad:
                return kind, bad
            pos = self._balise_pos.get(int(reading.balise_id))
            if pos is None:
                return kind, R.UNKNOWN_BALISE
            if abs(pos - reading.position) > p.balise_map_tolerance:
                return kind, R.BALISE_MAP_MISMATCH
            return kind, Measurement(
                y=np.array([pos]), C=_POS.copy(), R=np.array([[reading.position_variance]]),
                abar=np.array([p.alpha_bar_balise]), group=np.zeros(1, int),
                mask=np.array([True]))
        raise TypeError(f"unknown reading type {type(reading).__name__}")

    def _gate_ok(self, x, P, meas: Measurement) -> bool:
        g = self.params.gate
        if not math.isfinite(g) or not np.any(meas.mask) or not np.all(np.isfinite(P)):
            return True
        m = meas.mask
        C = meas.C[m]
        S = np.einsum("ij,jk,ik->i", C, P, C) + np.diag(meas.R)[m]
        nu = meas.y[m] - C @ x
        return bool(np.all(np.abs(nu) <= g * np.sqrt(S)))

    def update(self, reading) -> Decision:
        """Validate and apply one reading (predicting to its stamp first). See class doc."""
        kind, meas = self._measurement(reading)
        if isinstance(meas, str):
            return self._decide(False, meas)
        x, P, act = self._propagate(float(reading.stamp))
        if not self._gate_ok(x, P, meas):
            return self._decide(False, R.OUTSIDE_GATE)
        x, P = self._apply(x, P, meas)
        if not (np.all(np.isfinite(x)) and _finite_or_nan_cov(P)):
            return self._decide(False, R.NUMERICAL_FAILURE)  # keep the old state
        self.x, self.P, self.actuator, self.t = x, P, act, float(reading.stamp)
        if self._last_seq.get(kind, -1) > int(reading.seq):
            self.counters[R.SEQ_RESET] += 1
        self._last_seq[kind] = int(reading.seq)
        self._last_stamp[kind] = float(reading.stamp)
        received = bool(np.any(meas.mask))
        if kind == "odometer" and received:
            self._speed_var = float(reading.speed_variance)
        self._used |= received
        return self._decide(True, R.OK if received else R.MISSING)


def _finite_or_nan_cov(P) -> bool:
    return bool(np.all(np.isfinite(P)) or np.all(np.isnan(P)))


class RobustFilter(_FilterBase):
    """Wen et al. (2017) recursive robust filter, eq. (13), (21), (22), (24).

    ``estimate()`` returns ``(x^(k|k), Sigma(k|k))``; ``Sigma`` is the upper bound of the
    error second moment (Theorem 2). ``last_gamma`` / ``last_epsilon`` hold the values of the
    last prediction step.
    """

    name = "robust"

    def __init__(self, model: WenModel, params: FilterParams, x0, Sigma0, t0: float = 0.0,
                 brake=None):
        super().__init__(model, params, x0, Sigma0, t0, brake)
        self.last_gamma = math.nan
        self.last_epsilon = math.nan

    def _predict(self, x, P, dt, u):
        dm = self.model.discrete(dt)
        xp, Sp, self.last_gamma, self.last_epsilon = robust_predict(
            x, P, self.model, dm, u, self.params.epsilon, self.params.clamp_standstill)
        return xp, Sp

    def _apply(self, x, P, meas):
        xn, Sn, _ = robust_update(x, P, meas, self.params.gain)
        return xn, Sn


class IntermittentKF(_FilterBase):
    """Kalman filter with intermittent observations on the same discrete model.

    Process noise ``Q = q E~ E~^T`` (the wind force of eq. (7) as a white force of variance
    ``q`` N^2 held over each step; ``params.kf_q`` overrides ``model.q``). ``ekf=True`` uses the
    exact Davis resistance linearised at the estimate (the oracle on the true model).
    """

    name = "kf"

    def __init__(self, model: WenModel, params: FilterParams, x0, P0, t0: float = 0.0,
                 brake=None, ekf: bool = False, accel_psd: float = 0.0):
        super().__init__(model, params, x0, P0, t0, brake)
        self.ekf = ekf
        self.accel_psd = float(accel_psd)  # (m/s^2)^2 / Hz, extra white-acceleration noise
        self._q = model.q if params.kf_q is None else params.kf_q

    def _predict(self, x, P, dt, u):
        dm = self.model.discrete(dt)
        Q = self._q * np.outer(dm.E, dm.E)
        if self.accel_psd > 0.0:
            Q = Q + self.accel_psd * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
        return kf_predict(x, P, self.model, dm, u, Q, self.ekf, self.params.clamp_standstill)

    def _apply(self, x, P, meas):
        return kf_update(x, P, meas)


class FOHFilter(_FilterBase):
    """The paper's "direct measurements with First-Order Hold" (Section IV).

    The estimate is the last received odometer measurement (position: odometer origin +
    distance; velocity: speed). At a time without a fresh measurement it is the straight line
    through the last two received samples, extrapolated to the current time (one sample: held).
    No model, no covariance (NaN), no gate. Balise readings are validated and counted but not
    used (reason ``ignored``): the paper's FOH compensates the one sensor stream, and mixing a
    balise sample into the two-point line makes the slope explode when a balise and an odometer
    sample are milliseconds apart (seen on metro_demo: 1.6 km errors).
    """

    name = "foh"

    def __init__(self, model: WenModel, params: FilterParams, x0, t0: float = 0.0):
        super().__init__(model, replace(params, gate=math.inf), x0,
                         np.full((2, 2), np.nan), t0, None)
        self._hist: list[list[tuple[float, float]]] = [[(t0, float(x0[0]))],
                                                       [(t0, float(x0[1]))]]

    def _extrapolate(self, i: int, t: float, hist=None) -> float:
        h = (hist or self._hist)[i]
        if len(h) == 1 or h[-1][0] == h[-2][0]:
            return h[-1][1]
        (t1, y1), (t2, y2) = h[-2], h[-1]
        return y2 + (y2 - y1) * (t - t2) / (t2 - t1)

    def _propagate(self, t):
        x = np.array([self._extrapolate(0, t), self._extrapolate(1, t)])
        return x, self.P, self.actuator

    def _predict(self, x, P, dt, u):  # pragma: no cover - not used (propagate overridden)
        return x, P

    def _apply(self, x, P, meas):  # pragma: no cover - not used (update overridden)
        return x, P

    def update(self, reading) -> Decision:
        kind, meas = self._measurement(reading)
        if isinstance(meas, str):
            return self._decide(False, meas)
        t = float(reading.stamp)
        if kind == "balise":  # time moves on (as for the other filters), data unused
            self.x = np.array([self._extrapolate(0, t), self._extrapolate(1, t)])
            self.t = t
            self._last_seq[kind] = int(reading.seq)
            self._last_stamp[kind] = t
            return self._decide(True, R.IGNORED)
        hist = [list(h) for h in self._hist]
        for row, y, ok in zip(meas.C, meas.y, meas.mask):
            if ok:
                i = int(np.argmax(row))
                if hist[i][-1][0] == t:
                    hist[i][-1] = (t, float(y))
                else:
                    hist[i] = (hist[i] + [(t, float(y))])[-2:]
        self._hist = hist
        self.x = np.array([self._extrapolate(0, t), self._extrapolate(1, t)])
        self.t = t
        self._last_seq[kind] = int(reading.seq)
        self._last_stamp[kind] = t
        received = bool(np.any(meas.mask))
        self._used |= received
        return self._decide(True, R.OK if received else R.MISSING)


# ---------------------------------------------------------------------------------------------
# Conveniences for the ROS node
# ---------------------------------------------------------------------------------------------

def make_robust_filter(train, line, x0, t0: float = 0.0, Sigma0=None, q: float = 0.49,
                       uncertainty: str = "velocity", **params) -> RobustFilter:
    """A :class:`RobustFilter` from ``train.yaml`` / ``line.yaml`` objects.

    ``x0 = (position m, speed m/s)`` at ``t0``; ``Sigma0`` defaults to
    ``diag(distance_variance, speed_variance)``; ``params`` are :class:`FilterParams` fields
    (``alpha_bar``, ``epsilon``, ``gate``, ``odometer_origin``, ...). ``distance_variance`` and
    ``speed_variance`` default to the odometer noise stated in ``train.yaml``.
    ``uncertainty="velocity"`` is the tight, exact structure of the v^2 term (recommended);
    ``"paper"`` reproduces Lemma 1 with E = I as printed.
    """
    params.setdefault("distance_variance", max(train.odometer_distance_std ** 2, 1e-4))
    params.setdefault("speed_variance", max(train.odometer_speed_std ** 2, 1e-6))
    p = FilterParams(**params)
    if Sigma0 is None:
        Sigma0 = np.diag([p.distance_variance, p.speed_variance])
    model = WenModel.from_params(train, line, q, uncertainty=uncertainty)
    return RobustFilter(model, p, np.asarray(x0, float), np.asarray(Sigma0, float), t0,
                        brake=train.brake)


def covariance16(Sigma: np.ndarray) -> list[float]:
    """``TrainState.covariance``: row-major 4x4 over (position, velocity, acceleration,
    braking_rate) with the 2x2 ``Sigma`` in the top-left corner and NaN elsewhere."""
    out = np.full((4, 4), np.nan)
    out[:2, :2] = Sigma
    return [float(v) for v in out.ravel()]
