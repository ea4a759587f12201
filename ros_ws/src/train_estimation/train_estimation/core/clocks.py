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
``LATE_MIN`` s and ``LATE_SCALES`` robust standard deviations): a radio's jitter, tens of
milliseconds, never comes near, so an undisturbed bag keeps the plain least-squares fit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

LATE_MIN = 0.5  # s: a reading logged this much later than the fit says was held up (a stall)
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
            late = e - centre > max(LATE_MIN, LATE_SCALES * scale)
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
