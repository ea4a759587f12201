"""Adapters from CONTRACT.md message fields to the estimator cores (pure).

Each adapter turns the dict fields of ``odometer``, ``balise`` and ``control`` messages into
calls of one filter core and reports its state as a :class:`~train_estimation.core.runner.Output`.
The ROS nodes and the offline replay (``replay.py``) use the same adapters through
:class:`~train_estimation.core.runner.EstimatorRunner`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from train_core.model import Line, TrainParams

from .braking_filters import GSMA, QGRBPF, SMA, BrakingKF, DiscreteRBPF, sticky_transition
from .braking_model import BrakingModel, BrakingParams
from .robust_filter import (
    BaliseReading,
    FilterParams,
    OdometerReading,
    RobustFilter,
    covariance16,
)
from .runner import Output
from .wen_model import WenModel

NAN16 = (math.nan,) * 16


@dataclass(frozen=True)
class StartState:
    """Where the train is when the estimator starts (the railway knows its stabling point)."""

    position: float  # m, front end; also where the odometer distance is zero
    position_std: float = 5.0  # m
    velocity: float = 0.0  # m/s
    velocity_std: float = 0.5  # m/s


# ---------------------------------------------------------------------------------------------
# Wen et al. (2017) recursive robust filter
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class RobustConfig:
    q: float = 0.49  # N^2, bound on the squared wind force (Wen eq. (7))
    epsilon: float | None = None  # -, eq. (21); None = per-step minimiser
    alpha_bar: float = 0.875  # -, Prob(odometer packet received), eq. (12)
    gate: float = 8.0  # -, innovation gate in standard deviations
    use_distance: bool = True  # odometer distance as a position measurement
    distance_variance: float = 1.0  # m^2, variance of (origin + distance) as a position reading
    period: float = 0.1  # s, odometer sample period (lost samples are detected on this grid)


class RobustAdapter:
    """Drives :class:`RobustFilter`; a lost odometer sample enters as ``received=False``."""

    source = "robust_filter"

    def __init__(self, train: TrainParams, line: Line, start: StartState,
                 cfg: RobustConfig = RobustConfig(), filter_cls=RobustFilter):
        self.model = WenModel.from_params(train, line, q=cfg.q)
        self.params = FilterParams(alpha_bar=cfg.alpha_bar, epsilon=cfg.epsilon, gate=cfg.gate,
                                   use_distance=cfg.use_distance,
                                   distance_variance=cfg.distance_variance,
                                   speed_variance=train.odometer_speed_std ** 2,
                                   odometer_origin=start.position)
        self.train, self.start_state, self.cfg, self.filter_cls = train, start, cfg, filter_cls
        self.f: RobustFilter | None = None
        self.last_odo: tuple[float, int] | None = None  # (stamp, seq) of the last odometer slot

    def start(self, t0: float) -> None:
        s = self.start_state
        self.f = self.filter_cls(self.model, self.params, [s.position, s.velocity],
                                 np.diag([s.position_std ** 2, s.velocity_std ** 2]), t0=t0,
                                 brake=self.train.brake)

    def control(self, stamp: float, fields: dict) -> str:
        d = self.f.set_control(stamp, float(fields["target_acceleration"]))
        return "" if d.accepted else d.reason

    def odometer(self, stamp: float, fields: dict) -> str:
        d = self.f.update(OdometerReading(stamp=stamp, seq=int(fields["seq"]),
                                          distance=float(fields["distance"]),
                                          speed=float(fields["speed"]),
                                          speed_variance=float(fields["speed_variance"])))
        if d.accepted:
            self.last_odo = (stamp, int(fields["seq"]))
        return "" if d.accepted else d.reason

    def balise(self, stamp: float, fields: dict) -> str:
        d = self.f.update(BaliseReading(stamp=stamp, seq=int(fields["seq"]),
                                        balise_id=int(fields["balise_id"]),
                                        position=float(fields["position"]),
                                        position_variance=float(fields["position_variance"])))
        return "" if d.accepted else d.reason

    def predict_to(self, t: float) -> None:
        # alpha(k) = 0 from the sequence numbers: no sample for this slot arrived in time, so the
        # slot enters as a lost packet (Wen eq. (11)-(12)) and the bound (22) grows accordingly.
        if self.last_odo is not None:
            last_stamp, last_seq = self.last_odo
            slots = int(round((t - last_stamp) / self.cfg.period))
            if slots >= 1:
                d = self.f.update(OdometerReading(stamp=t, seq=last_seq + slots, received=False))
                if d.accepted:
                    self.last_odo = (t, last_seq + slots)
        self.f.predict_to(t)

    def output(self, t: float) -> Output:
        x, P = self.f.estimate()
        return Output(stamp=t, position=float(x[0]), velocity=float(x[1]),
                      acceleration=math.nan, braking_rate=math.nan,
                      covariance=tuple(covariance16(P)),
                      measurement_used=self.f.pop_measurement_used())

    @property
    def counters(self) -> dict:
        return dict(self.f.counters) if self.f else {}


# ---------------------------------------------------------------------------------------------
# Zheng et al. (2015) braking-rate estimators
# ---------------------------------------------------------------------------------------------

ALGORITHMS = ("gsma", "sma", "rbpf", "qgrbpf", "kf")


@dataclass(frozen=True)
class BrakingConfig:
    algorithm: str = "kf"  # one of ALGORITHMS (kf: the exact estimator, README "Braking rate")
    values: tuple[float, ...] = tuple(np.round(np.linspace(1.3, 0.0, 14), 10))  # discrete f set
    #   (up to 1.3 so that a prior centred on the nominal 1.0 is not cut in half by the set)
    f_prior_std: float = 0.15  # -, std of every algorithm's f prior, centred on train.yaml's
    #   braking_rate (on a discrete set: the Gaussian's mass per value)
    merge: bool = True  # GSMA/SMA: merge particles on one value after each step instead of
    #   pruning to the N best (at most (#values) x (children) KFs per step); pruning to N every
    #   step makes GSMA over-confident on metro_drift (2-sigma coverage 0.83), Q = 500 costs a
    #   p99 of ~3 ms; merged: coverage 1.00 at the KF's accuracy (README)
    n_init: int = 50  # N0, initial particles
    n_keep: int = 50  # N, particles kept after pruning
    q_max: int = 500  # Q, prune when the branched count exceeds it (merge = False only)
    rbpf_particles: int = 250  # RBPF particle count
    rbpf_p_move: float = 0.1  # RBPF sticky kernel: probability of moving to a neighbour value
    branch_p_move: float = 0.1  # GSMA/SMA children prior: P(move to a neighbour value); -1 =
    #   the paper's uniform prior over the children, which forgets f at every branching
    qgrbpf_particles: int = 50
    qgrbpf_q_theta: float = 3e-4  # 1/s, random-walk variance of f per second (Q-GRBPF; as the KF)
    kf_q_theta: float = 3e-4  # 1/s, random-walk variance of f per second of braking (KF; chosen
    #   on metro_drift: 1e-3 tracks as fast but its std breaks the ATO gate, 1e-4 lags)
    transition_interval: float = 1.0  # s between f transitions, whatever the message rate
    accel_var: float = 0.02  # m^2/s^3, white acceleration noise PSD on v (unmodelled forces)
    ahat_var: float = 0.001  # m^2/s^5, white noise PSD on a_hat (actuator mismatch)
    distance_variance: float = 1.0  # m^2, odometer distance as a position reading
    use_distance: bool = True
    standstill_speed: float = 0.3  # m/s: at or below (estimated), with a brake command, the
    #   train is held at rest and f is not observed (odometer speed noise is ~0.1 m/s)
    min_brake: float = 0.1  # m/s^2: weaker braking commands do not inform f
    seed: int = 0  # particle-filter random stream


class BrakingAdapter:
    """Drives one of GSMA, SMA, RBPF, Q-GRBPF or the exact KF over the (D, v, a_hat, a_z) model of
    Zheng eq. (4). Every algorithm's f prior is N(train.brake.braking_rate, f_prior_std^2).

    The known acceleration offset ``d`` on v is minus the believed Davis resistance and gradient
    at the current estimate (Zheng treat them as noise; here they are known forces).
    """

    def __init__(self, train: TrainParams, line: Line, start: StartState,
                 cfg: BrakingConfig = BrakingConfig()):
        if cfg.algorithm not in ALGORITHMS:
            raise ValueError(f"algorithm must be one of {ALGORITHMS}, got {cfg.algorithm!r}")
        if train.brake.delay <= 0:
            raise ValueError("the braking model needs a transport delay > 0 (Pade lambda = 2/T)")
        self.train, self.line, self.start_state, self.cfg = train, line, start, cfg
        self.source = cfg.algorithm
        self.fam = BrakingModel(BrakingParams(
            tau=train.brake.time_constant, delay=train.brake.delay, dt=cfg.transition_interval,
            noise_model="white", accel_var=cfg.accel_var, ahat_var=cfg.ahat_var,
            meas_var=(cfg.distance_variance, train.odometer_speed_std ** 2, 1.0),
            standstill_speed=cfg.standstill_speed, min_brake=cfg.min_brake))
        values = np.asarray(cfg.values, dtype=float)
        M, p = len(values), cfg.branch_p_move
        if not (math.isfinite(cfg.f_prior_std) and cfg.f_prior_std > 0):
            raise ValueError(f"f_prior_std must be finite and > 0, got {cfg.f_prior_std!r}")
        prior = (float(train.brake.braking_rate), float(cfg.f_prior_std))
        if cfg.algorithm == "gsma":
            # children: the group of three neighbours; prior stay 1 - p, each neighbour p / 2
            self.filt = GSMA(self.fam, values, n_init=cfg.n_init, n_keep=cfg.n_keep,
                             q_max=cfg.q_max,
                             transition=None if p < 0 else sticky_transition(M, p),
                             prior=prior, merge=cfg.merge)
        elif cfg.algorithm == "sma":
            # children: every value (the paper's SMA); prior stay 1 - p, the rest p / (M - 1)
            full = (1 - p) * np.eye(M) + p / (M - 1) * (1 - np.eye(M))
            self.filt = SMA(self.fam, values, n_init=cfg.n_init, n_keep=cfg.n_keep,
                            q_max=cfg.q_max, transition=None if p < 0 else full,
                            prior=prior, merge=cfg.merge)
        elif cfg.algorithm == "rbpf":
            self.filt = DiscreteRBPF(self.fam, values,
                                     sticky_transition(len(values), cfg.rbpf_p_move),
                                     cfg.rbpf_particles, prior=prior)
        elif cfg.algorithm == "qgrbpf":
            self.filt = QGRBPF(self.fam, [(float(values.min()), float(values.max()))],
                               cfg.qgrbpf_particles, q_theta=cfg.qgrbpf_q_theta, prior=prior)
        else:
            self.filt = BrakingKF(self.fam, q_theta=cfg.kf_q_theta, f_prior=prior)
        self.filt.transition_interval = cfg.transition_interval
        self.rng = np.random.default_rng(cfg.seed)
        self.a_tar = 0.0
        self.est = None
        self.used = False
        self.balises = {b.id: b.position for b in line.balises}
        self.last_seq: int | None = None  # odometer seq: duplicates and replays are refused

    def start(self, t0: float) -> None:
        s = self.start_state
        P0 = np.diag([s.position_std ** 2, s.velocity_std ** 2, 0.01, 0.01])
        self.est = self.filt.reset([s.position, s.velocity, 0.0, 0.0], P0, rng=self.rng, t0=t0)

    def _d(self) -> float:
        """m/s^2, known acceleration on v: -(Davis resistance + gradient) per effective mass."""
        x, v = float(self.est.x_mean[0]), max(float(self.est.x_mean[1]), 0.0)
        tr = self.train
        return -(tr.resistance_accel(v) + self.line.gradient_accel(x) * tr.mass /
                 tr.effective_mass) if v > 0 else 0.0

    def _step(self, stamp: float, y=None, mask=None, meas_var=None) -> str:
        e = self.filt.step(self.a_tar, y, mask, self.rng, t=stamp, meas_var=meas_var, d=self._d())
        if not e.accepted:
            return e.reason or "rejected"
        self.est = e
        self.used |= e.measurement_used
        return ""

    def _advance(self, stamp: float) -> str:
        if self.filt.t is not None and stamp > self.filt.t:
            return self._step(stamp)
        return ""

    def control(self, stamp: float, fields: dict) -> str:
        a = float(fields["target_acceleration"])
        if not (math.isfinite(a) and math.isfinite(stamp)):
            return "non_finite"
        if self.filt.t is not None and stamp < self.filt.t:
            return "out_of_order"
        reason = self._advance(stamp)  # the old command holds up to the new one's stamp
        if not reason:
            self.a_tar = a
        return reason

    def odometer(self, stamp: float, fields: dict) -> str:
        seq = int(fields["seq"])
        if self.last_seq is not None and seq <= self.last_seq:
            return "duplicate" if seq == self.last_seq else "out_of_order"
        var = float(fields["speed_variance"])
        if not (math.isfinite(var) and var > 0):
            return "non_positive_variance" if math.isfinite(var) else "non_finite"
        y = [self.start_state.position + float(fields["distance"]), float(fields["speed"]),
             math.nan]
        reason = self._step(stamp, y, [self.cfg.use_distance, True, False],
                            [self.cfg.distance_variance, var, 1.0])
        if not reason:
            self.last_seq = seq
        return reason

    def balise(self, stamp: float, fields: dict) -> str:
        pos = self.balises.get(int(fields["balise_id"]))
        if pos is None:
            return "unknown_balise"
        var = float(fields["position_variance"])
        if not (math.isfinite(var) and var > 0):
            return "non_positive_variance" if math.isfinite(var) else "non_finite"
        return self._step(stamp, [pos, math.nan, math.nan], [True, False, False], [var, 1.0, 1.0])

    def predict_to(self, t: float) -> None:
        self._advance(t)

    def output(self, t: float) -> Output:
        e = self.est
        used, self.used = self.used, False
        return Output(stamp=t, position=float(e.mean[0]), velocity=float(e.mean[1]),
                      acceleration=float(e.mean[2]), braking_rate=float(e.mean[3]),
                      covariance=tuple(float(v) for v in np.asarray(e.cov).ravel()),
                      measurement_used=used)

    @property
    def counters(self) -> dict:
        return dict(self.filt.rejected)
