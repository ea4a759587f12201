r"""The robust filter's compiled step (``robust_compiled``) against its numpy form
(``robust_steps``): within a derived rounding bound on random cases, the same exceptions and
non-finite results where the numpy form has them, compiled == interpreted bit for bit, and a
whole seeded run of :class:`RobustFilter` both ways.

**The bound.** ``u = 2^-53`` (unit roundoff), ``g(k) = k u / (1 - k u)`` (Higham's gamma_k).
Both forms evaluate the same expressions in the same order; they differ only where numpy hands
an operation to BLAS/LAPACK (2-term dot products, possibly fused; a triangular solve that may
multiply by a reciprocal; ``eigh``). In either form a quantity made of sums and products is
within ``g(k)`` of its exact value relative to ``|.|``, the same expression evaluated on
absolute values (``k`` roundings on its longest path), so the two forms differ by at most
``2 g(k) |.|``; where a step is not a sum of products its condition enters:

* eq. (21), ``Sigma(k+1|k)``: ``k = 14`` (``Sigma Y`` 2, ``+ Sigma`` 1, ``A M`` 2, ``A^T`` 2,
  ``+ HH / gamma`` 1, the two factors ``1 + eps``, ``1 + 1/eps`` 2 and their products and sums
  3, symmetrising 1) on ``N = (1 + eps)(|A| |M| |A|^T + |HH| / gamma) + (1 + 1/eps) lam |HH|
  + q |EE|``, ``|M| = |Sigma| + |Sigma Eu^T| |Y|``, ``Y = W^{-1} Eu Sigma``; plus
  - the solve of ``W``: ``2 g(3) (1 + eps) |A| |Sigma Eu^T| |W^{-1}| P^T |L| |U| |Y| |A|^T``
    (LU with partial pivoting, Higham Thm 9.4, one more rounding for a reciprocal);
  - gamma: each form stops its Newton iteration within ``tau = 5e-15 + 8 u`` of the root of its
    own ``r`` (``|r| <= 1e-14 h`` with ``gamma r' >= 2 h``; the bracket and step tolerances are
    1e-15; ``r`` is evaluated to ~14 u h), and the roots move with the inputs: ``g_i`` by
    ``2 |G_i| 2 g(4) |A| |Sigma Eu^T| |V_i| + 2 g(2) g_i`` (weighted ``t_i^2 / (2 sum g_j
    t_j^2)``), the
    eigenvalues by ``8 u |Sigma|`` (moving the root by ``gamma ds``) and the eigenvectors by an
    angle ``<= 8 u |Sigma| / gap`` (moving it by ``8 u kW^2 (kappa - 1)``, ``kW`` the condition
    of ``W``, ``kappa = 1 / (1 - gamma s_max)``): ``rho = 2 tau + shift``, relative. The
    bracket moves by ``rho (1 + eps)(kappa max diag A (M - Sigma) A^T + max |HH| / gamma)``
    (``d (M - Sigma) / d gamma <= kappa (M - Sigma) / gamma`` in the PSD order);
  - epsilon ``= sqrt(b / a)``: relative ``eta = (da / a + db / b) / 2 + 2 u``, moving the
    result by ``eta (eps |B| + lam |HH| / eps)``.
* the mean ``A x + B fb + E fe``: ``2 g(3) (|A| |x| + |B fb| + |E fe|)``; the standstill clamp's
  travel ``v0^2 / (2 |a|)`` then by ``dp_v / (|p_v| + v0) + 4 u`` relative.
* eq. (22), ``Sigma(k+1|k+1)``: ``k = 14`` on ``|I - K Abar C| |Sigma| |.|^T + |K| (|Pi - abar
  abar^T| o |C| |Sigma| |C|^T + |Pi| o |R|) |K|^T``, plus the gain's difference
  ``dK^T <= |D^{-T}| (dN^T + (dD^T + 2 g(3) P^T |L| |U|) |K^T|)`` (``D = Pi o S`` or ``S``,
  ``dD = 2 g(6) |D|``-magnitudes, ``dN = 2 g(3) |Sigma| |C|^T abar``): eq. (22) is stationary in
  K at the corrected gain (``f(K + dK) = f(K) + dK (Pi o S) dK^T``), so there it enters as
  ``|dK| |D| |dK|^T``; the paper's gain (24) is not, ``+ |dK| |X| + |X|^T |dK|^T``,
  ``X = (Pi o S) K^T - Abar C Sigma``; and a product ``K Abar C`` of two non-zero terms adds
  ``2 g(2) |K| |Abar C|`` to ``I - K Abar C`` (one term, as the filter's channels have: exact).
* the update's mean ``x + K nu``: ``|dK| |nu| + 2 g(3) (|x| + |K| |nu|) + 2 g(3) |K| (|y| +
  |C| |x|)``.

In the filter's runs (well-conditioned Sigma and R) ``|.|`` is within a factor ~2 of the
result, so the bound is ~30 u ~ 3e-15 relative to the largest entry; on purpose-built
ill-conditioned cases (Sigma near singular, R many decades below Sigma) eq. (22) cancels to
a result many decades below ``|.|`` and both forms' rounding errors, hence their difference,
are that large relative to the result (e.g. 1e-6), within the bound. Observed (``pytest -s``
prints it): differences up to 0.12 (Sigma(k+1|k)), 0.38 (gamma), 0.16 (epsilon), 0.15
(Sigma(k+1|k+1)) and 0.30 (the update's mean) of their bounds; Sigma(k+1|k) within 5.2 u of its
largest entry, gamma within 45 u (5e-15) relative; on metro_demo's steps both within 3.5 u of
the largest entry, 87-96 % (prediction) and 44-46 % (update) of the steps equal bit for bit.
"""

import math
import os
import sys

import numpy as np
import pytest
from train_core.model import Brake, Davis, TrainParams

from train_estimation.core.robust import robust_compiled as rc
from train_estimation.core.robust.robust_filter import (
    BaliseReading,
    FilterParams,
    Measurement,
    OdometerReading,
    RobustFilter,
    robust_predict,
    robust_update,
)
from train_estimation.core.robust.wen_model import DiscreteWen, WenModel

sys.path.insert(0, os.path.dirname(__file__))
import nojit  # noqa: E402
from test_robust_filter import LINE, TRAIN  # noqa: E402  (the same train and line)

U = 2.0 ** -53


def g(k: int) -> float:
    return k * U / (1 - k * U)


TAU = 5e-15 + 8 * U  # one form's Newton: its gamma within TAU of its own root (module doc)
needs_numba = pytest.mark.skipif(not rc.COMPILED, reason="numba not installed (TRAIN_NO_JIT)")


# -- cases ----------------------------------------------------------------------------------

def _sigma(rng, scale):
    """A random PSD 2x2: diagonal, or rotated with an eigenvalue ratio down to 1e-16."""
    if rng.random() < 0.2:
        return np.diag(scale * 10.0 ** rng.uniform(-6, 6, 2))
    th = rng.uniform(0, np.pi)
    V = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    S = V @ np.diag(scale * np.array([1.0, 10.0 ** -rng.uniform(0, 16)])) @ V.T
    return 0.5 * (S + S.T)


def _model(rng, unc, c=None):
    tr = TrainParams(mass=10 ** rng.uniform(4, 6), rotary_allowance=0.1,
                     davis=Davis(3000.0, rng.uniform(0, 300),
                                 rng.uniform(0, 20) if c is None else c), brake=Brake(0.4, 1.2))
    return WenModel.from_params(tr, LINE, q=10 ** rng.uniform(-3, 3),
                                v_max=rng.uniform(10, 100), uncertainty=unc)


def _toy(unc, f):
    """A big uncertainty (H up to 10): gamma s_max near 1, W ill-conditioned."""
    return DiscreteWen(dt=1.0, A1=np.eye(2), B=np.zeros(2), E=np.array([0.5, 1.0]),
                       A2=np.zeros(2), A=np.array([[1.0, 1.0], [0.0, 1.0]]), F=f,
                       H=f * np.array([[0.5], [1.0]]),
                       Eu=np.eye(2) if unc == "paper" else np.array([[0.0, 1.0]]))


def predict_cases(n, seed):
    """(model, dm, Sigma, x, u, epsilon, clamp): both uncertainty forms, dt 1 ms - 1 s, H = 0
    (hh = 0: gamma = 0), big H, Sigma from 1e-30 to 1e30, fixed and per-step epsilon."""
    rng = np.random.default_rng(seed)
    for i in range(n):
        unc = ("paper", "velocity")[i % 2]
        model = _model(rng, unc, c=0.0 if i % 7 == 0 else None)  # c = 0: H = 0
        dm = model.discrete(float(10 ** rng.uniform(-3, 0)))
        if i % 5 == 0:
            dm = _toy(unc, 10 ** rng.uniform(-3, 1))
        scale = 10.0 ** (rng.uniform(-30, 30) if i % 3 == 0 else rng.uniform(-6, 6))
        x = np.array([rng.uniform(0, 3000), rng.uniform(-1, 1) * 10 ** rng.uniform(-3, 2)])
        eps = None if rng.random() < 0.7 else float(10 ** rng.uniform(-3, 3))
        yield model, dm, _sigma(rng, scale), x, rng.uniform(-2, 2), eps, rng.random() < 0.8


def update_cases(n, seed):
    """(x, Sigma, Measurement, gain): the filter's channels (speed + position of one packet,
    a balise) and random ones, 1-2 channels, masks, lost packets (mask all False), abar = 0
    (dropped), one or two packets, R correlated, Sigma from 1e-20 to 1e20 against R."""
    rng = np.random.default_rng(seed)
    for i in range(n):
        m = 1 + i % 2
        x = np.array([rng.uniform(0, 3000), rng.uniform(0, 30)])
        S = _sigma(rng, 10.0 ** rng.uniform(-20, 20) if i % 4 == 0 else 10.0 ** rng.uniform(-4, 4))
        if i % 3 == 0:
            C = rng.standard_normal((m, 2))
        else:
            C = np.array([[0.0, 1.0], [1.0, 0.0]] if i % 3 == 1 else [[1.0, 0.0], [0.0, 1.0]])[:m]
        r = 10 ** rng.uniform(-4, 4, m)
        R = np.diag(r)
        if m == 2 and rng.random() < 0.3:
            R[0, 1] = R[1, 0] = rng.uniform(-0.9, 0.9) * np.sqrt(r[0] * r[1])
        ab = rng.uniform(0.05, 1.0, m)
        if rng.random() < 0.2:
            ab[rng.integers(m)] = 1.0
        if rng.random() < 0.1:
            ab[rng.integers(m)] = 0.0
        mask = rng.random(m) < 0.7 if rng.random() < 0.8 else np.zeros(m, bool)
        y = C @ x + rng.standard_normal(m) * np.sqrt(r) * 3
        yield x, S, Measurement(y=y, C=C, R=R, abar=ab, group=rng.integers(0, 2, m),
                                mask=mask), ("corrected", "paper")[(i // 2) % 2]


def _kernel_predict(kernel, model, dm, S, x, u, eps, clamp):
    return kernel(x, S, dm.A, dm.B, dm.E, dm.HH, dm.hh, dm.EE, dm.Eu,
                  float(model.q), eps is None, 0.0 if eps is None else float(eps),
                  model.drive_mass * u, model.a + model.gradient_force(x[0]), dm.dt, clamp)


def _kernel_update(kernel, x, S, meas, gain, gate=math.inf, accel=0.0, since=0.0):
    return kernel(x, S, meas.y, meas.C, meas.R, meas.abar, meas.group, meas.mask,
                  gain == "corrected", gate, accel, since)


# -- the bounds (module doc) ------------------------------------------------------------------

def _lu_mag(D):
    """``P^T |L| |U|`` of LU with partial pivoting (gesv's), for the solve's backward error."""
    n = D.shape[0]
    if n == 1:
        return np.abs(D)
    swap = abs(D[1, 0]) > abs(D[0, 0])
    Dp = D[::-1] if swap else D
    lf = Dp[1, 0] / Dp[0, 0]
    LU = np.abs([[1.0, 0.0], [lf, 1.0]]) @ np.abs([[Dp[0, 0], Dp[0, 1]],
                                                   [0.0, Dp[1, 1] - lf * Dp[0, 1]]])
    return LU[::-1] if swap else LU


def predict_bound(model, dm, S, x, u, eps, clamp):
    """(bound on |dSigma(k+1|k)| (2, 2), on |dx| (2,), on |dgamma| / gamma, on |deps| / eps)."""
    A, HH, Eu = dm.A, dm.HH, dm.Eu
    aA = np.abs(A)
    Eux = Eu @ x
    lam = float(Eux @ Eux)
    _, gam, e_used = robust_predict(x, S, model, dm, u, eps, clamp)[1:]
    if gam > 0.0:
        Su, SE = Eu @ S @ Eu.T, S @ Eu.T
        W = dm.I_u / gam - Su
        Y = np.linalg.solve(W, SE.T)
        Bm = aA @ (np.abs(S) + np.abs(SE) @ np.abs(Y)) @ aA.T + np.abs(HH) / gam
        solve = aA @ np.abs(SE) @ np.abs(np.linalg.inv(W)) @ _lu_mag(W) @ np.abs(Y) @ aA.T
        s, V = np.linalg.eigh(Su)
        t = gam / (1.0 - gam * s)
        kappa, kW = t[-1] / gam, t[-1] / t[0]
        G = A @ SE @ V
        gi = np.sum(G * G, axis=0)
        dG = 2 * g(4) * (aA @ np.abs(SE) @ np.abs(V))
        dg = 2 * np.sqrt(gi) * np.sqrt(np.sum(dG * dG, axis=0)) + 2 * g(2) * gi
        shift = float(t * t @ dg) / (2.0 * float(gi @ (t * t)))
        if Eu.shape[0] == 2:  # eigh against the closed form: eigenvalues and -vectors
            shift += gam * 8 * U * abs(s).max() + 8 * U * kW ** 2 * (kappa - 1.0)
        rho = 2 * TAU + shift
        D = A @ (SE @ Y) @ A.T
        G_term = rho * (kappa * np.diag(D).max() + np.abs(HH).max() / gam)
    else:
        Bm, solve, rho, G_term = aA @ np.abs(S) @ aA.T, 0.0, 0.0, 0.0
    B = A @ S @ A.T if gam == 0.0 else None
    beta = 2 * g(8) * Bm + 2 * g(3) * solve + G_term  # the bracket's difference
    if B is None:
        Su, SE = Eu @ S @ Eu.T, S @ Eu.T
        B = A @ (S + SE @ np.linalg.solve(dm.I_u / gam - Su, SE.T)) @ A.T + HH / gam
    C = lam * np.abs(HH)
    if e_used > 0.0:
        N = (1 + e_used) * Bm + (1 + 1 / e_used) * C + model.q * np.abs(dm.EE)
        eta = 0.0
        if eps is None:
            eta = 0.5 * (np.trace(beta) / np.trace(B) + 2 * g(3)) + 2 * U
        bP = (2 * g(14) * N + (1 + e_used) * (2 * g(3) * solve + G_term)
              + eta * (e_used * Bm + C / e_used))
    else:
        eta = 0.0
        bP = 2 * g(14) * (Bm + model.q * np.abs(dm.EE)) + 2 * g(3) * solve + G_term
    fb, fe = model.drive_mass * u, model.a + model.gradient_force(x[0])
    Nx = aA @ np.abs(x) + np.abs(dm.B * fb) + np.abs(dm.E * fe)
    bx = 2 * g(3) * Nx
    p = A @ x + dm.B * fb + dm.E * fe
    if clamp and p[1] < 0.0:
        v0 = max(x[1], 0.0)
        travel = 0.5 * v0 * v0 * dm.dt / (v0 - p[1]) if v0 > 0 else 0.0
        bx = np.array([travel * (bx[1] / (abs(p[1]) + v0) + 4 * U)
                       + 2 * U * (abs(x[0]) + travel), 0.0])
    return bP, bx, rho, eta


def update_bound(x, S, meas, gain):
    """(bound on |dSigma(k+1|k+1)| (2, 2), on |dx| (2,)) (module doc)."""
    keep = meas.abar > 0.0
    if not keep.any():
        return np.zeros((2, 2)), np.zeros(2)
    C, R, ab = meas.C[keep], meas.R[np.ix_(keep, keep)], meas.abar[keep]
    grp, mask, y = meas.group[keep], meas.mask[keep], meas.y[keep]
    same = grp[:, None] == grp[None, :]
    Pi = np.where(same, np.minimum(ab[:, None], ab[None, :]), np.outer(ab, ab))
    aC, aS = np.abs(C), np.abs(S)
    CSC = aC @ aS @ aC.T
    Sx = C @ S @ C.T + R
    Dc = Pi * Sx
    D, Dabs = (Dc, Pi * (CSC + np.abs(R))) if gain == "corrected" else (Sx, CSC + np.abs(R))
    Nm = S @ C.T * ab
    K = np.linalg.solve(D.T, Nm.T).T
    aK = np.abs(K)
    dN = 2 * g(3) * aS @ aC.T * ab
    dKT = np.abs(np.linalg.inv(D.T)) @ (dN.T + (2 * g(6) * Dabs.T + 2 * g(3) * _lu_mag(D.T))
                                        @ aK.T)
    dK = dKT.T
    e = ab[:, None] * C
    IKC = np.eye(2) - K @ e
    terms = aK[:, :, None] * np.abs(e)[None, :, :]  # (i, l, j): |K_il| |e_lj|
    Er = 2 * g(2) * terms.sum(axis=1) * ((terms != 0).sum(axis=1) > 1)
    inner = np.abs(Pi - np.outer(ab, ab)) * CSC + np.abs(Pi) * np.abs(R)
    NJ = np.abs(IKC) @ aS @ np.abs(IKC).T + aK @ inner @ aK.T
    bP = 2 * g(14) * NJ + Er @ aS @ np.abs(IKC).T + np.abs(IKC) @ aS @ Er.T
    bP = bP + dK @ np.abs(Dc) @ dK.T
    if gain == "paper":
        X = np.abs(Dc @ K.T - Nm.T)
        bP = bP + dK @ X + X.T @ dK.T
    nu = np.where(mask, y - C @ x, 0.0)
    bx = (dK @ np.abs(nu) + 2 * g(3) * (np.abs(x) + aK @ np.abs(nu))
          + 2 * g(3) * aK @ (mask * (np.abs(y) + aC @ np.abs(x))))
    return bP, bx


# -- the tests ------------------------------------------------------------------------------

def test_predict_within_bound_of_numpy_form():
    """Eq. (21), the gamma rule, epsilon, the mean and the clamp: 4000 random cases."""
    worst = {"P": 0.0, "x": 0.0, "gamma": 0.0, "eps": 0.0, "P / (u max|P|)": 0.0,
             "dgamma / (u gamma)": 0.0}
    n_clamped = n_zero_h = 0
    for case in predict_cases(4000, 1):
        model, dm, S, x, u, eps, clamp = case
        st, xk, Pk, gk, ek = _kernel_predict(rc.predict, *case)
        assert st == rc.OK
        xr, Pr, gr, er = robust_predict(x, S, model, dm, u, eps, clamp)
        bP, bx, rho, eta = predict_bound(*case)
        dP, dx = np.abs(Pk - Pr), np.abs(xk - xr)
        assert np.all(dP <= bP), (case, dP, bP)
        assert np.all(dx <= bx), (case, dx, bx)
        assert abs(gk - gr) <= rho * gr and abs(ek - er) <= max(eta, 0.0) * er
        assert (gk == 0.0) == (dm.hh == 0.0) and np.array_equal(Pk, Pk.T)
        worst["P"] = max(worst["P"], (dP / np.maximum(bP, 1e-300)).max())
        worst["x"] = max(worst["x"], (dx / np.maximum(bx, 1e-300)).max())
        worst["gamma"] = max(worst["gamma"], abs(gk - gr) / (rho * gr) if gr else 0.0)
        worst["eps"] = max(worst["eps"], abs(ek - er) / (eta * er) if er and eta else 0.0)
        worst["P / (u max|P|)"] = max(worst["P / (u max|P|)"], dP.max() / (U * np.abs(Pr).max()))
        worst["dgamma / (u gamma)"] = max(worst["dgamma / (u gamma)"],
                                          abs(gk - gr) / (U * gr) if gr else 0.0)
        n_clamped += bool(clamp and xr[1] == 0.0 and x[1] != 0.0)
        n_zero_h += dm.hh == 0.0
    assert n_clamped > 100 and n_zero_h > 300  # the clamp and the hh = 0 branch were met
    print("largest difference / bound:", worst)


def test_update_within_bound_of_numpy_form():
    """Eq. (22) with both gains: 4000 random cases (channels, masks, lost packets, drops)."""
    worst = {"P": 0.0, "x": 0.0, "P / (u max|P|)": 0.0}
    seen = set()
    for x, S, meas, gain in update_cases(4000, 2):
        st, xk, Pk = _kernel_update(rc.update, x, S, meas, gain)
        assert st == rc.OK
        xr, Pr, _ = robust_update(x, S, meas, gain)
        bP, bx = update_bound(x, S, meas, gain)
        dP, dx = np.abs(Pk - Pr), np.abs(xk - xr)
        assert np.all(dP <= bP), (x, S, meas, gain, dP, bP)
        assert np.all(dx <= bx), (x, S, meas, gain, dx, bx)
        assert np.array_equal(Pk, Pk.T)
        worst["P"] = max(worst["P"], (dP / np.maximum(bP, 1e-300)).max())
        worst["x"] = max(worst["x"], (dx / np.maximum(bx, 1e-300)).max())
        worst["P / (u max|P|)"] = max(worst["P / (u max|P|)"], dP.max() / (U * np.abs(Pr).max()))
        seen.add((gain, int((meas.abar > 0).sum()), bool(meas.mask.any())))
    assert len(seen) == 12  # both gains x 0-2 channels kept x received or lost
    print("largest difference / bound:", worst)


def test_gate_decides_as_gate_ok():
    """The kernel's gate and FilterBase._gate_ok on the filter's channels (unit rows: both
    exact), near the threshold too, with and without gate_accel."""
    f = RobustFilter(WenModel.from_params(TRAIN, LINE), FilterParams(), np.zeros(2), np.eye(2))
    rng = np.random.default_rng(3)
    n_out = 0
    for i, (x, S, meas, gain) in enumerate(update_cases(3000, 4)):
        if np.any((meas.C != 0.0) & (meas.C != 1.0)):
            continue
        gate, accel, since = rng.uniform(0.5, 5), (0.0, 0.3)[i % 2], rng.uniform(0, 5)
        if i % 3 == 0:  # a channel exactly at the gate
            j = int(rng.integers(meas.y.size))
            s = meas.C[j] @ S @ meas.C[j] + meas.R[j, j]
            if accel:
                s += (meas.C[j] @ [0.5 * accel * since * since, accel * since]) ** 2
            meas.y[j] = meas.C[j] @ x + gate * np.sqrt(s)
        f.params = FilterParams(gate=gate, gate_accel=accel)
        ok = f._gate_ok(x, S, meas, since)
        st = _kernel_update(rc.update, x, S, meas, gain, gate, accel, since)[0]
        assert (st != rc.GATE) == ok
        n_out += not ok
    assert n_out > 200


@pytest.mark.filterwarnings("ignore:overflow encountered", "ignore:invalid value encountered")
def test_fallbacks_raise_or_fail_as_numpy_form(monkeypatch):
    """Where the numpy form raises or gives a non-finite state, the compiled path gives the
    same (it runs the numpy form): zero Sigma (ZeroDivisionError in the gamma rule), epsilon 0
    with a cross term (ValueError), a NaN or overflowing Sigma, a singular gain solve."""
    model = WenModel.from_params(TRAIN, LINE, uncertainty="velocity")

    def outcome(kernels, step):
        monkeypatch.setattr(RobustFilter, "kernels", kernels)
        f = RobustFilter(model, FilterParams(epsilon=step.get("eps")), np.array([10.0, 5.0]),
                         np.eye(2))
        try:
            return step["call"](f)
        except Exception as exc:  # noqa: BLE001 - the type is what is compared
            return type(exc).__name__

    steps = [
        {"call": lambda f: f._predict(f.x, np.zeros((2, 2)), 0.1, 0.0)},
        {"call": lambda f: f._predict(f.x, np.eye(2), 0.1, 0.0), "eps": 0.0},
        {"call": lambda f: f._predict(f.x, np.full((2, 2), np.nan), 0.1, 0.0)},
        {"call": lambda f: f._predict(f.x, np.array([[1e308, 0.0], [0.0, 1e308]]), 1.0, 0.0)},
        {"call": lambda f: f._gated_apply(f.x, np.array([[1.0, 1.0], [1.0, 1.0]]), Measurement(
            y=f.x.copy(), C=np.eye(2), R=np.zeros((2, 2)), abar=np.ones(2),
            group=np.zeros(2, int), mask=np.ones(2, bool)), 0.0)},  # singular: LinAlgError
        {"call": lambda f: f._gated_apply(f.x, np.eye(2), Measurement(
            y=np.full(3, 15.0), C=np.ones((3, 2)), R=np.eye(3), abar=np.ones(3),
            group=np.zeros(3, int), mask=np.ones(3, bool)), 0.0)},  # 3 channels: numpy's
    ]
    kinds = []
    for step in steps:
        a, b = outcome(False, step), outcome(True, step)
        if isinstance(a, str):
            assert a == b
        else:
            for u, v in zip(a, b):
                np.testing.assert_array_equal(u, v)
        kinds.append(a if isinstance(a, str) else "finite" if np.isfinite(a[1]).all() else "nan")
    assert kinds[:2] == ["ZeroDivisionError", "ValueError"] and "LinAlgError" in kinds
    # an Eu of neither form (Lemma 1 allows any): the kernel declines, the numpy form runs
    toy = _toy("paper", 0.1)
    odd = DiscreteWen(dt=1.0, A1=toy.A1, B=toy.B, E=toy.E, A2=toy.A2, A=toy.A, F=toy.F,
                      H=toy.H, Eu=np.array([[1.0, 0.0]]))
    assert _kernel_predict(rc.predict, model, odd, np.eye(2), np.ones(2), 0.0, None,
                           True)[0] == rc.FALLBACK


def _run(f, seed: int, n: int = 400):
    """A seeded run: 10 Hz odometer (speed + distance), lost packets, three balises, a reading
    outside the gate, commands that accelerate, cruise and brake to a standstill."""
    rng = np.random.default_rng(seed)
    truth = np.array([1333.8, 0.0])
    out = []
    for k in range(1, n + 1):
        t = 0.1 * k
        a = 0.8 if t < 12 else (0.0 if t < 25 else -1.0)
        f.set_control(t - 0.1, a)
        truth = np.array([truth[0] + truth[1] * 0.1, max(truth[1] + a * 0.1, 0.0)])
        if k % 9 == 0:
            r = OdometerReading(t, k, distance=0.0, speed=0.0, speed_variance=0.0,
                                received=False)
        else:
            r = OdometerReading(t, k, distance=truth[0] - 1333.8 + rng.normal(0, 1.0),
                                speed=truth[1] + rng.normal(0, 0.1), speed_variance=0.01)
        if k == 200:
            r = OdometerReading(t, k, distance=truth[0] + 500.0, speed=truth[1],
                                speed_variance=0.01)  # outside the gate
        out.append((f.update(r), *f.estimate(), f.last_gamma, f.last_epsilon))
        for b in LINE.balises:
            if truth[0] - truth[1] * 0.1 < b.position <= truth[0]:
                out.append((f.update(BaliseReading(t + 0.01, b.id, b.id, b.position, 0.25)),
                            *f.estimate(), f.last_gamma, f.last_epsilon))
    # two seconds on without readings: braked at a standstill, the clamp holds v = 0
    out.append((f.predict_to(0.1 * n + 2.0), *f.estimate(), f.last_gamma, f.last_epsilon))
    return out


def _filter(unc, gain, eps):
    model = WenModel.from_params(TRAIN, LINE, uncertainty=unc)
    params = FilterParams(gain=gain, epsilon=eps, gate=5.0, odometer_origin=1333.8,
                          distance_variance=1.0, speed_variance=0.01, gate_accel=0.1)
    return RobustFilter(model, params, np.array([1333.8, 0.0]), np.diag([1.0, 0.01]), 0.0,
                        brake=TRAIN.brake)


@pytest.mark.parametrize("unc,gain,eps", [("velocity", "corrected", None),
                                          ("paper", "corrected", None),
                                          ("paper", "paper", 0.5),
                                          ("velocity", "paper", None)])
def test_whole_run_within_bound_of_numpy_form(unc, gain, eps):
    """400 odometer slots and the balises, compiled against the numpy form: the same decisions
    at every reading, the estimates within n * 30 u of their scale (each step's difference is
    within ~30 u of its magnitudes, which these well-conditioned states keep within ~2 of the
    entries, and the filter's recursion does not amplify a past difference: the error
    dynamics (I - K C) A contract), gamma and epsilon within n * 1.2e-14 relative."""
    a, b = _filter(unc, gain, eps), _filter(unc, gain, eps)
    b.kernels = False
    ra, rb = _run(a, 5), _run(b, 5)
    n = len(ra)
    assert [r[0] for r in ra] == [r[0] for r in rb]
    assert {r[0].reason for r in ra} >= {"ok", "missing", "outside_gate"}
    x_scale = max(np.abs(r[1]).max() for r in rb)
    worst = 0.0
    for (_, xa, Pa, ga, ea), (_, xb, Pb, gb, eb) in zip(ra, rb):
        assert np.abs(xa - xb).max() <= n * 30 * U * x_scale
        assert np.abs(Pa - Pb).max() <= n * 30 * U * np.abs(Pb).max()
        assert abs(ga - gb) <= n * 1.2e-14 * gb and abs(ea - eb) <= n * 1.2e-14 * eb
        worst = max(worst, np.abs(Pa - Pb).max() / (U * np.abs(Pb).max()))
    assert ra[-1][1][1] == rb[-1][1][1] == 0.0  # braked to a standstill: clamped
    print(f"{n} readings, largest |dSigma| / (u max|Sigma|) = {worst:.3g}")


def _kernel_values() -> np.ndarray:
    """Every kernel output on seeded cases and a whole run, flattened (for the test below);
    without numba the kernels run interpreted."""
    out = []
    for case in predict_cases(300, 7):
        st, xk, Pk, gk, ek = _kernel_predict(rc.predict, *case)
        out += [[st, gk, ek], xk, Pk.ravel()] if st == rc.OK else [[st]]
    for x, S, meas, gain in update_cases(300, 8):
        st, xk, Pk = _kernel_update(rc.update, x, S, meas, gain, 2.0, 0.1, 1.0)
        out += [[st], xk if st == rc.OK else [], Pk.ravel() if st == rc.OK else []]
    f = _filter("paper", "corrected", None)
    for _, x, P, gam, eps in _run(f, 6, 150):
        out += [x, P.ravel(), [gam, eps]]
    return np.concatenate([np.ravel(np.asarray(v, dtype=float)) for v in out])


@needs_numba
def test_compiled_equals_interpreted():
    """The kernels run interpreted -- ``.py_func`` here, and every function of the module in a
    process with TRAIN_NO_JIT=1 -- give the compiled numbers bit for bit (the same IEEE
    operations in the same order, no fast-math)."""
    for case in predict_cases(500, 9):
        for a, b in zip(_kernel_predict(rc.predict, *case),
                        _kernel_predict(rc.predict.py_func, *case)):
            np.testing.assert_array_equal(a, b)
    for x, S, meas, gain in update_cases(500, 10):
        a = _kernel_update(rc.update, x, S, meas, gain, 3.0, 0.1, 1.0)
        b = _kernel_update(rc.update.py_func, x, S, meas, gain, 3.0, 0.1, 1.0)
        assert a[0] == b[0]
        if a[0] == rc.OK:
            np.testing.assert_array_equal(a[1], b[1])
            np.testing.assert_array_equal(a[2], b[2])
    interpreted = nojit.interpreted("test_robust_compiled", "_kernel_values",
                                    "train_estimation.core.robust.robust_compiled")
    np.testing.assert_array_equal(_kernel_values(), interpreted)


@needs_numba
def test_a_filter_never_compiles_after_it_starts():
    """After a filter is made (``warm_up``), numba has one specialization of each kernel and
    compiles no other in the process: a whole run, then read-only, Fortran-ordered and strided
    copies of every array argument, Python ints for floats, give the same numbers through the
    one general signature. (Each new combination of layouts was a compilation of seconds inside
    a node's callback on a loaded machine.)"""
    f = _filter("paper", "corrected", None)
    general = rc._signatures()
    for kernel, sig in zip((rc.predict, rc.update), general):
        assert sig in [tuple(s) for s in kernel.signatures]
        assert not kernel._can_compile
    # (other tests of this process may have called the kernels before any filter was made:
    # those specializations stay, none is added from here on)
    before = [len(rc.predict.signatures), len(rc.update.signatures)]
    _run(f, 5, 40)

    def odd(a):  # the same values, read-only and (2-D) Fortran-ordered, or strided (1-D)
        if not isinstance(a, np.ndarray):
            return a
        b = np.asfortranarray(a) if a.ndim == 2 else np.repeat(a, 2)[::2]
        b = b.copy(order="K") if a.ndim == 2 else b
        b.setflags(write=False)
        return b

    for case in predict_cases(50, 11):
        ref = _kernel_predict(rc.predict, *case)
        got = _kernel_predict(lambda *args: rc.predict(*map(odd, args)), *case)
        for a, b in zip(ref, got):
            np.testing.assert_array_equal(a, b)
    for x, S, meas, gain in update_cases(50, 12):
        ref = _kernel_update(rc.update, x, S, meas, gain, 3.0, 0.1, 1.0)
        got = _kernel_update(lambda *args: rc.update(*map(odd, args)), x, S, meas, gain, 3,
                             0.1, 1)
        assert ref[0] == got[0]
        if ref[0] == rc.OK:
            np.testing.assert_array_equal(ref[1], got[1])
            np.testing.assert_array_equal(ref[2], got[2])
    assert [len(rc.predict.signatures), len(rc.update.signatures)] == before
