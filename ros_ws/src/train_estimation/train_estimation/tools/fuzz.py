"""Corrupted input streams for the estimators (pure; used by ``benchmarks/bench_fuzz.py`` and the
tests).

:func:`corrupt` takes a clean arrival-ordered stream ``(topic, stamp, fields, recv)`` and returns
it with corrupted readings mixed in, as a radio link, a rebooting sensor or a broken clock would
deliver them. Every corrupted reading is a *new* message next to a clean one (the clean stream
stays complete), except ``reordered`` (a clean reading delivered after the next one) and the
whole-stream changes (``seq_jump``: one clean reading carries seq 2^32 - 1; ``seq_reset``: from
a point on the seq numbers restart at 0; stamp epoch/phase/drift are applied before, by the
caller). ``expected`` says which rejection names may answer each corruption.
"""

from __future__ import annotations

import math
from collections import Counter

import numpy as np

from train_estimation.core import reasons as R

ODOMETER = {
    "nan": ({"speed": math.nan}, (R.NON_FINITE,)),
    "inf": ({"distance": math.inf}, (R.NON_FINITE,)),
    "zero_variance": ({"speed_variance": 0.0}, (R.NON_POSITIVE_VARIANCE,)),
    "negative_variance": ({"speed_variance": -1.0}, (R.NON_POSITIVE_VARIANCE,)),
    "distance+1e6": ({"distance": 1e6}, (R.OUTSIDE_GATE,)),
    "distance-1e6": ({"distance": -1e6}, (R.OUTSIDE_GATE,)),
    "speed+1e6": ({"speed": 1e6}, (R.OUTSIDE_GATE,)),
    "speed-1e6": ({"speed": -1e6}, (R.OUTSIDE_GATE,)),
}
BALISE = {
    "unknown_balise": ({"balise_id": 10**6}, (R.UNKNOWN_BALISE,)),
    "contradicting_balise": ({"position": 1e6}, (R.BALISE_MAP_MISMATCH,)),
    "balise_nan": ({"position_variance": math.nan}, (R.NON_FINITE,)),
}
CONTROL = {
    "command_nan": ({"target_acceleration": math.nan}, (R.NON_FINITE,)),
    "command_1e6": ({"target_acceleration": 1e6}, (R.OUTSIDE_GATE,)),
}
STAMPS = {  # stamp change (s), expected reasons
    "future_stamp": (1e6, (R.FUTURE_STAMP,)),
    "future_stamp_1e9": (1e9, (R.FUTURE_STAMP,)),
    "stale_stamp": (-500.0, (R.OUT_OF_ORDER, R.STALE_STAMP)),
    "nan_stamp": (math.nan, (R.NON_FINITE,)),
}
ORDER = ("duplicate", "reordered")
EXPECTED = {**{k: v[1] for k, v in ODOMETER.items()}, **{k: v[1] for k, v in BALISE.items()},
            **{k: v[1] for k, v in CONTROL.items()}, **{k: v[1] for k, v in STAMPS.items()},
            "duplicate": (R.DUPLICATE,), "reordered": (R.OUT_OF_ORDER,)}


def corrupt(events: list, rng: np.random.Generator, per_reading: float = 5.0,
            seq_jump: bool = True, seq_reset: bool = True,
            stamps: dict = STAMPS) -> tuple[list, Counter]:
    """``(stream, counts)``: about ``per_reading`` corrupted messages per clean one (Poisson),
    each of a kind drawn uniformly from those that fit its topic; ``counts`` per kind.
    ``stamps``: the stamp changes to draw from (kind -> (change s, expected reasons))."""
    out: list = []
    counts: Counter = Counter()
    odo_idx = [i for i, e in enumerate(events) if e[0] == "odometer"]
    jump_at = odo_idx[len(odo_idx) // 3] if seq_jump and odo_idx else -1
    reset_at = odo_idx[2 * len(odo_idx) // 3] if seq_reset and odo_idx else -1
    reset_by = None
    pending = None  # a clean reading held back to arrive after the next one (reordered)
    dt = 0.03  # s, corrupted copies sit between samples (distinct stamps: not duplicates)
    for i, (topic, stamp, fields, recv) in enumerate(events):
        if topic not in ("control", "odometer", "balise"):
            continue
        f = dict(fields)
        if topic == "odometer":
            if i == reset_at:
                reset_by = f["seq"]
                counts["seq_reset"] += 1
            if reset_by is not None:
                f["seq"] = f["seq"] - reset_by
            if i == jump_at:
                f["seq"] = 2**32 - 1
                counts["seq_jump"] += 1
        clean = (topic, stamp, f, recv)
        if pending is not None and topic == pending[0]:
            out += [clean, pending]
            pending = None
        elif topic in ("odometer", "balise") and pending is None and rng.random() < 0.002 \
                and i not in (jump_at, reset_at):
            pending = clean
            counts["reordered"] += 1
        else:
            out.append(clean)
        for _ in range(rng.poisson(per_reading)):
            table = {"odometer": ODOMETER, "balise": BALISE, "control": CONTROL}[topic]
            kinds = list(table) + list(stamps) + ["duplicate"]
            kind = kinds[rng.integers(len(kinds))]
            counts[kind] += 1
            g = dict(f)
            s = stamp + dt if topic != "control" else stamp
            if kind in table:
                g.update(table[kind][0])
                if topic != "control":
                    g["seq"] = f["seq"] + 1 if kind in ODOMETER and "1e6" in kind else f["seq"]
            elif kind in stamps:
                s = stamp + stamps[kind][0]
            else:  # duplicate: the clean message again
                s = stamp
            if topic == "control" and kind in CONTROL:
                s = stamp  # a command at the same instant, with a bad value
            out.append((topic, s, g, recv))
    if pending is not None:
        out.append(pending)
    return out, counts
