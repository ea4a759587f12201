"""Data from the braking model's own discrete recursion (Zheng et al. 2015, Section 4): the
open-loop toy of the braking tests and ``benchmarks/bench_braking.py``.

Test and benchmark support, deliberately outside the estimation core (no data generator
in the core). It is *not* the simulator's open loop (``train_sim.world.open_loop``):
the world uses the exact transport delay and train physics, while the exactness tests and
Zheng's Tables 1-2 need data from the estimators' own model (Pade delay, exact ZOH), where the
KF is the exact posterior.
"""

from __future__ import annotations

import numpy as np

from train_estimation.core.braking.braking_model import C_ROWS, BrakingParams, discretize

__all__ = ["simulate_open_loop"]


def simulate_open_loop(params: BrakingParams, braking_rates, u_seq, x0, rng: np.random.Generator,
                       meas_std=None, dt: float | None = None):
    """Data from the discrete model itself (Zheng Section 4): ``x_k = Phi(f_k) x_{k-1} + B(f_k)
    u_k + w_k``, ``y_k = C x_k + e_k`` for k = 1..K.

    ``u_seq (K, 2)`` is held over ``(k-1, k]``; ``braking_rates (K,)`` is the true braking rate
    on that interval. Returns ``x (K+1, 4)`` (``x[0] = x0``) and ``y (K, 3)``. ``meas_std``
    defaults to the square root of ``params.meas_var``.
    """
    braking_rates = np.asarray(braking_rates, dtype=float)
    u_seq = np.asarray(u_seq, dtype=float).reshape(len(braking_rates), -1)
    K = len(braking_rates)
    dt = params.dt if dt is None else dt
    Phi, Bd, Qd = discretize(braking_rates, params, dt)
    # Qd may be rank one ("zoh"): an eigen factor is exact for PSD matrices, Cholesky is not.
    ev, V = np.linalg.eigh(Qd)
    Lq = V * np.sqrt(np.clip(ev, 0.0, None))
    sd = np.sqrt(np.asarray(params.meas_var)) if meas_std is None else np.asarray(meas_std)
    x = np.empty((K + 1, 4))
    x[0] = x0
    w = rng.standard_normal((K, 4)) @ Lq.T
    for k in range(K):  # a time loop (not a particle loop): the truth is one trajectory
        x[k + 1] = Phi[k] @ x[k] + Bd[k] @ u_seq[k] + w[k]
    y = x[1:] @ C_ROWS.T + rng.standard_normal((K, 3)) * sd
    return x, y
