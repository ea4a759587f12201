"""Synthetic data of the hybrid-filter EM paper's CRH3 example: the discrete mass-point model
(``train_core.mass_point``, eq. (5)-(7)) driven by a feedback driver.

Pure: numpy only; randomness from the caller's ``rng``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from train_core.mass_point import CRH3_VARTHETA, NoiseParams, velocity_drift

__all__ = ["CRH3Data", "crh3_input_schedule", "simulate_crh3"]


# ---------------------------------------------------------------------------------------------
# Synthetic CRH3 data. The paper gives neither the data length nor the input u(t); the input here
# is a driver that cycles accelerate -> cruise -> coast -> brake between random speed targets so
# that u, 1, v and v^2 are all excited (0 .. ~80 m/s).
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CRH3Data:
    """Simulated data set; arrays have time first and the batch (seeds) trailing."""

    u: np.ndarray  # (n, *b) N/kN, u(1..n)
    y1: np.ndarray  # (n, *b) m, y1(1..n)
    y2: np.ndarray  # (n, *b) m/s, y2(1..n)
    s: np.ndarray  # (n+1, *b) m, true s(0..n)
    v: np.ndarray  # (n+1, *b) m/s, true v(0..n)
    T: float = 1.0  # s

    @property
    def n(self) -> int:
        return self.u.shape[0]


def crh3_input_schedule(v, phase, target, timer, rng, vt=CRH3_VARTHETA):
    """One step of the driver (vectorised over the batch): returns (u, phase, target, timer).

    Phases 0 accelerate (u = 35 N/kN) until v > target, 1 cruise (u balances the resistance at
    the current speed, ~ 40-160 s), 2 coast (u = 0, ~ 30-90 s), 3 brake (u = -30 N/kN) until
    v < target. Targets: high in U(40, 80) m/s, low in U(5, 30) m/s.
    """
    shape = np.shape(v)
    hi = rng.uniform(40.0, 80.0, shape)
    lo = rng.uniform(5.0, 30.0, shape)
    cruise_len = rng.integers(40, 160, shape)
    coast_len = rng.integers(30, 90, shape)
    timer = timer - 1
    to_cruise = (phase == 0) & (v > target)
    to_coast = (phase == 1) & (timer <= 0)
    to_brake = (phase == 2) & (timer <= 0)
    to_acc = (phase == 3) & (v < target)
    phase = np.where(to_cruise, 1, np.where(to_coast, 2, np.where(to_brake, 3,
                     np.where(to_acc, 0, phase))))
    timer = np.where(to_cruise, cruise_len, np.where(to_coast, coast_len, timer))
    target = np.where(to_brake, lo, np.where(to_acc, hi, target))
    res = (vt[1] + vt[2] * v + vt[3] * v * v) / vt[0]
    u = np.select([phase == 0, phase == 1, phase == 2], [35.0, res, 0.0], -30.0)
    return u, phase, target, timer


def simulate_crh3(n: int, rng: np.random.Generator, batch: int | None = None,
                  vt=CRH3_VARTHETA, noise: NoiseParams | None = None, T: float = 1.0,
                  v0_std: float = 0.2) -> CRH3Data:
    """Simulate eq. (5)-(7) for ``n`` steps (``batch`` independent runs in a trailing axis).

    s(0) = 0, v(0) ~ N(0, v0_std^2) (the paper's particle initialisation, step 2), clipped >= 0.
    The input is the feedback driver :func:`crh3_input_schedule`: u(t) depends on v(t-1) only,
    which is what eq. (4) allows (u(t) = f(v(t-1)) measurable).
    """
    if n < 10:
        raise ValueError(f"n must be >= 10, got {n}")
    noise = NoiseParams() if noise is None else noise
    shape = () if batch is None else (batch,)
    vt = np.asarray(vt, float)
    s = np.zeros((n + 1,) + shape)
    v = np.zeros((n + 1,) + shape)
    u = np.zeros((n,) + shape)
    v[0] = np.abs(v0_std * rng.standard_normal(shape))
    phase = np.zeros(shape, int)
    target = rng.uniform(40.0, 80.0, shape)
    timer = np.zeros(shape, int)
    w1 = np.sqrt(noise.q_s) * rng.standard_normal((n,) + shape)
    w2 = np.sqrt(noise.q_v) * rng.standard_normal((n,) + shape)
    for t in range(1, n + 1):
        ut, phase, target, timer = crh3_input_schedule(v[t - 1], phase, target, timer, rng, vt)
        u[t - 1] = ut
        s[t] = s[t - 1] + T * v[t - 1] + w1[t - 1]
        v[t] = v[t - 1] + velocity_drift(vt, ut, v[t - 1]) + w2[t - 1]
    y1 = s[1:] + np.sqrt(noise.r_s) * rng.standard_normal((n,) + shape)
    y2 = v[1:] + np.sqrt(noise.r_v) * rng.standard_normal((n,) + shape)
    return CRH3Data(u=u, y1=y1, y2=y2, s=s, v=v, T=T)
