"""One record of a measured run: what the offline tools (identify, diagnose, fleet) read of a
bag, and the health of its topics.

Only ``odometer``, ``balise`` and ``control`` are taken (a ``ground_truth`` topic, if present,
is never read). Stamps as recorded (docs/interfaces.md clocks): odometer and balise on the train's
clock, control on the reference clock; ``*_recv`` are the bag's log (receive) times on the
reference clock. Arrays in bag order.

Pure: numpy and train_core only (a read :class:`train_core.bagio.Bag` in, no file access).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from .. import reasons as R
from .clock_fit import clock_rate_change, clock_steps, control_on_train_clock

TOPICS = ("odometer", "balise", "control")  # never ground_truth


@dataclass(frozen=True)
class MeasuredRun:
    """Measured series of one run, as recorded."""

    odo_stamp: np.ndarray  # s, train clock
    odo_recv: np.ndarray  # s, reference clock (bag log time)
    odo_seq: np.ndarray  # -, uint32 sample counter before the link
    odo_distance: np.ndarray  # m
    odo_speed: np.ndarray  # m/s
    odo_speed_variance: np.ndarray  # (m/s)^2
    ctrl_stamp: np.ndarray  # s, reference clock
    ctrl_a_tar: np.ndarray  # m/s^2
    balise_stamp: np.ndarray  # s, train clock
    balise_recv: np.ndarray  # s, reference clock
    balise_id: np.ndarray  # -
    balise_position: np.ndarray  # m, surveyed position
    balise_variance: np.ndarray  # m^2
    ctrl_recv: np.ndarray | None = None  # s, reference clock (bag log time)
    topics: tuple = ()  # the topics the bag held (names relative to its namespace)
    notes: tuple = ()  # what was read otherwise than recorded, and why

    @classmethod
    def from_bag(cls, bag) -> MeasuredRun:
        """The record of a read bag (:class:`train_core.bagio.Bag`)."""

        def col(topic, key, dtype=float):
            return np.array([f[key] for _, _, f in bag.topics.get(topic, [])], dtype=dtype)

        def stamps(topic):
            return np.array([s for _, s, _ in bag.topics.get(topic, [])], dtype=float)

        def recv(topic):
            return np.array([t for t, _, _ in bag.topics.get(topic, [])], dtype=float) * 1e-9

        ctrl_stamp, ctrl_recv, notes = stamps("control"), recv("control"), ()
        if ctrl_stamp.size >= 2 and ctrl_recv.size == ctrl_stamp.size and \
                not np.any(ctrl_stamp != 0.0) and np.ptp(ctrl_recv) > 0.0:
            # a producer that leaves the commands' header empty: the contract stamps commands
            # on the reference clock, the receive time (as the estimators' runner reads them)
            ctrl_stamp = ctrl_recv.copy()
            notes = ("every control command stamped 0 (no stamp stated): their log times "
                     "used, the reference clock the contract stamps commands on",)
        return cls(
            odo_stamp=stamps("odometer"), odo_recv=recv("odometer"),
            odo_seq=col("odometer", "seq", np.int64), odo_distance=col("odometer", "distance"),
            odo_speed=col("odometer", "speed"),
            odo_speed_variance=col("odometer", "speed_variance"),
            ctrl_stamp=ctrl_stamp, ctrl_a_tar=col("control", "target_acceleration"),
            balise_stamp=stamps("balise"), balise_recv=recv("balise"),
            balise_id=col("balise", "balise_id", np.int64),
            balise_position=col("balise", "position"),
            balise_variance=col("balise", "position_variance"),
            ctrl_recv=ctrl_recv, topics=tuple(sorted(bag.topics)), notes=notes)

    def without_clock_steps(self) -> tuple[MeasuredRun, list]:
        """The run with the train clock's steps taken out of the odometer and balise stamps
        (:func:`~train_estimation.core.offline.clock_fit.clock_steps` on the odometer's
        readings in sequence order): every reading from a step on is put back on the clock
        before it; a balise reading is after a step when it was logged after halfway between
        the last odometer reading before it and the first after it. Returns (run, steps),
        each step (stamp where it happened, on the clock before it; J s, what the clock reads
        more from there; log time from which readings are after it). Unchanged without seq
        numbers or log times, or without a step."""
        s, r = np.asarray(self.odo_stamp, float), np.asarray(self.odo_recv, float)
        seq = np.asarray(self.odo_seq)
        ok = np.isfinite(s) & np.isfinite(r)
        if seq.size != s.size or r.size != s.size or ok.sum() < 2:
            return self, []
        idx = np.flatnonzero(ok)
        by_recv = idx[np.argsort(r[idx], kind="stable")]
        q_recv = unwrap(seq[by_recv])
        o = _stamp_order(q_recv)  # sequence order, a repeated seq's first reading
        order, q = by_recv[o], q_recv[o]
        found = clock_steps(s[order], q)
        if not found:
            return self, []
        q_all = np.full(s.size, np.iinfo(np.int64).min)
        q_all[by_recv] = q_recv
        odo, bal = s.copy(), np.asarray(self.balise_stamp, float).copy()
        bal_r = np.asarray(self.balise_recv, float)
        steps = []
        for i, jump in found:
            odo[q_all >= q[i]] -= jump
            r_from = 0.5 * (r[order[i - 1]] + r[order[i]])
            if bal_r.size == bal.size:
                bal[bal_r >= r_from] -= jump
            steps.append((float(odo[order[i]]), float(jump), float(r_from)))
        return dataclasses.replace(self, odo_stamp=odo, balise_stamp=bal), steps

    def without_rate_change(self) -> tuple[MeasuredRun, dict | None]:
        """The run with a change of the train clock's rate taken out of the odometer and
        balise stamps (:func:`~train_estimation.core.offline.clock_fit.clock_rate_change` on
        the odometer's stamps and log times): stamps after the bend are put on the rate
        before it, s' = at + (s - at) (1 + drift_before) / (1 + drift_after). Returns (run,
        the change with ``at``, the stamp of the bend), or (self, None) without one."""
        s, r = np.asarray(self.odo_stamp, float), np.asarray(self.odo_recv, float)
        if r.size != s.size:
            return self, None
        ok = np.flatnonzero(np.isfinite(s) & np.isfinite(r))
        o = ok[_stamp_order(s[ok])]
        ch = clock_rate_change(s[o], r[o])
        if ch is None:
            return self, None
        at = float(s[o][0] + ch["when"])
        k = (1.0 + ch["drift_before"]) / (1.0 + ch["drift_after"])

        def fix(x):
            x = np.asarray(x, float)
            return np.where(x > at, at + (x - at) * k, x)

        return (dataclasses.replace(self, odo_stamp=fix(s), balise_stamp=fix(self.balise_stamp)),
                dict(ch, at=at))

    def to_identify(self):
        """identify's :class:`SIData`: every time on the odometer's (train) clock, control
        mapped through the odometer's stamps and log times. Raises IdentificationError
        naming the missing topics."""
        from .identify import IdentificationError, SIData

        missing = [t for t, a in (("odometer", self.odo_stamp), ("control", self.ctrl_stamp))
                   if len(a) == 0]
        if missing:
            raise IdentificationError(
                f"the bag has no {' and no '.join(missing)} messages (topics: "
                f"{list(self.topics) or 'none'})", missing=missing,
                unidentifiable=("davis.a", "davis.b", "davis.c", "mass", "rotary_allowance",
                                "braking_rate"))
        # a step or a change of rate of the train's clock would move the readings after it
        # against the commands
        self, _ = self.without_clock_steps()
        self, _ = self.without_rate_change()
        ctrl_recv = self.ctrl_recv if self.ctrl_recv is not None else np.array([])
        ctrl_t = control_on_train_clock(self.odo_stamp, self.odo_recv, self.ctrl_stamp,
                                        ctrl_recv)
        # A bag holds messages in arrival order: a link with jitter reorders them and may
        # deliver one twice. identify wants each series in stamp order, one reading a stamp
        # (the first kept), as diagnose prepares it.
        o = _stamp_order(self.odo_stamp)
        c = _stamp_order(ctrl_t)
        b = _stamp_order(self.balise_stamp)
        has_bal = b.size > 0
        return SIData(
            odo_t=self.odo_stamp[o], odo_distance=self.odo_distance[o],
            odo_speed=self.odo_speed[o],
            # every variance 0: not stated (zeros mean "unknown" in ROS's covariance
            # fields), so identify takes train.yaml's (None)
            odo_speed_variance=None if variances_unstated(self.odo_speed_variance)
            else self.odo_speed_variance[o],
            ctrl_t=ctrl_t[c], ctrl_a_tar=self.ctrl_a_tar[c],
            balise_t=self.balise_stamp[b] if has_bal else None,
            balise_position=self.balise_position[b] if has_bal else None)


def variances_unstated(var) -> bool:
    """A stream that states no variance: some entries 0 and none positive and finite (zeros
    mean "unknown" in ROS's covariance fields; a NaN beside them states nothing either). The
    one rule of diagnose and identify (the estimators' runner decides per reading, online)."""
    var = np.asarray(var, float)
    return bool(np.any(var == 0) and not np.any(np.isfinite(var) & (var > 0)))


def no_counter(seq) -> bool:
    """A stream without a sample counter: more than two readings, every seq the same (a
    producer that leaves the field at its default)."""
    seq = np.asarray(seq)
    return bool(seq.size > 2 and np.all(seq == seq.flat[0]))


def unwrap(seq: np.ndarray) -> np.ndarray:
    """uint32 sequence numbers in time order -> increasing int64 (wrap-around at 2^32)."""
    q = np.asarray(seq).astype(np.int64)
    d = np.diff(q)
    d = np.where(d < -(2 ** 31), d + 2 ** 32, d)
    return np.concatenate([[0], np.cumsum(d)]) + (q[0] if q.size else 0)


def counter_runs(seq, stamp) -> tuple[np.ndarray, np.ndarray]:
    """A sample counter in log order: its values unwrapped past 2^32 - 1 (:func:`unwrap`) and
    the run of the counter each belongs to. A run ends where the counter goes back while the
    stamps go on past the highest sample's (a sender that restarted its count); a counter that
    goes back with its stamp is a reading the link delivered late, and one ahead of the run's
    highest with a stamp before it is a late reading of the run before. Counts of received and
    lost samples are per run: across a restart the counter says nothing about losses."""
    q = unwrap(np.asarray(seq))
    st = np.asarray(stamp, float)
    runs = np.zeros(q.size, dtype=np.int64)
    if q.size == 0:
        return q, runs
    r, hi_q, hi_s = 0, q[0], st[0]
    for i in range(1, q.size):
        if q[i] > hi_q:
            if r and st[i] < hi_s:
                runs[i] = r - 1  # late, from the run before the restart
                continue
            hi_q, hi_s = q[i], st[i]
        elif q[i] < hi_q and st[i] > hi_s:
            r, hi_q, hi_s = r + 1, q[i], st[i]  # restarted
        runs[i] = r
    return q, runs


def counter_gaps(q: np.ndarray, runs: np.ndarray) -> list[tuple[int, int, int]]:
    """Per run of a counter (:func:`counter_runs`): (samples received, samples the counter
    spans, gaps in it)."""
    out = []
    for r in np.unique(runs):
        u = np.unique(q[runs == r])
        out.append((int(u.size), int(u[-1] - u[0] + 1), int(np.sum(np.diff(u) > 1))))
    return out


def _stamp_order(stamp) -> np.ndarray:
    """Indices of ``stamp`` in increasing order, a repeated stamp's first reading only."""
    stamp = np.asarray(stamp, float)
    if stamp.size == 0:
        return np.zeros(0, dtype=int)
    idx = np.argsort(stamp, kind="stable")
    keep = np.concatenate([[True], np.diff(stamp[idx]) > 0])
    return idx[keep]


# TrainState fields where NaN is a value by design: "not estimated" (docs/interfaces.md), e.g.
# the control acceleration and braking rate of the robust filter, which estimates neither.
# Infinity is never by design.
NOT_ESTIMATED_NAN = ("acceleration", "braking_rate", "covariance")


def _non_finite(stamp: float, fields: dict) -> bool:
    """A stamp or field that is not a finite number, NaN-by-design fields excepted."""
    if not math.isfinite(stamp):
        return True
    state = "source" in fields and "covariance" in fields  # a TrainState
    for k, v in fields.items():
        if isinstance(v, (float, np.floating)):
            if math.isfinite(v) or (state and k in NOT_ESTIMATED_NAN and math.isnan(v)):
                continue
            return True
        if isinstance(v, np.ndarray) and v.dtype.kind == "f":
            bad = ~np.isfinite(v)
            if state and k in NOT_ESTIMATED_NAN:
                bad &= ~np.isnan(v)
            if bad.any():
                return True
    return False


def topic_health(bag, topic: str) -> dict:
    """Count, type, stamp order, non-finite values, largest gap and (with ``seq``) the received
    fraction of one topic of a read bag; the estimators' rejection names (core/reasons.py) for
    what the stamps alone show."""
    msgs = bag.topics.get(topic, [])
    stamps = bag.stamps(topic)
    out: dict = {"count": len(msgs), "type": bag.types.get(topic, "")}
    if len(msgs) == 0:
        return out
    d = np.diff(stamps)
    out[R.OUT_OF_ORDER] = int(np.sum(d < 0))
    out["duplicate_stamps"] = int(np.sum(d == 0))
    out[R.NON_FINITE] = int(sum(1 for _, s, f in msgs if _non_finite(s, f)))
    out["max_gap_s"] = float(d.max()) if d.size else 0.0
    if "seq" in msgs[0][2]:
        # per run of the counter, unwrapped past 2^32 - 1 (a counter that wraps lost nothing;
        # one that restarted says nothing of the samples between its runs)
        runs = counter_gaps(*counter_runs(bag.series(topic, "seq"), stamps))
        span = sum(n for _, n, _ in runs)
        out["seq_span"] = span
        out["received_fraction"] = sum(k for k, _, _ in runs) / span
        out["seq_gaps"] = sum(g for _, _, g in runs)
        out["seq_restarts"] = len(runs) - 1
    return out
