"""The sensors' residuals against what they state: the odometer's scatter, correlation in
time, dependence on speed and distance, and its speed readings against its own count; the
balise readings' correlation in time and dependence on speed and distance (pure: arrays in,
figures out).

A sensor whose readings scatter more than its stated variance, whose errors are correlated in
time, or whose noise grows with speed is not the sensor the estimators assume, and no listed
cause is such a sensor: the motion model's fitted process noise absorbs it (on an
independent simulator's odometer with such noise it rose by five orders of magnitude, and the
verdict was ``none``). Three tests, each at a stated false-alarm rate under the stated sensor:

- **Scatter** (:func:`scatter_test`): the speed readings less the motion model's speed (the
  commands through the believed train: its kinks where a command steps or the train stops)
  of each stretch of the run without a gap longer than ``MAX_GAP`` (a link's burst) or a
  standstill are fitted by a cubic spline with knots every
  ``KNOT_S`` s, by least squares weighted by the stated variances; under the stated sensor
  (white noise of the stated variance about a motion that such a spline follows) the sum
  T = sum r^2 / rv of the residuals is chi-square with n - p degrees of freedom exactly (p:
  the splines' coefficients). Excess scatter: the upper tail below ``alpha``. What the model
  misses of the motion is smooth on 2 s, the noise is not; without the model's speed the
  spline missed the kinks (nominal metro bags: 1.07-1.16 times the stated variance, p down
  to 1e-6; with it 1.00-1.07).
- **Correlation in time** (:func:`ljung_box`): the same standardised residuals z = r /
  sqrt(rv) through the Ljung-Box statistic over lags 1..``lags`` (products within the
  stretches only), each autocorrelation less the one the spline's fit gives white noise by
  itself (-sum_k H_(k,k+l) / (n - p), exact from the fit's hat matrix H: about -0.1 at lag 1
  with knots every ten readings, which alone gave p 4e-13 on a nominal bag), Q = n (n + 2)
  sum_l (rho_l - rho0_l)^2 / (n - l), chi-square with ``lags`` degrees of freedom. A slowly
  varying error (AR(1)) is positively correlated over many lags. The motion model's
  innovations would test the model as much as the sensor: any effect it lacks correlates
  them (an odometer re-calibrated mid-run, which the odometer's own entry names, gave
  Ljung-Box p 1e-116 there), while what it lacks is smooth on 2 s and the spline takes it.
- **Dependence on speed and distance** (:func:`dependence_test`): the scatter test's
  standardised residuals r / sqrt(rv), squared, regressed on the speed and the distance
  (Koenker's studentised Breusch-Pagan test: n R^2 of that regression is chi-square with as
  many degrees of freedom as covariates when the variance does not depend on them, Gaussian
  or not).

- **The speed readings against the count** (:func:`count_consistency`): an odometer's count
  is the integral of the speed it reads, so over a window of about ``COUNT_WINDOW`` s the
  count's increase less the trapezoid of the speed readings is noise about 0. A speed channel
  that lags the train by tau (a filter, a speed computed over a gate, a message sent late
  while the count is not) leaves tau times the speed's change over the window; the motion
  model cannot see it (the command offset and the process noise take it: on the independent
  simulator's odometer with its speed 0.3 s late and its count on time, the verdict was
  ``none``), and the spline above follows it (smooth on 2 s). On disjoint windows of
  consecutive readings while the train moves, the remainder is regressed on the reference
  speed's change (and a constant), tau's standard error robust to a variance that changes
  from window to window (HC1); two-sided. A count and speed read 0.3 s late alike show
  nothing here (the balises' latency test sees the two streams off each other).

``alpha`` of :func:`sensor_checks` is the false-alarm rate of the four together (shared out
equally, Bonferroni).

**The balise readings** (:func:`balise_checks`). Their scatter is a hypothesis of the structure
test (``balise_rounds.scatter_round``); their correlation in time and their dependence on speed
and distance are tested here, on the readings' whitened innovations z (the odometer's track
through the model, the count's origin at its least-squares value). A run has 3 to 17 readings
(20 case bags of four families), too few for the asymptotic statistics above, so each test is
exact: under the stated
readings z is normal with covariance C = I - c c^T / I_s0 (c the origin's column of the
whitened innovations, I_s0 its information: fitting the origin takes one degree of freedom),
and each statistic is a ratio of quadratic forms T = z^T A z / z^T z, whose tail P(T >= r) =
P(z^T (A - r I) z >= 0) is that of a weighted sum of chi-square variables with the
eigenvalues of C^(1/2) (A - r I) C^(1/2) as weights (Imhof 1961, computed by
:func:`positive_sf`). Two-sided, each at a third of ``alpha``:

- **Correlation in time**: A the lag-1 products, T the readings' lag-1 autocorrelation. A
  reader error that varies slowly (its timing drifting, a section of the map surveyed off the
  same way) is positively correlated from one reading to the next.
- **Dependence on speed** and **on distance**: A = diag(x - mean x), T the squared
  innovations' covariance with x over their sum. A reader's timing jitter grows its errors
  with the speed at which balises are passed; a count drifting from the balises, or a map
  whose error grows along the line, with the distance.
"""

from __future__ import annotations

import math

import numpy as np

from train_estimation.core.numerics import lsq_spline
from train_estimation.core.numerics.special import chdtrc

# s, knot spacing of the speed's spline: a train's speed follows a cubic on 2 s (its
# acceleration changes through the actuator's lag of 0.3-1 s), the readings' noise does not;
# at least KNOT_PERIODS sampling periods (an odometer read at 1 Hz)
KNOT_S = 2.0
KNOT_PERIODS = 4
# s, a gap in the readings longer than this (and than GAP_PERIODS sampling periods) starts a
# new stretch (a burst of the link)
MAX_GAP = 1.0
GAP_PERIODS = 2.5
# readings a stretch needs to be fitted (and so tested)
MIN_STRETCH = 30
# s, the longest median sampling period at which the spline is fitted: at 1 Hz a spline with
# knots 4 s apart does not follow a metro's speed (on nominal wen2017_subway bags, seeds 1-8,
# the scatter came out 1.06-1.31 times the stated variance and the dependence test's p down
# to 1.3e-4), so the scatter and dependence tests are not made there
MAX_PERIOD = 0.25


def _period(t: np.ndarray) -> float:
    """s, the readings' median sampling period."""
    return float(np.median(np.diff(t))) if t.size > 1 else 0.0


def stretches(t: np.ndarray, cut: np.ndarray | None = None) -> np.ndarray:
    """Stretch index of every reading (times ``t`` increasing): a new stretch after each gap
    longer than ``MAX_GAP`` s and ``GAP_PERIODS`` sampling periods, and at each reading where
    ``cut`` is True."""
    gap = max(MAX_GAP, GAP_PERIODS * _period(t))
    new = np.diff(t) > gap
    if cut is not None:
        new = new | cut[1:]
    return np.concatenate([[0], np.cumsum(new)]).astype(int)


def spline_residuals(t: np.ndarray, y: np.ndarray, rv: np.ndarray,
                     base: np.ndarray | None = None, cut: np.ndarray | None = None,
                     lags: int = 0) -> tuple:
    """(r, dof, lag_sums): the residuals of the weighted least-squares cubic spline of
    ``y - base`` over ``t`` per stretch (:func:`stretches` with ``cut``; NaN where a stretch
    is too short to fit), the degrees of freedom left (readings fitted less spline
    coefficients), and for lags 1..``lags`` the expected sum of the standardised residuals'
    products z_k z_(k+l) within stretches under white noise of the stated variances (the
    fit's own correlation: -sum_k H_(k,k+l), H the weighted hat matrix). None with readings
    sparser than ``MAX_PERIOD``. ``base``: the motion model's speed up to a constant per
    stretch (its kinks, where a command steps or the train stops, are not a cubic's)."""
    r = np.full(y.size, np.nan)
    dof = 0
    lag_sums = np.zeros(lags)
    if _period(t) > MAX_PERIOD:
        return r, 0, lag_sums
    if base is not None:
        y = y - base
    knot_s = max(KNOT_S, KNOT_PERIODS * _period(t))
    seg = stretches(t, cut)
    for s in np.unique(seg):
        i = np.flatnonzero(seg == s)
        if i.size < MIN_STRETCH:  # also: too few readings to tell noise from motion
            continue
        x = t[i]
        m = max(int((x[-1] - x[0]) // knot_s), 1)
        inner = x[0] + (x[-1] - x[0]) * np.arange(1, m) / m
        knots = np.r_[[x[0]] * 4, inner, [x[-1]] * 4]
        w = 1.0 / np.sqrt(rv[i])
        try:  # scipy's make_lsq_spline, without importing scipy.interpolate (lsq_spline)
            c = lsq_spline.lsq_coefficients(x, y[i], knots, 3, w)
        except (ValueError, np.linalg.LinAlgError):  # a stretch the knots do not fit
            continue
        r[i] = y[i] - lsq_spline.evaluate(knots, c, 3, x)
        dof += i.size - (knots.size - 4)
        if lags:
            A = lsq_spline.design_matrix(x, knots, 3) * w[:, None]
            M = A @ np.linalg.pinv(A.T @ A)
            for lag in range(1, min(lags, i.size - 1) + 1):
                lag_sums[lag - 1] -= float(np.sum(M[:-lag] * A[lag:]))
    return r, dof, lag_sums


def scatter_test(r: np.ndarray, dof: int, rv: np.ndarray, alpha: float) -> dict:
    """Spline residuals ``r`` (:func:`spline_residuals`, ``dof`` left) of readings of stated
    variances ``rv`` against their stated scatter (module docstring): {ratio (observed /
    stated variance), dof, p, finding}."""
    ok = np.isfinite(r)
    if dof < MIN_STRETCH:
        return {"test": "scatter", "tested": False, "finding": False}
    stat = float(np.sum(r[ok] ** 2 / rv[ok]))
    p = float(chdtrc(dof, stat))
    return {"test": "scatter", "tested": True, "ratio": stat / dof, "dof": int(dof), "p": p,
            "finding": bool(p < alpha)}


def ljung_box(z: np.ndarray, seg: np.ndarray, lags: int, alpha: float,
              lag_sums: np.ndarray | None = None, dof: int | None = None) -> dict:
    """Standardised residuals ``z`` (NaN: none) in stretches ``seg`` against white noise
    (module docstring): the autocorrelations rho_l (products within stretches) less what a
    fit of ``dof`` degrees of freedom left gives them by itself (``lag_sums``, from
    :func:`spline_residuals`; None: plain white noise, its mean removed), Q = n (n + 2)
    sum_l (rho_l - rho0_l)^2 / (n - l), chi-square with ``lags`` degrees of freedom:
    {Q, lags, p, rho (lags 1..3, as found), finding}."""
    ok = np.isfinite(z)
    n = int(ok.sum())
    if n < 10 * lags:
        return {"test": "correlation in time", "tested": False, "finding": False}
    x = np.where(ok, z if lag_sums is not None else z - np.mean(z[ok]), 0.0)
    c0 = float(np.sum(x * x))
    rho = np.array([float(np.sum((x[lag:] * x[:-lag])[seg[lag:] == seg[:-lag]])) / c0
                    for lag in range(1, lags + 1)])
    rho0 = np.zeros(lags) if lag_sums is None else lag_sums / max(dof or n, 1)
    q = float(n * (n + 2) * np.sum((rho - rho0) ** 2 / (n - np.arange(1, lags + 1))))
    p = float(chdtrc(lags, q))
    return {"test": "correlation in time", "tested": True, "Q": q, "lags": lags, "p": p,
            "rho": [float(v) for v in rho[:3]], "rho_fit": [float(v) for v in rho0[:3]],
            "finding": bool(p < alpha)}


def dependence_test(u: np.ndarray, covariates: dict, alpha: float) -> dict:
    """The variance of the standardised innovations ``u`` against ``covariates`` ({name:
    array}) (module docstring): {LM, dof, p, ratio: {name: [variance ratio at its 5th, at its
    95th percentile]}, finding}."""
    ok = np.isfinite(u) & np.all([np.isfinite(c) for c in covariates.values()], axis=0)
    n = int(ok.sum())
    k = len(covariates)
    if n < 50 or k == 0:
        return {"test": "dependence on speed and distance", "tested": False, "finding": False}
    e2 = u[ok] ** 2
    X = np.column_stack([np.ones(n)] + [c[ok] for c in covariates.values()])
    sd = X[:, 1:].std(axis=0)
    use = np.r_[True, sd > 0]
    X = X[:, use]
    coef, *_ = np.linalg.lstsq(X, e2, rcond=None)
    fit = X @ coef
    tss = float(np.sum((e2 - e2.mean()) ** 2))
    r2 = 1.0 - float(np.sum((e2 - fit) ** 2)) / tss if tss > 0 else 0.0
    lm = n * r2
    dof = int(use[1:].sum())
    p = float(chdtrc(dof, lm)) if dof else 1.0
    mean = float(e2.mean())
    ratio, j = {}, 1
    for name, c in covariates.items():
        if not use[list(covariates).index(name) + 1]:
            continue
        lo, hi = np.percentile(c[ok], [5, 95])
        ratio[name] = [float((mean + coef[j] * (lo - c[ok].mean())) / mean),
                       float((mean + coef[j] * (hi - c[ok].mean())) / mean)]
        j += 1
    return {"test": "dependence on speed and distance", "tested": dof > 0, "LM": lm,
            "dof": dof, "p": p, "ratio": ratio, "finding": bool(p < alpha)}


# s, the window over which the count's increase is compared with the speed readings' integral
# (at least COUNT_PERIODS readings): long enough for the speed to change by what a lag shows,
# short enough for many disjoint windows
COUNT_WINDOW = 1.0
COUNT_PERIODS = 2
# windows needed for the comparison to be made
MIN_WINDOWS = 30


def count_consistency(t: np.ndarray, d: np.ndarray, y: np.ndarray, vs: np.ndarray,
                      alpha: float, min_speed: float = 1.0) -> dict:
    """The odometer's speed readings ``y`` against its count ``d`` at times ``t`` (every
    reading, in time order; ``vs`` the reference speed there) (module docstring): {lag (s, >
    0: the speed readings behind the count), std_error, z, p, windows, finding}. A window is
    taken where the reference speed stays at or above ``min_speed`` m/s, never by the readings
    themselves: kept where the noisy count moved forward and every noisy speed was above 0,
    the windows at a departure or a stop were a biased sample of the noise (a count with 0.47
    m of noise at 5 Hz on metro_demo: z -3.3 on a nominal bag)."""
    out = {"test": "speed readings against the count", "tested": False, "finding": False}
    ok = np.isfinite(t) & np.isfinite(d) & np.isfinite(y) & np.isfinite(vs)
    t, d, y, vs = t[ok], d[ok], y[ok], vs[ok]
    if t.size < 2 * MIN_WINDOWS:
        return out
    period = _period(t)
    w = max(COUNT_PERIODS, int(round(COUNT_WINDOW / max(period, 1e-9))))
    steady = np.diff(t) < 1.5 * period  # no reading lost between two neighbours
    rem, dv = [], []
    i = 0
    while i + w < t.size:
        j = i + w
        if steady[i:j].all() and (vs[i:j + 1] >= min_speed).all():
            rem.append((d[j] - d[i]) - float(np.sum(0.5 * (y[i + 1:j + 1] + y[i:j])
                                                    * np.diff(t[i:j + 1]))))
            dv.append(vs[j] - vs[i])
            i = j + 1  # disjoint: the next window shares no reading
        else:
            i += 1
    n = len(rem)
    if n < MIN_WINDOWS:
        return out
    r, x = np.asarray(rem), np.asarray(dv)
    X = np.column_stack([np.ones(n), x])
    xtx = X.T @ X
    if np.linalg.matrix_rank(xtx) < 2:
        return out
    inv = np.linalg.inv(xtx)
    beta = inv @ (X.T @ r)
    e = r - X @ beta
    # HC1: the sandwich with the windows' own squared remainders (a count rounded to a
    # metre, noise that grows with speed), scaled by n / (n - 2)
    cov = inv @ (X.T * e ** 2) @ X @ inv * n / (n - 2)
    se = math.sqrt(max(cov[1, 1], 0.0))
    if not se > 0:
        return out
    lag = float(beta[1])  # speed read tau late: its integral falls short of the count by tau dv
    z = lag / se
    p = float(math.erfc(abs(z) / math.sqrt(2.0)))
    return {"test": "speed readings against the count", "tested": True, "lag": lag,
            "std_error": se, "z": z, "p": p, "windows": n, "finding": bool(p < alpha)}


def sensor_checks(t: np.ndarray, y: np.ndarray, rv: np.ndarray, v: np.ndarray,
                  d: np.ndarray, alpha: float = 1e-3, lags: int = 10,
                  base: np.ndarray | None = None, cut: np.ndarray | None = None,
                  raw: tuple | None = None, min_speed: float = 1.0) -> dict:
    """The four tests of the odometer's speed readings ``y`` (stated variances ``rv``) at
    times ``t``, with the speed ``v`` and the distance ``d`` there; ``alpha``: the
    false-alarm rate of the four together; ``base``, ``cut``: the model's speed and where
    it does not follow the train (:func:`spline_residuals`); ``raw``: (times, counts, speed
    readings, reference speed) of every reading, for :func:`count_consistency` (None: not
    made), with the train moving where the reference speed is at or above ``min_speed`` m/s.
    {scatter, correlation, dependence, count, finding, signature (words, or None)}."""
    a = alpha / 4.0
    r, dof, sums = spline_residuals(t, y, rv, base, cut, lags)
    z = r / np.sqrt(rv)
    sc = scatter_test(r, dof, rv, a)
    lb = ljung_box(z, stretches(t, cut), lags, a, sums, dof) if dof else \
        {"test": "correlation in time", "tested": False, "finding": False}
    dp = dependence_test(z, {"speed": v, "distance": d}, a)
    cc = count_consistency(*raw, a, min_speed) if raw is not None else \
        {"test": "speed readings against the count", "tested": False, "finding": False}
    words = []
    if sc["finding"]:
        words.append(f"its speed readings scatter {math.sqrt(sc['ratio']):.2f} times the "
                     f"stated SD (p {sc['p']:.2g})")
    if lb["finding"]:
        words.append(f"its errors are correlated in time (lag-1 correlation "
                     f"{lb['rho'][0]:+.2f}, Ljung-Box p {lb['p']:.2g})")
    if dp["finding"]:
        parts = [f"x{r[0]:.2f} to x{r[1]:.2f} of the mean over its {name}"
                 for name, r in dp["ratio"].items()]
        words.append(f"its error variance changes with speed and distance ({'; '.join(parts)};"
                     f" p {dp['p']:.2g})")
    if cc["finding"]:
        side = "behind" if cc["lag"] > 0 else "ahead of"
        words.append(f"its speed readings run {abs(cc['lag']):.2f} +- {cc['std_error']:.2f} s "
                     f"{side} its own count (p {cc['p']:.2g})")
    return {"scatter": sc, "correlation": lb, "dependence": dp, "count": cc, "alpha": alpha,
            "finding": bool(words), "signature": "; ".join(words) or None}


# how the reason of a sensor entry begins (tools.diagnose_unexplained tells the entry by it)
SENSOR_WHY = "the odometer's speed readings are not the sensor it states"


def sensor_entry(checks: dict, speed: list) -> dict:
    """The ``unexplained`` entry of :func:`sensor_checks`' finding (phase ``all``, no
    ``where`` nor ``when``: the whole run): ``size`` the readings' SD over the stated SD
    (1 where only their correlation or their dependence on speed and distance was found),
    ``speed`` [v0, v1] m/s of the run, its signature as the reason."""
    sc = checks["scatter"]
    size = math.sqrt(sc["ratio"]) if sc.get("tested") else 1.0
    return {"phase": "all", "where": None, "when": None, "speed": speed, "size": size,
            "best_listed": {"cause": "odometer_scale",
                            "why": f"{SENSOR_WHY}: {checks['signature']}; a scale changes "
                                   "what it counts, not how its readings scatter"}}


# -- the balise readings (module docstring) ----------------------------------------------------

# nodes and weights of the Gauss-Legendre rule on [0, 1) for positive_sf's integral (400
# nodes: within 1e-9 of the integral by adaptive quadrature at tail probabilities of 1e-5)
_GL_S, _GL_W = np.polynomial.legendre.leggauss(400)
_GL_S, _GL_W = 0.5 * (_GL_S + 1.0), 0.5 * _GL_W
# readings the balise tests need (a lag-1 correlation of fewer says nothing at 1e-3)
BALISE_MIN = 8


def positive_sf(lam: np.ndarray) -> float:
    """P(sum_j lam_j g_j^2 > 0), g_j independent standard normals (Imhof 1961, eq. 3.2 at
    x = 0): 1/2 + (1/pi) int_0^inf sin(theta(u)) / (u rho(u)) du, theta(u) = sum_j
    arctan(lam_j u) / 2, rho(u) = prod_j (1 + lam_j^2 u^2)^(1/4); u = s / (1 - s) maps the
    integral onto [0, 1), where a fixed Gauss-Legendre rule takes it (no scipy.integrate,
    whose import costs diagnose a fifth of a second)."""
    lam = np.asarray(lam, float)
    top = float(np.max(np.abs(lam))) if lam.size else 0.0
    if top == 0.0:
        return 0.5
    lam = lam[np.abs(lam) > 1e-12 * top] / top  # the probability does not see the scale
    if np.all(lam > 0):
        return 1.0
    if np.all(lam < 0):
        return 0.0
    u = _GL_S / (1.0 - _GL_S)
    lu = lam[None, :] * u[:, None]
    theta = 0.5 * np.sum(np.arctan(lu), axis=1)
    decay = np.exp(-0.25 * np.sum(np.log1p(lu * lu), axis=1))  # 1 / rho(u): 0, not inf
    f = np.sin(theta) * decay / u / (1.0 - _GL_S) ** 2
    return float(min(max(0.5 + float(np.dot(_GL_W, f)) / math.pi, 0.0), 1.0))


def cov_half(cov: np.ndarray) -> np.ndarray:
    """The symmetric square root of a covariance (its negative rounding clipped)."""
    w, V = np.linalg.eigh(cov)
    return (V * np.sqrt(np.clip(w, 0.0, None))) @ V.T


def ratio_test(z: np.ndarray, half: np.ndarray, A: np.ndarray) -> tuple[float, float]:
    """(T, p): T = z^T A z / z^T z and its two-sided p-value for z ~ N(0, C), ``half`` =
    C^(1/2) (:func:`cov_half`) (module docstring)."""
    T = float(z @ A @ z) / float(z @ z)
    upper = positive_sf(np.linalg.eigvalsh(half @ (A - T * np.eye(z.size)) @ half))
    return T, float(min(1.0, 2.0 * min(upper, 1.0 - upper)))


def balise_checks(z: np.ndarray, cov: np.ndarray, speed: np.ndarray, position: np.ndarray,
                  alpha: float = 1e-3, seg: np.ndarray | None = None) -> dict:
    """The balise readings' whitened innovations ``z`` (covariance ``cov`` under the stated
    readings), in time order, with the speed and the position where each was read, against
    white noise (module docstring): {readings, correlation, speed, distance, finding,
    signature}; ``alpha`` the false-alarm rate of the three together. ``seg``: the run each
    reading belongs to, when several runs are pooled (a fleet's passes, ``cov`` block
    diagonal): lag-1 products within a run only."""
    n = int(z.size)
    out = {"readings": n, "alpha": alpha, "finding": False, "signature": None}
    why = f"fewer than {BALISE_MIN} balise readings" if n < BALISE_MIN else \
        "an innovation is not finite" if not np.all(np.isfinite(z)) else \
        "every innovation is 0" if not float(z @ z) > 0 else None
    if why:
        out["tested"] = False
        out["note"] = why
        return out
    a = alpha / 3.0
    out["tested"] = True
    out["sd_ratio"] = math.sqrt(float(z @ z) / max(float(np.trace(cov)), 1.0))
    half = cov_half(cov)
    lag = np.eye(n, k=1)
    if seg is not None:  # no product across two runs
        lag[np.arange(n - 1), np.arange(1, n)] = np.asarray(seg)[1:] == np.asarray(seg)[:-1]
    T, p = ratio_test(z, half, 0.5 * (lag + lag.T))
    out["correlation"] = {"lag1": T, "p": p, "finding": bool(p < a)}
    words = []
    if p < a:
        words.append(f"their errors are correlated from one reading to the next (lag-1 "
                     f"correlation {T:+.2f}, p {p:.2g})")
    for name, x, unit in (("speed", speed, "m/s"), ("distance", position, "m")):
        x = np.asarray(x, float)
        dx = x - x.mean()
        if not np.any(dx):
            out[name] = {"tested": False, "finding": False}
            continue
        T, p = ratio_test(z, half, np.diag(dx))
        # the squared innovations' mean below and above x's median over their mean: what
        # the variance does with x, in words a reader takes in
        e2, mid = z * z, float(np.median(x))
        m = float(e2.mean())
        ratio = [float(e2[x <= mid].mean()) / m, float(e2[x > mid].mean()) / m] \
            if np.any(x > mid) else [1.0, 1.0]
        out[name] = {"T": T, "p": p, "ratio": ratio, "median": mid, "finding": bool(p < a)}
        if p < a:
            words.append(f"their error variance changes with {name} (x{ratio[0]:.2f} of the "
                         f"mean below {mid:.0f} {unit}, x{ratio[1]:.2f} above; p {p:.2g})")
    out["finding"] = bool(words)
    out["signature"] = "; ".join(words) or None
    return out


# how the reason of a balise readings entry begins (tools.diagnose_unexplained tells the entry
# by it, as the odometer's)
BALISE_WHY = "the balise readings are not the sensor they state"


def balise_entry(checks: dict, speed: list) -> dict:
    """The ``unexplained`` entry of :func:`balise_checks`' finding (phase ``all``, no ``where``
    nor ``when``: the whole run): ``size`` the readings' SD over the stated SD, ``speed`` [v0,
    v1] m/s of the run, its signature as the reason."""
    return {"phase": "all", "where": None, "when": None, "speed": speed,
            "size": checks["sd_ratio"],
            "best_listed": {"cause": "odometer_scale",
                            "why": f"{BALISE_WHY}: {checks['signature']}; the listed "
                                   "causes move the readings' mean (an odometer scale by a "
                                   "share of the distance run), not how they scatter"}}
