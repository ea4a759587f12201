"""What every filter of ``robust_filter`` shares: settings, validation of the readings,
counters, time keeping and the believed actuator (:class:`FilterBase`).

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
``|nu_i| / sqrt(S_ii) > gate`` on any channel, S from the filter's own covariance / bound and
``gate_accel``: :meth:`FilterBase._gate_ok`),
``future_stamp`` (more than ``max_horizon`` ahead), ``numerical_failure`` -- the names of
``core/reasons.py``. Duplicates, order and the horizon are judged by the estimator's
:class:`~..numerics.stamp_order.StampOrder` (order by stamp; ``seq`` marks duplicates only, and
a ``seq`` that goes back while the stamp goes on, a sensor reset or a wrap-around, is accepted
and counted as ``seq_reset``).

Lost packets are not bad input: an odometer slot with ``received=False`` is accepted with
reason ``missing``. Accepted ``predict_to``/``set_control`` calls are not counted.


Pure: numpy only.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass

import numpy as np

from .. import reasons as R
from ..numerics.stamp_order import StampOrder
from .readings import BaliseReading, Decision, OdometerReading
from .robust_steps import Measurement
from .wen_model import Actuator, WenModel

__all__ = ["FilterParams", "FilterBase", "filter_params_from_train"]


@dataclass(frozen=True)
class FilterParams:
    """Settings shared by the filters (SI units)."""

    alpha_bar: float = 0.875  # -, Prob(odometer packet received), eq. (12)
    alpha_bar_balise: float = 1.0  # -, balise readings enter on arrival (see module doc)
    epsilon: float | None = None  # -, eq. (21); None = per-step minimiser of the trace
    gain: str = "corrected"  # "corrected" (minimises tr (22)) or "paper" (eq. (24) literally)
    gate: float = 8.0  # -, reject if |innovation| > gate * sqrt(S_ii); math.inf disables
    gate_accel: float = 0.0  # m/s^2, acceleration error allowed in the gate's look-ahead over
    #   the time since the last odometer reading taken (0: none; the nodes' gate_accel)
    use_distance: bool = True  # odometer distance as a position measurement
    distance_variance: float = 1.0  # m^2, variance of origin + distance as a position reading
    speed_variance: float = 0.01  # (m/s)^2, odometer speed variance until a packet states it
    #   (filter_params_from_train: train.yaml's, the constructors' one fallback)
    odometer_origin: float = 0.0  # m, track position where the odometer distance is zero
    balise_map_tolerance: float = 1.0  # m, max |sent position - map position|
    actuator: bool = True  # pass a_Tar through the believed delay + lag (wen_model.Actuator)
    clamp_standstill: bool = True  # project v^ onto v >= 0 (the world never rolls back)
    kf_q: float | None = None  # N^2, IntermittentKF's wind-force variance (None: model.q)
    max_dt: float = 1.0  # s, longer predictions are split (ZOH of gradient and resistance)
    max_horizon: float = 3600.0  # s, a reading further ahead of the estimate is future_stamp


def filter_params_from_train(train, **params) -> FilterParams:
    """:class:`FilterParams` with the odometer noise of ``train.yaml`` where not given: the
    one place where ``distance_variance`` and ``speed_variance`` fall back to the train file
    (``TrainParams.odometer_distance_variance`` / ``odometer_speed_variance``)."""
    params.setdefault("distance_variance", train.odometer_distance_variance)
    params.setdefault("speed_variance", train.odometer_speed_variance)
    return FilterParams(**params)


_POS = np.array([[1.0, 0.0]])
_VEL = np.array([[0.0, 1.0]])


def _finite(*vals) -> bool:
    return all(isinstance(v, (int, float, np.floating, np.integer)) and math.isfinite(v)
               for v in vals)


class FilterBase:
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
        self.t_fix = float(t0)  # s, the last received odometer reading taken, or the start
        self.counters: Counter = Counter()
        self.order = StampOrder(params.max_horizon)  # readings and commands taken (order)
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

    def shift(self, dx: float, dv: float) -> None:
        """Move the estimate by ``dx`` m and ``dv`` m/s, its covariance unchanged (the frame of
        the readings moved: the odometer's calibration, ``online/odometer_scale.py``)."""
        self.x = self.x + np.array([dx, dv])

    def inflate(self, Q: np.ndarray) -> None:
        """Add ``Q`` (2x2: m^2, m^2/s, m^2/s^2) to the covariance: an error the readings' frame
        carries that the model does not (the odometer's scale since the last balise,
        ``online/estimators.py``)."""
        self.P = self.P + np.asarray(Q, dtype=float)

    def pop_measurement_used(self) -> bool:
        """True if a received reading entered the estimate since the last call."""
        used, self._used = self._used, False
        return used

    # -- control -------------------------------------------------------------------------------
    def set_control(self, stamp: float, target_acceleration: float) -> Decision:
        if not _finite(stamp, target_acceleration):
            return self._decide(False, R.NON_FINITE)
        why = self.order.judge("control", stamp)  # commands in order among themselves
        if why:
            return self._decide(False, why)
        self.order.took("control", float(stamp))
        self.actuator.command(stamp, target_acceleration)
        return Decision(True, R.OK)  # accepted commands are not counted (rejections are)

    # -- time update ---------------------------------------------------------------------------
    def predict_to(self, t: float, control: float | None = None) -> Decision:
        """Move the estimate to time ``t`` (s). ``control`` (a_Tar, m/s^2), if given, is recorded
        as a command issued at the current filter time first."""
        if not _finite(t) or (control is not None and not _finite(control)):
            return self._decide(False, R.NON_FINITE)
        why = self.order.judge(None, t, t=self.t)
        if why:
            return self._decide(False, why)
        if control is not None:
            self.set_control(self.t, control)
        self.x, self.P, self.actuator = self._propagate(t)
        self.t = float(t)
        return Decision(True, R.OK)

    def _propagate(self, t: float):
        """Prediction to ``t`` on copies; returns (x, P, actuator)."""
        act = self.actuator.copy()
        x, P = self.x, self.P
        for dt, u in self.steps(self.t, t, act):
            x, P = self._predict(x, P, dt, u)
        return x, P, act

    def steps(self, t0: float, t: float, act):
        """The prediction steps from ``t0`` to ``t``: ``(dt, u)``, steps of at most
        ``params.max_dt`` s and ``u`` the mean achieved control acceleration over each through
        ``act`` (which advances)."""
        tc = t0
        while t - tc > 0.0:
            dt = min(t - tc, self.params.max_dt)
            if t - (tc + dt) < 1e-9:  # avoid a sliver of a step from round-off
                dt = t - tc
            yield dt, act.mean(tc, tc + dt)
            tc += dt

    def _predict(self, x, P, dt, u):  # pragma: no cover - abstract
        raise NotImplementedError

    def _apply(self, x, P, meas: Measurement):  # pragma: no cover - abstract
        raise NotImplementedError

    # -- measurement update --------------------------------------------------------------------
    def _check(self, kind: str, reading, values: tuple, variance: float | None) -> str | None:
        """The checks every reading gets: finite stamp and values, an integer seq, a positive
        stated variance, then the order (:class:`StampOrder`). None when it passes."""
        if not _finite(reading.stamp, *values) or not isinstance(reading.seq, (int, np.integer)):
            return R.NON_FINITE
        if variance is not None and variance <= 0.0:
            return R.NON_POSITIVE_VARIANCE
        return self.order.judge(kind, reading.stamp, int(reading.seq), self.t) or None

    def _odometer_check(self, reading: OdometerReading) -> str | None:
        """The reason an odometer reading is refused before the gate (its own checks and its
        order: all :meth:`_measurement` refuses it for), or None; without building its
        channels (an adapter asks before entering lost slots, then :meth:`update` asks
        again)."""
        values = ((reading.distance, reading.speed, reading.speed_variance)
                  if reading.received else ())
        return self._check("odometer", reading, values,
                           reading.speed_variance if reading.received else None)

    def _measurement(self, reading) -> tuple[str, Measurement | str]:
        """Validate a reading and turn it into channels, or return the rejection reason."""
        p = self.params
        if isinstance(reading, OdometerReading):
            kind = "odometer"
            bad = self._odometer_check(reading)
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
            bad = self._check(kind, reading, (reading.position, reading.position_variance),
                              reading.position_variance)
            if bad:
                return kind, bad
            pos = self._balise_pos.get(int(reading.balise_id))
            if pos is None:
                return kind, R.UNKNOWN_BALISE
            if abs(pos - reading.position) > p.balise_map_tolerance:
                return kind, R.BALISE_MAP_MISMATCH
            if reading.measured is not None:
                if not math.isfinite(reading.measured):
                    return kind, R.NON_FINITE
                pos = float(reading.measured)
            return kind, Measurement(
                y=np.array([pos]), C=_POS.copy(), R=np.array([[reading.position_variance]]),
                abar=np.array([p.alpha_bar_balise]), group=np.zeros(1, int),
                mask=np.array([True]))
        raise TypeError(f"unknown reading type {type(reading).__name__}")

    def _gate_ok(self, x, P, meas: Measurement, since: float = 0.0) -> bool:
        """Every channel's innovation within ``gate`` standard deviations of ``S = C P C^T + R``
        plus the effect of an acceleration error up to ``gate_accel`` over ``since`` (s, the
        time since the last odometer reading taken: the prediction's own error grows for as
        long as no reading corrects it, so a filter that was wrong, e.g. started on a moving
        train, takes the odometer again once the train could have reached its reading)."""
        g = self.params.gate
        if not math.isfinite(g) or not meas.mask.any() or not np.isfinite(P).all():
            return True
        m = meas.mask
        C = meas.C[m]
        S = np.einsum("ij,jk,ik->i", C, P, C) + np.diag(meas.R)[m]
        a = self.params.gate_accel
        if a > 0.0 and since > 0.0:
            S = S + (C @ np.array([0.5 * a * since * since, a * since])) ** 2
        nu = meas.y[m] - C @ x
        return bool((np.abs(nu) <= g * np.sqrt(S)).all())

    def _gated_apply(self, x, P, meas: Measurement, since: float):
        """:meth:`_apply` if the reading passes :meth:`_gate_ok`, else None: one hook, so that
        a filter can do both in one call (``RobustFilter``: one compiled step)."""
        if not self._gate_ok(x, P, meas, since):
            return None
        return self._apply(x, P, meas)

    def update(self, reading, predicted=None) -> Decision:
        """Validate and apply one reading (predicting to its stamp first). See class doc.
        ``predicted``: ``self._propagate(reading.stamp)``'s result when the caller has it from
        this very state (``online/estimators.py``: a lost slot's published prediction)."""
        kind, meas = self._measurement(reading)
        if isinstance(meas, str):
            return self._decide(False, meas)
        x, P, act = self._propagate(float(reading.stamp)) if predicted is None else predicted
        applied = self._gated_apply(x, P, meas, float(reading.stamp) - self.t_fix)
        if applied is None:
            return self._decide(False, R.OUTSIDE_GATE)
        x, P = applied
        if not (np.isfinite(x).all() and _finite_or_nan_cov(P)):
            return self._decide(False, R.NUMERICAL_FAILURE)  # keep the old state
        self.x, self.P, self.actuator, self.t = x, P, act, float(reading.stamp)
        if self.order.took(kind, float(reading.stamp), int(reading.seq)):
            self.counters[R.SEQ_RESET] += 1
        received = bool(meas.mask.any())
        if kind == "odometer" and received:
            self._speed_var = float(reading.speed_variance)
            self.t_fix = self.t
        self._used |= received
        return self._decide(True, R.OK if received else R.MISSING)


def _finite_or_nan_cov(P) -> bool:
    P = np.asarray(P)  # (the array's own reductions: np.all's dispatch costs more than they)
    return bool(np.isfinite(P).all() or np.isnan(P).all())
