"""The odometer's residual checks (``diagnose.phases.sensor_residuals``) on the nominal bags of
``train_sim.cases`` and on the same bags with an error hidden in the odometer's speed readings:
what tests/test_diagnose_residuals.py asserts and ``./run bench diagnose`` (part ``residuals``)
reports against its targets.
"""

from __future__ import annotations

import dataclasses
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import bench_balise_scatter as BS  # noqa: E402

ALPHA = 1e-3  # the stated false-alarm rate of the four tests together


def checks_on_case(seed: int, effect=None, alpha: float = ALPHA) -> dict:
    """The checks on nominal bag ``seed`` (``bench_balise_scatter.nominal_bag``: case [seed,
    31], its family drawn), with ``effect(speeds, rng, stamps)`` added to the odometer's speed
    readings: ``sensor_residuals``' result and the bag's ``family``."""
    from train_estimation.core.offline.diagnose.motion import Motion
    from train_estimation.core.offline.diagnose.phases import sensor_residuals
    from train_estimation.core.offline.diagnose.run import DiagConfig, prepare
    from train_estimation.core.offline.diagnose.stage import Null, Stage

    case, data = BS.nominal_bag(seed)
    if effect is not None:
        data = dataclasses.replace(data, odo_speed=effect(data.odo_speed,
                                                          np.random.default_rng(seed),
                                                          data.odo_stamp))
    cfg = DiagConfig()
    sc = case.scenario
    run = prepare(data, sc.line, cfg, sc.train)
    mo = Motion(run, sc.line, sc.train, cfg)
    null = Null(shift=Stage(mo, Null(), cfg).nuisance_shift()[0])
    st = Stage(mo, null, cfg)
    out = sensor_residuals(mo, null, cfg, (st.q, st.r_s), alpha)
    out["family"] = case.family
    return out


def ar1(speed, rng, t, phi=0.9, sd=0.1):
    """An AR(1) error (``phi``, SD ``sd`` m/s: 1-2 times the stated SD of these bags)."""
    eta = rng.standard_normal(speed.size) * sd * np.sqrt(1 - phi * phi)
    x = np.zeros(speed.size)
    for k in range(1, speed.size):
        x[k] = phi * x[k - 1] + eta[k]
    return speed + x


def grows(speed, rng, t, sd=0.1):
    """Extra noise from 0 at standstill to 0.1 m/s at the top speed (1-2 times the stated SD
    of these bags)."""
    return speed + sd * np.abs(speed) / np.max(np.abs(speed)) * rng.standard_normal(speed.size)


# effect -> the words of the signature that name it (what the check for it says)
EFFECTS = {"ar1": (ar1, "correlated in time"), "grows": (grows, "changes with speed")}
LABELS = {"ar1": "an AR(1) error (phi 0.9, SD 0.1 m/s)",
          "grows": "noise growing with speed (to 0.1 m/s)"}


def false_alarm_bound(n: int, alpha: float = ALPHA) -> int:
    """The most alarms in ``n`` nominal bags within the binomial 99.9 % bound at ``alpha``."""
    from scipy.stats import binom

    return int(binom.ppf(0.999, n, alpha))
