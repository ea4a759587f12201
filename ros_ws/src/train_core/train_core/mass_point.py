"""Single mass-point train model of the hybrid-filter EM paper (eq. (1)-(7)): the model both the
simulator (``train_sim.crh3``) and the estimator (``train_estimation.core.offline.em_model``) use.

Continuous model (eq. (1)-(2)), specific forces in N/kN (newton per kilonewton of train weight)::

    ds/dt = v,    dv/dt = epsilon (f(v) - w(v)),   w(v) = a + b v + c v^2,
    epsilon = 0.0098 / (1 + d)                     # (m/s^2) per (N/kN); d = rotary allowance

(1 N/kN = 1e-3 g = 0.0098 m/s^2, hence the constant.) Euler discretisation with step T
(eq. (3)-(7)), time index t = 1..n, state (s(0), v(0)) given by a prior::

    s(t) = s(t-1) + T v(t-1) + w1(t)                                    w1 ~ N(0, delta1^2)
    v(t) = v(t-1) + dbar [u(t) - (a + b v(t-1) + c v(t-1)^2)] + w2(t)   w2 ~ N(0, delta2^2)
    y1(t) = s(t) + e1(t),   y2(t) = v(t) + e2(t)                        e_i ~ N(0, sigma_i^2)

Parameters (eq. (31)-(34)): ``vartheta = [dbar, dbar a, dbar b, dbar c]`` with
``dbar = 0.0098 T / (1 + d)``; the velocity increment is ``Phi(t)^T vartheta`` (regressors
``Phi = [u, -1, -v, -v^2]``).

Pure: numpy only. Arrays carry the time index first and an optional batch in trailing axes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["G_PER_KN", "CRH3_PARAMS", "CRH3_VARTHETA", "MassPointParams", "NoiseParams",
           "expand_to", "regressors", "velocity_drift"]

G_PER_KN = 0.0098  # (m/s^2) per (N/kN): 1 N per kN of weight = g/1000 (paper rounds g = 9.8)


@dataclass(frozen=True)
class MassPointParams:
    """Theta = [a, b, c, d] of eq. (9): specific Davis resistance and rotary allowance."""

    a: float  # N/kN, constant specific resistance
    b: float  # N/kN per (m/s), linear term
    c: float  # N/kN per (m/s)^2, quadratic (aerodynamic) term
    d: float  # -, rotary mass coefficient: effective mass = (1 + d) M

    def to_vartheta(self, T: float = 1.0) -> np.ndarray:
        """eq. (32), (34): [dbar, dbar a, dbar b, dbar c] with dbar = 0.0098 T / (1 + d)."""
        dbar = G_PER_KN * T / (1.0 + self.d)
        return np.array([dbar, dbar * self.a, dbar * self.b, dbar * self.c])

    @staticmethod
    def from_vartheta(vt, T: float = 1.0) -> MassPointParams:
        """Inverse of eq. (32), (34). Requires dbar > 0."""
        vt = np.asarray(vt, dtype=float)
        if vt.shape != (4,) or not np.all(np.isfinite(vt)) or vt[0] <= 0:
            raise ValueError(f"vartheta must be 4 finite numbers with dbar > 0, got {vt!r}")
        dbar = vt[0]
        return MassPointParams(a=vt[1] / dbar, b=vt[2] / dbar, c=vt[3] / dbar,
                               d=G_PER_KN * T / dbar - 1.0)


# CRH3 example of Section 3 (four motor + four trailer cars): a, b, c per the paper, d = 0.06.
CRH3_PARAMS = MassPointParams(a=0.53, b=0.0039, c=0.000114, d=0.06)
# The vector the paper's Tables 1-3 measure the error against (a rounding of CRH3_PARAMS, T = 1).
CRH3_VARTHETA = np.array([0.0092, 0.0049, 0.00004, 0.000001])


@dataclass(frozen=True)
class NoiseParams:
    """Known noise variances of eq. (5)-(7) (the paper treats them as known)."""

    q_s: float = 0.01  # m^2, delta1^2: displacement process noise per step
    q_v: float = 0.01  # (m/s)^2, delta2^2: velocity process noise per step
    r_s: float = 0.01  # m^2, sigma1^2: displacement measurement noise
    r_v: float = 0.01  # (m/s)^2, sigma2^2: velocity measurement noise

    def __post_init__(self):
        for k in ("q_s", "q_v", "r_s", "r_v"):
            val = getattr(self, k)
            if not (np.isfinite(val) and val > 0):
                raise ValueError(f"NoiseParams.{k} must be finite and > 0, got {val!r}")


def expand_to(x, ndim: int) -> np.ndarray:
    """Append singleton axes so a (n,) series broadcasts against (n, *batch) arrays."""
    x = np.asarray(x, float)
    return x.reshape(x.shape + (1,) * (ndim - x.ndim))


def regressors(u, v_prev) -> np.ndarray:
    """eq. (33): Phi = [u, -1, -v, -v^2] stacked on a new last axis (broadcast u with v)."""
    u, v = np.broadcast_arrays(np.asarray(u, float), np.asarray(v_prev, float))
    return np.stack([u, -np.ones_like(v), -v, -v * v], axis=-1)


def velocity_drift(vt, u, v_prev):
    """Phi^T vartheta: the deterministic velocity increment of eq. (18) for parameters ``vt``.

    ``vt`` has shape (4,) or (4, *batch) (batch trailing, to match data arrays); ``u`` and
    ``v_prev`` broadcast against the batch shape (particles lead).
    """
    vt = np.asarray(vt, float)
    return vt[0] * u - vt[1] - vt[2] * v_prev - vt[3] * v_prev * v_prev
