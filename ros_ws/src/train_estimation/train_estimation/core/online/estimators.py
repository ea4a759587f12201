"""Adapters from docs/interfaces.md message fields to the estimator cores (pure).

Each adapter turns the dict fields of ``odometer``, ``balise`` and ``control`` messages into
calls of one filter core and reports its state as a
:class:`~train_estimation.core.online.runner.Output`.
The ROS nodes and the offline replay (``replay.py``) use the same adapters through
:class:`~train_estimation.core.online.runner.EstimatorRunner`.
"""

from __future__ import annotations

import copy
import itertools
import math
from dataclasses import dataclass, replace

import numpy as np
from train_core.config import param, require, require_finite
from train_core.dynamics import GradientLookup
from train_core.model import Line, TrainParams

from .. import reasons as R
from ..braking.braking_filters import (
    GSMA,
    QGRBPF,
    SMA,
    BrakingKF,
    DiscreteRBPF,
    sma_transition,
    sticky_transition,
)
from ..braking.braking_model import BrakingModel, BrakingParams
from ..numerics.stamp_order import StampOrder
from ..robust.filter_base import filter_params_from_train
from ..robust.readings import BaliseReading, OdometerReading, covariance16
from ..robust.robust_filter import RobustFilter
from ..robust.wen_model import WenModel
from .calibrated_odometry import DistanceAsPosition, OdometryConfig
from .runner import Output

NAN16 = (math.nan,) * 16


@dataclass(frozen=True)
class StartState:
    """Where the train is when the estimator starts (the railway knows its stabling point)."""

    position: float  # m, front end; also where the odometer distance is zero
    position_std: float = 5.0  # m
    position_fault: float = 50.0  # m, the largest start error beyond position_std that the
    #   protection levels cover until a balise confirms the start (odometer_scale module doc)
    velocity: float = 0.0  # m/s
    velocity_std: float = 0.5  # m/s


@dataclass(frozen=True)
class NodeConfig:
    """Parameters every estimator node has (declared from this metadata; config/*.yaml
    document them)."""

    line_file: str = param("", "", "line.yaml; '' = metro_demo's line")
    train_file: str = param("", "", "train.yaml the estimator believes; required ('' is "
                            "refused unless use_demo_line is true: then metro_demo's train)")
    initial_position: float = param(math.nan, "m", "position at start (odometer origin); NaN = "
                                    "first station of the line")
    initial_position_std: float = param(5.0, "m", "standard deviation of the initial position",
                                        lo=0.0)
    initial_position_fault: float = param(
        StartState.position_fault, "m", "the largest error of initial_position beyond its "
        "standard deviation that the protection levels cover until a balise confirms the start "
        "(a position keyed in or stored from the last mission; a bias bound, as ARAIM's b_nom); "
        "0 = the start is trusted as stated", lo=0.0)
    odometer_rate: float = param(10.0, "Hz", "odometer sample rate = output rate", lo=0.0)
    output_delay: float = param(0.05, "s", "without control messages, an estimate of time t is "
                                "output at clock t + delay", lo=0.0)
    control_clock: str = param("auto", "", "clock of control stamps: auto (judged from "
                               "arrivals; drift tracked) | same (the odometer's: a simulator) | "
                               "reference (the receive clock)")
    count_clock: bool = param(True, "", "without a sample counter, judge the odometer's stamps "
                              "by its count while the train moves (the speed's scale and "
                              "its lag behind the count learnt); false: by their arrivals "
                              "alone, for a producer whose speed is not its count's rate")
    max_future: float = param(600.0, "s", "a stamp this far after its arrival is refused "
                              "(future_stamp)", lo=0.0)
    wait_for_subscribers: int = param(0, "", "output nothing until the estimate topic has this "
                                      "many subscribers (a recorder sees every estimate)", lo=0)
    tick_period: float = param(0.05, "s", "period of the node's timer (steady clock) that "
                               "publishes the estimates due by the clock alone: a lost "
                               "reading's slot, a silent input", lo=0.0)
    slot_grace: float = param(0.5, "s", "a slot whose odometer reading has not arrived this long "
                              "after it was due (on the train clock's tracked offset and rate) "
                              "is published as a prediction (not on simulated time, "
                              "use_sim_time: there the inputs' watermarks publish it)", lo=0.0)

    def __post_init__(self):
        require_finite(self, ("initial_position_std", "odometer_rate", "tick_period"))
        require(math.isfinite(self.output_delay) and self.output_delay >= 0, "output_delay",
                self.output_delay, "must be >= 0")
        require(math.isfinite(self.slot_grace) and self.slot_grace >= 0, "slot_grace",
                self.slot_grace, "must be >= 0")


# ---------------------------------------------------------------------------------------------
# Wen et al. (2017) recursive robust filter
# ---------------------------------------------------------------------------------------------

def _eps_to_ros(v):
    return -1.0 if v is None else v


def _eps_from_ros(v):
    return None if v <= 0 else v


@dataclass(frozen=True)
class RobustConfig(OdometryConfig):
    """Settings of the robust filter node (declared from this metadata, config/robust_filter.yaml
    documents them)."""

    q: float = param(0.49, "N^2", "bound q on the squared wind force, w^2 <= q (Wen eq. (7))",
                     lo=0.0)
    epsilon: float | None = param(None, "-", "epsilon of eq. (21) (> 0); -1 (None) = choose it "
                                  "per step to minimise the bound",
                                  ros=(_eps_to_ros, _eps_from_ros))
    alpha_bar: float = param(0.875, "-", "Prob(odometer packet received), alpha-bar of eq. (12)",
                             lo=0.0, hi=1.0)
    period: float = param(0.1, "s", "nominal odometer sample period (lost samples: gap / period "
                          "- 1); the node sets it from odometer_rate", node=False)
    outage_slots: int = param(8, "-", "more lost odometer slots in a row are an outage: "
                              "prediction only", lo=0)

    def __post_init__(self):
        require(0.0 < self.alpha_bar <= 1.0, "alpha_bar", self.alpha_bar, "must be in (0, 1]")
        require(math.isfinite(self.q) and self.q >= 0, "q", self.q, "must be finite and >= 0")
        super().__post_init__()
        require(self.epsilon is None or self.epsilon > 0, "epsilon", self.epsilon,
                "must be > 0 (or None: per step)")
        require(math.isfinite(self.period) and self.period > 0, "period", self.period,
                "must be > 0")
        require(self.outage_slots >= 0, "outage_slots", self.outage_slots, "must be >= 0")


class RobustAdapter(DistanceAsPosition):
    """Drives :class:`RobustFilter` on the odometer's own clock.

    Lost odometer samples are found from the odometer's stamps (not from an output grid, so any
    epoch, phase and drift work): when a sample arrives ``n = round(gap / period) - 1`` slots
    after the previous one, the ``n`` lost slots enter first as ``received=False`` at evenly
    spaced stamps (Wen eq. (11)-(12): alpha = 0, the bound (22) takes the expectation over
    alpha). A gap of more than ``outage_slots`` slots is not Bernoulli loss (probability
    ``(1 - abar)^n``, 6e-8 for 8 slots at abar = 0.875) but an outage (a tunnel, a dead
    radio): no expected update is taken for it, the bound grows by prediction alone (21), so
    that it still covers the error after the outage (event ``outage``). Estimates between
    samples are predictions on copies: the state only moves with readings.
    """

    source = "robust_filter"

    def __init__(self, train: TrainParams, line: Line, start: StartState,
                 cfg: RobustConfig = RobustConfig(), filter_cls=RobustFilter):
        self.model = WenModel.from_params(train, line, q=cfg.q)
        self.params = filter_params_from_train(
            train, alpha_bar=cfg.alpha_bar, epsilon=cfg.epsilon, gate=cfg.gate,
            gate_accel=cfg.gate_accel, use_distance=cfg.use_distance,
            distance_variance=cfg.distance_variance, odometer_origin=start.position)
        self.train, self.start_state, self.cfg, self.filter_cls = train, start, cfg, filter_cls
        self.line = line  # the integrity monitor's standing check reads the map's gradient
        self.f: RobustFilter | None = None
        self.last_odo: tuple[float, int] | None = None  # (stamp, seq) of the last odometer slot
        self.outages = 0
        # (state token, t, x, P, actuator, exact mean, source) of the last prediction; source =
        # (x, P, actuator, number of commands) of the filter it was made from when made in one go
        # from the filter's own state (a lost slot's update takes it then: _predicted)
        self._pred = None
        self._init_odometry()

    def start(self, t0: float) -> None:
        s = self.start_state
        self.f = self.filter_cls(self.model, self.params, [s.position, s.velocity],
                                 np.diag([s.position_std ** 2, s.velocity_std ** 2]), t0=t0,
                                 brake=self.train.brake)

    def control(self, stamp: float, fields: dict) -> str:
        a = float(fields["target_acceleration"])
        if math.isfinite(a) and abs(a) > self.cfg.max_command:
            return f"{R.OUTSIDE_GATE}: command {a:.3g} m/s^2"
        d = self.f.set_control(stamp, a)
        if d.accepted and self._pred is not None and stamp + self.f.actuator.delay < self._pred[1]:
            self._pred = None  # a command that acts before the cached prediction: start afresh
        return "" if d.accepted else d.reason

    def _lost_slots(self, stamp: float, seq: int) -> None:
        """Enter the slots lost between the last odometer sample and one stamped ``stamp``
        with counter ``seq``: the stamps' gap in periods, but never more than the counter says
        were lost (``seq`` is +1 per sample before the link: a slot is a sample). With
        ``odometer_rate`` set above the sensor's (2 Hz for a 1 Hz odometer) the stamps alone
        put a lost slot between every two samples, its seq the next sample's, and the robust
        filter refused every second reading as a duplicate. A counter that went back (reset,
        wrap) says nothing: the stamps decide; one that skipped while the stamps ran on
        (``seq_skip``) is held to them."""
        if self.last_odo is None:
            return
        last_stamp, last_seq = self.last_odo
        n = int(round((stamp - last_stamp) / self.cfg.period)) - 1
        if seq > last_seq:
            n = min(n, seq - last_seq - 1)
        if n > self.cfg.outage_slots:
            self.outages += 1
            return
        step = (stamp - last_stamp) / (n + 1) if n >= 1 else 0.0
        for i in range(1, n + 1):
            t = last_stamp + i * step
            if t <= self.f.t:  # a balise was fused after this slot: the slot is past
                continue
            self.f.update(OdometerReading(stamp=t, seq=last_seq + i, received=False),
                          self._predicted(t))

    def _predicted(self, t: float):
        """The filter's prediction to ``t`` -- ``(x, P, actuator)`` as ``f._propagate(t)`` returns
        it -- when :meth:`output` made it already, in one go from the filter's present state
        (the same arrays, actuator and commands: a lost slot's estimate is published before the
        slot enters the filter, and the two predictions were the same arithmetic twice); else
        None. A command given since that acts before ``t`` voids it."""
        c, f = self._pred, self.f
        if c is None or c[6] is None or c[1] != t:
            return None
        x0, P0, act0, n = c[6]
        act = f.actuator
        if x0 is not f.x or P0 is not f.P or act0 is not act or c[0][0] != f.t:
            return None
        if act.acts_before(n, t):
            return None
        new = c[4].with_commands_of(act)  # the lag state at t; the commands as the filter's now
        new._prune(t)
        return c[2], c[3], new

    def odometer(self, stamp: float, fields: dict) -> str:
        self._origin(fields)
        self._heard(stamp, fields)
        undo, held = self._restart(stamp, fields)
        if held:  # a count off its course without a counter: the next reading decides
            return held
        pos, speed, rv = self._mapped(fields, stamp)
        r = OdometerReading(stamp=stamp, seq=int(fields["seq"]),
                            distance=pos - self.start_state.position, speed=speed,
                            speed_variance=rv)
        # the reading's own checks first, so that a bad one does not enter lost slots
        bad = self.f._odometer_check(r)
        if bad:
            self._unrestart(undo)
            return self.f._decide(False, bad).reason
        self._lost_slots(stamp, r.seq)
        d = self.f.update(r)
        if d.accepted:
            self.last_odo = (stamp, int(fields["seq"]))
            self._odometer_fused(stamp, fields)
        else:
            self._unrestart(undo)
        return "" if d.accepted else d.reason

    def balise(self, stamp: float, fields: dict) -> str:
        r = BaliseReading(stamp=stamp, seq=int(fields["seq"]),
                          balise_id=int(fields["balise_id"]),
                          position=float(fields["position"]),
                          position_variance=float(fields["position_variance"]))
        kind, meas = self.f._measurement(r)
        fix = None if isinstance(meas, str) else \
            self._balise_fix(stamp, float(meas.y[0]), float(meas.R[0, 0]))
        if fix is None:
            d = self.f.update(r)  # refused as it is, or no odometer reading yet
            return "" if d.accepted else d.reason
        if not self.reads_distance:
            # the balise enters the filter where the calibration puts the train (class doc)
            pos, var, dv, q = self._balise_for_filter(fix, stamp, self.f.t)
            self.f.shift(0.0, dv)
            self.f.inflate(np.diag([q, 0.0]))
            before = self._carried(self.f.x, self.f.P, max(stamp - self.f.t, 0.0))
            # (the message's position stays what was sent, checked against the map; ``pos``
            # is where the train stood: passed as the sent position, a latency moving it by
            # more than the map's tolerance, 1 m, had every balise refused at speed, and one
            # within it was fused at the map's position, the latency ignored)
            d = self.f.update(BaliseReading(stamp=stamp, seq=r.seq, balise_id=r.balise_id,
                                            position=r.position, position_variance=var,
                                            measured=pos))
            if d.accepted:
                self._balise_fused(fix, float(self.f.x[0]), before)
            return "" if d.accepted else d.reason
        if self._count_failed(stamp, fix, float(meas.R[0, 0])):
            # the count failed: the filter onto the speeds' track, read without the distance
            dx, dv, Q = self._exclude_count(stamp, self.f.t, *self.f.x[:2])
            self.f.params = replace(self.f.params, use_distance=False)
            self.f.shift(dx, dv)
            self.f.inflate(Q)
            self._pred = None
            return self.balise(stamp, fields)
        # the count's calibration takes the balise; the estimate moves with the mapping
        ok, dx, dv = self._calibrate(fix, self.f.t)
        if not ok:
            return self.f._decide(False, R.OUTSIDE_GATE).reason
        self.f.shift(dx, dv)
        self.f.order.took("balise", float(stamp), int(r.seq))
        self.f._used = True
        return ""

    def output(self, t: float) -> Output:
        f = self.f
        if t > f.t:
            # a prediction on copies (the state is untouched); through a gap each output goes
            # on from the previous one instead of from the last reading (linear, not quadratic)
            token = (f.t, float(f.x[0]), float(f.x[1]), float(f.P[0, 0]))
            c = self._pred
            if c is not None and c[0] == token and c[1] <= t:
                # the cached actuator's lag state, with every command known now: commands
                # given since the cached prediction must drive this one (a copy without them
                # held the speed through a 60 s outage while the train accelerated)
                act0, source = c[4].with_commands_of(f.actuator), None
                t0, xe = c[1], c[5]
                saved = f.x, f.P, f.t, f.actuator
                f.x, f.P, f.t, f.actuator = c[2], c[3], c[1], act0
                try:
                    x, P, act = f._propagate(t)
                finally:
                    f.x, f.P, f.t, f.actuator = saved
            else:
                act0, t0, xe = f.actuator, f.t, f.x
                x, P, act = f._propagate(t)
                source = (f.x, f.P, f.actuator, f.actuator.commands())
            xe = self._exact_mean(xe, t0, t, act0)
            self._pred = (token, t, x, P, act, xe, source)
            if xe is not None:
                x, P = xe, cover_shift(P, xe - x)
        else:
            x, P = f.estimate()
        return Output(stamp=t, position=float(x[0]), velocity=float(x[1]),
                      acceleration=math.nan, braking_rate=math.nan,
                      covariance=tuple(covariance16(P)),
                      measurement_used=self.f.pop_measurement_used(),
                      **self._calibration(t))

    def _exact_mean(self, x, t0: float, t: float, act0):
        """The mean carried from ``t0`` to ``t`` with the whole Davis resistance, or None when
        the filter's own prediction is not the nominal one of eq. (13).

        Eq. (13) predicts with the resistance linearised at ``v_max/2`` (eq. (8)-(10)): the rest,
        ``c v (v - v_max/2)``, is the norm-bounded uncertainty the bound (21) covers. Between
        readings that costs nothing, but through an outage it is a bias the model knows: on
        metro_b6 cruising at 19 m/s, 0.005 m/s^2, 8-11 m after 60 s. The published prediction
        takes the whole resistance (the same commands, steps and standstill rule as the
        filter's), and its bound is widened to cover the shift (:func:`cover_shift`). The
        filter's own state, and so the paper's recursion, are untouched."""
        f = self.f
        if not isinstance(f, RobustFilter):
            return None
        for dt, u in f.steps(t0, t, act0.copy()):
            xn = self.model.step_exact(self.model.discrete(dt), x, u)
            x = self.model.standstill(x, xn, dt) if f.params.clamp_standstill else xn
        return x

    def snapshot(self):
        """The mutable state, for the runner's rewinding (models, maps, params are shared)."""
        state = {}
        for k, v in vars(self.f).items():
            if isinstance(v, np.ndarray):
                v = v.copy()
            elif isinstance(v, dict | list):  # Counter, seq/stamp dicts, FOH history
                v = copy.deepcopy(v) if k == "_hist" else type(v)(v)
            elif k in ("actuator", "order"):
                v = v.copy()
            state[k] = v
        return state, self.last_odo, self.outages, self._pred, self._odometry_snapshot()

    def restore(self, snap) -> None:
        state, self.last_odo, self.outages, self._pred, odometry = snap
        self.f.__dict__.update(self.snapshot_copy(state))
        self._odometry_restore(odometry)

    @staticmethod
    def snapshot_copy(state: dict) -> dict:
        out = {}
        for k, v in state.items():
            if isinstance(v, np.ndarray):
                v = v.copy()
            elif isinstance(v, dict | list):
                v = copy.deepcopy(v) if k == "_hist" else type(v)(v)
            elif k in ("actuator", "order"):
                v = v.copy()
            out[k] = v
        return out

    @property
    def counters(self) -> dict:
        c = dict(self.f.counters) if self.f else {}
        if self.outages:
            c[R.OUTAGE] = self.outages
        c.update(self.odometry_events())
        return c


def cover_shift(P: np.ndarray, d: np.ndarray) -> np.ndarray:
    """A bound on the second moment of ``e - d`` given ``E[e e^T] <= P``: for any ``eps > 0``,
    ``(e - d)(e - d)^T <= (1 + eps) e e^T + (1 + 1/eps) d d^T``; ``eps = |d| / sqrt(tr P)``
    minimises the trace. ``d`` is a known shift of the estimate."""
    d = np.asarray(d, float)
    dd = float(d @ d)
    tr = float(np.trace(P))
    if not dd > 0.0 or not tr > 0.0:
        return P + np.outer(d, d) if dd > 0.0 else P
    eps = math.sqrt(dd / tr)
    return (1.0 + eps) * P + (1.0 + 1.0 / eps) * np.outer(d, d)


# ---------------------------------------------------------------------------------------------
# Zheng et al. (2015) braking-rate estimators
# ---------------------------------------------------------------------------------------------

ALGORITHMS = ("gsma", "sma", "rbpf", "qgrbpf", "kf")
# attributes of the braking filters set at construction and never changed, in place or
# otherwise (GSMA's groups of value indices: a list of tuples, deep-copied element by
# element at every snapshot before it was shared)
SHARED_ATTRS = frozenset({"groups"})


@dataclass(frozen=True)
class BrakingConfig(OdometryConfig):
    """Settings of the braking-rate estimator node (declared from this metadata,
    config/gsma_estimator.yaml documents them)."""

    algorithm: str = param("gsma", "", f"one of {', '.join(ALGORITHMS)} (gsma: Zheng et "
                           "al.'s GSMA, the node's name; kf: the exact estimator of the same "
                           "model, docs/benchmarks.md 'Braking-rate estimation')")
    values: tuple[float, ...] = param(
        tuple(float(v) for v in np.round(np.linspace(1.3, 0.0, 14), 10)), "-",
        "discrete braking-rate set (GSMA, SMA, RBPF; Q-GRBPF uses its range); up to 1.3 so that "
        "a prior centred on the nominal 1.0 is not cut in half")
    braking_rate_prior_std: float = param(
        0.15, "-", "std of every algorithm's braking-rate prior, centred on train.yaml's "
        "braking_rate (on a discrete set: the Gaussian's mass per value)", lo=0.0)
    merge: bool = param(True, "", "GSMA/SMA: merge particles on one value after each step "
                        "instead of pruning to the N best")
    #   (at most (#values) x (children) KFs per step); pruning to N every step makes GSMA
    #   over-confident on metro_drift (2-sigma coverage 0.83), Q = 500 costs a p99 of ~3 ms;
    #   merged: coverage 1.00 at the KF's accuracy (docs/benchmarks.md)
    n_init: int = param(50, "-", "N0, initial particles (GSMA, SMA)", lo=1)
    n_keep: int = param(50, "-", "N, particles kept after pruning (GSMA, SMA)", lo=1)
    q_max: int = param(500, "-", "Q, prune when the branched count exceeds it (merge = false)",
                       lo=1)
    rbpf_particles: int = param(250, "-", "RBPF particle count", lo=1)
    rbpf_p_move: float = param(0.1, "-", "RBPF sticky kernel: probability of moving to a "
                               "neighbour value", lo=0.0, hi=1.0)
    branch_p_move: float = param(0.1, "-", "GSMA/SMA children prior: P(move to a neighbour "
                                 "value), in [0, 1]; -1 = the paper's uniform prior (forgets f "
                                 "at every branching)", lo=-1.0, hi=1.0)
    sma_p_jump: float = param(1e-3, "-", "SMA children prior: P(jump to a value beyond the "
                              "neighbours) per transition, spread evenly over them (an abrupt "
                              "change: a brake cut out, a cylinder failure -- rare)",
                              lo=0.0, hi=1.0)
    qgrbpf_particles: int = param(50, "-", "Q-GRBPF particle count", lo=1)
    qgrbpf_braking_rate_q: float = param(3e-4, "1/s", "Q-GRBPF: random-walk variance of the "
                                         "braking rate per second (as the KF)", lo=0.0)
    kf_braking_rate_q: float = param(3e-4, "1/s", "KF: random-walk variance of the braking "
                                     "rate per second of braking", lo=0.0)
    #   (chosen on metro_drift: 1e-3 tracks as fast but its std breaks the ATO gate, 1e-4 lags)
    transition_interval: float = param(1.0, "s", "of braking between braking-rate "
                                       "transitions, whatever the message rate (applied with a "
                                       "reading only: f is held between readings and through "
                                       "an outage)", lo=0.0)
    accel_var: float = param(0.02, "m^2/s^3", "white acceleration noise PSD on v (unmodelled "
                             "forces)", lo=0.0)
    ahat_var: float = param(0.001, "m^2/s^5", "white noise PSD on a_hat (actuator mismatch)",
                            lo=0.0)
    standstill_speed: float = param(0.3, "m/s", "at or below (estimated), with a brake "
                                    "command, the train is held at rest and the braking rate "
                                    "is not observed", lo=0.0)
    min_brake: float = param(0.1, "m/s^2", "weaker braking commands do not inform the braking "
                             "rate", lo=0.0)
    seed: int = param(0, "", "particle-filter random stream", lo=0)
    balise_map_tolerance: float = param(1.0, "m", "max |sent position - map position|", lo=0.0)
    max_horizon: float = param(3600.0, "s", "a reading further ahead of the estimate is "
                               "future_stamp", lo=0.0)

    def __post_init__(self):
        require(self.algorithm in ALGORITHMS, "algorithm", self.algorithm,
                f"(allowed: {', '.join(ALGORITHMS)})")
        require(math.isfinite(self.braking_rate_prior_std) and self.braking_rate_prior_std > 0,
                "braking_rate_prior_std", self.braking_rate_prior_std, "must be finite and > 0")
        require(0 <= self.sma_p_jump < 1, "sma_p_jump", self.sma_p_jump, "must be in [0, 1)")
        # a braking rate is a fraction of the nominal deceleration: below 0 the brake would
        # accelerate the train; above 2 (the zone controller's plausible range) it is no train's
        # and the set is a grid: GSMA's children and the sticky priors move to the neighbours
        # by index, so the values must run one way
        d = np.diff(self.values)
        require(len(self.values) > 0 and all(math.isfinite(v) and 0.0 <= v <= 2.0
                                             for v in self.values)
                and (np.all(d < 0) or np.all(d > 0)),
                "values", list(self.values), "must be one or more braking rates in [0, 2], "
                "distinct and in order (rising or falling)")
        p = self.branch_p_move
        require(p == -1.0 or 0.0 <= p <= 1.0, "branch_p_move", p,
                "must be in [0, 1], or -1 for the paper's uniform prior")
        super().__post_init__()


class BrakingAdapter(DistanceAsPosition):
    """Drives one of GSMA, SMA, RBPF, Q-GRBPF or the exact KF over the (D, v, a_hat, a_z) model of
    Zheng eq. (4). Every algorithm's braking-rate prior is
    N(train.brake.braking_rate, braking_rate_prior_std^2).

    The known acceleration offset ``d`` on v is minus the believed Davis resistance and gradient
    at the current estimate (Zheng treat them as noise; here they are known forces).
    """

    def __init__(self, train: TrainParams, line: Line, start: StartState,
                 cfg: BrakingConfig = BrakingConfig()):
        if train.brake.delay <= 0:
            raise ValueError("the braking model needs a transport delay > 0 (Pade lambda = 2/T)")
        self.train, self.line, self.start_state, self.cfg = train, line, start, cfg
        self.source = cfg.algorithm
        self.fam = BrakingModel(BrakingParams(
            tau=train.brake.time_constant, delay=train.brake.delay, dt=cfg.transition_interval,
            noise_model="white", accel_var=cfg.accel_var, ahat_var=cfg.ahat_var,
            meas_var=(cfg.distance_variance, train.odometer_speed_variance, 1.0),
            standstill_speed=cfg.standstill_speed, min_brake=cfg.min_brake))
        values = np.asarray(cfg.values, dtype=float)
        M, p = len(values), cfg.branch_p_move
        prior = (float(train.brake.braking_rate), float(cfg.braking_rate_prior_std))
        if cfg.algorithm == "gsma":
            # children: the group of three neighbours; prior stay 1 - p, each neighbour p / 2
            self.filt = GSMA(self.fam, values, n_init=cfg.n_init, n_keep=cfg.n_keep,
                             q_max=cfg.q_max,
                             transition=None if p < 0 else sticky_transition(M, p),
                             prior=prior, merge=cfg.merge)
        elif cfg.algorithm == "sma":
            # children: every value (the paper's SMA); prior: GSMA's sticky drift (stay 1 - p,
            # each neighbour p / 2) and, with sma_p_jump, a jump to any farther value. Not a
            # uniform p over every value: a braking rate drifts (wear, adhesion) and jumps
            # only on a failure; moving mass evenly to every value drags f to the middle of
            # the set at each transition, faster than the first seconds of a brake application
            # can pull it back (the predicted stop moves tens of metres)
            self.filt = SMA(self.fam, values, n_init=cfg.n_init, n_keep=cfg.n_keep,
                            q_max=cfg.q_max,
                            transition=None if p < 0 else sma_transition(M, p, cfg.sma_p_jump),
                            prior=prior, merge=cfg.merge)
        elif cfg.algorithm == "rbpf":
            self.filt = DiscreteRBPF(self.fam, values,
                                     sticky_transition(len(values), cfg.rbpf_p_move),
                                     cfg.rbpf_particles, prior=prior)
        elif cfg.algorithm == "qgrbpf":
            self.filt = QGRBPF(self.fam, [(float(values.min()), float(values.max()))],
                               cfg.qgrbpf_particles, braking_rate_q=cfg.qgrbpf_braking_rate_q,
                               prior=prior)
        else:
            self.filt = BrakingKF(self.fam, braking_rate_q=cfg.kf_braking_rate_q,
                                  braking_rate_prior=prior)
        self.filt.transition_interval = cfg.transition_interval
        self.rng = np.random.default_rng(cfg.seed)
        self.a_tar = 0.0
        self.est = None
        self._t_start = None  # s, the filter's start (_gate, before any reading is fused)
        self.used = False
        self.balises = {b.id: b.position for b in line.balises}
        # the last fused reading of each kind (duplicates): a copy of it is a duplicate even
        # when stamped before the filter's time (which moves with every output)
        self.order = StampOrder(cfg.max_horizon, copies_first=True, kind_order=False)
        self._grad = GradientLookup(line, train.rotary_allowance)
        self._init_odometry()

    def start(self, t0: float) -> None:
        s = self.start_state
        P0 = np.diag([s.position_std ** 2, s.velocity_std ** 2, 0.01, 0.01])
        self.est = self.filt.reset([s.position, s.velocity, 0.0, 0.0], P0, rng=self.rng, t0=t0)
        self._t_start = t0

    def _d(self) -> float:
        """m/s^2, known acceleration on v: -(Davis resistance + gradient) per effective mass."""
        x, v = float(self.est.x_mean[0]), max(float(self.est.x_mean[1]), 0.0)
        # g sin(theta(x)) M / M_eff by bisection (the simulator's lookup): Line.gradient_accel
        # scans every section, a tenth of a millisecond per step on metro_demo
        return -(self.train.resistance_accel(v) + self._grad(x)) if v > 0 else 0.0

    def _step(self, stamp: float, y=None, mask=None, meas_var=None) -> str:
        e = self.filt.step(self.a_tar, y, mask, self.rng, t=stamp, meas_var=meas_var, d=self._d())
        if not e.accepted:
            return R.normalise(e.reason or R.INVALID)
        self.est = e
        self.used |= e.measurement_used
        return ""

    def _advance(self, stamp: float) -> str:
        if self.filt.t is not None and stamp > self.filt.t:
            return self._step(stamp)
        return ""

    def _gate(self, stamp: float, rows: list[tuple[int, float, float]]) -> str:
        """Innovation test of readings ``(state index 0 = D / 1 = v, value, variance)`` against
        the estimate predicted to ``stamp`` (constant a-hat), like the robust filter's gate.

        ``S = C P C^T + R + slack``: ``P`` from the mixture covariance moved by ``dt`` (NaN or
        negative entries count as 0, so a collapsed covariance cannot close the gate), and the
        slack of an acceleration error up to ``gate_accel`` over the time since the last
        odometer reading the filter fused (or its start): the model neglects the resistance in
        this look-ahead, and its error grows for as long as no reading corrects the state (the
        robust filter's gate, ``FilterBase._gate_ok``, is the same). Not since the filter's
        own time, which every published estimate moves by a time update: a filter that was
        wrong (a node started on a moving train, whose start state says standing) then refused
        every reading to the end of the run. What a reading taken after a long refusal is worth
        the integrity monitor says (``blind``, ``reacquired``: ALARM until a balise agrees with
        the odometer; a filter that was lost and an odometer that stopped while the train ran
        on look alike until then).
        """
        g = self.cfg.gate
        if not math.isfinite(g):
            return ""
        e = self.est
        dt = max(stamp - (self.filt.t if self.filt.t is not None else stamp), 0.0)
        fixed = self.odo[0] if self.odo is not None else self._t_start  # last fused reading
        since = dt if fixed is None else max(stamp - fixed, 0.0)
        m = np.asarray(e.mean, dtype=float)[:3]
        P = np.asarray(e.cov, dtype=float)[:3, :3]
        # nan_to_num is a handful of array passes: taken only when something is not finite
        # (it leaves a finite array as it is); found on the floats (np.isfinite's answer, a
        # quarter of its cost with the reductions)
        if not all(map(math.isfinite, itertools.chain.from_iterable(P.tolist()))):
            P = np.nan_to_num(P, nan=0.0)
        if not all(map(math.isfinite, m.tolist())):
            m = np.nan_to_num(m)
        F = np.array([[1.0, dt, 0.5 * dt * dt], [0.0, 1.0, dt]])
        pred = F @ m
        Pp = F @ P @ F.T
        slack = (0.5 * self.cfg.gate_accel * since * since, self.cfg.gate_accel * since)
        for i, y, r in rows:
            s = max(Pp[i, i], 0.0) + r + slack[i] ** 2
            nu = y - pred[i]
            if abs(nu) > g * math.sqrt(s):
                return f"{R.OUTSIDE_GATE}: {('position', 'speed')[i]} innovation {nu:.3g}"
        return ""

    def control(self, stamp: float, fields: dict) -> str:
        a = float(fields["target_acceleration"])
        if not (math.isfinite(a) and math.isfinite(stamp)):
            return R.NON_FINITE
        if abs(a) > self.cfg.max_command:
            return f"{R.OUTSIDE_GATE}: command {a:.3g} m/s^2"
        # as a reading: a prediction over hours is no estimate (one command mapped 14 h ahead
        # of the readings overflowed the process noise's matrix exponential)
        why = self.order.judge(None, stamp, t=self.filt.t)
        if why:
            return why
        reason = self._advance(stamp)  # the old command holds up to the new one's stamp
        if not reason:
            self.a_tar = a
        return reason

    def odometer(self, stamp: float, fields: dict) -> str:
        seq = int(fields["seq"])
        dist, speed = float(fields["distance"]), float(fields["speed"])
        var = float(fields["speed_variance"])
        if not all(math.isfinite(v) for v in (stamp, dist, speed, var)):
            return R.NON_FINITE
        if var <= 0:
            return R.NON_POSITIVE_VARIANCE
        why = self.order.judge("odometer", stamp, seq, self.filt.t)
        if why:
            return why
        self._origin(fields)
        self._heard(stamp, fields)
        undo, held = self._restart(stamp, fields)
        if held:  # a count off its course without a counter: the next reading decides
            return held
        pos, speed, var = self._mapped(fields, stamp)
        rows = [(1, speed, var)] + ([(0, pos, self.cfg.distance_variance)]
                                    if self.reads_distance else [])
        why = self._gate(stamp, rows)
        if why:
            self._unrestart(undo)
            return why
        reason = R.normalise(self._step(stamp, [pos, speed, math.nan],
                                        [self.reads_distance, True, False],
                                        [self.cfg.distance_variance, var, 1.0]))
        if not reason:
            self.order.took("odometer", stamp, seq)
            self._odometer_fused(stamp, fields)
        else:
            self._unrestart(undo)
        return reason

    def balise(self, stamp: float, fields: dict) -> str:
        seq, sent = int(fields["seq"]), float(fields["position"])
        var = float(fields["position_variance"])
        if not all(math.isfinite(v) for v in (stamp, sent, var)):
            return R.NON_FINITE
        if var <= 0:
            return R.NON_POSITIVE_VARIANCE
        pos = self.balises.get(int(fields["balise_id"]))
        if pos is None:
            return R.UNKNOWN_BALISE
        if abs(pos - sent) > self.cfg.balise_map_tolerance:
            return f"{R.BALISE_MAP_MISMATCH}: sent {sent:.1f} m, map {pos:.1f} m"
        fix = self._balise_fix(stamp, pos, var)
        why = self.order.judge("balise", stamp, seq, self.filt.t)
        if why:
            return why
        t_now = self.filt.t if self.filt.t is not None else stamp
        if fix is not None and self.reads_distance:
            # the count's calibration takes the balise; the estimate moves with the mapping
            if self._count_failed(stamp, fix, var):
                # the count failed: the filter onto the speeds' track, read without the distance
                dx, dv, Q = self._exclude_count(stamp, t_now, *self.est.mean[:2])
                self.est = self.filt.shift(dx, dv)
                self.est = self.filt.inflate(Q)
                return self.balise(stamp, fields)
            ok, dx, dv = self._calibrate(fix, t_now)
            if not ok:
                return R.OUTSIDE_GATE
            self.est = self.filt.shift(dx, dv)
            self.used = True
            self.order.took("balise", stamp, seq)
            return ""
        if fix is not None:
            # without the distance the balise enters the filter where the calibration puts
            # the train, the filter's position widened by what it lacks (class doc)
            pos, var, dv, q = self._balise_for_filter(fix, stamp, t_now)
            self.est = self.filt.shift(0.0, dv)
            self.est = self.filt.inflate(np.diag([q, 0.0]))
            before = self._carried(self.est.mean, self.est.cov, max(stamp - t_now, 0.0))
        why = self._gate(stamp, [(0, pos, var)])
        if why:
            return why
        reason = R.normalise(self._step(stamp, [pos, math.nan, math.nan], [True, False, False],
                                        [var, 1.0, 1.0]))
        if not reason:
            self.order.took("balise", stamp, seq)
            if fix is not None:
                self._balise_fused(fix, float(self.est.mean[0]), before)
        return reason

    def output(self, t: float) -> Output:
        # the braking filters step in time (their transition clock): an output between readings
        # is a time update of the filter itself, as Zheng's filters do at every sample
        self._advance(t)
        e = self.est
        used, self.used = self.used, False
        return Output(stamp=t, position=float(e.mean[0]), velocity=float(e.mean[1]),
                      acceleration=float(e.mean[2]), braking_rate=float(e.mean[3]),
                      covariance=tuple(np.asarray(e.cov, dtype=float).ravel().tolist()),
                      measurement_used=used, **self._calibration(t))

    def _shared(self) -> dict:
        """deepcopy memo of the models the filter only reads (the family and the filter's view
        of it, e.g. the KF's augmented one, and the constants set at construction: read-only
        arrays, GSMA's groups of values): shared by the snapshots, never copied -- copying
        them was most of a snapshot's time, taken at every odometer sample. Found once per
        filter object (a restore makes a new one) and handed out as a fresh dict (deepcopy
        adds to its memo)."""
        cached = getattr(self, "_memo", None)
        # (the family's check: a copied adapter carries a memo keyed by the originals' ids)
        if cached is None or cached[0] is not self.filt or \
                cached[1].get(id(self.fam)) is not self.fam:
            memo = {id(self.fam): self.fam}
            view = getattr(self.filt, "family", None)
            if view is not None:
                memo[id(view)] = view
            for k, v in vars(self.filt).items():  # parameters made read-only at construction
                if isinstance(v, np.ndarray) and not v.flags.writeable or k in SHARED_ATTRS:
                    memo[id(v)] = v
            cached = self._memo = (self.filt, memo)
        return dict(cached[1])

    def snapshot(self):
        """The mutable state, for the runner's rewinding (the model family is shared). The
        generator's state property builds a new dict at each read: nothing to copy."""
        return (copy.deepcopy(self.filt, self._shared()),
                self.rng.bit_generator.state, self.a_tar, self.est, self.used,
                self.order.copy(), self._odometry_snapshot())

    def restore(self, snap) -> None:
        filt, rng_state, self.a_tar, self.est, self.used, order, odometry = snap
        self.filt = copy.deepcopy(filt, self._shared())
        self.rng.bit_generator.state = copy.deepcopy(rng_state)
        self.order = order.copy()
        self._odometry_restore(odometry)

    @property
    def counters(self) -> dict:
        c = dict(self.filt.rejected)
        c.update(self.odometry_events())
        return c
