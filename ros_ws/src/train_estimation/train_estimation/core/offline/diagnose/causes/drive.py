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
        profiled: w_uu - w_u1^2 / w_11; w_uu where the events carry no information on s0
        (w_11 = 0: no speed updated, as on a fold without odometer speeds), as the stage's
        own profile (``Stage``) takes it."""
        W = self.W
        wu1 = u @ W[:, 1]
        uwu = float(u @ W @ u)
        return uwu - float(wu1 * wu1 / W[1, 1]) if W[1, 1] > 0 else uwu

    def quads_each(self) -> np.ndarray:
        """The quadratic form of the null plus each candidate column alone (coefficient 1), s0
        profiled as in :meth:`quad_fixed`."""
        W = self.W
        j = np.arange(2, self.k + 2)
        w00, w01, w11 = W[0, 0], W[0, 1], W[1, 1]
        wuu = w00 + 2 * W[0, j] + W[j, j]
        wu1 = w01 + W[j, 1]
        return wuu - wu1 * wu1 / w11 if w11 > 0 else wuu

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


def delay_profile(prof: dict) -> tuple[list, list, dict]:
    """The profile likelihood of an extra delay d from {(offset s, d): log-likelihood}: the
    offset maximised out at each d (the two trade off: both move a chain's timing, so the
    curvature at the best offset alone understates the delay's doubt). Returns the delays in
    order, their values and {d: the best offset at d}."""
    best: dict = {}
    for (s, d), v in prof.items():
        if d not in best or v > best[d][0]:
            best[d] = (v, s)
    ds = sorted(best)
    return ds, [best[d][0] for d in ds], {d: best[d][1] for d in ds}


# the profile log-likelihood's drop from its best within which a delay's profile is fitted by
# a parabola (:func:`envelope`): 8 is +-4 standard errors of a quadratic profile
ENVELOPE_DROP = 8.0


def envelope(xs, lls, i: int, drop: float = ENVELOPE_DROP) -> tuple[float, float]:
    """Vertex and standard error of the parabola fitted by least squares to the profile
    log-likelihood ``lls`` over ``xs`` at the points around its best ``i`` (contiguous) that
    lie within ``drop`` of it; :func:`parabola` at ``i`` when fewer than four points do, when
    they reach an end of the grid (the profile's fall on that side unseen) or when the fit is
    not concave.

    A delay's profile is rough: the commands change on the driver's grid and the readings
    come on the odometer's, so the likelihood moves in small steps as a delay passes their
    instants, with local peaks 0.05-0.1 s apart 1-3 log-likelihood units deep (a foreign ATO
    at 0.2 s and a 5 Hz odometer). The curvature through three neighbours of the best is that
    roughness, not the information: it gave a traction delay 1.511 +- 0.016 s for a truth of
    1.464 (z +2.9; another bag +4.2), and the two halves of that run 1.535 +- 0.015 and
    1.420 +- 0.014, each on another local peak (z +5.6). The parabola over +-4 standard errors
    follows the profile's envelope: 1.483 +- 0.030 s, halves 1.521 +- 0.041 and 1.453 +- 0.043
    (z +1.2), the whole run's SE about 1/sqrt(2) of a half's, as the information says. On a
    smooth quadratic profile it is the three-point parabola's vertex and SE."""
    y = np.asarray(lls, dtype=float)
    x = np.asarray(xs, dtype=float)
    lo = hi = i
    while lo > 0 and y[lo - 1] >= y[i] - drop:
        lo -= 1
    while hi < y.size - 1 and y[hi + 1] >= y[i] - drop:
        hi += 1
    if hi - lo < 3 or lo == 0 or hi == y.size - 1:
        # too few points, or the window reaches an end of the grid (the profile's fall on
        # that side unseen): the three points around the best
        return parabola(xs, lls, i)
    c2, c1, _ = np.polyfit(x[lo:hi + 1] - x[i], y[lo:hi + 1], 2)
    if not c2 < 0:
        return parabola(xs, lls, i)
    return float(np.clip(x[i] - c1 / (2 * c2), x[lo], x[hi])), 1.0 / math.sqrt(-2 * c2)


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
