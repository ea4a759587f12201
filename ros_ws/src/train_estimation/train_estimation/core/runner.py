"""Time-ordered stepping of an estimator from messages that arrive out of step (pure).

The ROS nodes and the offline replay both drive an estimator through :class:`EstimatorRunner`,
so the node's estimates can be reproduced from a bag without ROS:

- ``push(kind, stamp, fields)`` queues a reading or command (the node's callbacks only do this);
- ``advance_to(t)`` processes every queued item with stamp <= each output time in stamp order
  (commands before readings at equal stamps), predicts to the output time and emits one estimate
  per output time ``k * period`` (the odometer rate), whether or not a measurement arrived.

Items stamped before a time already output are late: they go to the estimator anyway, which
rejects them as out of order (counted, state untouched). The node calls ``advance_to(now -
delay)`` with a small ``delay`` so that readings of a sample time arrive before it is output.
"""

from __future__ import annotations

import heapq
import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Protocol

KIND_ORDER = {"control": 0, "odometer": 1, "balise": 2}


@dataclass(frozen=True)
class Output:
    """One estimate, as published in a TrainState (SI units; NaN where not estimated)."""

    stamp: float  # s
    position: float  # m
    velocity: float  # m/s
    acceleration: float  # m/s^2
    braking_rate: float  # -
    covariance: tuple  # 16 floats, row-major 4x4 over (position, velocity, acceleration, f)
    measurement_used: bool


class Adapter(Protocol):
    """What the runner needs from an estimator (see train_estimation.core.estimators)."""

    def start(self, t0: float) -> None: ...
    def control(self, stamp: float, fields: dict) -> str: ...  # "" accepted, else a reason
    def odometer(self, stamp: float, fields: dict) -> str: ...
    def balise(self, stamp: float, fields: dict) -> str: ...
    def predict_to(self, t: float) -> None: ...
    def output(self, t: float) -> Output: ...


@dataclass
class EstimatorRunner:
    adapter: Adapter
    period: float  # s, output period (the odometer's)
    queue: list = field(default_factory=list)
    rejected: Counter = field(default_factory=Counter)
    accepted: Counter = field(default_factory=Counter)
    last_reasons: list = field(default_factory=list)  # (kind, stamp, reason), most recent last
    high: dict = field(default_factory=dict)  # kind -> largest stamp pushed (the watermark)
    _k: int | None = None  # index of the next output time
    _n: int = 0  # insertion counter: FIFO among equal stamps and kinds

    def push(self, kind: str, stamp: float, fields: dict) -> str:
        """Queue one item; returns "" or the reason it was refused at the door."""
        if kind not in KIND_ORDER:
            return self._reject(kind, stamp, f"unknown kind {kind}")
        if not (isinstance(stamp, float | int) and math.isfinite(stamp)):
            return self._reject(kind, float("nan"), "non_finite_stamp")
        heapq.heappush(self.queue, (float(stamp), KIND_ORDER[kind], self._n, kind, fields))
        self.high[kind] = max(self.high.get(kind, -math.inf), float(stamp))
        self._n += 1
        return ""

    def _reject(self, kind: str, stamp: float, reason: str) -> str:
        # count by category (the text before any ':' detail), keep the full text for the log
        self.rejected[f"{kind}:{reason.split(':', 1)[0]}"] += 1
        self.last_reasons.append((kind, stamp, reason))
        del self.last_reasons[:-20]
        return reason

    def _apply(self, stamp: float, kind: str, fields: dict) -> None:
        reason = getattr(self.adapter, kind)(stamp, fields)
        if reason:
            self._reject(kind, stamp, reason)
        else:
            self.accepted[kind] += 1

    def advance_to(self, t: float) -> list[Output]:
        """Emit the estimates of every output time <= t not emitted yet."""
        out: list[Output] = []
        if self._k is None:
            if not self.queue:
                return out
            t0 = self.queue[0][0]
            self.adapter.start(t0)
            self._k = math.ceil(t0 / self.period - 1e-9)
        while True:
            tk = self._k * self.period
            if tk > t + 1e-9:
                break
            while self.queue and self.queue[0][0] <= tk + 1e-9:
                stamp, _, _, kind, fields = heapq.heappop(self.queue)
                self._apply(stamp, kind, fields)
            self.adapter.predict_to(tk)
            out.append(self.adapter.output(tk))
            self._k += 1
        return out

    def ready_time(self, now: float, delay: float, fallback: float) -> float:
        """Latest output time a live node can emit at clock ``now`` without racing its inputs.

        Output time t needs every reading stamped <= t. Each topic arrives in order, so the
        largest stamp pushed per topic (its watermark) says how far that topic is complete.
        ``control`` is not sent over the lossy link: its watermark is the data's own clock.
        The odometer is complete up to its watermark, or -- when samples were lost -- up to
        ``fallback`` seconds behind the control watermark. Without control messages the node's
        clock stands in for it. ``now - delay`` is an upper bound in every case. Driven by the
        data rather than by the clock, a node emits what the offline replay of the same
        messages emits, however the executor interleaves /clock and the subscriptions.
        """
        lead = self.high.get("control", now - delay)
        odo = self.high.get("odometer", -math.inf)
        return min(now - delay, lead, max(odo, lead - fallback))

    def drain(self) -> list[Output]:
        """Process everything queued (offline use): estimates up to the last item's stamp."""
        if not self.queue:
            return []
        return self.advance_to(max(item[0] for item in self.queue))

