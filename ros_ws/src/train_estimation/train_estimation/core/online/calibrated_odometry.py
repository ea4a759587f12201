"""The odometer as both adapters read it (pure): its count mapped to the track by the
balise-calibrated :class:`~.odometer_scale.OdometerCalibration`, the calibrations that carry the
fault hypotheses beside it (a late balise reader, a start or count that is off), and the doubt
they add to an estimate (``Output.consider`` and ``Output.separation``).

:class:`DistanceAsPosition` is the base of ``estimators.RobustAdapter`` and
``estimators.BrakingAdapter``; :class:`OdometryConfig` holds (and checks) the parameters
their configs share.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np
from train_core.config import param, require

from .. import reasons as R
from .odometer_scale import (
    A_MAX,
    LATENCY_WIDE,
    BaliseFix,
    OdometerCalibration,
    latency_beyond_prior,
    log_density,
    wald,
)

COUNT_JUMP_RISK = 1e-7  # probability per reading that a count running its course is found off it
#   (``DistanceAsPosition._off_course``; without a sample counter a count off its course is held
#   as a possible restart: a false one costs a reading and, twice in a row, a splice)
SEQ_MADE = "seq_from_stamp"  # fields key: the seq is not a sensor's counter but one the runner
#   made of the stamp for a stream without one (runner.EstimatorRunner._call): no reboot shows in it
ON_TIME = "position_on_time"  # fields key (m): a balise reading's position read without the
#   calibrated reader latency (``DistanceAsPosition.monitor_balise``)
CLOCK_UNSURE = "clock_unsure"  # fields key (s): the reading's stamp is in doubt by this much, the
#   runner's clock decision after a gap nothing timed (a step back or a latency that rose as
#   much: ``IntegrityMonitor.untimed``), so a count spliced at it is in doubt by the motion in it
COUNT_A_BOUND = 2.5  # m/s^2, no train accelerates or brakes harder (emergency braking with
#   magnetic track brakes), gradients included: bounds the count between two odometer readings
COUNT_JUMP_K = NormalDist().inv_cdf(1.0 - COUNT_JUMP_RISK / 2.0)  # its two-sided bound, in sds


@dataclass(frozen=True)
class OdometryConfig:
    """The odometer, balise and command settings both estimator nodes share (the base of their
    configs; :class:`DistanceAsPosition` reads them): declared from this metadata, the nodes'
    YAML files document them."""

    gate: float = param(8.0, "-", "innovation gate in standard deviations (.inf disables)",
                        lo=0.0)
    gate_accel: float = param(1.5, "m/s^2", "acceleration error allowed in the gate's "
                              "look-ahead, over the time since the last odometer reading fused "
                              "(so a filter that refused readings for long takes them again)",
                              lo=0.0)
    use_distance: bool = param(True, "", "odometer distance as a position measurement")
    distance_variance: float = param(1.0, "m^2", "variance of (initial_position + counted "
                                     "distance) as a position reading", lo=0.0)
    odometer_scale: float = param(1.0, "-", "the odometer's reading / true distance at start, "
                                  "as diagnose reports it (cause odometer_scale) or an earlier "
                                  "run learnt it (/diagnostics: odometer_scale); 1 when unknown",
                                  lo=0.5, hi=2.0)
    odometer_scale_std: float = param(0.01, "-", "std of the odometer's scale (true / counted "
                                      "distance) before balises calibrate it", lo=0.0)
    balise_gate: float = param(4.0, "-", "a balise further than this many standard deviations "
                               "from the odometer's calibrated count is held until another "
                               "confirms it (outside_gate)", lo=0.0)
    balise_latency_std: float = param(0.1, "s", "std of the balise reader's latency (its "
                                      "stamp minus the time the train passed the balise) "
                                      "before balises read at different speeds calibrate it; "
                                      "a reader found far beyond it is calibrated with a wide "
                                      "prior (event balise_latency)", lo=0.0)
    max_command: float = param(5.0, "m/s^2", "|a_Tar| beyond is no train's command "
                               "(outside_gate)", lo=0.0)

    def __post_init__(self):
        require(self.gate > 0, "gate", self.gate, "must be > 0")
        require(self.distance_variance > 0, "distance_variance", self.distance_variance,
                "must be > 0")
        require(math.isfinite(self.odometer_scale_std) and self.odometer_scale_std > 0,
                "odometer_scale_std", self.odometer_scale_std, "must be finite and > 0")
        require(math.isfinite(self.odometer_scale) and 0.5 <= self.odometer_scale <= 2.0,
                "odometer_scale", self.odometer_scale, "must be in [0.5, 2] (a ratio of "
                "distances, 1 when unknown)")
        require(self.balise_gate > 0, "balise_gate", self.balise_gate, "must be > 0")
        require(math.isfinite(self.balise_latency_std) and self.balise_latency_std >= 0,
                "balise_latency_std", self.balise_latency_std, "must be finite and >= 0")
        require(self.max_command > 0, "max_command", self.max_command, "must be > 0")


class DistanceAsPosition:
    """The odometer as both adapters read it (``start_state``, ``cfg``): its count mapped to
    the track by the balise-calibrated :class:`OdometerCalibration`, and the calibration's own
    uncertainty beside the filter's (``Output.consider``).

    Without the distance (``use_distance: false``: a speed-only sensor, or a count that is not
    to be trusted) the balises enter the filter as position readings, and the filter carries
    the position from one to the next on the odometer's speed. The scale and a late balise
    reader are then as wrong as they are with the distance, only less visible: a speed 1-2 %
    off ran a KF 200 m from the train with a metre of variance (the balises it then met lay
    outside its gate), and a reader stamping 0.2-0.5 s late put every fix ``v tau`` behind it
    (thousands of wrong-side estimates per run, either way). So the calibration runs here too,
    on a count made of the speeds (``_count``: the trapezoid between fused readings), and
    serves the filter instead of replacing its position reading:

    - the speed is fused mapped by the calibrated scale, and the estimate's speed moves with
      the mapping when a balise changes it;
    - a balise is fused where the calibrated latency puts the train at its stamp, ``b + c v_b
      tau``, with ``(c v_b sd_tau)^2`` more variance;
    - what the filter does not carry (its speed taken as exact) is the error since the last
      balise it fused: ``dp = (run + v_b tau) dc + c v_b dtau`` (``run``: the count since that
      balise, ``v_b`` the counted speed at it), ``dv = v_odo dc``. It is published as the
      consider term, and added to the filter's position variance before the next balise is
      fused (so that the balise corrects it rather than a filter sure of a drifted position
      refusing it or taking half of it);
    - a balise can lie (a survey error), and the filter takes one that its own interval
      holds: the published position variance also covers the filter without each of the last
      three balises it fused (solution separation, as the calibration does with the
      distance): that balise's move squared plus the variance before it.
    """

    def _init_odometry(self) -> None:
        # cal, cal_wide; cal_alt: after the wide one took over, the calibration it replaced,
        # as the hypothesis "the reader is on time" (two balises at one speed cannot tell a
        # late reader from a start or a count that is off), until a sequential
        # likelihood-ratio test excludes one of the two (:meth:`_judge`); llr: log-likelihood
        # of the balises under cal minus under cal_alt
        self._new_calibrations()
        self.latency_found = 0  # the wide calibration took over (event balise_latency)
        self.count_out: float | None = None  # stamp of the balise at which the count was
        #   excluded (:meth:`_count_failed`): from then on the estimator reads no distance
        self.odo: tuple | None = None  # (stamp s, distance m, speed m/s) of the last fused
        #   odometer reading, as counted (without the distance: the count made of the speeds)
        self.anchor = (0.0, 0.0)  # without the distance: (count m, counted speed m/s) at the
        #   last balise the filter fused (the start: the count's zero, standing)
        self.separation: tuple = ()  # without the distance: (shift m, variance before m^2) of
        #   the last EXCLUDED balises the filter fused (solution separation, class doc)
        self.splice = 0.0  # m added to the odometer's distance: its count restarted (_restart)
        self.odo_seq: int | None = None  # the counter of the last fused odometer reading
        self.restarts = 0  # counts spliced (event count_reset)
        self.jump: tuple | None = None  # without a counter: (stamp s, count m, speed m/s) of a
        #   held reading whose count left its course (_restart)
        self.odo_dt: float | None = None  # s, the least interval between fused odometer
        #   readings: the sample period (a longer one missed samples: _after_silence)
        self.odo_heard: tuple | None = None  # (stamp s, count m, speed m/s) of the last
        #   odometer reading looked at, fused or not (without a counter: _restart)
        self.origin_far = 0  # 1: the first reading's count was far from the start (_origin)
        self.origin_seen = False  # the first odometer reading's count was looked at
        self.speeds: tuple | None = None  # with the distance: the odometer's speeds integrated
        #   from the count at the last balise the calibration took, over every reading heard
        #   (fused or not): (stamp s, count m, speed m/s, variance m^2, speed variance, the
        #   count read then m, the count read at the reading before less the track there m)
        self.odo_rv = math.nan  # speed variance of the last fused odometer reading
        self.unsure_taken = False  # without the distance: the doubt of the readings' stamps
        #   (CLOCK_UNSURE) is in the calibrations' origin (_unsure_count)
        self.unsure_var = 0.0  # m^2, that doubt, not yet given to the filter (the position it
        #   carries on the speeds is in doubt as much: _balise_for_filter)

    def _new_calibrations(self, place: tuple | None = None) -> None:
        """The calibration (:attr:`cal`) from its priors, the same with a wide latency prior
        beside it (:attr:`cal_wide`, on the same fixes: it replaces the narrow one when the
        reader is found out of its prior; odometer_scale module doc) and no alternative.
        ``place``: ``(count m, position m, variance m^2)``, the count placed there instead of
        the start (a count excluded: :meth:`_exclude_count`; no start hypothesis then)."""
        s, cfg = self.start_state, self.cfg

        def calibration(latency_std: float) -> OdometerCalibration:
            cal = OdometerCalibration(s.position, s.position_std, cfg.odometer_scale_std,
                                      cfg.balise_gate, scale=1.0 / cfg.odometer_scale,
                                      latency_std=latency_std,
                                      start_fault=s.position_fault if place is None else 0.0)
            if place is not None:
                cal.place(*place)
            return cal

        self.cal = calibration(cfg.balise_latency_std)
        self.cal_wide = calibration(LATENCY_WIDE) \
            if cfg.balise_latency_std < LATENCY_WIDE else None
        self.cal_alt: OdometerCalibration | None = None
        self.llr = 0.0

    @property
    def reads_distance(self) -> bool:
        """The odometer's count is a position reading: ``use_distance`` and not excluded."""
        return self.cfg.use_distance and self.count_out is None

    def _count(self, stamp: float, fields: dict) -> float:
        """m, the odometer's count at a reading: its distance, or without the distance the
        speeds integrated from the last fused reading (trapezoid; 0 at the first)."""
        if self.reads_distance:
            return float(fields["distance"]) + self.splice
        if self.odo is None:
            return 0.0
        t0, d0, v0 = self.odo
        return d0 + 0.5 * (v0 + float(fields["speed"])) * (stamp - t0)

    def _mapped(self, fields: dict, stamp: float = math.nan) -> tuple[float, float, float]:
        """``(position m, speed m/s, speed variance)`` of an odometer reading (stamped
        ``stamp``) on the track (the speed by the calibrated scale too); NaN where a field is
        missing or not a number."""
        try:
            v, rv = (float(fields[k]) for k in ("speed", "speed_variance"))
            d = self._count(stamp, fields)
        except (KeyError, TypeError, ValueError):
            return math.nan, math.nan, math.nan
        c = float(self.cal.theta[1])
        return self.cal.position(d), c * v, c * c * rv

    def monitor_fields(self, fields: dict) -> dict:
        """An odometer reading as the integrity monitor judges it: the speed (and its
        variance) by the calibrated scale, as the filter fuses it."""
        _, v, rv = self._mapped(fields)
        return {**fields, "speed": v, "speed_variance": rv}

    def monitor_balise(self, fields: dict) -> dict:
        """A balise reading as the integrity monitor judges it against the odometer: where the
        train was at its stamp by the reader's latency as calibrated so far (``v tau`` on from
        the balise, with ``(v sigma_tau)^2`` more variance; module doc of ``odometer_scale``),
        as the calibration fuses it, and where it read the train without that latency
        (``ON_TIME``: the calibration's latency is a hypothesis of its own, which a count
        that failed can make up, and the monitor keeps the reading's own word beside it)."""
        if self.odo is None:
            return fields
        tau, s_tau = self.cal.latency()
        if tau == 0.0 and s_tau == 0.0:
            return fields
        try:
            pos, var = float(fields["position"]), float(fields["position_variance"])
        except (KeyError, TypeError, ValueError):
            return fields
        v = float(self.cal.theta[1]) * self.odo[2]
        return {**fields, "position": pos + v * tau, "position_variance": var + (v * s_tau) ** 2,
                ON_TIME: pos}

    def _restart(self, stamp: float, fields: dict) -> tuple:
        """Splice a restarted count onto the old one (a sensor that rebooted: its counter and
        its distance begin again from 0 while the train runs on). A reading whose counter went
        back (its stamp on) says its count may have too, by any amount: its count is taken to
        be where the estimator's own prediction puts the train at its stamp (the commands
        through the gap included), and the prediction's variance is added to the count's
        origin from there on (:meth:`OdometerCalibration.splice`); a counter that wrapped with
        its count going on costs one period's prediction variance until the next balise.
        Taken as it came, the restarted count put the estimate 750 m back, refused by the
        gates (ALARM until two balises relocated the count: the zone controller brakes on
        ALARM), and 80 m back after a 10 s reboot early in a run, inside the KF's gate: 226
        estimates OK while beyond 5 sigma. (A test of the distance for a step back missed that
        one, the new count since the boot exceeding the old; a count carried at the last
        speed, 45 m short after 10 s of acceleration, was refused by the KF's gate.)

        Without a sample counter (its seq the last fused reading's, or one the runner made of the
        stamp: :data:`SEQ_MADE`; it says nothing of a reboot) the count
        itself is the only witness, and two hypotheses explain a count that left its course
        (:meth:`_off_course`): the reading is corrupt, or the count's origin moved (a reboot).
        They differ in what follows: the next reading returns to the old course, or follows
        the new one. So the first reading off the course is held (refused, remembered as
        :attr:`jump`) and the next decides: on the old course, the held one was corrupt; off it
        but on the held one's, the count restarted and is spliced here as above; off both, it
        is held instead. A splice puts the count where the prediction is, so a wrong one
        (two corrupt readings that agree) costs the prediction's variance, never a position
        outside it, and the old course's return is spliced back the same way. Without this,
        the robust filter (which has no gate) took a count restarted by a 10 s reboot at
        face value: 2-11 km off with protection levels of 76-2,242 m, 118 misleading
        estimates in the campaign without counters.

        Returns ``(undo, reason)``: what to restore should the reading not be fused (a
        corrupted copy must not move the count), or None; and a rejection reason when the
        reading is held, or ""."""
        if not self.reads_distance or self.odo is None or self.odo_seq is None:
            return None, ""
        try:
            seq, d = int(fields["seq"]), float(fields["distance"])
            v, rv = float(fields["speed"]), float(fields["speed_variance"])
        except (KeyError, TypeError, ValueError):
            return None, ""
        if not (math.isfinite(d) and math.isfinite(v) and math.isfinite(rv) and rv > 0.0
                and stamp > self.odo[0]):
            return None, ""
        # the sensor's last word before this one, fused or not: a sensor that sent readings
        # did not reboot meanwhile (refused ones included: a stuck count refused reading after
        # reading is no silence)
        heard = self.odo if self.odo_heard is None or self.odo_heard[0] < self.odo[0] \
            else self.odo_heard
        if seq != self.odo_seq and not fields.get(SEQ_MADE):
            # the sensor's counter speaks: it went back (a reboot) or it went on
            self.jump = None
            if not (0 <= seq < self.odo_seq and d >= 0.0):
                return None, ""
            # went back: a reboot, whose count began again after the sensor's last reading
            # (fused or not), so it is at most the travel since that reading; a count beyond it
            # is no reboot's (a counter that wrapped with its count going on, or one corrupted
            # message: the fuzz sent the counter's jump to 2^32 - 1 and, next, a copy with a
            # count 1e6 m on and a counter below it, whose splice put every later genuine
            # reading 1e6 m off the count, refused for 100 s). Where its stamp is in doubt by
            # T s (CLOCK_UNSURE: a step back of the clock by T read as a latency that rose as
            # much), the silence may have lasted T s longer, and so may the count's run: on
            # the stamps alone a 10 s reboot whose clock resumed where it stopped had run 194
            # m in 1 s, taken for no reboot, and every estimate then followed the count's new
            # origin, 1.5-1.9 km behind the train (crh3_high_speed at 100 s; the robust filter
            # outside its levels)
            unsure = fields.get(CLOCK_UNSURE)
            trap, slack, bound = self._course(heard, stamp + (float(unsure) if unsure else 0.0),
                                              v, rv)
            return (self._splice(stamp, d, fields) if d <= trap + slack + bound else None), ""
        here = (stamp, d + self.splice, v)
        if self.odo_heard is None or stamp > self.odo_heard[0]:
            self.odo_heard = here
        off = self._off_course(self.odo, here, rv)
        if off is None:
            self.jump = None
            return self._after_silence(heard, stamp, d, v, rv, fields), ""
        held = self.jump
        why = (f"{R.OUTSIDE_GATE}: the odometer's count left its course by {off:+.1f} m without "
               f"a sample counter (held: a restart if the next reading follows it)")
        if held is None or not held[0] < stamp or self._off_course(held, here, rv) is not None:
            self.jump = here
            return None, why
        trap, slack, bound = self._course(held, stamp, v, rv)
        moving = abs(held[2] + v) > 2.0 * COUNT_JUMP_K * math.sqrt(max(rv, 0.0))
        if moving and abs(trap) <= slack + bound:
            # the two agree, but over less travel than tells a count that runs from one that
            # stopped (a frozen register under speeds that read on agrees with itself within
            # the counts' noise): the first held reading waits for one further on. Spliced at
            # each such pair, a count frozen at 21 m/s on metro_demo was taken as restarted 163
            # times, the robust filter 663 m off with 872 misleading estimates. (Where the
            # speeds read standstill both place the train alike: spliced, as before.)
            return None, why
        # two readings that agree with each other over a travel a stopped count would not
        # show, and not with the old course: the count's origin moved
        self.jump = None
        return self._splice(stamp, d, fields), ""

    def _after_silence(self, heard: tuple, stamp: float, d: float, v: float, rv: float,
                       fields: dict):
        """Without a counter, the first reading after a silence (at least one sample missed
        since ``heard``, the sensor's last reading, fused or not), on the old count's course
        and yet small enough to be a count restarted in the silence (at most the travel in it,
        ``COUNT_A_BOUND dt^2 / 4`` and the noise included): the data allow both hypotheses.
        Where the two would place the train further apart than the count's noise (a restart
        puts it at least the old count further on), the count is spliced where the
        prediction puts the train, as a restart is (:meth:`_splice`): right under both, since
        the prediction does not use the count, at the cost of the count's word on the distance
        run in the silence (a balise gives it back). Taken as a continuing count, a reboot
        within a 60 s silence early in a run (metro_demo at 47 s: 646 m counted since the boot,
        the old course 1,624 m on, both within the 2,250 m an acceleration of 2.5 m/s^2 allows
        in 60 s) put the robust filter 1.09 km off with levels of 45-374 m. Measured from the
        last reading fused instead of the last heard, a stuck count refused reading after
        reading had every link loss taken for such a silence and spliced (291 misleading).
        Returns what to restore should the reading not be fused, or None when the case does
        not arise."""
        d0 = heard[1]  # the sensor's last reading before this one, fused or not
        if self.odo_dt is None or stamp - heard[0] < 1.5 * self.odo_dt or d < 0.0:
            return None  # no silence: no sample missed since the sensor was last heard
        trap, slack, bound = self._course(heard, stamp, v, rv)
        if d > trap + slack + bound:
            return None  # more than the train can have run since: no restart in the silence
        # where a restart would put the train against where this count does: at least the old
        # count further (the boot came after the last reading), at most the travel since as
        # well; within the noise (a standing start, the count near 0) the two agree
        if d0 + max(0.0, trap + slack - d) <= bound:
            return None
        return self._splice(stamp, d, fields)

    def _off_course(self, ref: tuple, here: tuple, rv: float) -> float | None:
        """How far (m of count) the reading ``here`` = ``(stamp, count, speed)`` lies from the
        course of the count from ``ref`` (same form): the count at ``ref`` plus the trapezoid
        of the two speeds; None when within it. The trapezoid is off by at most
        ``COUNT_A_BOUND dt^2 / 4`` whatever the train did between the readings (the extreme: a
        speed that rises at the bound for half the interval and falls for the other half);
        beyond that, both counts' noise (``distance_variance``) and the speeds' over the
        interval, at :data:`COUNT_JUMP_RISK`. The count and the speed come from one axle, so a
        slip, a slide or a worn wheel moves both alike and stays on the course."""
        t, d, v = here
        trap, slack, bound = self._course(ref, t, v, rv)
        resid = (d - ref[1]) - trap
        return resid if abs(resid) > slack + bound else None

    def _course(self, ref: tuple, t: float, v: float, rv: float) -> tuple:
        """The count's course from ``ref`` = ``(stamp, count, speed)`` to a reading at ``t``
        read at speed ``v`` (variance ``rv``): ``(travel, slack, bound)`` in m, the trapezoid
        of the two speeds, what any acceleration up to ``COUNT_A_BOUND`` may add to it
        (``COUNT_A_BOUND dt^2 / 4``), and the counts' and speeds' noise at
        :data:`COUNT_JUMP_RISK` (:meth:`_off_course`, :meth:`_after_silence`)."""
        dt = t - ref[0]
        noise = 2.0 * self.cfg.distance_variance + max(rv, 0.0) * dt * dt
        return (0.5 * (ref[2] + v) * dt, 0.25 * COUNT_A_BOUND * dt * dt,
                COUNT_JUMP_K * math.sqrt(noise))

    def _splice(self, stamp: float, d: float, fields: dict):
        """The count ``d`` at ``stamp`` spliced where the prediction puts the train
        (:meth:`_restart`); what to restore, or None when the prediction is not usable.

        Where the reading's stamp is itself in doubt (:data:`CLOCK_UNSURE`: after a gap that
        neither a counter nor the count timed, a step back of the train clock by ``T`` s and a
        link latency that rose as much read alike), the prediction at it is in doubt by the
        train's motion over ``T``, and so is the origin spliced there: ``(v T)^2`` more
        variance. Spliced at the prediction's own variance, a reboot whose clock stepped
        back 3 s at 82 m/s (crh3_high_speed, no counter) left the next balise 249 m off a
        count stated to a few metres, which the calibration could explain only as a reader
        4.5 s late with a scale of 1.093; the balises after it then agreed with that track
        while the train was 355-430 m behind it (12 estimates outside their levels)."""
        pred = self.output(stamp)  # on copies: the state is untouched
        x, var = float(pred.position), float(pred.covariance[0])
        unsure = fields.get(CLOCK_UNSURE)
        if unsure:
            var += (float(pred.velocity) * float(unsure)) ** 2
        x0, c = (float(v) for v in self.cal.theta[:2])
        if not (math.isfinite(x) and math.isfinite(var) and var > 0.0):
            return None
        undo = (self.splice, self.restarts,
                *(cal.copy() if cal is not None else None
                  for cal in (self.cal, self.cal_wide, self.cal_alt)))
        at = (x - x0) / c  # the old count where the train is predicted
        self.splice = at - d
        for cal in self._cals():
            cal.splice(at, var)
        self.restarts += 1
        return undo

    def _origin(self, fields: dict) -> None:
        """The first odometer reading's count against ``initial_position`` (where the count is
        zero). A count ``c`` other than zero there means one of two things, and nothing before
        a balise tells which: the train ran ``c`` from the start before the data began
        (``initial_position + c``), or the count began before the data did (a count not reset
        at the start, a bag recorded from mid-run, a sensor that counts from its power-up: the
        train at ``initial_position``). Both hypotheses are carried, whatever the size of
        ``c``: the calibration's origin is put where the estimate starts and its variance grown
        by ``c^2``, so that the interval holds both, and the first balise places the count. A
        rule that took the count as distance run below 8 start deviations (40 m) and as unknown
        above left counts of 26-39 m not reset at the start 26-53 m off with an OK label
        through the run (the balises that contradicted it were refused by the gate); taken as
        the parameter says, a count of 5 km had every reading refused for the whole run. The
        event ``count_origin`` is said where the count lies beyond the start's own standard
        deviation (below it, the widening is within what the start already allowed)."""
        if not self.reads_distance or self.odo is not None or self.origin_seen:
            return
        try:
            d = float(fields["distance"])
        except (KeyError, TypeError, ValueError):
            return
        if not math.isfinite(d):
            return
        self.origin_seen = True
        far = float(self.cal.theta[1]) * d
        if far == 0.0:
            return
        for cal in self._cals():
            cal.widen_origin(-far, far * far)
        self.origin_far = int(abs(far) > self.start_state.position_std)

    def _unrestart(self, undo) -> None:
        """The reading that spliced the count was not fused: as before it (:meth:`_restart`)."""
        if undo is not None:
            self.splice, self.restarts, self.cal, self.cal_wide, self.cal_alt = undo

    def _unsure_count(self, stamp: float, fields: dict) -> None:
        """Without the distance, the count is the speeds integrated over the stamps
        (:meth:`_count`), and across a silence after which the stamps are in doubt by ``T``
        s (:data:`CLOCK_UNSURE`: a step back of the train clock and a link latency that rose
        as much read alike) that integral is in doubt by the train's motion over ``T``: the
        calibrations' origin takes ``(c v T)^2`` more variance from this count on, once per
        such doubt (its first fused reading spans the silence; the readings after it are
        timed against one another). Without it, a reboot whose clock stepped back 3 s at 82
        m/s (crh3_high_speed, kf without the distance) had the count 246 m short at the next
        balise, stated to a few metres: the wide calibration explained it as a reader 4.9 s
        late with a scale of 1.10, and the speeds it then mapped carried the kf 8.5 m/s fast,
        its estimates up to 390 m off. The filter, which carried its position on the same
        speeds and stamps, is in doubt as much: its next balise inflates it by that variance
        (:meth:`_balise_for_filter`; its gate refused the balise 248 m off otherwise)."""
        unsure = fields.get(CLOCK_UNSURE)
        if not unsure:
            self.unsure_taken = False
            return
        if self.unsure_taken or self.reads_distance or self.odo is None \
                or not stamp > self.odo[0]:
            return
        try:
            v = 0.5 * (self.odo[2] + float(fields["speed"]))
        except (KeyError, TypeError, ValueError):
            return
        var = (float(self.cal.theta[1]) * v * float(unsure)) ** 2
        if math.isfinite(var):
            d = self._count(stamp, fields)
            for cal in self._cals():
                cal.splice(d, var)
            self.unsure_taken = True
            self.unsure_var += var

    def _odometer_fused(self, stamp: float, fields: dict) -> None:
        self._unsure_count(stamp, fields)
        if self.odo is not None and stamp > self.odo[0]:
            gap = stamp - self.odo[0]
            self.odo_dt = gap if self.odo_dt is None else min(self.odo_dt, gap)
        self.odo = (stamp, self._count(stamp, fields), float(fields["speed"]))
        try:
            self.odo_seq = int(fields["seq"])
        except (KeyError, TypeError, ValueError):
            self.odo_seq = None
        try:
            self.odo_rv = float(fields["speed_variance"])
        except (KeyError, TypeError, ValueError):
            self.odo_rv = math.nan
        for cal in self._cals():
            cal.walk_to(self.odo[1])
        if self.speeds is None and self.reads_distance:
            self._speeds_from_count()  # the count's first word (until a balise)

    def _exclude_count(self, stamp: float, t_now: float, x_now: float,
                       v_now: float) -> tuple[float, float, np.ndarray]:
        """The count excluded at the balise stamped ``stamp`` (:meth:`_count_failed`): from
        here on the estimator reads no distance, its count made of the speeds
        (:meth:`_count`) from the speeds' track's latest reading, where the filter is placed
        with the track's variance (so that reading is its anchor). Returns how the adapter
        moves its filter, whose estimate at ``t_now`` is ``x_now`` m and ``v_now`` m/s, onto
        where the track puts the train then before it fuses the balise: ``(dx m, dv m/s,
        the (position, speed) covariance to add)``."""
        t0, d, v, var, rv = self.speeds[:5]
        c = float(self.cal.theta[1])
        x, var_x = self.cal.position(d), c * c * var + self.cal.position_variance(d)
        self.count_out = stamp
        self.speeds = None
        self.odo = (t0, d, v)
        self.anchor = (d, v)  # (the track's doubt up to here is in the filter: var_x, below)
        self.separation = ()
        self.jump = None
        # what the calibration learnt since the count failed (between the last balise that
        # agreed with it and this one: a scale, a reader latency, a start made up to fit the
        # failed count) is not to be trusted: it starts again from its priors, the count made
        # of the speeds placed where the speeds' track puts the train. (Kept, a count at half
        # the distance without a sample counter, spliced 45 times, left a scale 3 % off: the
        # speeds carried the kf 0.56 m/s off after the exclusion, 634 estimates beyond levels
        # of 20-30 m on metro_demo.)
        self._new_calibrations((d, x, var_x))
        c = float(self.cal.theta[1])
        dt = t_now - t0
        var_t = var_x + c * c * (rv * dt * dt + (0.5 * A_MAX * dt * dt) ** 2)
        return (self.cal.position(d + v * dt) - float(x_now), c * v - float(v_now),
                np.diag([var_t, c * c * rv]))

    def _speeds_from_count(self) -> None:
        """Start the speeds' track (:attr:`speeds`) at the last fused odometer reading: the
        count it continues, agreed by the balise the calibration just took (or the first)."""
        t, d, v = self.odo
        rv = self.odo_rv if math.isfinite(self.odo_rv) else 0.0
        self.speeds = (t, d, v, 0.0, rv, d, 0.0)

    def _heard(self, stamp: float, fields: dict) -> None:
        """An odometer reading heard (fused or not, before any check of its count) runs the
        speeds' track on: the trapezoid of the two speeds, their noise over the interval and
        what an acceleration up to :data:`COUNT_A_BOUND` may add to it (``COUNT_A_BOUND dt^2
        / 4``, taken as a standard deviation). A speed no train reaches from the track's last
        (beyond :data:`COUNT_JUMP_K` of the two readings' noise) is not taken (a corrupted
        reading). The count itself is kept beside it as it was read, and its distance from
        the track at the reading before (:meth:`_count_failed`)."""
        sp = self.speeds
        if sp is None or not self.reads_distance:
            return
        try:
            v, rv = float(fields["speed"]), float(fields["speed_variance"])
            d = float(fields["distance"]) + self.splice
        except (KeyError, TypeError, ValueError):
            return
        if not (math.isfinite(stamp) and math.isfinite(v) and math.isfinite(rv) and rv >= 0.0
                and math.isfinite(d) and stamp > sp[0]):
            return
        dt = stamp - sp[0]
        if abs(v - sp[2]) > COUNT_A_BOUND * dt + COUNT_JUMP_K * math.sqrt(rv + sp[4]):
            return
        trap, slack, _ = self._course(sp, stamp, v, rv)  # (the count's course from sp)
        var = sp[3] + 0.25 * (sp[4] + rv) * dt * dt + slack ** 2
        self.speeds = (stamp, sp[1] + trap, v, var, rv, d, sp[5] - sp[1])

    def _count_failed(self, stamp: float, fix: BaliseFix, variance: float) -> bool:
        """Whether a balise stamped ``stamp`` (``fix``, against the count as last fused;
        ``variance`` m^2, the reading's own) that the count's calibration refuses on the
        count as read (outside ``balise_gate``) excludes the odometer's count: fault
        detection and exclusion, as ARAIM does for a satellite. The count and the speeds
        come from one sensor but fail apart (a register
        that froze or lost one of its two pulse channels while the speeds read on). Two
        single faults explain a balise that the count contradicts: the balise lies elsewhere
        than the map says (the count and the speeds then agree with each other), or the count
        failed (the balise then agrees with the speeds integrated from the last balise the
        calibration took, :attr:`speeds`). Each leaves one quantity free (the balise's
        position, the count), taken alike; the log-likelihood ratio is the speeds' track's
        predictive density of the balise over the density of the count's distance from that
        track, and Wald's test at :data:`~.odometer_scale.EXCLUSION_RISK` decides
        (:func:`~.odometer_scale.wald`: the wrong exclusion's probability is at most that
        risk, charged to the integrity risk as the start's and the reader's are). The balise
        must also pass the calibration's own gate (``balise_gate``) on the speeds' track, so
        that a balise wrong beside a failed count (two faults) is not taken for the truth.
        Across a silence the track's variance grows past any decision."""
        sp = self.speeds
        if sp is None or not self.reads_distance:
            return False
        dt = stamp - sp[0]
        if not abs(dt) <= 2.0:
            return False  # no reading near the balise (an outage): the track says little
        # the count as read (not as last fused: a filter that refused a failed count's
        # readings carries its last fused one at its speed, as the speeds do), off the
        # speeds' track by the smaller of its last two readings' distances from it (one
        # corrupted message is no count that failed: both must lie off it, on one side)
        off_now, off_before = sp[5] - sp[1], sp[6]
        off = min(off_now, off_before, key=abs) if off_now * off_before > 0.0 else 0.0
        as_read = BaliseFix(fix.position, fix.variance, sp[1] + off + sp[2] * dt, fix.speed)
        cal = self.cal.copy()  # (walked as the calibration's own test does first; a copy:
        #   nothing of the calibration moves unless the count is excluded)
        cal.walk_to(max(as_read.distance, fix.distance))
        nu, s_nu = cal._innovation(as_read)
        if not abs(nu) > self.cfg.balise_gate * math.sqrt(s_nu):
            return False  # the count's calibration takes it (or cannot judge it: NaN)
        c = float(cal.theta[1])
        # the speeds' count carried to the stamp at its last speed, as the count is
        # (_balise_fix), with an acceleration error of up to A_MAX
        var = sp[3] + sp[4] * dt * dt + (0.5 * A_MAX * dt * dt) ** 2
        by_speeds = BaliseFix(fix.position, variance + c * c * var, sp[1] + sp[2] * dt, sp[2])
        nu, s_nu = cal._innovation(by_speeds)
        if not (math.isfinite(nu) and s_nu > 0.0) or \
                abs(nu) > self.cfg.balise_gate * math.sqrt(s_nu):
            return False
        # the count read against the speeds' count (both channels' noise, the count's at
        # both ends)
        apart = c * off
        s_apart = c * c * sp[3] + 2.0 * float(self.cfg.distance_variance)
        if not s_apart > 0.0:
            return False
        return wald(log_density(nu, s_nu) - log_density(apart, s_apart)) > 0

    def _cals(self) -> list:
        """The calibrations alive: the model, the wide-latency check, the alternative."""
        return [c for c in (self.cal, self.cal_wide, self.cal_alt) if c is not None]

    def _count_at(self, t: float) -> float:
        """m, the odometer's count at ``t``, carried from the last fused reading at its
        speed."""
        t0, d0, v0 = self.odo
        return d0 + v0 * (t - t0)

    def position_reading(self, fields: dict):
        """The odometer reading as this estimator's position measurement for the integrity
        monitor: ``(position m, distance_variance m^2, the calibration's variance of it m^2)``,
        or None when distance is not used."""
        if not self.reads_distance:
            return None
        try:
            d = float(fields["distance"]) + self.splice
        except (KeyError, TypeError, ValueError):
            return None
        return (self.cal.position(d), float(self.cfg.distance_variance),
                self.cal.position_variance(d))

    def _balise_fix(self, stamp: float, position: float, variance: float) -> BaliseFix | None:
        """The balise against the odometer's count at its stamp (carried from the last reading
        at its speed, with an acceleration error of up to ``A_MAX``), or None before the
        first reading."""
        if self.odo is None:
            return None
        dt = abs(stamp - self.odo[0])
        c = float(self.cal.theta[1])
        rd = self.train.odometer_speed_variance * dt * dt + (0.5 * A_MAX * dt * dt) ** 2
        return BaliseFix(position, variance + self.cfg.distance_variance + c * c * rd,
                         self._count_at(stamp), self.odo[2])

    def _calibrate(self, fix: BaliseFix, t_now: float) -> tuple[bool, float, float]:
        """``(fused, dx m, dv m/s)``: the balise given to the calibration, and how far the
        estimate at ``t_now`` moves with the mapping."""
        old = self.cal.theta.copy()
        judged = self._likelihoods(fix)
        ok = self.cal.balise(fix)
        if self.cal_alt is not None:
            self.cal_alt.balise(fix)
            ok = self._judge(judged) or ok
        if self.cal_wide is not None:
            self.cal_wide.balise(fix)
            if latency_beyond_prior(self.cal_wide, self.cfg.balise_latency_std):
                # the reader is out of its prior: the wide calibration (which took this balise
                # or held it) is the model from now on, the one it replaces its alternative
                self.cal, self.cal_alt, self.cal_wide = self.cal_wide, self.cal, None
                self.llr = 0.0
                self.latency_found += 1
                ok = True
        if not ok:
            return False, 0.0, 0.0
        if self.reads_distance and (self.speeds is None or self.odo[0] >= self.speeds[0]):
            # the balise agrees with the count as read: the speeds' track starts again from
            # it. Not where the count's last fused reading is older than the track's latest
            # (readings refused since: the balise then agreed with the count carried at an old
            # speed, not with the count read, and the track keeps its older start)
            self._speeds_from_count()
        d = self._count_at(t_now)
        dx = self.cal.position(d) - float(old[0] + old[1] * d)
        return True, dx, float(self.cal.theta[1] - old[1]) * self.odo[2]

    def _likelihoods(self, fix: BaliseFix) -> tuple | None:
        """The log predictive densities of ``fix`` under the calibration and its alternative
        (before either takes it), or None without an alternative."""
        if self.cal_alt is None:
            return None
        out = []
        for cal in (self.cal, self.cal_alt):
            cal.walk_to(fix.distance)
            out.append(log_density(*cal._innovation(fix)))
        return tuple(out)

    def _judge(self, judged: tuple | None) -> bool:
        """Wald's sequential test (``odometer_scale.wald``) between the calibration and its
        alternative on the balises both predicted: the one the summed log-likelihood ratio
        speaks against is excluded. Returns True when the alternative becomes the model (the
        estimate moves with its mapping)."""
        if judged is None:
            return False
        self.llr += judged[0] - judged[1]
        decided = wald(self.llr)
        if decided > 0:
            self.cal_alt = None
        elif decided < 0:
            self.cal, self.cal_alt = self.cal_alt, None
            return True
        return False

    def _uncounted(self, t: float) -> np.ndarray:
        """Without the distance: the row ``dp / d theta`` of the position the filter carries
        at ``t`` from the last balise it fused (class doc)."""
        c, tau = float(self.cal.theta[1]), float(self.cal.theta[2])
        d_b, v_b = self.anchor
        return np.array([0.0, self._count_at(max(t, self.odo[0])) - d_b + v_b * tau, c * v_b])

    def _calibration(self, t: float) -> dict:
        """The calibration's doubt at ``t`` as an Output's ``consider`` (its (position, speed)
        covariance, row-major 2x2: module doc of ``odometer_scale``; without the distance, the
        class doc's) and ``separation`` (the same as solutions: ``(variance, ((shift,
        variance, kind), ...))``, :meth:`OdometerCalibration.doubt`, with ``kind`` "map" for
        a solution that leaves out one balise (a map fault's), "start" for the start's (the
        start wrong) and "reader" for the other calibration (a late balise reader): the rare
        faults whose priors may be stated, protection.py); both empty before the first
        odometer reading."""
        if self.odo is None:
            return {"consider": (), "separation": ()}
        d = self._count_at(max(t, self.odo[0]))
        alt = self._alternative(d)
        if self.reads_distance:
            C, (var, alts) = self.cal.doubt(d, self.odo[2])
            for m, v in alt:
                C[0, 0] = max(C[0, 0], m * m + v)
            # the doubt lists the solutions without each recent balise first, then the start's
            n = len(self.cal.alternatives)
            return {"consider": tuple(C.ravel()),
                    "separation": (var, _tagged(map=alts[:n], start=alts[n:], reader=alt))}
        J = np.array([self._uncounted(t), [0.0, self.odo[2], 0.0]])
        C = J @ self.cal.Sigma @ J.T
        var = float(C[0, 0])
        start = self.cal.start_doubt(d)  # the start wrong (odometer_scale module doc)
        # solution separation: the filter without each of its last balises lies that balise's
        # move away, as sure as it was before it (one may lie: a survey error)
        C[0, 0] += max((m * m + v for m, v in self.separation + alt + start), default=0.0)
        return {"consider": tuple(C.ravel()),
                "separation": (var, _tagged(map=self.separation, start=start, reader=alt))}

    def _alternative(self, d: float) -> tuple:
        """``((shift m, variance m^2),)`` of the alternative calibration at the count ``d``
        relative to the model (:attr:`cal_alt`), or ``()``."""
        if self.cal_alt is None:
            return ()
        return ((self.cal_alt.position(d) - self.cal.position(d),
                 self.cal_alt.position_variance(d)),)

    def _balise_for_filter(self, fix: BaliseFix, stamp: float,
                           t_now: float) -> tuple[float, float, float, float]:
        """Without the distance: the calibration takes the balise (it learns the scale and the
        latency); returns ``(position m, variance m^2, dv m/s, q m^2)`` for the filter: the
        balise where the calibrated latency puts the train at its stamp, the speed's move with
        the mapping (0 when the calibration refused the balise) and the position variance the
        filter lacks since the last balise it fused (class doc)."""
        h = self._uncounted(stamp)
        q = float(h @ self.cal.Sigma @ h) + self.unsure_var  # (the stamps' doubt once)
        self.unsure_var = 0.0
        ok, _, dv = self._calibrate(fix, t_now)
        tau, s_tau = self.cal.latency()
        v = float(self.cal.theta[1]) * fix.speed
        return fix.position + v * tau, fix.variance + (v * s_tau) ** 2, dv if ok else 0.0, q

    @staticmethod
    def _carried(x, P, dt: float) -> tuple[float, float]:
        """``(position m, its variance m^2)`` of the estimate ``x`` = (position, speed, ...)
        with covariance ``P`` carried ``dt`` s at its speed."""
        P = np.asarray(P, dtype=float)
        return (float(x[0] + x[1] * dt),
                float(P[0, 0] + 2.0 * P[0, 1] * dt + P[1, 1] * dt * dt))

    def _balise_fused(self, fix: BaliseFix, position: float,
                      before: tuple[float, float]) -> None:
        """Without the distance: the filter fused ``fix`` and its position is now ``position``;
        ``before``: its position and variance at the balise's stamp before (:meth:`_carried`)."""
        self.anchor = (fix.distance, fix.speed)
        move, var_before = position - before[0], before[1]
        if math.isfinite(move) and math.isfinite(var_before):
            # the solution without this balise lies where the filter stood before it: ``-move``
            # from the estimate (a shift is where the truth lies from it under the fault,
            # protection.py; stored as ``move``, a balise stamped 30 m of travel late pulled
            # the KF 23 m back while the level ahead of it said 18 m: 16 estimates beyond it)
            self.separation = (self.separation + ((-move, var_before),))[
                -OdometerCalibration.EXCLUDED:]

    def odometer_scale(self) -> tuple[float, float] | None:
        """The odometer's scale as learnt so far, ``(reading / true distance, its std)``, in the
        terms of the ``odometer_scale`` parameter (a next run can start from it), or None
        without a calibration."""
        c, var = float(self.cal.theta[1]), float(self.cal.Sigma[1, 1])
        if not (math.isfinite(c) and c > 0 and math.isfinite(var) and var >= 0):
            return None
        return 1.0 / c, math.sqrt(var) / (c * c)  # d(1/c) = -dc / c^2

    def balise_latency(self) -> tuple[float, float] | None:
        """The balise reader's latency as learnt so far, ``(s, its std s)`` (the
        ``balise_latency_std`` parameter's terms), or None without a calibration or a latency
        prior."""
        if self.cfg.balise_latency_std == 0.0 and not self.latency_found:
            return None
        return self.cal.latency()

    def odometry_events(self) -> dict:
        """Event name -> how many so far, of the odometer's calibration (in :attr:`counters`;
        the runner logs each new one)."""
        counts = (self.cal.relocated, self.cal.excluded, self.latency_found, self.restarts,
                  self.origin_far, self.cal.start_excluded, int(self.count_out is not None))
        if not any(counts):  # (the usual answer, asked after every reading)
            return {}
        return {k: n for k, n in zip(_EVENTS, counts) if n}

    def _odometry_snapshot(self):
        return tuple(c.copy() if c is not None else None
                     for c in (self.cal, self.cal_wide, self.cal_alt)) \
            + (self.llr, self.odo, self.latency_found, self.anchor, self.separation,
               self.splice, self.odo_seq, self.restarts, self.origin_far, self.origin_seen,
               self.jump, self.odo_dt, self.odo_heard, self.count_out, self.speeds, self.odo_rv,
               self.unsure_taken, self.unsure_var)

    def _odometry_restore(self, snap) -> None:
        cal, wide, alt, self.llr, self.odo, self.latency_found, self.anchor, self.separation, \
            self.splice, self.odo_seq, self.restarts, self.origin_far, self.origin_seen, \
            self.jump, self.odo_dt, self.odo_heard, self.count_out, self.speeds, \
            self.odo_rv, self.unsure_taken, self.unsure_var = snap
        self.cal = cal.copy()
        self.cal_wide = wide.copy() if wide is not None else None
        self.cal_alt = alt.copy() if alt is not None else None


_EVENTS = (R.RELOCATED, R.BALISE_EXCLUDED, R.BALISE_LATENCY, R.COUNT_RESET, R.COUNT_ORIGIN,
           R.START_EXCLUDED, R.COUNT_EXCLUDED)  # odometry_events' names, in its order


def _tagged(**groups) -> tuple:
    """``((shift, variance, kind), ...)`` of the solutions ``((shift, variance), ...)`` of each
    kind (:meth:`DistanceAsPosition._calibration`)."""
    return tuple([(float(m), float(v), kind) for kind, sols in groups.items() for m, v in sols])
