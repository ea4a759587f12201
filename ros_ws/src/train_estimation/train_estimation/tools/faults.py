"""Fault injection and integrity scoring for the estimators (pure; used by
``benchmarks/bench_integrity.py`` and the tests).

A clean run (the simulator's ``(topic, t, fields)`` events, ``t`` the true sampling time) is turned
into what a node would receive, ``(topic, stamp, fields, recv)`` in arrival order, with one
:class:`Fault` applied:

===============  ========================================================================
kind             ``size``
===============  ========================================================================
none             (the clean stream)
stamp            s added to the stamps of ``count`` consecutive odometer readings from ``at``
                 (a flipped bit, a sender's bad clock read): the readings stay where they are
                 in the stream, only their stamps lie
step             s by which the train clock (odometer and balise stamps) jumps at ``at`` and
                 stays (a clock set by GPS or NTP, a reboot)
drift            s/s: the train clock runs at ``1 + size`` against the reference (control and
                 arrival) clock, from the start
outage           s without odometer or balise readings from ``at`` (a tunnel, a dead radio)
command_stop     (none): no control message from ``at`` on, odometer readings go on
latency          s: largest link latency of odometer and balise readings from ``at`` on; the
                 latency is ``LATENCY`` s times a Pareto(1.5) factor (1 % above 1 s, 0.1 %
                 above 5 s), capped at ``size``; the stream is then in arrival order
queue            r (> 1): every ``QUEUE_EVERY`` s from ``at`` on the link holds the odometer and
                 balise readings for ``QUEUE_BACKLOG`` s, then delivers the queue ``r`` times
                 as fast as it was sampled: a reading sampled ``u`` s into an episode comes
                 ``QUEUE_BACKLOG - u (1 - 1 / r)`` s later (a congested radio cell, a modem
                 that retransmits); stamps and values untouched
route            s: from ``at`` on the odometer and balise readings come ``size`` s later and
                 stay so (the link changed its route: a handover, a satellite path, a
                 congested backhaul); stamps and values untouched
wander           s: from ``at`` on each topic's link (the commands' too, on its own) adds a
                 latency that wanders: an Ornstein-Uhlenbeck process of ``size`` s standard
                 deviation and ``WANDER_TAU`` s correlation time, folded to stay above the
                 floor (a loaded host, a radio link whose quality drifts); stamps and values
                 untouched
recorder_stall   s: odometer and balise readings arriving in ``[at, at + size)`` are logged at
                 ``at + size`` (the recorder's subscription blocked; commands unaffected)
node_stall       s: every message arriving in ``[at, at + size)`` is taken at ``at + size``
                 (the node's callbacks blocked, then the backlog in one burst)
fuzz             mean corrupted messages per clean one: :func:`~.fuzz.corrupt` with stamps
                 inside ``max_future`` too (:data:`INSIDE_FUTURE`) besides its own
balise           m: the first balise read at or after ``at`` lies ``size`` m further on than
                 the map and its telegram say (a survey error): it is read when the train has
                 run ``size`` m more (timed by the odometer's distance), reporting the map's
                 position with its usual variance
count_rate       fraction: from ``at`` on the odometer's count advances ``size`` times the
                 distance run while its speed reads true (0: a distance register that froze,
                 the speed from another path; 0.5: one that lost one of its two pulse
                 channels); each reading within its noise of the last one's course
stuck            (none): from ``at`` on every odometer reading repeats the last count before
                 ``at`` and reads standstill (a sensor that stopped), while the train runs on
seq_skip         samples: from ``at`` on the odometer's sample counter (``seq``) runs ``size``
                 ahead (< 0: behind) of the samples taken (a sampling loop that missed a cycle
                 and counted it); stamps, values and arrivals are untouched
reboot           s: the odometer reboots at ``at``: no reading for ``size`` s, then its counter
                 and its distance begin again from the boot (``at + size / 2``), as a sensor
                 that restarted counts (balises and commands unaffected)
odometer_scale   fraction: from ``at`` on the odometer counts ``1 + size`` times the distance
                 run and reads ``1 + size`` times the speed (a worn or mis-set wheel
                 diameter; 0.01 = 1 %); the distance is continuous at ``at``
first_count      m: every odometer distance is ``size`` m more than the distance run (a count
                 not reset at the start, data from mid-run): the train is at
                 ``initial_position`` with a first count of ``size``
rounded          m: every odometer distance is rounded to a grid of ``size`` m and its speed to
                 whole km/h (a recorder that logs whole metres, or decimetres, and km/h)
start_offset     m: the stream is clean, the estimator's ``initial_position`` is ``size`` m
                 off the train's (:func:`start_position`; the count's zero is where the train
                 truly started)
===============  ========================================================================

Any kind can run on links whose latency wanders as well (``Fault.wander``, s: the kind
``wander``'s process, from the start; drawn after each message's other draws, so that a fault
without it draws as before).
Any kind can run on a jittery link: ``Fault.jitter`` (s) adds an exponential extra latency of
that mean to every odometer and balise reading, so that arrivals leave sending order; and with a
clock that steps at its onset: ``Fault.clock_step`` (s; a unit that rebooted with its clock).

Clocks: odometer and balise are stamped by the train clock ``EPOCH + t (1 + drift)`` plus the
steps so far (:class:`TrainClock`); control by the reference clock ``EPOCH + t``; the arrival is
``EPOCH + t + LATENCY`` (the same epoch on both clocks, which the runner's default
``control_clock: auto`` takes as one clock until the drift or a step says otherwise).

:func:`score` judges the estimates as a zone controller would read them: an estimate claims
``position`` at the time its stamp means on the train clock (:meth:`TrainClock.true_time`) as it
could be known when the estimate was published (a step from the arrival of its first reading on:
:meth:`TrainClock.known_at`), and it
is *wrong-side* when it says integrity OK (0) while ``|error| > WRONG_SIDE_M`` and
``|error| > WRONG_SIDE_SIGMAS`` standard deviations of its published position variance (or the
variance is not a positive finite number, or the position is not finite).
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field, replace

import numpy as np

from train_estimation.core import reasons as R

from .fuzz import STAMPS, corrupt

EPOCH = 1.7e9  # s, both clocks at start (a Unix time)
LATENCY = 0.05  # s, link latency of every message in the clean stream
WRONG_SIDE_M = 1.0  # m: smaller errors are never a hazard, whatever the covariance says
WRONG_SIDE_SIGMAS = 5.0  # published standard deviations
STANFORD_EDGES = np.logspace(-2.0, 4.0, 61)  # m, bins of |error| and protection level
START_SLOTS = 2  # odometer slots of a run's start-up, not counted in ``availability``
AVAILABLE_LAG = 1.0  # s: an OK estimate published further from the time it claims is not
#   available (counted in ``availability``)
TRAIN_TOPICS = ("odometer", "balise")
QUEUE_EVERY = 30.0  # s between the starts of two episodes of the "queue" kind
QUEUE_BACKLOG = 1.0  # s, the delay of the first reading of an episode ("queue")
WANDER_TAU = 20.0  # s, the correlation time of a link's wandering latency ("wander")
KINDS = ("none", "stamp", "step", "drift", "outage", "command_stop", "latency", "queue", "route",
         "recorder_stall",
         "node_stall", "fuzz", "balise", "odometer_scale", "stuck", "seq_skip", "reboot",
         "first_count", "start_offset", "rounded", "count_rate", "wander")
# stamps a few seconds to minutes off: inside the runner's max_future (600 s), so the door lets
# them in and only the clocks' and the filters' own checks stand between them and the estimate
INSIDE_FUTURE = {
    "stamp+0.5": (0.5, (R.OUTSIDE_GATE, R.OUT_OF_ORDER, R.DUPLICATE, R.FUTURE_STAMP)),
    "stamp+5": (5.0, (R.OUTSIDE_GATE, R.OUT_OF_ORDER, R.FUTURE_STAMP)),
    "stamp+60": (60.0, (R.OUTSIDE_GATE, R.OUT_OF_ORDER, R.FUTURE_STAMP)),
    "stamp+300": (300.0, (R.OUTSIDE_GATE, R.OUT_OF_ORDER, R.FUTURE_STAMP)),
    "stamp-5": (-5.0, (R.OUT_OF_ORDER, R.STALE_STAMP, R.OUTSIDE_GATE)),
}


@dataclass(frozen=True)
class TrainClock:
    """The train clock: ``epoch + t (1 + drift) + (sum of the steps at or before t)``."""

    epoch: float = EPOCH  # s
    drift: float = 0.0  # s/s
    steps: tuple[tuple[float, float], ...] = ()  # (true time s, jump s), in time order
    seen: tuple[float, ...] = ()  # s, true arrival of each step's first train-clock reading
    #   (inf: none arrived); empty: every step known from its instant on

    def known_at(self, arrival: float) -> TrainClock:
        """The clock as a reader of the train's messages can know it at true time ``arrival``:
        without the steps none of whose readings had arrived by then. Before a step's first
        reading arrives nothing tells of it (commands run on the reference clock), and an
        estimate predicted for a lost reading's slot is stamped on the clock in force -- as a
        zone controller reading it at that time maps it too."""
        if not self.seen:
            return self
        return replace(self, steps=tuple(st for st, s in zip(self.steps, self.seen)
                                         if s <= arrival + 1e-6), seen=())

    def offset(self, t: float) -> float:
        return sum(j for ts, j in self.steps if t >= ts)

    def stamp(self, t: float) -> float:
        return self.epoch + t * (1.0 + self.drift) + self.offset(t)

    def true_time(self, s: float, near: float) -> float:
        """The true time a train-clock stamp ``s`` stands for, for an estimate published at true
        time ``near``. Each clock segment (between steps) inverts ``s``; after a backward step
        two segments can both contain it, and the one nearer ``near`` is meant (an estimate is of
        a recent sample). A segment includes the instant of the step that ends it: the estimate
        of the slot after the old clock's last sample, predicted at the old clock's next stamp,
        means that instant. A stamp in no segment (a corrupted one) is read on the clock in force
        at ``near``: it claims that time."""
        valid, current = self._meanings(s, near)
        if valid:
            return min(valid, key=lambda t: abs(t - near))
        return current

    def meanings(self, s: float, near: float) -> list:
        """Every true time the stamp ``s`` stands for (one, or two or more after a backward
        step), nearest to ``near`` first."""
        valid, current = self._meanings(s, near)
        return sorted(valid, key=lambda t: abs(t - near)) if valid else [current]

    def _meanings(self, s: float, near: float):
        bounds = [-math.inf] + [ts for ts, _ in self.steps] + [math.inf]
        valid, current = [], None
        for k in range(len(bounds) - 1):
            off = sum(j for _, j in self.steps[:k])
            t = (s - self.epoch - off) / (1.0 + self.drift)
            if bounds[k] <= t <= bounds[k + 1]:
                valid.append(t)
            if bounds[k] <= near < bounds[k + 1]:
                current = t
        return valid, current


@dataclass(frozen=True)
class Fault:
    kind: str = "none"  # one of KINDS
    size: float = 0.0  # meaning per kind (module doc): s, s/s or messages per clean one
    at: float = 0.0  # s, true time of onset
    count: int = 1  # readings affected ("stamp")
    jitter: float = 0.0  # s, mean of an exponential extra latency of every odometer and balise
    #   reading, whatever the kind (a jittery link: arrivals then no longer keep sending order)
    clock_step: float = 0.0  # s by which the train clock steps at ``at`` as well, whatever the
    #   kind (a unit that rebooted with its clock; the kind ``step`` is this alone)
    wander: float = 0.0  # s, a wandering latency on every topic's link from the start, whatever
    #   the kind (the kind ``wander`` is this alone, from ``at``)
    again: float = 0.0  # s after ``at``: a reboot (with its clock step) happens once more
    #   (0: once; a unit that fails twice before a balise can tell the first)

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"unknown fault kind {self.kind!r} (one of {', '.join(KINDS)})")

    @property
    def label(self) -> str:
        if self.kind in ("none", "command_stop", "stuck"):
            return self.kind + (f" jitter {self.jitter:g}" if self.jitter else "")
        n = f" x{self.count}" if self.kind == "stamp" and self.count != 1 else ""
        n += f" clock {self.clock_step:+g}" if self.clock_step else ""
        n += f" jitter {self.jitter:g}" if self.jitter else ""
        n += f" wander {self.wander:g}" if self.wander else ""
        n += f" again {self.again:g}" if self.again else ""
        return f"{self.kind} {self.size:+g}{n}" if self.kind in ("stamp", "step", "drift",
                                                                   "balise", "odometer_scale",
                                                                   "seq_skip") \
            else f"{self.kind} {self.size:g}{n}"


@dataclass
class Faulted:
    events: list  # (topic, stamp, fields, recv) in arrival order
    clock: TrainClock
    onset: float  # s, true time the fault starts
    end: float  # s, true time it ends (inf: persists)
    counts: Counter = field(default_factory=Counter)  # corrupted messages by kind ("fuzz")
    stalled: tuple = ()  # (t0, t1) s, true times in which the node's callbacks are blocked


def uncounted(events: list) -> list:
    """``events`` (``(topic, t, fields, ...)``) as a producer without a sample counter sends
    them: every train reading's ``seq`` 0."""
    return [(e[0], e[1], {**e[2], "seq": 0}) + tuple(e[3:])
            if e[0] in TRAIN_TOPICS and isinstance(e[2], dict)
            and isinstance(e[2].get("seq"), int) else e for e in events]


def noisy_count(events: list, sigma: float, rng: np.random.Generator) -> list:
    """``events`` (``(topic, stamp, fields, ...)``) with ``sigma`` m of white Gaussian noise on
    every odometer distance: a producer whose count is read with noise (a count interpolated
    between pulses, a distance from a noisy speed), which the contract does not state. The
    noise is the count's, not the stamps': a clock step of less than about ``5 sigma / v``
    then hides in it (:meth:`~train_estimation.core.numerics.clocks.StepWatch._level_test`)."""
    return [(e[0], e[1], {**e[2], "distance": e[2]["distance"] + rng.normal(0.0, sigma)})
            + tuple(e[3:]) if e[0] == "odometer" and isinstance(e[2], dict)
            and isinstance(e[2].get("distance"), float) else e for e in events]


def wandered(state: dict, key, t: float, size: float, rng: np.random.Generator,
             tau: float = WANDER_TAU) -> float:
    """s, the extra latency at true time ``t`` of the link ``key`` whose latency wanders
    (``wander``): an Ornstein-Uhlenbeck process of ``size`` s standard deviation and ``tau`` s
    correlation time, exact over the time since the link's last message (``state``: key ->
    (that time, the process there), updated), folded to stay above the link's floor."""
    t0, x = state.get(key, (t, rng.normal(0.0, size)))
    a = math.exp(-max(t - t0, 0.0) / tau)
    x = a * x + rng.normal(0.0, size * math.sqrt(1.0 - a * a))
    state[key] = (t, x)
    return abs(x)


def inject(events: list, fault: Fault, rng: np.random.Generator) -> Faulted:
    """The received stream of a clean run ``events`` = ``(topic, t, fields)`` (true time ``t``)
    with ``fault`` applied (module doc). Topics other than control, odometer and balise are
    left out."""
    k, size, at = fault.kind, fault.size, fault.at
    onsets = (at, at + fault.again) if k == "reboot" and fault.again > 0 else (at,)
    clock = TrainClock(drift=size if k == "drift" else 0.0,
                       steps=((at, size),) if k == "step" else
                       tuple((o, fault.clock_step) for o in onsets) if fault.clock_step
                       else ())
    rows = []  # [topic, t, fields, stamp error, true arrival]
    hit = 0
    d_at = None  # m, the odometer's distance at ``at`` ("odometer_scale")
    # the odometer's reading at its boot ("reboot"): what its restarted counter and count start
    # from
    boots = [next((f for tp, tt, f in events if tp == "odometer" and tt >= o + 0.5 * size),
                  None) for o in onsets] if k == "reboot" else []
    wander: dict = {}  # topic -> (true time s, its link's wander s) of its last message
    w_size, w_at = (size, at) if k == "wander" else (fault.wander, 0.0)
    for topic, t, fields in events:
        if topic not in ("control",) + TRAIN_TOPICS:
            continue
        if k == "first_count" and topic == "odometer":
            fields = dict(fields, distance=fields["distance"] + size)
        if k == "rounded" and topic == "odometer":
            fields = dict(fields, distance=round(fields["distance"] / size) * size,
                          speed=round(fields["speed"] * 3.6) / 3.6)
        if k == "odometer_scale" and topic == "odometer" and t >= at:
            d_at = fields["distance"] if d_at is None else d_at
            fields = {**fields, "distance": d_at + (1.0 + size) * (fields["distance"] - d_at),
                      "speed": (1.0 + size) * fields["speed"]}
        if k == "stuck" and topic == "odometer":
            if t < at:
                d_at = fields["distance"]
            else:
                d_at = fields["distance"] if d_at is None else d_at
                fields = {**fields, "distance": d_at, "speed": 0.0}
        if k == "count_rate" and topic == "odometer" and t >= at:
            d_at = fields["distance"] if d_at is None else d_at
            fields = {**fields, "distance": d_at + size * (fields["distance"] - d_at)}
        if k == "seq_skip" and topic == "odometer" and t >= at and "seq" in fields:
            fields = {**fields, "seq": fields["seq"] + int(size)}
        if k == "reboot" and topic == "odometer" and t >= at:
            j = max(i for i, o in enumerate(onsets) if o <= t)  # the latest boot
            if t < onsets[j] + size:
                continue  # booting
            fields = {**fields, "seq": fields["seq"] - boots[j]["seq"],
                      "distance": fields["distance"] - boots[j]["distance"]}
        train = topic in TRAIN_TOPICS
        if k == "outage" and train and at <= t < at + size:
            continue
        if k == "command_stop" and topic == "control" and t >= at:
            continue
        err = 0.0
        if k == "stamp" and topic == "odometer" and t >= at and hit < fault.count:
            err, hit = size, hit + 1
        if k == "balise" and topic == "balise" and t >= at and not hit:
            t, hit = _when_run(events, t, size), 1
        recv = t + LATENCY
        if k == "latency" and train and t >= at:
            recv = t + min(size, LATENCY * (1.0 + rng.pareto(1.5)))
        if fault.jitter and train:
            recv += rng.exponential(fault.jitter)
        if k == "queue" and train and t >= at:
            u, slope = (t - at) % QUEUE_EVERY, 1.0 - 1.0 / size
            if u * slope < QUEUE_BACKLOG:
                recv += QUEUE_BACKLOG - u * slope
        if k == "route" and train and t >= at:
            recv += size
        if w_size > 0.0 and t >= w_at:
            # each topic's own link (the commands' too): its latency wanders above the
            # floor, an Ornstein-Uhlenbeck process of ``w_size`` s and WANDER_TAU folded to
            # stay above it (a loaded host, a radio link whose quality drifts)
            recv += wandered(wander, topic, t, w_size, rng)
        if k == "recorder_stall" and train or k == "node_stall":
            if at <= recv < at + size:
                recv = at + size
        rows.append((topic, t, fields, err, recv))
    rows.sort(key=lambda r: r[4])  # arrival order (stable: equal arrivals keep sending order)
    if clock.steps:
        clock = replace(clock, seen=tuple(
            min((r[4] for r in rows if r[0] in TRAIN_TOPICS and r[1] >= ts),
                default=math.inf) for ts, _ in clock.steps))
    out = [(topic, (clock.stamp(t) if topic in TRAIN_TOPICS else EPOCH + t) + err, fields,
            EPOCH + recv) for topic, t, fields, err, recv in rows]
    counts: Counter = Counter()
    if k == "fuzz":
        out, counts = corrupt(out, rng, size, stamps={**STAMPS, **INSIDE_FUTURE})
    end = {"none": at, "stamp": at, "outage": at + size, "recorder_stall": at + size,
           "node_stall": at + size, "reboot": onsets[-1] + size}.get(k, math.inf)
    stalled = ((at, at + size),) if k == "node_stall" else ()
    return Faulted(out, clock, at, end, counts, stalled)


def _when_run(events: list, t: float, metres: float) -> float:
    """The true time at which the train has run ``metres`` more than at ``t`` (m, negative:
    less), by the odometer readings' distance (interpolated; clipped to the run)."""
    od = [(ti, f["distance"]) for topic, ti, f in events if topic == "odometer"]
    if len(od) < 2:
        return t
    ts, ds = (np.asarray(a, float) for a in zip(*od))
    d = float(np.interp(t, ts, ds)) + metres
    # the first time the odometer reaches d (distance never decreases on a forward run)
    return float(np.interp(d, np.maximum.accumulate(ds), ts))


class _Timed:
    """Adapter proxy that notes the arrival time at which each estimate was produced."""

    def __init__(self, adapter):
        self._a, self.now, self.emitted = adapter, math.nan, []
        self.taken = 0  # events the replay has taken so far
        self.after = []  # the events taken when each estimate was produced

    def output(self, t):
        self.emitted.append(self.now)
        self.after.append(self.taken)
        return self._a.output(t)

    def __getattr__(self, name):
        return getattr(self._a, name)


def stanford_counts(err: np.ndarray, pl: np.ndarray) -> np.ndarray:
    """The Stanford diagram's 2-D histogram (Tossaint et al., ION GNSS 2006): counts of
    ``(|error|, protection level)`` on :data:`STANFORD_EDGES` (rows: error, columns: level;
    values beyond the edges land in the first or last bin)."""
    lo, hi = STANFORD_EDGES[0], STANFORD_EDGES[-1] * 0.999
    e = np.clip(np.nan_to_num(np.abs(err), nan=hi, posinf=hi), lo, hi)
    p = np.clip(np.nan_to_num(pl, nan=hi, posinf=hi), lo, hi)
    h, _, _ = np.histogram2d(e, p, bins=(STANFORD_EDGES, STANFORD_EDGES))
    return h.astype(np.int64)


def plot_stanford(counts: np.ndarray, alert_limit: float, title: str, path) -> dict:
    """Draw a Stanford diagram (|error| against protection level, log-log, the diagonal and
    the alert limit marked) into ``path``; returns the counts per region: ``nominal`` (error
    within the level, level within the limit), ``unavailable`` (level beyond the limit),
    ``misleading`` (error beyond the level), ``hazardous`` (error beyond the level and the
    limit). Regions are judged on bin centres (the scores' exact counts are in the table)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = np.sqrt(STANFORD_EDGES[:-1] * STANFORD_EDGES[1:])
    E, P = np.meshgrid(c, c, indexing="ij")
    regions = {"nominal": int(counts[(E <= P) & (P <= alert_limit)].sum()),
               "unavailable": int(counts[(E <= P) & (P > alert_limit)].sum()),
               "misleading": int(counts[(E > P) & (E <= alert_limit)].sum()),
               "hazardous": int(counts[(E > P) & (E > alert_limit)].sum())}
    fig, ax = plt.subplots(figsize=(6.4, 5.2))
    masked = np.ma.masked_where(counts == 0, counts)
    mesh = ax.pcolormesh(STANFORD_EDGES, STANFORD_EDGES, masked, norm=matplotlib.colors.LogNorm(),
                         cmap="viridis", shading="flat")
    fig.colorbar(mesh, ax=ax, label="estimates")
    ax.plot(STANFORD_EDGES, STANFORD_EDGES, "k-", lw=1)
    ax.axvline(alert_limit, color="tab:red", lw=1, ls="--")
    ax.axhline(alert_limit, color="tab:red", lw=1, ls="--")
    ax.set(xscale="log", yscale="log", xlabel="protection level (m, larger side)",
           ylabel="|position error| (m)", title=title)
    ax.text(0.02, 0.97, f"misleading {regions['misleading']}\nhazardous {regions['hazardous']}",
            transform=ax.transAxes, va="top", fontsize=9)
    ax.text(0.97, 0.03, f"nominal {regions['nominal']}\nunavailable {regions['unavailable']}",
            transform=ax.transAxes, ha="right", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return regions


def start_position(fault: Fault, true_start: float) -> float:
    """m, the ``initial_position`` an estimator is given under ``fault`` (``start_offset``:
    ``size`` m off the train's true start; every other kind: the true start)."""
    return true_start + (fault.size if fault.kind == "start_offset" else 0.0)


def run(events: list, adapter, period: float, delay: float = 0.05, fallback: float = 0.2,
        tick_period: float | None = 0.05, stalled: tuple = (), **runner_kw):
    """``(outputs, emitted, runner)``: ``core.online.replay.replay`` itself (the runner the
    nodes use, its ticks at the node timer's times), with ``emitted[i]`` the arrival time (s,
    reference clock) of the message or timer tick after which ``outputs[i]`` was produced (the
    drain at the end: the last arrival; 2 us earlier where a train reading arriving at that
    same instant was taken after it). ``stalled``: ``(t0, t1)`` true-time intervals in which
    the node's callbacks are blocked (:attr:`Faulted.stalled`): its timer does not fire."""
    from train_estimation.core.online.replay import replay

    timed = _Timed(adapter)

    def at(t):
        timed.now = t

    def blocked(t):
        return any(t0 <= t - EPOCH < t1 for t0, t1 in stalled)

    def taken():
        for ev in events:
            timed.taken += 1
            yield ev

    out, runner = replay(taken(), timed, period, delay=delay, fallback=fallback,
                         tick_period=tick_period, on_time=at,
                         blocked=blocked if stalled else None, **runner_kw)
    # An estimate produced at the arrival instant of a train reading not yet taken (a command
    # arrived with it and was taken first, as the node takes them) was published before that
    # reading: just before its arrival time, so that a clock step it is the first reading of
    # is not known to it (TrainClock.known_at)
    em = np.array(timed.emitted, float)
    arrivals = [e[3] if len(e) > 3 else None for e in events]
    for i, (t, n) in enumerate(zip(timed.emitted, timed.after)):
        k = n
        while k < len(events) and arrivals[k] == t:
            if events[k][0] in TRAIN_TOPICS:
                em[i] = t - 2e-6
                break
            k += 1
    return out, em, runner


def _not_pd(C: np.ndarray) -> bool:
    if not np.all(np.isfinite(C)):
        return True
    try:
        np.linalg.cholesky(0.5 * (C + C.T))
        return False
    except np.linalg.LinAlgError:
        return True


def true_times(outs: list, em: np.ndarray, faulted: Faulted) -> tuple[list, np.ndarray]:
    """``(clocks, t)``: each estimate's stamp read on the train clock as known when it was
    published (``em``: reference seconds since EPOCH; :meth:`TrainClock.known_at`), and the
    true time (s since EPOCH) that stamp means on it."""
    clocks = [faulted.clock.known_at(e) for e in em]
    return clocks, np.array([c.true_time(o.stamp, e - LATENCY)
                             for c, o, e in zip(clocks, outs, em)], float)


def score(outs: list, emitted: np.ndarray, faulted: Faulted, truth: dict, rate: float,
          t_end: float, window: float = 10.0, alert_limit: float = 10.0) -> dict:
    """Integrity figures of one run's estimates (true times: reference seconds since EPOCH).

    - ``wrong_side``: OK estimates with a hazardous error (module doc), whole run; ``twice_given``:
      those not counted because their stamp is one the train clock gave twice within
      ``AVAILABLE_LAG`` (a backward step) and they are right for the other instant it means;
    - ``off_run``: OK estimates whose stamp means a time more than 1 s outside the simulated run
      (no truth to judge them by; a claim that cannot be right either);
    - ``hazards``: estimates, from the onset on, whose error exceeds the bound (whatever their
      integrity); ``tta``: from the first of them to the first non-OK estimate published at or
      after the onset (0 when the alarm came first; inf: never; NaN: no hazard);
    - ``availability``: OK estimates (both protection levels within the alert limit) published
      from the onset on (after the run's first ``START_SLOTS`` slots: the start-up), within
      ``AVAILABLE_LAG`` of the time they claim, over the odometer slots of that time (at most
      1); ``clear``: the same of the estimates no check of the integrity monitor doubts (not
      ALARM, empty ``integrity_reason``: no widening, no live hypothesis; what the tests of
      each check judge, whatever the alert limit); ``silence``: the
      longest time without an estimate from the onset on;
    - ``max_err``/``rms_err``: |position error| from the onset on; ``window_err``: the largest
      |error| from the onset to ``window`` s after the fault's end;
    - ``bad_cov``: estimates whose position/velocity covariance is not positive definite
      (negative or non-finite variances included);
    - ``misleading``: estimates not in ALARM whose error lies beyond their protection level
      on its side (``protection.py``; the true position outside ``[x - behind, x + ahead]``),
      whole run; ``hazardous``: OK estimates (both levels within ``alert_limit``) whose
      |error| exceeds ``alert_limit``; ``pl_median``: the median of the larger protection
      level over the estimates not in ALARM (m).
    """
    n = len(outs)
    em = np.asarray(emitted, float) - EPOCH
    integ = np.array([o.integrity for o in outs], int)
    x = np.array([o.position for o in outs], float)
    C = [np.array(o.covariance, float).reshape(4, 4)[:2, :2] for o in outs]
    var = np.array([c[0, 0] for c in C], float)
    clocks, t = true_times(outs, em, faulted)
    tr_t, tr_x = np.asarray(truth["t"], float), np.asarray(truth["position"], float)
    inside = (t >= tr_t[0] - 1.0) & (t <= tr_t[-1] + 1.0)  # (else off-run, if said OK)
    # judged where the truth is known: before its first time the train stands where it starts
    # (a run begins at rest); after its last the truth is not known, and held at its last value
    # it read a moving train's correct estimates as off by its travel (83 m/s on
    # crh3_high_speed: estimates stamped past the run's end counted misleading)
    known = (t >= tr_t[0] - 1.0) & (t <= tr_t[-1])
    err = np.full(n, np.nan)
    err[known] = x[known] - np.interp(t[known], tr_t, tr_x)
    a = np.abs(err)
    with np.errstate(invalid="ignore"):
        sigma = np.sqrt(np.where(var > 0, var, np.nan))
        # beyond the bound, or no bound at all (NaN position, variance <= 0 or NaN)
        beyond = (a > WRONG_SIDE_M) & ~(a <= WRONG_SIDE_SIGMAS * sigma)
        hazard = known & (~np.isfinite(a) | beyond)
    ok = integ == 0
    # no doubt: bounded, and no check of the monitor doubts it (no widening, no live hypothesis)
    clear = (integ != 2) & np.array([not getattr(o, "integrity_reason", "") for o in outs], bool)
    # A stamp the train clock gave twice within AVAILABLE_LAG (a backward step of less than
    # that, at its edge): no reader can tell which instant it means, and the estimate of one
    # of them is not judged by the other; counted apart (``twice_given``), not wrong-side
    twice = np.zeros(n, bool)
    if faulted.clock.steps:
        for i in np.flatnonzero(ok & hazard):
            ts = clocks[i].meanings(outs[i].stamp, em[i] - LATENCY)
            alt = [u for u in ts[1:] if abs(u - ts[0]) <= AVAILABLE_LAG]
            for u in alt:
                e = x[i] - np.interp(u, tr_t, tr_x)
                if abs(e) <= WRONG_SIDE_M or abs(e) <= WRONG_SIDE_SIGMAS * sigma[i]:
                    twice[i] = True
    hazard &= ~twice
    ahead = np.array([getattr(o, "protection_level_ahead", math.inf) for o in outs], float)
    behind = np.array([getattr(o, "protection_level_behind", math.inf) for o in outs], float)
    bounded = (integ != 2) & known & ~twice
    with np.errstate(invalid="ignore"):
        misleading = bounded & (~np.isfinite(err) | (err < -ahead) | (err > behind))
        hazardous = ok & known & ~twice & ~(a <= alert_limit)
    pl = np.maximum(ahead, behind)[integ != 2]
    after = em >= faulted.onset
    h = np.flatnonzero(hazard & after)
    alarms = np.flatnonzero(~ok & after)
    if h.size == 0:
        tta = math.nan
    elif alarms.size == 0:
        tta = math.inf
    else:
        tta = max(0.0, float(em[alarms[0]] - em[h[0]]))
    # availability from the onset, but not over the start-up: the runner starts on the run's
    # third odometer reading (one corrupted first stamp must not start it in the past), so the
    # first START_SLOTS slots are published with it, late by design and not by a fault
    a_from = max(faulted.onset, float(tr_t[0]) + START_SLOTS / rate)
    span = max(t_end - a_from, 1.0 / rate)
    # an estimate is of use when it is published near the time it claims (not a backlog
    # published at once, nor a claim about a time far ahead)
    timely = np.abs(em - LATENCY - t) <= AVAILABLE_LAG
    e_after = a[after & np.isfinite(a)]
    tight = _tightness(em, t, a, ahead, behind, integ, faulted, tr_t, tr_x)
    w = after & (em <= faulted.end + window) & np.isfinite(a)
    stamps_after = np.concatenate([[faulted.onset], em[after], [t_end]])
    return dict(
        outputs=n, wrong_side=int(np.sum(ok & hazard)), twice_given=int(np.sum(twice)),
        off_run=int(np.sum(ok & ~inside)),
        hazards=int(h.size), tta=tta,
        availability=min(1.0, float(np.sum(ok & (em >= a_from) & timely))
                         / max(1.0, math.floor(span * rate))),
        clear=min(1.0, float(np.sum(clear & (em >= a_from) & timely))
                  / max(1.0, math.floor(span * rate))),
        silence=float(np.max(np.diff(stamps_after))) if stamps_after.size > 1 else span,
        max_err=float(e_after.max()) if e_after.size else math.nan,
        rms_err=float(np.sqrt(np.mean(e_after ** 2))) if e_after.size else math.nan,
        window_err=float(a[w].max()) if np.any(w) else math.nan,
        bad_cov=int(sum(_not_pd(c) for c in C)),
        misleading=int(np.sum(misleading)), hazardous=int(np.sum(hazardous)),
        pl_median=float(np.median(pl)) if pl.size else math.inf,
        stanford=stanford_counts(a[bounded], np.maximum(ahead, behind)[bounded]),
        max_ratio=float(np.nanmax(np.where(ok & hazard, a / sigma, np.nan)))
        if np.any(ok & hazard & np.isfinite(sigma)) else math.nan,
        **tight,
    )


ETCS_LOCACC = 1.0  # m, a balise group's location accuracy (ETCS Q_LOCACC) in the comparison


def _tightness(em, t, a, ahead, behind, integ, faulted, tr_t, tr_x) -> dict:
    """What the protection levels are worth, over the estimates published after the first
    balise reached the estimator: ``p95_err`` (m, |error|), ``pl_p50`` (m, the median of the
    larger level; ALARM counts as +inf), ``al99`` (m, the alert limit at which 99 % of them
    would be OK: the 99th percentile of the larger level) and ``etcs_p50`` (m, the median of
    ETCS's confidence interval at the same points: ``ETCS_LOCACC`` + 1 % of the true distance
    run since the last balise read)."""
    nan = dict(p95_err=math.nan, pl_p50=math.nan, al99=math.nan, etcs_p50=math.nan)
    bal = sorted((float(rc) - EPOCH, float(f["position"])) for tp, _, f, rc in faulted.events
                 if tp == "balise" and isinstance(f, dict)
                 and np.isfinite(f.get("position", np.nan)))
    if not bal:
        return nan
    sel = (em >= bal[0][0]) & np.isfinite(a)
    if not np.any(sel):
        return nan
    pl = np.where(integ == 2, math.inf, np.maximum(ahead, behind))[sel]
    read_t = np.array([b[0] for b in bal])
    read_x = np.interp(read_t, tr_t, tr_x)  # where the train was when each was read
    last = np.searchsorted(read_t, em[sel], side="right") - 1
    run = np.abs(np.interp(t[sel], tr_t, tr_x) - read_x[np.maximum(last, 0)])
    # quantiles taken at an estimate (no interpolation: a level may be +inf, in ALARM)
    return dict(p95_err=float(np.percentile(a[sel], 95)),
                pl_p50=float(np.quantile(pl, 0.5, method="higher")),
                al99=float(np.quantile(pl, 0.99, method="higher")),
                etcs_p50=float(np.median(ETCS_LOCACC + 0.01 * run)))
