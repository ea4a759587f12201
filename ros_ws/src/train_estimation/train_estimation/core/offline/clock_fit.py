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
``LATE`` is the online clocks' lateness bar (``core/numerics/clocks.py``), one rule for both;
offline the bar is raised to ``LATE_SCALES`` robust standard deviations for a link whose jitter
is wider (the whole bag is there to measure it).

Besides the fit: the train clock's steps on the sample grid (:func:`clock_steps`) and a change
of its rate within the run (:func:`clock_rate_change`), which ``measured`` reports and
``diagnose`` takes into account.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..numerics.clocks import LATE, SMALL_MOVE

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
        return cls.fit_kept(stamps, recv)[0]

    @classmethod
    def fit_kept(cls, stamps: np.ndarray, recv: np.ndarray) -> tuple[ClockFit, np.ndarray]:
        """:meth:`fit` and the readings it kept (not logged late), a boolean mask."""
        s = np.asarray(stamps, float)
        r = np.asarray(recv, float)
        t_first = float(s[0])
        x = s - t_first
        keep = np.ones(s.size, bool)
        if s.size < 2 or np.ptp(x) <= 0:
            return cls(t_first, float(np.mean(r) - np.mean(x)), 1.0), keep
        A = np.stack([np.ones_like(x), x], axis=1)
        for _ in range(5):  # the late set settles in two or three rounds
            coef, *_ = np.linalg.lstsq(A[keep], r[keep], rcond=None)
            e = r - A @ coef
            centre = np.median(e[keep])
            late = e - centre > max(LATE, LATE_SCALES * _robust_sd(e[keep]))
            if np.array_equal(~late, keep) or late.sum() > s.size // 2 or np.ptp(x[~late]) <= 0:
                break
            keep = ~late
        return cls(t_first, float(coef[0]), float(coef[1])), keep

    def ref_of_train(self, s):
        """Train-clock stamps -> reference seconds since the first odometer stamp."""
        return self.beta * (np.asarray(s, float) - self.t_first)

    def ref_of_control(self, c):
        """Control stamps (reference clock) -> the same reference seconds."""
        return np.asarray(c, float) - self.alpha

    def train_of_control(self, c):
        """Control stamps -> the train clock (where identify reads every time)."""
        return self.t_first + self.ref_of_control(c) / self.beta


def _robust_sd(x: np.ndarray) -> float:
    """1.4826 x the median absolute deviation: the SD of a normal sample, robust to outliers."""
    return 1.4826 * float(np.median(np.abs(x - np.median(x))))


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


def clock_steps(stamps, seq, window: int = 20, max_steps: int = 5) -> list[tuple[int, float]]:
    """Steps of the train's clock in odometer readings in sequence order (``stamps`` s,
    ``seq`` unwrapped and increasing): [(i, J)], the readings from index ``i`` on read ``J`` s
    more than the sample grid before them says.

    An odometer samples on a grid: stamp = s0 + T seq (a drift is in T). A clock step (a
    reboot, a time server's correction) moves the grid by J at once and for good; the link's
    latency moves no stamp, so a change of the link is not a step, and nothing here needs the
    log times. A step is an increment of stamp - T seq beyond the bar (``SMALL_MOVE`` and 10
    robust SDs of those increments) after which the level holds: the medians of the
    ``window`` readings either side differ by the same J (within the bar). One wrong stamp,
    or a burst shorter than half the window, comes back and is no step. Nothing is reported
    where the readings are not on a grid (the increments' robust SD above a tenth of the
    period, or fewer than 90 % of them within the bar: irregular sampling, no seq), nor when
    there are more than ``max_steps`` (a clock that moves that often is not one with a few
    steps, and this does not follow it)."""
    s = np.asarray(stamps, float)
    q = np.asarray(seq, float)
    n = s.size
    if n < 2 * window or q.size != n:
        return []
    dq, ds = np.diff(q), np.diff(s)
    if np.any(dq <= 0):
        return []
    period = float(np.median(ds / dq))
    if not period > 0:
        return []
    de = ds - period * dq
    scale = _robust_sd(de)
    bar = max(SMALL_MOVE, 10.0 * scale)
    if scale > 0.1 * period or np.mean(np.abs(de) <= bar) < 0.9:
        return []
    e = s - period * q
    out = []
    for c in np.flatnonzero(np.abs(de) > bar):
        i = int(c) + 1
        if i < window or n - i < window:
            continue
        jump = float(np.median(e[i:i + window]) - np.median(e[i - window:i]))
        if abs(jump) > bar and abs(jump - de[c]) < bar:
            out.append((i, jump))
    return out if len(out) <= max_steps else []


RATE_CHANGE_LR = 30.0  # 2 ln LR a rate change must reach against one rate (one change, profiled)
MIN_RATE_CHANGE = 1e-5  # s/s, below it the two rates are one (clock_drift's resolution)


def clock_rate_change(stamps, recv, n_times: int = 81) -> dict | None:
    """Whether the train clock's rate against the reference clock changes once in the run:
    a time server slewing it, a clock that warms up. Against one rate (log time r = a + b x,
    x = stamp - the first), a change at x_k adds c (x - x_k)+ (the offset bends there); x_k
    is profiled over ``n_times`` points from 10 % to 90 % of the run, on the readings not
    logged late (:class:`ClockFit`'s rule). A change is found when 2 ln LR > ``RATE_CHANGE_LR``,
    |c| > ``MIN_RATE_CHANGE`` and the offset it makes by the end is more than ``SMALL_MOVE``:
    {when (s of stamp since the first), drift_before, drift_after (stamp rate minus 1), offset
    (s the clock reads more by the end than one rate says), lr}; else None. A one-rate drift
    bends nowhere; a link whose latency changes for good moves the offset at once: where one
    level shift (profiled over the same points) fits at least as well as the bend, it is no
    change of rate (the clock's own steps are found on the sample grid, before)."""
    s = np.asarray(stamps, float)
    r = np.asarray(recv, float)
    if s.size < 50 or np.ptp(s) <= 0:
        return None
    fit, keep = ClockFit.fit_kept(s, r)
    x, r = s[keep] - fit.t_first, r[keep]
    A = np.stack([np.ones_like(x), x], axis=1)
    rss0 = float(np.sum((r - A @ np.linalg.lstsq(A, r, rcond=None)[0]) ** 2))
    best = jump = None
    for xk in np.linspace(0.1, 0.9, n_times) * x[-1]:
        B = np.column_stack([A, np.clip(x - xk, 0.0, None)])
        coef = np.linalg.lstsq(B, r, rcond=None)[0]
        rss = float(np.sum((r - B @ coef) ** 2))
        if best is None or rss < best[0]:
            best = (rss, xk, coef)
        S = np.column_stack([A, (x >= xk).astype(float)])
        rss_s = float(np.sum((r - S @ np.linalg.lstsq(S, r, rcond=None)[0]) ** 2))
        jump = rss_s if jump is None else min(jump, rss_s)
    rss1, xk, coef = best
    if jump <= rss1:  # the offset moves at once (the link's latency), not by a rate
        return None
    n = x.size
    lr = n * (math.log(max(rss0, n * 1e-12)) - math.log(max(rss1, n * 1e-12)))
    b0, c = float(coef[1]), float(coef[2])
    offset = -c * (x[-1] - xk)  # the stamp clock runs faster when r grows slower per stamp
    if lr <= RATE_CHANGE_LR or abs(c) <= MIN_RATE_CHANGE or abs(offset) <= SMALL_MOVE:
        return None
    return {"when": float(xk), "drift_before": 1.0 / b0 - 1.0,
            "drift_after": 1.0 / (b0 + c) - 1.0, "offset": float(offset), "lr": float(lr)}
