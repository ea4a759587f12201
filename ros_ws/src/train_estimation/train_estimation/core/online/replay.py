"""Offline replay: feed recorded messages through the same runner and adapters as the nodes."""

from __future__ import annotations

from collections.abc import Iterable

from .runner import EstimatorRunner, Output

INPUT_TOPICS = ("control", "odometer", "balise")


def replay(events: Iterable[tuple], adapter, period: float, delay: float = 0.05,
           fallback: float = 0.2, **runner_kw) -> tuple[list[Output], EstimatorRunner]:
    """Estimates from ``(topic, stamp, fields[, recv])`` events **in arrival (log-time) order**.

    Each event is pushed and the runner advanced to its ready time, as the node does on every
    message, then everything left is drained. ``recv`` (s) is the arrival time (the bag's log
    time); without it the arrival is judged from the other clock's stamps (see the runner).
    Every step is bounded by the stamps pushed, and a stamp far in the future is refused at the
    door, so the replay always terminates.
    """
    runner = EstimatorRunner(adapter, period, **runner_kw)
    out: list[Output] = []
    now = None
    for ev in events:
        topic, stamp, fields = ev[0], ev[1], ev[2]
        recv = ev[3] if len(ev) > 3 else None
        if topic not in INPUT_TOPICS:
            continue
        runner.push(topic, stamp, fields, recv)
        now = recv if recv is not None else now
        out += runner.advance_to(runner.ready_time(now if now is not None else stamp, delay,
                                                   fallback))
    return out + runner.drain(), runner
