"""The measured data's two clocks, offline (pure; docs/interfaces.md, "The measured data's clocks").

Odometer and balise stamps come from the train's clock (any epoch, a small drift); control is
stamped on the reference clock, which is also the clock of the bag's log (receive) times. The
odometer's (stamp, log time) pairs tie the two together by least squares,

    r = alpha + beta (s - t_first)            (r: log time, s: odometer stamp)

with the link's mean latency inside ``alpha`` (it cannot be told apart from an offset: an
analysis that needs command timing to better than the latency profiles a command offset, as
``diagnose`` does). ``diagnose`` and ``identify`` read bags through this one fit.

Latency is never negative, and a recorder (or the node behind it) that stalls logs its backlog
late, all at once: an 8 s stall in a 10-minute bag moved the least-squares fit's command timing
by up to 0.2 s, as large as the brake delays ``diagnose`` looks for. So the fit is refitted
without the readings logged grossly late (residual above the median by more than
``LATE`` s and ``LATE_SCALES`` robust standard deviations): a radio's jitter, tens of
milliseconds, never comes near, so an undisturbed bag keeps the plain least-squares fit.

Online, :class:`StreamClock` is the streaming counterpart of :class:`ClockFit`: it follows one
clock's offset against the arrival clock and (for the train clock) its rate, one reading at a
time, as the :class:`~train_estimation.core.online.runner.EstimatorRunner` admits them, and
:func:`is_step` is its step test. Both wings judge lateness by the one rule below.

Lateness, the one rule. Latency is never negative, so ``stamp - arrival`` of a reading can only
fall below where its clock is. A reading whose ``stamp - arrival`` lies more than ``LATE`` s
below its clock's centre (online: the robust centre of the recent offsets; offline: the fit,
i.e. a log time more than ``LATE`` s after the fitted one -- the same quantity with the sign
turned) *came late*: a backlog after a stalled recorder or node, a retried packet. Its arrival
says how late it came, not where its clock is: it does not vote for the offset, does not inform
the rate, and is left out of the offline fit. ``LATE`` is above a radio's jitter (p99 of 20 ms +
Exp(50 ms) is 0.25 s) and below the stalls worth excluding (seconds). Offline the bar is raised
to ``LATE_SCALES`` robust standard deviations for a link whose jitter is wider (the whole bag is
there to measure it); online the window is too short to measure a tail, so the bar is ``LATE``.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

LATE = 0.5  # s: a reading this much later than its clock says came late (module doc)
LATE_SCALES = 10.0  # robust standard deviations of the residuals, for links with a wide jitter


@dataclass(frozen=True)
class ClockFit:
    t_first: float  # s, first odometer stamp (train clock)
    alpha: float  # s, reference time of the first stamp (log-time offset, latency included)
    beta: float  # s/s, reference seconds per train-clock second (1 + drift)

    @classmethod
    def fit(cls, stamps: np.ndarray, recv: np.ndarray) -> ClockFit:
        """Least squares of log times on stamps (sorted odometer stamps, their log times),
        refitted without the readings logged grossly late (module doc)."""
        s = np.asarray(stamps, float)
        r = np.asarray(recv, float)
        t_first = float(s[0])
        x = s - t_first
        if s.size < 2 or np.ptp(x) <= 0:
            return cls(t_first, float(np.mean(r) - np.mean(x)), 1.0)
        A = np.stack([np.ones_like(x), x], axis=1)
        keep = np.ones(s.size, bool)
        for _ in range(5):  # the late set settles in two or three rounds
            coef, *_ = np.linalg.lstsq(A[keep], r[keep], rcond=None)
            e = r - A @ coef
            centre = np.median(e[keep])
            scale = 1.4826 * np.median(np.abs(e[keep] - centre))
            late = e - centre > max(LATE, LATE_SCALES * scale)
            if np.array_equal(~late, keep) or late.sum() > s.size // 2 or np.ptp(x[~late]) <= 0:
                break
            keep = ~late
        return cls(t_first, float(coef[0]), float(coef[1]))

    def ref_of_train(self, s):
        """Train-clock stamps -> reference seconds since the first odometer stamp."""
        return self.beta * (np.asarray(s, float) - self.t_first)

    def ref_of_control(self, c):
        """Control stamps (reference clock) -> the same reference seconds."""
        return np.asarray(c, float) - self.alpha

    def train_of_control(self, c):
        """Control stamps -> the train clock (where identify reads every time)."""
        return self.t_first + self.ref_of_control(c) / self.beta


def control_on_train_clock(odo_stamp, odo_recv, ctrl_stamp, ctrl_recv,
                           same_clock_tolerance: float = 2.0) -> np.ndarray:
    """Control stamps on the odometer's clock.

    Unchanged when the two streams are on one clock (their median ``stamp - log time``
    offsets agree within ``same_clock_tolerance`` s, as the runner's ``auto`` decides: a
    simulator's bag, or a bag logged on a clock unrelated to both); else mapped through the
    :class:`ClockFit` of the odometer."""
    s, r = np.asarray(odo_stamp, float), np.asarray(odo_recv, float)
    c, rc = np.asarray(ctrl_stamp, float), np.asarray(ctrl_recv, float)
    if s.size < 2 or c.size == 0 or rc.size != c.size:
        return c
    if abs(np.median(s - r) - np.median(c - rc)) < same_clock_tolerance:
        return c
    order = np.argsort(s, kind="stable")
    fit = ClockFit.fit(s[order], r[order])
    if not 0.5 < fit.beta < 1.5:  # log times on yet another time base: nothing to map with
        return c
    return fit.train_of_control(c)


# -- online ----------------------------------------------------------------------------------

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


class StreamClock:
    """One clock against the arrival clock, streaming (the counterpart of :class:`ClockFit`).

    ``offset``: the robust centre of the last ``n`` offsets ``stamp - arrival``, the densest
    one (most others within ``TOL``), the median of the densest on ties. A plain median fails
    when over half of a window is wild (a fuzzed stream); wild stamps scatter, while good ones
    agree to milliseconds. ``drift``: the clock's rate minus 1, least squares of stamps on the
    arrivals of readings on time (:meth:`rate_point`). Lateness by the module's one rule.
    """

    def __init__(self, n: int = 31):
        self.n, self.fifo, self.sorted = n, deque(), []
        self.arrivals: deque = deque()  # arrival (s, or None) of each offset in fifo
        self._value = None  # cached centre (recomputed after an add)
        self.pending: list = []  # consecutive values away from a full window's centre
        self._fit = [0, 0.0, 0.0, 0.0, 0.0, 0.0, None]  # n, sx, sy, sxx, sxy, syy, origin
        self._reg_last: tuple | None = None  # (stamp, arrival) of the last point in the fit
        self._top: deque = deque()  # (index, offset), decreasing: the sliding maximum
        self._pushed = 0  # offsets pushed so far

    tol = TOL
    late = LATE
    horizon = 600  # offsets over which the ceiling is the maximum (1 min at 10 Hz)
    settled = 9  # offsets in the window before its centre says where the clock is (the
    #   runner's min_judged): earlier ones do not lift the ceiling

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
        # advance with the arrival frozen. Taken for a step, such a burst moved one clock's
        # centre by seconds and not the other's, so "auto" judged the clocks separate and
        # mapped the commands seconds off (tens of metres of error after an 8 s recorder
        # stall). So the far run must also be paced (:func:`paced`); older values of a run
        # that is not are dropped from it.
        if len(self.fifo) >= self.n and -self.tol <= v - self.value < -self.late:
            # came late (module doc): neither votes nor informs the rate
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
            for p, a in self.pending[:-1]:
                self._push(p, at=a)
            self.pending = []
        elif self.pending:
            self.pending = []
        self._push(v, lift, at)

    @staticmethod
    def _persists(run: list) -> bool:
        """A run of far (offset, arrival) values that is paced: a clock step, not a backlog."""
        (v0, a0), (v1, a1) = run[0], run[-1]
        if a0 is None or a1 is None:
            return True
        return paced((v0 + a0, a0), (v1 + a1, a1))

    def _push(self, v: float, lift: bool = True, at: float | None = None) -> None:
        self._value = None
        self._pushed += 1
        self.fifo.append(v)
        self.arrivals.append(at)
        bisect.insort(self.sorted, v)
        if len(self.fifo) > self.n:
            old = self.fifo.popleft()
            self.arrivals.popleft()
            del self.sorted[bisect.bisect_left(self.sorted, old)]
        if len(self.fifo) <= self.settled or not lift:
            return
        # only offsets that voted once the clock had a centre: among the first few a wild
        # stamp (1e9 s ahead) votes unjudged, and as the ceiling it hid every forward step and
        # stamp ahead for `horizon` readings (a fuzzed 1 Hz stream: a reading stamped 5 s
        # ahead then took a genuine one's slot). Later ones are judged before they vote (the
        # runner holds a reading above the ceiling by more than its bar), so one lifts it by
        # no more than that bar
        while self._top and self._top[-1][1] <= v:
            self._top.pop()
        self._top.append((self._pushed, v))
        if self._top[0][0] <= self._pushed - self.horizon:
            self._top.popleft()

    def __len__(self) -> int:
        return len(self.fifo)

    def on_time(self, v: float) -> bool:
        """``v`` (stamp - arrival) is at most ``LATE`` s below the centre, and not far above."""
        return -self.late <= v - self.value <= self.tol

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

    @classmethod
    def _centre(cls, s: list) -> float:
        """The densest value of the sorted ``s`` (most others within ``tol``), the median of
        the densest on ties."""
        if not s:
            return math.nan
        counts = [bisect.bisect_right(s, v + cls.tol) - bisect.bisect_left(s, v - cls.tol)
                  for v in s]
        best = max(counts)
        dense = [v for v, c in zip(s, counts) if c == best]
        return dense[len(dense) // 2]

    def value_at(self, at: float | None, drift: float) -> float:
        """The offset at arrival ``at`` (s) of a clock whose offset moves by ``drift`` s/s:
        the robust centre of the window's offsets, each carried from its own arrival to ``at``
        along the drift. The plain centre is the offset of the window's middle, half a window
        ago: on a clock 1 % fast, 31 readings at 1 Hz put it 0.15 s behind the clock's
        present offset (:attr:`value` when the drift is 0 or an arrival is unknown)."""
        if not drift or at is None or not self.fifo or None in self.arrivals:
            return self.value
        return self._centre(sorted(v + drift * (at - a)
                                   for v, a in zip(self.fifo, self.arrivals)))

    @property
    def scale(self) -> float:
        """Robust spread of the window's offsets around the centre (1.4826 x the median
        absolute deviation, s): the link's jitter as this clock sees it."""
        if not self.sorted:
            return math.nan
        c = self.value
        dev = sorted(abs(v - c) for v in self.sorted)
        return 1.4826 * dev[len(dev) // 2]

    @property
    def ceiling(self) -> float:
        """The largest offset that voted among the last ``horizon``, once ``settled`` were
        in: where the clock is when the latency is least. A node that lagged its input for a
        while moves the centre down with it; when it catches up, its offsets return to the
        ceiling, never above it."""
        return self._top[0][1] if self._top else math.nan

    def above(self, v: float) -> float:
        """How far the offset ``v`` lies above where its clock can be (s): only a forward step
        or a wrong stamp puts it there, since latency only ever lowers an offset."""
        return v - max(self.value, self.ceiling)

    # -- rate -----------------------------------------------------------------------------
    def rate_point(self, stamp: float, arrival: float) -> None:
        """Offer a reading (after :meth:`add`) to the rate fit: used when on time and paced.

        A late reading, or one whose arrival advanced less than half its stamp since the last
        one used (the tail of a backlog: its latency shrinking as the stamps advance with the
        arrival frozen), is left out. With a backlog's readings in the fit, an 8 s stall on
        separate clocks left a drift error of 9e-5 (true drift 0) and the KF 0.20-0.26 m off
        for half a minute after it (0.06-0.07 m without the stall)."""
        if not self.on_time(stamp - arrival):
            return
        if self._reg_last is not None and not paced(self._reg_last, (stamp, arrival)):
            return
        self._reg_last = (stamp, arrival)
        f = self._fit
        if f[6] is None:
            f[6] = (arrival, stamp)
        x, y = arrival - f[6][0], stamp - f[6][1]
        f[0] += 1
        f[1] += x
        f[2] += y
        f[3] += x * x
        f[4] += x * y
        f[5] += y * y

    def rate(self, min_n: int = 20, min_span: float = 10.0) -> tuple[float, float]:
        """(drift, its standard error): the clock's rate minus 1 (s/s) against the arrival
        clock; (0, inf) until ``min_n`` points over ~``min_span`` s of arrivals are in, or when
        the fit says more than 10 % (not a clock)."""
        n, sx, sy, sxx, sxy, syy, _ = self._fit
        if n < min_n:
            return 0.0, math.inf
        var = sxx - sx * sx / n
        if var < n * min_span ** 2 / 12:  # less than ~min_span of arrivals
            return 0.0, math.inf
        slope = (sxy - sx * sy / n) / var
        d = slope - 1.0
        if not abs(d) < 0.1:
            return 0.0, math.inf
        rss = max(syy - sy * sy / n - slope * (sxy - sx * sy / n), 0.0)
        return d, math.sqrt(rss / max(n - 2, 1) / var)

    @property
    def drift(self) -> float:
        return self.rate()[0]
