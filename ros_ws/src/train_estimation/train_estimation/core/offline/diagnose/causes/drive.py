"""What the causes acting on the delivered drive share (``power_limit``, ``adhesion_section``,
``traction_delay``): their extension is a drift column that is not among the motion model's
elementary ones, so each candidate (a power, a section's bins, a delay) is a column of one
further augmented filter run at the stage's noise and on the stage's events; the Kalman gains do
not depend on the columns, so every candidate's exact log-likelihood, and the null's, come from
that one run (stage.py) and are compared on it."""

from __future__ import annotations

import math
import weakref

import numpy as np

from train_estimation.core.numerics.augmented_kf import LOG2PI


class Candidates:
    """The augmented filter over [the stage's null, s0, candidate drift columns ...].

    ``R``: candidate columns on the motion model's time grid (n_grid, K), m/s^2, zero where
    the train is not moving; or ``drift``: their interval integrals (Bv, Bs), each (n_ev, K)."""

    def __init__(self, st, R: np.ndarray | None = None, drift: tuple | None = None):
        mo = st.mo
        if drift is None:
            drift = mo.grid.integrate(R, mo.ev.t.size)
        g = st.null.drive_gain  # the drive scaled by an accepted mass change (stage.Null)
        if g != 1.0:
            drift = (g * drift[0], g * drift[1])
        self.st, self.Bv, self.Bs = st, drift[0], drift[1]
        self.k = self.Bv.shape[1]
        self.kf = st.augmented(st.fv, st.fs, drift=drift, update=st.update)
        self.W = self.kf.W
        e0 = np.zeros(self.k + 2)
        e0[0] = 1.0
        self.null_quad = self.quad_fixed(e0)

    def ll(self, quad: float) -> float:
        return -0.5 * (self.kf.logdet + self.kf.m * LOG2PI + quad)

    def dll(self, quad: float) -> float:
        """Log-likelihood gain of a hypothesis with this quadratic form over the null."""
        return 0.5 * (self.null_quad - quad)

    def quad_fixed(self, u: np.ndarray) -> float:
        """The quadratic form of the fixed combination ``u`` (over [fixed, s0, columns]), s0
        profiled: w_uu - w_u1^2 / w_11."""
        W = self.W
        wu1 = u @ W[:, 1]
        return float(u @ W @ u - wu1 * wu1 / W[1, 1])

    def quads_each(self) -> np.ndarray:
        """The quadratic form of the null plus each candidate column alone (coefficient 1)."""
        W = self.W
        j = np.arange(2, self.k + 2)
        w00, w01, w11 = W[0, 0], W[0, 1], W[1, 1]
        wuu = w00 + 2 * W[0, j] + W[j, j]
        wu1 = w01 + W[j, 1]
        return wuu - wu1 * wu1 / w11

    def column(self, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The drift increments (Bv, Bs) of a combination of the candidate columns (what the
        null is extended by)."""
        return self.Bv @ weights, self.Bs @ weights


def parabola(xs, lls, i: int) -> tuple[float, float]:
    """Vertex of the parabola through the profile at i - 1, i, i + 1 (any spacing) and its
    standard error from the curvature of the profile log-likelihood; (xs[i], nan) at an edge or
    when the profile is not concave there."""
    x_hat, se = float(xs[i]), math.nan
    if 0 < i < len(xs) - 1:
        x0, x1, x2 = xs[i - 1], xs[i], xs[i + 1]
        y0, y1, y2 = lls[i - 1], lls[i], lls[i + 1]
        # second-order divided differences (Newton form)
        d01 = (y1 - y0) / (x1 - x0)
        d12 = (y2 - y1) / (x2 - x1)
        c2 = (d12 - d01) / (x2 - x0)
        if c2 < 0:
            b = d01 - c2 * (x0 + x1)
            x_hat = float(np.clip(-b / (2 * c2), x0, x2))
            se = 1.0 / math.sqrt(-2 * c2)
    return x_hat, se


def untestable_without_traction(run, cfg, min_traction: float) -> str | None:
    """Why a traction cause cannot be tested: no command of at least ``min_traction`` (m/s^2)
    given while the train moves (None: there is one)."""
    trac = run.ctrl_a > min_traction
    v_at_cmd = np.interp(run.ctrl_t, run.odo_t, run.odo_v)
    return None if np.any(trac & (v_at_cmd > cfg.standstill_speed)) else \
        "no traction command while moving in the data"


_TRACTION: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # Motion -> {timing: a_tr}


def traction_at(mo, timing: float) -> np.ndarray:
    """m/s^2 on the grid: the believed traction through the actuator with the commands re-timed
    by ``timing`` s (cached per run)."""
    cache = _TRACTION.setdefault(mo, {})
    key = round(float(timing), 6)
    if key not in cache:
        cache[key] = mo.a_tr0 if key == 0.0 else mo._part(key, "traction")
    return cache[key]


def null_traction(mo, null) -> np.ndarray:
    """The traction the null delivers before any power limit: the commands re-timed by the
    accepted traction delay, else by the common command-time offset."""
    timing = null.traction_timing if null.traction_timing is not None else null.shift
    return traction_at(mo, timing)


def capped(mo, a_tr: np.ndarray, p_spec: float | None) -> np.ndarray:
    """The traction ``a_tr`` capped at p_spec / v (train_core dynamics.py); uncapped when
    ``p_spec`` is None."""
    if p_spec is None:
        return a_tr
    return np.minimum(a_tr, p_spec / np.maximum(mo.v_ref, 1e-3))
