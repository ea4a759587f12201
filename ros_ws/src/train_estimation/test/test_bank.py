"""numerics.bank: the compiled bank step against the numpy form (kalman.update,
BrakingModel.predict, smc.log_normalize, braking_base's mixture moments) and against itself
interpreted.

Bounds. Elementwise operations are the numpy form's, in its order: equal bit for bit. A sum
that numpy hands to BLAS, einsum or its pairwise ``sum`` is summed in index order by the
kernel; each order's rounding error is at most ``(L - 1) u sum |terms|`` (recursive
summation, Higham 2002 eq. (4.4), u = eps / 2, L terms), so the two differ by at most
``L eps sum |terms|`` (``log``/``exp``: numpy's SIMD form and libm are both within 1 ulp).
"""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest

from train_estimation.core.braking.braking_filters import (
    GSMA,
    QGRBPF,
    SMA,
    BrakingKF,
    DiscreteRBPF,
    RandomWalkRBPF,
    sticky_transition,
)
from train_estimation.core.braking.braking_model import (
    BrakingModel,
    BrakingParams,
    _affine_pieces,
    _predict_maps,
)
from train_estimation.core.numerics import bank
from train_estimation.core.numerics.kalman import _selectors, update

sys.path.insert(0, os.path.dirname(__file__))
import nojit  # noqa: E402  (the interpreted run in a fresh process)

EPS = np.finfo(float).eps
pytestmark = pytest.mark.skipif(not bank.COMPILED, reason="numba not installed")


def _bank(rng, N, n=4):
    x = rng.normal(size=(N, n)) * [100.0, 10.0, 1.0, 1.0][:n]
    A = rng.normal(size=(N, n, n))
    P = np.einsum("kij,klj->kil", A, A) + 0.1 * np.eye(n)
    return x, P


def test_update_equals_numpy_form():
    """x and P bit for bit (the same elementwise operations); the log likelihood within the
    summation bound over its 2 r + 1 terms."""
    rng = np.random.default_rng(1)
    x, P = _bank(rng, 37)
    H = BrakingModel().H
    R = np.array([0.25, 0.09, 1e-4])
    sel = np.array(_selectors(H), dtype=np.int64)
    for mask in ([1, 1, 1], [1, 0, 0], [0, 1, 1], [1, 1, 0]):
        mask = np.array(mask, dtype=bool)
        for y in (rng.normal(size=3), rng.normal(size=(37, 3))):
            xr, Pr, llr = update(x, P, y, H, R, mask)
            xc, Pc, llc = bank.update(x, P, np.atleast_2d(y), H, R, np.flatnonzero(mask), sel)
            np.testing.assert_array_equal(xc, xr)
            np.testing.assert_array_equal(Pc, Pr)
            # terms: r log(2 pi), log s_r, e^2 / s_r; |ll| itself bounds their sum from above
            # only when they share a sign, so bound with the terms recomputed
            r = mask.sum()
            mag = _loglik_terms(x, P, y, H, R, mask)
            assert np.all(np.abs(llc - llr) <= (2 * r + 1) * EPS * mag + 0.0)
    # a general (non-selector) row: the products summed in index order
    Hg = np.array([[1.0, -0.8, 0.3, 0.0], [-0.5, 0.7, 0.0, 0.2]])
    sel = np.array(_selectors(Hg), dtype=np.int64)
    assert list(sel) == [-1, -1]
    y = rng.normal(size=2)
    xr, Pr, llr = update(x, P, y, Hg, np.array([0.3, 0.2]), np.ones(2, bool))
    xc, Pc, llc = bank.update(x, P, y[None], Hg, np.array([0.3, 0.2]), np.arange(2), sel)
    scale_x = np.abs(x).max() + 1.0
    assert np.max(np.abs(xc - xr)) <= 64 * EPS * scale_x * np.abs(P).max()
    assert np.max(np.abs(Pc - Pr)) <= 64 * EPS * np.abs(P).max() ** 2
    np.testing.assert_allclose(llc, llr, rtol=1e-9)


def _loglik_terms(x, P, y, H, R, mask):
    """sum of |terms| of each particle's log likelihood (the numpy form's own intermediates)."""
    rows = np.flatnonzero(mask)
    mag = np.full(x.shape[0], rows.size * np.log(2 * np.pi))
    xs, Ps = x.copy(), P.copy()
    for j in rows:
        yy = y[..., j]
        xr, Pr, _ = update(xs, Ps, y, H, R, np.arange(len(mask)) == j)
        i = int(np.argmax(H[j]))
        s = Ps[:, i, i] + R[j]
        e = yy - xs[:, i]
        mag += np.abs(np.log(s)) + e * e / s
        xs, Ps = xr, Pr
    return mag


def test_predict_equals_numpy_form():
    """BrakingModel.predict's Horner form: within the bound of its sums (x: 4 + 4 terms and
    the Horner steps, P: 16 terms per coefficient), for informative (one f per particle) and
    shared-gain steps."""
    rng = np.random.default_rng(2)
    fam = BrakingModel(BrakingParams(noise_model="white", ahat_var=0.01))
    x, P = _bank(rng, 29)
    theta = rng.uniform(0.0, 1.3, size=(29, 1))
    u = np.array([-0.8, 0.05])
    logw = np.full(29, -np.log(29))
    for informative, hold in ((True, None), (False, 0.7), (False, None)):
        for dt in (0.1, 1.0, 0.0371):
            xr, Pr = fam.predict(x, P, theta, u, dt, informative, hold)
            pred, f = fam.bank_maps(theta, u, dt, informative, hold)
            st, xc, Pc, *_ = bank.bank_step(x, P, np.zeros((1, 3)), fam.H, fam.R,
                                            np.zeros(0, np.int64), np.zeros(3, np.int64), logw,
                                            theta, None, pred, f)
            assert st == bank.OK
            mx, mP = _predict_magnitudes(fam, x, P, f, u, dt)
            assert np.all(np.abs(xc - xr) <= 16 * EPS * mx)
            assert np.all(np.abs(Pc - Pr) <= 24 * EPS * mP)
            np.testing.assert_array_equal(Pc, np.swapaxes(Pc, 1, 2))  # exactly symmetric


def _predict_magnitudes(fam, x, P, f, u, dt):
    """The prediction evaluated on absolute values: sum |terms| of every output."""
    Kx, KP, qd, full = _predict_maps(fam.params, dt)
    f = np.abs(f)[:, None] if f.size > 1 else np.abs(f)
    bu = np.abs(u) @ np.abs(Kx[4:])
    X = np.abs(x) @ np.abs(Kx[:4])
    mx = (X[:, 4:] + bu[4:]) * f + X[:, :4] + bu[:4]
    Y = np.abs(P).reshape(-1, 16) @ np.abs(KP).T
    mP = (Y[:, 20:] * f + Y[:, 10:20]) * f + Y[:, :10] + np.abs(qd[:, 0])
    return mx, mP[:, full].reshape(-1, 4, 4)


def _filters(fam):
    vals = np.round(np.arange(10, -1, -1) * 0.1, 10)
    pr = dict(prior=(1.0, 0.15))
    return {
        "rbpf": DiscreteRBPF(fam, vals, sticky_transition(11, 0.1), 200, **pr),
        "sma": SMA(fam, vals, n_init=30, n_keep=30, q_max=300, **pr),
        "gsma": GSMA(fam, vals, n_init=30, n_keep=30, q_max=300, **pr),
        "gsma merged": GSMA(fam, vals, transition=sticky_transition(11, 0.1), merge=True, **pr),
        "qgrbpf": QGRBPF(fam, [(0.0, 1.3)], 50, braking_rate_q=1e-3, **pr),
        "gh3": QGRBPF(fam, [(0.0, 1.3)], 3, braking_rate_q=1e-3, quadrature=True, **pr),
        "rw": RandomWalkRBPF(fam, [(0.0, 1.3)], 200, braking_rate_q=1e-3, **pr),
    }


@pytest.mark.parametrize("name", ["rbpf", "sma", "gsma", "gsma merged", "qgrbpf", "gh3", "rw"])
def test_filter_step_equals_numpy_form(name):
    """One filter step from the same particle set, compiled and numpy: the same particles
    (Q-GRBPF's redraw: within its sums' bound) and weights, the estimate's moments within the
    summation bound (N terms per weighted sum, and the weights' own normalisation: 2 N + 4 eps
    relative on each product)."""
    fam = BrakingModel(BrakingParams(meas_var=(0.25, 0.09, 1e-4)))
    rng = np.random.default_rng(5)
    a, b = _filters(fam)[name], _filters(fam)[name]
    b._bank_ok = False  # the numpy form
    assert a._compiled() and not b._compiled()
    a.reset([0, 20, -1, -2], 0.01 * np.eye(4), np.random.default_rng(9))
    b.reset([0, 20, -1, -2], 0.01 * np.eye(4), np.random.default_rng(9))
    for k in range(12):
        y = np.array([20.0 * (k + 1) - 0.5 * (k + 1) ** 2, 20.0 - (k + 1), -2.0])
        y = y + rng.normal(size=3) * [0.5, 0.3, 0.01]
        # both from the same (numpy) state: compare one step, not a chaotic run
        a._s, a._last, a._t, a._since = b._s, b._last, b._t, b._since
        ea = a.step(-1.0, y, None, np.random.default_rng(100 + k), t=float(k + 1))
        eb = b.step(-1.0, y, None, np.random.default_rng(100 + k), t=float(k + 1))
        assert ea.accepted and eb.accepted
        N = eb.n_particles
        assert ea.n_particles == N
        sa, sb = a._s, b._s
        L = 2 * N + 8
        if name == "qgrbpf":
            # the redraw mu + sd z: mu and the variance are weighted sums over the old set
            # (numpy: BLAS and einsum; compiled: index order), each within L eps of its terms
            bound = L * EPS * (np.abs(sb.theta).max() + 1.0)
            assert np.all(np.abs(sa.theta - sb.theta) <= bound), k
        else:
            np.testing.assert_array_equal(sa.theta, sb.theta)
        for u, v in ((sa.x, sb.x), (sa.P, sb.P)):
            # the prediction's sums are bounded by the particle's own scale (|Phi| |x|, |Phi|
            # |P| |Phi|^T), not by each entry, which can be a cancellation (a_hat near 0)
            M = v.shape[0]  # kept after the step's pruning (SMA/GSMA: fewer than N)
            scale = np.abs(v).reshape(M, -1).max(axis=1)
            assert np.all(np.abs(u - v).reshape(M, -1) <= L * EPS * scale[:, None]), k
        # the log weight: its own sums, plus the predicted state's rounding carried into
        # e^2 / s (first order: 2 |e| |dx| / s <= 2 (|y| + |x|) dx / R, dx the bound above)
        scale_x = np.abs(sb.x).max()
        dl = L * EPS * ((1 + np.abs(sb.logw).max() + abs(eb.log_evidence))
                        + np.sum(2 * (np.abs(y) + np.abs(sb.x).max(axis=0)[[0, 1, 3]])
                                 * scale_x / fam.R))
        assert np.all(np.abs(sa.logw - sb.logw) <= dl), k
        assert abs(ea.log_evidence - eb.log_evidence) <= dl
        # moments: their sums, plus the weights' relative error dl on each weighted term
        for u, v in ((ea.mean, eb.mean), (ea.cov, eb.cov), (ea.x_cov, eb.x_cov)):
            scale = np.abs(v).max() + np.abs(eb.x_mean).max() ** 2 + 1.0
            assert np.all(np.abs(u - v) <= (L * EPS + 2 * dl) * scale), k
        assert abs(ea.n_eff - eb.n_eff) <= (L * EPS + 4 * dl) * eb.n_eff


def test_rejections_match_numpy_form():
    """A NaN likelihood (an infinite measurement variance's 0 * inf) is rejected with the
    numpy form's reason, and the state is left as it was."""
    fam = BrakingModel()
    for force in (False, True):
        f = _filters(fam)["gsma"]
        f._bank_ok = force and None
        f.reset([0, 20, -1, -2], 0.01 * np.eye(4), np.random.default_rng(1))
        before = f.particles
        P = f._s.P.copy()
        P[0, 0, 0] = np.inf
        f._s.P = P
        e = f.step(-1.0, [1.0, 20.0, -2.0], None, np.random.default_rng(2), t=1.0)
        assert not e.accepted and e.reason.startswith("numerical failure"), e.reason
        np.testing.assert_array_equal(f.particles[0], before[0])


def _kernel_values() -> np.ndarray:
    return np.concatenate([np.ravel(a) for a in _kernel_case()])


def _interpreted(name: str) -> np.ndarray:
    """This module's function ``name`` (no arguments, an array back) run in a fresh process
    without numba (TRAIN_NO_JIT=1: its decorator is a no-op), checked to be interpreted."""
    return nojit.interpreted("test_bank", name, "train_estimation.core.numerics.bank", 300.0)


def test_compiled_equals_interpreted_kernel():
    """The kernel run interpreted (TRAIN_NO_JIT=1: numba's decorator is a no-op) gives the
    compiled kernel's numbers bit for bit (the same IEEE operations in the same order)."""
    interpreted = _interpreted("_kernel_values")
    np.testing.assert_array_equal(_kernel_values(), interpreted)


def _kernel_case():
    """A predict + update + reweight + moments step on a seeded bank (for the test above)."""
    rng = np.random.default_rng(11)
    fam = BrakingModel()
    x, P = _bank(rng, 23)
    theta = rng.uniform(0.0, 1.3, size=(23, 1))
    tv = np.full((23, 1, 1), 0.01 / 12)
    logw = np.log(rng.dirichlet(np.ones(23)))
    pred, f = fam.bank_maps(theta, np.array([-1.0, 0.0]), 0.1, True)
    st, xo, Po, lw, w, m, c, logz, ess = bank.bank_step(
        x, P, np.array([[1.0, 19.0, -2.0]]), fam.H, fam.R, np.arange(3),
        np.array(_selectors(fam.H), dtype=np.int64), logw, theta, tv, pred, f)
    return xo, Po, lw, w, m, c, np.array([st, logz, ess])


def test_gauss_hermite_equals_numpy_form():
    """QGRBPF's quadrature transition compiled: its sums within their bound (each a weighted
    sum of N terms; the magnitudes are those of the terms: |x|, |P| + |dx|^2, |C| |beta|)."""
    fam = BrakingModel()
    rng = np.random.default_rng(4)
    filt = QGRBPF(fam, [(0.0, 1.3)], 5, braking_rate_q=1e-3, quadrature=True)
    filt.reset([0, 20, -1, -2], 0.01 * np.eye(4), rng)
    for N in (3, 7, 40):
        x, P = _bank(rng, N)
        s = filt._s.__class__(rng.uniform(0.2, 1.2, size=(N, 1)), x, P,
                              np.log(rng.dirichlet(np.ones(N))))
        ref = filt._quadrature_numpy(s, 0.3)
        th, xc, Pc = bank.gauss_hermite(s.logw, s.theta, s.x, s.P, filt._gh[0], 1e-3 * 0.3,
                                        filt.min_var, 0.0, 1.3)
        L = 2 * N + 8
        dx = np.abs(x).max()
        np.testing.assert_allclose(th, ref.theta, rtol=L * EPS, atol=L * EPS)
        beta = np.abs(xc - xc.mean(axis=0)).max() + 1.0  # |(t - mu) beta| and |beta|
        assert np.all(np.abs(xc - ref.x) <= L * EPS * (dx + beta) * 4)
        assert np.all(np.abs(Pc - ref.P) <= L * EPS * (np.abs(P).max() + 4 * dx * dx) * 4)
        np.testing.assert_array_equal(Pc, np.swapaxes(Pc, 1, 2))
    with pytest.raises(ValueError, match="all log-weights are -inf"):
        bank.gauss_hermite(np.full(3, -np.inf), np.ones((3, 1)), x[:3], P[:3], filt._gh[0],
                           0.0, 1e-8, 0.0, 1.3)


def test_log_normalize_and_all_finite():
    """smc.log_normalize's checks, messages and numbers (sums within (N + 2) eps); the
    finiteness test of a particle set."""
    from train_estimation.core.numerics import smc

    rng = np.random.default_rng(6)
    for N in (1, 5, 300):
        lw = rng.normal(size=N) * 30
        lw[rng.uniform(size=N) < 0.1] = -np.inf
        if not np.isfinite(lw).any():
            lw[0] = 0.0
        w, lz = bank.log_normalize(lw)
        wr, lzr = smc.log_normalize(lw)
        np.testing.assert_allclose(w, wr, rtol=(N + 2) * EPS, atol=0)
        assert abs(lz - lzr) <= (N + 2) * EPS * (1 + abs(lzr))
    for bad, msg in (([0.0, np.nan], "NaN or \\+inf"), ([np.inf, 0.0], "NaN or \\+inf"),
                     ([-np.inf, -np.inf], "all log-weights are -inf")):
        for fn in (bank.log_normalize, smc.log_normalize):
            with pytest.raises(ValueError, match=msg):
                fn(np.array(bad))
    x, P = _bank(rng, 4)
    th = np.ones((4, 1))
    assert bank.all_finite(x, P, th)
    for arr in (x, P, th):
        arr.ravel()[-1] = np.nan
        assert not bank.all_finite(x, P, th)
        arr.ravel()[-1] = 1.0


def test_clocks_median_is_numpys():
    """numerics.clocks.median: np.median's number, bit for bit (odd and even sizes, ties,
    NaN)."""
    from train_estimation.core.numerics.clocks import median

    rng = np.random.default_rng(8)
    for n in (1, 2, 3, 4, 7, 8, 63, 64):
        for a in (rng.normal(size=n) * 1e3 + 1.7e9, np.round(rng.normal(size=n)), np.ones(n)):
            assert median(a) == float(np.median(a))
            assert median(a) == median(a[::-1])
    a = rng.normal(size=9)
    a[3] = np.nan
    assert np.isnan(median(a)) and np.isnan(np.median(a))


@pytest.mark.parametrize("name", ["rbpf", "sma", "gsma merged", "qgrbpf", "gh3", "rw"])
def test_snapshot_copy_is_independent(name):
    """``copy.deepcopy`` of a filter (the runner's snapshots): the copy steps to the same
    estimates as the original with the same random stream, and stepping it leaves the
    original's particles as they were; the shared family stays shared."""
    import copy

    fam = BrakingModel()
    f = _filters(fam)[name]
    f.reset([0, 20, -1, -2], 0.01 * np.eye(4), np.random.default_rng(3))
    f.step(-1.0, [19.5, 19.0, -2.0], None, np.random.default_rng(4), t=1.0)
    before = f.particles, f._s.x.copy(), f._s.P.copy(), f.estimate().mean.copy()
    g = copy.deepcopy(f, {id(fam): fam})
    assert g.family is fam and g._s is not f._s and g.rejected is not f.rejected
    for k in range(2, 5):
        y = [20.0 * k - 0.5 * k * k, 20.0 - k, -2.0]
        eg = g.step(-1.0, y, None, np.random.default_rng(k), t=float(k))
        g.step(float("nan"), y, None, None, t=float(k))  # a rejection: counted in the copy
        assert eg.accepted
    np.testing.assert_array_equal(f.particles[0], before[0][0])
    np.testing.assert_array_equal(f._s.x, before[1])
    np.testing.assert_array_equal(f._s.P, before[2])
    np.testing.assert_array_equal(f.estimate().mean, before[3])
    assert sum(f.rejected.values()) == 0 and sum(g.rejected.values()) == 3
    for k in range(2, 5):  # the original, stepped the same way, gives the copy's estimates
        y = [20.0 * k - 0.5 * k * k, 20.0 - k, -2.0]
        ef = f.step(-1.0, y, None, np.random.default_rng(k), t=float(k))
    np.testing.assert_array_equal(ef.mean, eg.mean)
    np.testing.assert_array_equal(ef.cov, eg.cov)


def _run_filters(steps=8):
    """Estimates (f mean, f var, D) of every algorithm over a few steps (for the test below)."""
    fam = BrakingModel(BrakingParams(meas_var=(0.25, 0.09, 1e-4)))
    out = []
    for f in _filters(fam).values():
        rng = np.random.default_rng(21)
        f.reset([0, 20, -1, -2], 0.01 * np.eye(4), rng)
        for k in range(1, steps + 1):
            e = f.step(-1.0, [20.0 * k - 0.5 * k * k, 20.0 - k, -2.0], None, rng, t=float(k))
        out.append([e.mean[3], e.cov[3, 3], e.mean[0]])
    return np.array(out)


def test_filters_run_without_numba():
    """Without numba (TRAIN_NO_JIT=1) every algorithm runs its numpy form and gives the
    compiled run's estimates to rounding (8 steps: the reordered sums' differences, ~1e-15
    relative each step, stay far below 1e-9; no resampling decision sits that close)."""
    interpreted = _interpreted("_run_filters")
    np.testing.assert_allclose(_run_filters(), interpreted, rtol=1e-9, atol=1e-12)


def _step_kernel_values() -> np.ndarray:
    """Every filter's compiled step kernel (``braking_compiled``) on seeded sets and draws:
    branching with pruning and with merging, the discrete draw, the random walk, the
    Q-GRBPF redraw and its Gauss-Hermite form, the resampling and the exact KF, each on an
    informative step, an uninformative one (a shared gain) and one without prediction (for
    the test below)."""
    from train_estimation.core.braking import braking_compiled as bc

    rng = np.random.default_rng(12)
    fam = BrakingModel()
    H = np.ascontiguousarray(fam.H)
    sel = np.array(_selectors(H), dtype=np.int64)
    N, M = 9, 5
    vals = np.linspace(1.0, 0.6, M)
    cv = np.full(M, 0.01 / 12)
    idx = rng.integers(0, M, N).astype(np.int64)
    x, P = _bank(rng, N)
    x[:, 1] = np.abs(x[:, 1])
    lw = np.log(rng.dirichlet(np.ones(N)))
    y = np.array([[x[0, 0] + 1.0, x[0, 1] - 0.5, -2.0]])
    out = []
    for informative, dt in ((True, 0.5), (False, 0.5), (True, 0.0)):
        if dt > 0:
            fh = np.ones(1) if informative else np.array([0.8])
            common = (True, *fam.bank_pred(np.array([-1.0, 0.02]), dt), fh)
        else:
            common = (False, *bank._NO_PREDICT, np.zeros(1))
        common += (y, H, fam.R.copy(), np.arange(3, dtype=np.int64), sel)
        th = vals[idx][:, None]
        allowed = np.abs(np.arange(M)[:, None] - np.arange(M)[None, :]) <= 1
        rows = [np.flatnonzero(r) for r in allowed]
        ptr = np.concatenate([[0], np.cumsum([r.size for r in rows])]).astype(np.int64)
        col = np.concatenate(rows).astype(np.int64)
        with np.errstate(divide="ignore"):
            lp = np.log(allowed / allowed.sum(axis=1, keepdims=True))
        res = [bc.branching_step(vals, cv, ptr, col, lp, merge, 12, 6, th, x, P, lw, idx,
                                 True, informative, *common) for merge in (False, True)]
        cdf = np.cumsum(np.full((M, M), 1.0 / M), axis=1)
        res.append(bc.discrete_step(vals, cv, cdf, rng.random(N), th, x, P, lw, idx, True,
                                    informative, *common))
        thc = rng.uniform(0.2, 1.2, size=(N, 1))
        z = rng.standard_normal((N, 1))
        res.append(bc.random_walk_step(0.0, 1.3, np.sqrt(0.5), 0.03, z, thc, x, P, lw, True,
                                       informative, *common))
        res.append(bc.qgrbpf_step(0.0, 1.3, 1e-3, 1e-8, False, z, 0.5 * (1 + np.tanh(z[:, 0])),
                                  -np.log(N), lw, thc, x, P, lw, True, informative, *common))
        res.append(bc.qgrbpf_step(0.0, 1.3, 1e-3, 1e-8, True, np.array([[-1.0], [0.0], [1.0]]),
                                  lw, -np.log(N), np.log(np.array([1 / 6, 2 / 3, 1 / 6])), thc,
                                  x, P, lw, True, informative, *common))
        for r in res:
            assert r[0] == bank.OK
            out += [np.ravel(np.asarray(a, dtype=float)) for a in r]
        r = res[2]
        out += [np.ravel(np.asarray(a, dtype=float))
                for a in bc.resample(r[6], 0.37, -np.log(N), r[1], r[2], r[3], r[5])]
        # the exact KF: f the fifth state
        z = np.append(x[0], 0.9)[None]
        Pz = np.zeros((1, 5, 5))
        Pz[0, :4, :4] = P[0]
        Pz[0, 4, 4] = 0.0225
        pieces = _affine_pieces(fam.params, max(dt, 0.1))
        r = bc.kf_step(z, Pz, *pieces, np.array([-1.0, 0.02]), informative, 0.8, 1e-3 * dt,
                       dt > 0, y, np.hstack([H, np.zeros((3, 1))]), fam.R.copy(),
                       np.arange(3, dtype=np.int64), sel)
        assert r[0] == bank.OK
        out += [np.ravel(np.asarray(a, dtype=float)) for a in r]
    return np.concatenate(out)


def test_step_kernels_compiled_equal_interpreted():
    """Every filter's step kernel run interpreted (TRAIN_NO_JIT=1) gives the compiled
    kernel's numbers bit for bit (the same IEEE operations in the same order)."""
    compiled = _step_kernel_values()
    np.testing.assert_array_equal(compiled, _interpreted("_step_kernel_values"))


@pytest.mark.parametrize("name", ["rbpf", "sma", "gsma", "gsma merged", "qgrbpf", "gh3", "rw",
                                  "kf"])
def test_compiled_run_equals_numpy_form(name):
    """A seeded run of 40 steps (braking, then coasting and a standstill command: the shared
    gain; readings of one or two rows; outputs without a reading; a reading at the time of
    the last output: no prediction), the whole step compiled against the numpy form with the
    same random stream: the same particle counts and the estimates within 1e-9 relative
    (every step's reordered sums differ by ~1e-15 relative; no pruning, resampling or
    pairing decision sits that close over 40 steps)."""
    fam = BrakingModel(BrakingParams(meas_var=(0.25, 0.09, 1e-4), standstill_speed=0.1))
    if name == "kf":
        a, b = (BrakingKF(fam, 1e-3, (1.0, 0.15)) for _ in range(2))
        b._fused_ok = lambda: False  # the numpy form
    else:
        a, b = _filters(fam)[name], _filters(fam)[name]
        b._bank_ok = False  # the numpy form
    assert a._fused_ok() and not b._fused_ok()
    ra, rb = np.random.default_rng(31), np.random.default_rng(31)
    for f, r in ((a, ra), (b, rb)):
        f.reset([0, 20, -1, -2], 0.01 * np.eye(4), r)
    data = np.random.default_rng(32)
    t = 0.0
    for k in range(40):
        t += 0.0 if k == 25 else 1.0
        a_tar = -1.0 if k < 20 else (0.3 if k < 30 else -0.5)
        y = np.array([20.0 * t - 0.5 * t * t, 20.0 - t, 2 * a_tar]) + data.normal(size=3)
        mask = [None, [True, False, False], [False, True, True]][k % 3]
        if k % 7 == 6:
            y, mask = None, None
        ea = a.step(a_tar, y, mask, ra, t=t)
        eb = b.step(a_tar, y, mask, rb, t=t)
        assert ea.accepted == eb.accepted and ea.n_particles == eb.n_particles, k
        for u, v in ((ea.mean, eb.mean), (ea.cov, eb.cov), (ea.n_eff, eb.n_eff)):
            np.testing.assert_allclose(u, v, rtol=1e-9, atol=1e-12 * (1 + np.abs(v).max()),
                                       err_msg=f"step {k}")
        assert a._s.theta.shape == b._s.theta.shape
    assert ra.random() == rb.random()  # the same numbers drawn


def _inplace_filters(fam):
    """Every algorithm with few particles (interpreted steps take ~50 us per particle), sized
    so that SMA and GSMA prune, GSMA's set outgrows its first buffers and the RBPFs
    resample."""
    vals = np.round(np.arange(10, -1, -1) * 0.1, 10)
    pr = dict(prior=(1.0, 0.15))
    return {
        "rbpf": DiscreteRBPF(fam, vals, sticky_transition(11, 0.1), 20, **pr),
        "sma": SMA(fam, vals, n_init=8, n_keep=8, q_max=40, **pr),
        "gsma": GSMA(fam, vals, n_init=8, n_keep=8, q_max=30, **pr),
        "gsma merged": GSMA(fam, vals, transition=sticky_transition(11, 0.1), merge=True, **pr),
        "sma merged": SMA(fam, vals, transition=sticky_transition(11, 0.1), merge=True, **pr),
        "qgrbpf": QGRBPF(fam, [(0.0, 1.3)], 12, braking_rate_q=1e-3, **pr),
        "gh3": QGRBPF(fam, [(0.0, 1.3)], 3, braking_rate_q=1e-3, quadrature=True, **pr),
        "rw": RandomWalkRBPF(fam, [(0.0, 1.3)], 20, braking_rate_q=1e-3, **pr),
        "kf": BrakingKF(fam, 1e-3, (1.0, 0.15)),
    }


_FIELDS = ("accepted", "t", "mean", "cov", "x_mean", "x_cov", "theta_mean", "theta_cov",
           "n_particles", "n_eff", "informative", "measurement_used", "log_evidence")


def _inplace_run() -> np.ndarray:
    """Every field of every estimate of a seeded 45-step run of each algorithm's compiled
    step (``braking_inplace``): braking, coasting and a standstill command (the shared gain),
    readings of one or two rows, outputs without a reading, a reading at the time of the
    last output (no prediction), stated variances, rejected inputs, a shift and an inflation
    of the set; then the final set and the next random number. Without numba the compiled
    path is forced: its kernels run interpreted (for the test below)."""
    fam = BrakingModel(BrakingParams(meas_var=(0.25, 0.09, 1e-4), standstill_speed=0.1))
    out = []
    for name, f in _inplace_filters(fam).items():
        if not bank.COMPILED:  # the kernels as Python (TRAIN_NO_JIT=1: jit is a no-op)
            if name == "kf":
                f._fused_ok = lambda: True
            else:
                f._bank_ok = True
        assert f._fused_ok()
        rng = np.random.default_rng(41)
        data = np.random.default_rng(42)
        f.reset([0, 20, -1, -2], 0.01 * np.eye(4), rng)
        t = 0.0
        for k in range(45):
            t += 0.0 if k == 25 else (0.4 if k % 5 == 0 else 1.0)
            a_tar = -1.0 if k < 20 else (0.3 if k < 30 else (-0.5 if k < 36 else -1.0))
            y = np.array([20.0 * t - 0.5 * t * t, 20.0 - t, 2 * a_tar]) + data.normal(size=3)
            mask = [None, [True, False, False], [False, True, True]][k % 3]
            var = [0.3, 0.1, 1e-4] if k % 4 == 0 else None
            if k % 7 == 6:
                y, mask = None, None
            if k == 15:
                f.shift(0.5, -0.1)
            if k == 16:
                f.inflate(0.01 * np.eye(2))
            steps = [f.step(a_tar, y, mask, rng, t=t, meas_var=var)]
            if k % 11 == 3:
                steps.append(f.step(float("nan"), y, mask, rng, t=t + 0.5))
                steps.append(f.step(-1.0, [1.0, np.inf, 0.0], None, rng, t=t + 0.5))
            for e in steps:
                out += [np.ravel(np.asarray(getattr(e, k_), dtype=float)) for k_ in _FIELDS]
        theta, logw = f.particles
        out += [theta.ravel(), logw.ravel(), f._s.x.ravel(), f._s.P.ravel(),
                np.array([rng.random()])]
    return np.concatenate(out)


def test_inplace_run_equals_interpreted():
    """The compiled steps on the filters' buffers give, over a seeded run of every
    algorithm, every estimate bit for bit as the same steps interpreted (the reference, run
    first in a process without numba): the in-place form changes where the numbers are kept,
    not one of them."""
    reference = _interpreted("_inplace_run")
    np.testing.assert_array_equal(_inplace_run(), reference)


@pytest.mark.parametrize("name", ["rbpf", "gsma merged", "qgrbpf", "gh3", "kf"])
def test_prediction_packed_per_dt_is_packed_per_step(name):
    """A live node's command and known acceleration d are new at every step while its dts
    repeat: the compiled step's prediction arguments, this dt's pack made once with the
    command's entries written in, are bit for bit those packed afresh for the step
    (``pack_pred`` of ``bank_pred`` and the braking rate; ``pack_kf``), braking, coasting
    and a weak brake trim (the shared gain: 1, f's estimate) and at standstill alike; one
    pack per dt."""
    from train_estimation.core.braking import braking_inplace as bi

    fam = BrakingModel(BrakingParams(meas_var=(0.25, 0.09, 1e-4), standstill_speed=0.1,
                                     min_brake=0.2))
    f = _inplace_filters(fam)[name]
    if not bank.COMPILED:  # the compiled path forced, its kernels interpreted (as above)
        if name == "kf":
            f._fused_ok = lambda: True
        else:
            f._bank_ok = True
    rng = np.random.default_rng(43)
    f.reset([0, 20, -1, -2], 0.01 * np.eye(4), rng, t0=0.0)
    t, seen, holds = 0.0, set(), set()
    for k in range(30):
        dt = (1.0, 0.4, 0.1)[k % 3]
        t += dt
        # braking; coasting (gain 1); a weak trim (below min_brake: f's estimate); braking
        a_tar = (-1.0 - 0.01 * k, 0.3 + 0.01 * k, -0.1 - 0.001 * k, -0.5)[min(k // 6, 3)]
        d = -0.05 - 0.001 * k
        v = 0.0 if k >= 24 else 20.0 - t  # standing from step 24 on: braking does not inform
        e = f.step(a_tar, [20.0 * t - 0.5 * t * t, v, 2 * a_tar], None, rng, t=t, d=d)
        assert e.accepted, k
        key, _, got = f._pred_last
        dt_k, u = key[0], (key[1], key[2])
        assert abs(dt_k - dt) < 1e-9 and u == (a_tar, d), k  # this step's prediction
        seen.add(dt_k)  # (the stamps' differences: dts that differ by an ulp, as a node's)
        informative, hold = key[3], key[4]
        holds.add(hold)
        if name == "kf":
            want = (bi.pack_kf(*_affine_pieces(fam.params, dt_k), u),)
            got = got[:1]
        else:
            fh = np.ones(1) if informative else fam.braking_rates(None, u, False, hold=hold)
            want = bi.pack_pred(fam.bank_pred(u, dt_k), fh)
            got = got[1:]
        for a, b in zip(got, want):
            assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), k
    assert set(f._dt_cache[1]) == seen and len(seen) < 30
    assert any(h not in (None, 1.0) for h in holds)  # a shared gain of f's estimate written in
