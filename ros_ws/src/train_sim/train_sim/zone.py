"""Zone-controller logic (pure): movement authorities from trains' position estimates.

Each train reports a ``TrainState`` (position of its front end, velocity, covariance, and a braking
rate where one is estimated). Like an ETCS confidence interval, the zone controller keeps each
train's position as an interval::

    [x - k sigma_x,  x + k sigma_x]        (front end; rear end = front - train_length)

and grants movement authority (end of authority, EoA) up to the nearest danger point ahead:

- the configured danger points (a red signal, an occupied block, the end of the line), and
- the worst-case rear of the train ahead: ``x_lead - k sigma_lead - train_length`` minus a margin.

It sets ``emergency_brake`` when the worst-case front plus the braking distance at the worst-case
speed passes the EoA::

    x + k sigma_x + (v + k sigma_v)^2 / (2 f_low b_emergency) > EoA,

where ``f_low = max(f_hat - k sigma_f, f_min)`` is the estimated braking rate's lower bound when
a braking rate is published (``braking_rate`` finite) and 1 (nominal) otherwise.

A train is unsafe (stale) when its last report arrived more than ``stale_timeout`` ago, when the
estimate's own stamp is older than ``stale_timeout`` (an estimator that republishes old
estimates), or when its estimator has not used a measurement for ``measurement_timeout``
(``stamp - stamp of the last report with measurement_used``, both on the estimator's clock: an
estimator that keeps publishing predictions is not fresh; a source that never sets the flag,
such as ground truth, is judged by its stamps only). An unsafe train gets the emergency
brake, and so does every train behind it (its rear can no longer be bounded from recent data).
While a supervised train has not reported at all, no other train gets an authority (it may be
anywhere). Each authority carries a short ``state`` (``ok``, ``stale``, ``no_estimate``,
``ahead_stale``, ``ahead_unknown``, ``overrun``) so that a node logs a change of state once,
not every publication of a reason whose numbers change.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from train_core.config import param, require


@dataclass(frozen=True)
class ZoneParams:
    """The zone's rules (the node declares them from this metadata; config/zone_controller.yaml
    documents them)."""

    k_sigma: float = param(3.0, "-", "half-width of the position/speed confidence interval in "
                           "standard deviations")
    stale_timeout: float = param(3.0, "s", "reports (arrival or stamp) older than this: "
                                 "emergency brake")
    measurement_timeout: float = param(10.0, "s", "no measurement used for this long: "
                                       "emergency brake")
    check_stamp_age: bool = param(True, "", "judge age by the estimate's stamp too (the zone "
                                  "and the estimates on one clock)")
    emergency_decel: float = param(1.2, "m/s^2", "guaranteed emergency braking at the nominal "
                                   "braking rate")
    train_length: float = param(120.0, "m", "front to rear")
    margin: float = param(20.0, "m", "kept between an end of authority and the hazard it "
                          "protects")
    danger_points: tuple[float, ...] = param((), "m", "fixed hazards (red signals, end of "
                                             "line); the node builds them", node=False)
    permitted_speed: float = param(22.23, "m/s", "speed granted with every authority")
    min_braking_rate: float = param(0.2, "-", "floor for the braking-rate lower bound")

    def __post_init__(self):
        for name in ("k_sigma", "stale_timeout", "measurement_timeout", "emergency_decel"):
            v = getattr(self, name)
            require(math.isfinite(v) and v > 0, name, v, "must be > 0")


@dataclass(frozen=True)
class ZoneNodeConfig:
    """What the zone_controller node adds to :class:`ZoneParams` (declared from this metadata)."""

    trains: tuple[str, ...] = param(("",), "", "train namespaces ('' = this node's namespace)")
    state_topic: str = param("estimate/robust", "", "TrainState topic of each train, relative "
                             "to its namespace")
    line_file: str = param("", "", "line.yaml; its length is a danger point")
    danger_points: tuple[float, ...] = param((-1.0,), "m", "fixed danger points (red signals); "
                                             "[-1.0] = none")
    rate: float = param(1.0, "Hz", "movement authority publication rate")

    def __post_init__(self):
        require(math.isfinite(self.rate) and self.rate > 0, "rate", self.rate, "must be > 0")


@dataclass
class TrainReport:
    t_received: float  # s, zone-controller clock when the report arrived
    stamp: float  # s, sample time of the estimate
    position: float  # m, front end
    velocity: float  # m/s
    var_position: float  # m^2
    var_velocity: float  # (m/s)^2
    braking_rate: float = math.nan  # -, NaN where not estimated
    var_braking_rate: float = math.nan
    measurement_used: bool = True  # a measurement entered this estimate
    last_measurement: float = math.nan  # s, stamp of the last report with a measurement (set
    #   by ZoneController.report)


@dataclass(frozen=True)
class Authority:
    train_id: str
    end_of_authority: float  # m
    permitted_speed: float  # m/s
    emergency_brake: bool
    reason: str  # why the brake is set ("" when it is not)
    state: str = "ok"  # short category of the reason (changes are logged once)


@dataclass
class ZoneController:
    params: ZoneParams
    reports: dict[str, TrainReport] = field(default_factory=dict)
    rejected: dict[str, int] = field(default_factory=dict)

    def report(self, train_id: str, rep: TrainReport) -> str:
        """Store a train's report; returns "" if accepted or the reason it was rejected."""
        vals = (rep.position, rep.velocity, rep.var_position, rep.var_velocity)
        reason = ""
        if not all(math.isfinite(v) for v in vals):
            reason = "non-finite position, velocity or variance"
        elif rep.var_position < 0 or rep.var_velocity < 0:
            reason = "negative variance"
        else:
            last = self.reports.get(train_id)
            if last is not None and rep.stamp < last.stamp:
                reason = "out-of-order stamp"
        if reason:
            self.rejected[reason] = self.rejected.get(reason, 0) + 1
            return reason
        last = self.reports.get(train_id)
        if rep.measurement_used:
            rep.last_measurement = rep.stamp
        else:  # carried over; NaN until a report says a measurement was used (ground truth,
            # or an estimator that does not set the flag, is judged by its stamps only)
            rep.last_measurement = last.last_measurement if last is not None else math.nan
        self.reports[train_id] = rep
        return ""

    def staleness(self, rep: TrainReport, now: float) -> str:
        """Why a report is too old to bound the train ("" if fresh)."""
        p = self.params
        if now - rep.t_received > p.stale_timeout:
            return f"estimates stale: none received for {now - rep.t_received:.1f} s " \
                   f"(> {p.stale_timeout} s)"
        if p.check_stamp_age and now - rep.stamp > p.stale_timeout:
            return f"estimates stale: stamped {now - rep.stamp:.1f} s ago (> {p.stale_timeout} s)"
        if math.isfinite(rep.last_measurement) and \
                rep.stamp - rep.last_measurement > p.measurement_timeout:
            return (f"estimates stale: no measurement used for "
                    f"{rep.stamp - rep.last_measurement:.1f} s (> {p.measurement_timeout} s)")
        return ""

    def _bounds(self, rep: TrainReport) -> tuple[float, float, float, float]:
        """(worst-case front, worst-case rear, worst-case speed, braking-rate lower bound)."""
        p = self.params
        sx = math.sqrt(max(rep.var_position, 0.0))
        sv = math.sqrt(max(rep.var_velocity, 0.0))
        front = rep.position + p.k_sigma * sx
        rear = rep.position - p.k_sigma * sx - p.train_length
        speed = max(rep.velocity, 0.0) + p.k_sigma * sv
        f_low = 1.0
        if math.isfinite(rep.braking_rate):
            sf = math.sqrt(rep.var_braking_rate) if math.isfinite(rep.var_braking_rate) else 0.0
            f_low = max(rep.braking_rate - p.k_sigma * sf, p.min_braking_rate)
        return front, rear, speed, f_low

    def authorities(self, now: float, train_ids: list[str]) -> list[Authority]:
        """One authority per train in ``train_ids`` at zone-controller time ``now`` (s)."""
        p = self.params
        why_stale = {tid: self.staleness(self.reports[tid], now) if tid in self.reports
                     else "no estimate" for tid in train_ids}
        stale = {tid: bool(w) for tid, w in why_stale.items()}
        out = []
        for tid in train_ids:
            rep = self.reports.get(tid)
            if rep is None:
                out.append(Authority(tid, -math.inf, 0.0, True, "no estimate received yet",
                                     "no_estimate"))
                continue
            front, _, speed, f_low = self._bounds(rep)
            hazards = [(d - p.margin, f"danger point at {d:.1f} m") for d in p.danger_points
                       if d - p.margin >= rep.position - p.k_sigma * math.sqrt(rep.var_position)]
            reason, state = "", "ok"
            for other in train_ids:
                orep = self.reports.get(other)
                if other == tid:
                    continue
                if orep is None:  # a supervised train not yet localised may be anywhere ahead
                    reason, state = f"position of {other} unknown", "ahead_unknown"
                    continue
                if orep.position <= rep.position:
                    continue
                _, orear, _, _ = self._bounds(orep)
                hazards.append((orear - p.margin, f"rear of {other}"))
                if stale[other]:
                    reason, state = f"train ahead ({other}) has stale estimates", "ahead_stale"
            eoa, what = min(hazards, default=(math.inf, "open line"))
            if stale[tid]:
                reason, state = why_stale[tid], "stale"
            elif not reason:
                stop_dist = speed * speed / (2.0 * f_low * p.emergency_decel)
                if front + stop_dist > eoa:
                    reason = (f"worst-case stop {front + stop_dist:.1f} m passes EoA {eoa:.1f} m "
                              f"({what})")
                    state = "overrun"
            out.append(Authority(tid, eoa, p.permitted_speed, bool(reason), reason, state))
        return out
