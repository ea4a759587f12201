"""Corrupted TrainState reports for the zone controller (pure; used by the tests and
``benchmarks/bench_fuzz.py``), as :mod:`train_estimation.tools.fuzz` does for the estimators.

:func:`corrupt_reports` takes a clean stream of :class:`~train_sim.zone.TrainReport` (arrival
order) and returns it with corrupted copies mixed in after clean reports, as a broken estimator,
a flipped bit or a rebooting clock would deliver them. The clean stream stays complete, so every
clean report must still be accepted: a corrupted one that got in would show as a clean one
refused after it. ``EXPECTED`` names the refusal kind each corruption must get.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import replace

import numpy as np

from train_sim import zone as Z

FIELDS = {  # corruption -> (changed fields, expected refusal)
    "nan_position": ({"position": math.nan}, Z.NON_FINITE),
    "inf_velocity": ({"velocity": math.inf}, Z.NON_FINITE),
    "nan_position_variance": ({"var_position": math.nan}, Z.NON_FINITE),
    "nan_velocity_variance": ({"var_velocity": math.nan}, Z.NON_FINITE),
    "nan_stamp": ({"stamp": math.nan}, Z.NON_FINITE),
    "nan_braking_rate_variance": ({"braking_rate": 0.8, "var_braking_rate": math.nan},
                                  Z.NON_FINITE),
    "inf_braking_rate": ({"braking_rate": -math.inf}, Z.NON_FINITE),
    "negative_position_variance": ({"var_position": -1.0}, Z.NON_POSITIVE_VARIANCE),
    "zero_velocity_variance": ({"var_velocity": 0.0}, Z.NON_POSITIVE_VARIANCE),
    "negative_braking_rate_variance": ({"braking_rate": 1.0, "var_braking_rate": -0.01},
                                       Z.NON_POSITIVE_VARIANCE),
    "asymmetric_covariance": ({"cov_position_velocity": 0.5}, Z.NOT_POSITIVE_DEFINITE),
    "unknown_integrity": ({"integrity": 7}, Z.UNKNOWN_INTEGRITY),
    "huge_velocity": ({"velocity": 1e9}, Z.IMPLAUSIBLE_SPEED),
    "huge_negative_velocity": ({"velocity": -1e9}, Z.IMPLAUSIBLE_SPEED),
    "reversing_fast": ({"velocity": -149.0}, Z.IMPLAUSIBLE_SPEED),
    "nan_protection_level": ({"pl_ahead": math.nan}, Z.BAD_PROTECTION),
    "negative_protection_level": ({"pl_behind": -1.0}, Z.BAD_PROTECTION),
    "infinite_protection_level_ok": ({"pl_ahead": math.inf}, Z.BAD_PROTECTION),
    "huge_braking_rate": ({"braking_rate": 1e6, "var_braking_rate": 1e-4},
                          Z.IMPLAUSIBLE_BRAKING),
    "position_far_ahead": ({"position": 1e12}, Z.OFF_LINE),
    "position_far_behind": ({"position": -1e9}, Z.OFF_LINE),
}
NOT_PD = "covariance_not_positive_definite"  # |cov_xv| = 2 sqrt(var_x var_v), symmetric
FUTURE = (3.5, 60.0, 1e6, 1e9)  # s added to the stamp (beyond max_future, default 3 s)
BEHIND = (0.5, 500.0)  # s, range (log-uniform) subtracted from the stamp
EXPECTED = {**{k: v[1] for k, v in FIELDS.items()}, NOT_PD: Z.NOT_POSITIVE_DEFINITE,
            "future_stamp": Z.FUTURE_STAMP, "stamp_behind": Z.OUT_OF_ORDER}
KINDS = tuple(EXPECTED)


def corrupt_reports(clean: list, rng: np.random.Generator, per_report: float = 5.0
                    ) -> tuple[list, Counter]:
    """``(stream, counts)``: after each clean report about ``per_report`` corrupted copies
    (Poisson), each of a kind drawn uniformly from :data:`KINDS`, arriving with it;
    ``stream`` holds ``(kind or "", report)``, ``counts`` the corruptions per kind."""
    out: list = []
    counts: Counter = Counter()
    for rep in clean:
        out.append(("", rep))
        for _ in range(rng.poisson(per_report)):
            kind = KINDS[rng.integers(len(KINDS))]
            if kind in FIELDS:
                bad = replace(rep, **FIELDS[kind][0])
            elif kind == NOT_PD:
                c = 2.0 * math.sqrt(rep.var_position * rep.var_velocity)
                bad = replace(rep, cov_position_velocity=c, cov_velocity_position=c)
            elif kind == "future_stamp":
                bad = replace(rep, stamp=rep.stamp + FUTURE[rng.integers(len(FUTURE))])
            else:
                lo, hi = np.log(BEHIND[0]), np.log(BEHIND[1])
                bad = replace(rep, stamp=rep.stamp - float(np.exp(rng.uniform(lo, hi))))
            counts[kind] += 1
            out.append((kind, bad))
    return out, counts
