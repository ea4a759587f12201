"""Time-ordered stepping of an estimator from messages that arrive out of step (pure).

The ROS nodes and the offline replay both drive an estimator through :class:`EstimatorRunner`,
so the node's estimates can be reproduced from a bag without ROS:

- ``push(kind, stamp, fields, recv)`` checks one reading or command at the door (finite stamp,
  plausible clock, duplicate, sequence reset) and queues it (the node's callbacks only do this);
- ``advance_to(t)`` processes every queued item with stamp <= t in stamp order (commands before
  readings at equal stamps) and emits one estimate per odometer sample, **at the sample's own
  stamp**, as soon as it is processed; an odometer slot without a sample (lost packet, outage)
  gets a predicted estimate at the expected slot time once the inputs' watermarks pass it;
- ``tick(now)`` (the nodes' timer, and the replays at the same arrival times) publishes, by the
  arrival clock, every slot whose reading is ``slot_grace`` overdue on the train clock's
  offset: a lost reading's slot leaves when it is due, not when the next message arrives.

Clocks (docs/interfaces.md, "The measured data's clocks"). The estimator runs on the **odometer's
clock** (the train's clock: odometer and balise stamps are the sampling times, at any epoch,
phase and drift). ``control`` may be stamped on another clock (measured data: the reference =
receive clock). Each clock is followed by a :class:`~.clocks.StreamClock` (the streaming
counterpart of the offline ``ClockFit``): its offset ``stamp - recv`` (``recv`` = arrival time on
the node's clock; in a replay the bag's log time) is a robust running centre of the items that
came on time (lateness: the one rule of ``core/numerics/clocks.py``, ``LATE`` = 0.5 s below the
centre,
e.g. the burst that follows a stalled recorder or node, does not vote); a control stamp is mapped
onto the train clock by adding ``median(odometer offset) - median(control offset)`` (the error is
the difference of the two streams' median latencies, milliseconds for a radio link). When the
clocks' offsets can agree within ``same_clock_tolerance`` (each lies between its centre, which
a queue pulls down, and its quickest offsets: :meth:`EstimatorRunner._clock_gap`) and the train
clock's rate against the arrivals differs from the control clock's by no more than
``same_clock_rate`` (or not significantly, by each rate's error as a latency that wanders
allows: :meth:`~.clocks.StreamClock.rate_apart`) the two clocks are taken as one (the
simulator: mapping 0, exactly, so that a node and its replay compute the same numbers); once
found "separate" stays so, but never from offsets that all came at one instant while the
commands could be on the train clock (commands wait until the train clock is judged).
``control_clock`` forces ``"same"`` (the simulator's launch) or ``"reference"``; ``"auto"`` is
the default, in the nodes and offline. On separate clocks the train clock's rate (least squares
of odometer stamps on the arrival times of the readings on time, ``drift``) is used and the
filter runs in reference seconds: stamps are converted piecewise from the last processed sample,
the estimates keep the sample's own stamp. One clock
needs no rate (a drift shared by all stamps only rescales time; not corrected).

A stamp more than ``max_future`` seconds (default 10 min: generous, because a node whose
callbacks lag its input sees late arrivals) after what its stream's median offset predicts from
its arrival is refused (``future_stamp``): one reading stamped 1e6 s ahead is counted and dropped,
never queued, so it can neither blind the filter nor make ``advance_to`` run for ever. Without
receive times (``recv=None``) the arrival is taken as the latest stamp admitted on any topic
(first, the previous stamp pushed), which is the same test on one clock; without receive times
the topics are taken to share one clock.

Out-of-sequence readings (a radio link with jitter delivers a reading after later ones): a
reading up to ``history`` seconds older than the newest fused one is fused by **rewinding**, as
robot_localization's history does: the adapter's state before the first fused odometer sample
after the late reading is restored (``snapshot``/``restore``) and everything since is
re-filtered with the late reading in its place (event ``fused_late``). Estimates already
published stay published; the next ones carry the correction. Older readings are refused
(``out_of_order``). A replay in arrival order meets the same lateness, so it reproduces the
node's estimates. The state kept for a reading need not be copied between its arrival and its
estimate: ``settle()``, called once the estimates are out (the node after publishing), copies
the adapter's state then, and a reading processed after nothing but commands keeps that copy
with the commands' calls, which a rewind makes again (:class:`_Replayed`: the same calls on
the same state, so the same state as a copy taken just before the reading).

Clock steps (a train clock reset to 0 by a reboot, or set to GPS time) are watched by a
:class:`~.clocks.StepWatch` (``core/numerics/clocks.py``, where its docstring states the rules):
it tells the runner, for each train-clock reading, whether to pass it on, hold it, admit or
refuse the readings it held, or map every later train-clock stamp back onto the old timeline
after a step (event ``clock_reset``; estimates keep the sample's own stamp, the new clock); the
runner admits, counts, logs and tells the integrity monitor. A command stamped above its own
clock by more than the same bar (:meth:`~.clocks.StepWatch.bar`) is refused (``future_stamp``);
it still votes, so a control clock that truly stepped is followed once the step fills half the
window.

Duplicates and sequence resets are judged by a :class:`~..numerics.stamp_order.StampOrder`,
the one rule the filters' own checks use too: sequence numbers only detect duplicates (same
``seq`` and stamp as a recent reading, or a sample fused at another stamp) and resets (``seq``
goes back while the stamp goes on: a sensor reboot or a wrap-around, accepted and counted as
the event ``seq_reset``). Order is decided by stamps, so ``seq = 2**32 - 1`` cannot blind a
stream; a reading older than the history is refused by the estimator's own
:class:`~..numerics.stamp_order.StampOrder` (``out_of_order``).
"""

from __future__ import annotations

import bisect
import heapq
import math
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from train_core.failsafe import guarded

from .. import reasons as R
from ..numerics.clocks import (
    ADMIT,
    HOLD,
    LATENCY,
    PASS,
    REFUSE,
    SKIP,
    SLIP,
    STEP,
    TIE,
    StepWatch,
    StreamClock,
)
from ..numerics.stamp_order import StampOrder
from .calibrated_odometry import CLOCK_UNSURE, SEQ_MADE
from .integrity import UNBOUNDED, IntegrityMonitor, IntegrityParams, changed

KIND_ORDER = {"control": 0, "odometer": 1, "balise": 2}
# the early hold waits past min_judged arrivals while two groups of offsets are as dense as
# each other (StreamClock.one_densest), up to this many times min_judged
EARLY_CAP = 4
UNCOUNTED_AFTER = 3  # readings at distinct stamps, all with one seq, spread over 1.5 periods at
#   least: a stream without a sample counter (:meth:`EstimatorRunner._note_counter`)
TICKS = 1000.0  # per s: the counter an uncounted stream's readings are given (ms of its stamp)
TICK0 = 2 ** 31  # the first such reading's tick (earlier stamps stay positive for 24 days)
NO_SLOT = (R.OUT_OF_ORDER, R.DUPLICATE, R.FUTURE_STAMP, R.STALE_STAMP, R.NON_FINITE)
CLOCK_OF = {"control": "control", "odometer": "train", "balise": "train"}
SETTLED_CALLS = 8  # commands a settled copy carries at most (EstimatorRunner.settle): one per
#   reading at the usual rates; more (an odometer silent while commands flow) and the next
#   settle copies the state afresh rather than keep a list that a rewind would make again


@dataclass(frozen=True)
class Output:
    """One estimate, as published in a TrainState (SI units; NaN where not estimated)."""

    stamp: float  # s, on the odometer (train) clock
    position: float  # m
    velocity: float  # m/s
    acceleration: float  # m/s^2
    braking_rate: float  # -
    covariance: tuple  # 16 floats, row-major 4x4 over (position, velocity, acceleration, f)
    measurement_used: bool
    integrity: int = 0  # 0 OK (both protection levels within the alert limit), 1 DEGRADED
    #   (bounded, but wider), 2 ALARM (no bound)
    integrity_reason: str = ""  # the integrity monitor's doubts (empty when it has none)
    separation: tuple = ()  # the consider term as solutions: (fault-free position variance
    #   m^2, ((shift m, variance m^2, kind), ...): kind "map" the solution without each recent
    #   balise, "start" the start's, "reader" the late reader's), or ()
    protection_level_ahead: float = math.inf  # m: the true position is at most position + this
    #   except with the integrity risk (protection.py); inf: no bound (ALARM, or not assessed)
    protection_level_behind: float = math.inf  # m: at least position - this, likewise
    consider: tuple = ()  # row-major 2x2 (position, speed) covariance the estimator's filter
    #   does not carry (the odometer's calibration, ``odometer_scale``): added to ``covariance``
    #   by the runner after the integrity monitor has judged the filter's own, and kept here
    #   (the published covariance minus it is the filter's own, or the monitor's inflation)


INTEGRITY_OK, INTEGRITY_DEGRADED, INTEGRITY_ALARM = 0, 1, 2


class Adapter(Protocol):
    """What the runner needs from an estimator (see train_estimation.core.online.estimators)."""

    def start(self, t0: float) -> None: ...
    def control(self, stamp: float, fields: dict) -> str: ...  # "" accepted, else a reason
    def odometer(self, stamp: float, fields: dict) -> str: ...
    def balise(self, stamp: float, fields: dict) -> str: ...
    def output(self, t: float) -> Output: ...  # estimate at t >= last fused time, state unchanged


_VALUES = {"odometer": (("distance", "speed"), ("speed_variance",)),
           "balise": (("position",), ("position_variance",))}


# a reading's variance field -> the believed train's (TrainParams) property for it
_BELIEVED = {"speed_variance": "odometer_speed_variance",
             "position_variance": "balise_position_variance"}


def _believed_variance(adapter, key: str) -> float | None:
    """The believed train's variance for a reading's field (None: the adapter has no train)."""
    train = getattr(adapter, "train", None)
    return None if train is None else float(getattr(train, _BELIEVED[key]))


def _content(kind: str, fields: dict) -> str:
    """Why a reading's values can say nothing (a NaN or infinite value, a variance <= 0), or
    "" (the filters judge the rest: gates, order)."""
    values, variances = _VALUES.get(kind, ((), ()))
    for k in values + variances:
        v = fields.get(k)
        if isinstance(v, bool) or not isinstance(v, int | float):
            return f"{R.INVALID}: {k} {v!r}"
        if not math.isfinite(v):
            return f"{R.NON_FINITE}: {k}"
    for k in variances:
        if fields[k] <= 0:
            return f"{R.NON_POSITIVE_VARIANCE}: {k} {fields[k]!r}"
    return ""


@dataclass
class EstimatorRunner:
    adapter: Adapter
    period: float  # s, odometer sample period (nominal; the slots follow the odometer's stamps)
    control_clock: str = "auto"  # "auto", "same" or "reference" (see module doc)
    max_future: float = 600.0  # s, stamp beyond arrival (+ median offset): future_stamp
    same_clock_tolerance: float = 2.0  # s, "auto": closer clocks are one clock ...
    same_clock_rate: float = 1e-4  # s/s, ... unless their rates differ by more (significantly)
    max_gap_outputs: int = 6000  # predicted slots after the last fused sample (10 min at 10 Hz)
    min_judged: int = 9  # arrivals of a clock before its stamps are judged (earlier ones wait);
    #   the fewest readings of a clock step: longer than any burst of readings stamped alike
    #   wrongly (a burst and a step undone after as many readings are the same data)
    history: float = 3.0  # s of fused input kept: a reading up to this late is fused by rewinding
    step_back: float = 0.3  # s: an odometer stamp this far behind the newest one admitted is
    #   held as a possible backward clock step (at least 2.5 periods); min_judged such readings
    #   continuing one another, arriving at their stamps' pace, are a step and re-anchored
    small_step: float = 0.05  # s: on a link whose jitter is small, a train-clock offset this
    #   far from its clock (and beyond small_step_z robust spreads of the link's jitter) is
    #   watched as a possible step too (not with control_clock 'same': step_back alone)
    small_step_z: float = 10.0  # robust spreads of the offsets (StreamClock.scale)
    step_risk: float = 1e-7  # -, the probability that readings held as a possible step are
    #   declared one while the old clock ran on and only its readings were lost on the link
    #   (clocks.silence_risk: the link's own loss rate sets how many readings that takes)
    false_step_rate: float = 1e-4  # 1/h: false small forward steps per hour at most (the
    #   envelope test's threshold, numerics/envelope.py)
    count_clock: bool = True  # an odometer without a sample counter: its stamps judged by its
    #   count while the train moves (StepWatch._count_resid), else by their arrivals alone
    queue: list = field(default_factory=list)
    rejected: Counter = field(default_factory=Counter)  # "kind:reason" -> count
    accepted: Counter = field(default_factory=Counter)
    events: Counter = field(default_factory=Counter)  # "kind:event" -> count (seq_reset, ...)
    last_reasons: list = field(default_factory=list)  # (kind, stamp, reason), most recent last
    last_events: list = field(default_factory=list)  # (kind, stamp, event text)
    high: dict = field(default_factory=dict)  # kind -> largest stamp queued (the watermark)
    _started: bool = False
    _t0: float | None = None  # the estimator's start (advance_to)
    _last_out: float | None = None  # stamp of the last estimate emitted
    _out_applied: float | None = None  # stamp of the latest estimate output to the adapter's
    #   state as it is now (a rewind's state is without the outputs after its copy)
    _n: int = 0  # insertion counter: FIFO among equal stamps and kinds
    _offsets: dict = field(default_factory=dict)  # clock -> StreamClock (offset, rate)
    _first_train: float = math.inf  # the lowest train-clock stamp admitted (_one_clock_possible)
    _prev_raw: float | None = None  # the last stamp pushed (no-arrival mode, early phase)
    _admitted_high: float = -math.inf  # the latest stamp admitted (no-arrival mode)
    _last_recv: float = -math.inf  # the latest arrival pushed (s, receive clock): drain's present
    _order: StampOrder | None = None  # copies of a message or a sample, seq resets
    _held: list = field(default_factory=list)  # control pushed before any odometer (raw)
    _ahead: list = field(default_factory=list)  # commands held above a control clock that
    #   queued items set (_hold_ahead)
    _ctl_first: float | None = None  # arrival of the first command (_hold_ahead)
    _early: dict = field(default_factory=dict)  # clock -> items waiting for min_judged
    _ready: set = field(default_factory=set)  # clocks whose early hold ended
    _adapter_seen: Counter = field(default_factory=Counter)  # the adapter's events said so far
    _stated_kinds: set = field(default_factory=set)  # kinds whose stream stated a variance > 0
    unstated: Counter = field(default_factory=Counter)  # kind -> readings whose variance 0
    #   was read as not stated (:meth:`_stated`)
    _counters: dict = field(default_factory=dict)  # kind -> _CounterWatch
    uncounted: Counter = field(default_factory=Counter)  # kind -> readings admitted without a
    #   sample counter (:meth:`_note_counter`)
    _tick0: dict = field(default_factory=dict)  # kind -> filter time of the counter's origin
    _control_stamped: bool = False  # the control stream stated a stamp (not 0)
    _zero_recv: float | None = None  # arrival of the first command stamped 0
    unstamped: int = 0  # commands stamped 0 taken at their arrival (:meth:`_control_stamp`)
    _odo: list = field(default_factory=list)  # heap of the queued odometer stamps
    _first_odometer: float | None = None  # stamp of the first odometer reading queued
    _lags: deque = field(default_factory=lambda: deque(maxlen=31))  # s, how far the control
    #   watermark led each of the latest odometer readings as it was queued (ready_time)
    _lags_sorted: list = field(default_factory=list)  # the same, in order (_odometer_lag)
    _anchor: tuple | None = None  # (train stamp, filter time) of the last processed odometer
    _last_mapped: float = -math.inf
    _hist: list = field(default_factory=list)  # [stamp, order, n, kind, fields, snapshot]
    _high_done: float = -math.inf  # largest stamp fused
    _last_fused: float = -math.inf  # stamp of the last odometer sample accepted (or the start)
    separate_clocks: bool = False  # control was found (or said) to be on another clock
    separate_why: str = ""  # what the tests said when control was found on another clock
    _steps: StepWatch | None = None  # the train clock's steps (and the train StreamClock)
    _ctl_wall: float | None = None  # arrival of the latest command (push's ``wall``)
    integrity: IntegrityParams = field(default_factory=IntegrityParams)
    command_slack: float = 0.25  # odometer periods: a reading stamped this little past the
    #   control watermark is processed without waiting for the next command (ready_time)
    command_timeout: float | None = None  # s without commands before the node's clock stands
    #   in for the control watermark (None: integrity.command_timeout)
    slot_grace: float = 0.5  # s on the arrival clock: a slot whose reading has not arrived this
    #   long after it was due is published as a prediction by :meth:`tick`
    _backlog: bool = False  # the latest message pushed came late (tick waits)
    monitor: IntegrityMonitor | None = None
    _base: tuple | None = None  # (the adapter's snapshot taken by settle, [(filter time,
    #   fields) of each control call since]); None once any other call changed the adapter
    fail_safe: bool = False  # an exception inside a call latches the runner as failed (ALARM
    #   from then on, :mod:`train_core.failsafe`) instead of propagating: the nodes' setting
    failure: str | None = None  # what failed ("call: Type: message"), once latched
    failure_trace: str = ""  # its traceback, for the node's log
    _alarms: list = field(default_factory=list)  # ALARM estimates not yet returned (failed)
    _published: Output | None = None  # the latest estimate emitted

    @property
    def arrival_resolution(self) -> float:
        """s, how finely ``recv`` times an arrival: 0 on a steady clock; on simulated time the
        ROS clock moves in /clock's ticks, and a message can be handled before the tick that
        delivered it, up to a tick early. A step smaller than that cannot be seen: it floors
        the bar beyond which an offset is watched as a step or refused as stamped ahead
        (:meth:`~.clocks.StepWatch.bar`). The node sets it from the ticks it sees."""
        return self._steps.resolution

    @arrival_resolution.setter
    def arrival_resolution(self, value: float) -> None:
        self._steps.resolution = float(value) if math.isfinite(value) and value > 0 else 0.0

    @property
    def _can_rewind(self) -> bool:
        return self.history > 0 and hasattr(self.adapter, "snapshot")

    def __post_init__(self):
        if self.control_clock not in ("auto", "same", "reference"):
            raise ValueError(f"control_clock must be auto, same or reference, "
                             f"got {self.control_clock!r}")
        if self.monitor is None:
            self.monitor = IntegrityMonitor(self.integrity, self.period,
                                            getattr(self.adapter, "train", None),
                                            getattr(self.adapter, "line", None))
        if self.command_timeout is None:
            self.command_timeout = self.integrity.command_timeout
        # the samples of the last ``history`` seconds are judged for copies (StampOrder)
        self._order = StampOrder(samples=max(8, math.ceil(self.history / self.period)))
        self._steps = StepWatch(self.period, self.min_judged, self.step_back, self.small_step,
                                self.small_step_z, self.max_future,
                                same=self.control_clock == "same", step_risk=self.step_risk,
                                false_step_rate=self.false_step_rate, count=self.count_clock)

    # -- door ---------------------------------------------------------------------------------
    @guarded(lambda self, *a, **k: self._failed_push(*a, **k))
    def push(self, kind: str, stamp: float, fields: dict, recv: float | None = None,
             wall: float | None = None) -> str:
        """Check and queue one item; returns "" or the reason it was refused at the door.

        ``recv``: arrival time (s) on the receive clock (the reference clock: a node's steady
        clock, or /clock on simulated time; a replay: the bag's log time), or None. ``wall``:
        the arrival on the clock waiting is measured on (:meth:`ready_time`; default ``recv``).
        """
        if kind not in KIND_ORDER:
            return self._reject(kind, math.nan, f"{R.UNKNOWN_KIND}: {kind}")
        if not (isinstance(stamp, float | int) and math.isfinite(stamp)):
            return self._reject(kind, math.nan, R.NON_FINITE + ": stamp")
        stamp = float(stamp)
        if kind == "control":
            stamp = self._control_stamp(stamp, recv)
        if CLOCK_OF.get(kind) == "train":  # onto the timeline before the steps
            stamp = self._steps.onto_timeline(stamp, kind == "odometer")
        if recv is not None and not math.isfinite(recv):
            recv = None
        if recv is not None:
            self._last_recv = max(self._last_recv, recv)
        if kind == "control" and recv is not None:
            w = recv if wall is None else wall
            self._ctl_wall = w if self._ctl_wall is None else max(self._ctl_wall, w)
        if kind != "control":
            seq = fields.get("seq") if isinstance(fields, dict) else None
            if not isinstance(seq, int) or isinstance(seq, bool):
                return self._reject(kind, stamp, f"{R.INVALID}: seq {seq!r}")
            fields = self._stated(kind, stamp, fields)
            self._note_counter(kind, stamp, seq, recv)
            why = _content(kind, fields)
            if why:
                # a reading that says nothing is no evidence about its clock either: refused
                # before the clocks see it (fuzzed copies with a NaN distance, their stamps
                # 30 ms off, were held as possible steps and doubted 2 estimates in 3)
                if kind == "odometer":
                    self.monitor.reading(stamp, None, False)
                return self._reject(kind, stamp, why)
        clock = CLOCK_OF[kind]
        med = self._offsets.get(clock)
        if med is None:  # the train clock is the one the step watch follows
            med = self._offsets[clock] = self._steps.clock if clock == "train" else \
                StreamClock(settled=self.min_judged)
        early = not self._clock_ready(clock, med)
        if recv is not None:
            arrival = recv
        elif early:  # no arrival times: the stamps themselves (one clock), jump from the last
            arrival = self._prev_raw if self._prev_raw is not None else stamp
        else:  # ... then from the latest stamp admitted on any topic
            arrival = self._admitted_high if math.isfinite(self._admitted_high) else stamp
        self._prev_raw = stamp
        if recv is not None and not early:
            # a message later than its clock's lateness bar (LATE): the node or its link is
            # catching up with a backlog (a stall's burst), whose next messages may well hold
            # the readings the arrival clock says are overdue; tick waits for one on time
            self._backlog = med.is_late(stamp - arrival)
        if early and not (clock == "train" and recv is not None and
                          self._steps.last is not None):
            # too early to judge a stamp against its clock: hold it until the clock's median
            # offset rests on min_judged arrivals (one corrupted first stamp must not set the
            # watermarks or the start), then judge the held ones like any other. Not once the
            # step watch judges the train clock (a reading admitted, arrivals known): it holds
            # what does not continue the clock, and an offset voted here before it judged put
            # a step's readings into the clock's centre (a +3 s step 4 s into a 1 Hz run: the
            # slots then came 3 s early to the end of the run, every reading fused late)
            # (for the centre only: an offset not judged lifts no ceiling, StreamClock._push;
            # a fuzzed 50 Hz stream has the clock's settled votes within 0.1 s, and its copies
            # stamped 5 s ahead then set the ceiling at +4.95 s for the whole run: nothing
            # below it was ahead of its clock, and the train was lost for 160 s)
            med.add(stamp - arrival, arrival, lift=clock != "train")
            early_items = self._early.setdefault(clock, [])
            early_items.append((kind, stamp, fields, recv, arrival))
            if self._clock_ready(clock, med):
                release = early_items
            else:  # those that agree with two others already are good: no need to wait
                uncounted = {k for k in KIND_ORDER if self._uncounted(k)}
                release = [e for e in early_items
                           if _agreeing(early_items, e, med.tol, uncounted) >= 3]
            self._judge_early(clock, release)
            return ""
        why = self._admit(kind, stamp, fields, recv, arrival)
        if self._clock_ready(clock, med):
            # what the early hold still keeps is judged once the clock is (above)
            self._judge_early(clock, self._early.get(clock, []))
        return why

    def _stated(self, kind: str, stamp: float, fields) -> dict:
        """The reading with a variance of exactly 0 read as *not stated* while its stream has
        never stated one (> 0): a producer that leaves the field at its default (zeros mean
        "unknown" in ROS's covariance fields). The believed train's value stands in
        (``train.yaml``: ``odometer.speed_std``, ``balise.position_std``), the event is logged
        once per stream and every such reading counted (:attr:`unstated`). Once the stream has
        stated a variance, a 0 is a corrupted reading and refused (``non_positive_variance``):
        a copy that says it is exact is no sensor's."""
        if not isinstance(fields, dict):
            return fields
        for key in _VALUES.get(kind, ((), ()))[1]:
            v = fields.get(key)
            if isinstance(v, bool) or not isinstance(v, int | float):
                continue
            if v > 0 and math.isfinite(v):
                self._stated_kinds.add(kind)
            elif v == 0 and kind not in self._stated_kinds:
                default = _believed_variance(self.adapter, key)
                if default is None:
                    continue
                fields = {**fields, key: default}
                if not self.unstated[kind]:
                    self._event(kind, stamp, f"{R.VARIANCE_UNSTATED}: {key} 0 read as not "
                                             f"stated; the believed train's {default:.3g} used "
                                             f"until the stream states one")
                self.unstated[kind] += 1
        return fields

    def _control_stamp(self, stamp: float, recv: float | None) -> float:
        """A command stamped 0 while its stream has never stated a stamp is stamped by its
        arrival: the contract puts commands on the reference clock, the receive time, and a
        producer that leaves the header empty sends zeros. The second such command (arriving
        after the first) decides it: a clock that starts at 0, as a simulation's, stamps one
        command 0 and the next ones on (event ``stamp_unstated``, once; counted in
        :attr:`unstamped`). Taken as stamped, every command lay an epoch before the readings,
        was fused late or refused, and three estimates in four were not published on time. A
        0 after a stated stamp is judged as any stamp."""
        if stamp != 0.0:
            self._control_stamped = True
            return stamp
        if self._control_stamped or recv is None or not math.isfinite(recv):
            return stamp
        if not self.unstamped:
            if self._zero_recv is None:
                self._zero_recv = recv
            if recv <= self._zero_recv:
                return stamp  # the first: possibly a clock's own 0
            self._event("control", recv, f"{R.STAMP_UNSTATED}: commands stamped 0: no stamp "
                                         f"stated; their arrival times used")
            # the first, still in the early hold: at its arrival too (its offset voted an epoch
            # off, one wild vote among the clock's)
            early = self._early.get("control", [])
            for i, (k, st, f, rc, ar) in enumerate(early):
                if st == 0.0 and rc is not None:
                    early[i] = (k, float(rc), f, rc, ar)
                    self.unstamped += 1
        self.unstamped += 1
        return float(recv)

    def _note_counter(self, kind: str, stamp: float, seq: int, recv: float | None) -> None:
        """Whether a train-clock stream has a sample counter. A stream whose readings all carry
        one ``seq`` (``UNCOUNTED_AFTER`` readings at distinct stamps, arriving over 1.5 periods
        at least: copies of one corrupted message arrive together; two balises) has none: a
        producer that leaves the field at its default. Its readings are then judged without
        one (:meth:`_uncounted`): a copy is a reading with the stamp and values of one already
        taken, the clocks judge the stamps against their arrivals alone, and the filters get a
        counter made of the stamp (ms, :meth:`_call`), so that lost samples are counted from
        the stamps at the configured rate. Before this, every reading after the first was
        refused as a copy of it and the estimator stayed blind for the whole run. Two readings
        with other values first: a counter (one may be a corrupted seq). Once decided it holds
        for the stream; event ``seq_unstated``, once."""
        w = self._counters.get(kind)
        t = recv if recv is not None else stamp
        if w is None:
            self._counters[kind] = _CounterWatch(seq, {stamp}, t, t)
            return
        if w.state:
            return
        if seq != w.seq:
            w.others += 1
            if w.others >= 2:
                w.state = "counted"
            return
        if len(w.stamps) < UNCOUNTED_AFTER:
            w.stamps.add(stamp)
        w.first, w.last = min(w.first, t), max(w.last, t)
        odo = kind == "odometer"
        if len(w.stamps) >= (UNCOUNTED_AFTER if odo else 2) and \
                w.last - w.first >= (1.5 * self.period if odo else 0.0):
            w.state = "uncounted"
            self._event(kind, stamp, f"{R.SEQ_UNSTATED}: {len(w.stamps)} readings all with seq "
                                     f"{w.seq}: no sample counter; judged by their stamps")

    def _uncounted(self, kind: str) -> bool:
        w = self._counters.get(kind)
        return w is not None and w.state == "uncounted"

    def _fused_elsewhere(self, kind: str, stamp: float, fields) -> str:
        """``duplicate`` when this odometer reading's sample was fused at another stamp in the
        last ``history`` seconds (a corrupted copy: a clock step sends new samples, not old
        ones, so it is no evidence of a step either), else "". A copy carries its sample's
        count: a reading with the seq of a fused one and another count is a new sample (an
        odometer that rebooted counts its seqs again; at 1 Hz its first nine were refused as
        copies of the samples before the reboot), judged as any other."""
        if kind != "odometer" or not isinstance(fields, dict):
            return ""
        seq = fields.get("seq")
        if seq is None and fields.get("speed") == 0:
            return ""  # no counter: a standing train reads its count and speed again and again
        key = _sample_key(fields)
        if self._order.elsewhere(key, stamp, fields.get("distance")):
            if seq is None and not self._count_moves(fields, stamp - self._order.fused[key][0]):
                # no counter, and a count rounded to a grid coarser than the train ran between
                # the two stamps: a new sample that the rounding left where the last one was
                # (a recorder's whole metres and km/h at 4 m/s and 10 Hz: half the readings
                # were refused as copies), or a copy within the count's own resolution
                return ""
            what = "count and speed" if seq is None else f"seq {seq}"
            return f"{R.DUPLICATE}: {what} fused at another stamp"
        return ""

    def _count_moves(self, fields: dict, dt: float) -> bool:
        """Whether an odometer's count (no counter) moves by more than its grid
        (:attr:`~.clocks.StepWatch.count_grid`) at the reading's speed over ``dt`` s."""
        v = fields.get("speed")
        return not isinstance(v, int | float) or abs(v * dt) > self._steps.count_grid

    def _clock_ready(self, clock: str, med: StreamClock) -> bool:
        """The early hold's end for a clock: ``min_judged`` offsets in, one group of them
        denser than any other (:meth:`~.clocks.StreamClock.one_densest`; at most
        ``EARLY_CAP`` times as many offsets waited for). Once ended it stays ended: later
        windows with two groups as dense (a step half-way through the window) are the step
        watch's and the centre's to judge, not a reason to hold every message again."""
        if clock in self._ready:
            return True
        n = len(med)
        if n >= self.min_judged and med.one_densest() or n >= EARLY_CAP * self.min_judged:
            self._ready.add(clock)
            return True
        return False

    def _judge_early(self, clock: str, release: list) -> None:
        """Admit ``release``, items the early hold kept for ``clock`` (their offsets voted
        already), and keep the rest held."""
        if release:
            self._early[clock] = [e for e in self._early[clock] if e not in release]
            for k, st, f, rc, ar in release:
                self._admit(k, st, f, rc, ar, counted=True)

    def _admit(self, kind: str, stamp: float, fields: dict, recv, arrival,
               counted: bool = False, watch: bool = True) -> str:
        """Judge a stamp against its clock's median offset, check seq, queue."""
        clock = CLOCK_OF[kind]
        med = self._offsets[clock]
        if kind != "control" and isinstance(fields, dict) and fields.get("seq") is not None \
                and self._uncounted(kind):
            fields = {**fields, "seq": None}  # no counter: nothing judged by it
            self.uncounted[kind] += 1
        # a copy of a message already come (its seq, stamp and values; a command's stamp and
        # target) is judged once, here, as it comes (a reading the step watch held comes back
        # with ``watch`` False): it is no evidence of a step, nor of anything else, and a
        # command's copy fused late made the runner rewind for nothing (a 50 Hz fuzzed run:
        # 2,433 of its 6,598 late commands)
        if watch and self._order.copy_of(kind, _copy_key(fields, stamp)):
            return self._reject(kind, stamp, R.DUPLICATE)
        why = self._fused_elsewhere(kind, stamp, fields)
        if why:
            return self._reject(kind, stamp, why)
        judged = med.judged  # (before the readings the step watch may release vote)
        if watch and clock == "train" and arrival is not None and self._steps.last is not None:
            held, stamp = self._watch_step(kind, stamp, fields, recv, arrival)
            self._clock_doubt()
            if held:
                return ""
        if arrival is not None:
            off = stamp - arrival
            if off - med.value > self.max_future:
                return self._reject(kind, stamp, f"{R.FUTURE_STAMP}: {off - med.value:.3g} s "
                                                 f"ahead of its arrival")
        if kind != "control":
            self._note_seq(kind, stamp, fields)
        # a command stamped above where its clock can be (latency only lowers stamp - arrival)
        # is refused, though it still votes: one command stamped 300 s ahead made the
        # control watermark run 300 s ahead, the runner predicted every slot up to it at once
        # and then refused every genuine reading as out of order (a clock that truly stepped
        # moves the window, and its commands are taken again)
        lead = med.above(stamp - arrival) if kind == "control" and recv is not None and \
            self.control_clock != "same" and med.judged else -math.inf
        bar = self._steps.bar(med) if lead > 0 else math.inf
        # only an offset judged against its clock lifts the clock's ceiling
        # (StreamClock._push): one that came while its clock was not yet judged votes for the
        # centre only, though the votes of the readings the step watch released before it
        # judged the clock. A fuzzed 50 Hz stream's copy stamped 5 s ahead came so, set the
        # ceiling at +4.95 s, and from then on nothing below it was ahead of its clock: its
        # kind were admitted, voted and held it there for the whole run (crh3_high_speed: the
        # train lost for 160 s, 653 m under ALARM)
        if arrival is not None and not counted:
            med.add(stamp - arrival, arrival, lift=not lead > bar and (judged or
                                                                      clock != "train"))
        if kind == "control" and arrival is not None and self._ctl_first is None:
            self._ctl_first = arrival
        if kind == "control" and self._ahead:
            self._judge_ahead(med)
        if lead > bar:
            if self._hold_ahead(med, stamp, fields, recv, arrival):
                return ""
            return self._refuse_ahead(kind, stamp, lead)
        if kind in ("odometer", "control") and recv is not None:
            med.rate_point(stamp, recv)  # only stamps on time inform the rate (not a backlog's)
        return self._admitted(kind, stamp, fields, recv, arrival)

    def _hold_ahead(self, med: StreamClock, stamp: float, fields: dict, recv, arrival) -> bool:
        """Whether a command above its clock is held rather than refused: the clock rests on
        the stream's first arrival instant still (its window holds votes of it). The items
        that arrive together at a stream's start were queued (what a node received before its
        first /clock, or the middleware's repair of what was sent before it matched, all timed
        at one /clock): their offsets bound the clock from below only, by how long they
        waited, which nothing states. A command on time is then above that clock, and refused
        as stamped ahead it would be lost: a node that joined a run at 10x beside two busy
        loops refused 25 (offline, a backlog timed 0.4 s late refused 5-7 commands, 0.8 s
        9-15). Held, it is judged as the commands after it move the clock
        (:meth:`_judge_ahead`); meanwhile the commands' watermark stays where the admitted ones
        put it, so a stamp far ahead moves nothing."""
        if not self._hold_on(med):
            return False
        self._ahead.append((stamp, fields, recv, arrival, stamp - arrival))
        return True

    def _judge_ahead(self, med: StreamClock, force: bool = False) -> None:
        """The held commands (:meth:`_hold_ahead`) judged against their clock as the commands
        after them move it: one that now lies within the step watch's bar of it was on time,
        and is admitted; once the clock no longer rests on its first instant (or ``force``: at
        the end of the data) one still above it was stamped ahead (``future_stamp``: a wrong
        stamp, which the commands after it did not follow). (Judged by the commands after it
        alone, a fuzzed stream's corrupted copies continued one another: a stream of five
        copies per command lost its estimates for minutes.)"""
        bar = self._steps.bar(med)
        final = force or not self._hold_on(med)
        keep = []
        for h in sorted(self._ahead, key=lambda h: h[0]):
            stamp, fields, recv, arrival, off = h
            lead = med.above(off)
            if lead <= bar:
                self._admitted("control", stamp, fields, recv, arrival)
            elif final:
                self._refuse_ahead("control", stamp, lead)
            else:
                keep.append(h)
        self._ahead = keep

    def _refuse_ahead(self, kind: str, stamp: float, lead: float) -> str:
        """Refuse an item stamped ``lead`` s above its clock (``future_stamp``)."""
        return self._reject(kind, stamp, f"{R.FUTURE_STAMP}: {lead:.3g} s ahead of its clock")

    def _hold_on(self, med: StreamClock) -> bool:
        """Whether the control clock still rests on its stream's first arrival instant."""
        return self._ctl_first is not None and self._ctl_first in med.arrivals

    def _admitted(self, kind: str, stamp: float, fields: dict, recv, arrival) -> str:
        """Queue an item its clock admitted (the end of :meth:`_admit`)."""
        self._steps.admitted(kind, stamp, arrival, fields.get("seq") if isinstance(fields, dict)
                             else None)
        if self._steps.untimed_moved():
            self._clock_doubt()  # the first reading after an untimed gap, off its clock
        self._admitted_high = max(self._admitted_high, stamp)
        if kind == "control":
            if not self._judged("train"):
                self._held.append((stamp, recv, fields))
                return ""
            stamp = self._to_train(stamp, recv)
        else:
            self._first_train = min(self._first_train, stamp)
            if self._held:
                held, self._held = self._held, []
                for s, rc, f in held:
                    self._queue("control", self._to_train(s, rc), f)
        if kind == "odometer" and "control" in self.high and not self._backlog:
            # (a backlog's readings say how long the stall was, not how the link delivers)
            self._lag(self.high["control"] - stamp)
        self._queue(kind, stamp, fields)
        return ""

    def _clock_doubt(self) -> None:
        """Tell the integrity monitor the step watch's doubt: the readings it holds, the
        largest discontinuity among them, whether one is conclusive, and a late balise."""
        n, doubt, conclusive = self._steps.doubt()
        self.monitor.clock(n, doubt=doubt, conclusive=conclusive, stray=self._steps.stray())

    def _watch_step(self, kind: str, stamp: float, fields: dict, recv, arrival):
        """``(held, stamp)``: act on the step watch's answer for a train-clock reading, in
        order (each held reading is judged as the admission of the ones before it left the
        clock); ``stamp`` comes back mapped when this reading completed a step."""
        held = False
        for act in self._steps.watch(kind, stamp, fields, recv, arrival, self.drift):
            if act[0] == ADMIT:
                self._admit(*act[1], watch=False)
            elif act[0] == REFUSE:
                _, k, st, ahead = act
                if ahead > 0:
                    self._count(k, st, f"{R.FUTURE_STAMP}: {ahead:.3g} s ahead of its stream, "
                                       f"not continued by later readings")
                else:
                    self._count(k, st, f"{R.STALE_STAMP}: {-ahead:.3g} s behind its sample "
                                       f"grid, not continued by later readings")
            elif act[0] == STEP:
                _, shift, first, measured, unsure = act
                self.monitor.clock(0, reanchored_at=first - shift, measured=measured,
                                   step=shift)
                if unsure:
                    self.monitor.untimed(shift)
                # the first new reading's stamp as sent: its timeline stamp plus the shifts
                # before this one
                sent = first + self._steps.shift - shift
                self._event("odometer", stamp, f"{R.CLOCK_RESET}: train clock stepped by "
                                               f"{shift:+.3f} s at stamp {sent:.3f}; "
                                               f"re-anchored")
            elif act[0] == LATENCY:
                if act[2]:
                    self.monitor.untimed(act[1])
                self._event("odometer", stamp, f"{R.LINK_LATENCY}: the readings' latency "
                                               f"moved by {-act[1]:+.3f} s and stayed while "
                                               f"their stamps ran on; no clock step")
            elif act[0] == SKIP:
                self._event("odometer", stamp, f"{R.SEQ_SKIP}: the sample counter moved by "
                                               f"{act[1]:+d} samples while the stamps and "
                                               f"arrivals ran on; grid re-learnt")
            elif act[0] == SLIP:
                self._slip_event(stamp, act[1])
            elif act[0] == PASS:
                stamp = act[1]
            elif act[0] == HOLD:
                held = True
        return held, stamp

    def _note_seq(self, kind: str, stamp: float, fields: dict) -> None:
        """A seq reset logged. (``seq`` is an int, checked by :meth:`push`, or None on a
        stream without a counter.)"""
        seq, last = fields.get("seq"), self._order.last.get(kind)
        if seq is not None and self._order.took(kind, stamp, seq):
            self._event(kind, stamp, f"{R.SEQ_RESET}: seq {last[0]} -> {seq}")

    def _to_train(self, stamp: float, recv: float | None) -> float:
        """A control stamp on the train (odometer) clock (module doc), for a command that
        arrived at ``recv``.

        One clock while the two clocks' offsets can agree (:meth:`_clock_gap` within
        ``same_clock_tolerance``) and their rates do (:meth:`_drifting`), asked again at every
        command; two once they cannot, and that answer stays. But not from one instant: the
        offsets that arrived at one instant are one latency, and a queue's (a topic whose
        delivery stalled, a node that joined under load) lie below their clock by as much as
        it stalled. While every vote of either clock came at one arrival instant and the
        command's stamp could be on the train clock (:meth:`_one_clock_possible`), the answer
        waits and the command is taken on the train clock. (Decided from the first three
        commands of a joining node's backlog, 32 s below the odometer's offsets because the
        topic's first delivery had waited for a repair, "separate" stayed for the run and
        mapped the commands by the centres' wandering difference: 8-28 refused, as ahead or
        out of order.)"""
        if self.control_clock == "same" or recv is None:
            return stamp
        train, control = self._offsets["train"], self._offsets["control"]
        if self.control_clock == "auto" and not self.separate_clocks:
            if self._clock_gap(train, control) < self.same_clock_tolerance \
                    and not self._drifting():
                return stamp
            res = max(TIE, self.arrival_resolution)
            if (train.one_instant(res) or control.one_instant(res)) \
                    and self._one_clock_possible(stamp, recv):
                return stamp
        if not self.separate_clocks:
            self.separate_clocks = True
            self.separate_why = self._separate_why(train, control, stamp, recv)
        # both offsets where they are at the command's arrival, not half a window ago: on a
        # train clock 1e-2 fast the plain centres mapped every command 0.15 s early, below the
        # reading sampled with it, and a 1 Hz reading then waited for the next command, a
        # second late (StreamClock.value_at)
        shift = train.value_at(recv, train.drift) - control.value_at(recv, control.drift)
        # the shift follows the medians: keep the mapped commands in their order
        mapped = max(stamp + shift, self._last_mapped)
        self._last_mapped = mapped
        return mapped

    def _separate_why(self, train: StreamClock, control: StreamClock, stamp: float,
                      recv: float) -> str:
        """Why the clocks were taken as two (for the log): what each test said."""
        if self.control_clock == "reference":
            return "control_clock: reference"
        d_t, se_t = train.rate_apart()
        d_c, se_c = control.rate_apart()
        return (f"offsets {self._clock_gap(train, control):.3f} s apart at least "
                f"(tolerance {self.same_clock_tolerance:g}); rates {d_t - d_c:.2e} apart "
                f"+- {math.hypot(se_t, se_c):.1e} (bound {self.same_clock_rate:g} or 5 se); "
                f"a command stamped {stamp:.3f} s arriving at {recv:.3f} s")

    def clock_summary(self) -> str:
        """One line on the clocks as judged so far (for a node's closing log): whether control
        is taken on the odometer's clock, and each clock's rate against the arrivals with its
        standard error (the rate fit's, and as the two clocks are told apart: StreamClock.
        rate_apart) and the spread of its offsets."""
        where = f"on another clock: {self.separate_why}" if self.separate_clocks \
            else "on the odometer clock"
        parts = [f"control {where} ({self.control_clock})"]
        for name in ("train", "control"):
            c = self._offsets.get(name)
            if c is not None and len(c):
                (d, se), (da, sa) = c.rate(), c.rate_apart()
                parts.append(f"{name} rate {d:+.2e} +- {se:.1e} (apart {da:+.2e} +- {sa:.1e}), "
                             f"offsets spread {c.scale:.3g} s")
        return "; ".join(parts)

    @staticmethod
    def _clock_gap(train: StreamClock, control: StreamClock) -> float:
        """s, the least distance between the two clocks' offsets that their stamps allow: the
        gap between their spans (:meth:`~.clocks.StreamClock.span`, from the centre up to the
        quickest offsets), 0 where they overlap. The centres alone, compared as a node joined
        a running world under load (a 2.9 s stall at 10x: a window of offsets half on time and
        half a backlog), fell on either side by the luck of one more command, 2.3 s apart,
        and "separate" stayed for the run: 28 commands refused as ahead."""
        (lt, ht), (lc, hc) = train.span(), control.span()
        return max(lt - hc, lc - ht, 0.0)

    def _one_clock_possible(self, stamp: float, recv: float) -> bool:
        """Whether a command stamped ``stamp`` that arrived at ``recv`` can be on the train
        clock: sent no earlier than the first train-clock stamp this runner took (a node
        receives what is sent once it listens; ``same_clock_tolerance`` for a reading lost
        or matched a moment later), and not after its arrival on that clock (the train
        clock's highest offset; the same tolerance)."""
        tol = self.same_clock_tolerance
        return self._first_train - tol <= stamp <= recv + self._offsets["train"].span()[1] + tol

    def _drifting(self) -> bool:
        """The train clock's rate differs from the control clock's (each against the
        arrivals) by more than ``same_clock_rate``, significantly (5 standard errors): two
        clocks, however close their offsets still are (a clock 1 % slow is 2 s off after 200
        s; taken as one until then, the commands were mapped up to 2 s off). Rates against
        each other, not against the arrivals: a node falling behind its input (sim time at
        10x on a loaded machine) sees every stream's latency grow alike, which is no second
        clock; and each with its error as :meth:`~.clocks.StreamClock.rate_apart` states it,
        whose latency may wander."""
        d_t, se_t = self._offsets["train"].rate_apart()
        d_c, se_c = self._offsets["control"].rate_apart()
        d, se = d_t - d_c, math.hypot(se_t, se_c)
        return abs(d) > max(self.same_clock_rate, 5.0 * se)

    @property
    def drift(self) -> float:
        """Train clock rate minus 1 (s/s), from stamps vs arrivals (StreamClock.rate); 0 until
        the clocks are known to be separate (one clock needs no rate: same seconds)."""
        if not self.separate_clocks or "train" not in self._offsets:
            return 0.0
        return self._offsets["train"].drift

    def _filter_time(self, stamp: float) -> float:
        """Train-clock stamp -> filter time in reference seconds (the drift removed piecewise
        from the last processed odometer sample, so that it stays monotone as the estimate of
        the drift improves). Identity while the drift is 0."""
        if self._anchor is None:
            return stamp
        s0, f0 = self._anchor
        return f0 + (stamp - s0) / (1.0 + self.drift)

    def _queue(self, kind: str, stamp: float, fields: dict) -> None:
        mon = self.monitor
        # the clock's reading after an untimed gap is in doubt (IntegrityMonitor.untimed), and
        # so is a reading that comes while the step watch holds others as a possible step (by
        # the largest discontinuity among them): so is this stamp, for a count that restarted
        # and is spliced at it. (Only the decision's doubt marked it, and a reboot's first
        # reading, overtaken on a jittery link by the one after it, came while that one was
        # held and was spliced as sure: yizhuang_metro, the clock stepped back 3 s at 21 m/s,
        # the next balise 54 m off a count stated to 0.3 m, the kf 116 m off within 99 m)
        if kind == "odometer" and isinstance(fields, dict):
            unsure = abs(mon.unsure[0]) if mon.unsure is not None else mon.doubt if mon.held \
                else 0.0
            if unsure > 0.0:
                fields = {**fields, CLOCK_UNSURE: unsure}
        heapq.heappush(self.queue, (stamp, KIND_ORDER[kind], self._n, kind, fields))
        if kind == "odometer":
            heapq.heappush(self._odo, stamp)
            if self._first_odometer is None:
                self._first_odometer = stamp
        self.high[kind] = max(self.high.get(kind, -math.inf), stamp)
        self._n += 1

    def _reject(self, kind: str, stamp: float, reason: str) -> str:
        reason = R.normalise(reason)
        self.rejected[f"{kind}:{R.category(reason)}"] += 1
        self.last_reasons.append((kind, stamp, reason))
        del self.last_reasons[:-20]
        return reason

    def _event(self, kind: str, stamp: float, text: str) -> None:
        self.events[f"{kind}:{R.category(text)}"] += 1
        self.last_events.append((kind, stamp, text))
        del self.last_events[:-20]

    # -- processing ---------------------------------------------------------------------------
    def _call(self, stamp: float, kind: str, fields: dict) -> str:
        ft = self._filter_time(stamp)
        if kind == "odometer":
            self._anchor = (stamp, ft)
        if kind != "control" and isinstance(fields, dict) and "seq" in fields \
                and fields["seq"] is None:
            # an uncounted stream (_note_counter): the filters order, mark duplicates and count
            # lost samples by seq; a counter made of the stamp (ms) gives them the stamps' word
            t0 = self._tick0.setdefault(kind, ft)
            # (marked as made: the adapters do not read a restart from it)
            fields = {**fields, "seq": TICK0 + int(round((ft - t0) * TICKS)),
                      SEQ_MADE: True}
        base = self._base
        if base is not None:  # the settled copy stands while only commands follow it
            if kind == "control" and len(base[1]) < SETTLED_CALLS:
                base[1].append((ft, fields))
            else:
                self._base = None
        try:
            reason = getattr(self.adapter, kind)(ft, fields)
        except (KeyError, TypeError, ValueError, OverflowError) as exc:  # malformed fields
            self._base = None  # (a call that raised is not made again: a fresh copy)
            return f"{R.INVALID}: {type(exc).__name__}: {exc}"
        self._adapter_events(kind, stamp)
        return reason

    def _adapter_events(self, kind: str, stamp: float) -> None:
        """The adapter's own events (the count relocated, a balise excluded, the reader's
        latency found, the count restarted) as the runner's, logged once each: a count above
        the highest seen (a rewind replays what it already said)."""
        odometry = getattr(self.adapter, "odometry_events", None)
        if odometry is None or kind == "control":
            return
        for name, n in odometry().items():
            if n > self._adapter_seen[name]:
                self._adapter_seen[name] = n
                self._event(kind, stamp, f"{name}: {R.DESCRIPTION.get(name, '')}")

    @guarded(lambda self, *a, **k: self._failed_nothing(*a, **k))
    def settle(self) -> None:
        """Copy the adapter's state now, for the next odometer reading's rewind point
        (:class:`_Replayed`), unless a copy taken since the last change still stands: called
        once the estimates are out (the node after publishing them), so that the copy, a
        tenth of an estimate's work, is not made between a reading's arrival and its
        estimate. Nothing changes in what is computed: without it each reading's state is
        copied just before the reading, as a rewind needs it."""
        if self._base is None and self._started and self._can_rewind:
            self._base = (self.adapter.snapshot(), [])

    def _restore(self, snap) -> None:
        """The adapter back to a history entry's state (its snapshot, or the settled one with
        the control calls made since, made again)."""
        self._base = None
        if isinstance(snap, _Replayed):
            self.adapter.restore(snap.base)
            for ft, fields in snap.controls:
                self.adapter.control(ft, fields)
        else:
            self.adapter.restore(snap)

    def _process(self, entry: list) -> str:
        """Apply one item, keeping it (and the state before it, for odometer items) in the
        history that a late item rewinds. The history stays in stamp order: an item older than
        its last one (beyond the history's reach, or with no copy before it) is placed at its
        stamp without a copy of its own (appended with the copy taken after the outputs since,
        it became the first copy kept, the ones before it were let go, and the braking filters
        refused every late reading after it that the history still reached)."""
        hist = self._hist
        in_order = not hist or (entry[0], entry[1]) >= (hist[-1][0], hist[-1][1])
        rewinds = self._can_rewind  # (asked once: a wrapped adapter answers through getattr)
        if entry[3] == "odometer" and rewinds and in_order:
            base = self._base
            snap = _Replayed(base[0], tuple(base[1])) if base is not None \
                else self.adapter.snapshot()
            # (with the stamp of the latest estimate output to the state copied: a braking
            # filter's output is a time update of the filter itself, which the copy holds)
            entry[5] = (snap, self._anchor, self._out_applied)
        reason = self._call(entry[0], entry[3], entry[4])
        if len(entry) > 6:
            # fused again after a rewind: the item is counted once, by what it is now (the
            # first reading after a backward step, stamped as the last one before it, was
            # refused as its duplicate; re-stamped it is fused)
            if R.normalise(entry[6]) != R.normalise(reason):
                self._uncount(entry[3], entry[6])
                self._count(entry[3], entry[0], reason)
            entry[6] = reason
        else:
            entry.append(reason)
        if self.history > 0:
            if in_order:
                hist.append(entry)
            else:
                key = (entry[0], entry[1])
                hist.insert(next(k for k, h in enumerate(hist) if (h[0], h[1]) > key), entry)
            self._high_done = max(self._high_done, entry[0])
            if not rewinds:
                # an adapter without snapshots is never rewound: only the last item is read
                # (what is late); the whole history kept would be scanned below per item
                del hist[:-1]
                return reason
            # keep the history back to the first snapshot older than the horizon
            cut = self._high_done - self.history
            while len(hist) > 1:
                for first_snap in range(1, len(hist)):
                    if hist[first_snap][5] is not None:
                        break
                else:
                    break
                if hist[first_snap][0] > cut:
                    break
                del hist[:first_snap]
        return reason

    def _apply(self, stamp: float, order: int, n: int, kind: str, fields: dict) -> str:
        # the admission's check again, now that the queue has fused what came before: two
        # copies of one sample admitted before either was fused (the early hold released a
        # copy stamped 5 s ahead with the original; fused 5 s late with its sample's distance,
        # it left the robust filter 11 m behind with a sigma of 1.1 m)
        if kind == "control" and self._t0 is not None and stamp < self._t0:
            # given before the estimator's start: the command in force at it (the filters start
            # at t0; the braking filters refused a command 45 ms older as out of order)
            stamp = self._t0
        reason = self._fused_elsewhere(kind, stamp, fields)
        if reason:
            self._count(kind, stamp, reason)
            self._observe(kind, stamp, fields, reason)
            return reason
        entry = [stamp, order, n, kind, fields, None]
        hist = self._hist
        # late: older than an item fused, or than an estimate output (a braking filter's
        # output is a time update of the filter itself)
        late = hist and ((stamp, order) < (hist[-1][0], hist[-1][1])
                         or (self._last_out is not None and stamp < self._last_out))
        if late and self._can_rewind and stamp >= self._high_done - self.history:
            # rewind to the state before the first fused item after it, and re-filter
            j = next((k for k in range(len(hist)) if (hist[k][0], hist[k][1]) > (stamp, order)),
                     len(hist))
            i = self._copy_before(j, stamp)
            if i is not None:
                redo = self._rewind_to(i)
                redo.insert(j - i, entry)
                reason = ""
                for e in redo:
                    e[5] = None
                    r = self._process(e)
                    if e is entry:
                        reason = r
                self._count(kind, stamp, reason)
                self._observe(kind, stamp, fields, reason)
                if not reason:
                    self._event(kind, stamp, f"{R.FUSED_LATE}: {self._high_done - stamp:.3f} s "
                                             f"late")
                return reason
        reason = self._process(entry)
        if late and reason == R.OUT_OF_ORDER:
            # how late, so that a log or /diagnostics tells a link that delivers later than
            # the history (raise `history`, or mend the link) from input that is misordered
            reason += (f": {self._high_done - stamp:.3f} s older than the newest input fused "
                       f"(history {self.history:g} s)")
        self._count(kind, stamp, reason)
        self._observe(kind, stamp, fields, reason)
        return reason

    def _copy_before(self, j: int, stamp: float) -> int | None:
        """The latest history entry at or before ``j`` with a copy of a state that no estimate
        later than ``stamp`` was output to (None: none kept). The braking filters' outputs step
        the filter itself, and a copy taken after a lost reading's slot was predicted holds the
        filter at that slot's time (a reading sampled a few ms before its nominal slot, late on
        the link, was refused as out of order)."""
        hist = self._hist
        return next((k for k in range(min(j, len(hist) - 1), -1, -1) if hist[k][5] is not None
                     and (hist[k][5][2] is None or hist[k][5][2] <= stamp)), None)

    def _rewind_to(self, i: int) -> list:
        """The adapter back to the state before history entry ``i`` (its copy); the entries from
        ``i`` on, taken out of the history, to be fused again."""
        hist = self._hist
        snap, anchor, out = hist[i][5]
        redo = hist[i:]
        del hist[i:]
        self._restore(snap)
        self._anchor = anchor
        self._out_applied = out  # (outputs are not made again: the state is without them)
        return redo

    def _observe(self, kind: str, stamp: float, fields: dict, reason: str) -> None:
        """Tell the integrity monitor what became of an item the filter processed."""
        if not self.monitor.count_out and getattr(self.adapter, "count_out", None) is not None:
            self.monitor.count_excluded()  # (asked at every item: a rewind may have excluded)
        if kind == "odometer":
            fused = not reason or R.category(reason) in R.ACCEPTED
            if fused and isinstance(fields, dict):
                self._steps.fused(stamp, fields.get("distance"), fields.get("seq"),
                                  fields.get("speed"))
                self._order.fuse(_sample_key(fields), stamp, fields.get("distance"))
            pos = getattr(self.adapter, "position_reading", None)
            gate = R.category(reason) == R.OUTSIDE_GATE if reason else False
            mapped = getattr(self.adapter, "monitor_fields", None)
            if mapped is not None and isinstance(fields, dict):
                fields = mapped(fields)
            self.monitor.reading(stamp, fields if isinstance(fields, dict) else None, fused,
                                 pos(fields) if pos is not None and (fused or gate) and
                                 isinstance(fields, dict) else None, gate=gate)
        elif kind == "control" and not reason:
            try:
                a = float(fields["target_acceleration"])
            except (KeyError, TypeError, ValueError):
                a = math.nan
            self.monitor.command(stamp, a)
        elif kind == "balise":
            fused = not reason or R.category(reason) in R.ACCEPTED
            mapped = getattr(self.adapter, "monitor_balise", None)
            if mapped is not None and fused and isinstance(fields, dict):
                fields = mapped(fields)
            self.monitor.balise(stamp, fields if isinstance(fields, dict) else None, fused,
                                R.category(reason) if reason else "")

    def _uncount(self, kind: str, reason: str) -> None:
        """Take back the count of an item's earlier outcome (fused again after a rewind)."""
        if reason:
            key = f"{kind}:{R.category(R.normalise(reason))}"
            self.rejected[key] -= 1
            if self.rejected[key] <= 0:
                del self.rejected[key]
        else:
            self.accepted[kind] -= 1

    def _count(self, kind: str, stamp: float, reason: str) -> None:
        if reason:
            self._reject(kind, stamp, reason)
        else:
            self.accepted[kind] += 1

    def _emit(self, t: float, out: list) -> None:
        self._base = None  # an output may step the filter (the braking filters')
        o = self.monitor.assess(self.adapter.output(self._filter_time(t)), t)
        changes = {}
        if o.consider:
            # the (position, speed) block of the row-major 4x4, each entry plus its consider
            # term in one float64 addition, as adding the 2x2 arrays does (the monitor's
            # covariance is of float64 scalars already: no 16-entry array to build and unpack)
            C = list(o.covariance)
            cons = o.consider
            for i, k in ((0, 0), (1, 1), (4, 2), (5, 3)):
                C[i] = np.float64(C[i]) + float(cons[k])
            changes["covariance"] = tuple(C)
        # published on the train clock (after a step: the new one, the sample's stamp as sent)
        stamp = self._steps.as_sent(t)
        if o.stamp != stamp:
            changes["stamp"] = stamp
        o = changed(o, changes) if changes else o
        out.append(o)
        self._published = o
        self._last_out = t
        self._out_applied = t

    @guarded(lambda self, *a, **k: self._failed_outputs(*a, **k))
    def advance_to(self, t: float) -> list[Output]:
        """Process everything queued with stamp <= t; the estimates that became due."""
        out: list[Output] = []
        if not self._started:
            # the odometer defines the clock and the slots: start with the third sample, at the
            # earliest item no more than 2 s before the median of the first three (one stale or
            # corrupted first stamp must not start the estimator 500 s in the past)
            if len(self._odo) < 3:
                return out
            first = sorted(self._odo[:3]) if len(self._odo) == 3 else sorted(self._odo)[:3]
            t0 = min(s for s, *_ in self.queue if s >= first[1] - 2.0)
            self.adapter.start(t0)
            self._t0 = t0
            self._anchor = (t0, t0)
            self._last_fused = t0
            self._started = True
        while True:
            nxt = self.queue[0][0] if self.queue else math.inf
            if self._last_out is not None:
                # a lost slot: predicted estimate at the expected time, once nothing can fill it;
                # at most max_gap_outputs slots after the last fused sample (a stamp far ahead
                # cannot make the runner predict for ever)
                # one period of reference time later: on a drifting train clock the samples
                # are (1 + drift) periods of its stamps apart (a slot at the nominal period, 0.01
                # s early per lost sample on a clock 1 % fast, claimed a time before the sample)
                slot = self._last_out + self.period * (1.0 + self.drift)
                if slot <= t + 1e-9 and self._next_odometer() > slot + 0.5 * self.period \
                        and nxt > slot \
                        and slot - self._last_fused <= self.max_gap_outputs * self.period:
                    self._emit(slot, out)
                    continue
            if nxt > t + 1e-9:
                break
            stamp, order, n, kind, fields = heapq.heappop(self.queue)
            if kind == "odometer":
                heapq.heappop(self._odo)
            reason = self._apply(stamp, order, n, kind, fields)
            if kind == "odometer" and not reason:
                self._last_fused = max(self._last_fused, stamp)
            # one estimate per slot, at the sample's stamp -- unless the sample is no slot (a
            # stamp refused as out of order, duplicate or from the future), or its slot was
            # already published as a prediction (it came after the fallback: fused, it shows
            # in the next estimate)
            if kind == "odometer" and R.category(reason) not in NO_SLOT and (
                    self._last_out is None or stamp > self._last_out + 0.5 * self.period):
                self._emit(stamp, out)
            if self._steps.late is not None:
                self._late_step()
        return out

    def _slip_event(self, stamp: float, r: float) -> None:
        """Log the step watch's answer that the odometer's count, not the clock, moved by ``r``
        s of count time (``count_slip``)."""
        self._event("odometer", stamp, f"{R.COUNT_SLIP}: the odometer's count left its speed by "
                                       f"{r:+.3f} s of count time while the stamps stayed on "
                                       f"their clock (a wheel slip or slide, a count re-based); "
                                       f"no clock step")

    def _late_step(self) -> None:
        """Act on what the count's level test found among readings already fused
        (:meth:`~.clocks.StepWatch._level_test`), once their estimates are out: a count that
        moved (logged as the count's slip), or a step of the train clock that began at
        timeline stamp ``first``. Then the train-clock readings from ``first`` on, fused or
        queued, take their stamps on the new clock (``d`` s earlier on the timeline), and those
        fused are fused again from the copy before the first of them, in the new order (as for
        a late reading; an adapter without copies keeps what it fused)."""
        what, first, d, count0 = self._steps.late
        self._steps.late = None
        if what == SLIP:
            self._slip_event(first, d)
            return

        def moved(kind: str, x: float, f=None) -> float:
            # an odometer reading by its count (one after a backward step of a period carries
            # the stamp of the last one before it), a balise by its stamp
            if kind == "odometer" and isinstance(f, dict) and \
                    isinstance(f.get("distance"), int | float):
                return x - d if f["distance"] > count0 and x >= first - abs(d) - 1e-9 else x
            return x - d if CLOCK_OF.get(kind) == "train" and x >= first else x

        if any(moved(k, s, f) != s for s, _, _, k, f in self.queue):
            self.queue = [(moved(k, s, f), o, n, k, f) for s, o, n, k, f in self.queue]
            heapq.heapify(self.queue)
            self._odo = [s for s, _, _, k, _ in self.queue if k == "odometer"]
            heapq.heapify(self._odo)
        for k in ("odometer", "balise"):
            if k in self.high:
                self.high[k] = moved(k, self.high[k])
        hist = self._hist
        j = next((i for i, e in enumerate(hist) if moved(e[3], e[0], e[4]) != e[0]), None)
        i = self._copy_before(j, min(moved(e[3], e[0], e[4]) for e in hist[j:])) \
            if j is not None and self._can_rewind else None
        if i is not None:
            redo = self._rewind_to(i)
            for e in redo:
                e[0], e[5] = moved(e[3], e[0], e[4]), None
            redo.sort(key=lambda e: (e[0], e[1]))
            for e in redo:
                self._process(e)
            self._high_done = max(e[0] for e in hist)
        if self._last_out is not None:
            self._last_out = moved("odometer", self._last_out)
        self._last_fused = moved("odometer", self._last_fused)
        self.monitor.clock(0, reanchored_at=first - d, measured=True, step=d)
        self._event("odometer", first, f"{R.CLOCK_RESET}: train clock stepped by {d:+.3f} s "
                                       f"at stamp {first + self._steps.shift - d:.3f}, found by "
                                       f"the count's level among readings fused; re-stamped")

    def _next_odometer(self) -> float:
        return self._odo[0] if self._odo else math.inf

    def due_time(self, now: float) -> float:
        """Latest train-clock stamp whose reading is overdue at ``now`` (s, the arrival clock
        ``recv`` is on): a reading stamped there would have arrived ``slot_grace`` s ago at the
        train clock's offset (:class:`~.clocks.StreamClock`: its centre carried along its drift
        to that arrival). Bounded by the inputs: at most ``command_slack`` periods past the
        latest stamp queued (a command or a reading sent at or after it), so that silence on
        every input is not filled with predictions here (:meth:`ready_time` decides that).
        -inf before the train clock is known (:meth:`_judged`: until then the commands wait
        too)."""
        train = self._offsets.get("train")
        # (_judged("train"), on the clock in hand: asked at every tick)
        if train is None or not _known(train) or not math.isfinite(now) \
                or self._awaiting_commands():
            return -math.inf
        at = now - self.slot_grace
        due = at + train.value_at(at, train.drift)
        lead = max(self.high.get("control", -math.inf), self.high.get("odometer", -math.inf))
        return min(due, lead + self.command_slack * self.period)

    def _judged(self, clock: str) -> bool:
        """The clock's offset is known well enough to map commands onto it and to call a slot
        overdue: ``min_judged`` arrivals, or three that agree (the early hold's rule) -- at 1 Hz
        nine are nine seconds, and a reading lost in them was published only with the next one
        (a second late: not available)."""
        med = self._offsets.get(clock)
        return med is not None and _known(med)

    @guarded(lambda self, *a, **k: self._failed_outputs(*a, **k))
    def tick(self, now: float) -> list[Output]:
        """The estimates that became due by the arrival clock alone at ``now`` (s, as
        ``recv``): the nodes call it from a timer and after each message, the replays at the
        same arrival times.

        A lost reading's slot is otherwise published once the inputs' watermarks pass it
        (:meth:`ready_time`): with a 1 Hz odometer and 1 Hz commands, when the next message
        arrives, a second after the slot -- too late to use. Here every slot up to
        :meth:`due_time` is published, as :meth:`advance_to` publishes it: the items queued up
        to it processed first (the commands that arrived), a reading that did arrive fused and
        published at its own stamp, a lost one's slot predicted and assessed by the integrity
        monitor. A reading that arrives after its slot was predicted is fused by rewinding and
        shows in the next estimate: no slot is published twice or out of order. Nothing
        while the latest message came late (a backlog being caught up: its next messages are
        what the arrival clock would call overdue)."""
        if not self._started or self._last_out is None or self._backlog:
            return []
        due = self.due_time(now)
        if due <= self._last_out:
            return []
        return self.advance_to(due)

    @guarded(lambda self, *a, **k: self._failed_ready(*a, **k))
    def ready_time(self, now: float, delay: float, fallback: float,
                   wall: float | None = None) -> float:
        """Latest stamp (train clock) a live node can process at clock ``now`` without racing
        its inputs.

        Stamp t needs every reading stamped <= t. Each topic arrives in order, so the largest
        stamp queued per topic (its watermark) says how far that topic is complete. ``control``
        is not sent over the lossy link: its watermark leads. The odometer is complete up to
        its watermark, or -- when samples were lost -- up to ``fallback`` seconds behind the
        control watermark beyond how far it usually leads the readings (:meth:`_odometer_lag`:
        a slow link is no loss). A reading stamped no more than ``command_slack`` periods past the
        control watermark does not wait for the next command: a reading and a command sampled
        together on two clocks are mapped apart by the mapping's error (the two links'
        latencies, a drift not yet found), and a reading mapped a millisecond after its
        command waited a whole command period (1 s at 1 Hz: the estimate published too late
        to use). A command that does come later inside the slack is fused by rewinding; what
        it would have changed in the estimates already published is at most a quarter
        period of its acceleration (1.5 m/s^2 over 0.25 s at 1 Hz: 5 cm). Until a first
        command is queued, the readings wait for one (:meth:`_awaiting_commands`); a stream
        that sent none by then has the node's clock (``now - delay``, mapped onto the train
        clock through the odometer's offset) stand in for its watermark; once a command stream
        has been silent for ``command_timeout`` s the readings admitted lead, as they come.
        The command stream's silence is measured on ``wall`` (the clock push's ``wall`` is
        on; default ``now``): waiting is the node's. Driven by the data rather than by the
        clock, a node emits what the offline replay of the same messages emits, however the
        executor interleaves /clock and the subscriptions.
        """
        if self._awaiting_commands():
            return -math.inf
        train = self._offsets.get("train")
        now_train = now - delay + (train.value if train is not None and len(train) else 0.0)
        lead = self.high.get("control", now_train)
        odo = self.high.get("odometer", -math.inf)
        # silence on the arrival clock when arrivals are known: at 20x sim time a node's
        # 100 ms of wall jitter is 2 s of stamps, which must not make it run ahead of commands
        # that are on their way (the run would depend on the machine's load)
        silent = (now if wall is None else wall) - self._ctl_wall \
            if self._ctl_wall is not None else now_train - lead
        if "control" in self.high and silent > self.command_timeout:
            # the command stream stopped while readings go on: waiting for it would leave the
            # train without an estimate and the queue growing; the filters hold the last
            # command, the integrity monitor says DEGRADED (no_command). The readings admitted
            # lead instead, as they come: no command is awaited, and the node's clock is no
            # bound on them (without arrival times ``now`` is a stamp; on simulated time it
            # stands still once the world stops, and the last readings, stamped above the
            # clock less output_delay, waited for it for ever)
            lead = max(lead, odo)
        slack = self.command_slack * self.period if "control" in self.high else 0.0
        return min(lead + slack, max(odo, lead - fallback - self._odometer_lag()))

    def _odometer_lag(self) -> float:
        """s, how far the commands usually lead the odometer's readings as they come: the
        median of the last 31 leads of the control watermark over a reading's stamp as it was
        queued (0 when the readings lead). A slot is given up as lost ``fallback`` s beyond
        that: a link that delivers every reading 0.7 s after the commands of its cycle had each
        slot predicted before its reading came (``fallback`` 0.2 s), fused late, and every
        estimate published without a measurement (DEGRADED all run)."""
        s = self._lags_sorted  # (statistics.median's, on the leads kept in order: _lag)
        n = len(s)
        if not n:
            return 0.0
        return max(0.0, s[n // 2] if n % 2 else (s[n // 2 - 1] + s[n // 2]) / 2)

    def _lag(self, lead: float) -> None:
        """A lead of the control watermark into the last 31 (:meth:`_odometer_lag`), kept in
        order too: their median is asked at every message, the leads change with odometer
        readings only. (Of two equal leads, either may be the one dropped: 0.0 and -0.0
        alike give a lag of 0.)"""
        lags, s = self._lags, self._lags_sorted
        if len(lags) == lags.maxlen:
            del s[bisect.bisect_left(s, lags[0])]
        lags.append(lead)
        bisect.insort(s, lead)

    def _awaiting_commands(self) -> bool:
        """Whether the readings wait for the command stream, none of it queued yet: commands
        came and wait for their clock or the train's to be judged (where on the train clock
        they lie is not known yet: a reading processed now would be fused without the commands
        sampled before it), or none came and the readings queued span less than
        ``command_timeout`` s of their own stamps. Both are the data's, not the node's clock:
        the node's clock stood in for the missing watermark, and a node stalled for a moment at
        its start (on simulated time, the paced simulator 2 s ahead when it resumed) fused its
        first readings before the commands it had already received, then published estimates
        that a replay of the same messages does not (3e-8 m off under the brake's first
        command). The wait is bounded: the early hold ends by ``EARLY_CAP`` x ``min_judged``
        offsets, and a stream that sends no command costs its first ``command_timeout`` s of
        estimates a delay of as much, once."""
        if "control" in self.high:
            return False
        if self._held or self._early.get("control"):
            return True
        first = self._first_odometer
        return first is None or self.high["odometer"] - first < self.command_timeout

    def drain(self) -> list[Output]:
        """Process everything queued (offline use: the end of a replay): estimates up to the
        last item's stamp, but not past the train clock's present at the last arrival: its
        centre there, plus the step watch's bar (how far a reading's offset may lie above it
        before it is watched as ahead of its clock). An item stamped beyond (a corrupted stamp
        ahead, admitted within ``max_future``) is what a live node would process only once
        the present came to it, its slot's estimate published then; drained at the last
        arrival, predictions up to 2.6 s ahead were published as if the train were there
        already (a zone controller then granted the train behind an authority past this
        one's rear: 113 of 3,051 in a 50 Hz fuzz run). Not the ceiling of the offsets: a
        fuzzed stream's copies 5 s ahead had voted it there. Without arrival times, or with
        ``control_clock`` 'same' (a simulated clock that stalls under load stamps the
        readings seconds ahead of their arrivals), the last item's stamp."""
        if self._ahead:  # (commands held above a clock that its first instant set)
            self._judge_ahead(self._offsets[CLOCK_OF["control"]], force=True)
        if not self.queue:
            return []
        end = max(item[0] for item in self.queue)
        train = self._offsets.get("train")
        if math.isfinite(self._last_recv) and train is not None and len(train) and \
                not self._steps.same:
            now = self._last_recv
            end = min(end, now + train.now(now) + self._steps.bar(train))
        return self.advance_to(end)

    # -- failed (fail_safe) ----------------------------------------------------------------------
    def _failed_push(self, kind: str, stamp, fields=None, recv=None, wall=None) -> str:
        """A message after the failure: refused (counted), and an odometer reading's slot
        published as ALARM, stamped as the reading, in order after the last estimate, at the
        last estimate's position and speed (where the train was last known; ALARM bounds
        nothing: protection levels +inf, position and speed variances :data:`UNBOUNDED`),
        so that a consumer brakes at once rather than after its staleness timeout."""
        last = self._published
        if kind == "odometer" and last is not None and isinstance(stamp, float | int) \
                and math.isfinite(stamp) and stamp > last.stamp:
            C = list(last.covariance)
            C[0], C[1], C[4], C[5] = UNBOUNDED, 0.0, 0.0, UNBOUNDED
            self._published = changed(last, dict(
                stamp=float(stamp), covariance=tuple(C), measurement_used=False,
                integrity=INTEGRITY_ALARM, integrity_reason=f"{R.ESTIMATOR_FAILED}: "
                f"{self.failure}", protection_level_ahead=math.inf,
                protection_level_behind=math.inf, separation=(), consider=()))
            self._alarms.append(self._published)
        return self._reject(kind, stamp if isinstance(stamp, float | int) else math.nan,
                            R.ESTIMATOR_FAILED)

    def _failed_outputs(self, *_args, **_kw) -> list[Output]:
        out, self._alarms = self._alarms, []
        return out

    def _failed_ready(self, now: float, *_args, **_kw) -> float:
        return now

    def _failed_nothing(self, *_args, **_kw) -> None:
        return None

    def sample_period(self) -> float | None:
        """The odometer's sample period as its stamps and counter give it (s; None before the
        sample grid has ``min_judged`` samples): against :attr:`period`, what the node was told
        (``odometer_rate``). Without a counter (:meth:`_note_counter`): its stamps'
        (:meth:`~.clocks.StepWatch.stamp_period`)."""
        if self._steps is None:
            return None
        p = self._steps.grid.sample_period()
        if p is None and self._uncounted("odometer"):
            p = self._steps.stamp_period(self.min_judged)
        return p

    @property
    def counts(self) -> dict:
        """Accepted, rejected (by vocabulary name) and events, for logs and summaries."""
        return {"accepted": dict(self.accepted), "rejected": dict(self.rejected),
                "events": dict(self.events), "variance_unstated": dict(self.unstated),
                "seq_unstated": dict(self.uncounted), "stamp_unstated": self.unstamped}


class _Replayed:
    """A history entry's state as the settled copy (:meth:`EstimatorRunner.settle`) and the
    control calls ``(filter time, fields)`` the adapter was given after it, in order: restored,
    the copy, then the same calls."""

    __slots__ = ("base", "controls")

    def __init__(self, base, controls: tuple):
        self.base, self.controls = base, controls


@dataclass
class _CounterWatch:
    """What a train-clock stream's ``seq`` has shown so far (:meth:`EstimatorRunner.
    _note_counter`)."""

    seq: int  # the first reading's
    stamps: set  # distinct stamps of readings with that seq (up to UNCOUNTED_AFTER)
    first: float  # s, earliest and latest arrival of those readings
    last: float
    others: int = 0  # readings with another seq
    state: str = ""  # "", "counted" or "uncounted"


def _known(med: StreamClock) -> bool:
    """:meth:`EstimatorRunner._judged` on the clock itself: ``min_judged`` offsets, or three
    that agree."""
    return med.judged or (len(med) >= 3 and med.near(med.value) >= 3)


def _copy_key(fields: dict, stamp: float) -> tuple:
    """What makes a reading a copy of another: the same seq, stamp and values. Without a
    counter (seq None) a backward clock step sends a new sample at a stamp already taken, with
    the count and speed of its own time; with one, two messages of one seq and stamp whose
    values differ are not copies but one sample and a corruption of it, and the filters judge
    both (a copy key without the values let a corrupted copy that came first, and was refused
    by the gate, refuse the true sample after it as its duplicate)."""
    get = fields.get
    return (get("seq"), stamp, get("distance"), get("speed"), get("balise_id"), get("position"),
            get("target_acceleration"))


def _sample_key(fields: dict):
    """An odometer reading's sample: its seq, or without a counter (seq None) its values."""
    seq = fields.get("seq")
    return ("values", fields.get("distance"), fields.get("speed")) if seq is None else seq


def _agreeing(items: list, e: tuple, tol: float, uncounted=frozenset()) -> int:
    """How many distinct samples among the early hold's ``items`` (kind, stamp, fields, recv,
    arrival) have offsets (stamp - arrival) within ``tol`` of ``e``'s: a reading counts once per
    sequence number, any other item once per stamp. Copies of one corrupted message, or of
    one sample at a wrong stamp, are one piece of evidence however often they come (the fuzz
    mix sent a reading's copy 5 s ahead three times in its first second, and the early hold
    took them for a clock of their own). A stream without a counter (``uncounted``: its
    kinds) counts once per stamp."""
    off = e[1] - e[4]
    keys = set()
    for k, st, f, _, ar in items:
        if abs(st - ar - off) <= tol:
            seq = f.get("seq") if isinstance(f, dict) and k not in uncounted else None
            keys.add((k, seq) if isinstance(seq, int) else (k, "stamp", round(st, 6)))
    return len(keys)
