"""Recursive robust filter under packet dropouts (Wen et al. 2017) and its baselines: the
stateful filters a node (through ``estimators``) calls in time order.

Where the pieces are:

* ``robust_steps``: the paper's maths -- eq. (13), (21)-(24), the rule for gamma and epsilon,
  the paper slip in the gain (module docstring there);
* ``robust_compiled``: the same prediction and gated update as one compiled scalar call each
  (numba; interpreted without it, the same bits), which :class:`RobustFilter` runs
  (``robust_steps`` for what the kernels leave to it: exceptions, non-finite states);
* ``readings``: the message-shaped readings, decisions and the covariance layout;
* ``filter_base``: settings (:class:`FilterParams`), validation with reasons, counters, time
  keeping and the believed actuator, shared by the filters below;
* ``kalman``: the Kalman predict/update of :class:`IntermittentKF`.

Baselines: :class:`FOHFilter` (the paper's "direct measurements with first-order hold",
odometer only),
:class:`IntermittentKF` (KF with the same nominal model, update skipped for missing channels;
Sinopoli et al. 2004) and the oracle (:class:`IntermittentKF` with ``ekf=True`` on the true
model with the true actuator output as input).


Pure: numpy/scipy only.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from .. import reasons as R
from ..numerics import kalman
from . import robust_compiled
from .filter_base import FilterBase, FilterParams, filter_params_from_train
from .readings import REASONS, BaliseReading, Decision, OdometerReading, covariance16
from .robust_steps import (
    Measurement,
    choose_gamma,
    packet_moments,
    robust_predict,
    robust_predict_cov,
    robust_update,
)
from .wen_model import DiscreteWen, WenModel

__all__ = [
    "Measurement", "Decision", "OdometerReading", "BaliseReading", "FilterParams",
    "choose_gamma", "robust_predict_cov", "robust_predict", "robust_update", "packet_moments",
    "kf_predict", "kf_update", "RobustFilter", "IntermittentKF", "FOHFilter", "REASONS",
    "make_robust_filter", "covariance16", "FilterBase",
]


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
    return xp, kalman.propagate_cov(P, J, Q)


def kf_update(x: np.ndarray, P: np.ndarray, meas: Measurement) -> tuple[np.ndarray, np.ndarray]:
    """Kalman update with the received channels only (intermittent observations): the
    sequential update of ``kalman.update`` (R is diagonal). Nothing received: returned
    unchanged."""
    m = meas.mask
    if not np.any(m):
        return x, P
    xn, Pn, _ = kalman.update(x[None], P[None], meas.y, meas.C, np.diag(meas.R), m)
    return xn[0], Pn[0]


class RobustFilter(FilterBase):
    """Wen et al. (2017) recursive robust filter, eq. (13), (21), (22), (24).

    ``estimate()`` returns ``(x^(k|k), Sigma(k|k))``; ``Sigma`` is the upper bound of the
    error second moment (Theorem 2). ``last_gamma`` / ``last_epsilon`` hold the values of the
    last prediction step.
    """

    name = "robust"
    #: each prediction and each gated update one call of ``robust_compiled``'s scalar kernels
    #: (the formulas of ``robust_steps``, equal to rounding; compiled by numba where installed,
    #: else interpreted: the same bits); False: ``robust_steps``' numpy form
    kernels = True

    def __init__(self, model: WenModel, params: FilterParams, x0, Sigma0, t0: float = 0.0,
                 brake=None):
        super().__init__(model, params, x0, Sigma0, t0, brake)
        self.last_gamma = math.nan
        self.last_epsilon = math.nan
        if self.kernels:
            robust_compiled.warm_up()  # numba's cache loaded here, not in a first callback

    def _predict(self, x, P, dt, u):
        dm = self.model.discrete(dt)
        eps = self.params.epsilon
        if self.kernels:
            m = self.model
            # the known input's two forces as WenModel.known_input forms them
            status, xp, Sp, gamma, eps_used = robust_compiled.predict(
                x, P, dm.A, dm.B, dm.E, dm.HH, dm.hh, dm.EE, dm.Eu, float(m.q),
                eps is None, 0.0 if eps is None else float(eps), m.drive_mass * u,
                m.a + m.gradient_force(x[0]), float(dt), bool(self.params.clamp_standstill))
            if status == robust_compiled.OK:
                self.last_gamma, self.last_epsilon = gamma, eps_used
                return xp, Sp
            # FALLBACK: the numpy form raises, or gives the non-finite state, as it always did
        xp, Sp, self.last_gamma, self.last_epsilon = robust_predict(
            x, P, self.model, dm, u, eps, self.params.clamp_standstill)
        return xp, Sp

    def _apply(self, x, P, meas):
        xn, Sn, _ = robust_update(x, P, meas, self.params.gain)
        return xn, Sn

    def _gated_apply(self, x, P, meas, since):
        gain = self.params.gain
        if self.kernels and gain in ("corrected", "paper"):
            p = self.params
            status, xn, Sn = robust_compiled.update(
                x, P, meas.y, meas.C, meas.R, meas.abar, meas.group, meas.mask,
                gain == "corrected", float(p.gate), float(p.gate_accel), since)
            if status == robust_compiled.OK:
                return xn, Sn
            if status == robust_compiled.GATE:
                return None
        return super()._gated_apply(x, P, meas, since)  # the numpy form, gate and all


class IntermittentKF(FilterBase):
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


class FOHFilter(FilterBase):
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
            self.order.took(kind, t, int(reading.seq))
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
        self.order.took(kind, t, int(reading.seq))
        received = bool(np.any(meas.mask))
        self._used |= received
        return self._decide(True, R.OK if received else R.MISSING)


def make_robust_filter(train, line, x0, t0: float = 0.0, Sigma0=None, q: float = 0.49,
                       uncertainty: str = "velocity", **params) -> RobustFilter:
    """A :class:`RobustFilter` from ``train.yaml`` / ``line.yaml`` objects.

    ``x0 = (position m, speed m/s)`` at ``t0``; ``Sigma0`` defaults to
    ``diag(distance_variance, speed_variance)``; ``params`` are :class:`FilterParams` fields
    (``alpha_bar``, ``epsilon``, ``gate``, ``odometer_origin``, ...); ``distance_variance`` and
    ``speed_variance`` default to the odometer noise of ``train.yaml``
    (:func:`~train_estimation.core.robust.filter_base.filter_params_from_train`).
    ``uncertainty="velocity"`` is the tight, exact structure of the v^2 term (recommended);
    ``"paper"`` reproduces Lemma 1 with E = I as printed.
    """
    p = filter_params_from_train(train, **params)
    if Sigma0 is None:
        Sigma0 = np.diag([p.distance_variance, p.speed_variance])
    model = WenModel.from_params(train, line, q, uncertainty=uncertainty)
    return RobustFilter(model, p, np.asarray(x0, float), np.asarray(Sigma0, float), t0,
                        brake=train.brake)
