"""A small forward clock step seen on the clock's envelope (pure; docs/integrity.md, "Clocks").

The model is the clock model's: a train-clock reading's offset ``v = stamp - arrival`` is the
clock's offset ``c`` less the reading's latency, ``v = c - L``, with ``L`` at least the link's
floor and otherwise random (jitter), the same law for every reading. So ``c - floor`` is the
offsets' *envelope*, and the largest offset seen lies just below it (the clock's ceiling,
:attr:`~.clocks.StreamClock.ceiling`). A forward step of ``d`` s moves ``c`` up by ``d``: a
reading of the new clock lies above the old ceiling whenever its latency's excess over the
floor is below ``d`` (with an exponential jitter of mean ``m``, with probability ``1 -
exp(-d / m)``: 0.86 for a 0.1 s step on 50 ms), where under the old clock a reading lands
only by being the least late of all so far. A step of 0.1 s is a third of the spread-based bar
(:meth:`~.clocks.StepWatch.bar`) on such a link, and the offsets' centre absorbs it: the
envelope sees it.

The test is on ranks, exact and free of the latency's law: if ``k`` new offsets and the ``n``
offsets whose largest is the ceiling are exchangeable (no step: one clock, one latency law),
the probability that at least ``j`` of the new ones lie above all ``n`` is that the ``j``
largest of the ``n + k`` are new ones, :func:`above_p` = ``C(k, j) / C(n + k, j)``. Ties count
against the step (an offset equal to the ceiling is not above it), which only lowers that
probability.

Its threshold comes from a stated false-alarm rate ``rate`` (false steps per hour,
:func:`level`): the step watch tests the readings it holds as one candidate at each odometer
reading that arrives (at most ``3600 / period`` tests an hour), the candidate starting at a
reading of the data's choosing, so at any of ``max_held`` lengths; a union bound over both
makes the false steps per hour at most ``rate`` when each test rejects at ``rate * period /
(3600 * max_held)``. This bounds the test's own errors; the readings it is given must first be
held (one above the ceiling by ``small_step``) and number ``min_judged`` above it, which no
clean link tried produced (docs/integrity.md measures it).
"""

from __future__ import annotations

import math


def _log_comb(n: int, k: int) -> float:
    """log C(n, k) (0 <= k <= n)."""
    return math.lgamma(n + 1.0) - math.lgamma(k + 1.0) - math.lgamma(n - k + 1.0)


def above_p(k: int, j: int, n: int) -> float:
    """P(at least ``j`` of ``k`` new offsets lie above the largest of ``n`` earlier ones), all
    ``n + k`` exchangeable: ``C(k, j) / C(n + k, j)`` (module doc); 1 when ``j <= 0``, 0 when
    ``j > k``."""
    if j <= 0:
        return 1.0
    if j > k:
        return 0.0
    return math.exp(_log_comb(k, j) - _log_comb(n + k, j))


def level(rate: float, period: float, max_held: int) -> float:
    """The p-value at which :func:`above_p` declares a step so that false steps are at most
    ``rate`` per hour (module doc): one test per reading, ``3600 / period`` an hour, each at
    any of ``max_held`` lengths."""
    return rate * period / (3600.0 * max_held)


def holds(k: int, j: int, n: int, wait: float) -> bool:
    """Whether ``k`` held readings of which ``j`` lie above the ceiling of ``n`` offsets are
    still held as a small forward step: at least half of them there (a step of d puts a
    reading of the new clock there when its latency's excess over the floor is below d: half
    of them or more for a step beyond the excess's median), and as unlikely under one clock as
    ``wait`` (:func:`above_p`: a ceiling of a few offsets is no envelope, and one reading above
    that of hundreds holds a few readings, not dozens)."""
    return 2 * j >= k and above_p(k, j, n) <= wait


def candidate(lifts: list, n: int, small_step: float, back: float, bar: float,
              wait: float) -> tuple[int, int] | None:
    """(k, j) of held readings whose offsets lie ``lifts`` s above the ceiling of ``n``
    offsets (negative: below), when they are held as a small forward step (:func:`holds`; one
    of them above the ceiling by more than ``small_step``, none above it by more than
    ``back`` nor below it by more than ``bar``: beyond, the step watch's bars judge); else
    None."""
    if not lifts or not small_step < max(lifts) <= back or min(lifts) < -bar:
        return None
    k, j = len(lifts), sum(x > 0.0 for x in lifts)
    return (k, j) if holds(k, j, n, wait) else None
