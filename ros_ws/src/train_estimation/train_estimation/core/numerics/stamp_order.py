"""Whether an input is a duplicate, out of order or too far ahead: one judgement (pure).

Every place that must refuse input out of order keeps one :class:`StampOrder`: the robust
filters (``robust/filter_base.py``: readings, commands, predictions), the braking-rate adapter
(``online/estimators.py``) and the runner's door (``online/runner.py``: copies of a message
and sequence resets, before its clocks see them). The rule:

- **Order is by stamp.** A stamp before ``t``, the time the owner's estimate has reached, is
  ``out_of_order``: the estimate cannot go back (the runner rewinds what it can before that).
- **Horizon.** A stamp more than ``horizon`` seconds after ``t`` is ``future_stamp``: a
  prediction over hours is no estimate, so such a stamp is a clock error, not an outage.
- **seq marks duplicates.** A reading with the ``seq`` or the stamp of the last one of its
  kind taken (:meth:`took`) is a ``duplicate``; one stamped before it is ``out_of_order``
  (with ``kind_order``). Commands carry no ``seq``: only their stamps are ordered, and a
  command at the stamp of the last one is taken (it replaces it).
- **seq marks resets.** A ``seq`` that goes back while the stamp goes on is a sensor reboot or
  a wrap-around: taken, and :meth:`took` says so (event ``seq_reset``). So ``seq = 2**32 - 1``
  cannot blind a stream: order never follows ``seq``.
- **Copies of a message** (:meth:`copy_of`): the runner's door refuses a reading whose copy
  key (its ``seq`` and stamp) is among the last ``window`` of its kind, whatever came between,
  and one that carries a sample fused at another stamp with the same count
  (:meth:`elsewhere`, the last ``samples`` fused): a clock step sends new samples, not old
  ones, so a re-stamped copy is no evidence of a step either.

Two filters weigh a reading that is both a copy and out of order differently, and the
parameters state it: ``copies_first`` names such a reading ``duplicate`` (the braking-rate
adapter, whose time moves with every estimate it outputs, past its last reading), otherwise
``out_of_order``; ``kind_order`` also refuses a reading stamped before the last of its kind
taken when the estimate's time lags it (the robust filters: a balise that moved the
calibration without moving the filter's time).
"""

from __future__ import annotations

import math
from collections import deque

from .. import reasons as R


class StampOrder:
    """The order state of one estimator's inputs: the last reading of each kind taken and
    the copy keys of recent messages (class and module doc)."""

    def __init__(self, horizon: float = math.inf, copies_first: bool = False,
                 kind_order: bool = True, window: int = 64, samples: int = 8):
        self.horizon = horizon  # s, a stamp further ahead of the estimate is future_stamp
        self.copies_first = copies_first
        self.kind_order = kind_order
        self.window = window  # messages per kind whose copy keys are kept
        self.samples = samples  # fused samples kept (:meth:`elsewhere`)
        self.last: dict = {}  # kind -> (seq, stamp) of the last reading taken
        self.recent: dict = {}  # kind -> deque of copy keys (:meth:`copy_of`)
        self.keyed: dict = {}  # kind -> [{hashable key in recent: how often}, unhashable ones]
        self.fused: dict = {}  # sample key -> (stamp, value) of the last samples fused

    def judge(self, kind: str | None, stamp: float, seq: int | None = None,
              t: float | None = None) -> str:
        """"" or why the input is refused: ``kind`` None judges a time (a prediction, a
        command against the estimate) against ``t`` alone; ``seq`` None (a command) is ordered
        among its kind by stamp only; ``t`` None: no estimate yet."""
        last = self.last.get(kind)
        copy = seq is not None and last is not None and (seq == last[0] or stamp == last[1])
        if copy and self.copies_first:
            return R.DUPLICATE
        if t is not None and stamp < t:
            return R.OUT_OF_ORDER
        if t is not None and stamp - t > self.horizon:
            return R.FUTURE_STAMP
        if copy:
            return R.DUPLICATE
        if last is not None and stamp < last[1] and (self.kind_order or seq is None):
            return R.OUT_OF_ORDER
        return ""

    def took(self, kind: str, stamp: float, seq: int | None = None) -> bool:
        """Record a reading (or command) taken; True when its ``seq`` went back while its
        stamp went on (a reset). With ``kind_order``, a reading stamped before the last one
        (a late one, fused by rewinding) leaves the last one in place; without, the last taken
        is the last one."""
        last = self.last.get(kind)
        reset = (seq is not None and last is not None and last[0] is not None
                 and seq < last[0] and stamp > last[1])
        if last is None or stamp >= last[1] or not self.kind_order:
            self.last[kind] = (seq, stamp)
        return reset

    def copy_of(self, kind: str, key) -> bool:
        """Whether a message with copy ``key`` came among the last ``window`` of its kind;
        one that did not is remembered. Looked up by hash (``keyed``: every message asks, and
        the window is 64 keys long) while every key in the window has one (equal keys hash
        alike); else by comparing with each, as ``in`` does."""
        recent = self.recent.get(kind)
        if recent is None:
            recent = self.recent[kind] = deque(maxlen=self.window)
            self.keyed[kind] = [{}, 0]
        keyed = self.keyed[kind]
        try:
            hash(key)
        except TypeError:  # (a corrupted field's list, say)
            hashable = False
        else:
            hashable = True
        if key in recent if keyed[1] or not hashable else key in keyed[0]:
            return True
        if len(recent) == recent.maxlen:  # the oldest leaves the window
            self._unkey(keyed, recent[0])
        recent.append(key)
        if hashable:
            keyed[0][key] = keyed[0].get(key, 0) + 1
        else:
            keyed[1] += 1
        return False

    @staticmethod
    def _unkey(keyed: list, key) -> None:
        try:
            n = keyed[0][key]
        except TypeError:
            keyed[1] -= 1
            return
        if n > 1:
            keyed[0][key] = n - 1
        else:
            del keyed[0][key]

    def elsewhere(self, key, stamp: float, value) -> bool:
        """Whether the sample ``key`` was fused at another stamp with the same ``value`` (its
        count): a copy of it, re-stamped."""
        fused = self.fused.get(key)
        return fused is not None and fused[0] != stamp and fused[1] == value

    def fuse(self, key, stamp: float, value) -> None:
        """Record the sample ``key`` fused at ``stamp`` with ``value``; the last ``samples``
        are kept (a copy comes with its original, while a sender restarted later reuses older
        keys for new samples)."""
        self.fused.pop(key, None)
        self.fused[key] = (stamp, value)
        while len(self.fused) > self.samples:
            del self.fused[next(iter(self.fused))]

    def copy(self) -> StampOrder:
        """An independent copy (a snapshot for rewinding)."""
        new = StampOrder(self.horizon, self.copies_first, self.kind_order, self.window,
                         self.samples)
        new.last = dict(self.last)
        new.recent = {k: deque(v, maxlen=self.window) for k, v in self.recent.items()}
        new.keyed = {k: [dict(c), u] for k, (c, u) in self.keyed.items()}
        new.fused = dict(self.fused)
        return new
