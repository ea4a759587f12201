"""Offline replay: feed recorded messages through the same runner and adapters as the nodes."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable

from .runner import EstimatorRunner, Output

INPUT_TOPICS = ("control", "odometer", "balise")


class TimerTicks:
    """The arrival times at which a node's timer of period ``period`` (s; None or 0: no timer)
    fires between messages: multiples of the period, from the first message's arrival on.

    At most ``cap`` ticks per silence: a tick publishes nothing past the latest stamp queued
    (``EstimatorRunner.due_time``), so once the silence is longer than ``slot_grace`` the
    later ticks are no-ops, and a log time far ahead (a corrupted bag) must not make the
    replay tick for ever."""

    cap = 1000

    def __init__(self, period: float | None):
        self.period = period if period and math.isfinite(period) and period > 0 else None
        self.k: int | None = None  # index of the next tick (k * period)

    def until(self, now: float | None) -> list[float]:
        """The ticks before ``now`` not yet given (none without an arrival time)."""
        if self.period is None or now is None or not math.isfinite(now):
            return []
        if self.k is None:
            self.k = math.floor(now / self.period) + 1
            return []
        ticks = []
        while self.k * self.period < now and len(ticks) < self.cap:
            ticks.append(self.k * self.period)
            self.k += 1
        if self.k * self.period < now:
            self.k = math.floor(now / self.period) + 1
        return ticks


def replay(events: Iterable[tuple], adapter, period: float, delay: float = 0.05,
           fallback: float = 0.2, tick_period: float | None = 0.05,
           on_time: Callable[[float], None] | None = None,
           blocked: Callable[[float], bool] | None = None,
           runner: EstimatorRunner | None = None,
           **runner_kw) -> tuple[list[Output], EstimatorRunner]:
    """Estimates from ``(topic, stamp, fields[, recv])`` events **in arrival (log-time) order**.

    Each event is pushed and the runner advanced to its ready time and ticked
    (``EstimatorRunner.tick``), as the node does on every message, and ticked at the times its
    timer (``tick_period``) fires between messages; then everything left is drained. ``recv``
    (s) is the arrival time (the bag's log time); without it the arrival is judged from the
    other clock's stamps (see the runner) and there are no ticks. Every step is bounded by the
    stamps pushed, and a stamp far in the future is refused at the door, so the replay always
    terminates. After each message and tick the runner settles (``EstimatorRunner.settle``),
    as the node does once it has published. ``on_time(t)`` (optional) is told each arrival and
    tick time before the runner works at it (``tools.faults.run`` notes there when each
    estimate was produced);
    ``blocked(t)`` (optional) is true for the arrival times at which the node's callbacks are
    blocked (a stalled node: its timer does not fire either). ``runner`` (optional): the runner
    to drive, built by the caller (who can then watch it from ``on_time``); ``adapter``,
    ``period`` and ``runner_kw`` are then its own.
    """
    if runner is None:
        runner = EstimatorRunner(adapter, period, **runner_kw)
    out: list[Output] = []
    now = None
    ticks = TimerTicks(tick_period)
    for ev in events:
        topic, stamp, fields = ev[0], ev[1], ev[2]
        recv = ev[3] if len(ev) > 3 else None
        if topic not in INPUT_TOPICS:
            continue
        for t in ticks.until(recv):
            if blocked is not None and blocked(t):
                continue
            if on_time is not None:
                on_time(t)
            out += runner.tick(t)
            runner.settle()
        if on_time is not None and recv is not None:
            on_time(recv)
        runner.push(topic, stamp, fields, recv)
        now = recv if recv is not None else now
        out += runner.advance_to(runner.ready_time(now if now is not None else stamp, delay,
                                                   fallback))
        if recv is not None:
            out += runner.tick(recv)
        runner.settle()  # as the node once it has published (EstimatorRunner.settle)
    return out + runner.drain(), runner
