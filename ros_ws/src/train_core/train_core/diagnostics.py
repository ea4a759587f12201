"""A node's health from its counts: the levels, messages and values of ``/diagnostics`` (pure).

Every node of the project publishes ``diagnostic_msgs/DiagnosticArray`` on ``/diagnostics`` once
per ``diagnostics_period``; the node only gathers its counters and converts the
:class:`Status` built here into the message. The rules, the same for every node:

- an input silent for ``stale_warn`` s is WARN, for ``stale_error`` s ERROR (age since its last
  message, or since the node started when none came yet);
- the fraction of an input's messages received during the last period that were rejected:
  WARN at ``rejected_warn``, ERROR at ``rejected_error``;
- the p99 of the input -> output latency over the last period: WARN at ``latency_warn`` s,
  ERROR at ``latency_error`` s;
- an estimator's integrity: DEGRADED is WARN, ALARM is ERROR, with the estimator's reason.

The status is the worst of these checks; its message names every check at that level.
Counts in the values are cumulative since the node started; rates are over the last period.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from train_core.config import param, require

OK, WARN, ERROR = 0, 1, 2  # diagnostic_msgs/DiagnosticStatus levels
LEVEL_NAMES = {OK: "OK", WARN: "WARN", ERROR: "ERROR"}
INTEGRITY_LEVEL = {0: OK, 1: WARN, 2: ERROR}  # TrainState.integrity -> level
INTEGRITY_NAMES = {0: "OK", 1: "DEGRADED", 2: "ALARM"}
MIN_PERIOD = 0.05  # s, the shortest diagnostics_period: 20 statuses a second (1e-9 was
#   accepted and made the node publish 1,674 a second, a third of a core)


def _pair(obj, warn: str, error: str) -> None:
    a, b = getattr(obj, warn), getattr(obj, error)
    require(math.isfinite(a) and a > 0, warn, a, "must be > 0")
    require(math.isfinite(b) and b >= a, error, b, f"must be >= {warn} ({a:g})")


@dataclass(frozen=True)
class DiagnosticsPeriod:
    """Every node: how often it publishes its status."""

    diagnostics_period: float = param(1.0, "s", "between two /diagnostics messages (at least "
                                      "0.05: a status is for people and aggregators, and each "
                                      "one costs the node a callback)", lo=MIN_PERIOD)

    def __post_init__(self):
        v = self.diagnostics_period
        require(math.isfinite(v) and v >= MIN_PERIOD, "diagnostics_period", v,
                f"must be finite and >= {MIN_PERIOD:g}")


@dataclass(frozen=True)
class StaleThresholds(DiagnosticsPeriod):
    """A node with inputs: how long an input may be silent."""

    stale_warn: float = param(2.0, "s", "an input silent this long: WARN", lo=0.0)
    stale_error: float = param(5.0, "s", "an input silent this long: ERROR", lo=0.0)

    def __post_init__(self):
        super().__post_init__()
        _pair(self, "stale_warn", "stale_error")


@dataclass(frozen=True)
class InputThresholds(StaleThresholds):
    """A node that checks its inputs: how many may be refused."""

    rejected_warn: float = param(0.05, "-", "fraction of an input's messages in the last "
                                 "period that were rejected: WARN at or above", lo=0.0, hi=1.0)
    rejected_error: float = param(0.5, "-", "fraction rejected in the last period: ERROR at "
                                  "or above", lo=0.0, hi=1.0)

    def __post_init__(self):
        super().__post_init__()
        _pair(self, "rejected_warn", "rejected_error")
        require(self.rejected_error <= 1.0, "rejected_error", self.rejected_error,
                "must be <= 1")


@dataclass(frozen=True)
class EstimatorThresholds(InputThresholds):
    """An estimator: also how late its estimates may be."""

    latency_warn: float = param(0.2, "s", "p99 odometer received -> estimate published over "
                                "the last period: WARN at or above", lo=0.0)
    latency_error: float = param(1.0, "s", "p99 latency over the last period: ERROR at or "
                                 "above", lo=0.0)

    def __post_init__(self):
        super().__post_init__()
        _pair(self, "latency_warn", "latency_error")


@dataclass(frozen=True)
class InputCounts:
    """One input stream as a node counted it (cumulative since the node started)."""

    name: str
    received: int = 0
    accepted: int = 0
    rejected: Mapping[str, int] | None = None  # reason -> count
    last_arrival: float = math.nan  # s on the node's clock; NaN: nothing came yet
    watch_stale: bool = True  # False for a sparse input (balises: minutes apart)

    @property
    def n_rejected(self) -> int:
        return sum((self.rejected or {}).values())


@dataclass(frozen=True)
class Status:
    """What goes into one diagnostic_msgs/DiagnosticStatus."""

    level: int
    message: str
    values: tuple[tuple[str, str], ...]


def grade(value: float, warn: float, error: float) -> int:
    """OK below ``warn``, WARN from ``warn``, ERROR from ``error`` (NaN: ERROR)."""
    if not value < error:
        return ERROR
    return WARN if value >= warn else OK


def _fmt(v: float) -> str:
    return f"{v:.3g}" if math.isfinite(v) else "-"


def input_checks(now: float, started: float, inputs: Sequence[InputCounts],
                 previous: Mapping[str, InputCounts], period: float,
                 cfg: StaleThresholds) -> tuple[list[tuple[int, str]], list[tuple[str, str]]]:
    """(checks, values) of a node's inputs: staleness, and (InputThresholds) the rejected
    fraction over the last period. ``previous``: the counts one period ago (by name)."""
    checks: list[tuple[int, str]] = []
    values: list[tuple[str, str]] = []
    for c in inputs:
        prev = previous.get(c.name) or InputCounts(c.name)
        fresh = c.received - prev.received
        values.append((f"{c.name}.rate_hz", _fmt(fresh / period if period > 0 else math.nan)))
        values.append((f"{c.name}.received", str(c.received)))
        values.append((f"{c.name}.accepted", str(c.accepted)))
        for reason, n in sorted((c.rejected or {}).items()):
            values.append((f"{c.name}.rejected.{reason}", str(n)))
        never = not math.isfinite(c.last_arrival)
        age = now - (started if never else c.last_arrival)
        values.append((f"{c.name}.age_s", _fmt(age) if not never else "never received"))
        if c.watch_stale:
            level = grade(age, cfg.stale_warn, cfg.stale_error)
            if level:
                what = "nothing received since start" if never else "silent"
                checks.append((level, f"{c.name}: {what} for {age:.1f} s"))
        if isinstance(cfg, InputThresholds) and fresh > 0:
            refused = c.n_rejected - prev.n_rejected
            frac = refused / fresh
            values.append((f"{c.name}.rejected_fraction", _fmt(frac)))
            level = grade(frac, cfg.rejected_warn, cfg.rejected_error)
            if level:
                worst = max(((n - (prev.rejected or {}).get(r, 0), r)
                             for r, n in (c.rejected or {}).items()), default=(0, "?"))
                checks.append((level, f"{c.name}: {refused} of {fresh} rejected in the last "
                                      f"{period:g} s (mostly {worst[1]})"))
    return checks, values


def latency_check(latencies: Sequence[float], cfg: EstimatorThresholds
                  ) -> tuple[list[tuple[int, str]], list[tuple[str, str]]]:
    """p50/p99 (order statistics) of the last period's latencies, graded on the p99."""
    if not latencies:
        return [], [("latency_p50_ms", "-"), ("latency_p99_ms", "-")]
    v = sorted(latencies)
    p50, p99 = v[len(v) // 2], v[min(len(v) - 1, int(0.99 * len(v)))]
    values = [("latency_p50_ms", f"{1e3 * p50:.2f}"), ("latency_p99_ms", f"{1e3 * p99:.2f}")]
    level = grade(p99, cfg.latency_warn, cfg.latency_error)
    return ([(level, f"latency p99 {1e3 * p99:.0f} ms")] if level else []), values


def rate_check(sampled: float | None, configured: float, tolerance: float = 0.2
               ) -> tuple[list[tuple[int, str]], list[tuple[str, str]]]:
    """The odometer's sample period as its stamps and counter give it (``sampled`` s, None
    while unknown) against the one the node was told (``configured`` s: ``odometer_rate``):
    WARN beyond ``tolerance`` of it, with the setting to use."""
    if sampled is None or not math.isfinite(sampled) or sampled <= 0:
        return [], [("odometer_period_s", "-")]
    values = [("odometer_period_s", f"{sampled:.4g}")]
    if abs(sampled / configured - 1.0) <= tolerance:
        return [], values
    return [(WARN, f"odometer samples every {sampled:.3g} s where odometer_rate "
                   f"{1.0 / configured:.3g} Hz expects {configured:.3g} s: set odometer_rate: "
                   f"{1.0 / sampled:.3g}")], values


def integrity_check(integrity: int | None, reason: str, ahead: float = math.nan,
                    behind: float = math.nan
                    ) -> tuple[list[tuple[int, str]], list[tuple[str, str]]]:
    """The estimator's own integrity state (TrainState.integrity, the doubts of its monitor and
    its protection levels in m) as a check."""
    if integrity is None:
        return [], [("integrity", "no estimate yet"), ("integrity_reason", ""),
                    ("protection_level_ahead", ""), ("protection_level_behind", "")]
    name = INTEGRITY_NAMES.get(integrity, f"unknown ({integrity})")
    values = [("integrity", name), ("integrity_reason", reason),
              ("protection_level_ahead", f"{ahead:.3f}"),
              ("protection_level_behind", f"{behind:.3f}")]
    level = INTEGRITY_LEVEL.get(integrity, ERROR)
    return ([(level, f"integrity {name}" + (f": {reason}" if reason else ""))]
            if level else []), values


def combine(checks: Sequence[tuple[int, str]], values: Sequence[tuple[str, str]]) -> Status:
    """The worst level of the checks; the message lists every check at that level."""
    level = max((lv for lv, _ in checks), default=OK)
    if level == OK:
        return Status(OK, "OK", tuple(values))
    return Status(level, "; ".join(m for lv, m in checks if lv == level), tuple(values))
