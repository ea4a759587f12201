"""How finely a node on simulated time knows when a message arrived (pure).

On simulated time (``use_sim_time``) a node times each message's arrival on the ROS clock,
which is the world's ``/clock`` as it last reached the node. The world's clock runs on between
two of its messages, and a ``/clock`` message can reach the node after the data published
after it, or not at all (it is best effort: a loaded machine drops some), so a message can
arrive when the world's clock is already past what the node's clock says. By how much is not
one tick: it is how far the world's clock has run since the node's last saw it move, at the
world's pace against the node's steady clock. A judgement of stamps against arrivals (a stamp
"ahead of its clock", offsets that came "at one instant") has to allow that much.

:class:`SimArrival` keeps that account: each arrival is ``observe(ros, wall)`` (the ROS clock's
reading and the steady clock's, both in s) and returns ``(recv, resolution)``: the arrival on
the ROS clock, and the most the world's clock can be past it (s of simulated time): the
largest recent step of the ROS clock seen (one tick), or the steady time since it last moved
times the world's pace (simulated s per steady s, from the recent steps), the larger. (With
the resolution one tick alone, a node that joined a 10x run on a loaded machine refused a
command as 0.3 s ahead of its clock, three ticks: what a node sees when three ``/clock``
messages have not reached it, the likeliest reading of that log.)
"""

from __future__ import annotations

import math
from collections import deque


class SimArrival:
    """The ROS clock's recent steps against the steady clock (module doc)."""

    def __init__(self, window: int = 64):
        self.last: tuple[float, float] | None = None  # (ROS s, steady s) when it last moved
        self.steps: deque = deque(maxlen=window)  # (ROS step s, steady interval s)

    def observe(self, ros: float, wall: float) -> tuple[float, float]:
        """``(recv, resolution)`` (s) for a message read at ROS time ``ros`` and steady time
        ``wall`` (module doc)."""
        if self.last is None or ros != self.last[0]:
            if self.last is not None and ros > self.last[0]:
                self.steps.append((ros - self.last[0], wall - self.last[1]))
            self.last = (ros, wall)
        if not self.steps:
            return ros, 0.0
        tick = max(s for s, _ in self.steps)
        ran, took = sum(s for s, _ in self.steps), sum(w for _, w in self.steps)
        pace = ran / took if took > 0 else math.inf
        behind = (wall - self.last[1]) * pace if math.isfinite(pace) else 0.0
        return ros, max(tick, behind)
