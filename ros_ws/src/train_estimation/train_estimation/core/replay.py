"""Offline replay: feed recorded messages through the same runner and adapters as the nodes."""

from __future__ import annotations

from collections.abc import Iterable

from .runner import EstimatorRunner, Output

INPUT_TOPICS = ("control", "odometer", "balise")


def replay(events: Iterable[tuple[str, float, dict]], adapter, period: float) -> tuple[
        list[Output], EstimatorRunner]:
    """Estimates at every output time from ``(topic, stamp, fields)`` events (any order)."""
    runner = EstimatorRunner(adapter, period)
    for topic, stamp, fields in events:
        if topic in INPUT_TOPICS:
            runner.push(topic, stamp, fields)
    return runner.drain(), runner
