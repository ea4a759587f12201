"""The train clock online (pure; docs/integrity.md, "The clock model's named parameters").

:class:`StreamClock` follows one clock's offset against the arrival clock and (for the train
clock) its rate, one reading at a time, as the
:class:`~train_estimation.core.online.runner.EstimatorRunner` admits them (its offline
counterpart, the least-squares fit a bag is read through, is ``core/offline/clock_fit.py``);
:class:`SampleGrid` is the train's sample grid, odometer stamps against their sample counter;
and :class:`StepWatch` watches the train clock for steps (a reboot, a resynchronisation) with
its step test :func:`is_step`, telling the runner what to do with each train-clock reading.
Both wings judge lateness by the one rule below.

Lateness, the one rule. Latency is never negative, so ``stamp - arrival`` of a reading can only
fall below where its clock is. A reading whose ``stamp - arrival`` lies more than ``LATE`` s
below its clock's centre (online: the robust centre of the recent offsets; offline: the fit,
i.e. a log time more than ``LATE`` s after the fitted one -- the same quantity with the sign
turned) *came late*: a backlog after a stalled recorder or node, a retried packet. Its arrival
says how late it came, not where its clock is: it does not vote for the offset, does not inform
the rate, and is left out of the offline fit. ``LATE`` is above a radio's jitter (p99 of 20 ms +
Exp(50 ms) is 0.25 s) and below the stalls worth excluding (seconds). Online the window is too
short to measure a tail, so the bar is ``LATE``.
"""

from __future__ import annotations

import bisect
import functools
import math
from collections import deque

import numpy as np

from . import envelope
from .special import chdtrc, fdtrc, lambertw, ndtr, stdtrit

LATE = 0.5  # s: a reading this much later than its clock says came late (module doc)


def median(a) -> float:
    """``np.median`` of a non-empty 1-D float array, the same number (the middle order
    statistic, or the two middle ones' sum halved; NaN if any entry is NaN), without its generic
    axis machinery: ~15 us a call less, and the sample grid is refitted at every reading."""
    a = np.sort(np.asarray(a, dtype=float))  # NaN sorts last
    n = a.size
    if math.isnan(a[-1]):
        return math.nan
    h = n // 2
    return float(a[h]) if n % 2 else float((a[h - 1] + a[h]) / 2.0)


def _median_sorted(a: list) -> float:
    """:func:`median` of a sorted non-empty list of floats without NaN (the same number)."""
    n = len(a)
    h = n // 2
    return a[h] if n % 2 else (a[h - 1] + a[h]) / 2.0


TREND_WAIT = 0.05  # -, a held step's rank trend towards its old clock at which its decision
#   waits for more readings (StepWatch._returning): a true step waits with this probability
TREND_N = 64  # held readings at most in that rank test (its cost grows as their square)
TIE = 1e-3  # s: offsets closer than this (or than the arrivals' resolution) have no order
SMALL_MOVE = 0.05  # s: the least move of a clock's offset level taken as one (the runner's
#   small_step); smaller moves are jitter and drift
MAX_SPEED = 200.0  # m/s, beyond any train (720 km/h): a reading claiming more is corrupt
# The odometer's count as a clock (StepWatch._count_resid): moving, the time between two samples
# is twice their count's difference over the sum of their speeds (exact at constant
# acceleration), whatever the link did to their arrivals
COUNT_Z = 5.0  # standard deviations of the count's residual (learnt, robust) beyond which a
#   reading's stamp is off its clock (a Gaussian's two-sided tail: 6e-7 per reading)
COUNT_MIN_SPEED = 1.0  # m/s: below this mean speed of two samples the count times them too
#   coarsely (the link's arrivals judge them, as without it)
COUNT_SPAN = 5.0  # s: the longest time one link of the count's chain spans (a lost reading or
#   two at 1 Hz); the trapezoid's error from a change of acceleration grows as its cube
COUNT_JERK = 1.0  # m/s^3, the rate of change of acceleration the trapezoid tolerates (a
#   passenger train's comfort limit is 0.5-1): at most jerk dt^3 / 12 of count between samples
COUNT_LAG = 0.5  # s, the prior standard deviation of the lag of the odometer's speed behind
#   its count (a filtered speed, a rate over a window of pulses) until brakings measure it
#   (_count_fit): a lag tau puts -tau ln(v1 / v0) into the time the count gives two samples
COUNT_LEARN = 16  # count residuals learnt at speed before the count judges stamps
COUNT_SLIP = 0.3  # -, the largest slip ratio of the wheel the count comes from: under braking
#   it slides and counts less than the train runs, in traction it spins and counts more (wheel-
#   slide and anti-slip protection hold 10-20 %, transients more); a reading the count puts off
#   its clock by less than this share of the stamps' time since the newest fused reading (and
#   its tolerance) may be the count's, not the stamp's (StepWatch._slip_room)
COUNT_GRIDS = (1.0, 0.5, 0.2, 0.1, 0.05, 0.02, 0.01, 0.005, 0.002, 0.001)  # m: the grids a
#   producer may round its count to (a recorder's whole metres or decimetres) (Grid)
STAMP_GRIDS = (1.0, 0.5, 0.1, 0.05, 0.01, 0.005, 0.001)  # s: and its stamps to (a log's
#   whole, tenths, hundredths or thousandths of seconds) (Grid)
SPEED_GRIDS = (1.0 / 3.6, 0.5 / 3.6, 0.1, 0.1 / 3.6, 0.01, 0.01 / 3.6, 0.001)  # m/s: and its
#   speed to (whole, half or tenths of km/h, tenths or hundredths of m/s) (Grid)
COUNT_ACCEL_SPAN = 2.0  # s of the count's links over which the train's acceleration is taken
#   (StepWatch._slip_room; clocks._accel): its noise against the lag it adds at a braking's onset
COUNT_SLIP_ACCEL = 0.2  # m/s^2, the least deceleration (acceleration) of a train whose braking
#   (traction) may exceed the rail's adhesion: 0.02 g, the worst wet, leaf-covered rail's
#   (the diagnose tool's MU_MIN); below it the wheel rolls and the count is a clock
LEVEL_WINDOW = 128  # the count's links over which its level is tested (StepWatch._level_test):
#   the readings before a candidate change give the level and its line (a speed a few per cent
#   off the count's rate tilts it), and at least LEVEL_PRE of them
LEVEL_PRE = 32
LEVEL_LLR = 4.5  # the log-likelihood ratio (2 ln LR 9: three of the arrivals' standard errors
#   between the two) at which the arrivals tell a step of the stamps from a move of the count,
#   where they can (StepWatch._level_test); where they cannot (a jittery link), the step
LEVEL_LEARN = 600  # links of steady stretches learnt before the count's level is tested: its
#   noise's spread to about 6 % and its correlation to about 0.15 (StepWatch._learn_noise; a
#   correlation read above the truth only widens the test's bar)
LEVEL_MEMORY = 3000  # links, the memory of that learning (5 min at 10 Hz)
LEVEL_SPAN = (3, 2.0)  # the fewest readings after a candidate change (one reading's spike, within
#   the count's tolerance, moves the mean of three by less than the test's bar) and the longest
#   time (s) after it that the test looks back, within the runner's history, which it re-stamps
SEG_MIN = 4  # the rate fit's points off its line that can start a segment of it (StreamClock._off)
SEG_RISK = TREND_WAIT  # -, the rate at which a true move of the line's level is held for one
#   more point: its points scatter about one level as the line's own (chi-square at this risk)
LINE_SPREAD = 5.0  # robust spreads of the offsets: a rate fit whose points scatter wider about
#   their line than this (and SMALL_MOVE) mixes two levels and is not used
DIP_REF = 0.5  # the rate fit's standard errors of a point: half the least dip of its envelope
#   (a latency that rises for a while) it watches for, the CUSUM's reference (StreamClock._off)
DIP_RISK = 1e-4  # -, per point: the rate at which the fit's clean points start a false dip
#   (then a few of them leave the fit), and a false level move (an intercept more, the slope
#   unbiased: StreamClock._level_move)
MOVE_PRIOR = 0.1  # -, the prior probability that the link's latency level moved within the
#   rate fit's current segment (a route or a queue that changed for good): the stated rate
#   error averages the one-line fit and its best two-level one by their posterior
#   (StreamClock._rate_of). On clean links it widens the error by 0-6 % at 10 Hz, up to 2.3x
#   at 1 Hz where a split fits by chance; 1 Hz moves of 10 ms read 8.4 errors at 0, 3.4 at it
#   (docs/integrity.md)
SERIAL_CHAIN = 512  # the rate fit's latest points whose differences are kept (the residuals'
#   serial correlation, StreamClock._serial): a dip's points that leave the fit are unlinked
#   from among them
SERIAL_LAG = 8  # points (4 s at 10 Hz in blocks of 5): the longer lag of the residuals'
#   variogram, whose correlation against lag one's tells a wander from the envelope's own noise
MOVE_SPLITS = 32  # the rate fit's candidate times of a level move in its current segment, at
#   most (StreamClock._level_move): its cost per point; they thin out as the segment grows
TOL = 5.0  # s: wider than arrival jitter (a node at 10x sees 1 Hz stamps 0.9 s apart in
#   stamp - arrival), far narrower than a clock error worth refusing


def paced(prev: tuple, cur: tuple) -> bool:
    """``cur`` = (stamp, arrival) arrived at least half as much later than ``prev`` as it was
    stamped later: a clock running on. A backlog's burst (arrivals frozen while the stamps
    advance) is not paced. Without arrival times (None), anything is."""
    if prev[1] is None or cur[1] is None:
        return True
    return cur[1] - prev[1] >= 0.5 * (cur[0] - prev[0])


def continues(prev: tuple, cur: tuple, tol: float = TOL) -> bool:
    """``cur`` = (stamp, arrival) comes after ``prev`` on one clock: a later stamp, no more
    ahead of it than the arrival time elapsed (+ ``tol``)."""
    return 0.0 < cur[0] - prev[0] <= max(cur[1] - prev[1], 0.0) + tol


def is_step(chain: list, n: int, period: float) -> bool:
    """The step test: ``chain`` = (stamp, arrival) of the readings away from their clock, each
    continuing the one before (:func:`continues`), is a clock that jumped and runs on when there
    are at least ``n`` of them, their stamps advance at least at half the nominal pace
    (``period`` s per reading), and their arrivals span at least half their stamps (a backlog's
    burst, all arriving at once, is no step). One reading, or one stall's burst, never is."""
    if len(chain) < n:
        return False
    (s0, a0), (s1, a1) = chain[0], chain[-1]
    return s1 - s0 >= 0.5 * (len(chain) - 1) * period and paced((s0, a0), (s1, a1))


def silence_risk(lost: int, got: int, n: int) -> float:
    """The probability that the old clock's next ``n`` readings were all lost, given that the
    link lost ``lost`` and delivered ``got`` of its recent slots and delivered the ``n`` held
    readings themselves: the Bayes factor of "no step, the old clock's readings lost (and the
    held ones from elsewhere)" against "a step: the old clock has no more readings".

    Each reading is lost with an unknown probability ``q``, the same for every message on the
    link, uniform a priori. Under no step the data have the likelihood ``q^(lost + n) (1 -
    q)^(got + n)``, under a step ``q^lost (1 - q)^(got + n)``; their ratio, integrated over
    ``q``, is ``B(lost + n + 1, got + n + 1) / B(lost + 1, got + n + 1)``, the n-th moment of
    ``q`` under Beta(lost + 1, got + n + 1). A step needs it at most ``step_risk`` (and
    ``min_judged`` readings, the longest burst of alike wrong stamps covered): at 1e-7 that
    is 9 readings on a link that loses one in eight, 22 on one that loses every other, 3 on
    one that loses none, 13 before any history (the losses counted from the gaps between the
    stamps admitted: :meth:`StepWatch._silent`)."""
    a, b = lost + 1.0, got + n + 1.0
    p = 1.0
    for i in range(n):
        p *= (a + i) / (a + b + i)
    return p


_ROWS = [[1], [1]]  # the permutations of n items counted by their inversions, n = 0, 1, ...
_CUMULATIVE: dict = {}  # n -> the same counts summed up to each number of inversions


def _mahonian(n: int) -> tuple:
    """Cumulative counts of the permutations of ``n`` items by their number of inversions."""
    cum = _CUMULATIVE.get(n)
    if cum is not None:
        return cum
    while len(_ROWS) <= n:  # the k-th item inserted adds 0..k-1 inversions
        row, k = _ROWS[-1], len(_ROWS)
        pre = [0]
        for c in row:
            pre.append(pre[-1] + c)
        m = len(row)
        _ROWS.append([pre[min(i, m - 1) + 1] - pre[max(i - k + 1, 0)]
                      for i in range(m + k - 1)])
    out, acc = [], 0
    for c in _ROWS[n]:
        acc += c
        out.append(acc)
    cum = _CUMULATIVE[n] = tuple(out)
    return cum


def kendall_tail(n: int, inversions: int) -> float:
    """P(a uniformly random order of ``n`` distinct values has at most ``inversions``
    pairs out of order): the exact one-sided tail of Kendall's rank statistic, free of the
    values' distribution."""
    if n < 2:
        return 1.0
    cum = _mahonian(n)
    return cum[min(max(inversions, 0), len(cum) - 1)] / cum[-1]


class StreamClock:
    """One clock against the arrival clock, streaming (the counterpart of the offline
    ``ClockFit``, ``core/offline/clock_fit.py``).

    ``offset``: the robust centre of the last ``n`` offsets ``stamp - arrival``, the densest
    one (most others within ``TOL``), the median of the densest on ties. A plain median fails
    when over half of a window is wild (a fuzzed stream); wild stamps scatter, while good ones
    agree to milliseconds. ``drift``: the clock's rate minus 1, least squares of stamps on the
    arrivals of the clock's envelope, each block's reading with the least latency
    (:meth:`rate_point`). Lateness by the module's one rule.
    """

    def __init__(self, n: int = 31, settled: int = 9):
        self.n, self.fifo, self.sorted = n, deque(), []
        self.settled = settled  # offsets in the window before its centre says where the clock
        #   is (the runner's ``min_judged``, :attr:`judged`): earlier ones do not lift the
        #   ceiling, nor are later ones judged late against it
        self.arrivals: deque = deque()  # arrival (s, or None) of each offset in fifo
        self._value = None  # cached centre (recomputed after an add)
        self._scale = None  # cached robust spread (likewise: the runner asks several times per
        #   message, the step watch's bar and the rate fit's band)
        self._at_cache = None  # ((pushes, drift), newest arrival, centre, spread there):
        self.pending: list = []  # consecutive values away from a full window's centre
        self._fit = [0, 0.0, 0.0, 0.0, 0.0, 0.0, None]  # n, sx, sy, sxx, sxy, syy, origin
        self._closed = [0, 0, 0.0, 0.0, 0.0]  # segments, n, centred sxx, sxy, syy before a move
        self._snaps: list = []  # the current segment's sums up to a point, and its arrival:
        #   the candidate times of a level move (:meth:`_level_move`)
        self._snap_every, self._since_snap = 1, 0  # points between two of them, since the last
        self._rates: dict = {}  # rate()'s by (min_n, min_span), until the fit changes
        self._held_points: list = []  # (arrival, stamp, residual) of the rate fit's points
        #   held above its line (:meth:`_off`)
        self._coarse = [[0, 0.0, 0.0, 0.0, 0.0, 0.0, None], [0, 0, 0.0, 0.0, 0.0]]  # the
        #   same points with an intercept per declared level only (:meth:`rate_apart`): the
        #   current one's raw sums and origin, and the closed ones' like ``_closed``
        self._pairs = {1: [0, 0.0, 0.0, 0.0], SERIAL_LAG: [0, 0.0, 0.0, 0.0]}  # by lag, the
        #   points of one declared level that many apart: how many, and the sums of
        #   d(offset)^2, d(offset) d(arrival), d(arrival)^2 (:meth:`_serial`)
        self._chain: deque = deque(maxlen=SERIAL_CHAIN)  # the current declared level's latest
        #   fit points (arrival, stamp), in order: the pairs they make
        self._dip: list = [0.0, [], False]  # the CUSUM of the points' fall below the line, the
        #   points fitted since it was last 0, whether a dip is under way (:meth:`_off`)
        self._block = [0, 0.0, 0.0]  # readings so far in the rate fit's block, and the
        #   (stamp, arrival) of its highest offset (:meth:`rate_point`)
        self._top: deque = deque()  # (index, offset, arrival), decreasing: the sliding maximum
        self._ceil_cache = None  # ((pushes, drift), the ceiling carried to the newest arrival)
        self._pushed = 0  # offsets pushed so far
        self._lifted = 0  # offsets that could lift the ceiling since it was last cleared
        self._instant = [None, -math.inf, [], []]  # the newest arrival instant: its arrival,
        #   its head (:meth:`_queued`), its votes (push index, offset, lifted), and its offsets
        #   that may head it, sorted

    tol = TOL
    late = LATE
    horizon = 600  # offsets over which the ceiling is the maximum (1 min at 10 Hz)
    block = 5  # readings per point of the rate fit: its highest offset (:meth:`rate_point`)

    # -- offset ---------------------------------------------------------------------------
    def add(self, v: float, at: float | None = None, lift: bool = True) -> None:
        """Add the offset ``v`` = stamp - arrival of an item that arrived at ``at`` (s; None:
        unknown). ``lift=False``: it votes for the centre but not for the ceiling (an item
        refused as stamped above its clock)."""
        # Once the window is full, a value far from its centre does not vote: wild stamps
        # mixed with good ones (a fuzzed or corrupted stream) could otherwise, by a run of
        # bad luck, outnumber the good ones in the window and move the centre by their offset
        # (a control clock moved 500 s ahead blinds the filter). Only n // 2 + 1 *consecutive*
        # far values that agree among themselves -- the clock itself has stepped -- replace
        # the window.
        #
        # A clock that stepped keeps its new offset as time goes on; a backlog does not: after
        # a stall (a node or recorder blocked for longer than tol), the readings of the stall
        # arrive in one burst, their offsets sweeping from -stall towards 0 as the stamps
        # advance with the arrival frozen (taken for a step, it moved one clock's centre by
        # seconds and "auto" judged the clocks separate). So the far run must also be paced
        # (:func:`paced`); older values of a run that is not are dropped from it.
        if self._queued(v, at, lift):
            return
        if self.judged and v - self.value >= -self.tol and self.is_late(v):
            # came late (module doc): neither votes nor informs the rate -- from the moment
            # the centre is settled, not only once the window is full (a recorder stalled 8 s
            # at 26 s of a 1 Hz run voted its burst into the centre, which moved 4 s)
            self.pending = []
            return
        if len(self.fifo) >= self.n and abs(v - self.value) > self.tol:
            if self.pending and abs(v - self.pending[-1][0]) > self.tol:
                self.pending = []
            self.pending.append((v, at))
            while len(self.pending) > self.n // 2 and not self._persists(self.pending):
                self.pending.pop(0)
            if len(self.pending) <= self.n // 2:
                return
            self.fifo.clear()
            self.arrivals.clear()
            self.sorted = []
            self._top.clear()  # the clock itself moved: where it was says nothing now
            self._lifted = 0
            self._instant = [None, -math.inf, [], []]
            for p, a in self.pending[:-1]:
                self._push(p, at=a)
            self.pending = []
        elif self.pending:
            self.pending = []
        self._push(v, lift, at)

    def _queued(self, v: float, at: float | None, lift: bool = True) -> bool:
        """Whether the offset ``v`` arriving at ``at`` came late behind another of its
        instant; and such votes of the instant taken back. Items that arrive at one instant
        were queued behind one another, and latency only lowers an offset: each is late by at
        least its stamp's distance to the newest among them, and one more than ``LATE`` below
        the instant's head (within ``tol`` of it) came late by the module's one rule, before
        any centre says so. The head is the highest offset of the instant that another of it
        agrees with (within ``LATE``): a queue's newest half-second, never one stamp alone,
        which may be wrong (a fuzzed stream sends corrupted copies beside each message, at its
        instant: one stamped 5 s ahead, taken as the head, took the good one's vote at every
        instant, and the clock followed the wrong stamps); nor an item refused as stamped above
        its clock (``lift`` False). A head beyond ``tol`` of a vote (two wild copies that
        agree, 1e6 s ahead) says nothing of it, either way. Without this a node on simulated time
        that joined a running world (what it received before its first /clock, and the
        middleware's repairs of what was sent before it matched, all timed at one /clock)
        had the control clock's first votes spread over the 1-3 s of that backlog: the
        centre lay about 1.2 s below the commands that then came on time, refused as stamped
        ahead (11-28 per node at 10x). The newest half-second of the backlog still votes, so
        a clock that only a backlog has shown is judged from it."""
        inst = self._instant
        if at is None or at != inst[0]:
            self._instant = inst = [at, -math.inf, [], []]
            if at is None:
                return False
        if lift:
            offs = inst[3]
            bisect.insort(offs, v)
            head = next((offs[j] for j in range(len(offs) - 1, 0, -1)
                         if offs[j] - offs[j - 1] <= self.late), -math.inf)
            if head > inst[1] and (inst[1] == -math.inf or head - inst[1] <= self.tol):
                inst[1] = head
                gone = [e for e in inst[2] if self.late < head - e[1] <= self.tol]
                if gone:
                    self._take_back(gone)
        return self.late < inst[1] - v <= self.tol

    def _take_back(self, gone: list) -> None:
        """Take back the votes ``gone`` (push index, offset, lifted) of the newest instant,
        the last of the window's (:meth:`_queued`)."""
        idx = {e[0] for e in gone}
        k = len(self._instant[2])
        tail_v = [self.fifo.pop() for _ in range(k)][::-1]
        tail_a = [self.arrivals.pop() for _ in range(k)][::-1]
        keep = []
        for e, v, a in zip(self._instant[2], tail_v, tail_a):
            if e[0] in idx:
                del self.sorted[bisect.bisect_left(self.sorted, v)]
                self._lifted -= e[2]
            else:
                self.fifo.append(v)
                self.arrivals.append(a)
                keep.append(e)
        self._instant[2] = keep
        self._top = deque(t for t in self._top if t[0] not in idx)
        self._value = self._scale = self._at_cache = self._ceil_cache = None

    @staticmethod
    def _persists(run: list) -> bool:
        """A run of far (offset, arrival) values that is paced: a clock step, not a backlog."""
        (v0, a0), (v1, a1) = run[0], run[-1]
        if a0 is None or a1 is None:
            return True
        return paced((v0 + a0, a0), (v1 + a1, a1))

    def _push(self, v: float, lift: bool = True, at: float | None = None) -> None:
        self._value = self._scale = None
        self._pushed += 1
        self.fifo.append(v)
        self.arrivals.append(at)
        bisect.insort(self.sorted, v)
        if len(self.fifo) > self.n:
            old = self.fifo.popleft()
            self.arrivals.popleft()
            del self.sorted[bisect.bisect_left(self.sorted, old)]
        inst = self._instant
        lifts = len(self.fifo) > self.settled and lift
        if at is not None and at == inst[0]:
            inst[2].append((self._pushed, v, lifts))
            del inst[2][:-len(self.fifo)]  # (the window's, the last of it)
        if not lifts:
            return
        # only offsets that voted once the clock had a centre: among the first few a wild
        # stamp (1e9 s ahead) votes unjudged, and as the ceiling it hid every forward step and
        # stamp ahead for `horizon` readings (a fuzzed 1 Hz stream: a reading stamped 5 s
        # ahead then took a genuine one's slot). Later ones are judged before they vote (the
        # runner holds a reading above the ceiling by more than its bar), so one lifts it by
        # no more than that bar
        self._lifted += 1
        while self._top and self._top[-1][1] <= v:
            self._top.pop()
        self._top.append((self._pushed, v, at))
        if self._top[0][0] <= self._pushed - self.horizon:
            self._top.popleft()

    def move(self, d: float) -> None:
        """The offsets' level moved by ``d`` s and stays (the link's latency moved, the clock
        did not): the window, its ceiling and the rate fit's level follow at once."""
        self.fifo = deque(v + d for v in self.fifo)
        self.sorted = [v + d for v in self.sorted]
        self._top = deque((i, v + d, a) for i, v, a in self._top)
        self._instant = [None, -math.inf, [], []]
        self.pending, self._held_points = [], []
        self._value = self._scale = self._at_cache = self._ceil_cache = None
        self._new_segment()  # (the dip's run starts afresh with it)
        self._block = [0, 0.0, 0.0]

    def __len__(self) -> int:
        return len(self.fifo)

    @property
    def judged(self) -> bool:
        """Whether the clock is known: its centre rests on ``settled`` offsets, and stamps
        are judged against it (late, above its ceiling, a step from it). The one answer to
        "is this clock known yet?" that the runner and the step watch ask."""
        return len(self.fifo) >= self.settled

    def is_late(self, v: float) -> bool:
        """``v`` (stamp - arrival) lies more than ``LATE`` s below the centre: the item came
        late (module doc). The one lateness rule: such an offset does not vote once the clock
        is judged (:meth:`add`), is no point of the rate fit (:meth:`on_time`), and the
        runner's tick waits while the latest message came so (a backlog being caught up)."""
        return v - self.value < -self.late

    def on_time(self, v: float) -> bool:
        """``v`` (stamp - arrival) is not late (:meth:`is_late`), and not far above."""
        return not self.is_late(v) and v - self.value <= self.tol

    def near(self, v: float) -> int:
        """How many values of the window lie within ``tol`` of ``v``."""
        return bisect.bisect_right(self.sorted, v + self.tol) - \
            bisect.bisect_left(self.sorted, v - self.tol)

    @property
    def value(self) -> float:
        """The offset: robust centre of stamp - arrival (s)."""
        if self._value is not None:
            return self._value
        self._value = self._centre(self.sorted)
        return self._value

    def one_densest(self) -> bool:
        """Whether one group of agreeing offsets is denser than every other (its values within
        ``2 tol`` of one another): with two groups as dense, the centre is a coin toss (the
        fuzz mix's first message, three copies 1e9 s ahead against the genuine command and two
        copies of it with corrupted values: the control clock's centre went 1e9 s ahead)."""
        s = self.sorted
        if not s:
            return False
        counts = [bisect.bisect_right(s, v + self.tol) - bisect.bisect_left(s, v - self.tol)
                  for v in s]
        best = max(counts)
        dense = [v for v, c in zip(s, counts) if c == best]
        return dense[-1] - dense[0] <= 2 * self.tol

    @classmethod
    def _centre(cls, s: list) -> float:
        """The densest value of the sorted ``s`` (most others within ``tol``), the median of
        the densest on ties."""
        if not s:
            return math.nan
        tol = cls.tol
        if s[0] + tol >= s[-1] and s[-1] - tol <= s[0]:
            # every value within tol of every other (the usual window: a link's jitter is
            # milliseconds): each counts all of them, and the densest are the whole window.
            # The bounds as the counts compute them (v + tol, v - tol rounded), so this is
            # their answer exactly, without a count per value
            return s[len(s) // 2]
        counts = [bisect.bisect_right(s, v + tol) - bisect.bisect_left(s, v - tol) for v in s]
        best = max(counts)
        dense = [v for v, c in zip(s, counts) if c == best]
        return dense[len(dense) // 2]

    def value_at(self, at: float | None, drift: float) -> float:
        """The offset at arrival ``at`` (s) of a clock whose offset moves by ``drift`` s/s:
        the robust centre of the window's offsets, each carried from its own arrival to ``at``
        along the drift. The plain centre is the offset of the window's middle, half a window
        ago: on a clock 1 % fast, 31 readings at 1 Hz put it 0.15 s behind the clock's
        present offset (:attr:`value` when the drift is 0 or an arrival is unknown)."""
        if not drift or at is None or not self.fifo:
            return self.value
        # Carried to the newest arrival ``a1`` and then on to ``at``: the window's shape does
        # not depend on ``at``, so its centre is computed once per window and drift (the
        # runner asks for it several times per message; recomputing it was a quarter of the
        # per-message time under the fuzz mix)
        carried = self._carried(drift)
        if carried is None:
            return self.value
        _, a1, c, _ = carried
        return c + drift * (at - a1)

    def _carried(self, drift: float) -> tuple | None:
        """(key, newest arrival a1, centre, spread) of the window's offsets carried along
        ``drift`` to ``a1``, cached per window and drift; None when an arrival is unknown."""
        key = (self._pushed, drift)
        if self._at_cache is None or self._at_cache[0] != key:
            a1 = self.arrivals[-1]
            if a1 is None or None in self.arrivals:
                return None
            s = sorted([v + drift * (a1 - a) for v, a in zip(self.fifo, self.arrivals)])
            c = self._centre(s)
            self._at_cache = (key, a1, c, self._spread(s, c))
        return self._at_cache

    def now(self, at: float | None) -> float:
        """The clock's offset at arrival ``at``, carried along its own drift (:meth:`value_at`)."""
        return self.value_at(at, self.drift)

    @property
    def jitter(self) -> float:
        """The offsets' robust spread about the clock's line (each carried along the clock's
        drift, :attr:`scale` without one): the link's jitter alone. About a constant centre a
        clock 1 % off spreads 31 readings at 1 Hz over 0.31 s (a robust spread of 0.1 s for
        50 ms of jitter), and the step bar, ten of them, hid steps of 0.5 s."""
        d = self.drift
        carried = self._carried(d) if d and self.fifo else None
        return self.scale if carried is None else carried[3]

    @property
    def scale(self) -> float:
        """Robust spread of the window's offsets around the centre (1.4826 x the median
        absolute deviation, s): the link's jitter as this clock sees it."""
        if self._scale is None:
            self._scale = self._spread(self.sorted, self.value)
        return self._scale

    @staticmethod
    def _spread(s: list, c: float) -> float:
        """1.4826 x the middle of the absolute deviations of ``s`` from ``c`` (nan when
        empty)."""
        if not s:
            return math.nan
        dev = sorted([abs(v - c) for v in s])
        return 1.4826 * dev[len(dev) // 2]

    @property
    def ceiling(self) -> float:
        """The largest offset that voted among the last ``horizon``, once ``settled`` were
        in, each carried along the clock's drift to the newest arrival: where the clock is when
        the latency is least. A node that lagged its input for a while moves the centre down
        with it; when it catches up, its offsets return to the ceiling, never above it. Carried,
        since on a clock 1 % slow the offsets of a minute ago at 10 Hz lie 0.6 s above the
        present ones, and hid every forward step below it. (The sliding maximum keeps the
        offsets that no later one exceeds; on a slow clock the ones it dropped stay below the
        later ones when carried, on a fast one the carried maximum is the newest offsets'.)"""
        if not self._top:
            return math.nan
        d = self.drift
        a1 = self.arrivals[-1] if self.arrivals else None
        if not d or a1 is None:
            return self._top[0][1]
        key = (self._pushed, d)
        if self._ceil_cache is None or self._ceil_cache[0] != key:
            self._ceil_cache = (key, max(v if a is None else v + d * (a1 - a)
                                         for _, v, a in self._top))
        return self._ceil_cache[1]

    def span(self) -> tuple[float, float]:
        """Where the clock's offset can lie (s, stamp - arrival at zero latency): from the
        centre, which a queue or a backlog pulls down by as much as the node lagged, up to the
        highest offset that voted (the window's, or the ceiling), since latency only lowers an
        offset; a stamp written ahead may have lifted that end, never the centre."""
        lo = self.value
        hi = max(self.sorted[-1] if self.sorted else lo, self.ceiling if self._top else lo)
        return lo, max(hi, lo)

    def one_instant(self, resolution: float) -> bool:
        """Every vote of the window arrived at one instant (within ``resolution`` s, the
        arrivals'): one latency, however many stamps."""
        a = self.arrivals
        return bool(a) and a[0] is not None and a[-1] is not None and \
            a[-1] - a[0] <= resolution

    @property
    def ceiling_n(self) -> int:
        """How many offsets the ceiling is the largest of (the envelope test's ``n``)."""
        return min(self._lifted, self.horizon)

    def lift(self, v: float) -> float:
        """:meth:`above` on one clock (no drift): how far the offset ``v`` lies above the
        centre and the largest offset of the last ``horizon`` as they voted, not carried along
        the rate fit, whose error (its standard error times a minute) the envelope cannot
        absorb."""
        return v - max(self.value, self._top[0][1]) if self._top else -math.inf

    def above(self, v: float) -> float:
        """How far the offset ``v`` (of a reading arriving now) lies above where its clock can
        be (s): only a forward step or a wrong stamp puts it there, since latency only ever
        lowers an offset. The centre and the ceiling carried to the newest arrival along the
        clock's drift."""
        a1 = self.arrivals[-1] if self.arrivals else None
        return v - max(self.now(a1), self.ceiling)

    # -- rate -----------------------------------------------------------------------------
    def rate_point(self, stamp: float, arrival: float) -> None:
        """Offer a reading (after :meth:`add`) to the rate fit: used when on time.

        The fit is on the clock's envelope, not on every reading. Latency is never negative,
        so ``stamp - arrival`` lies on or below the clock's line, and the reading with the
        least latency among ``block`` in a row lies closest to it: the fit takes each block's
        highest offset (its stamp against its arrival), whose latency is the least of
        ``block`` draws -- a link's jitter shrunk about ``block`` times, the blocks
        independent of one another (least squares over every reading stated half its error on
        a 200 ms jittery link). A late reading (the module's one rule) is left out.

        Once the rate is known, each block's point is judged against the line (:meth:`_off`):
        on it, it joins the fit; off it, it is held until the held points show where the
        line went."""
        if not self.on_time(stamp - arrival):
            return
        b = self._block
        if b[0] == 0 or stamp - arrival > b[1] - b[2]:
            b[1], b[2] = stamp, arrival
        b[0] += 1
        if b[0] < self.block:
            return
        b[0] = 0
        point = (b[2], b[1])  # (arrival, stamp) of the block's highest offset
        if self._off(point):
            return
        self._fit_add(*point)
        self._level_move()

    def _off(self, point: tuple) -> bool:
        """Whether the block's ``point`` (arrival, stamp) lies off the clock's line, and is held.

        The model: stamp = line(arrival) - latency, the latency never negative and, at the
        envelope, scattered as the fit's own residuals (``sd``). A point is off the line beyond
        ``SMALL_MOVE`` and :func:`t_spread` of its prediction's standard errors (the residuals'
        and the line's own, growing with the distance from the points' mean): a point of the
        line lies there at the Gaussian ``LINE_SPREAD`` sigma's rate whatever their number.
        Below the line is where latency puts a point (a queue that drains, a latency that
        wanders, or one that rose and stays: the step watch's to declare, :meth:`move`), and a
        clock's rate does not wander, so the envelope's dips stay out of the fit: a point far
        below, and a run within the band that together lies below the line (a one-sided CUSUM
        of the points' fall in the band's standard errors, reference ``DIP_REF``, each capped at
        the band, alarm at :func:`dip_bar`): the points fitted since it was last 0 leave the
        fit, and none joins until one lies within ``DIP_REF`` of them below the line again.
        (Fitted, a wander's climb back read as slope: 0.4 s over two minutes, +528 ppm.) Above
        it latency never puts one: the line's level rose (the latency's floor fell, or a step
        within ``TOL`` that no step test declared). Points beyond the band are held and start a
        new segment of the fit (an intercept of their own, the slope shared) once there are
        ``SEG_MIN`` of them and their scatter about their mean is the line's at ``SEG_RISK`` (a
        chi-square test of their variance); a point back on the line drops them. A level
        that moves by less than the band, either way, is :meth:`_level_move`'s."""
        d, se = self.rate()
        if not math.isfinite(se):  # the line is not known yet: every point informs it
            return False
        f = self._fit
        n1 = f[0]
        _, var, _, rss, dof = self._pooled()
        sd = max(math.sqrt(rss / dof), 1e-6)
        arrival, stamp = point
        resid, band = 0.0, LINE_SPREAD * sd
        if n1:
            # the current segment's line at this arrival: its mean point carried on the slope
            x0, y0 = f[6]
            dx = arrival - x0 - f[1] / n1
            resid = (stamp - y0 - f[2] / n1) - (1.0 + d) * dx
            band = t_spread(dof) * sd * math.sqrt(1.0 + 1.0 / n1 + dx * dx / var)
        unit, band = band / LINE_SPREAD, max(SMALL_MOVE, band)
        if resid <= band:
            self._held_points = []
            dip = self._dip
            fall = min(-resid, band) / unit
            if dip[2] and fall > DIP_REF:
                return True  # the dip goes on
            if dip[2]:  # back on the line: a new CUSUM from this point
                dip[:] = [0.0, [], False]
            dip[0] = max(dip[0] + fall - DIP_REF, 0.0)
            if dip[0] > dip_bar():
                for a, s in dip[1]:  # the dip's points leave the fit
                    self._fit_add(a, s, -1.0)
                dip[:] = [0.0, [], True]
                return True
            if resid < -band:
                return True  # far below: the latency's
            if dip[0] > 0.0:
                dip[1].append((arrival, stamp))
            else:
                dip[1].clear()  # (short runs)
            return False
        self._dip = [0.0, [], False]
        held = self._held_points
        held.append((arrival, stamp, resid))
        if len(held) > TREND_N:
            held.pop(0)
        if len(held) < SEG_MIN:
            return True
        r = [h[2] for h in held]
        mean = sum(r) / len(r)
        chi = sum((v - mean) ** 2 for v in r) / sd ** 2
        if float(chdtrc(len(r) - 1, chi)) <= SEG_RISK:
            return True  # scattered wider than one level: not yet a move
        self._held_points = []
        self._new_segment()
        for a, s, _ in held:
            self._fit_add(a, s)
        return True

    def _pooled(self) -> tuple:
        """(n, var, cov, rss, dof) of the fit over all its segments (an intercept each, the
        slope shared): points, centred sums of squares and products, the residual sum of
        squares about the pooled line (0 while var is not positive), its degrees of freedom."""
        n1, cxx1, cxy1, cyy1 = self._centred()
        segs, n0, cxx0, cxy0, cyy0 = self._closed
        n, var, cov, vyy = n0 + n1, cxx0 + cxx1, cxy0 + cxy1, cyy0 + cyy1
        rss = max(vyy - cov / var * cov, 0.0) if var > 0 else 0.0
        return n, var, cov, rss, max(n - 1 - segs - (n1 > 0), 1)

    def _fit_add(self, arrival: float, stamp: float, w: float = 1.0) -> None:
        """One point (arrival, stamp) into the current segment's sums (``w`` -1: out of them)."""
        f = self._fit
        x, y = _sums_add(f, arrival, stamp, w)
        _sums_add(self._coarse[0], arrival, stamp, w)
        self._rates = {}
        self._link(arrival, stamp, w)
        snaps = self._snaps
        if w < 0:  # a point that leaves the fit leaves the sums that hold it
            for sn in reversed(snaps):
                if sn[6] < arrival:
                    break
                for i, v in enumerate((1, x, y, x * x, x * y, y * y)):
                    sn[i] -= v
            return
        self._since_snap += 1
        if self._since_snap >= self._snap_every:
            self._since_snap = 0
            snaps.append([*f[:6], arrival])
            if len(snaps) > MOVE_SPLITS:  # bounded: every other one, twice as far apart
                del snaps[::2]
                self._snap_every *= 2

    def _pair(self, p: tuple, q: tuple, w: float, lag: int = 1) -> None:
        """The fit points ``p``, ``q`` (arrival, stamp), ``lag`` apart, into the pairs' sums
        (``w`` -1: out of them), by the offset's change and the arrival's (the stamps' own
        change would cancel to a few digits in the slope's residual)."""
        dx = q[0] - p[0]
        do = (q[1] - p[1]) - dx
        pr = self._pairs[lag]
        pr[0] += int(w)
        pr[1] += w * do * do
        pr[2] += w * do * dx
        pr[3] += w * dx * dx

    def _link(self, arrival: float, stamp: float, w: float) -> None:
        """A point joins the chain of the current declared level's fit points, or leaves it (a
        dip's, in the middle of the chain): the pairs' sums are then those of the points left,
        successive, at both lags (the pairs that held or spanned it out, the ones its leaving
        makes in; exact within the chain kept)."""
        chain, pt, k = self._chain, (arrival, stamp), SERIAL_LAG
        if w > 0:
            if chain:
                self._pair(chain[-1], pt, 1.0)
            if len(chain) >= k:
                self._pair(chain[-k], pt, 1.0, k)
            chain.append(pt)
            return
        try:
            i = chain.index(pt)
        except ValueError:  # beyond the chain kept: its pairs stay (one in SERIAL_CHAIN)
            return
        n = len(chain)
        for lag in (1, k):
            for m in range(max(i - lag, 0), min(i, n - 1 - lag) + 1):  # held or spanned it
                self._pair(chain[m], chain[m + lag], -1.0, lag)
            for m in range(max(i - lag, 0), min(i, n - 1 - lag)):  # m and m + lag + 1 now
                self._pair(chain[m], chain[m + lag + 1], 1.0, lag)
        del chain[i]

    def _serial(self, d: float, rss: float, dof: int) -> float:
        """The factor by which the rate fit's residuals about the line of drift ``d`` (rss and
        dof about it) state the slope's variance too small for their serial correlation (1
        and above): the long-run variance's ratio to the variance, 1 + 2 sum of the
        autocorrelations.

        A latency that wanders (a loaded host, a node behind at 10x: milliseconds over tens of
        seconds) leaves runs of residuals on one side of the line, which the fit's own spread
        cannot see; blocks of a white latency's envelope are independent. The model: an AR(1)
        wander (coefficient phi) beside the envelope's white noise, whose autocorrelation is
        rho_1 phi^(k-1) at lag k >= 1 (an ARMA(1, 1)); the factor 1 + 2 rho_1 / (1 - phi).
        Each rho from the variogram, 1 - (mean square difference of residuals k apart) / (2
        their variance), in which each level's own intercept cancels; phi from lags 1 and
        ``SERIAL_LAG``. Lag one alone (AR(1), Durbin-Watson) read a 3 ms wander under 1 ms of
        envelope noise as rho 0.3 and stated the slope's error 3 times too small (and an
        AR(1) wander of 3 beside white noise of 1, phi 0.97, as a factor of 15 for 59:
        test_clocks)."""
        if not rss > 0.0:
            return 1.0
        var = rss / dof

        def rho(lag: int) -> float | None:
            m, soo, sox, sxx = self._pairs[lag]
            if m < 3:
                return None
            dr2 = max(soo - 2.0 * d * sox + d * d * sxx, 0.0) / m
            return min(max(1.0 - dr2 / (2.0 * var), 0.0), 0.999)

        r1 = rho(1)
        if not r1:
            return 1.0
        rk = rho(SERIAL_LAG) if self._pairs[SERIAL_LAG][0] >= 2 * SERIAL_LAG else None
        phi = r1 if rk is None else \
            min(max((rk / r1) ** (1.0 / (SERIAL_LAG - 1)), r1), 0.999) if rk > 0.0 else r1
        return 1.0 + 2.0 * r1 / (1.0 - phi)

    def _centred(self) -> tuple[int, float, float, float]:
        """The current segment's n and centred sums (sxx, sxy, syy)."""
        n = self._fit[0]
        return (n, *_centred_sums(self._fit)) if n else (0, 0.0, 0.0, 0.0)

    def _close(self, sums, c: list | None = None) -> None:
        """Points with these raw sums [n, sx, sy, sxx, sxy, syy] become a closed segment: an
        intercept of their own, the slope shared (in ``c``; the rate fit's own by default)."""
        c = self._closed if c is None else c
        c[0] += 1
        c[1] += sums[0]
        for i, v in enumerate(_centred_sums(sums)):
            c[2 + i] += v

    def _new_segment(self) -> None:
        """The offset's level moved: later points get an intercept of their own and share the
        slope with the earlier ones."""
        if self._fit[0]:
            self._close(self._fit)
        self._fit = [0, 0.0, 0.0, 0.0, 0.0, 0.0, None]
        c = self._coarse
        if c[0][0]:
            self._close(c[0], c[1])
        c[0] = [0, 0.0, 0.0, 0.0, 0.0, 0.0, None]
        self._rates = {}
        self._snaps, self._snap_every, self._since_snap = [], 1, 0
        self._chain.clear()  # no pair across two levels
        # the dip CUSUM's run holds points of the segment closed
        self._dip = [0.0, [], False]

    def _level_move(self) -> None:
        """Whether the current segment's points lie on two levels of one slope rather than on
        one line: a level move within the band, which :meth:`_off` cannot see since the line it
        judges points against tilts towards the new level point by point (a latency 10 ms
        slower for good, 1 sd of the envelope at 10 Hz, read as -25 ppm at 14 standard errors;
        a 30 ms faster one as +75 ppm at 49, before a CUSUM of the rise). A generalised
        likelihood ratio over the candidate times (the sums kept at up to ``MOVE_SPLITS`` of
        the segment's points): the F statistic of an intercept more at the best one, its tail
        times the candidates tried (Bonferroni) against ``DIP_RISK``. On alarm the points
        before it close a segment of their own. A false move costs the slope some precision,
        never a bias (an intercept more is free under one line); a true one left in biases it
        by up to 1.5 move / span."""
        snaps, f = self._snaps, self._fit
        if len(snaps) < 2 or not math.isfinite(self.rate()[1]):
            return
        split = self._best_split()
        if split is None:
            return
        r, k, _, _, rss, dof = split
        stat = (rss - r) / max(r / (dof - 1), 1e-300)
        if float(fdtrc(1, dof - 1, stat)) * len(snaps) > DIP_RISK:
            return
        sn = snaps[k]
        self._close(sn)
        for i in range(6):  # the points after it are the current segment (same origin)
            f[i] -= sn[i]
        self._snaps = [[s[i] - sn[i] for i in range(6)] + [s[6]] for s in snaps[k + 1:]]
        self._rates = {}
        # the dip CUSUM's run may hold points now closed (no dip is under way: a point joined)
        self._dip = [0.0, [], False]

    def _best_split(self) -> tuple | None:
        """The current segment's best two-level fit (:meth:`_level_move`): (its residual sum
        of squares, the candidate's index, its centred sxy and sxx with the closed segments',
        the one-line fit's rss and dof), or None when no candidate has ``SEG_MIN`` points on
        either side or it fits no better. Kept with the rates until the fit changes."""
        if "split" in self._rates:
            return self._rates["split"]
        self._rates["split"] = best = None
        snaps, f = self._snaps, self._fit
        n, var, cov, rss, dof = self._pooled()
        if len(snaps) < 2 or dof < 2 or not rss > 0.0:
            return None
        # the closed segments' sums: the pooled ones less the current segment's
        _, cxx1, cxy1, _ = self._centred()
        cxx0, cxy0, cyy0 = var - cxx1, cov - cxy1, self._closed[4]
        for k, sn in enumerate(snaps):
            if sn[0] < SEG_MIN or f[0] - sn[0] < SEG_MIN:
                continue
            a, b = _centred_sums(sn), _centred_sums([f[i] - sn[i] for i in range(6)])
            v = cxx0 + a[0] + b[0]
            if not v > 0.0:
                continue
            c = cxy0 + a[1] + b[1]
            r = max(cyy0 + a[2] + b[2] - c * c / v, 0.0)
            if best is None or r < best[0]:
                best = (r, k, c, v, rss, dof)
        if best is None or not best[0] < rss:
            return None
        self._rates["split"] = best
        return best

    def rate(self, min_n: int = 20, min_span: float = 10.0) -> tuple[float, float]:
        """(drift, its standard error): the clock's rate minus 1 (s/s) against the arrival
        clock, least squares with one intercept per level of the offset (:meth:`rate_point`);
        (0, inf) until ``min_n`` readings (in blocks, three at least) over ~``min_span`` s of
        arrivals are in, or when the fit says more than 10 % (not a clock). Kept until the fit
        changes (the runner asks for it at every message)."""
        key = (min_n, min_span)
        if key not in self._rates:
            self._rates[key] = self._rate_of(min_n, min_span)
        return self._rates[key]

    def _rate_of(self, min_n: int, min_span: float) -> tuple[float, float]:
        n, var, cov, rss, dof = self._pooled()
        if n < max(3, math.ceil(min_n / self.block)):  # min_n readings, in blocks
            return 0.0, math.inf
        if var < n * min_span ** 2 / 12:  # less than ~min_span of arrivals
            return 0.0, math.inf
        d = cov / var - 1.0
        if not abs(d) < 0.1:
            return 0.0, math.inf
        if math.sqrt(rss / dof) > max(SMALL_MOVE, LINE_SPREAD * self.scale):
            # the points lie on two levels, not about one line: a move of the offset the level
            # test could not see yet (a step before the rate was known: 3 s in the first 4 s
            # of a 1 Hz run without a counter read as a drift of 0.09)
            return 0.0, math.inf
        # widened for the few points' guess of their own spread (t_spread): 4 or 5 points of
        # a 1 Hz stream stated a tenth of their error, and one clock was judged two
        se = math.sqrt(rss / dof / var) * t_spread(dof) / LINE_SPREAD
        split = self._best_split()
        if split is None:
            return d, se
        # A level move too small for the likelihood ratio to confirm at DIP_RISK is left in
        # the line, whose slope it biases by up to 1.5 move / span (a latency 10 ms slower at
        # 1 Hz: 7-8 stated errors after ten minutes). The rate stays the one-line fit's; its
        # error averages the two models by their posterior (Bayesian model averaging, the
        # Bayes factor by BIC: Raftery 1995, one parameter more), prior MOVE_PRIOR: the mean
        # square of the truth about d is (1 - p) se^2 + p (se1^2 + (d1 - d)^2). On a clean
        # link the best split's factor is mostly below 1 and p about MOVE_PRIOR.
        r, _, c, v, _, _ = split
        d1 = c / v - 1.0
        se1 = math.sqrt(r / (dof - 1) / v) * t_spread(dof - 1) / LINE_SPREAD
        log_odds = 0.5 * n * math.log(rss / max(r, 1e-300)) - 0.5 * math.log(n) \
            + math.log(MOVE_PRIOR / (1.0 - MOVE_PRIOR))
        p = 1.0 / (1.0 + math.exp(-min(log_odds, 700.0)))
        return d, math.sqrt((1.0 - p) * se * se + p * (se1 * se1 + (d1 - d) ** 2))

    def rate_apart(self, min_n: int = 20, min_span: float = 10.0) -> tuple[float, float]:
        """(drift, its standard error) as :meth:`rate`, for telling this clock from another:
        one line through the same points, an intercept per declared level only (a step of
        the clock, a move of the latency that the step watch declared), its error widened
        for the residuals' serial correlation (:meth:`_serial`), as many fewer independent
        points (the effective sample size, at most n), the degrees of freedom of
        :func:`t_spread`. (0, inf) where :meth:`rate` is.

        :meth:`rate` models the latency's floor as levels that move now and then, split where
        the likelihood says (:meth:`_level_move`). A floor that wanders (a loaded host; a
        node behind at 10x on simulated time: milliseconds over tens of seconds) is cut
        there into a score of short levels, and the slope they share is the wander's own
        local slope: two streams of one simulated clock read 2.2e-4 apart at 5.4 of its
        standard errors, and the control clock was judged another one."""
        key = ("apart", min_n, min_span)
        if key not in self._rates:
            d, se = self.rate(min_n, min_span)
            if math.isfinite(se):
                c, (segs, n0, cxx0, cxy0, cyy0) = self._coarse
                n1 = c[0]
                cxx1, cxy1, cyy1 = _centred_sums(c) if n1 else (0.0, 0.0, 0.0)
                n, var, cov = n0 + n1, cxx0 + cxx1, cxy0 + cxy1
                if var > 0.0:
                    d = cov / var - 1.0
                    rss = max(cyy0 + cyy1 - cov / var * cov, 0.0)
                    dof = max(n - 1 - segs - (n1 > 0), 1)
                    infl = min(self._serial(d, rss, dof), float(n))
                    dof_e = max(int((dof + 1) / infl) - 1, 1)
                    se = math.sqrt(rss / dof / var * infl) * t_spread(dof_e) / LINE_SPREAD
                else:
                    d, se = 0.0, math.inf
            self._rates[key] = (d, se) if abs(d) < 0.1 else (0.0, math.inf)
        return self._rates[key]

    @property
    def drift(self) -> float:
        return self.rate()[0]


class Grid:
    """The coarsest of a few grids that every value seen lies on, to a few of its float's last
    digits: the resolution a producer rounds a field to (a recorder's whole metres, km/h), 0
    where none (a value that is not rounded lies on none of them within a few readings). It can
    only shrink: values that lie on a coarser grid by chance (2 m a sample at 20 m/s and 10
    Hz) leave it when the speed changes."""

    def __init__(self, grids: tuple, tol: float = 0.0):
        self._left = sorted(grids, reverse=True)  # the grids every value seen so far lies on,
        #   coarsest first
        self.tol = tol  # the values' own error besides their float's (a stamp less its first)

    def add(self, x: float) -> None:
        # (float64 values of a decimal grid, parsed or scaled)
        left = self._left
        if left:
            tol = max(1e-9 * max(1.0, abs(x)), self.tol)
            least = 10.0 * tol
            self._left = [q for q in left if q > least and abs(x - round(x / q) * q) <= tol]

    @property
    def q(self) -> float:
        return self._left[0] if self._left else 0.0


class Rows:
    """A deque of float rows of one width (at most ``maxlen``, the oldest dropped) whose rows
    are also kept in one C-contiguous array as they come (:meth:`array`), so that the compiled
    fits read them without building an array from tuples at every reading (the count fit's
    and the level test's: 30 us a reading, 6 % of the runner's work per reading). Read
    as the deque; written only through ``append``, ``clear`` and item assignment."""

    __slots__ = ("_d", "_a", "_n")

    def __init__(self, width: int, maxlen: int, rows=()):
        self._d: deque = deque(maxlen=maxlen)
        self._a = np.empty((maxlen, width))
        self._n = 0
        for row in rows:
            self.append(row)

    @property
    def maxlen(self) -> int:
        return self._d.maxlen

    def append(self, row: tuple) -> None:
        self._d.append(row)
        if self._n < self._d.maxlen:
            self._a[self._n] = row
            self._n += 1
        else:  # (numpy copies overlapping slices as if through a buffer)
            self._a[:-1] = self._a[1:]
            self._a[-1] = row

    def clear(self) -> None:
        self._d.clear()
        self._n = 0

    def __setitem__(self, k: int, row: tuple) -> None:
        self._d[k] = row
        self._a[k if k >= 0 else self._n + k] = row

    def __getitem__(self, k: int) -> tuple:
        return self._d[k]

    def __len__(self) -> int:
        return self._n

    def __iter__(self):
        return iter(self._d)

    def __reversed__(self):
        return reversed(self._d)

    def array(self) -> np.ndarray:
        """The rows, oldest first, as an (n, width) float64 view (valid until the next write)."""
        return self._a[:self._n]


def _count_link(s0: float, d0: float, v0, s1: float, d1: float, v1):
    """``(r s, mean speed m/s)`` of two odometer samples of one stream
    (stamps ``s``, counts ``d`` m, speeds ``v`` m/s): the stamps' difference less the time the
    count puts between them, ``2 (d1 - d0) / (v0 + v1)`` (the trapezoid: exact at constant
    acceleration); None when the train is not moving forward at ``COUNT_MIN_SPEED`` or the
    samples lie more than ``COUNT_SPAN`` apart."""
    if not all(isinstance(x, int | float) and math.isfinite(x) for x in (v0, v1, d0, d1)):
        return None
    vbar = 0.5 * (v0 + v1)
    if min(v0, v1) <= 0.0 or vbar < COUNT_MIN_SPEED:
        return None
    dt = (d1 - d0) / vbar
    if abs(dt) > COUNT_SPAN:
        return None
    return (s1 - s0) - dt, vbar


def _count_fit(links, lag_prior: tuple | None) -> tuple[float, float, tuple, float]:
    """``(rate, lag s, covariance of (rate, lag), sd m)`` of the count's clock from recent fused
    pairs' links (:func:`_count_link` and the count's time): the model and its fit are
    :func:`~train_estimation.core.numerics.count_fit.count_fit`'s, one compiled call. Imported
    here, where a count is fitted, so that a process that only reads a bag's clocks offline
    (``clock_fit``, which takes this module's constants) does not import numba."""
    from .count_fit import count_fit

    return count_fit(links.array() if isinstance(links, Rows) else links, lag_prior,
                     COUNT_LEARN // 2)


def _accel(links, span: float) -> float:
    """m/s^2, the train's acceleration over the last ``span`` s of the count's links
    (:func:`_count_link`; :class:`Rows` or a list of them): the least-squares slope of their
    later samples' speeds against their stamps (one pair's speeds, a period apart, differ by
    their noise: 1.4 m/s^2 at 10 Hz and 0.1 m/s; a slope over 2 s of 20 samples has 0.04
    m/s^2 of it); 0 with fewer than 3. One compiled call (``count_fit.accel``), imported here
    as :func:`_count_fit` is."""
    from .count_fit import accel

    q = links.array() if isinstance(links, Rows) else \
        np.array(list(links), float).reshape(-1, 4)
    return accel(q, span)


def _sums_add(s: list, arrival: float, stamp: float, w: float) -> tuple[float, float]:
    """One point (arrival, stamp) into the raw sums ``s`` = [n, sx, sy, sxx, sxy, syy, origin]
    of a line fit, about their origin (its first point); ``w`` -1 takes it out. Returns the
    point about the origin, (x, y)."""
    if s[6] is None:
        s[6] = (arrival, stamp)
    x, y = arrival - s[6][0], stamp - s[6][1]
    s[0] += int(w)
    s[1] += w * x
    s[2] += w * y
    s[3] += w * x * x
    s[4] += w * x * y
    s[5] += w * y * y
    return x, y


def _centred_sums(s) -> tuple[float, float, float]:
    """(sxx, sxy, syy) about their means from the raw sums [n, sx, sy, sxx, sxy, syy]."""
    n, sx, sy, sxx, sxy, syy = s[:6]
    return sxx - sx * sx / n, sxy - sx * sy / n, syy - sy * sy / n


def arrivals_llr(r: float, moved: float, prec: float) -> float | None:
    """The log-likelihood ratio of readings' arrivals that moved ``moved`` s off their old
    clock (Gaussian to ``prec`` s) for a step of ``r`` s of their stamps (the offsets moved by
    ``r``) against a move of what timed them (a sample counter, the count: the offsets
    stayed); None where no ratio beyond ``LEVEL_LLR`` either way could come (``r`` within 3
    precisions: the link's jitter cannot tell the two apart)."""
    if r * r <= 2.0 * LEVEL_LLR * prec * prec:
        return None
    return r * (2.0 * moved - r) / (2.0 * prec * prec)


@functools.lru_cache(maxsize=64)
def _t_bar(dof: int, p: float) -> float:
    """Student's t quantile with ``dof`` degrees of freedom beyond which lies ``p``."""
    return -float(stdtrit(dof, p))


@functools.cache
def dip_bar() -> float:
    """The rate fit's dip CUSUM's alarm (standard errors, StreamClock._off): ``DIP_RISK`` false
    dips per point, ``exp(-theta h)`` (Lundberg's bound) with ``theta`` the root of ``E exp(theta
    (L / mean - 1 - DIP_REF)) = 1`` for an exponential latency ``L``, whose envelope's lower tail
    is the heaviest of the links measured: 15.8 for 1e-4."""
    c = 1.0 + DIP_REF
    theta = 1.0 + float(lambertw(-c * math.exp(-c)).real) / c
    return math.log(1.0 / DIP_RISK) / theta


@functools.cache
def t_spread(dof: int) -> float:
    """Estimated standard errors of a fit with ``dof`` degrees of freedom that a value exceeds
    as seldom as ``LINE_SPREAD`` true ones (Student's t): ``LINE_SPREAD`` for many, 1,321 for 2."""
    return float(-stdtrit(dof, ndtr(-LINE_SPREAD)))


# -- the train clock's steps -----------------------------------------------------------------

PASS, HOLD, ADMIT, REFUSE, STEP, SKIP = "pass", "hold", "admit", "refuse", "step", "skip"
SLIP = "slip"
LATENCY = "latency"  # the step watch's answer: the link's latency moved, not the clock
PHASE_RES = 1e-6  # s: the stamps' resolution, the least scatter of a stream's sampling phase
#   (StepWatch.phase): a float Unix time resolves 2.4e-7 s, a ROS stamp 1e-9 s


class SampleGrid:
    """The train's own sample grid: odometer stamps against their ``seq`` (the sample counter
    before the radio link, +1 per sample), streaming. On one clock ``stamp = c + P seq``, with
    ``P`` the sample period on the train clock; the link's latency and jitter do not enter (the
    stamp is taken at sampling, the seq counted there too). So a clock step of ``d`` s moves the
    :meth:`residual` of every later sample by exactly ``d``, however jittery the link, while a
    reading that is merely late keeps a residual of zero. Lost packets skip seqs and change
    nothing.

    The line is robust: ``P`` the median of the slopes between neighbours, ``c`` the median of
    ``stamp - P seq``, so that one corrupted stamp or seq among the samples moves neither; once
    trusted, only samples on it are learnt. Trusted (:meth:`residual` not None) once ``n_min``
    samples agree: the period within half and twice the nominal one, the residuals' robust
    spread small against it. ``n_min`` admitted samples in a row off the line (a sender
    restarted, its counter wrapped) replace it by theirs; a step measured otherwise forgets it.

    Before that, from ``n_early`` samples that lie on one line within ``floor`` (a corrupted
    stamp or seq among so few breaks the line, and then there is none), the grid is
    *provisional*: the same residuals, with a tolerance that also allows ``rate_tol`` of the
    period per sample beyond the learnt ones (the period known from so few samples only to a
    drifting clock's rate). A train clock that steps in the first seconds of a 1 Hz run is then
    seen by the seqs: the readings after a -10 s step at 4 s, stamped where the old clock had
    already been, were taken as the old clock's late ones and its estimates ran 70 m behind.
    """

    def __init__(self, period: float, n_min: int = 9, floor: float = 0.01, keep: int = 64,
                 n_early: int = 3, rate_tol: float = 0.02):
        self.period = period  # s, nominal odometer period
        self.n_min = n_min  # samples before the grid is trusted
        self.n_early = n_early  # samples on one line before the grid is provisional
        self.rate_tol = rate_tol  # -, the provisional period's allowance per sample beyond
        #   the learnt ones (a clock's rate error, 1e-2 at most, and the slope of few samples)
        self.floor = floor  # s: the smallest residual taken as off the grid (sampling jitter)
        self.keep = keep  # recent samples kept
        self._pts: dict = {}  # seq -> timeline stamp of learnt samples
        # The line is refitted at every reading (the samples change); what it is made of is
        # kept sorted as they change, one sample in and one out, instead of sorted again:
        self._seqs: list = []  # the learnt samples' seqs, sorted
        self._ratios: list | None = []  # the slopes between neighbours, sorted (None: to
        #   be rebuilt; only for seqs exact as floats, :meth:`_robust`)
        self._res: tuple | None = None  # (P, the residuals stamp - P seq, sorted) for the
        #   last period fitted: kept while the period does not change (it seldom does)
        self._misfits: list = []  # (seq, stamp) admitted in a row off the trusted line
        self._fit = None  # cached (P, c, tolerance, lowest seq, highest seq), or False when not
        #   trusted
        self._early = None  # the same, provisional (class doc), or False when there is none

    def reset(self) -> None:
        self._pts.clear()
        self._seqs.clear()
        self._ratios = []
        self._res = None
        self._misfits.clear()
        self._fit = None
        self._early = None

    @staticmethod
    def _seq(seq):
        return seq if isinstance(seq, int) and not isinstance(seq, bool) else None

    def add(self, seq, stamp: float) -> None:
        """A sample the runner admitted (timeline stamp)."""
        seq = self._seq(seq)
        if seq is None or not math.isfinite(stamp):
            return
        if self._line() is not None:
            r = self._on_line(seq, stamp)
            if r is None or abs(r) > self.tol:
                self._misfits.append((seq, stamp))
                if len(self._misfits) < self.n_min:
                    return
                misfits = self._misfits[-self.n_min:]
                self.reset()
                for q, st in misfits:
                    self._learn(q, st)
                return
        self._misfits.clear()
        self._learn(seq, stamp)
        if len(self._pts) > self.keep:
            self._pair(0, False)
            self._resid_of(self._seqs[0], False)
            del self._pts[self._seqs.pop(0)]  # the lowest seq
        self._fit = None
        self._early = None

    def _learn(self, seq: int, stamp: float) -> None:
        """Learn the sample ``seq`` at ``stamp`` (a new one, or a new stamp for one known),
        keeping the sorted slopes and residuals (``__init__``) up to date."""
        qs, pts = self._seqs, self._pts
        if not -2 ** 53 <= seq <= 2 ** 53:
            self._ratios = None  # not exact as a float: the arrays' way (_robust)
        i = bisect.bisect_left(qs, seq)
        if seq in pts:  # its slopes and residual go, the new ones come
            self._pair(i - 1, False)
            self._pair(i, False)
            self._resid_of(seq, False)
        else:
            self._pair(i - 1, False)  # its neighbours are neighbours no more
            qs.insert(i, seq)
        pts[seq] = stamp
        self._pair(i - 1, True)
        self._pair(i, True)
        self._resid_of(seq, True)

    def _slope(self, i: int) -> float:
        """The slope between the ``i``-th and the next learnt sample (as np.diff divides)."""
        a, b = self._seqs[i], self._seqs[i + 1]
        return (self._pts[b] - self._pts[a]) / (float(b) - float(a))

    def _pair(self, i: int, add: bool) -> None:
        """Add (or remove) the slope of neighbours ``i``, ``i + 1`` to the sorted slopes."""
        r = self._ratios
        if r is None or not 0 <= i < len(self._seqs) - 1:
            return
        v = self._slope(i)
        if add:
            bisect.insort(r, v)
        else:
            del r[bisect.bisect_left(r, v)]

    def _resid_of(self, seq: int, add: bool) -> None:
        """Add (or remove) sample ``seq``'s residual to those kept for the last period."""
        if self._res is None or self._ratios is None:
            self._res = None
            return
        P, r = self._res
        v = self._pts[seq] - P * float(seq)
        if add:
            bisect.insort(r, v)
        else:
            del r[bisect.bisect_left(r, v)]

    def sample_period(self) -> float | None:
        """The train's sample period as the recent samples give it (s: the median of the
        stamps' steps over the seqs'), whatever the nominal one; None before ``n_min``."""
        if len(self._pts) < self.n_min:
            return None
        q = np.array(sorted(self._pts), float)
        st = np.array([self._pts[int(k)] for k in q])
        return median(np.diff(st) / np.diff(q))

    def _robust(self):
        """The learnt samples' robust line: ``(P, c, the median and the largest of the
        residuals' absolute values, lowest seq, highest seq)``, or None when the median period
        is not within half and twice the nominal one.

        On plain floats, the same operations as on arrays (each rounded once: the same
        numbers), on the slopes and residuals kept sorted (``__init__``): a fifth of the cost,
        and the grid is refitted at every reading. Seqs beyond 2**53 (not exact as floats) or
        residuals that overflow take the arrays."""
        qs, pts = self._seqs, self._pts
        if not -2 ** 53 <= qs[0] <= qs[-1] <= 2 ** 53:
            return self._robust_arrays()
        if self._ratios is None:
            self._ratios = sorted(self._slope(i) for i in range(len(qs) - 1))
        P = _median_sorted(self._ratios)
        if not 0.5 * self.period <= P <= 2.0 * self.period:
            return None
        if self._res is None or self._res[0] != P:
            self._res = (P, sorted([pts[k] - P * float(k) for k in qs]))
        r = self._res[1]
        if not (math.isfinite(r[0]) and math.isfinite(r[-1])):
            return self._robust_arrays()
        c = _median_sorted(r)
        dev = sorted([abs(v - c) for v in r])
        return P, c, _median_sorted(dev), dev[-1], qs[0], qs[-1]

    def _robust_arrays(self):
        """:meth:`_robust` on arrays (any seq, any stamp)."""
        q = np.array(sorted(self._pts), float)
        st = np.array([self._pts[int(k)] for k in q])
        P = median(np.diff(st) / np.diff(q))
        if not 0.5 * self.period <= P <= 2.0 * self.period:
            return None
        r = st - P * q
        c = median(r)
        a = np.abs(r - c)
        return P, c, median(a), float(np.max(a)), int(q[0]), int(q[-1])

    def _line(self):
        """(P s, c s, tolerance s, lowest seq, highest seq) of the grid, or None while it is
        not trusted."""
        if self._fit is None:
            self._fit = False
            line = self._robust() if len(self._pts) >= self.n_min else None
            if line is not None:
                P, c, mad, _, lo, hi = line
                tol = max(self._floor(P), 8.0 * 1.4826 * mad)
                if tol < 0.25 * P:
                    self._fit = (P, c, tol, lo, hi)
        return self._fit or None

    def _provisional(self):
        """The provisional line (class doc), as :meth:`_line`'s tuple, or None."""
        if self._early is None:
            self._early = False
            line = self._robust() if self.n_early <= len(self._pts) < self.n_min else None
            if line is not None:
                P, c, _, worst, lo, hi = line
                floor = self._floor(P)
                if worst <= floor and floor < 0.25 * P:
                    self._early = (P, c, floor, lo, hi)
        return self._early or None

    def _floor(self, P: float) -> float:
        """The least tolerance of a line of period ``P``: ``floor``, at most a fifth of the
        period, below the quarter its trust asks (a 10 ms floor against a 5 ms quarter made
        the grid of a 50 Hz odometer never trusted, and a step there was measured from the
        arrivals, whole periods off: 20-60 ms in 3 of 6 link seeds, the filter's time as far
        off to the end). 10 Hz and slower keep ``floor`` itself."""
        return min(self.floor, 0.2 * P)

    def tol_at(self, seq) -> float:
        """The tolerance (s) of :meth:`residual` at sample ``seq``: the trusted grid's, or the
        provisional one's grown per sample beyond the learnt ones by ``rate_tol`` periods
        (a clock's rate) and by what the provisional period itself may be off: its samples
        lie within ``floor`` of its line and, by the floor's own statement, within ``floor``
        of the true one, so the two lines part by up to 2 ``floor`` at each end of the learnt
        samples and their slopes by 4 ``floor`` over their span (a period of 0.094 s fitted
        to three samples of a 0.1 s grid sampled 20 ms apart at random: the readings after
        them, taken as off the grid, were refused as ahead of their stream, and never learnt
        from); inf without a grid."""
        fit = self._line()
        if fit:
            return fit[2]
        fit, seq = self._provisional(), self._seq(seq)
        if fit is None or seq is None:
            return math.inf
        P, _, tol, lo, hi = fit
        slope = 4.0 * self.floor / max(hi - lo, 1)
        return tol + (self.rate_tol * P + slope) * max(lo - seq, seq - hi, 0)

    def _on_line(self, seq, stamp: float):
        """:meth:`residual` on the learnt line alone (what :meth:`add` learns by)."""
        fit = self._line() or self._provisional()
        seq = self._seq(seq)
        if fit is None or seq is None:
            return None
        P, c, tol, lo, hi = fit
        if not lo - 100_000 <= seq <= hi + 100_000:
            return None
        if seq < hi and stamp > c + P * hi + tol:
            return None  # the seq back while the stamp went on: restarted, wrapped or corrupt
        return stamp - (c + P * seq)

    def residual(self, seq, stamp: float):
        """``stamp`` less where the grid puts sample ``seq`` (s); None while the grid is
        neither trusted nor provisional, or for a seq far from it (a counter restarted or
        wrapped, a corrupted seq)."""
        r = self._on_line(seq, stamp)
        if r is None:
            return None
        P, _, tol, _, _ = self._line() or self._provisional()
        seq = self._seq(seq)
        if abs(r) > tol and len(self._misfits) >= 2:
            # admitted samples off the line in a row (each on it clears them): a counter that
            # restarted, counting on past the old highest seq. A sample on their own line is
            # on the grid that replaces this one after n_min of them (at 1 Hz an odometer
            # rebooted at 10 s reached its old seq 9 at 20 s: held as a step of -11 samples,
            # then its readings refused as late)
            qs = np.array([q for q, _ in self._misfits], float)
            cs = np.array([st for _, st in self._misfits]) - P * qs
            cm = median(cs)
            if float(np.max(np.abs(cs - cm))) <= tol and abs(stamp - (cm + P * seq)) <= tol:
                return stamp - (cm + P * seq)
        return r

    @property
    def tol(self) -> float:
        fit = self._line()
        return fit[2] if fit else math.inf


class StepWatch:
    """The train clock's steps, streaming: what to do with each train-clock reading.

    Clock steps (a train clock reset to 0 by a reboot, or set to GPS time): odometer stamps jump
    and stay on the new clock. A reading is *discontinuous* when its stamp is more than ``TOL``
    behind the last odometer stamp admitted, or ahead of it by more than the arrival time
    elapsed since (+ ``TOL``), or (arrivals known, the clock judged) its ``stamp - arrival``
    lies more than a bar below its clock's centre (paced: a backward step) or above it (a
    forward step: latency only lowers it). The bar (:meth:`bar`) is ``back`` = ``max(step_back,
    2.5 periods)`` on a jittery link and with ``control_clock: same``; where the link's jitter
    is small it comes down to ``max(small_step, small_step_z`` robust spreads of the offsets),
    so that small steps (0.1 s is 8 m at 300 km/h) are watched too. An outage moves stamps and
    arrivals alike, and a node whose callbacks lag sees small stamp gaps whatever its arrivals,
    so neither is discontinuous. Discontinuous readings are held back (the integrity monitor
    says DEGRADED from the second one, the position variance grown by the candidate step:
    :meth:`doubt`); the step test (:func:`is_step`: odometer readings in a row that continue one
    another at a plausible pace, arriving at their stamps' pace: at least ``min_judged``, more
    than the longest burst of alike wrong stamps covered, and as many as make the old clock's
    silence over them a chance of at most ``step_risk`` on this link's losses
    (:func:`silence_risk`)) with no continuous reading between them makes a step: every later
    train-clock stamp is mapped back onto the old timeline (``stamp - shift``), the held
    readings are admitted, and the runner logs the event ``clock_reset``. With arrival times
    known for every reading of the step and the clock judged, ``shift`` is *measured*: the
    median offset of those readings less the clock's centre (known to the link's jitter);
    otherwise it is assumed from the stamps: the jump less the elapsed arrival time, at least
    one period. Estimates keep the sample's own stamp (the new clock: :meth:`as_sent`).
    Otherwise the held readings are judged as any other (a stale stamp), except that one
    stamped ahead of its stream or of its clock, which no later reading continued, is refused
    (``future_stamp``). A step smaller than ``back`` must also move every held reading's offset
    alike (their spread within the bar) and by more than half the bar: a node falling further
    behind its input puts readings below the centre each later than the one before, which is
    no step (they are released as late). A step within the bar is not told from arrival jitter
    and not re-anchored; without arrival times only steps beyond ``TOL`` are seen.

    Whatever its size, a step moves every later offset alike, so the held readings' offsets,
    in stamp order, are exchangeable under it; a link that queued them and now delivers them
    faster than they were sampled makes them climb back to the old clock instead. Kendall's
    rank test (:meth:`_returning`, exact and free of the latency's distribution) releases them
    at a p-value within ``trend_risk`` and makes the decision wait for more readings within
    ``TREND_WAIT``. A reading of a forward step's clock that came with enough latency to lie
    within the bar of the old clock but above its ceiling, where latency never puts the old
    clock's readings, joins the held ones instead of releasing them (:meth:`_above_old`).

    Where the train's sample grid is known (:class:`SampleGrid`, fed by :meth:`admitted`) it
    decides first: a reading on the grid is continuous however late it arrives, one off it is
    discontinuous however small the move, held readings belong to one new clock when their grid
    residuals agree, and the step is their median residual (``measured``, to the sampling
    jitter). A jittery link then neither hides a small step nor breaks a step's chain. Without
    it the stamps' sampling phase (:meth:`phase`) does the same for a step by a fraction of a
    period: a reading off the phase is discontinuous, held readings on one residual off it are
    a step whatever their offsets, and every step is put onto the phase when measured.

    The runner keeps admission (duplicates, sequence numbers, ``max_future``, the offsets' votes)
    and acts; this decides. :meth:`watch` answers one reading with a sequence of actions,
    judged one at a time: each held reading released is judged against the clock as the
    admission of the ones before it left it, so the runner must act on each action before
    taking the next. The runner tells it every odometer reading admitted (:meth:`admitted`).
    """

    def __init__(self, period: float, min_judged: int = 9, step_back: float = 0.3,
                 small_step: float = 0.05, small_step_z: float = 10.0,
                 max_future: float = 600.0, same: bool = False, trend_risk: float = 1e-3,
                 step_risk: float = 1e-7, false_step_rate: float = 1e-4, count: bool = True):
        self.period = period  # s, nominal odometer period
        self.count = count  # without a sample counter, judge the stamps by the odometer's
        #   count while moving (:meth:`_count_resid`)
        # the envelope test's p-value for a step: false steps at most false_step_rate per hour
        self.env_level = envelope.level(false_step_rate, period, TREND_N)
        # ... and the phase's: a stamp on it is judged off it at most as often (one per reading)
        self.phase_level = false_step_rate * period / 3600.0
        self._phase: tuple = (-min_judged, None)  # (admissions, phase()) when last fitted
        self.step_risk = step_risk  # -, the probability that readings held as a step are
        #   declared one while the old clock's readings were only lost (:func:`silence_risk`)
        self.trend_risk = trend_risk  # -, the probability that a true step's held readings
        #   look like a draining queue (:meth:`_returning`) and are released: it delays the
        #   step's decision, never makes one
        self.min_judged = min_judged  # arrivals before a clock is judged; the fewest readings
        #   of a step (more than the longest burst of alike wrong stamps covered)
        self.back = max(step_back, 2.5 * period)  # s: the bar on a jittery link (class doc)
        self.small_step, self.small_step_z = small_step, small_step_z
        self.max_future = max_future  # s: a reading this far above its clock is refused anyway
        self.same = same  # control_clock 'same': no forward steps, no small bar (sim time)
        self.resolution = 0.0  # s, how finely arrivals are timed (the runner's
        #   arrival_resolution: a simulated clock's tick)
        # the train clock (the runner's, fed by its admissions), known after min_judged
        self.clock = StreamClock(settled=min_judged)
        self.shift = 0.0  # s, train-clock steps so far: timeline stamps = raw - shift
        self.raised = 0.0  # s, the link's latency raised by the latency moves declared so far
        self._late: list = []  # the latest readings in a row (as held ones) that the grid or
        #   the count placed on its clock while their arrivals put them off it, on one side
        #   (:meth:`_latency_moved`)
        self.last: tuple | None = None  # (stamp, arrival) of the newest odometer admitted
        self.held: list = []  # (kind, stamp, fields, recv, arrival, refused): discontinuous
        self._pushed: tuple | None = None  # (stamp, arrival) of the last odometer watched
        self._admitted: list = []  # sorted recent odometer stamps admitted
        self._untimed: list | None = None  # [first stamp, readings on the old offset since,
        #   slots unfilled before it, whether the sample counter began again there] after a
        #   gap that nothing timed, until the readings after it show the old clock's offset
        #   (min_judged of them) or a decision is taken (:meth:`_note_silence`)
        self._seq_last = None  # the sample counter of the newest odometer reading admitted
        self._stray: tuple | None = None  # (stamp, arrival) of a reading of another topic
        #   that came later than lateness allows since the last odometer reading (:meth:`stray`)
        self._placement: dict = {}  # odometer stamp -> placed on its clock by the grid or
        #   the count when watched (the latest 64)
        self._n_admitted = 0  # odometer readings admitted so far
        self._sent: dict = {}  # timeline odometer stamp -> stamp as sent (after a step)
        self.grid = SampleGrid(period, min_judged)  # odometer stamps against their seq
        self._dist: tuple | None = None  # (stamp, counted distance, seq, speed) of the newest
        #   fused odometer reading
        self._count_e = Rows(4, 64)  # (r s, dt s, mean speed m/s, speed m/s) of
        #   the links of recent fused pairs (:func:`_count_link`)
        self._count_fit = (0.0, 0.0, (math.inf, 0.0, math.inf), math.inf)  # their rate, lag
        #   s, covariance, sd m (:func:`_count_fit`)
        from .count_fit import warm_up

        warm_up()  # (the fit's compiled code loaded now, while a node starts, not at a reading)
        self._count_n = 0  # links learnt so far
        self._lag_learnt = [1.0 / COUNT_LAG ** 2, 0.0]  # the lag's long memory (:meth:`fused`):
        #   information 1/s^2 and information times lag s, the prior's and the disjoint windows'
        #   of 64 links before the current window
        self._lag_block: tuple | None = None  # (links learnt at its end, lag, information) of
        #   the newest disjoint window, until the current window has left it
        self._rounded = False  # the count's rounding to its grid was seen (:meth:`_rounding_seen`)
        self._grids = (Grid(COUNT_GRIDS), Grid(SPEED_GRIDS), None)  # the count's and the speed's
        #   rounding (no counter; :attr:`count_grid`) and the stamps' (:attr:`stamp_grid`; made
        #   at the first stamp: stamps less it) (:meth:`_learn_grids`)
        self._stamp0 = 0.0  # s, the first stamp (:meth:`_rounding_seen`)
        self._stamps_rounded = False  # the stamps' rounding to their grid was seen
        self._accel = 0.0  # m/s^2, the train's acceleration by the fused readings' speeds
        self._slipped: set = set()  # timeline stamps of readings admitted off the count's clock
        #   within a slip's reach (:meth:`_count_off`): no link to them is learnt
        self._level = Rows(6, LEVEL_WINDOW)  # the count's links as in _count_e,
        #   (r s, dt s, mean speed m/s, speed m/s, timeline stamp and count m of the later
        #   sample), over a longer window (:meth:`_level_test`)
        self._arr: dict = {}  # timeline stamp -> arrival of the recent odometer readings admitted
        self._noise = [0.0, 0.0, 0.0, None]  # the count's noise over the run's steady stretches
        #   (:meth:`_learn_noise`): links learnt, the mean square of the links' residuals and
        #   of neighbours' products (exponentially weighted), the previous link's residual
        self.late: tuple | None = None  # (STEP or SLIP, first timeline stamp, s, count m):
        #   what the count's level test found among readings already fused (:meth:`_level_test`)
        #   from the odometer reading after the one of that count on, for the runner to act on
        #   (a step: re-stamp them)

    # -- stamps ---------------------------------------------------------------------------
    def onto_timeline(self, stamp: float, odometer: bool) -> float:
        """A train-clock stamp as sent -> the timeline before the steps (``stamp - shift``);
        an odometer reading's estimate is published at the stamp as sent, bit for bit."""
        if not self.shift:
            return stamp
        mapped = stamp - self.shift
        if odometer:
            self._sent[mapped] = stamp
        return mapped

    def as_sent(self, t: float) -> float:
        """The stamp to publish an estimate at timeline time ``t`` with: the sample's stamp as
        sent (the new clock), else ``t + shift`` (a predicted slot)."""
        stamp = self._sent.pop(t, None) if self._sent else None
        if stamp is None:
            stamp = t + self.shift
        if len(self._sent) > 1000:  # refused samples never emitted
            self._sent = {k: v for k, v in self._sent.items() if k > t}
        return stamp

    def admitted(self, kind: str, stamp: float, arrival: float | None, seq=None) -> None:
        """The runner admitted this train-clock reading (timeline stamp; ``seq`` its sample
        counter)."""
        if kind != "odometer":
            return
        self.grid.add(seq, stamp)
        before = self.last
        restarted = self._restarted(seq)
        if self.last is None or stamp > self.last[0]:
            self._seq_last = SampleGrid._seq(seq)
            if arrival is not None:
                self.last = (stamp, arrival)
        self._stray = None
        self._note_silence(stamp, arrival, before, restarted)
        bisect.insort(self._admitted, stamp)
        del self._admitted[:-128]
        self._n_admitted += 1
        if arrival is not None:
            self._arr[stamp] = arrival
            if len(self._arr) > 256:
                keep = sorted(self._arr)[-128:]
                self._arr = {k: self._arr[k] for k in keep}

    def _restarted(self, seq) -> bool:
        """Whether a reading's sample counter ``seq`` lies below the newest admitted one's:
        the counter began again (a unit that rebooted)."""
        n = SampleGrid._seq(seq)
        return n is not None and self._seq_last is not None and n < self._seq_last

    def _note_silence(self, stamp: float, arrival: float | None, before: tuple | None,
                      restarted: bool = False) -> None:
        """Whether the reading admitted at ``stamp`` is the first after a gap in the stream
        that neither the sample grid nor the count placed on its clock (a counter that
        restarted, a count that went back or whose link spans too long), a silence of the
        arrivals as well (:func:`paced` against ``before``, the newest reading admitted
        before it, as (stamp, arrival): stamps that jump ahead while readings keep coming are
        no silence): the two re-learn
        their references from the readings after it, which they then place wherever their
        stamps say, so until the readings show the old clock's offset again (``min_judged``
        of them within the bar) a latency decision on their word leaves a step back open
        (:meth:`_step_open`; ``_latency_moved``: a reboot with a -3 s step on metro_demo,
        cruising, published 174 estimates 62 m off within levels of 39-45 m).

        ``restarted``: the sample counter began again at this reading (a unit that rebooted).
        Its silence is then the unit's, not the link's losses (:meth:`_step_open`), and it is
        one even where the stamps show no gap while the arrivals do: a unit whose clock
        resumed where it stopped (stepped back by as long as it was silent) reads, stamp for
        stamp, as a link whose latency rose by that much (metro_demo, a 3 s reboot whose
        clock stepped back 3 s, cruising: taken for a latency with nothing beside it, 34
        estimates 63 m off within levels of 51-60 m)."""
        if self._untimed is not None and arrival is not None and self.clock.judged and \
                abs(stamp - arrival - self.clock.now(arrival)) <= self.bar(self.clock):
            self._untimed[1] += 1
            if self._untimed[1] >= self.min_judged:
                self._untimed = None
        adm = self._admitted
        if adm and stamp > adm[-1] and not self._placement.get(stamp, False) and \
                before is not None and arrival is not None and \
                paced(before, (stamp, arrival)):
            gap = self._gap(stamp, adm[-1])
            if gap or restarted and arrival - before[1] - (stamp - before[0]) > \
                    self.bar(self.clock):
                self._untimed = [stamp, 0, gap, restarted]

    def stray(self) -> float:
        """s: how far below its clock lies a reading of another topic that came later than
        lateness allows since the last odometer reading admitted (0: none). Where the
        odometer then falls silent the reading that decides is not coming, and the estimates
        are in doubt by that much (``IntegrityMonitor.clock``: a reboot with a -3 s step on
        metro_demo, its first balise stamped on the new clock refused as out of order, the
        slots predicted through the silence read 3 s off: 10 estimates 66 m off within
        levels of 65 m)."""
        if self._stray is None:
            return 0.0
        return max(-self.clock.above(self._stray[0] - self._stray[1]), 0.0)

    def untimed_moved(self) -> bool:
        """The readings admitted since an untimed gap (:meth:`_note_silence`) are in doubt:
        the newest lies where no lateness puts a reading of the old clock (below its centre by
        more than the clock's lateness bar, or above where it can be by more than
        ``step_back``), as :meth:`_conclusive` judges one held reading; a reading late by a
        jittery link's tail after a lost one is not."""
        if self._untimed is None or self.last is None or not self.clock.judged:
            return False
        v = self.last[0] - self.last[1]
        return self.clock.is_late(v) or self.clock.above(v) > self.back

    def _silent(self, n: int) -> bool:
        """``n`` held readings are enough for a step at ``step_risk``: the old clock's silence
        over them is that unlikely on this link (:func:`silence_risk`), its losses counted over
        the recent odometer stamps admitted (the slots between them, a nominal period apart,
        that none filled). Not the stamps' own period (their median step): that is two periods
        on a link that loses every other reading, which then looked lossless; a clock 1 % off
        the nominal rate miscounts one slot in a hundred."""
        return silence_risk(*self._losses(), n) <= self.step_risk

    def _losses(self) -> tuple[int, int]:
        """``(lost, got)``: the odometer slots of the recent stamps admitted that none filled
        (a nominal period apart, from the first to the newest), and the readings admitted."""
        adm = self._admitted
        got = len(adm)
        return (max(round((adm[-1] - adm[0]) / self.period) + 1 - got, 0) if got > 1 else 0,
                got)

    def stamp_period(self, n_min: int) -> float | None:
        """s, the median step between the recent odometer stamps admitted (a stream without a
        sample counter: lost samples make steps of two periods or more, fewer than half of
        them on any link the filters can use); None with fewer than ``n_min`` steps."""
        st = np.diff(np.asarray(self._admitted, float))
        st = st[st > 0]
        return median(st) if st.size >= n_min else None

    def phase(self) -> tuple | None:
        """The stream's sampling phase from the recent odometer stamps admitted, ``(P, s1, c,
        tol)``: a stamp on it lies ``c`` s past the newest ``s1`` plus whole periods ``P``
        (s), one whose residual is beyond ``tol`` lies off it; None before ``min_judged`` steps
        or without a phase (stamps scattered over the period). Refitted every ``min_judged``.

        The model: ``stamp = s1 + c + P k + e``, ``k`` whole (lost samples skip some), ``e``
        the sampling loop's own Gaussian scatter, not the link's (the stamp is taken with the
        sample). ``k`` is counted from the neighbour's (a period known to a stamp's scatter
        misplaces the stamps of two minutes), ``P`` is the median slope between stamps half
        the window apart, ``c`` the median residual, the scatter their robust spread, at least
        the stamps' resolution ``PHASE_RES``; ``tol`` its Student's t quantile at
        ``phase_level``: one reading judged per period, off the phase while on it at most
        ``false_step_rate`` times an hour. A step by a fraction of a period puts every later
        stamp off the phase, whatever the link's jitter (a -0.1 s step at 1 Hz moved the
        offsets within a 50 ms link's jitter, and nothing else saw it); a latency that moves
        leaves them on it (:meth:`_stamps_ran_on`)."""
        if self._n_admitted - self._phase[0] < self.min_judged:
            return self._phase[1]  # (it moves by far less than its tolerance meanwhile)
        out, p0 = None, self.stamp_period(self.min_judged)
        if p0:
            adm = self._admitted
            a = np.asarray(adm, float) - adm[-1]
            k = np.concatenate(([0.0], np.cumsum(np.round(np.diff(a) / p0))))
            h = len(a) // 2
            dk = k[h:] - k[:len(k) - h]
            P = median((a[h:] - a[:len(a) - h])[dk > 0] / dk[dk > 0])
            e = a - P * (k - k[-1])
            c = median(e)
            sd = max(1.4826 * median(np.abs(e - c)), PHASE_RES)
            tol = _t_bar(max(len(a) - 2, 1), 0.5 * self.phase_level) * sd
            if self._stamps_rounded:
                # stamps rounded to a grid hide the loop's scatter below half a step, and one
                # in so many lands a whole step off (_rounding_seen): 3.4 % of the estimates
                # were in doubt with a log's hundredths of a second and a 4 ms jittery loop
                tol += self.stamp_grid
            if tol < 0.25 * P:
                out = (P, adm[-1], c, tol)
        self._phase = (self._n_admitted, out)
        return out

    def phase_resid(self, stamp: float) -> float | None:
        """How far (s) ``stamp`` lies from the stream's sampling phase (:meth:`phase`), within
        half a period either side; None while it is not measured."""
        ph = self.phase()
        if ph is None:
            return None
        P, s1, c, _ = ph
        x = (stamp - s1) - c
        return x - P * round(x / P)

    def _chain_phase(self, chain: list) -> tuple | None:
        """``(r, off)``: the held odometer readings' common residual on the stream's phase (s)
        and whether it lies off it, when their residuals agree (within the phase's tolerance
        of one another: one clock), else None."""
        ph = self.phase()
        if ph is None or not chain:
            return None
        P, tol = ph[0], ph[3]
        rr = [self.phase_resid(h[1]) for h in chain]
        d = [x - rr[0] - P * round((x - rr[0]) / P) for x in rr]
        if max(d) - min(d) > 2.0 * tol:
            return None
        r = rr[0] + median(d)
        r -= P * round(r / P)
        return r, abs(r) > tol

    def fused(self, stamp: float, distance, seq=None, speed=None) -> None:
        """The filter fused this odometer reading (timeline stamp, counted distance m, its
        sample counter, speed m/s): the reference of :meth:`_plausible` and of the count's
        residual (:meth:`_count_resid`), whose scale it learns from consecutive fused readings
        at speed."""
        if isinstance(distance, int | float) and math.isfinite(distance) and \
                (self._dist is None or stamp > self._dist[0]):
            v = float(speed) if isinstance(speed, int | float) and math.isfinite(speed) \
                else None
            prev = self._dist
            self._dist = (stamp, float(distance), SampleGrid._seq(seq), v)
            if seq is None:  # (as watched, :meth:`_learn_grids`; a value seen twice is one)
                self._grids[0].add(float(distance))
                if v is not None:
                    self._grids[1].add(v)
            slipped = stamp in self._slipped
            if self._slipped:
                self._slipped = {x for x in self._slipped if x > stamp}
            if prev is not None and prev[2] is None and seq is None and not slipped:
                # (not to a reading that the count put off its clock as a slip may: a slide's
                # links learnt took the rate and the lag with them, and every braking after it
                # was misjudged)
                link = _count_link(prev[0], prev[1], prev[3], stamp, float(distance), v)
                if link is not None:
                    self._count_e.append((link[0], stamp - prev[0] - link[0], link[1], v))
                    self._count_n += 1
                    self._accel = _accel(self._count_e, COUNT_ACCEL_SPAN)
                    if not abs(self._accel) < COUNT_SLIP_ACCEL:
                        self._level.clear()  # (the level is tested over a steady stretch)
                        self._noise[3] = None
                    else:
                        self._level.append(self._count_e[-1] + (stamp, float(distance)))
                    if len(self._count_e) >= COUNT_LEARN:
                        self._count_fit = _count_fit(self._count_e, self._lag_prior())
                        if self._level:
                            self._learn_noise()
                            self._level_test()
                    if self._count_n % self._count_e.maxlen == 0:
                        # a disjoint window's own fit: what it says of the lag (a producer's
                        # speed lags its count alike all run; only braking and accelerating
                        # tell it, and a window of 64 links at 10 Hz is one cruise's 6 s)
                        _, lag, (_, _, c_ll), _ = _count_fit(self._count_e, None)
                        if math.isfinite(c_ll) and c_ll > 0.0:
                            self._lag_block = (self._count_n, lag, 1.0 / c_ll)

    @property
    def count_grid(self) -> float:
        """m, the grid that the odometer's counts (no counter) are rounded to (:class:`Grid`), 0
        where none."""
        return self._grids[0].q

    @property
    def stamp_grid(self) -> float:
        """s, the grid the odometer's stamps are rounded to (:class:`Grid`) where it is finer
        than a tenth of the period, else 0: stamps that all lie on the sampling's own grid (k /
        10 s at 10 Hz, whole seconds at 1 Hz) are the sampling's, exactly, and a whole-period
        step lies on that grid too; a rounded stamp leaves it whenever the loop's own jitter
        carries it across a line of the finer grid."""
        g = self._grids[2]
        return g.q if g is not None and g.q <= 0.1 * self.period else 0.0

    def _learn_grids(self, stamp: float, fields: dict) -> None:
        """Learn the producer's grids from an odometer reading (:class:`Grid`): its stamp's,
        and without a counter its count's and speed's."""
        if fields.get("seq") is None:
            self._grids[0].add(float(fields["distance"]))
            self._grids[1].add(float(fields["speed"]))
        if self._grids[2] is None:
            # (stamps at a Unix epoch: their float's own spacing, 2.4e-7 s at 1.7e9, bounds how
            # finely their grid is seen)
            self._stamp0 = stamp
            self._grids = self._grids[:2] + (Grid(STAMP_GRIDS, 8.0 * math.ulp(stamp)),)
        self._grids[2].add(stamp - self._stamp0)

    def _rounding_seen(self, r: float, tol: float, fields: dict, count: bool = True) -> bool:
        """Whether a held reading that no later one continued (:meth:`_release`; residual
        ``r`` s on the sample grid or the count's clock, ``tol`` its tolerance) first shows a
        rounding by its producer, off its clock beyond its tolerance by up to a step of it: of its
        count (:attr:`count_grid`, at its speed; where the speed carries the count across a
        grid line) or of its stamp (:attr:`stamp_grid`; where the sampling's own jitter
        carries a stamp across). From then on the tolerances hold the grid
        (:meth:`_count_resid`, :meth:`_resid_tol`, :meth:`phase`). An exact count or stamp
        never shows it, though one sampled at a steady speed and rate lies on a grid (2 m and
        0.1 s a sample at 20 m/s and 10 Hz), and a step's readings continue one another.
        ``count`` False: ``r`` is the stamp's residual on its sampling phase (:meth:`phase`),
        which says nothing of the count's rounding."""
        seen = False
        q, v = self.count_grid, fields.get("speed")
        if count and fields.get("seq") is None and not self._rounded and q > 0.0 and \
                abs(v) > 0.0 and abs(r * v) <= q + tol * abs(v):
            self._rounded = seen = True
        q = self.stamp_grid
        if not self._stamps_rounded and q > 0.0 and abs(r) <= q + tol:
            self._stamps_rounded = seen = True
            self._phase = (-math.inf, None)  # its tolerance refitted with the grid
        return seen

    def _lag_error(self, span: float, v: float) -> float:
        """s, the lag model's own error over ``span`` s of count at speed ``v``: it is first
        order (the speed tau ago is the speed less tau times the acceleration then), so an
        acceleration that changed by j (span + tau) within the span or the lag before it leaves
        up to j tau^2 / 2 of count per unit speed, j = ``COUNT_JERK``; tau the fitted lag and
        its standard deviation (before brakings measure it, the prior's)."""
        _, lag, (_, _, c_ll), _ = self._count_fit
        tau = abs(lag) + math.sqrt(c_ll)
        return COUNT_JERK * (abs(span) + tau) * tau * tau / (2.0 * v)

    def _learn_noise(self) -> None:
        """Learn the count's noise from the newest link of a steady stretch (:meth:`fused`):
        its residual less the count fit's rate, in metres at the link's speed (the count's
        noise is metres whatever the speed: learnt in seconds over a run that cruises at 20 and
        at 4 m/s, it was a fifth of a 4 m/s cruise's, and the test made false steps there),
        the mean square of those residuals and of neighbours' products, exponentially weighted
        over ``LEVEL_MEMORY`` links (the differences of the readings' noise: for noise of
        correlation r from one reading to the next, their lag-1 correlation is -(1 - r) / 2),
        each residual within 5 of the learnt spread (a step's link is no noise)."""
        rate = self._count_fit[0]
        r, dt, vbar = self._level[-1][:3]
        u = (r - rate * dt) * vbar  # (in metres: the count's noise is, whatever the speed)
        nl = self._noise
        if nl[0] >= COUNT_LEARN and nl[1] > 0.0:
            lim = 5.0 * math.sqrt(nl[1])
            u = min(max(u, -lim), lim)
        w = 1.0 / min(nl[0] + 1.0, LEVEL_MEMORY)
        nl[1] += w * (u * u - nl[1])
        if nl[3] is not None:
            nl[2] += w * (u * nl[3] - nl[2])
        nl[0] += 1
        nl[3] = u

    def _level_test(self) -> None:
        """A step of the stamps by a part of the count's noise, among the readings already
        fused (a stream without a counter): the count's clock moved by ``D`` s from some reading
        on, every later link continuing it. A chain's two ends cannot show it (-0.1 s at 10 Hz
        and 20 m/s is 2 m, within 3 of the two ends' noise at 0.5 m a reading, and the step
        watch's bar on a 50 ms link is 0.36 s), but the level of the count's cumulative residual
        (:func:`_count_fit`: ``R`` less its model, whose inner counts cancel, so that each
        reading carries its own noise alone) moves by ``D`` and stays.

        The test, over the steady stretch's last ``LEVEL_WINDOW`` links: a line (the stamps'
        rate against the count's) and one level move ``m`` readings back, for each ``m`` within
        ``LEVEL_SPAN``'s time, fitted by least squares; the largest move in its standard errors
        (the level's long-run variance from the noise learnt over the run,
        :meth:`_learn_noise`) is the generalised likelihood ratio of one move, at its most
        likely place. A step is declared beyond Student's quantile of ``phase_level``
        (``false_step_rate`` per hour, one test a reading) shared over the candidates, at least
        ``LEVEL_SPAN[0]`` readings back and larger than what the producer's roundings and the
        lag model's own error move a level by. Not while the train brakes or accelerates by
        ``COUNT_SLIP_ACCEL`` or more (a slip's count moves as a step's would: the held
        readings' tests judge those), nor while readings are held or a slip was let in.

        Then the arrivals, where they can tell the two apart: offsets that stayed where they
        were while the count moved (the log-likelihood ratio of the medians' move after and
        before the change, against one of ``D``, beyond ``LEVEL_LLR``) are the count's move (a
        wheel, a producer re-basing its count), not the clock's: the count's series carries
        it, no step; undecided, the next readings tell, up to the span's end (then the likelier
        of the two). Otherwise (or where the link's jitter cannot tell them apart) a step of
        ``D``, measured by the count, its part of a period the stamps' phase's where the stream
        has one: the readings from the change on are mapped onto the timeline again
        (:meth:`_restamp`; the runner fuses them again at their new stamps, :attr:`late`)."""
        n_min, span = LEVEL_SPAN
        n = len(self._level)
        m_max = min(n - LEVEL_PRE, int(span / self.period))
        if self.late is not None or m_max < n_min or self.held or self._slipped or \
                not abs(self._accel) < COUNT_SLIP_ACCEL or self._dist[3] is None:
            return
        rate, lag, _, sd = self._count_fit
        # the readings' noise as learnt over the run (:meth:`_learn_noise`): a window of a
        # hundred readings measures its long-run error too loosely for this test's level (a
        # white count's lag-1 correlation read 0.2-0.3 there)
        n_l, s0, s1, _ = self._noise
        if n_l < LEVEL_LEARN or not (math.isfinite(sd) and math.isfinite(rate) and
                                     math.isfinite(lag)):
            return
        rho = min(max(1.0 + 2.0 * s1 / s0, 0.0), 0.98) if s0 > 0.0 else 0.0
        q = self._level.array()
        # the cumulative residual less the speed's lag (_count_fit: R = c + a S + b ln v), its
        # line and a level move fitted anew (count_fit.level_scan, one compiled call): the
        # count fit's rate, over 64 links, leans towards a move at its end (-0.1 s read as
        # -0.06 s and a rate of -0.02 within 1.5 s of it)
        from .count_fit import level_scan

        v, span_all, span_m, m, d, den, z = level_scan(q, lag, rate, m_max)
        # What else moves the level, at the slowest link's speed: a count or stamps rounded by
        # their producer (their grids as learnt, seen or not: a level known to within the
        # rounding, whose offset moves wherever the speed or the sampling's phase changes; whole
        # metres at 20 m/s and 10 Hz show no noise, and their offset moved by 0.02 s from one
        # cruise to the next), a speed rounded to its grid (each link timed up to half of it
        # over the speed off: a rate that changes wherever the rounded speed does, up to that
        # share of the window's time), and the lag model's own error, first order
        # (_count_resid: an acceleration that changed within the readings after the move or
        # the lag before them; 3-4 ms at 4 m/s where a braked train sets off again, its speed
        # 0.3 s behind an exact count)
        grid = self.count_grid / v + self.stamp_grid + \
            span_all * self._grids[1].q / (2.0 * v) + self._lag_error(span_m, v)
        # the level's long-run variance: a reading's, s0 / (2 (1 - rho)) m^2 over the slowest
        # speed squared, times (1 + rho) / (1 - rho) for means of correlated readings (exact
        # counts and stamps: at least their resolution, and the bound above as a uniform error)
        var = max(s0 / (2.0 * (1.0 - rho) * v * v), PHASE_RES ** 2, grid * grid / 12.0) * \
            (1.0 + rho) / (1.0 - rho)
        # the move in its standard errors at its most likely place (located among all;
        # decided with n_min after it)
        z /= var
        if m < n_min or z <= _t_bar(min(int(n_l), LEVEL_MEMORY), 0.5 * self.phase_level /
                                    m_max) ** 2:
            return  # (a move most likely fewer than n_min readings back: the next ones tell)
        se = math.sqrt(var / den)
        stamps = q[:, 4].tolist()
        first, count0 = stamps[-m], float(q[-m - 1, 5])
        ph = self.phase()
        if ph is not None:
            # the stamps' phase gives the step's part of a period exactly (the readings after
            # it were on the phase, or they would have been held), the count the whole periods
            P = ph[0]
            c = median([self.phase_resid(x) for x in stamps[-m:]])
            snap = c + P * round((d - c) / P)
            if abs(snap - d) <= 3.0 * se:
                d = snap
        if abs(d) < max(TIE, grid):
            return  # no move worth a stamp (the phase puts it on none), or a rounding's
        offs = [[s - self._arr[s] for s in st if s in self._arr]
                for st in (stamps[-m:], stamps[-m - LEVEL_PRE:-m])]
        if len(offs[0]) >= n_min and len(offs[1]) >= n_min and len(self.clock) >= 3:
            # the arrivals' word: the medians' move after and before it, Gaussian to the link's
            # jitter; the log-likelihood ratio of offsets that moved by d (a step) against
            # offsets that stayed (the count's move: a wheel, a producer re-basing its count)
            moved = median(offs[0]) - median(offs[1])
            prec = 1.2533 * max(self.clock.jitter, 1e-3) * math.sqrt(1.0 / len(offs[0]) +
                                                                      1.0 / len(offs[1]))
            llr = arrivals_llr(d, moved, prec)
            if llr is not None:  # (they can tell the two apart)
                if -llr > LEVEL_LLR or (m == m_max and llr <= 0.0):
                    # the count moved, the stamps stayed: its series carries the move from here
                    self._link_less(first, d)
                    self.late = (SLIP, first, d, count0)
                    return
                if llr <= LEVEL_LLR and m < m_max:
                    return  # not yet: the next readings tell
        self._restamp(first, d)
        self.late = (STEP, first, d, count0)

    def _link_less(self, first: float, d: float) -> None:
        """The count's link into the reading at timeline stamp ``first`` less ``d`` s (a move
        found across it: the level after it is the level before), in both series."""
        lv = self._level
        j = next((k for k in range(len(lv) - 1, -1, -1) if lv[k][4] == first), None)
        if j is None:
            return
        r, dt, vb, vv, st, x = lv[j]
        lv[j] = (r - d, dt, vb, vv, st, x)
        k = len(self._count_e) - (len(lv) - j)
        if k >= 0:
            self._count_e[k] = (r - d, dt, vb, vv)
            self._count_fit = _count_fit(self._count_e, self._lag_prior())

    def _restamp(self, first: float, d: float) -> None:
        """A step of ``d`` s found among the readings fused from timeline stamp ``first`` on
        (:meth:`_level_test`): every later train-clock stamp is mapped ``d`` further back
        (:attr:`shift`), and so is every reference this watch keeps of the readings from
        ``first`` on."""
        def moved(x: float) -> float:
            return x - d if x >= first else x

        self.shift += d
        if self.last is not None:
            self.last = (moved(self.last[0]), self.last[1])
        if self._pushed is not None:
            self._pushed = (moved(self._pushed[0]), self._pushed[1])
        if self._dist is not None:
            self._dist = (moved(self._dist[0]),) + self._dist[1:]
        self._admitted = sorted(moved(x) for x in self._admitted)
        self._slipped = {moved(x) for x in self._slipped}
        self._arr = {moved(x): a for x, a in self._arr.items()}
        self._sent = {moved(x): a for x, a in self._sent.items()}
        self._link_less(first, d)  # the link across it: the stamps' step taken out
        self._level = Rows(6, self._level.maxlen,
                           (h[:4] + (moved(h[4]), h[5]) for h in self._level))
        self._phase = (-math.inf, None)

    def _lag_prior(self) -> tuple:
        """``(mean s, variance s^2)`` of the speed's lag behind its count before the current
        window of links: ``N(0, COUNT_LAG^2)`` and every disjoint window learnt before it
        (one that overlaps it would count its links twice), by their information."""
        b = self._lag_block
        if b is not None and b[0] <= self._count_n - self._count_e.maxlen:
            self._lag_learnt[0] += b[2]
            self._lag_learnt[1] += b[2] * b[1]
            self._lag_block = None
        info, m = self._lag_learnt
        return m / info, 1.0 / info

    # -- judging --------------------------------------------------------------------------
    def bar(self, clock: StreamClock) -> float:
        """How far (s) an offset may lie from ``clock`` before the reading is watched as a
        possible step: ``back`` on a jittery link or with ``control_clock 'same'``, down to
        ``small_step`` where the link's jitter (the offsets' robust spread) is small. A radio's
        jitter cannot shift every offset of nine readings in a row by the same amount, which a
        small step does: left unwatched, a 0.2 s step left the kf 4 m off at 20 m/s with a sigma
        of 0.1 m. Never below the arrival clock's ``resolution``: a message timed on a clock
        that ticks (/clock on simulated time) arrives up to a tick before the clock says so."""
        if self.same or not clock.judged:
            return max(self.back, self.resolution)
        return max(min(self.back, max(self.small_step, self.small_step_z * clock.jitter)),
                   self.resolution)

    def watch(self, kind: str, stamp: float, fields, recv, arrival: float, drift: float = 0.0):
        """What to do with a train-clock reading (timeline ``stamp``; ``recv`` None when the
        arrival is inferred; ``drift`` the train clock's rate minus 1 as the runner maps it, 0
        on one clock), once an odometer reading was admitted with its arrival. Yields
        actions, one at a time (class doc):

        - ``(ADMIT, (kind, stamp, fields, recv, arrival))``: a held reading to admit (unwatched);
        - ``(REFUSE, kind, stamp, ahead)``: a held reading stamped ``ahead`` s ahead of its
          stream or clock, that no later reading continued: refuse it (``future_stamp``);
        - ``(STEP, shift, first, measured, unsure)``: a step of ``shift`` s (now in
          :attr:`shift`), its first reading at timeline stamp ``first`` (before this shift),
          ``measured`` from the arrivals or assumed from the stamps (class doc); ``unsure``: a
          step back after a silence that nothing timed, which a latency that rose as much
          explains as well (:meth:`_step_open`); the held readings follow as ADMITs;
        - ``(LATENCY, moved, unsure)``: no step, the link's latency moved by ``-moved`` s and
          stays (the clock's offset follows it); ``unsure``: after a silence that nothing
          timed, where a step back by as much explains the readings as well;
        - ``(SKIP, samples)``: no step, the sample counter moved by ``samples`` (< 0: back)
          while the stamps and arrivals ran on; the grid is re-learnt and the held readings
          follow as ADMITs (judged as any other);
        - ``(SLIP, r)``: no step, the odometer's count (no counter) left its speed by ``r`` s
          of count time (a wheel that slid or slipped) while the stamps and arrivals stayed on
          their clock (:meth:`_count_moved`; or this reading alone, where its arrival tells);
          the count's chain restarts at the next fused reading and the held readings follow as
          ADMITs (judged as any other);
        - last, for this reading: ``(PASS, stamp)``, go on judging it at this timeline stamp
          (mapped when it completed a step; one beyond ``max_future`` is held only as evidence
          for a step and passes, to be refused at the door as always), or ``(HOLD,)``, nothing
          more to do (held, or judged among the released)."""
        tol = TOL
        s0, a0 = self.last
        # Back by more than step_back: possibly a small backward step (a clock resynchronised
        # by a few seconds), held until later readings decide. A reading late by jitter is
        # held too, and released (then fused by rewinding) by the next reading that continues
        # the stream, one period later.
        back = self.back
        med = self.clock
        bar = self.bar(med)
        # ... and so is a reading whose stamp - arrival fell by more than that below its
        # clock's on-time centre: late (jitter, released by the next reading on time), or the
        # first of a small backward step whose stamps overlap those already fused (then the
        # readings that follow stay that far below: min_judged of them are the step)
        # (arriving at the stamps' pace: a backlog's burst, all late, arrives at once and is
        # no step)
        prev = self._pushed
        if kind == "odometer":
            self._pushed = (stamp, arrival)
        elif recv is not None and med.judged and med.is_late(stamp - arrival):
            # a reading of another topic on this clock, later than lateness allows: a latency
            # tail, or the first of a clock stepped back, which the next odometer reading
            # decides (:meth:`stray`)
            self._stray = (stamp, arrival)
        chain = [h for h in self.held if h[0] == "odometer"]
        # the pace against the previous reading, or against the first held one: between two
        # neighbours a link's jitter alone breaks the pace (50 ms of exponential jitter at 10
        # Hz: one reading in six), and such a reading, taken as continuous, released a step's
        # held readings as late ones and let the filter fuse them at the old clock's times
        # (-0.5 s step: the kf 10 m off with a sigma of 0.1 m); a backlog's burst arrives at
        # once and is paced against neither
        on_pace = prev is None or paced(prev, (stamp, arrival)) or \
            (bool(chain) and paced((chain[0][1], chain[0][4]), (stamp, arrival)))
        behind = kind == "odometer" and on_pace and med.judged and \
            stamp - arrival - med.now(arrival) < -bar
        # Ahead by more than that above where the clock can be (its centre, and the ceiling of
        # its offsets: latency only ever lowers stamp - arrival, an outage moves stamps and
        # arrivals alike): a forward step or one wrong stamp; held until later readings decide
        # Not with control_clock "same" (the simulator's launch, sim time): a node's sim clock
        # stalls under load and stamps then run ahead of arrivals by seconds
        ahead = not self.same and recv is not None and \
            med.judged and med.above(stamp - arrival) > bar
        # above the ceiling by more than small_step, where under the old clock only the least
        # late reading of all lands: possibly a small forward step, held and judged on the
        # envelope (module envelope: a +0.1 s step hid in a 50 ms jitter's 0.36 s bar)
        # (on one clock: drift 0, see _envelope)
        lift = med.lift(stamp - arrival) if kind == "odometer" and not drift and \
            not self.same and recv is not None and med.judged and \
            envelope.holds(1, 1, med.ceiling_n, TREND_WAIT) else -math.inf
        continuous = -back <= stamp - s0 <= max(arrival - a0, 0.0) + tol and not behind \
            and not ahead and not lift > self.small_step
        # The sample grid decides where it is known: a stamp on the train's own grid is on
        # the clock, however late it arrives; one off it by more than the grid's tolerance
        # is not, however small the move (a 0.1 s step hides in a link's jitter, and the kf
        # then stayed 2 m off with a sigma of 0.1 m for 7 s)
        if kind == "odometer" and isinstance(fields, dict) and self._plausible(stamp, fields):
            self._learn_grids(stamp, fields)
        r, r_tol = self._resid_tol(kind, stamp, fields, chain)
        seq = fields.get("seq") if isinstance(fields, dict) else None
        if r is not None and seq is None and abs(r) > r_tol and not chain and on_pace and \
                recv is not None and med.judged and self._arrival_stayed(r, stamp - arrival,
                                                                         arrival, med):
            # The count (no counter) puts it r s off its clock while its arrival tells that the
            # stamps did not move (_arrival_stayed): the count left the train's course (it
            # froze, counts at another rate, slid), not the stamps. The count is then no
            # evidence on this stamp: judged by the arrivals and the phase as without a count,
            # no link of the count's chain learnt into it, its content left to the filter and
            # to the count's exclusion. (Taken as a stamp ahead, every reading of a count frozen
            # while the train braked was refused, the estimate had no odometer for 70 s, and
            # then took up the frozen count again 6.8 km behind the train.) Logged as the
            # count's slip, as a held chain's (_count_moved) is.
            self._slipped.add(stamp)
            yield SLIP, r
            r = None
        if r is not None and seq is None and abs(r) <= r_tol:
            # the count (no counter) places it on its clock within r_tol: a move of the bar's
            # size (behind, ahead, a stamp jump) is excluded, a small forward step on the
            # envelope only where the count resolves small_step, a fraction of a period off
            # the phase never; below, the arrivals and the phase judge what it leaves open
            continuous = not (lift > self.small_step and r_tol >= self.small_step)
            r, placed = None, True
        else:
            placed = r is not None and abs(r) <= r_tol  # on the grid
        if r is not None:
            continuous = placed
        if kind == "odometer":
            self._placement[stamp] = placed
            if len(self._placement) > 64:
                del self._placement[next(iter(self._placement))]
        if placed:  # on the count's or the grid's clock: the latency, if its arrival is off
            yield from self._latency_moved((kind, stamp, fields, recv, arrival, False),
                                           behind, ahead, med)
        if r is None and continuous and kind == "odometer":
            # without the grid, the stamps' sampling phase (:meth:`phase`): a reading off it is
            # not the stream's clock as it was, however small the move
            off = self.phase_resid(stamp)
            continuous = off is None or abs(off) <= self.phase()[3]
        # above the old clock's ceiling, on the clock of readings held as a forward step
        on_new = kind == "odometer" and self._above_old(chain, stamp - arrival, recv, bar)
        if continuous and r is None and on_new:
            continuous = False  # it joins them (below)
        # held as a small forward step (_envelope): a reading of the new clock may come as late
        # as to lie within the old clock's envelope; it joins them while at least half of
        # them lie above the old ceiling (a step of d puts a reading there when its latency's
        # excess is below d: half or more of them for a step beyond the excess's median)
        env = self._envelope(chain, bar, drift) if r is None and kind == "odometer" else None
        env_join = env is not None and -bar <= lift <= self.back and \
            (not continuous or not self._sampled_before(chain, stamp, seq, r)) and \
            envelope.holds(env[0] + 1, env[1] + (lift > 0.0), med.ceiling_n, TREND_WAIT)
        if env_join:
            continuous = False
        if kind != "odometer" and chain:
            # a balise while odometer readings are held as a possible step: its stamp is on
            # the same clock, in the same doubt, and waits with them (taken at once, a balise
            # 3 s into a -3 s step was placed 60 m off, refused by the gate, and its doubt held
            # the estimate DEGRADED until the next balise)
            continuous = False
        if continuous:
            if kind == "odometer" and self.held and not self._sampled_before(chain, stamp,
                                                                             seq, r):
                yield from self._release()
            yield PASS, stamp
            return
        refused = stamp - arrival - med.value > self.max_future
        entry = (kind, stamp, fields, recv, arrival, refused)
        if kind == "odometer" and chain:
            _, s1, _, _, a1, _ = chain[-1]
            rs = self._chain_resid(chain)
            if rs is not None and r is not None:  # one new clock: one residual
                joins = abs(r - rs[len(rs) // 2]) <= r_tol
            else:
                joins = continues((s1, a1), (stamp, arrival)) or \
                    self._joins(chain, stamp, arrival, bar) or on_new or env_join
            if not joins:
                yield from self._release()
                chain = []
        self.held.append(entry)
        self.held.sort(key=lambda h: (h[0] != "odometer", h[1]))
        if kind == "odometer":
            chain = [h for h in self.held if h[0] == "odometer"]
        rs = self._chain_resid(chain)
        # enough readings: more than the longest burst of readings stamped alike wrongly that
        # the design covers (min_judged: such a burst and a step undone after as many readings
        # are the same data), and as many as the old clock's silence needs at step_risk on
        # this link (_silent: its readings lost, not ended)
        if len(chain) < self.min_judged or not self._silent(len(chain)):
            yield (PASS, stamp) if refused else (HOLD,)
            return
        step = is_step([(h[1], h[4]) for h in chain], self.min_judged, self.period)
        # the first reading of the new clock came (elapsed arrival time, at least one period)
        # after the last one of the old clock
        first, a_first = chain[0][1], chain[0][4]
        shift = first - (s0 + max(a_first - a0, self.period))
        offs = sorted(h[1] - h[4] for h in chain)  # the new clock's offsets (stamp - arrival)
        new_off = offs[len(offs) // 2]
        if rs is not None and \
                self._counter_restarted(chain, r := rs[len(rs) // 2], new_off, med):
            # the counter began again on a clock that stepped with it: the grid re-learns the
            # counter from these readings and no longer times them; their arrivals do (below)
            self.grid.reset()
            for h in chain:
                self.grid.add(h[2].get("seq"), h[1])
            yield SKIP, -round(r / self.period)
            rs = None
        ph = self._chain_phase(chain) if rs is None else None
        p_trend = self._returning(chain, med) if rs is None else 1.0
        if p_trend <= self.trend_risk:
            # the held readings drift back towards the old clock: a queue draining (a link
            # that delayed its packets by a second, then delivered them faster than they were
            # sampled), not a step, which moves every later offset alike; late readings
            # (released, fused by rewinding)
            yield from self._release()  # this reading with them: judged there
            yield (HOLD,)
            return
        if p_trend <= TREND_WAIT:  # undecided: the next readings tell
            yield (PASS, stamp) if refused else (HOLD,)
            return
        off = ph is not None and ph[1]
        env = self._envelope(chain, bar, drift) if rs is None and not off else None
        if rs is not None:
            # the grid measures the step exactly (the link's jitter does not enter); without a
            # counter the count measures it to its noise, and the stamps' phase gives the part
            # of a period exactly where the stream has one (the count the whole periods)
            shift = rs[len(rs) // 2]
            if chain[0][2].get("seq") is None and (cph := self._chain_phase(chain)) is not None:
                P = self.phase()[0]
                shift = cph[0] + P * round((shift - cph[0]) / P)
                if abs(shift - rs[len(rs) // 2]) > max(t for _, t in map(
                        lambda h: self._resid_tol(h[0], h[1], h[2], chain), chain)):
                    # no step the stamps' phase allows is where the count puts them (a part
                    # of a period is the phase's, exactly): the count left its speed (after a
                    # slide, the last of its links before the held readings) -- taken for a
                    # step of the phase's, 0 s
                    yield from self._count_slipped(rs[len(rs) // 2])
                    return
        elif off:
            pass  # off the stream's phase together: a step, whatever its size (measured below)
        elif env is not None:
            # on the envelope: min_judged of them above the old ceiling (more than the longest
            # burst of alike wrong stamps covered), as unlikely under one clock as the stated
            # false-step rate allows (envelope.level); else the next readings tell, up to
            # TREND_N held
            k, j = env
            if j < self.min_judged or envelope.above_p(k, j, med.ceiling_n) > self.env_level:
                if k >= TREND_N:
                    yield from self._release()
                    yield (HOLD,)
                    return
                yield (PASS, stamp) if refused else (HOLD,)
                return
        elif abs(shift) < back:
            # a small step (below step_back) moves every offset of the new clock alike: its
            # readings agree with one another. A node falling further behind its input also
            # puts readings below the centre, each later than the one before: no step, late
            # readings (released, fused by rewinding); and a shift well inside the bar that
            # held them is none (a node catching up)
            if offs[-1] - offs[0] > bar or abs(shift) < 0.5 * bar:
                yield from self._release()  # this reading with them: judged there
                yield (HOLD,)
                return
        if not step:
            yield (PASS, stamp) if refused else (HOLD,)
            return
        if rs is not None and self._counter_moved(chain, r := rs[len(rs) // 2], new_off, med):
            # the sample counter moved, not the clock: the grid learns the counter's new
            # origin from these readings, which are then judged as any other (on time)
            self.grid.reset()
            for h in chain:
                self.grid.add(h[2].get("seq"), h[1])
            yield SKIP, -round(r / self.period)
            yield from self._release()  # this reading with them
            yield (HOLD,)
            return
        if rs is not None and self._count_moved(chain, r := rs[len(rs) // 2], new_off, med):
            yield from self._count_slipped(r)
            return
        measured = all(h[3] is not None for h in chain) and med.judged
        # the new clock's offsets less the old clock's, carried to the held readings' middle
        moved = new_off - med.now(chain[len(chain) // 2][4]) if measured else math.nan
        # the stamps ran on where the old clock's would have: the link's latency rose and
        # stays (a route change), not the clock (module doc of _stamps_ran_on). A latency
        # that rose lowers the offsets (``moved`` < 0): held readings whose first stamp lies
        # before the old clock's newest (``shift`` < 0: a late reading of the old clock among
        # them) but whose offsets rose are a forward step, not a route
        route = rs is None and env is None and not off and measured and shift < 0 and \
            moved < 0 and self._stamps_ran_on(chain, s0)
        # the stamps fell back after a gap that neither the count nor the grid timed: where
        # the link's losses leave it open (:meth:`_step_open`), a step back and a latency that
        # rose by as much differ only in how long the gap lasted, so whichever is taken the
        # other is carried beside it (the runner tells the integrity monitor) until a balise
        # places the train
        after = [h for h in chain if h[1] > s0 + 0.5 * self.period]
        gap = self._gap(min(h[1] for h in after), s0) \
            if after and measured and paced((s0, a0), min((h[1], h[4]) for h in after)) \
            else None
        # (the sample counter began again with them: the unit rebooted, and was silent as
        # long as that took, whatever its stamps say)
        fields0 = min(after, key=lambda h: h[1])[2] if after else None
        restarted = isinstance(fields0, dict) and self._restarted(fields0.get("seq"))
        untimed = not off and measured and (
            rs is None and gap is not None and self._step_open(gap, moved, restarted)
            or self._untimed is not None and self._step_open(self._untimed[2], moved,
                                                             self._untimed[3]))
        self._untimed = None
        if rs is not None:
            measured = True
        elif measured:
            # arrivals known: the step is how far the new clock's offsets lie from the old
            # clock's centre, the median of the chain's (two readings' arrivals, the last of
            # the old clock and the first of the new, put a link's jitter into the step whole:
            # 0.17 s with 50 ms of exponential jitter, the kf 55 estimates wrong-side once
            # re-anchored)
            shift = moved
        if ph is not None:
            # the stamps' phase measures the step's part of a period exactly, the arrivals (or
            # the stamps' jump) how many whole periods it adds; so the stamps mapped stay on
            # the stream's phase
            P = self.phase()[0]
            shift = ph[0] + P * round((shift - ph[0]) / P)
        # a clock stepped forward by ``shift`` stamps its first reading a period and the shift
        # after the old clock's last (more where readings were lost): one stamped sooner is the
        # old clock's stream arriving sooner, its latency fell back by at most what the latency
        # moves declared raised it (a queue's readings back on time after its drain was taken
        # for a slower route), no step. (Taken for steps: a queue draining at 1.2x made 4 an
        # hour of +0.3-0.4 s and the filter's time 1.4 s off.) Either way the clock's offset
        # follows the latency, nothing is re-anchored
        if route or (rs is None and measured and 0 < moved <= self.raised + self.small_step
                     and first < s0 + shift + 0.5 * self.period):
            med.move(moved)
            self.raised -= moved
            yield LATENCY, moved, untimed and route
            yield from self._release()  # this reading with them, now on time
            yield (HOLD,)
            return
        unsure = untimed and shift < 0
        self.shift += shift
        old = self.shift - shift
        if rs is None:  # measured otherwise: the grid's stamps may no longer continue
            self.grid.reset()
        held, self.held = self.held, []
        for h in held:
            if h[0] == "odometer" and (not h[5] or h is entry):
                self._sent[h[1] - shift] = h[1] + old  # as sent
        yield STEP, shift, first, measured, unsure
        for h in held:
            k, st, f, rc, ar, ref = h
            if h is entry or ref:
                continue
            # another topic's reading held with the step's: on the new clock when its offset
            # lies nearer theirs than the old clock's centre (a late one of the old clock is
            # not moved)
            on_new = k == "odometer" or rc is None or not len(med) or \
                abs(st - ar - new_off) <= abs(st - ar - med.value)
            yield ADMIT, (k, st - shift if on_new else st, f, rc, ar)
        yield PASS, stamp - shift

    def _latency_moved(self, entry: tuple, behind: bool, ahead: bool, med: StreamClock):
        """A reading the count or the grid placed on its clock although its arrival put it
        ``behind`` the clock by more than the bar (or ``ahead``, within the latency raised so
        far): the link's latency, not the stamps. An isolated one is jitter; ``min_judged`` in
        a row on one side (as many as a step needs), whose offsets do not climb back towards
        the clock (:meth:`_returning`: a queue draining), are a latency that moved and stays,
        which the clock's offset follows as for the arrivals' route answer (yields
        ``(LATENCY, moved)``). Left there after a route change, every later reading came
        late: fused by rewinding, the estimates published late, and where the train slowed
        below the count's speed the arrivals held them as a step (0.3 s more of silence on
        crh3_high_speed's 1.5 s route change at 1 Hz)."""
        v = entry[1] - entry[4] - med.now(entry[4])
        side = -1 if behind else 1 if ahead and 0.0 < v <= self.raised + self.small_step \
            else 0
        if not side or self.held or entry[3] is None:
            self._late = []
            return
        if self._late and (self._late[0][1] - self._late[0][4] > med.now(entry[4])) != \
                (side > 0):
            self._late = []
        self._late = (self._late + [entry])[-TREND_N:]
        if len(self._late) < self.min_judged:
            return
        p = self._returning(self._late, med)
        if p <= self.trend_risk:
            self._late = []  # a queue draining: late readings, fused by rewinding
            return
        if p <= TREND_WAIT:
            return  # undecided: the next readings tell
        moved = median([h[1] - h[4] - med.now(h[4]) for h in self._late])
        self._late = []
        med.move(moved)
        self.raised -= moved
        untimed = self._untimed is not None and moved < 0 and \
            self._step_open(self._untimed[2], moved, self._untimed[3])
        self._untimed = None
        yield LATENCY, moved, untimed

    def _envelope(self, chain: list, bar: float, drift: float) -> tuple[int, int] | None:
        """(k, j): the held odometer readings (``chain``) and how many of them lie above the
        old clock's ceiling, when they are held as a small forward step
        (:func:`~.envelope.candidate`), else None. Only on one clock (the runner's drift 0):
        carried along a rate fit, the ceiling is as wrong as the fit, and the envelope has no
        room for that."""
        med = self.clock
        if self.same or drift or not med.judged or \
                any(h[3] is None for h in chain):
            return None
        return envelope.candidate([med.lift(h[1] - h[4]) for h in chain], med.ceiling_n,
                                  self.small_step, self.back, bar, TREND_WAIT)

    def _returning(self, chain: list, med: StreamClock) -> float:
        """How likely, were the held odometer readings (``chain``, in stamp order; arrivals
        known, the clock judged) a step, a trend of their offsets back towards the old clock at
        least as strong as theirs: the exact one-sided p-value of Kendall's rank statistic
        (:func:`kendall_tail`); 1 when it cannot be judged.

        A step moves the offsets of every later reading alike: in stamp order they are the
        new level less independent latencies, exchangeable, so that each order of their ranks
        is as likely as any other whatever the link's latency distribution. A queue that
        drains does not: its readings came late by a latency that falls reading after
        reading, so their offsets climb back to the old clock in stamp order (a link that
        held its packets for a second, then delivered 20 readings in 1 s: nine of them, 1.0
        to 0.6 s late, were taken for a -0.78 s step, and every later reading was fused 0.78
        s off its time). :meth:`watch` releases them at a p-value within ``trend_risk`` (the
        rate at which a true step's readings are released: its decision then waits for the
        next ones) and waits for more readings within ``TREND_WAIT`` (a queue that drains
        slowly against the link's jitter shows its trend over more readings)."""
        if not med.judged or any(h[3] is None for h in chain):
            return 1.0
        drift = med.drift  # the clock's own rate moves the offsets too: taken out
        chain = chain[:TREND_N]  # (a queue shows its trend from its first readings on)
        a0 = chain[0][4]
        offs = [h[1] - h[4] - drift * (h[4] - a0) for h in chain]
        n = len(offs)
        # inversions towards the old clock: pairs (earlier stamp, later stamp) whose later
        # offset is nearer the old clock's centre (above it for readings held below it)
        # (offsets within TIE of each other are ties, counted half: a link without jitter
        # gives equal offsets up to rounding, which has no order)
        up = 1.0 if sorted(offs)[n // 2] < med.value_at(a0, drift) else -1.0
        tie = max(self.resolution, TIE)
        inv = 0.0
        for i in range(n):
            for j in range(i + 1, n):
                d = up * (offs[i] - offs[j])
                inv += 1.0 if d > tie else 0.5 if d >= -tie else 0.0
        return kendall_tail(n, math.ceil(inv))

    def _stamps_ran_on(self, chain: list, s0: float) -> bool:
        """Whether the held odometer readings' stamps continue the old clock's stream: each on
        its sampling phase (:meth:`phase`), after its newest stamp ``s0`` or else in a slot the
        stream never filled, within its memory (a slower route's first readings reordered by
        the link). Their offsets fell as a backward step's would, but a step moves the stamps:
        by a fraction of a period off the phase, by whole ones onto slots already admitted; a
        latency that rose and stays (a slower route) leaves them where they were. Taken for a
        -1.5 s step without a counter, crh3_high_speed's estimates were up to 119 m off. (A
        step by whole periods whose first readings were all lost reads as one too: at 10 Hz
        with 5 % lost, a -0.5 s step one time in 3e7.) Without a measured phase: a step.

        After a silence that the link's losses do not make (:meth:`_step_open`) the phase
        is the only word: a step by whole periods lands on it as well, and its readings
        would have landed on admitted slots only had the silence been shorter than it. A
        route is then the likelier (a clock set again by GPS or NTP is on the phase one time
        in ``P / 2 tol``), not a certain one, and the runner carries the step beside it."""
        ph = self.phase()
        if ph is None:
            return False
        P, tol, adm = ph[0], ph[3], self._admitted
        for h in chain:
            if not abs(self.phase_resid(h[1])) <= tol:
                return False
            if h[1] < s0 + 0.5 * P:
                i = bisect.bisect_left(adm, h[1] - tol)
                if h[1] < adm[0] - tol or i < len(adm) and adm[i] <= h[1] + tol:
                    return False
        return True

    def _gap(self, first: float, s0: float) -> int:
        """The odometer slots between the stamp ``s0`` and ``first`` that nothing filled."""
        return max(round((first - s0) / self.period) - 1, 0)

    def _step_open(self, unfilled: int, step: float, restarted: bool = False) -> bool:
        """Whether the link's losses leave a step back of ``|step|`` s open where the readings
        say a latency rose as much (or the other way round): the latency needs ``unfilled``
        slots lost in a row before the readings, the step ``|step| / period`` more (its first
        readings would have landed on them). The losses tell them apart only where the first
        silence is one they make (at more than ``step_risk``, :func:`silence_risk`) and the
        second is not; after a silence they do not make (an outage, a sensor that rebooted)
        the two differ only in how long it lasted, which nothing states: so always after a
        sample counter that began again (``restarted``), whose unit was silent as long as it
        took to boot."""
        if restarted:
            return True
        lost, got = self._losses()
        m = max(round(abs(step) / self.period), 1)
        return silence_risk(lost, got, unfilled) <= self.step_risk or \
            silence_risk(lost, got, unfilled + m) > self.step_risk

    def _above_old(self, chain: list, v: float, recv, bar: float) -> bool:
        """Whether a reading of offset ``v`` (stamp - arrival) that is within the bar of the
        old clock lies on the clock of the odometer readings held above it (``chain``, a
        possible forward step) instead: above the old clock's ceiling by more than
        ``small_step`` -- where no latency puts a reading of the old clock, since latency only
        lowers an offset and the ceiling is the offset of the least latency seen -- and not
        above the held readings' own offsets by more than the bar (some latency on their
        clock). The bar is a tolerance for the old clock's jitter below its centre; above its
        ceiling there is none to tolerate: after a +0.5 s step on a 50 ms jittery link the
        third reading of the new clock, 0.23 s late, lay 0.26 s above the ceiling, within the
        0.3 s bar; taken as the old clock's, it released the two held before it (refused as
        stamped ahead), lifted the ceiling, and the step was absorbed: the rest of the run was
        fused 0.5 s off its time."""
        if self.same or not chain or recv is None or any(h[3] is None for h in chain) or \
                not self.clock.judged:
            return False
        offs = sorted(h[1] - h[4] for h in chain)
        ceiling = self.clock.ceiling
        if not (math.isfinite(ceiling) and offs[len(offs) // 2] > ceiling + bar):
            return False  # the held readings are no forward step
        return self.clock.above(v) > self.small_step and v <= offs[-1] + bar

    def _sampled_before(self, chain: list, stamp: float, seq, r) -> bool:
        """Whether a reading on the old clock was sampled before the held ones (``chain``, the
        odometer readings held): a late reading of the old clock, which says nothing against
        them being a new clock -- only the old clock running on after them does. By the sample
        counter where the grid places the reading (its seq below the first held one's); else
        by its stamp, below where the old clock stood when the first held reading arrived
        (that arrival plus the clock's ceiling, the offset of the least latency: a reading
        stamped below it was sampled before that arrival whatever its own latency). Released
        by such a reading, the first three readings after a -0.5 s step without a counter on a
        50 ms jittery link were fused as the old clock's late ones, 0.5 s off their time (10 m
        at 20 m/s)."""
        if not chain:
            return False
        first_seq = chain[0][2].get("seq")
        if r is not None and isinstance(first_seq, int) and isinstance(seq, int):
            return seq < first_seq
        a1, ceiling = chain[0][4], self.clock.ceiling
        return a1 is not None and math.isfinite(ceiling) and stamp < a1 + ceiling

    def _counter_moved(self, chain: list, r: float, new_off: float, med: StreamClock) -> bool:
        """Whether the held readings that the grid puts ``r`` s off (a whole number of periods)
        are a sample counter that skipped or repeated samples rather than a clock step: the
        grid's ``r`` a whole number of periods, and their arrivals on the old clock
        (:meth:`_arrivals_stayed`). A train's sampling loop that misses a cycle counts on; its
        stamps do not move, nor do their arrivals: taken for a -1 s step at 1 Hz, the
        estimates were 81 m off and ALARM for half of the next minute."""
        return self._counter_off(chain, r) and self._arrivals_stayed(chain, r, new_off, med)

    def _counter_off(self, chain: list, r: float) -> bool:
        """Whether the grid puts the held readings, every one with a sample counter, a whole
        number (not 0) of periods ``r`` s off: their counter moved, whatever their clock did
        (:meth:`_counter_moved`, :meth:`_counter_restarted`). Without a counter the residual
        is the count's, which a counter cannot move."""
        if any(h[2].get("seq") is None for h in chain):
            return False
        k = round(r / self.period)
        return k != 0 and abs(r - k * self.period) <= max(self.grid.tol_at(h[2].get("seq"))
                                                          for h in chain)

    def _count_slipped(self, r: float):
        """The held readings that the count put ``r`` s off its clock are a count that left its
        speed, not a clock step: the count's chain restarts at the next fused reading (the
        speed taken off the reference: no link to it is learnt, no residual is chained through
        it), and the held readings are judged as any other, by their arrivals."""
        self._dist = self._dist[:3] + (None,)
        yield SLIP, r
        yield from self._release()  # this reading with them
        yield (HOLD,)

    def _count_moved(self, chain: list, r: float, new_off: float, med: StreamClock) -> bool:
        """Whether the held readings that the odometer's count (no counter) puts ``r`` s off
        its clock are a count that left its speed rather than a clock step: their arrivals on
        the old clock (:meth:`_arrivals_stayed`). The count is a clock only while the wheel it
        counts rolls: a wheel that slides under braking (or spins in traction) counts less (or
        more) than the train runs, and a speed from another source (a radar, another axle)
        does not follow it, so every link of the slide adds its share to the count's residual,
        which then stays where the slide left it. The stamps stay on their clock, and so do
        their arrivals: a 15 % slide for 3 s in each braking, taken for +0.4 s steps, made a
        false step per braking and refused the readings after it as stamped ahead."""
        if any(h[2].get("seq") is not None for h in chain):
            return False
        if self._arrivals_stayed(chain, r, new_off, med):
            return True
        # within a slip's reach of the newest fused reading (:meth:`_slip_room`) at the first
        # held reading on their level (a step puts the first there, a slide the first after
        # it ends), the count alone cannot tell a slip from a step: a step only where the
        # arrivals moved with it (:meth:`_arrivals_moved`)
        rts = [self._resid_tol(h[0], h[1], h[2], chain) for h in chain]
        at = next((h[1] for h, (rh, th) in zip(chain, rts) if abs(rh - r) <= th), chain[0][1])
        if not abs(r) <= max(t for _, t in rts) + self._slip_room(at, r):
            return False
        return not self._arrivals_moved(chain, r, new_off, med)

    def _arrivals_moved(self, chain: list, r: float, new_off: float, med: StreamClock) \
            -> bool:
        """Whether the held readings' arrivals moved ``r`` s off the old clock with them
        (:func:`arrivals_llr` beyond ``LEVEL_LLR``, where they can tell)."""
        m = self._arrivals_shift(chain, new_off, med)
        llr = arrivals_llr(r, *m) if m is not None else None
        return llr is not None and llr > LEVEL_LLR

    def _arrivals_stayed(self, chain: list, r: float, new_off: float, med: StreamClock) \
            -> bool:
        """Whether the held readings' arrivals put them on the old clock while the grid or the
        count puts them ``r`` s off it (:func:`arrivals_llr` below ``-LEVEL_LLR``, where they
        can tell). (With 3 and 6 of the median's precision as bars, a count re-based by 4 m at
        20 m/s on a 50 ms link, whose arrivals moved 27 ms against 0.26 s, 3.2 precisions,
        was a step of -0.3 s.) And they must lie on it, within the clock's bar or three
        precisions: arrivals that moved by neither ``r`` nor 0 stayed on no clock (a reboot
        whose clock stepped -10 s, its counter begun again ``r`` = +95 s off the grid, was
        read as a counter that moved and a clock that stayed: estimates 146 m off within
        levels of 36 m; :meth:`_counter_restarted`)."""
        m = self._arrivals_shift(chain, new_off, med)
        llr = arrivals_llr(r, *m) if m is not None else None
        return llr is not None and llr < -LEVEL_LLR and self._arrivals_at(m, 0.0, med)

    def _arrival_stayed(self, r: float, off: float, arrival: float, med: StreamClock) -> bool:
        """Whether one reading's arrival (offset ``off`` s at ``arrival``) tells that its stamp
        did not move by the ``r`` s its count puts it off its clock. A link's latency is its
        floor plus a one-sided excess, about exponential: a stamp moved by ``r`` puts the offset
        ``r`` further from where the link's excess would have put it, so that for a reading
        within the clock's envelope the likelihood ratio of "stayed" against "moved" is
        exp(|r| / j), j the excess's mean (the robust spread, 1.4826 MADs, is 0.71 of an
        exponential's mean), whatever the reading's own latency. Beyond ``LEVEL_LLR`` (|r| >
        4.5 j), and the offset nearer the clock's centre than the move (which stands in for
        the envelope: the ceiling itself is not asked): it stayed. (A Gaussian of the
        spread took a late reading of a +0.1 s step on a 50 ms link, its offset 0.1 s below the
        clock's centre, for one that stayed.)"""
        j = max(med.jitter, 1e-3) / 0.71
        moved = off - med.now(arrival)
        return abs(r) > LEVEL_LLR * j and abs(moved) < abs(moved - r)

    def _counter_restarted(self, chain: list, r: float, new_off: float, med: StreamClock) \
            -> bool:
        """Whether the held readings are a sample counter that began again (the grid puts them
        a whole number of periods ``r`` s off, as :meth:`_counter_moved`) on a clock that
        stepped as well: their arrivals moved, by neither 0 (a counter alone) nor ``r`` (a
        clock alone), beyond the clock's bar or three precisions of either. A unit that
        rebooted with its clock: the grid no longer times these readings, the arrivals do."""
        if not self._counter_off(chain, r):
            return False
        m = self._arrivals_shift(chain, new_off, med)
        return m is not None and not self._arrivals_at(m, 0.0, med) and \
            not self._arrivals_at(m, r, med)

    def _arrivals_at(self, m: tuple, x: float, med: StreamClock) -> bool:
        """Whether the held readings' arrivals, moved ``m`` = (s, precision s) off the old
        clock (:meth:`_arrivals_shift`), lie ``x`` s off it: within the clock's bar or three
        precisions of the median's."""
        return abs(m[0] - x) <= max(self.bar(med), 3.0 * m[1])

    def _arrivals_shift(self, chain: list, new_off: float, med: StreamClock) -> tuple | None:
        """``(moved s, its precision s)``: how far the held readings' offsets (their median
        ``new_off``) lie from the old clock's centre, and the median's precision (1.25 robust
        spreads of the link's jitter over the square root of the readings); None unless every
        arrival is known and the clock holds at least three offsets."""
        # (three offsets that agree place a clock: a counter that skips in the first seconds
        # of a 1 Hz run, taken for a step, put an estimate 3 s past the run's end)
        if any(h[3] is None for h in chain) or len(med) < 3:
            return None
        return new_off - med.now(chain[len(chain) // 2][4]), \
            1.2533 * max(med.jitter, 1e-3) / math.sqrt(len(chain))

    def _placed(self, kind: str, stamp: float, fields, chain: list | None = None) \
            -> float | None:
        """The residual of a reading the grid places, or the count places off its clock (a
        count's residual within its tolerance, or one a slip may have put in, leaves a small
        move open: None)."""
        r, tol = self._resid_tol(kind, stamp, fields, chain)
        if r is not None and isinstance(fields, dict) and fields.get("seq") is None and \
                not self._count_off(stamp, r, tol):
            return None
        return r

    def _count_off(self, stamp: float, r: float, tol: float) -> bool:
        """Whether one reading that the count (no counter) puts ``r`` s off its clock has a
        wrong stamp rather than a count that left its speed: beyond its tolerance ``tol`` and
        what a slip may have put in (:meth:`_slip_room`). With exact counts, every reading of a
        15 % slide in braking was refused as stamped ahead: 3 s of the odometer lost in every
        braking, then a false step of +0.4 s. A persistent level is judged as a chain
        (:meth:`watch`, :meth:`_count_moved`)."""
        return abs(r) > tol + self._slip_room(stamp, r)

    def _slip_room(self, stamp: float, r: float) -> float:
        """s: how far a slip of the counted wheel may have put a reading stamped ``stamp`` off
        the count's clock (residual ``r``) since the newest fused reading: ``COUNT_SLIP`` of
        the stamps' time between them, where the train decelerates (a slide: the count falls
        behind, ``r > 0``) or accelerates (a spin: ``r < 0``) by ``COUNT_SLIP_ACCEL`` or more;
        else none. A slide moves the count a little at every sample, a clock step the stamps
        at once: -1 s at 1 Hz or -0.1 s at 10 Hz puts a reading on the stamp of the one before
        it, and no slip puts any count there; a cruise (the wheel rolls) leaves no room."""
        ref = self._dist
        if ref is None:
            return 0.0
        a = self._accel
        # (a reading stamped before the fused one, arrived late, lies back along the count: its
        # residual's sign turns)
        fwd = r if stamp >= ref[0] else -r
        if (fwd > 0.0 and a <= -COUNT_SLIP_ACCEL) or (fwd < 0.0 and a >= COUNT_SLIP_ACCEL):
            return COUNT_SLIP * abs(stamp - ref[0])
        return 0.0

    def _resid_tol(self, kind: str, stamp: float, fields, chain: list | None = None) -> tuple:
        """``(r, tol)``: the reading's residual (s) on the sample grid, or for a stream without
        a sample counter on the count's clock (:meth:`_count_resid`, through the held readings
        ``chain``), and its tolerance; ``(None, inf)`` when neither places it (not an odometer
        reading, the grid not trusted, the train slow, or a reading whose values no train could
        produce: a corrupted copy is no evidence about the clock, and the filters' gates refuse
        it)."""
        if kind != "odometer" or not isinstance(fields, dict) or not self._plausible(stamp,
                                                                                  fields):
            return None, math.inf
        seq = fields.get("seq")
        if seq is None:
            return self._count_resid(stamp, fields, chain or [])
        r = self.grid.residual(seq, stamp)
        # (a stamp rounded to its grid: up to a step off, _rounding_seen)
        return (r, self.grid.tol_at(seq) + (self.stamp_grid if self._stamps_rounded else 0.0)) \
            if r is not None else (None, math.inf)

    def _count_resid(self, stamp: float, fields: dict, chain: list) -> tuple:
        """``(r, tol)``: how far (s) the reading's stamp lies from where the old clock would
        have stamped it, timed by the odometer's count from the newest fused reading: each link
        between two samples next in count (the fused one, the held ``chain``, this one) adds
        its stamps' difference less the count's time between them (:func:`_count_link`), so a
        step of any size shows whole in every later reading, and a jittery link's arrivals do
        not enter. The count's time is taken at the rate learnt from the fused pairs, and the
        sum less what the speed's lag put in between the chain's two ends (:func:`_count_fit`).
        ``tol``: ``COUNT_Z`` learnt standard deviations of the count at the two ends (the fit's
        robust scale, m, over the slowest link's mean speed; the inner samples' counts cancel)
        and of the model over the chain (the rate's and the lag's covariance), plus the
        trapezoid's error at a jerk of ``COUNT_JERK`` in each link and the lag model's own (it
        is first order: an acceleration that changed within the chain or the lag before it
        leaves up to ``COUNT_JERK (span + tau) tau^2 / 2`` of count, ``tau`` the lag and its
        standard deviation); ``(None, inf)`` while fewer than ``COUNT_LEARN`` residuals were
        learnt, the train slow or reversing, a link longer than ``COUNT_SPAN``, or a tolerance
        that resolves less than the arrivals' bar."""
        ref = self._dist
        if not self.count or ref is None or len(self._count_e) < COUNT_LEARN or \
                ref[2] is not None or ref[3] is None:
            return None, math.inf
        rate, lag, (c_rr, c_rl, c_ll), sd = self._count_fit
        d = fields.get("distance")
        # the samples before this one in count order: the fused one, then the held ones
        pts = [(ref[1], ref[0], ref[3])]
        for h in chain:
            f = h[2]
            if h[0] == "odometer" and isinstance(f, dict) and h[1] != stamp and \
                    isinstance(f.get("distance"), int | float) and ref[1] < f["distance"] < d:
                pts.append((f["distance"], h[1], f.get("speed")))
        pts.sort(key=lambda q: q[0])
        pts.append((d, stamp, fields.get("speed")))
        r, jerk, span, vmin = 0.0, 0.0, 0.0, math.inf
        for (d0, s0, v0), (d1, s1, v1) in zip(pts, pts[1:]):
            link = _count_link(s0, d0, v0, s1, d1, v1)
            if link is None:
                return None, math.inf
            dt = (s1 - s0) - link[0]  # the count's time between them
            r += link[0] - rate * dt  # the stamps' difference less the count's time, at its rate
            jerk += COUNT_JERK * abs(dt) ** 3 / (12.0 * link[1])
            span += dt
            vmin = min(vmin, link[1])
        # less what the speed's lag put in (_count_fit: -lag ln(v1 / v0) over the chain)
        dl = math.log(pts[-1][2] / pts[0][2])
        r += lag * dl
        # the inner samples' counts cancel in the sum (each adds to one link what it takes from
        # the next): the count's noise is the two ends', at the slowest link's speed; the model's
        # error over the chain, (span, -dl) through the fit's covariance
        model = math.sqrt(max(span * span * c_rr - 2.0 * span * dl * c_rl + dl * dl * c_ll, 0.0))
        jerk += self._lag_error(span, vmin)
        # a count rounded to a grid (count_grid) is off by at most half of it at each end:
        # bounded, not Gaussian, and seen seldom where the speed moves the rounding's phase
        # slowly (a robust scale learns nothing of it, and the crossings were refused as off
        # the clock: whole metres and km/h at 20 m/s, 215 readings in 10 min), once the
        # rounding was seen (watch: an exact count at 20 m/s and 10 Hz lies on whole metres
        # and never shows it)
        # and a speed rounded to its grid times the count by up to half of it over the mean
        # speed (whole km/h at 4 m/s: 3.5 % of each link's time, refused at a braking's onset); and
        # stamps rounded to theirs hide the sampling's own jitter where it is below half a
        # step (a log's hundredths of a second, a loop 3 ms jittery: nine stamps in ten on the
        # nominal slot, the robust scale 0, and the tenth a whole step off, refused): up to a
        # step at each end
        tol = COUNT_Z * sd / vmin + jerk + max(COUNT_Z * model + 1e-5 * abs(span), TIE) + \
            (self.count_grid / vmin if self._rounded else 0.0) + \
            abs(span) * self._grids[1].q / (2.0 * vmin) + \
            (2.0 * self.stamp_grid if self._stamps_rounded else 0.0)
        if tol >= self.bar(self.clock):
            return None, math.inf
        return r, tol

    def _plausible(self, stamp: float, fields: dict) -> bool:
        """Speed within ``MAX_SPEED`` and the counted distance within reach of the newest fused
        reading's at that speed (and a period's slack)."""
        v, d = fields.get("speed"), fields.get("distance")
        if not (isinstance(v, int | float) and math.isfinite(v) and isinstance(d, int | float)
                and math.isfinite(d)) or abs(v) > MAX_SPEED:
            return False
        if self._dist is None:
            return True
        s0, d0, q0, _ = self._dist
        # the time between the two samples: their stamps', or their counters' when these say
        # more (after a backward step the stamps lie close while the train ran on: a genuine
        # reading 3 s after a -3 s step at 80 m/s was taken for a corrupted one, and the step
        # was measured from the arrivals instead of the grid); without counters, the count's
        # time at the reading's speed, up to COUNT_SPAN (the same reading 1 s after a -1 s step
        # at 20 m/s, stamped as the last fused one, was taken for a corrupted one: the chain's
        # count left unresolved, the step measured from the arrivals a period off)
        q = SampleGrid._seq(fields.get("seq"))
        dt = abs(stamp - s0)
        if q is not None and q0 is not None:
            dt = max(dt, abs(q - q0) * self.period)
        elif q is None and q0 is None and abs(v) >= COUNT_MIN_SPEED:
            dt = max(dt, min(abs(d - d0) / abs(v), COUNT_SPAN))
        return abs(d - d0) <= MAX_SPEED * (dt + self.period) + 1.0

    def _chain_resid(self, chain: list) -> list | None:
        """The held odometer readings' grid (or count) residuals, sorted, when the grid (or
        the count) places them all and they agree (a new clock: one residual), else None."""
        rts = [self._resid_tol(h[0], h[1], h[2], chain) for h in chain]
        if not rts or any(r is None for r, _ in rts):
            return None
        tol = max(t for _, t in rts)
        rs = sorted(r for r, _ in rts)
        if chain[0][2].get("seq") is None and abs(rs[len(rs) // 2]) <= tol:
            return None  # the count does not resolve their move: the arrivals and phase judge
        return rs if rs[-1] - rs[0] <= 2.0 * tol else None

    @staticmethod
    def _joins(chain: list, stamp: float, arrival: float, bar: float) -> bool:
        """A reading that does not continue the last held one but belongs to their clock: a
        stamp not seen among them, within their span or a period or so past it, with an offset
        that agrees with theirs (within ``bar`` of their median). A jittery link delivers a new
        clock's readings out of order as it does the old one's (the first two readings after a
        -0.5 s step swapped, and the first was released as a late reading of the old clock)."""
        stamps = [h[1] for h in chain]
        if stamp in stamps or not min(stamps) - TOL < stamp < max(stamps) + TOL:
            return False
        offs = sorted(h[1] - h[4] for h in chain)
        return abs(stamp - arrival - offs[len(offs) // 2]) <= bar

    def _release(self):
        """No step after all: the held readings are judged as any other (stale, late, ...) --
        but a reading stamped *ahead* of its stream that no later reading confirmed is refused:
        one corrupt stamp (a flipped bit, 60 s ahead) admitted here became the stream's newest
        stamp, every genuine reading after it looked discontinuous, and a clock step of -60 s
        was declared (kf 1.3 km off with a covariance of centimetres)."""
        held, self.held = self.held, []
        s0, a0 = self.last
        for k, st, f, rc, ar, ref in held:
            if ref:
                continue
            ahead = st - s0 - max(ar - a0, 0.0)
            # above its clock's centre (arrival known): no forward step confirmed it
            lead = self.clock.above(st - ar) if rc is not None else -math.inf
            if ahead > TOL or lead > self.back:
                yield REFUSE, k, st, max(ahead, lead)
                continue
            # off the sample grid, and no step: its stamp lies about when it was sampled (a
            # copy 0.5 s ahead was admitted and fused 10 m off its time)
            r, r_tol = self._resid_tol(k, st, f)
            if r is not None and abs(r) > r_tol and self._rounding_seen(r, r_tol, f):
                r, r_tol = self._resid_tol(k, st, f)  # a rounding's crossing, not its stamp's
            elif r is None and k == "odometer" and (ph := self.phase()) is not None:
                # where nothing places it on its clock (count_clock off, the train slow) its
                # phase may show the stamps' rounding as well (38-58 estimates in doubt in 10
                # min with a log's hundredths of a second, none refused)
                off = self.phase_resid(st)
                if abs(off) > ph[3]:
                    self._rounding_seen(off, ph[3], f, count=False)
            if r is not None and (abs(r) > r_tol if f.get("seq") is not None
                                  else self._count_off(st, r, r_tol)):
                yield REFUSE, k, st, r
                continue
            if r is not None and abs(r) > r_tol:
                self._slipped.add(st)  # the count's, not the stamp's (_count_off)
            yield ADMIT, (k, st, f, rc, ar)

    # -- the integrity monitor's view -----------------------------------------------------
    def doubt(self) -> tuple[int, float, bool]:
        """(odometer readings held, the largest discontinuity among the held readings (s), and
        whether one of them is conclusive: :meth:`_conclusive`)."""
        s0, a0 = self.last
        odo = [h for h in self.held if h[0] == "odometer"]
        doubt = max((abs(h[1] - s0 - (h[4] - a0)) for h in self.held), default=0.0)
        # the grid's residual is the step itself (exact), where the link put jitter into it;
        # a held reading the grid places is off it, and in doubt at once
        rs = [self._placed(*h[:3], odo) for h in odo]
        doubt = max([doubt] + [abs(r) for r in rs if r is not None])
        n, conclusive = len(odo), any(r is not None or self._conclusive(h[1], h[3], h[4])
                                      for h, r in zip(odo, rs))
        if any(h[0] == "balise" and h[3] is not None and
               self.clock.above(h[1] - h[4]) > self.back for h in self.held):
            # a balise held above where its clock can be: a forward step or a wrong stamp, in
            # doubt at once as such an odometer reading is (a reboot with its clock stepped +3 s
            # on metro_demo: the odometer silent, the slots predicted through the silence on
            # the old clock were read 3 s off on the new one, 48 estimates 63 m off within
            # levels of 65 m)
            n, conclusive = max(n, 1), True
        if self.untimed_moved():
            # the readings admitted since an untimed silence, off the old clock's offset: the
            # clock is in question until a decision (the grid and the count, re-learnt from
            # them, place the held readings on their new clock and see no discontinuity)
            n, conclusive = max(n, 1), True
            doubt = max(doubt, abs(s0 - a0 - self.clock.now(a0)))
        return n, doubt, conclusive

    def _conclusive(self, stamp: float, recv, arrival) -> bool:
        """One held odometer reading that no lateness explains: stamped above its clock's
        centre (latency only lowers stamp - arrival), or behind the newest one on a slot already
        fused, or where readings were fused at the slot's pace all along (a late reading fills
        a slot that has none).
        Not yet a step (:func:`is_step` decides), but the estimate is in doubt at once: at 1 Hz,
        waiting for a second reading left one estimate wrong-side after a -3 s step. With a
        period over 0.5 s so is any held reading not on the stream's sampling phase at a slot
        not yet filled (below)."""
        if recv is not None and self.clock.above(stamp - arrival) > self.back:
            return True
        adm = self._admitted
        i = bisect.bisect_left(adm, stamp)
        near = min((abs(adm[k] - stamp) for k in (i - 1, i) if 0 <= k < len(adm)),
                   default=math.inf)
        if near < 0.25 * self.period or \
                (0 < i < len(adm) and adm[i] - adm[i - 1] < 1.5 * self.period):
            return True
        # the odometer silent before it (nothing admitted for 1.5 periods): the reading that
        # would decide may not come soon either, as at a slow rate (a reboot whose clock
        # stepped back 3 s: the slots predicted through its silence, published while its
        # first reading was held, were read 3 s off)
        late = recv is not None and -self.clock.above(stamp - arrival) > self.clock.late
        if self.period <= 0.5:
            return late and self.last is not None and \
                arrival - self.last[1] > 1.5 * self.period
        if late:
            # later than the clock's lateness bar: a latency tail that long, or the first of a
            # clock stepped back, whose slot's estimate then claims another time (a -10 s step
            # on crh3_high_speed without a counter: the 8 readings it held were refused as
            # stale when the ninth came on the old grid, and the slot published with that
            # one alone held was 790 m behind the train)
            return True
        # A slow odometer: the next reading, which decides, comes later than an alarm may
        # wait, so a held reading is in doubt at once -- except one on the stream's sampling
        # phase (:meth:`phase`) at a slot not yet filled: a late reading of the slot it was
        # due for (a latency tail). A backward step lands there only by whole periods, on a
        # slot already fused. (Every held reading at 1 Hz was in doubt: a 1 s latency cap cost
        # 9 % of the estimates.)
        ph, off = self.phase(), self.phase_resid(stamp)
        return i == 0 or ph is None or stamp - adm[i - 1] < 0.5 * ph[0] or abs(off) > ph[3]
