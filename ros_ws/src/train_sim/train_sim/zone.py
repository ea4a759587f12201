"""Zone-controller logic (pure): movement authorities from trains' position estimates.

Each train reports a ``TrainState`` (position of its front end, velocity, covariance, a braking
rate where one is estimated, and its protection levels). Like an ETCS confidence interval (the
max and min safe front end), the zone controller keeps each train's position as the interval
its estimator states at its integrity risk::

    [x - PL_behind,  x + PL_ahead]         (front end; rear end = front - train_length)

and grants movement authority (end of authority, EoA) up to the nearest danger point ahead:

- the configured danger points (a red signal, an occupied block, the end of the line), and
- the min safe rear of the train ahead: ``x_lead - PL_behind_lead - train_length`` minus a
  margin, carried back over the report's age at its worst reverse speed (its speed's lower
  bound, ``K`` standard deviations below it, where that is negative). A train is ahead when
  its bounded report is, and also wherever the two intervals allow it (this train's min safe
  front short of the other's max safe rear): while the order is open each train keeps behind
  the other's min safe rear. A danger point bounds the authority until the train's min safe
  front has passed it, however close it is.

It sets ``emergency_brake`` when the max safe front, carried to the present at the worst-case
speed, plus the braking distance at that speed passes the EoA::

    x + PL_ahead + (v + K sigma_v) age + a_max age^2 / 2
      + (v + K sigma_v + a_max age)^2 / (2 f_low b_emergency) > EoA,

(``age``: the time since the report's sample on the zone's clock, at least; a report that waited
in a stalled node is that much behind the train; ``a_max``: ``max_acceleration``, what the train
may have gained since)

where ``f_low = max(f_hat - K sigma_f, f_min)`` is the estimated braking rate's lower bound when
a braking rate is published (``braking_rate`` finite) and 1 (nominal) otherwise. The speed and
the braking rate carry no protection level of their own: their bounds take the multiplier
``K = Phi^-1(1 - integrity_risk / 2)`` of their standard deviations at the zone's
``integrity_risk`` (5.33 at 1e-7), one risk for every bound.

A train is unsafe (stale) when its last report arrived more than ``stale_timeout`` ago (or
after the zone's clock reads now: a clock that went back leaves every age unknown), when the
estimate's own stamp is older than ``stale_timeout`` (an estimator that republishes old
estimates), or when its estimator has not used a measurement for ``measurement_timeout``
(``stamp - stamp of the last report with measurement_used``, both on the estimator's clock: an
estimator that keeps publishing predictions is not fresh; a source that never sets the flag,
such as ground truth, is judged by its stamps only). An unsafe train gets the emergency
brake, and so does every train behind it (its rear can no longer be bounded from recent data).
While a supervised train has not reported at all, no other train gets an authority (it may be
anywhere). A report's ``integrity`` (TrainState: 0 OK, 1 DEGRADED, 2 ALARM) is obeyed the same
way: ALARM (no bound) brakes the train (and those behind it) at once; OK and DEGRADED are both
bounded by their protection levels, which the authority uses as they are (a wide interval
shortens the follower's authority and keeps the leader's rear far back: no timer is needed).
An ALARM report's position bounds nothing, so it never orders the trains: which train is ahead
of which is judged by each train's last bounded report (a train in ALARM since its first
report may be anywhere, as one not yet localised), and the train behind an ALARM one brakes
wherever the ALARM report puts it.
Each authority carries a short ``state`` (``ok``, ``stale``, ``alarm``, ``no_estimate``,
``ahead_stale``, ``ahead_alarm``, ``ahead_unknown``, ``overrun``, ``failed``) so that a node
logs a change of state once, not every publication of a reason whose numbers change. With
``fail_safe`` (the node's), an exception inside the zone controller (a defect) latches it as
failed: every train's emergency brake is set and every report refused from then on.

Input checks (:meth:`ZoneController.report`). A report is refused, counted by kind and never
stored when a field the zone reads is unusable: a non-finite stamp, position, velocity or
variance (a NaN variance is no information, never certainty), a variance <= 0 (a report the
node marks ``exact``, ground truth, may state 0), a position/velocity covariance that is not
symmetric positive definite, a braking rate with no finite positive variance, an unknown
integrity value, a protection level that is negative, NaN, or infinite without ALARM, a speed
no train runs (|velocity| > ``MAX_SPEED``), or a stamp that is implausible:

- *ahead*: more than ``max_future`` ahead of the zone's own clock (``check_stamp_age``: zone and
  estimates on one clock) or, on separate clocks, of the train's timeline (the largest
  ``stamp - arrival`` accepted, lowered since by what the clocks may drift apart,
  ``max_clock_drift``: latency only makes ``stamp - arrival`` smaller);
- *behind* the last accepted stamp (out of order).

Plausibility (a report that passes the field checks but cannot be true; refused the same way,
so the train keeps its last plausible report and goes stale if no plausible one follows):

- *off the line*: the interval ``[x - PL_behind, x + PL_ahead]`` misses the line
  ``[0, line_length]`` (a position of 1e12 m or -1e9 m);
- *jump*: the interval and the last accepted one, each widened by what the train can run
  between their stamps (``MAX_SPEED`` times the time between them), do not meet, or the
  interval lies behind the last one by more than the train reverses between them
  (``max_reverse_speed``; for a report stamped before the last one, a reset or a replay, over
  the time between their arrivals plus ``stale_timeout``): one of the two does not hold the
  train;
- *order*: a train reported at or past the last accepted position of a train that was ahead of
  it, or at or behind one that was behind it (trains on one track do not pass each other);
- a braking rate outside [0, ``MAX_BRAKING_RATE``], a speed below ``-max_reverse_speed``.

A refused stamp never moves anything, so one far-future report cannot lock out the reports that
follow. An estimator's clock reset is followed by evidence: ``reset_reports`` consecutive
stamp-refused reports whose ``stamp - arrival`` agree within ``max_future`` and whose stamps
increase form a new timeline, which is adopted (on one clock only where it is not ahead of the
zone's clock, so a stream of future stamps is never followed). A good report on the current
timeline in between breaks such a run. The age of the last measurement used is carried onto
the new timeline (by the time between the two reports' arrivals).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from statistics import NormalDist

from train_core.config import param, require, require_finite
from train_core.failsafe import guarded

CLOCK_RES = 1e-6  # s: the zone clock's resolution as read here (a float Unix time resolves
#   2.4e-7 s; a ROS time 1 ns): an arrival later than now by more is a clock that went back


@dataclass(frozen=True)
class ZoneParams:
    """The zone's rules (the node declares them from this metadata; config/zone_controller.yaml
    documents them)."""

    integrity_risk: float = param(1e-7, "-", "risk at which the speed and braking-rate bounds "
                                  "are taken from their variances (the position's is the "
                                  "estimator's protection level, stated at its own risk)")
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
    line_length: float = param(math.inf, "m", "length of the line: a report whose interval "
                               "misses [0, line_length] is refused (the node sets it from "
                               "line_file)", node=False)
    max_reverse_speed: float = param(1.0, "m/s", "a report running backwards faster than this "
                                     "is refused (a train in a supervised zone does not reverse "
                                     "at speed)")
    max_future: float = param(3.0, "s", "a report stamped further ahead than this (of the "
                              "zone's clock, or of the train's timeline on separate clocks) "
                              "is refused; also the agreement needed to follow a clock reset")
    reset_reports: int = param(5, "-", "consecutive reports on one new timeline after which "
                               "an estimator's clock reset is followed")
    max_acceleration: float = param(1.5, "m/s^2", "the greatest acceleration of a supervised "
                                    "train (traction and a downhill gradient): a report's "
                                    "front and speed are carried over its age at this",
                                    lo=0.0)
    max_clock_drift: float = param(1e-3, "s/s", "separate clocks (check_stamp_age false): the "
                                   "fastest a train's clock drifts from the zone's; the "
                                   "least latency seen is lowered no faster, so a latency that "
                                   "rose and stayed is carried into every report's age (a "
                                   "clock drifting faster reads as latency: fronts carried "
                                   "further, never short)", lo=0.0)

    def __post_init__(self):
        require_finite(self, ("stale_timeout", "measurement_timeout", "emergency_decel",
                              "max_future", "max_reverse_speed", "max_clock_drift",
                              "max_acceleration"))
        require(self.max_acceleration >= 0.0, "max_acceleration", self.max_acceleration,
                "must be >= 0")
        require(self.max_clock_drift >= 0.0, "max_clock_drift", self.max_clock_drift,
                "must be >= 0")
        require(0.0 < self.integrity_risk < 0.5, "integrity_risk", self.integrity_risk,
                "must be in (0, 0.5)")
        require(int(self.reset_reports) == self.reset_reports and self.reset_reports >= 2,
                "reset_reports", self.reset_reports, "must be an integer >= 2")


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
    log_interval: float = param(5.0, "s", "each kind of refused report is logged at most "
                                "once per train in this interval (with the count)")

    def __post_init__(self):
        require_finite(self, ("rate", "log_interval"))


# Integrity values of TrainState
OK, DEGRADED, ALARM = 0, 1, 2

# Kinds of refused report (the keys of ZoneController.rejected)
NON_FINITE = "non-finite value"
NON_POSITIVE_VARIANCE = "non-positive variance"
NOT_POSITIVE_DEFINITE = "covariance not positive definite"
UNKNOWN_INTEGRITY = "unknown integrity"
IMPLAUSIBLE_SPEED = "implausible speed"
FUTURE_STAMP = "future stamp"
OUT_OF_ORDER = "out-of-order stamp"
BAD_PROTECTION = "bad protection level"
OFF_LINE = "off the line"
JUMP = "implausible jump"
ORDER = "trains out of order"
IMPLAUSIBLE_BRAKING = "implausible braking rate"
FAILED = "zone controller failed"  # an exception inside the zone controller (fail_safe)
KINDS = (NON_FINITE, NON_POSITIVE_VARIANCE, NOT_POSITIVE_DEFINITE, UNKNOWN_INTEGRITY,
         IMPLAUSIBLE_SPEED, FUTURE_STAMP, OUT_OF_ORDER, BAD_PROTECTION, OFF_LINE, JUMP, ORDER,
         IMPLAUSIBLE_BRAKING, FAILED)
MAX_BRAKING_RATE = 2.0  # f: twice the nominal braking; a larger one is a corrupt report
# m/s: no train runs faster (540 km/h; the fastest wheeled train in service runs 97 m/s). A
# larger |velocity| is a corrupt report, and a large negative one must never be read as a
# train at rest (the worst-case stop takes max(velocity, 0)).
MAX_SPEED = 150.0


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
    cov_position_velocity: float = 0.0  # m^2/s, covariance[1]
    cov_velocity_position: float = 0.0  # m^2/s, covariance[4] (must equal covariance[1])
    integrity: int = OK  # 0 OK, 1 DEGRADED, 2 ALARM
    pl_ahead: float = 0.0  # m, protection level ahead (the max safe front end is x + this)
    pl_behind: float = 0.0  # m, protection level behind (the min safe front end is x - this)
    exact: bool = False  # ground truth: variances of 0 are allowed
    clock_shift: float = 0.0  # s, set by the zone: its timeline's shift (stamp - zone clock)
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


def check_fields(rep: TrainReport) -> tuple[str, str]:
    """``(kind, detail)`` of the first unusable field of ``rep``; ``("", "")`` if all are usable.

    Only what the zone reads is judged: the stamp, position, velocity, the position/velocity
    block of the covariance, the braking rate with its variance where one is published (NaN
    braking rate = not estimated, nominal braking assumed), the integrity value and the speed
    (|velocity| <= ``MAX_SPEED``).
    """
    vals = {"stamp": rep.stamp, "position": rep.position, "velocity": rep.velocity,
            "position variance": rep.var_position, "velocity variance": rep.var_velocity,
            "position/velocity covariance": rep.cov_position_velocity,
            "velocity/position covariance": rep.cov_velocity_position}
    if not math.isnan(rep.braking_rate):
        vals["braking rate"] = rep.braking_rate
        vals["braking-rate variance"] = rep.var_braking_rate
    for name, v in vals.items():
        if not (isinstance(v, (int, float)) and math.isfinite(v)):
            return NON_FINITE, f"{name} is {v}"
    if rep.integrity not in (OK, DEGRADED, ALARM):
        return UNKNOWN_INTEGRITY, f"integrity {rep.integrity} (0 OK, 1 DEGRADED, 2 ALARM)"
    for name, v in (("protection_level_ahead", rep.pl_ahead),
                    ("protection_level_behind", rep.pl_behind)):
        if not isinstance(v, (int, float)) or math.isnan(v) or v < 0 or \
                (math.isinf(v) and rep.integrity != ALARM):
            return BAD_PROTECTION, f"{name} is {v} with integrity {rep.integrity}"
    if not math.isnan(rep.braking_rate) and not 0.0 <= rep.braking_rate <= MAX_BRAKING_RATE:
        return IMPLAUSIBLE_BRAKING, (f"braking rate {rep.braking_rate:g} outside [0, "
                                     f"{MAX_BRAKING_RATE:g}]")
    if abs(rep.velocity) > MAX_SPEED:
        return IMPLAUSIBLE_SPEED, f"velocity {rep.velocity:g} m/s (|v| > {MAX_SPEED:g})"
    variances = {"position variance": rep.var_position, "velocity variance": rep.var_velocity}
    if not math.isnan(rep.braking_rate):
        variances["braking-rate variance"] = rep.var_braking_rate
    for name, v in variances.items():
        if v < 0 or (v == 0 and not rep.exact):
            return NON_POSITIVE_VARIANCE, f"{name} is {v:g}"
    vx, vv = rep.var_position, rep.var_velocity
    cxv, cvx = rep.cov_position_velocity, rep.cov_velocity_position
    scale = math.sqrt(vx * vv)
    # symmetric to rounding, and a 2x2 block is positive definite iff its determinant is > 0
    # (the diagonal is already > 0); an exact report may be singular
    if abs(cxv - cvx) > 1e-6 * scale or cxv * cvx > vx * vv or \
            (cxv * cvx == vx * vv and not rep.exact):
        return NOT_POSITIVE_DEFINITE, (f"position/velocity block [[{vx:g}, {cxv:g}], "
                                       f"[{cvx:g}, {vv:g}]]")
    return "", ""


@dataclass
class _Timeline:
    """One train's stamp timeline as the zone follows it (stamps are the estimator's)."""

    ref: float = -math.inf  # s, the largest stamp - arrival accepted, each lowered since its
    #   arrival by max_clock_drift per s (offset_at); -inf before the first
    t_ref: float = 0.0  # s, zone clock when ref was last brought up to date
    run: list = field(default_factory=list)  # (stamp, offset) of consecutive stamp-refused
    #   reports that agree with each other: evidence of a new timeline
    shift: float = 0.0  # s, stamp - zone clock of this timeline (0: the estimator's clock is
    #   the zone's; after a followed reset, the new timeline's offset at the reset)

    def offset_at(self, t: float, drift: float) -> float:
        """s, the train's timeline at zone time ``t`` (separate clocks): the largest ``stamp -
        arrival`` accepted, each lowered by ``drift`` per s since it arrived. Latency only
        lowers ``stamp - arrival``, so the clock offset is at least this while the clocks
        drift apart no faster than ``drift``. A latency that rose and stayed is thus carried
        (the reports' ages grow by it) and not taken for the clock's offset: on separate
        clocks the two read alike, and only the latency is safe to assume (a 60 s window
        adopted a route's 3 s as offset after a minute, and the fronts it carried fell short of
        the train's by those 3 s of running). A clock that steps back is followed as a new
        timeline (``reset_reports``); one that drifts faster reads as latency: older ages,
        fronts carried further, never short."""
        return self.ref - drift * max(t - self.t_ref, 0.0)

    def add(self, t_received: float, offset: float, drift: float) -> None:
        first = not math.isfinite(self.ref)
        self.ref = max(self.offset_at(t_received, drift), offset)
        self.t_ref = t_received if first else max(self.t_ref, t_received)


@dataclass
class ZoneController:
    params: ZoneParams
    reports: dict[str, TrainReport] = field(default_factory=dict)
    rejected: dict[str, int] = field(default_factory=dict)  # refusals per kind (KINDS)
    clock_resets: dict[str, int] = field(default_factory=dict)  # new timelines followed
    last_refusal: tuple[str, str, str] = ("", "", "")  # (train, kind, detail) of the latest
    timelines: dict[str, _Timeline] = field(default_factory=dict)
    bounded: dict[str, TrainReport] = field(default_factory=dict)  # each train's last report
    #   that bounds it (not ALARM): where it stands in the trains' order on the track
    fail_safe: bool = False  # an exception inside report or authorities latches the zone as
    #   failed: every report refused (FAILED), every train's emergency brake set from then on
    #   (the node's setting; offline and in tests the exception propagates, to be seen)
    failure: str | None = None  # what failed ("call: Type: message"), once latched
    failure_trace: str = ""  # its traceback, for the node's log

    def _failed_report(self, train_id: str, _rep=None) -> str:
        """A report once failed (``fail_safe``): refused as FAILED, counted."""
        self.rejected[FAILED] = self.rejected.get(FAILED, 0) + 1
        self.last_refusal = (train_id, FAILED, self.failure)
        return FAILED

    def _failed_authorities(self, _now: float, train_ids: list[str]) -> list[Authority]:
        """Once failed (``fail_safe``): every train braked, no authority (end -inf, as a train
        not yet heard of)."""
        return [Authority(tid, -math.inf, 0.0, True, f"{FAILED}: {self.failure}", "failed")
                for tid in train_ids]

    @guarded(_failed_report)
    def report(self, train_id: str, rep: TrainReport) -> str:
        """Store a train's report; returns "" if accepted or the kind of refusal (one of
        :data:`KINDS`, counted in ``rejected``; ``last_refusal`` holds the detail). Never
        raises on any report content."""
        kind, detail = check_fields(rep)
        if not kind:
            kind, detail = self._plausible(train_id, rep)
        if not kind:
            kind, detail = self._check_stamp(train_id, rep)
            if kind and self._follows_reset(train_id, rep):
                self.clock_resets[train_id] = self.clock_resets.get(train_id, 0) + 1
                self._store(train_id, rep, new_timeline=True)
                return ""
        if kind:
            self.rejected[kind] = self.rejected.get(kind, 0) + 1
            self.last_refusal = (train_id, kind, detail)
            return kind
        self._store(train_id, rep, new_timeline=False)
        return ""

    def _plausible(self, train_id: str, rep: TrainReport) -> tuple[str, str]:
        """``(kind, detail)`` where a report cannot be true (module doc: off the line, a jump,
        trains out of order, reversing at speed); ``("", "")`` if it can. ALARM reports bound
        nothing and are judged by their fields only."""
        p = self.params
        if rep.velocity < -p.max_reverse_speed:
            return IMPLAUSIBLE_SPEED, (f"velocity {rep.velocity:g} m/s (reversing faster than "
                                       f"{p.max_reverse_speed:g})")
        if rep.integrity == ALARM:
            return "", ""
        lo, hi = rep.position - rep.pl_behind, rep.position + rep.pl_ahead
        if hi < 0.0 or lo > p.line_length:
            return OFF_LINE, (f"interval [{lo:.6g}, {hi:.6g}] m misses the line [0, "
                              f"{p.line_length:g}]")
        last = self.reports.get(train_id)
        if last is not None and last.integrity != ALARM:
            run = MAX_SPEED * abs(rep.stamp - last.stamp)
            if lo > last.position + last.pl_ahead + run or \
                    hi < last.position - last.pl_behind - run:
                return JUMP, (f"interval [{lo:.6g}, {hi:.6g}] m is more than the "
                              f"{run:.3g} m a train runs in {abs(rep.stamp - last.stamp):.3g} s "
                              f"from the last one [{last.position - last.pl_behind:.6g}, "
                              f"{last.position + last.pl_ahead:.6g}] m")
            # nor back by more than it reverses (max_reverse_speed) between the two samples:
            # on one timeline the stamps tell that time; a report stamped before the last one
            # (a reset, a replay) was sampled at most stale_timeout before it arrived, as was
            # the last one (a burst of reports a minute old, each refused as out of order,
            # was followed as the estimator's clock reset and put the train 1.2 km back)
            dt = rep.stamp - last.stamp if rep.stamp >= last.stamp else \
                abs(rep.t_received - last.t_received) + p.stale_timeout
            back = p.max_reverse_speed * dt
            if hi < last.position - last.pl_behind - back:
                return JUMP, (f"interval [{lo:.6g}, {hi:.6g}] m lies more than the {back:.3g} m "
                              f"a train reverses in {dt:.3g} s behind the last one "
                              f"[{last.position - last.pl_behind:.6g}, "
                              f"{last.position + last.pl_ahead:.6g}] m")
        last = self.bounded.get(train_id)
        if last is not None:
            # the order the trains' bounded reports put them in (an ALARM report's position
            # bounds nothing and orders nothing)
            for other, orep in self.bounded.items():
                if other == train_id:
                    continue
                ahead_before = orep.position > last.position
                if ahead_before and rep.position >= orep.position or \
                        not ahead_before and rep.position <= orep.position:
                    return ORDER, (f"position {rep.position:.6g} m would put it "
                                   f"{'past' if ahead_before else 'behind'} {other} "
                                   f"({orep.position:.6g} m)")
        return "", ""

    def _check_stamp(self, train_id: str, rep: TrainReport) -> tuple[str, str]:
        p = self.params
        offset = rep.stamp - rep.t_received
        tl = self.timelines.get(train_id)
        ref = (tl.shift if tl is not None else 0.0) if p.check_stamp_age else \
            (tl.offset_at(rep.t_received, p.max_clock_drift) if tl is not None else offset)
        if offset - ref > p.max_future:
            return FUTURE_STAMP, (f"stamped {offset - ref:.3g} s ahead of the "
                                  f"{'zone clock' if p.check_stamp_age else 'train timeline'}"
                                  f" (> {p.max_future} s)")
        last = self.reports.get(train_id)
        if last is not None and rep.stamp < last.stamp:
            return OUT_OF_ORDER, f"stamp {last.stamp - rep.stamp:.3g} s behind the last one"
        return "", ""

    def _follows_reset(self, train_id: str, rep: TrainReport) -> bool:
        """Record a stamp-refused report as evidence of a new timeline; True when the run of
        such reports is long and consistent enough to follow it (this report included)."""
        p = self.params
        tl = self.timelines.get(train_id)
        if tl is None:
            return False
        offset = rep.stamp - rep.t_received
        run = tl.run
        if run and (abs(offset - run[0][1]) > p.max_future or rep.stamp <= run[-1][0]):
            run.clear()
        run.append((rep.stamp, offset))
        # on one clock, a new timeline ahead of the zone's clock is not adopted (a clock that
        # jumps forward would make old estimates look fresh); one behind it is (a reboot)
        plausible = not p.check_stamp_age or offset <= tl.shift + p.max_future
        return len(run) >= p.reset_reports and plausible

    def _store(self, train_id: str, rep: TrainReport, new_timeline: bool) -> None:
        offset = rep.stamp - rep.t_received
        tl = self.timelines.get(train_id)
        if tl is None or new_timeline:
            # a followed reset: stamp ages are judged on the new timeline from now on (its
            # offset at the reset, the latency of that report included, which only errs
            # towards "older")
            tl = self.timelines[train_id] = _Timeline(shift=offset if new_timeline else 0.0)
        rep.clock_shift = tl.shift
        tl.add(rep.t_received, offset, self.params.max_clock_drift)
        tl.run.clear()  # a good report on this timeline breaks a run of outliers
        last = self.reports.get(train_id)
        if rep.measurement_used:
            rep.last_measurement = rep.stamp
        elif last is not None and new_timeline:
            # carried onto the new timeline: as old as it was at the last report, and older
            # by the time between the two arrivals (forgotten, a reset kept an estimator that
            # predicted without measurements supervised for good)
            rep.last_measurement = rep.stamp - (last.stamp - last.last_measurement) - \
                max(rep.t_received - last.t_received, 0.0)
        else:  # carried over; NaN until a report says a measurement was used (ground truth,
            # or an estimator that does not set the flag, is judged by its stamps only)
            rep.last_measurement = last.last_measurement if last is not None else math.nan
        self.reports[train_id] = rep
        if rep.integrity != ALARM:
            self.bounded[train_id] = rep

    def unsafe(self, train_id: str, now: float) -> tuple[str, str]:
        """``(reason, state)`` why a train's position cannot be bounded now (stale, or
        integrity ALARM); ``("", "")`` if it can."""
        rep = self.reports[train_id]
        why = self.staleness(rep, now)
        if why:
            return why, "stale"
        if rep.integrity == ALARM:
            return "estimator integrity ALARM (it cannot bound its error)", "alarm"
        return "", ""

    def staleness(self, rep: TrainReport, now: float) -> str:
        """Why a report is too old to bound the train ("" if fresh)."""
        p = self.params
        if now < rep.t_received - CLOCK_RES:
            # the zone's clock went back (a restarted /clock, a bag played again): how old the
            # report is cannot be known on it
            return f"estimates stale: the zone's clock went back {rep.t_received - now:.3g} s " \
                   f"past the last report's arrival"
        if now - rep.t_received > p.stale_timeout:
            return f"estimates stale: none received for {now - rep.t_received:.1f} s " \
                   f"(> {p.stale_timeout} s)"
        age = now - (rep.stamp - rep.clock_shift)  # on the zone's clock
        if p.check_stamp_age and age > p.stale_timeout:
            return f"estimates stale: stamped {age:.1f} s ago (> {p.stale_timeout} s)"
        if math.isfinite(rep.last_measurement) and \
                rep.stamp - rep.last_measurement > p.measurement_timeout:
            return (f"estimates stale: no measurement used for "
                    f"{rep.stamp - rep.last_measurement:.1f} s (> {p.measurement_timeout} s)")
        return ""

    def _bounds(self, rep: TrainReport) -> tuple[float, float, float, float, float]:
        """(max safe front, min safe rear, worst-case speed, braking-rate lower bound, worst
        reverse speed: the speed's lower bound below 0, else 0)."""
        p = self.params
        k = NormalDist().inv_cdf(1.0 - p.integrity_risk / 2.0)
        sv = math.sqrt(max(rep.var_velocity, 0.0))
        front = rep.position + rep.pl_ahead
        rear = rep.position - rep.pl_behind - p.train_length
        speed = max(rep.velocity, 0.0) + k * sv
        f_low = 1.0
        if math.isfinite(rep.braking_rate):
            sf = math.sqrt(rep.var_braking_rate) if math.isfinite(rep.var_braking_rate) else 0.0
            f_low = max(rep.braking_rate - k * sf, p.min_braking_rate)
        return front, rear, speed, f_low, max(k * sv - rep.velocity, 0.0)

    def _age(self, train_id: str, rep: TrainReport, now: float) -> float:
        """s since the report's sample, on the zone's clock, at least: with one clock the
        stamp's age on the followed timeline; on separate clocks from the train timeline
        (:meth:`_Timeline.offset_at`: this report's sample was at the latest its stamp less
        that); never less than since it arrived."""
        tl = self.timelines.get(train_id)
        age = now - rep.t_received
        if tl is not None and math.isfinite(tl.ref):
            ref = tl.shift if self.params.check_stamp_age else \
                tl.offset_at(now, self.params.max_clock_drift)
            age = max(age, now - rep.stamp + ref)
        return max(age, 0.0)

    def worst_stop(self, train_id: str, rep: TrainReport, now: float) -> float:
        """m, where the train stops at worst from ``now`` on (module doc): its max safe front
        end carried to the present at the worst-case speed (the train may have run on since
        the report's sample: a node that stalled 8 s delivered its backlog within the stale
        timeout, and the fronts it stated were metres behind the train), plus the braking
        distance from that speed at the braking rate's lower bound. Over the report's age the
        train may also have accelerated at up to ``max_acceleration``: the front runs that much
        further and the speed braked from is that much higher."""
        front, _, speed, f_low, _ = self._bounds(rep)
        age = self._age(train_id, rep, now)
        # the train may have accelerated since its sample (a report 3 s old on a slower route
        # stated the speed of a metro pulling away, 3 m/s below its speed then: its worst stop
        # fell 1-7 m short)
        a = self.params.max_acceleration
        front += speed * age + 0.5 * a * age * age
        speed += a * age
        return front + speed * speed / (2.0 * f_low * self.params.emergency_decel)

    @guarded(_failed_authorities)
    def authorities(self, now: float, train_ids: list[str]) -> list[Authority]:
        """One authority per train in ``train_ids`` at zone-controller time ``now`` (s)."""
        p = self.params
        unsafe = {tid: self.unsafe(tid, now) if tid in self.reports else ("no estimate", "")
                  for tid in train_ids}
        out = []
        for tid in train_ids:
            rep = self.reports.get(tid)
            if rep is None:
                out.append(Authority(tid, -math.inf, 0.0, True, "no estimate received yet",
                                     "no_estimate"))
                continue
            # every danger point the train may not yet have passed (its min safe front short
            # of it), however close: one within the margin was dropped, and a train 10 m short
            # of the line's end got the open line
            hazards = [(d - p.margin, f"danger point at {d:.1f} m") for d in p.danger_points
                       if d >= rep.position - rep.pl_behind]
            reason, state = "", "ok"
            mine = self.bounded.get(tid, rep)
            for other in train_ids:
                orep = self.reports.get(other)
                if other == tid:
                    continue
                where = self.bounded.get(other)
                if orep is None or where is None:
                    # a supervised train not yet localised (or never bounded: ALARM from its
                    # first report) may be anywhere ahead
                    reason, state = f"position of {other} unknown", "ahead_unknown"
                    continue
                # ahead or behind by the trains' bounded reports: an ALARM report's position is
                # no bound and may put a train ahead behind the one it endangers (a restarted
                # count at -1.2 km took a leader off the follower's track: its authority ran to
                # the open line)
                # and ahead wherever the intervals allow it: its rear may lie ahead of this
                # train's front while this train's min safe front lies short of the other's
                # max safe rear (ordered by the point estimates of two overlapping intervals,
                # the true follower was taken for the leader and given the open line)
                if where.position <= mine.position and mine.position - mine.pl_behind >= \
                        where.position + where.pl_ahead - p.train_length:
                    continue
                _, orear, _, _, back = self._bounds(orep)
                # the rear carried back over the report's age at the report's worst reverse
                # speed (its speed's lower bound, K of its standard deviations, as the worst-
                # case speed ahead): a leader backing at 1 m/s, 2.9 s after its report, lay
                # 2.4 m behind the rear the follower was granted up to at a margin of 0
                orear -= back * self._age(other, orep, now)
                hazards.append((orear - p.margin, f"rear of {other}"))
                why, kind = unsafe[other]
                if why:
                    reason, state = f"train ahead ({other}): {why}", f"ahead_{kind}"
            eoa, what = min(hazards, default=(math.inf, "open line"))
            if unsafe[tid][0]:
                reason, state = unsafe[tid]
            elif not reason:
                stop = self.worst_stop(tid, rep, now)
                if stop > eoa:
                    reason = f"worst-case stop {stop:.1f} m passes EoA {eoa:.1f} m ({what})"
                    state = "overrun"
            out.append(Authority(tid, eoa, p.permitted_speed, bool(reason), reason, state))
        return out


@dataclass
class RefusalLog:
    """Which refusals to log: each (train, kind) at most once per ``interval`` s, with the
    number refused since it was last logged, so a flood of bad reports is one line per
    interval, not one per message."""

    interval: float  # s
    last_logged: dict = field(default_factory=dict)  # (train, kind) -> zone time
    pending: dict = field(default_factory=dict)  # (train, kind) -> refused since last logged

    def note(self, train_id: str, kind: str, now: float) -> int:
        """Count one refusal; the number to log now (0: stay quiet)."""
        key = (train_id, kind)
        self.pending[key] = self.pending.get(key, 0) + 1
        t = self.last_logged.get(key)
        if t is None or now - t >= self.interval or now < t:  # now < t: the clock was reset
            self.last_logged[key] = now
            return self.pending.pop(key)
        return 0
