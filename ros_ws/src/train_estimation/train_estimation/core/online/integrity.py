"""Integrity monitoring of an estimator's output (pure): the stated bound holds, or it says so.

A zone controller grants movement authority from the train's position interval; the worst
output is a position far off with a covariance that claims centimetres (a *wrong-side*
estimate). :class:`IntegrityMonitor` watches each estimator from outside the filter, on what
the runner sees (which readings were fused or refused, when, the clock events, the commands)
and on the estimates themselves, and labels every estimate:

- ``OK`` (0): none of the checks doubts it; the estimator's own covariance is published.
- ``DEGRADED`` (1): a check doubts it; the covariance is *inflated* to cover the doubt (below).
- ``ALARM`` (2): the error cannot be bounded; the estimate must not be used (the zone
  controller brakes).

Checks (each gives a reason, e.g. ``"no_measurement: 2.3 s"``):

``no_measurement``
    The time ``tau`` from the last fused odometer reading to the estimate's stamp. Beyond
    ``degraded_after`` the estimate is a prediction without measurements: DEGRADED, with the
    covariance of an unmodelled acceleration of at most ``accel_uncertainty`` (a white-jerk-free
    bound: a constant acceleration error ``a`` gives ``a tau^2 / 2`` of position and ``a tau`` of
    speed), added to the filter's own::

        P += a_u^2 [[tau^4 / 4, tau^3 / 2], [tau^3 / 2, tau^2]]

    Beyond ``alarm_after``: ALARM. (``degraded_after`` is at least 2.5 odometer periods: a
    1 Hz odometer's normal gaps are no doubt.)
``blind``
    Readings keep arriving but the estimator refuses them all (gate, order, stale stamps): a
    filter that disagrees with every measurement is lost. ``blind_readings`` odometer readings
    refused in a row with none fused: ALARM (at 10 Hz, 1 s).
``reacquired``
    The first odometer reading fused after a ``blind`` run, when the estimate jumps to take it
    (its position more than ``pos_z`` standard deviations from the estimate carried to it):
    the filter had refused the odometer for ``blind_readings`` readings or more, and takes it
    again only because its own prediction has grown wide enough to. Either the filter was
    lost and the odometer is right, or the odometer failed (a count stuck while the train ran
    on, which the filter then follows through the next departure) and the prediction was
    right: nothing on board tells which but a balise. ALARM until a balise is fused that
    agrees with the odometer's track (``balise`` below).
``position`` (a jump)
    The same two readings after a silence with nothing refused in it (an outage, a slow
    odometer's gaps), or a refused run shorter than ``blind_readings``: a fused reading whose
    position lies more than ``pos_z`` standard deviations (the estimate's own, the reading's
    and the odometer calibration's) from the last estimate carried to it. The estimate before
    the jump is carried as a solution beside the new one: its separation taken at the first
    estimate after the jump (the estimate carried on at its speed and acceleration, with
    ``accel_uncertainty``'s growth, less the new estimate) and kept, since a count that was
    wrong by so much carries its error on. DEGRADED until a balise fused on the odometer's
    track lies beyond ``pos_z`` of that solution too. Likewise a fused speed that no train
    reaches from the last estimate's (its speed-test term beyond ``pos_z`` squared, with
    ``max_acceleration``): a speed sensor stuck at standstill under a count spliced where the
    estimate was; the estimate before it is carried on at its own speed (the separation
    grows), until a balise excludes it the same way. Neither counts readings: the jump itself
    is the evidence (a consistent filter's estimate jumps beyond 5 sigma with probability
    about 6e-7).
``standing``
    The odometer's count has not moved (less than ``still_count`` or four of its stated
    distance deviations, three readings at least) over a span in which the traction commanded
    was surely delivered (in force for the believed actuator's delay plus three time
    constants before it, so at 95 % of itself) at a
    level above what holds a standing train there (the believed starting resistance plus the
    map's uphill gradient at the estimate plus ``still_margin``), by enough to have run the
    train ``still_run`` m at least. The train is moving and the odometer does not see it (a
    count stuck during a dwell, which the filter would follow through the departure). ALARM,
    held like ``reacquired`` until a balise is fused that agrees with the odometer's track.
    Likewise a count that has stood (two fused readings at least at one count, all but the
    first reading standstill, the last recent) while the train, from the speed read at the
    first of them (or, where that one reads standstill too, at the count's last move less
    what braking takes away since) and braking at the most it can (the believed emergency
    braking, the resistance at that speed, the map's climb and ``still_margin``), must have
    run ``still_run`` m at least: a count stuck while the train ran, which the filter took.
    (Needs the believed train and line: the runner gives the estimator's. A traction that
    takes effect a second later than believed has run the train metres by then, not
    centimetres.)
``speed_nis``
    The normalised innovation squared of each fused odometer speed against the previous
    estimate, ``(v_meas - v_prev)^2 / (P_vv + r + (a_max dt)^2)`` (``a_max``: the train's largest
    plausible acceleration, so that a consistent filter gives a mean of at most about 1),
    averaged over the last ``nis_window`` readings. For a consistent filter the window mean of
    ``n`` chi-square(1) terms exceeds ``1 + z sqrt(2 / n)`` with probability ~ the normal tail of
    ``z``; above it: DEGRADED, the covariance scaled by the mean (covariance inflation restores
    NIS = 1); above ``nis_alarm``: ALARM.
``position``
    The odometer's distance read as the estimator's own position measurement (start position
    plus counted distance, with the estimator's ``distance_variance``), against the previous
    estimate carried to the reading's stamp: innovation ``nu = pos - (x + v dt + a dt^2 / 2)``,
    variance ``S = P_xx + P_vv dt^2 + (accel_uncertainty dt^2 / 2)^2 + r``. A bias, not a
    spread: the mean of the last ``pos_window`` innovations against its standard error
    ``sqrt(mean S / pos_window)``; beyond ``pos_z`` of them (a consistent filter's innovations
    are white and unbiased) the estimate and the distance disagree by more than either claims:
    DEGRADED, position variance increased by the mean squared. (A filter that absorbs a
    position offset slowly, one reading's weight at a time, stays centimetre-confident while
    metres off; the speed test does not see it.)
``clock``
    Two or more readings held back as a possible clock step (the runner has not decided: one
    reading late by jitter is held for a period and says nothing), or one that no lateness
    explains (stamped above its clock, or on a slot already fused; with an odometer slower
    than 2 Hz, any: the reading that decides comes too late to wait for), or a step
    re-anchored less than ``reanchor_hold`` s ago (a step whose size was assumed from the
    stamps alone, without arrival times; one measured from the arrivals of the readings that
    decided it is known to the link's jitter and needs no hold): two solutions, the train where
    the estimate's motion puts it ``T`` s after and before its stamp (the stamp may be read on
    either side of the step: ``x +- v T + a T^2 / 2``, ``a`` the estimate's acceleration, with
    the variance ``(sd_x + T sd_v + T^2 sd_a / 2)^2 + (accel_uncertainty T^2 / 2)^2``: its state
    carried over ``T`` whatever its correlations, and the unmodelled acceleration's; without an
    acceleration estimate ``sd_a`` is ``max_acceleration`` and ``a`` 0), and the published
    position variance grown to cover them.
    While readings are held, ``T`` is the largest discontinuity among them (the candidate
    step), after a step one sample period (a re-anchored step is known to about that). So too
    a balise later than lateness allows while the odometer is silent (``T`` its lateness),
    and, until a balise places the train, the other reading of a clock decision taken after
    a gap that neither the counter nor the count timed (:meth:`IntegrityMonitor.untimed`).
``balise``
    A balise and the odometer that disagree by more than either claims: either the balise
    lies elsewhere than the map says or the estimate (and the odometer) is off, and nothing
    tells which until a later balise agrees. The odometer's *track* is its latest position
    reading (start position plus counted distance, with the estimator's distance variance),
    fused, or refused by the gate alone where its distance and speed continue the track (within
    ``pos_z`` and ``max_acceleration``), carried at its own speed reading; it does not depend on
    the filter, whose interval may be wide enough to take a balise that lies metres off and is
    narrow once it has. A balise the filter refused as far outside its interval
    (``outside_gate``), or fused while it lies more than ``pos_z`` standard deviations from
    the track (``S = r_odo + r_balise + r_speed dt^2 + (accel_uncertainty dt^2 / 2)^2``, and
    again when the next odometer reading is in, with the odometer's position interpolated
    between the readings either side, whose verdict replaces the first), puts the estimate in
    doubt: DEGRADED until a balise is fused that agrees with the track, the position variance
    increased so that the interval holds both the odometer's track and the balise's (the track
    moved by their disagreement) at the estimate's stamp. Without a track (an estimator that
    does not use the distance) a refused balise's position is carried at the estimated speed
    and a fused one is taken as it is. Refusals are counted by the runner
    (``balise:outside_gate``).
``no_command``
    No control command for ``command_timeout`` while readings arrive: the filters hold the last
    command; DEGRADED with the ``no_measurement`` inflation over the silence beyond the timeout
    limited to one sample period (measurements still correct the prediction every period).

Everything is on the estimator's (train) clock: stamps of estimates and readings, so that a
replay of a bag reproduces a node's labels exactly.
"""

from __future__ import annotations

import bisect
import itertools
import math
from collections import deque
from dataclasses import dataclass
from operator import itemgetter

import numpy as np
from train_core.config import param, require, require_finite

from .. import reasons as R
from .calibrated_odometry import ON_TIME
from .protection import RARE_SHARE, Hypothesis, label, protection_levels

OK, DEGRADED, ALARM = 0, 1, 2
V_STILL = 0.5  # m/s: an odometer speed reading at or below this reads standstill
_STAMP = _FIRST = itemgetter(0)  # the stamp of a window's entry (bisect's key)
_SECOND = itemgetter(1)
BURST_NEGLIGIBLE = 1e-3  # -, a step's burst hypothesis (IntegrityMonitor.clock) is dropped once
#   its prior is this fraction of its share of the risk: until then protection_levels charges
#   it its share, monitored or not; after, what it could still add is a thousandth of that
SURE = 1.0 - math.exp(-3.0)  # a first-order lag's output three time constants after a step
UNBOUNDED = 1e12  # m^2, (m/s)^2: the variance published when the filter's is not usable
NAMES = {OK: "OK", DEGRADED: "DEGRADED", ALARM: "ALARM"}


@dataclass(frozen=True)
class IntegrityParams:
    """Thresholds of the integrity checks (declared as node parameters; config/*.yaml)."""

    degraded_after: float = param(0.5, "s", "no odometer reading fused for this long: DEGRADED, "
                                  "covariance inflated by accel_uncertainty")
    alarm_after: float = param(60.0, "s", "no odometer reading fused for this long: ALARM")
    accel_uncertainty: float = param(0.15, "m/s^2", "bound on the acceleration the model does "
                                     "not know (gradient map, resistance, adhesion), used to "
                                     "inflate predictions without measurements")
    blind_readings: int = param(10, "-", "odometer readings refused in a row with none fused: "
                                "ALARM")
    max_acceleration: float = param(1.5, "m/s^2", "largest plausible acceleration of the train, "
                                    "for the speed-consistency check between samples")
    nis_window: int = param(30, "-", "fused odometer speeds in the consistency window")
    nis_z: float = param(5.0, "-", "window-mean NIS above 1 + nis_z sqrt(2 / nis_window): "
                         "DEGRADED (covariance scaled by the mean)")
    nis_alarm: float = param(100.0, "-", "window-mean NIS above this: ALARM")
    reanchor_hold: float = param(2.0, "s", "DEGRADED for this long after a clock step was "
                                 "re-anchored on its stamps alone (no arrival times; a step "
                                 "measured from the arrivals needs no hold)")
    stamp_burst_continue: float = param(0.5, "-", "probability that a burst of readings "
                                        "stamped alike wrongly (a sender's clock read wrong, "
                                        "then right again) goes on for one reading more: a "
                                        "declared clock step is carried as such a burst, prior "
                                        "continue^(n-1) after n readings on the new clock, "
                                        "until that is within its share of the integrity risk "
                                        "(protection.py, rare faults); 0 = no burst outlasts "
                                        "the readings that declare a step", lo=0.0, hi=0.99)
    command_timeout: float = param(2.0, "s", "no control command for this long while readings "
                                   "arrive: DEGRADED (above the keep-alive period of a command "
                                   "stream logged only when it changes)")
    pos_window: int = param(10, "-", "fused odometer distances in the position-bias window")
    pos_z: float = param(5.0, "-", "mean position innovation beyond pos_z standard errors: "
                         "DEGRADED (position variance + the mean squared)")
    still_run: float = param(5.0, "m", "the odometer's count unmoved while the traction "
                             "delivered must have run the train this far: ALARM")
    still_count: float = param(0.5, "m", "a count that moves less than this is unmoved")
    still_margin: float = param(0.05, "m/s^2", "traction beyond the starting resistance and "
                                "the map's uphill gradient that a standing train cannot "
                                "withstand (the map's and the resistance's errors)")
    integrity_risk: float = param(1e-7, "-", "probability per estimate that the true position "
                                  "lies outside [position - protection_level_behind, position + "
                                  "protection_level_ahead] without an ALARM (protection.py)")
    balise_map_prior: float = param(1.0, "-", "prior probability that a balise's surveyed "
                                    "position is wrong by more than its stated accuracy (per "
                                    "balise: a survey or map error): the solutions without each "
                                    "recent balise get the risk it allots (protection.py, rare "
                                    "faults); 1 = not stated, each covered as if certain",
                                    lo=0.0, hi=1.0)
    start_fault_prior: float = param(1.0, "-", "prior probability that the start "
                                     "(initial_position) is wrong by more than its stated "
                                     "standard deviation (per run: a position keyed in or "
                                     "carried over wrong): the solution without the start gets "
                                     "the risk it allots (protection.py, rare faults); 1 = not "
                                     "stated", lo=0.0, hi=1.0)
    alert_limit: float = param(math.nan, "m", "largest protection level the operation can "
                               "use: within it the estimate is OK, beyond it DEGRADED (still "
                               "bounded); NaN = the line's (line.yaml alert_limit), 10 m where "
                               "the line states none")

    def __post_init__(self):
        require_finite(self, ("degraded_after", "alarm_after", "accel_uncertainty",
                              "max_acceleration", "nis_z", "nis_alarm", "reanchor_hold",
                              "command_timeout", "pos_z", "still_run", "still_count",
                              "still_margin"), strict=False)
        require(self.alarm_after > self.degraded_after, "alarm_after", self.alarm_after,
                "must be > degraded_after")
        require(self.blind_readings >= 1, "blind_readings", self.blind_readings, "must be >= 1")
        require(self.nis_window >= 2, "nis_window", self.nis_window, "must be >= 2")
        require(self.pos_window >= 2, "pos_window", self.pos_window, "must be >= 2")
        require(0.0 < self.integrity_risk < 0.5, "integrity_risk", self.integrity_risk,
                "must be in (0, 0.5)")
        require(0.0 <= self.stamp_burst_continue < 1.0, "stamp_burst_continue",
                self.stamp_burst_continue, "must be in [0, 1)")
        for name in ("balise_map_prior", "start_fault_prior"):
            require(0.0 <= getattr(self, name) <= 1.0, name, getattr(self, name),
                    "must be in [0, 1]")
        require(math.isnan(self.alert_limit) or (math.isfinite(self.alert_limit)
                                                  and self.alert_limit > 0), "alert_limit",
                self.alert_limit, "must be > 0 (or NaN: the line's)")


# the odometer calibration's solutions (Output.separation) by kind, as hypotheses
_CAL_NAMES = {"map": "balise_map", "start": "start", "reader": "late_reader"}
_NEW = tuple.__new__

DEFAULT_ALERT_LIMIT = 10.0  # m, where neither the parameter nor the line states one


def alert_limit(params: IntegrityParams, line=None) -> float:
    """m, the alert limit in force: the parameter's, else the line's, else 10 m."""
    if math.isfinite(params.alert_limit):
        return float(params.alert_limit)
    stated = getattr(line, "alert_limit", math.nan)
    return float(stated) if math.isfinite(stated) else DEFAULT_ALERT_LIMIT


class IntegrityMonitor:
    """Labels and inflates the estimates of one estimator (module doc). Fed by the runner:
    :meth:`reading` for every odometer outcome, :meth:`command`, :meth:`clock`, then
    :meth:`assess` for each estimate."""

    def __init__(self, params: IntegrityParams = IntegrityParams(), period: float = 0.1,
                 train=None, line=None):
        self.p, self.period = params, float(period)
        # the believed train and line (``standing``; None: that check is off)
        self.train, self.line = train, line
        self.alert_limit = alert_limit(params, line)
        self.commands: deque = deque()  # (stamp, m/s^2) of the commands of the last window
        self.counts_seen: deque = deque()  # (stamp, odometer count m) of the last window
        self.fused_seen: deque = deque()  # (stamp, count m, speed m/s) of fused readings
        # kept along with it, for _stopped_short at every estimate (a dwell's readings are not
        # scanned again each time): how far from its end (1: the last) its latest reading that
        # does not read standstill lies, and (count m, readings) of its last readings within
        # the count's tolerance of that count (None: not known, scanned when asked)
        self.still_fast = math.inf
        self.still_run: tuple | None = None
        self.last_fused = -math.inf  # stamp of the last fused odometer reading
        self.refused_run = 0  # odometer readings refused since the last fused one
        self.last_command = -math.inf  # stamp of the last command
        self.last_reading = -math.inf  # stamp of the latest odometer reading seen
        self.reanchored_at = -math.inf  # stamp of the last step re-anchored by assumption
        self.burst: list | None = None  # [the last declared step (s), its first stamp on the
        #   new clock, readings seen on it]: the hypothesis that it was a burst (:meth:`clock`)
        self.unsure: list | None = None  # [the step (s), its separation (m), its variance
        #   (m^2)]: the other reading of a clock decision after a silence that nothing timed,
        #   carried until a balise places the train (:meth:`untimed`)
        self.stray = 0.0  # s, a balise this late since the last odometer reading (clock)
        self.held = 0  # readings the runner holds as a possible clock step
        self.doubt = 0.0  # s, the largest discontinuity among them
        self.suspect = False  # they put the estimate in doubt (see clock)
        self.nis: deque = deque(maxlen=params.nis_window)
        self.prev: tuple | None = None  # (stamp, velocity, P_vv) of the last estimate
        self.prev_pos: tuple | None = None  # (stamp, position, velocity, acceleration, P_xx,
        #   P_vv) of the last estimate whose covariance is known
        self.pos: deque = deque(maxlen=params.pos_window)  # (nu, S) of fused distances
        self.balise_doubt: tuple | None = None  # (stamp, offset m or position m, what,
        #   track-based, m the reading without the calibrated reader latency lies from it) of
        #   a balise refused by the gate or fused while it disagrees with the odometer, until
        #   a balise is fused that agrees with the odometer
        self.by_speed: list | None = None  # [balise stamp, balise position m, stamp, metres
        #   run, speed m/s, variance m^2 by then, that speed's variance, m to the reading
        #   without the latency]: the balise of balise_doubt carried on by the odometer's speed
        #   readings (its other channel)
        self.since: list | None = None  # the same of the latest fused balise, whether it agreed
        #   or not (before the first, of the first odometer reading): where the train is if
        #   the count failed since then and its speeds did not
        self.balise_fused = False  # a balise has been fused (since is anchored on balises)
        self.since_doubt: bool | None = None  # since's distance beyond its noise at the last
        #   estimate at a reading (None: since not assessed yet)
        self.since_own = math.inf  # m^2, that estimate's fault-free position variance
        self.odo_track: tuple | None = None  # (stamp, position m, variance m^2, speed m/s,
        #   speed variance) of the latest odometer reading fused or refused by the gate only
        self.pending_balise: tuple | None = None  # (stamp, position, variance, late) of the last
        #   fused balise, until the next odometer position reading judges it again
        self.jumped: list | None = None  # [prev_pos's six before a fused odometer reading
        #   that made the estimate jump, the separation m and variance m^2 of that solution,
        #   taken at the next estimate (NaN until then)], until a balise excludes it
        self.agreed: tuple | None = None  # (stamp, position m, variance m^2) of the latest
        #   balise that agreed with the odometer's track
        self.sped: tuple | None = None  # prev_pos's six before a fused odometer speed that
        #   no train reaches from it: that solution carried on, until a balise excludes it
        self.count_doubt: tuple | None = None  # (stamp, check, why): the odometer's count in
        #   doubt (``reacquired`` or ``standing``) until a balise confirms its track
        self.count_out = False  # the estimator excluded the odometer's count (count_excluded)
        self.counts = {NAMES[k]: 0 for k in NAMES}
        self.last_state = (OK, "")

    def count_excluded(self) -> None:
        """The estimator excluded the odometer's count (a balise and the odometer's speeds
        contradicted it: ``calibrated_odometry.DistanceAsPosition._count_failed``) and reads
        no distance from here on: the count's checks (``standing``, the tracks and doubts
        built on its positions) and the solutions carried beside an estimate that followed
        it go, as does the last estimate (the filter was moved onto the speeds' track: the
        jump is the exclusion's, judged by its likelihood ratio, not a reading's). The
        exclusion's own risk is the ratio's bound, charged as the calibration's are."""
        self.count_out = True
        self.odo_track = self.pending_balise = self.balise_doubt = self.by_speed = None
        self.since = self.jumped = self.sped = self.count_doubt = self.agreed = None
        self.since_doubt, self.since_own = None, math.inf
        self.prev = self.prev_pos = None
        self.pos.clear()
        self.counts_seen.clear()
        self.fused_seen.clear()
        self.still_fast, self.still_run = math.inf, None

    # -- inputs ---------------------------------------------------------------------------------
    def reading(self, stamp: float, fields: dict | None, fused: bool,
                position: tuple | None = None, gate: bool = False) -> None:
        """An odometer reading's outcome (fused or refused, for any reason); ``position``: the
        estimator's own position measurement of it, ``(m, variance m^2)``, or None; ``gate``:
        refused by the filter's gate only (its values plausible, the filter's state not: after
        a balise that lay elsewhere the odometer still tells where the train is)."""
        if not math.isfinite(stamp):
            self.refused_run += 1
            return
        if self.burst is not None and stamp >= self.burst[1]:
            self.burst[2] += 1
        if not self.count_out:
            self._remember(self.counts_seen, stamp, fields, ("distance",))
        if fused or gate:
            self._track(stamp, fields, position, fused)
        if fields is not None:
            self._speeds(stamp, fields)
        if not fused:
            self.refused_run += 1
            return
        if self.refused_run >= self.p.blind_readings and self._jumps(stamp, position, fields):
            self.count_doubt = (stamp, "reacquired", f"the odometer taken again after "
                                                     f"{self.refused_run} readings refused in "
                                                     "a row")
        elif self.jumped is None and position is not None \
                and self._jumps(stamp, position, fields, calibrated=True) \
                and not self._excluded(self.prev_pos):
            # the estimate jumps to take this reading (beyond its own and the calibration's
            # doubt): the reading is right and the estimate was off, or it is wrong (a count
            # stuck through a silence) and the estimate carried on was right. Nothing but a
            # balise tells which: the estimate before the jump is carried beside the new one
            # (unless the balise that moved the count's calibration there told already). On
            # a position reading only: without one (use_distance false) a speed is judged by
            # what no train reaches (sped, below), not by the unmodelled acceleration alone,
            # which a balise's correction of a speed read 1-2 % off exceeds at every reading
            self.jumped = [self.prev_pos, math.nan, math.nan]
        self.refused_run = 0
        kept = None if self.count_out else \
            self._remember(self.fused_seen, stamp, fields, ("distance", "speed"))
        if kept is not None:
            self._seen_fused(kept)
        self.last_fused = max(self.last_fused, stamp)
        self.last_reading = max(self.last_reading, stamp)
        if fields is not None and self.prev is not None:
            if self._speed_nis(stamp, fields) > self.p.pos_z ** 2 and self.sped is None \
                    and self.prev_pos is not None:
                # a speed no train reaches from the last estimate's (beyond pos_z with
                # max_acceleration): the reading is wrong (a speed stuck at standstill) or
                # the estimate was; the estimate before it, carried on, beside the new one
                self.sped = self.prev_pos
        if position is not None and self.prev_pos is not None:
            self._position_bias(stamp, position)

    def _track(self, stamp: float, fields: dict | None, position: tuple | None,
               fused: bool) -> None:
        """The odometer's own track: its latest position reading and speed (``odo_track``); a
        balise fused before it is judged again against it (:meth:`_balise_between`)."""
        try:
            z, r = float(position[0]), float(position[1])
            # the odometer's calibration: shared with the estimate (not in the position test)
            # but not with a balise, which the track is judged against
            r += float(position[2]) if len(position) > 2 else 0.0
            v, rv = float(fields["speed"]), float(fields["speed_variance"])
        except (KeyError, TypeError, ValueError, IndexError):
            return
        if not (math.isfinite(z) and math.isfinite(r) and math.isfinite(v)
                and math.isfinite(rv)) or r <= 0 or rv < 0:
            return
        if self.odo_track is not None and stamp < self.odo_track[0]:
            return
        if not fused and not self._continues(stamp, z, r, v, rv):
            return  # a reading the filter refused joins the track only where it continues it
        if self.pending_balise is not None and stamp > self.pending_balise[0]:
            self._balise_between(stamp, z, r, fused)
        self.odo_track = (stamp, z, r, v, rv)
        if self.since is None and fused and not self.balise_fused:
            self.since = self._speed_track(stamp, z, r)  # the count's first word (until a balise)
        elif self.since is None and fused and self.since_doubt is False:
            # its first after a silence: from the reading where it agrees with the estimate
            # carried to it (within pos_z of the two), else from that estimate: a reading the
            # estimate jumps to take is a count in question, no anchor (from the reading
            # itself, a count at half the distance re-anchored the track 145 m behind the
            # train, and the kf's next jump, 484 m, was outside its levels: crh3_high_speed
            # at 1 Hz, a reading lost while braking). (From the estimate always, a 60 s
            # outage anchored the track on an estimate carried through it: levels of 6.5 km
            # to the next balise, wen2017_subway)
            dt, pred, s = self._carried_moving(stamp)
            jump = dt >= 0 and math.isfinite(pred) and math.isfinite(s) and s > 0 and \
                abs(z - pred) > self.p.pos_z * math.sqrt(s + r)
            self.since = self._speed_track(stamp, pred, s) if jump else \
                self._speed_track(stamp, z, r)

    def _speeds(self, stamp: float, fields: dict) -> None:
        """The speed tracks (:attr:`by_speed`, :attr:`since`) run on by a reading's speed,
        whatever became of its count (a count that failed is refused, its speeds are what
        these tracks hold): the trapezoid of the two speeds, their variances with it and an
        unmodelled acceleration of ``accel_uncertainty`` over the interval (``dt^2 / 4`` of it
        is what the trapezoid can miss). A speed no train reaches from the track's last
        (``max_acceleration``, beyond ``pos_z``) is not taken (a corrupted reading).

        Across a silence neither channel read, and the speeds' trapezoid over it says little
        once its own variance exceeds the estimate's at the last reading (a standard deviation
        of 135 m over a 60 s outage, which the track then kept to the next balise: protection
        levels of 0.4-8 km after an outage; a few tenths of a metre over the 3 s a lossy link
        leaves between 1 Hz readings). :attr:`since` then starts again from the count's next
        fused reading, unless the two channels already disagreed before the silence (its
        doubt, :meth:`assess`): a count that fails after the silence is seen from there as
        from a balise, one that failed before it was seen before it and stays carried."""
        try:
            v, rv = float(fields["speed"]), float(fields["speed_variance"])
        except (KeyError, TypeError, ValueError):
            return
        if not (math.isfinite(v) and math.isfinite(rv) and rv >= 0):
            return
        p = self.p
        for b in (self.by_speed, self.since):
            if b is None or not stamp > b[2]:
                continue
            dt = stamp - b[2]
            if abs(v - b[4]) > p.max_acceleration * dt + p.pos_z * math.sqrt(rv + b[6]):
                continue
            gap = 0.25 * dt * dt * (b[6] + rv) + (0.25 * p.accel_uncertainty * dt * dt) ** 2
            if b is self.since and not self.since_doubt and gap > self.since_own:
                self.since = None  # from the count's next fused reading (_track)
                continue
            b[2:7] = [stamp, b[3] + 0.5 * (b[4] + v) * dt, v, b[5] + gap, rv]

    def _jumps(self, stamp: float, position: tuple | None, fields: dict | None = None,
               calibrated: bool = False) -> bool:
        """Whether a reading's position lies more than ``pos_z`` standard deviations (the
        filter's own position variance carried to it, plus the reading's) from the last
        estimate carried to its stamp: the estimate jumps to take it. A reading that continues
        the prediction after the filter refused a run of late ones (a recorder's stall) does
        not; one that moves a kilometre onto a count stuck since the last stop does. An
        estimator without a position reading (``use_distance: false``) is judged on the speed
        the same way: a filter that takes a speed sensor reading standstill while the train
        runs drops its speed by more than it claims to know it. ``calibrated`` (the jump
        hypothesis, :attr:`jumped`): the odometer calibration's variance in the test too, and
        a reading older than the estimate (fused again after a rewind) judged as well, the
        estimate carried back to it."""
        if self.prev_pos is None:
            return False
        if position is None:
            try:
                z, r = float(fields["speed"]), float(fields["speed_variance"])
            except (KeyError, TypeError, ValueError):
                return False
            t0, _, v0, a0, _, pvv = self.prev_pos
            dt = stamp - t0
            pred = v0 + (a0 if math.isfinite(a0) else 0.0) * dt
            s = pvv + r + (self.p.accel_uncertainty * dt) ** 2
        else:
            z, r = float(position[0]), float(position[1])
            dt, pred, s = self._carried(stamp)
            s += r
            if calibrated and len(position) > 2:
                s += float(position[2])  # the calibration's, which moves the reading's origin
        if not (math.isfinite(z) and math.isfinite(s) and s > 0 and (dt >= 0 or calibrated)):
            return False
        return abs(z - pred) > self.p.pos_z * math.sqrt(s)

    def _carried(self, stamp: float) -> tuple[float, float, float]:
        """The last estimate whose covariance is known carried to ``stamp`` at its speed and
        acceleration: (dt s, position m, the filter's own position variance carried, m^2)."""
        return _carry(self.prev_pos, stamp)

    def _carried_moving(self, stamp: float) -> tuple[float, float, float]:
        """:meth:`_carried`, its variance with an unmodelled acceleration of
        ``accel_uncertainty`` over the interval too (``(a dt^2 / 2)^2``): where the train is
        by the estimate, as a track to judge a reading against; NaNs without an estimate."""
        if self.prev_pos is None:
            return math.nan, math.nan, math.nan
        dt, pred, s = self._carried(stamp)
        return dt, pred, s + (0.5 * self.p.accel_uncertainty * dt * dt) ** 2

    def _position_bias(self, stamp: float, position: tuple) -> None:
        z, r = position[:2]
        dt, pred, s = self._carried(stamp)
        if not (math.isfinite(z) and math.isfinite(r) and r > 0 and 0 <= dt <= 2.0):
            return  # across a gap the test says nothing (no_measurement covers it)
        s += (0.5 * self.p.accel_uncertainty * dt * dt) ** 2 + r
        if math.isfinite(s) and s > 0:
            self.pos.append((z - pred, s))

    def _bias(self) -> tuple[float, float]:
        """(mean position innovation m, its standard error m) over the window (the first
        readings: over those there are; one innovation 5 standard errors off is as sure a
        doubt as a window's mean), else (0, inf)."""
        n = len(self.pos)
        if n == 0:
            return 0.0, math.inf
        return (sum(map(_FIRST, self.pos)) / n, math.sqrt(sum(map(_SECOND, self.pos)) / n / n))

    def _speed_nis(self, stamp: float, fields: dict) -> float:
        """The reading's NIS term, appended to the window (0 when it adds none)."""
        t0, v0, pvv = self.prev
        try:
            v, r = float(fields["speed"]), float(fields["speed_variance"])
        except (KeyError, TypeError, ValueError):
            return 0.0
        dt = stamp - t0
        if not (math.isfinite(v) and math.isfinite(r) and r > 0 and 0 <= dt <= 2.0):
            return 0.0  # across a gap the test says nothing (no_measurement covers it)
        s = pvv + r + (self.p.max_acceleration * max(dt, self.period)) ** 2
        if s > 0 and math.isfinite(s):
            self.nis.append((v - v0) ** 2 / s)
            return self.nis[-1]
        return 0.0

    def balise(self, stamp: float, fields: dict | None, fused: bool, reason: str = "") -> None:
        """A balise reading's outcome: fused, or refused (``reason``, a rejection name)."""
        try:
            pos, var = float(fields["position"]), float(fields["position_variance"])
        except (KeyError, TypeError, ValueError):
            pos = var = math.nan
        if not (math.isfinite(pos) and math.isfinite(stamp)):
            return
        # the calibration placed the balise by the reader's latency it found; the reading
        # itself says the train was at the balise at its stamp (the reader on time). The
        # latency is the calibration's own hypothesis and a sensor fault can make one up (a
        # count at half the distance read as a reader 7.6 s early), so a balise that
        # disagrees with the odometer is carried both ways
        try:
            late = float(fields.get(ON_TIME, pos)) - pos
        except (TypeError, ValueError):
            late = 0.0
        late = late if math.isfinite(late) else 0.0
        odo = self._odometer_at(stamp)
        if odo is None and self.odo_track is None and self.prev_pos is not None:
            # no position readings at all (``use_distance: false``): the track a balise is
            # judged against is the estimate carried to it on the odometer's speeds
            dt, pred, s = self._carried_moving(stamp)
            if 0 <= dt <= 2.0:
                odo = (pred, s)
        if fused:
            self.pending_balise = None
            if not (math.isfinite(var) and var > 0):
                self.balise_doubt = self.by_speed = self.since = None  # nothing to judge by
                return
            # the speeds carry the train on from the balise. With no odometer track at it to
            # judge it by (its count refused since before it: one that froze while the speeds
            # read on), from the latest speed read, the track's being seconds old; and the
            # track is kept (dropped, the solution that held a frozen count's train went with
            # it, and the robust filter, back on the count, published 16 estimates 764-1,037 m
            # off within levels of 670 m: wen2017_subway at 1 Hz)
            b = self.since
            newer = odo is None and b is not None and \
                (self.odo_track is None or b[2] > self.odo_track[0])
            self.since = self._speed_track(stamp, pos, var, late,
                                           (b[2], b[4], b[6]) if newer else None)
            self.balise_fused = True
            if odo is None:
                self.balise_doubt = self.by_speed = None  # nothing to judge the balise by
                return
            self.pending_balise = (stamp, pos, var, late)
            if self._judge_balise(stamp, pos, var, *odo, may_clear=True, late=late):
                self.count_doubt = None  # an independent position agrees with the odometer
                self._place_untimed(pos - odo[0], odo[1] + var)
                self._place_jumped(stamp, pos, var)
            return
        if reason == R.OUTSIDE_GATE:
            # the two tracks: the odometer's, and the balise's (the odometer's moved by their
            # disagreement); without the odometer's, the balise carried at the estimated speed
            self.balise_doubt = (stamp, pos - odo[0], "refused by the gate", True, 0.0) \
                if odo is not None else (stamp, pos, "refused by the gate", False, 0.0)
            self._carry_by_speed(stamp, pos, var)

    def _continues(self, stamp: float, z: float, r: float, v: float, rv: float) -> bool:
        """Whether a reading continues the odometer's track: its distance within ``pos_z``
        standard deviations of the track carried to it and its speed within what
        ``max_acceleration`` allows (a corrupted distance or speed, refused by the gate, must
        not become the reference a balise is judged against)."""
        odo = self._odometer_at(stamp, self.p.max_acceleration)
        if odo is None:
            return False
        t0, _, _, v0, rv0 = self.odo_track
        dv = self.p.max_acceleration * (stamp - t0) + self.p.pos_z * math.sqrt(rv + rv0)
        return abs(z - odo[0]) <= self.p.pos_z * math.sqrt(odo[1] + r) and abs(v - v0) <= dv

    def _judge_balise(self, stamp: float, pos: float, var: float, z: float, s: float,
                      may_clear: bool, late: float = 0.0) -> bool:
        """A fused balise against the odometer's position ``z`` (variance ``s``) at its stamp:
        a doubt when they disagree beyond ``pos_z``; an agreement ends one only when
        ``may_clear`` (judged on a reading the filter fused). True when they agree. ``late``:
        m from ``pos`` to the reading without the calibrated reader latency (:meth:`balise`)."""
        nu = pos - z
        if abs(nu) > self.p.pos_z * math.sqrt(s + var):
            self.balise_doubt = (stamp, nu, f"fused {nu:+.1f} m from the odometer's position",
                                 True, late)
            self._carry_by_speed(stamp, pos, var, late)
            return False
        if may_clear:
            self.balise_doubt = self.by_speed = None
        self.agreed = (stamp, pos, var)
        return True

    def _carry_by_speed(self, stamp: float, pos: float, var: float, late: float = 0.0) -> None:
        """Start carrying a balise that disagrees with the odometer (at ``pos``, variance
        ``var``) on by the odometer's speed readings (:attr:`by_speed`): where the truth is if
        the balise is right and the count is wrong, the speed right (a count that froze while
        the speed reads on). The count's track moved by the disagreement assumes the count's
        increments right; this one assumes its speeds right."""
        if self.by_speed is None or self.by_speed[0] != stamp:
            self.by_speed = self._speed_track(stamp, pos, var, late)

    def _speed_track(self, stamp: float, pos: float, var: float, late: float = 0.0,
                     speed: tuple | None = None):
        """A balise at ``pos`` (variance ``var``; ``late`` m from it the reading without the
        calibrated reader latency) carried on by the odometer's speed readings from its stamp:
        ``[stamp, pos, last reading's stamp, metres run, speed, variance, speed's variance,
        late]`` (:attr:`by_speed`, :attr:`since`; :meth:`_speeds` runs it on), from ``speed``
        (its stamp, the speed and its variance) or else the odometer track's latest reading;
        None without either."""
        if speed is None:
            if self.odo_track is None:
                return None
            t0, _, _, v, rv = self.odo_track
        else:
            t0, v, rv = speed
        if not math.isfinite(var):
            return None
        dt = max(t0 - stamp, 0.0)  # an odometer reading after the balise already in
        return [stamp, pos, max(t0, stamp), v * dt, v, var + rv * dt * dt, rv, late]

    def _balise_between(self, t1: float, z1: float, r1: float, fused: bool) -> None:
        """The last fused balise judged again once the odometer reading after it is in: the
        odometer's position interpolated between the readings either side (tighter than the
        track carried at a speed: an acceleration error of ``accel_uncertainty`` over the two
        intervals only). A reading the gate refused can raise a doubt, not end one."""
        tb, pos, var, late = self.pending_balise
        self.pending_balise = None
        if self.odo_track is None:
            return  # no track yet to judge it by (every reading so far refused)
        t0, z0, r0 = self.odo_track[:3]
        if not (t0 <= tb < t1 and t1 - t0 <= 2.0):
            return
        w = (tb - t0) / (t1 - t0)
        z = z0 + w * (z1 - z0)
        s = (1 - w) ** 2 * r0 + w * w * r1 + (0.5 * self.p.accel_uncertainty * (tb - t0)
                                              * (t1 - tb)) ** 2
        self._judge_balise(tb, pos, var, z, s, may_clear=fused, late=late)

    def _odometer_at(self, stamp: float, accel: float | None = None) -> tuple | None:
        """(position m, variance m^2) of the odometer's track carried to ``stamp`` at its own
        speed reading, with an unknown acceleration of ``accel`` (default
        ``accel_uncertainty``; module doc, ``balise``), or None (no track, or more than 2 s
        away)."""
        if self.odo_track is None or not math.isfinite(stamp):
            return None
        t0, z, r, v, rv = self.odo_track
        dt = stamp - t0
        if not abs(dt) <= 2.0:
            return None  # across a gap the odometer's track says little (no_measurement)
        a = self.p.accel_uncertainty if accel is None else accel
        return z + v * dt, r + rv * dt * dt + (0.5 * a * dt * dt) ** 2

    def command(self, stamp: float, value: float = math.nan) -> None:
        if math.isfinite(stamp):
            self.last_command = max(self.last_command, stamp)
            if self.train is not None and math.isfinite(value):
                self._keep(self.commands, (stamp, float(value)))

    # s, the spans over which the ``standing`` check asks whether the count moved
    STILL_SPANS = (1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0, 24.0)

    def _window(self) -> float:
        """s: the commands and counts the ``standing`` check looks back over."""
        b = self.train.brake
        return b.delay + 3.0 * b.time_constant + self.STILL_SPANS[-1] + 1.0

    def _keep(self, q: deque, item: tuple) -> bool:
        """``item`` (stamp first) into the window ``q``, kept in order (a rewound runner tells
        past items again), and what lies before the window dropped, but for one entry (the
        command in force at its start). True when ``item`` went to the end."""
        last = not q or item >= q[-1]
        if last:
            q.append(item)
        else:
            bisect.insort(q, item)
        while len(q) > 1 and q[1][0] < q[-1][0] - self._window():
            q.popleft()
        return last

    def _remember(self, q: deque, stamp: float, fields: dict | None, keys: tuple) -> bool | None:
        """``(stamp, fields[k] for k in keys)`` into the window ``q`` when every value is a
        finite number (the ``standing`` check's; nothing without a believed train): what
        :meth:`_keep` returns, None when nothing was kept."""
        if self.train is None or not isinstance(fields, dict):
            return None
        try:
            vals = [float(fields[k]) for k in keys]
        except (KeyError, TypeError, ValueError):
            return None
        if all(map(math.isfinite, vals)):
            return self._keep(q, (stamp, *vals))
        return None

    def _seen_fused(self, last: bool) -> None:
        """``still_fast`` and ``still_run`` after a fused reading went into ``fused_seen``
        (``last``: at its end). Readings dropped from its start move neither end: the run is
        cut at the window's start, a reading at speed beyond it is beyond the run."""
        q = self.fused_seen
        if not last:  # placed among earlier readings (a rewind): the latest at speed found again
            self.still_run = None
            self.still_fast = next((j for j, (_, _, v) in enumerate(reversed(q), 1)
                                    if abs(v) > V_STILL), math.inf)
            return
        _, d, v = q[-1]
        self.still_fast = 1 if abs(v) > V_STILL else self.still_fast + 1
        run = self.still_run
        # a reading at the very count of the run extends it (the same tolerance of the same
        # count); any other count has a run of its own, scanned when asked
        self.still_run = (d, min(run[1] + 1, len(q))) if run is not None and d == run[0] \
            else None

    def _stopped_short(self, t: float, x: float) -> str:
        """Why the count that stands since its last move cannot be a train that stopped (the
        speed read at that move is more than any braking takes away in the time since), or
        "" (module doc, ``standing``)."""
        if self.train is None or self.line is None or len(self.fused_seen) < 4 or \
                not math.isfinite(x):
            return ""
        p, tr = self.p, self.train
        tol = self._count_tolerance()
        seen = self.fused_seen  # in stamp order (_keep)
        if abs(seen[-2][1] - seen[-1][1]) >= tol:
            return ""  # the count moved at the last reading (the train runs, as it mostly does)
        d_now = seen[-1][1]
        # the readings at the newest count (``at``, the last ``n``; ``seen[k]`` the one before
        # them): all but the first must read standstill (still_run and still_fast, kept as
        # the readings come: :meth:`_seen_fused`)
        if self.still_run is None or self.still_run[0] != d_now:
            n = 0
            for _, d, _ in reversed(seen):
                if not abs(d - d_now) < tol:
                    break
                n += 1
            self.still_run = (d_now, n)
        n = self.still_run[1]
        k = len(seen) - 1 - n
        if n < 2 or seen[-1][0] < t - 2.5 * self.period or self.still_fast < n:
            return ""  # no two readings at one count, or none lately (an outage says nothing)
        at0, last = seen[-n], seen[-1]
        v0 = abs(at0[2])
        moving = v0 > V_STILL
        if not moving and k < 0:
            return ""
        # the strongest deceleration the train can have there: its emergency brake, its
        # resistance at that speed, the map's climb, and the margin
        a_stop = (tr.performance.emergency_brake
                  + tr.resistance_accel(v0 if moving else abs(seen[k][2]))
                  + max(float(self.line.gradient_accel(x)), 0.0) / (1.0 + tr.rotary_allowance)
                  + p.still_margin)
        if not moving:
            # the count moved up to its first reading here: the least speed there, from the
            # last move's and braking since (through an outage, to a stop)
            v0 = max(abs(seen[k][2]) - a_stop * (at0[0] - seen[k][0]), 0.0)
        # the least the train runs while the readings stay at one count (lost ones between
        # them do not matter: the count is the same at both ends of a gap)
        span = last[0] - at0[0]
        run = v0 * span - 0.5 * a_stop * span * span if v0 > a_stop * span else \
            v0 * v0 / (2.0 * a_stop)
        if run < p.still_run:
            return ""
        return (f"the count stood {span:.1f} s ({n - 1} readings at standstill) from "
                f"{v0:.1f} m/s at least: braking at {a_stop:.2f} m/s^2, the most there is, "
                f"runs the train {run:.0f} m")

    def _count_tolerance(self) -> float:
        """m, the spread of counts that is no move: ``still_count`` or four of the odometer's
        stated distance standard deviations, the larger."""
        return max(self.p.still_count, 4.0 * float(getattr(self.train, "odometer_distance_std",
                                                             0.0) or 0.0))

    def _standing(self, t: float, x: float) -> str:
        """Why the train cannot be standing where its odometer stands (module doc,
        ``standing``), or ""."""
        if self.train is None or self.line is None or not math.isfinite(x) or \
                not self.commands or not self.counts_seen:
            return ""
        p, tr = self.p, self.train
        if t - self.commands[-1][0] > p.command_timeout:
            return ""  # the commands have stopped: the one in force now is not known
        # the command in force at t (the window is in stamp order, _keep)
        current = next((a for s, a in reversed(self.commands) if s <= t), None)
        hold = tr.davis.a / tr.effective_mass + p.still_margin
        if current is None or SURE * current <= hold:
            return ""  # the traction in force now (a bound on every span's) holds the train
        # on a climb the map's gradient holds it too (looked up only where the traction could
        # matter: the lookup costs more than the rest of the check)
        hold += max(float(self.line.gradient_accel(x)), 0.0) / (1.0 + tr.rotary_allowance)
        if SURE * current <= hold:
            return ""
        # both windows are in stamp order (_keep): searched in place, not copied into lists
        # at every estimate (a few hundred entries each)
        cmds, seen = self.commands, self.counts_seen
        now = bisect.bisect_right(cmds, t, key=_STAMP)  # the commands up to t
        b = tr.brake
        settle = b.delay + 3.0 * b.time_constant
        lowest, since = math.inf, now  # the least command from index ``since`` to now
        for span in self.STILL_SPANS:
            if span < 2.5 * self.period:
                continue  # three readings at least
            t0 = t - span - settle
            first = bisect.bisect_right(cmds, t0, key=_STAMP)  # the command in force at t0:
            if first == 0:  # first - 1
                return ""  # no command known in force over so long a span
            # the least command in force since t0: the spans grow, so only the commands
            # before the last span's are new (the first least in order, as min takes it)
            if first - 1 < since:
                new = min(a for _, a in itertools.islice(cmds, first - 1, since))
                lowest = new if since == now else min(new, lowest)
                since = first - 1
            a_sure = SURE * lowest
            if a_sure <= hold:
                return ""  # a longer span only lowers the traction surely delivered
            if 0.5 * (a_sure - hold) * span * span < p.still_run:
                continue
            lo = bisect.bisect_left(seen, t - span, key=_STAMP)
            hi = bisect.bisect_right(seen, t, key=_STAMP)  # the readings ``seen[lo:hi]``
            # readings over the whole span (an outage says nothing about the count)
            if not (hi - lo >= 3 and seen[lo][0] <= t - span + 2.5 * self.period
                    and seen[hi - 1][0] >= t - 2.5 * self.period):
                return ""
            tol = self._count_tolerance()
            # the span's first and last counts as far apart as the tolerance: their spread is
            # no less (a running train's, read without copying the span's few hundred counts)
            if abs(seen[hi - 1][1] - seen[lo][1]) >= tol:
                return ""
            d = [c for _, c in itertools.islice(seen, lo, hi)]
            if max(d) - min(d) < tol:
                return (f"the count stood {span:g} s ({len(d)} readings within "
                        f"{max(d) - min(d):.2f} m) while a traction of {a_sure:.2f} m/s^2 was "
                        f"delivered, above the {hold:.2f} m/s^2 that holds the train there: "
                        f"it must have run {0.5 * (a_sure - hold) * span * span:.0f} m")
            return ""  # the count moved over the shortest span that decides
        return ""

    def clock(self, held: int, reanchored_at: float | None = None, doubt: float = 0.0,
              conclusive: bool = False, measured: bool = False, step: float = 0.0,
              stray: float = 0.0) -> None:
        """The runner's clock state: readings held as a possible step, the largest
        discontinuity among them (s), whether one of them is no late reading; a step of
        ``step`` s re-anchored at ``reanchored_at`` (its first stamp on the new clock),
        ``measured`` from the offsets of the readings that decided it against their clock's
        centre (then known to the link's jitter: no hold) or assumed from the stamps alone
        (then held for ``reanchor_hold``).

        A declared step is also carried as what the same data say otherwise: a burst of
        readings stamped alike wrongly, after which the old clock comes back. The readings are
        placed right either way (the step's readings at their stamps minus the step); what
        differs is the clock the estimates are published on, the new one, which a burst would
        make ``step`` s wrong. No reading tells the two apart while the burst lasts, so the
        hypothesis is dropped by its prior alone: ``stamp_burst_continue^(n-1)`` after ``n``
        readings on the new clock, until that is within its share of the risk (a step
        declared after ``min_judged`` readings was confirmed by a count of readings, and one
        burst of ten wrong stamps 4.5 s off published estimates 90 m off within a 39 m
        protection level).

        ``stray`` (s): a balise came that much later than lateness allows since the last
        odometer reading; where the odometer stays silent beyond 1.5 periods (the reading
        that would tell a latency tail from a clock stepped back is not coming), the estimate
        is in doubt as while readings are held, by that much."""
        self.stray = stray
        self.held = held
        self.suspect = held >= 2 or (held >= 1 and conclusive)
        self.doubt = doubt if held else 0.0
        if reanchored_at is not None:
            self.reanchored_at = -math.inf if measured else reanchored_at
            self.burst = [step, reanchored_at, 0] if step and math.isfinite(step) and \
                self.p.stamp_burst_continue > 0.0 else None

    def untimed(self, step: float) -> None:
        """The runner's clock decided, after a silence that neither the odometer's count nor
        its sample counter timed (an outage, a sensor that rebooted, with its clock or not),
        between a step back of the train clock by ``|step|`` s and a link latency that rose by
        as much: the two differ only in how long the silence lasted, which no reading states
        (``StepWatch._step_open``). The other solution is where the train would be had
        the silence lasted ``|step|`` s longer or shorter: ``|step|`` s of the estimate's
        motion ahead or behind (:meth:`_moved`, taken at the first estimate after the decision
        and kept, since the count restarted at that moment carries the difference on
        unchanged). No rate is stated for either, so it is carried until a balise is fused
        that agrees with the odometer (:meth:`balise`). Without it, a reboot whose clock
        stepped back 3 s, taken for a latency on its stamps' phase, published 130 estimates
        59 m off within levels of 31 m (metro_demo, braking)."""
        if step and math.isfinite(step):
            self.unsure = [step, math.nan, 0.0]

    def _place_untimed(self, nu: float, s: float) -> None:
        """A fused balise ``nu`` m from the odometer's track (variance ``s`` m^2 of the two),
        which agrees with it: it ends the other reading of an untimed clock decision
        (:meth:`untimed`) when it lies beyond ``pos_z`` of that solution as well (a track
        whose own variance covers both tells neither)."""
        if self.unsure is None or not math.isfinite(self.unsure[1]):
            return
        _, sep, extra = self.unsure
        bar = self.p.pos_z * math.sqrt(s + extra)
        if abs(nu - sep) > bar and abs(nu + sep) > bar:
            self.unsure = None

    def _before(self, state: tuple, t: float) -> tuple[float, float]:
        """(position m, variance m^2) at ``t`` of an estimate left by a jump (``state``:
        :attr:`prev_pos`'s six), carried at its speed and acceleration with the unmodelled
        acceleration's growth (as a silence widens the estimate, ``no_measurement``)."""
        dt, x, s = _carry(state, max(t, state[0]))
        return x, s + (0.5 * self.p.accel_uncertainty * dt * dt) ** 2

    def _excluded(self, state: tuple) -> bool:
        """Whether the latest balise that agreed with the odometer's track, if it came after
        the estimate ``state`` (:attr:`prev_pos`'s six), lies beyond ``pos_z`` of that estimate
        carried to it: a jump onto a count that a balise has just placed (the calibration
        relocated on it) carries no solution before it."""
        b = self.agreed
        if b is None or b[0] < state[0]:
            return False
        x, s = self._before(state, b[0])
        return abs(b[1] - x) > self.p.pos_z * math.sqrt(s + b[2])

    def _place_jumped(self, stamp: float, pos: float, var: float) -> None:
        """A fused balise at ``pos`` (variance ``var``) that agrees with the odometer: it
        excludes the solution before a jump (:attr:`jumped`, and before a speed no train
        reaches, :attr:`sped`) when it lies beyond ``pos_z`` of that solution too (one that
        agrees with both tells neither)."""
        if self.sped is not None:
            x, s = self._before(self.sped, stamp)
            if abs(pos - x) > self.p.pos_z * math.sqrt(s + var):
                self.sped = None
        if self.jumped is None or not math.isfinite(self.jumped[1]) or self.prev_pos is None:
            return
        _, sep, extra = self.jumped
        dt, x, s = self._carried(stamp)
        if abs(pos - x - sep) > self.p.pos_z * math.sqrt(s + extra + var):
            self.jumped = None

    # -- output ---------------------------------------------------------------------------------
    def _nis_mean(self) -> float:
        n = len(self.nis)
        return sum(self.nis) / n if n >= self.p.nis_window // 2 else 0.0

    def assess(self, out, t: float):
        """``out`` (a runner Output for stamp ``t`` on the runner's train timeline) labelled,
        with its protection levels (``protection.py``) and its covariance inflated where a
        check doubts it.

        Each check's doubt is of one of two kinds. A fault-free widening (a silence, an
        inconsistent speed, no commands) widens the estimate's own variance. A fault the data
        have not excluded (a clock step, a biased distance, a balise and the odometer that
        disagree) is a hypothesis: a solution beside the estimate, ``shift`` m from it, that the
        protection levels cover. The published covariance holds both (a Gaussian that covers
        every live solution at one sigma, as before); the label is the protection levels' against
        the alert limit, so a doubt whose interval still fits the limit is OK."""
        p = self.p
        doubt, why, hyps = OK, [], []
        # the (position, speed) block as four floats (xx, xv, vx, vv), widened below with the
        # same operations, each rounded once, as on 2x2 arrays (the same numbers, a fifth of
        # the cost: the monitor runs at every estimate)
        cov = out.covariance
        P = (float(cov[0]), float(cov[1]), float(cov[4]), float(cov[5]))
        finite = math.isfinite(P[0]) and math.isfinite(P[1]) and math.isfinite(P[2]) \
            and math.isfinite(P[3]) and math.isfinite(out.position) and math.isfinite(out.velocity)
        if not finite or not (P[0] > 0 and P[3] > 0 and P[0] * P[3] - P[1] * P[1] > 0):
            # the filter's own covariance is broken: published as "unbounded" (never a negative
            # or non-positive-definite matrix a consumer could take for a bound). Products, not
            # powers: a float's ** raises past 1e308 where * gives inf (a filter diverged to a
            # covariance of 1e200 raised OverflowError here and stopped the run), and a
            # determinant that is inf - inf (NaN) is no bound either
            return self._label(out, t, ALARM, "covariance: not positive definite",
                               (UNBOUNDED, 0.0, 0.0, UNBOUNDED))
        tau = t - self.last_fused
        if self.refused_run >= p.blind_readings:
            return self._label(out, t, ALARM, f"blind: {self.refused_run} readings refused in a "
                                           f"row", None)
        if self.count_doubt is None:
            why_still = self._standing(t, out.position) or \
                self._stopped_short(t, out.position)
            if why_still:
                self.count_doubt = (t, "standing", why_still)
        if self.count_doubt is not None:
            _, check, why_doubt = self.count_doubt
            return self._label(out, t, ALARM, f"{check}: {why_doubt}; no balise has confirmed "
                                           "the odometer since", None)
        degraded_after = max(p.degraded_after, 2.5 * self.period)  # a slow odometer's gaps
        if tau > p.alarm_after:
            return self._label(out, t, ALARM, f"no_measurement: {tau:.1f} s", None)
        m = self._nis_mean()
        if m > p.nis_alarm:
            return self._label(out, t, ALARM, f"speed_nis: window mean {m:.3g}", None)
        # fault-free widenings: the estimate's own variance
        if tau > degraded_after:
            doubt = DEGRADED
            why.append(f"no_measurement: {tau:.1f} s")
            P = _plus(P, _accel_terms(p.accel_uncertainty, tau))
        if m > 1.0 + p.nis_z * math.sqrt(2.0 / p.nis_window):
            doubt = DEGRADED
            why.append(f"speed_nis: window mean {m:.3g}")
            P = tuple(v * m for v in P)
        silent = t - self.last_command
        no_command = math.isfinite(self.last_command) and silent > p.command_timeout
        if no_command:
            P = _plus(P, _accel_terms(p.accel_uncertainty, min(tau, self.period) + self.period))
        fault_free = P[0]
        # faults not excluded: hypotheses (and the covariance widened to cover them)
        stray = self.stray if self.stray and tau > 1.5 * self.period else 0.0
        if self.suspect or t - self.reanchored_at < p.reanchor_hold or stray:
            doubt = DEGRADED
            why.append("clock: " + (f"{self.held} readings held as a possible step"
                                    if self.held else "step re-anchored"
                                    if not stray else f"a balise {stray:.2f} s late and the "
                                    "odometer silent since"))
            T = max(self.period, self.doubt if self.suspect else 0.0, stray)
            # the estimate's stamp may be read on either side of the step
            run, bend, extra = self._moved(out, P, T)
            hyps += [Hypothesis("clock", run + bend, extra),
                     Hypothesis("clock", -run + bend, extra)]
            far = abs(run) + abs(bend)  # the farther of the two
            P = _plus(P, (far * far + extra, 0.0, 0.0, 0.0))
        if self.unsure is not None:
            step, sep, extra = self.unsure
            if not math.isfinite(sep):
                run, bend, extra = self._moved(out, P, abs(step))
                sep = abs(run) + abs(bend)
                self.unsure = [step, sep, extra]
            doubt = DEGRADED
            why.append(f"clock: after a silence, a step of {-abs(step):+.3f} s or a latency "
                       f"that rose as much (the train {sep:.1f} m apart); no balise since")
            hyps += [Hypothesis("clock", sep, extra), Hypothesis("clock", -sep, extra)]
            P = _plus(P, (sep * sep + extra, 0.0, 0.0, 0.0))
        if self.jumped is not None:
            state, sep, extra = self.jumped
            if not math.isfinite(sep):
                # the separation, taken at the first estimate after the jump and then kept:
                # a reading that was wrong by so much carries its error on in the count
                x, extra = self._before(state, t)
                sep = x - out.position
                self.jumped = [state, sep, extra]
            doubt = DEGRADED
            why.append(f"position: the estimate jumped to take an odometer reading; the "
                       f"solution had it been wrong {sep:+.1f} m away; no balise since")
            hyps.append(Hypothesis("position", sep, extra))
            P = _plus(P, (sep * sep + extra, 0.0, 0.0, 0.0))
        if self.sped is not None:
            x, extra = self._before(self.sped, t)
            sep = x - out.position
            doubt = DEGRADED
            why.append(f"speed: the odometer read a speed no train reaches from the estimate's "
                       f"at {self.sped[0]:.2f} s; the estimate before it carried on, {sep:+.1f} "
                       "m away; no balise since")
            hyps.append(Hypothesis("position", sep, extra))
            P = _plus(P, (sep * sep + extra, 0.0, 0.0, 0.0))
        if self.burst is not None:
            step, _, n = self.burst
            prior = p.stamp_burst_continue ** max(n - 1, 0)
            if n >= burst_readings(p):
                self.burst = None
            else:
                # a burst: the estimate's stamp, on the new clock, is ``step`` s ahead of the
                # old one it would be read on, and the train there is where its motion puts
                # it ``step`` s on. A rare fault: its prior, not the data, keeps it live, and
                # once within its share protection_levels leaves it unmonitored (charged)
                run, bend, extra = self._moved(out, P, step)
                hyps.append(Hypothesis("clock", run + bend, extra, prior))
                why.append(f"clock: the step of {step:+.3f} s re-anchored {n} readings ago "
                           f"may be a burst of wrong stamps (prior {prior:.2g})")
        b, se = self._bias()
        if abs(b) > p.pos_z * se:
            doubt = DEGRADED
            why.append(f"position: distance innovations {b:+.2f} m on average over "
                       f"{len(self.pos)} readings")
            hyps.append(Hypothesis("position", b))
            P = _plus(P, (b * b, 0.0, 0.0, 0.0))
        if self.balise_doubt is not None:
            sb, d, what, tracked, late = self.balise_doubt
            odo = self._odometer_at(t) if tracked else None
            if odo is not None:
                # the truth is on the odometer's track or on the balise's (the odometer's moved
                # by their disagreement ``d``): the interval holds both; the balise's by the
                # calibrated reader latency and, where that moved it, without it
                d1 = odo[0] - out.position
                offs = (d1, d1 + d, d1 + d + late) if late else (d1, d1 + d)
                nu = max(abs(o) for o in offs) + math.sqrt(odo[1])
                hyps += [Hypothesis("balise", o, odo[1]) for o in offs]
                told = (f"the odometer's track {d1:+.1f} m, the balise's {d1 + d:+.1f} m from "
                        "the estimate")
            elif tracked:  # no odometer reading lately (no_measurement covers the gap)
                nu = abs(d)
                hyps += [Hypothesis("balise", d), Hypothesis("balise", -d)]
                told = f"the sensors {d:+.1f} m apart"
            else:
                nu = d + out.velocity * (t - sb) - out.position
                hyps.append(Hypothesis("balise", nu))
                told = f"{nu:+.1f} m from the estimate"
            b = self.by_speed
            if b is not None and b[0] == sb:
                # the balise's track by the speed readings too: the count may be the channel
                # that failed (carried over a silence at the last speed, as the estimate is)
                for o, s2 in self._by_speeds(b, out.position, t):
                    hyps.append(Hypothesis("balise", o, s2))
                    nu = max(nu, abs(o) + math.sqrt(s2))
            doubt = DEGRADED
            why.append(f"balise: {what}; {told}")
            P = _plus(P, (nu * nu, 0.0, 0.0, 0.0))
        b = self.since
        if b is not None and not (
                self.balise_doubt is not None and self.by_speed is not None
                and self.by_speed[0] == b[0]):
            # the count may have failed since the latest balise while its speeds read on (a
            # register that froze or counts half the pulses): where the speeds carry the
            # train from that balise (before the first, from the count's first reading).
            # Always a solution, at the distance the two channels put between them (within
            # their noise while both work, so the levels grow by that much), and a doubt
            # once that exceeds the noise. Its variance is its own, ``s2``, not added to the
            # estimate's (the solution does not contain the estimate): the variance beyond
            # the estimate's, as the calibration's solutions are given (_label)
            tracks = self._by_speeds(b, out.position, t)
            hyps += [Hypothesis("odometer", o, max(0.0, s2 - fault_free)) for o, s2 in tracks]
            o, s2 = min(tracks, key=lambda e: abs(e[0]))
            if t - b[2] <= self.period:  # judged where a reading is (not on its extrapolation)
                self.since_doubt = abs(o) > p.pos_z * math.sqrt(s2 + fault_free)
                self.since_own = fault_free
            if self.since_doubt:
                doubt = DEGRADED
                why.append(f"odometer: its speed readings carry the train {o:+.1f} m from the "
                           f"estimate since {b[0]:.2f} s; its count does not")
                far = max(abs(e[0]) for e in tracks)
                # and the speed: under this solution the train runs at the speed readings, so
                # the published speed variance covers their distance from the estimate's too
                # (the position alone widened, a kf that took a count at half the distance
                # ran at 76-77 m/s within 0.2-1.1 m/s while the train and its speed readings
                # were at 82.6: 21 worst-case stopping points short of the true one,
                # crh3_high_speed, by up to 440 m)
                dv = b[4] - out.velocity
                P = _plus(P, (far * far + s2, 0.0, 0.0, dv * dv + b[6]))
        if no_command:
            doubt = DEGRADED
            why.append(f"no_command: {silent:.1f} s")
        return self._label(out, t, doubt, "; ".join(why), P if doubt else None,
                           fault_free, tuple(hyps))

    def _by_speeds(self, b: list, x: float, t: float) -> tuple:
        """``((shift m, variance m^2), ...)`` of the speed track ``b`` (:meth:`_speed_track`)
        carried to ``t`` at its last speed, from an estimate at ``x``: the balise as the
        calibration placed it and, where its reader latency moved it, the reading itself."""
        dt = t - b[2]
        s2 = b[5] + b[6] * dt * dt + (0.5 * self.p.accel_uncertainty * dt * dt) ** 2
        d2 = b[1] + b[3] + b[4] * dt - x
        return ((d2, s2), (d2 + b[7], s2)) if b[7] else ((d2, s2),)

    def _moved(self, out, P: tuple, T: float) -> tuple:
        """``(run, bend, extra)``: the train ``T`` s after the estimate's stamp (``T`` < 0:
        before) is where its motion puts it, ``run + bend = v T + a T^2 / 2`` m from the
        estimate. Its variance there is at most ``(sd_x + |T| sd_v + T^2 sd_a / 2)^2`` whatever
        the state's correlations, plus the unmodelled acceleration's over ``T`` (m^2; the
        stamp's seconds are not metres): beyond the estimate's own (``P``'s), the rest is the
        solution's ``extra``. Without an acceleration estimate ``a`` is 0 and ``sd_a`` any the
        train can do."""
        p = self.p
        run = out.velocity * T
        pa = float(out.covariance[10])
        if math.isfinite(out.acceleration) and math.isfinite(pa) and pa >= 0.0:
            bend, sd_a = 0.5 * out.acceleration * T * T, math.sqrt(pa)
        else:  # no acceleration estimated: any the train can do
            bend, sd_a = 0.0, p.max_acceleration
        sd_x = math.sqrt(P[0])
        carried = sd_x + abs(T) * math.sqrt(P[3]) + 0.5 * T * T * sd_a
        return run, bend, carried * carried - P[0] + _accel_terms(p.accel_uncertainty, T)[0]

    def _label(self, out, t: float, doubt: int, why: str, P, fault_free: float | None = None,
               hyps: tuple = ()):
        """The estimate published: the monitor's ``doubt`` (OK, DEGRADED: a check doubts it,
        ALARM: nothing bounds it) with the covariance ``P`` widened by the doubts, and the
        protection levels of the fault-free variance ``fault_free`` (the filter's own when
        None) and the live hypotheses ``hyps``, which set the label (module doc of
        ``protection.py``). ``P``: the (position, speed) block (xx, xv, vx, vv), or None."""
        C = np.array(out.covariance, dtype=float)
        if P is not None:
            C[0], C[1], C[4], C[5] = P
        if doubt == ALARM:
            ahead = behind = math.inf
        else:
            var = float(out.covariance[0]) if fault_free is None else fault_free
            # the odometer's calibration (the consider term the runner adds to the published
            # covariance): its fault-free solution's variance, and the solution without each
            # recent balise (one may lie elsewhere than its map position) as a hypothesis
            if out.separation:
                cal, alts = out.separation
                prior = {"map": self.p.balise_map_prior, "start": self.p.start_fault_prior}
                # (tuple.__new__: Hypothesis's own, without its Python-level __new__)
                hyps = (*hyps, *[_NEW(Hypothesis, (_CAL_NAMES[kind], m, max(0.0, v - cal),
                                                   prior.get(kind, 1.0))) for m, v, kind in alts])
                var += cal
            elif out.consider:
                var += float(out.consider[0])
            ahead, behind = protection_levels(var, hyps, self.p.integrity_risk)
        state = label(ahead, behind, self.alert_limit, doubt == ALARM)
        self.counts[NAMES[state]] += 1
        self.last_state = (state, why)
        # the speed variance the next NIS term uses: unknown (a broken or ALARM covariance)
        # counts as a wide one, so one bad estimate does not make every reading inconsistent
        known = (doubt == OK or P is not None) and C[5] < UNBOUNDED
        if math.isfinite(out.velocity):
            self.prev = (t, float(out.velocity), float(C[5]) if known else 1e6)
        # the filter's own covariance, not the inflated one: the position test judges the
        # filter (an inflation it caused must not silence it); its two variances read as
        # floats, not through a third 4x4 array per estimate
        own_xx, own_vv = float(out.covariance[0]), float(out.covariance[5])
        if math.isfinite(out.position) and math.isfinite(out.velocity) and \
                0 < own_xx < UNBOUNDED and 0 <= own_vv < UNBOUNDED:
            self.prev_pos = (t, float(out.position), float(out.velocity),
                             float(out.acceleration), own_xx, own_vv)
        else:
            self.prev_pos = None
        return changed(out, {"covariance": tuple(C), "integrity": state,
                             "integrity_reason": why, "protection_level_ahead": ahead,
                             "protection_level_behind": behind})


def changed(o, changes: dict):
    """``dataclasses.replace(o, **changes)`` for an estimate (``runner.Output``: no
    __post_init__ to run, no field to check): a copy of its attributes, a fifth of the cost,
    at every estimate."""
    new = object.__new__(type(o))
    d = new.__dict__
    d.update(o.__dict__)
    d.update(changes)
    return new


def burst_readings(p: IntegrityParams) -> int:
    """The readings on a declared step's new clock by which its burst hypothesis is dropped
    (:meth:`IntegrityMonitor.clock`): the fewest ``n`` whose prior ``stamp_burst_continue^(n-1)``
    is at most ``BURST_NEGLIGIBLE`` of its share of the risk (37 at the defaults; 0 without
    a prior for bursts)."""
    q = p.stamp_burst_continue
    if q <= 0.0:
        return 0
    bar = BURST_NEGLIGIBLE * RARE_SHARE * p.integrity_risk / 2.0
    return 1 + math.ceil(math.log(bar) / math.log(q) - 1e-9)


def _carry(state: tuple, t: float) -> tuple[float, float, float]:
    """An estimate ``state`` = (stamp, position, speed, acceleration, P_xx, P_vv) carried to
    ``t`` at its speed and acceleration (none when not finite): (dt s, position m, its
    position variance carried, m^2)."""
    t0, x0, v0, a0, pxx, pvv = state
    dt = t - t0
    a0 = a0 if math.isfinite(a0) else 0.0
    return dt, x0 + v0 * dt + 0.5 * a0 * dt * dt, pxx + pvv * dt * dt


def _plus(P: tuple, Q: tuple) -> tuple:
    """Two (xx, xv, vx, vv) blocks added (as two 2x2 arrays add)."""
    return P[0] + Q[0], P[1] + Q[1], P[2] + Q[2], P[3] + Q[3]


def _accel_terms(a: float, tau: float) -> tuple:
    """:func:`_accel_cov` as (xx, xv, vx, vv) floats (the same numbers)."""
    a2 = a * a
    return a2 * (tau ** 4 / 4.0), a2 * (tau ** 3 / 2.0), a2 * (tau ** 3 / 2.0), a2 * tau ** 2


def _accel_cov(a: float, tau: float) -> np.ndarray:
    """Covariance of (position, speed) errors from a constant unknown acceleration of size ``a``
    over ``tau`` seconds (module doc)."""
    a2 = a * a
    return a2 * np.array([[tau ** 4 / 4.0, tau ** 3 / 2.0], [tau ** 3 / 2.0, tau ** 2]])
