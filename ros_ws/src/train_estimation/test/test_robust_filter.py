"""Robust filter of Wen et al. (2017) and its baselines against exact oracles.

No simulator: synthetic data come from the model itself (``WenModel.step_exact``) with an rng.
"""

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.stats import norm
from train_core.model import Balise, Brake, Davis, GradientSection, Line, TrainParams

from train_estimation.core.robust.robust_filter import (
    BaliseReading,
    Decision,
    FilterParams,
    FOHFilter,
    IntermittentKF,
    Measurement,
    OdometerReading,
    RobustFilter,
    choose_gamma,
    covariance16,
    kf_update,
    make_robust_filter,
    robust_predict_cov,
    robust_update,
)
from train_estimation.core.robust.wen_model import DiscreteWen, WenModel

TRAIN = TrainParams(mass=288e3, rotary_allowance=0.16, davis=Davis(3481.8036, 144.9154, 8.5212),
                    brake=Brake(0.4, 1.2))
LINE = Line(name="wen", length=3000.0,
            balises=(Balise(1, 1400.0), Balise(2, 1500.0), Balise(7, 1650.0)),
            gradients=(GradientSection(0.0, 1706.0, -3.0), GradientSection(1706.0, 2372.0, 3.0),
                       GradientSection(2372.0, 2479.0, -3.0),
                       GradientSection(2479.0, 2619.0, -9.0)))
X0 = np.array([1333.8031, 0.0])


def _spd(M):
    return np.allclose(M, M.T, rtol=0, atol=1e-12 * max(1.0, np.abs(M).max())) and \
        np.linalg.eigvalsh(M)[0] > 0


# ---------------------------------------------------------------------------------------------
# (21)-(22) pinned against a hand-computed two-step example
# ---------------------------------------------------------------------------------------------

def _toy() -> DiscreteWen:
    """A~ = [[1, 1], [0, 1]], E~ = [0.5, 1], F~ = 0.2 -> H = [0.1, 0.2]^T, Eu = I (paper)."""
    return DiscreteWen(dt=1.0, A1=np.eye(2), B=np.zeros(2), E=np.array([0.5, 1.0]),
                       A2=np.zeros(2), A=np.array([[1.0, 1.0], [0.0, 1.0]]), F=0.2,
                       H=np.array([[0.1], [0.2]]), Eu=np.eye(2))


def test_riccati_two_step_hand_example():
    """Two steps of (21), (13), (22) computed by hand (exact fractions, see below).

    Step 1, Sigma0 = I, x0 = (3, 4), q = 0.4, gamma = 0.5, eps = 1, lambda_bar = 3^2+4^2 = 25:
      (Sigma^{-1} - gamma I)^{-1} = 2 I;  A 2I A^T = [[4, 2], [2, 2]];  H H^T / gamma =
      [[.02, .04], [.04, .08]];  (1+eps)(...) = [[8.04, 4.08], [4.08, 4.16]];
      (1+1/eps) 25 H H^T = [[0.5, 1], [1, 2]];  q E E^T = [[0.1, 0.2], [0.2, 0.4]]
      => Sigma(1|0) = [[8.64, 5.28], [5.28, 6.56]].
    Update: position channel C = [1 0], R = 1.36, abar = 0.5, received y = 9, x(1|0) = (7, 4):
      S = 10, K = Sigma C^T / S = (0.864, 0.528) (corrected gain),
      x(1|1) = (7, 4) + 2 K = (8.728, 5.056),
      Sigma(1|1) = Sigma - 0.5 Sigma C^T C Sigma / 10 = [[4.90752, 2.99904], [2.99904, 5.16608]].
      Paper gain (24): K = 0.5 * (0.864, 0.528); Sigma - (2 abar^2 - abar^3) Sigma C^T C Sigma / S
      = [[5.84064, 3.56928], [3.56928, 5.51456]], x = (7.864, 4.528).
    Step 2 (from the corrected branch), gamma = 0.1, eps = 0.5, lambda_bar = |x(1|1)|^2 =
      101.74112, then a lost packet of both channels (C = I, R = diag(1, 0.01), abar = 0.5):
      Sigma(2|2) = Sigma(2|1) - 0.5 Sigma (Sigma + R)^{-1} Sigma, x(2|2) = x(2|1).
      The step-2 numbers are from exact rational arithmetic (Fraction) of the same formulas with
      the 2x2 inverse written out, rounded to 17 significant digits.
    """
    dm = _toy()
    S1p, g, e = robust_predict_cov(np.eye(2), dm, q=0.4, lam_bar=25.0, gamma=0.5, epsilon=1.0)
    np.testing.assert_allclose(S1p, [[8.64, 5.28], [5.28, 6.56]], rtol=1e-14)
    meas = Measurement(y=np.array([9.0]), C=np.array([[1.0, 0.0]]), R=np.array([[1.36]]),
                       abar=np.array([0.5]), group=np.zeros(1, int), mask=np.array([True]))
    x1, S1, K = robust_update(np.array([7.0, 4.0]), S1p, meas, "corrected")
    np.testing.assert_allclose(K[:, 0], [0.864, 0.528], rtol=1e-14)
    np.testing.assert_allclose(x1, [8.728, 5.056], rtol=1e-14)
    np.testing.assert_allclose(S1, [[4.90752, 2.99904], [2.99904, 5.16608]], rtol=1e-13)
    xp, Sp, _ = robust_update(np.array([7.0, 4.0]), S1p, meas, "paper")
    np.testing.assert_allclose(xp, [7.864, 4.528], rtol=1e-14)
    np.testing.assert_allclose(Sp, [[5.84064, 3.56928], [3.56928, 5.51456]], rtol=1e-13)

    lam = float(x1 @ x1)
    assert lam == pytest.approx(101.74112, rel=1e-14)
    S2p, _, _ = robust_predict_cov(S1, dm, q=0.4, lam_bar=lam, gamma=0.1, epsilon=0.5)
    np.testing.assert_allclose(S2p, [[126.20268423498567, 69.29598706890619],
                                     [69.29598706890619, 47.104878685129044]], rtol=1e-12)
    lost = Measurement(y=np.array([np.nan, np.nan]), C=np.eye(2), R=np.diag([1.0, 0.01]),
                       abar=np.array([0.5, 0.5]), group=np.zeros(2, int),
                       mask=np.array([False, False]))
    x2p = dm.A @ x1
    x2, S2, _ = robust_update(x2p, S2p, lost, "corrected")
    np.testing.assert_array_equal(x2, x2p)  # nothing received: the estimate is the prediction
    np.testing.assert_allclose(S2, [[63.58156597892383, 34.648284399479344],
                                    [34.648284399479344, 23.557434003321422]], rtol=1e-12)
    _, S2pap, _ = robust_update(x2p, S2p, lost, "paper")
    np.testing.assert_allclose(S2pap, [[79.23684554293929, 43.310210066836056],
                                       [43.310210066836056, 29.444295173773327]], rtol=1e-12)


def test_gamma_violating_constraint_23_is_refused():
    with pytest.raises(ValueError):
        robust_predict_cov(np.eye(2) * 4.0, _toy(), q=0.0, lam_bar=0.0, gamma=0.25,
                           epsilon=1.0)


@pytest.mark.parametrize("Eu", [np.eye(2), np.array([[0.0, 1.0]])])
def test_gamma_rule_minimises_trace_inside_constraint(Eu):
    rng = np.random.default_rng(3)
    for _ in range(20):
        L = rng.normal(size=(2, 2))
        Sigma = L @ L.T + 0.1 * np.eye(2)
        A = np.eye(2) + 0.3 * rng.normal(size=(2, 2))
        H = rng.normal(size=(2, 1)) * 10 ** rng.uniform(-3, 1)
        g = choose_gamma(Sigma, A, H, Eu)
        smax = np.linalg.eigvalsh(Eu @ Sigma @ Eu.T)[-1]
        assert 0 < g < 1 / smax  # constraint (23) strictly

        def trace(gam, Sigma=Sigma, A=A, H=H):  # vectorised over an array of gammas
            gam = np.atleast_1d(gam)[:, None, None]
            M = np.linalg.inv(np.linalg.inv(Sigma) - gam * (Eu.T @ Eu))
            return np.einsum("ij,njk,ik->n", A, M, A) + np.sum(H * H) / gam[:, 0, 0]

        grid = np.linspace(1e-6, 1 - 1e-6, 20001) / smax
        assert trace(g)[0] <= trace(grid).min() * (1 + 1e-9)


def test_corrected_gain_minimises_bound_22_and_paper_gain_does_not():
    """tr (22) is a convex quadratic in K: the corrected gain is its stationary point; the
    paper's (24) (extra factor abar) is strictly worse for abar < 1."""
    rng = np.random.default_rng(4)
    L = rng.normal(size=(2, 2))
    Sigma = L @ L.T + np.eye(2)
    meas = Measurement(y=np.zeros(2), C=np.eye(2), R=np.diag([1.0, 0.01]),
                       abar=np.array([0.875, 0.875]), group=np.zeros(2, int),
                       mask=np.ones(2, bool))
    ab = 0.875

    def bound22(K):  # eq. (22) as printed
        IK = np.eye(2) - ab * K @ meas.C
        return IK @ Sigma @ IK.T + ab * K @ meas.R @ K.T + ab * (1 - ab) * K @ Sigma @ K.T

    _, Sc, Kc = robust_update(np.zeros(2), Sigma, meas, "corrected")
    _, Sp, Kp = robust_update(np.zeros(2), Sigma, meas, "paper")
    np.testing.assert_allclose(Sc, bound22(Kc), rtol=1e-12)
    np.testing.assert_allclose(Sp, bound22(Kp), rtol=1e-12)
    np.testing.assert_allclose(Kc, Sigma @ np.linalg.inv(Sigma + meas.R), rtol=1e-12)
    np.testing.assert_allclose(Kp, ab * Kc, rtol=1e-12)
    assert np.trace(Sc) < np.trace(Sp)
    for _ in range(50):
        dK = 1e-3 * rng.normal(size=(2, 2))
        assert np.trace(bound22(Kc + dK)) > np.trace(Sc)


def test_two_packets_moments():
    """Two independent packets (odometer speed, balise position): Pi has abar_i abar_j across
    packets, and the bound equals the exact expectation over the four (alpha1, alpha2) cases."""
    Sigma = np.array([[4.0, 1.0], [1.0, 2.0]])
    C, R = np.array([[0.0, 1.0], [1.0, 0.0]]), np.diag([0.01, 1.0])
    ab = np.array([0.8, 0.6])
    meas = Measurement(y=np.zeros(2), C=C, R=R, abar=ab, group=np.array([0, 1]),
                       mask=np.ones(2, bool))
    _, Sb, K = robust_update(np.zeros(2), Sigma, meas, "corrected")
    expect = np.zeros((2, 2))
    for a1 in (0, 1):
        for a2 in (0, 1):
            p = (ab[0] if a1 else 1 - ab[0]) * (ab[1] if a2 else 1 - ab[1])
            Lam = np.diag([a1, a2])
            IK = np.eye(2) - K @ Lam @ C
            expect += p * (IK @ Sigma @ IK.T + K @ Lam @ R @ Lam @ K.T)
    np.testing.assert_allclose(Sb, expect, rtol=1e-12)


# ---------------------------------------------------------------------------------------------
# Intermittent KF against a dense joint-Gaussian solve
# ---------------------------------------------------------------------------------------------

def test_intermittent_kf_equals_dense_joint_gaussian():
    """Linear-Gaussian case (constant gradient, no clamp, no actuator): stack the states at all
    event times and the received measurements, condition the joint Gaussian, compare the KF's
    filtered mean and covariance at every event time (1e-9)."""
    line = Line(name="flat", length=1e6, gradients=(GradientSection(-1e6, 1e6, 5.0),))
    model = WenModel.from_params(TRAIN, line, q=4e6, v_max=22.23)
    params = FilterParams(actuator=False, clamp_standstill=False, gate=math.inf,
                          distance_variance=0.5, odometer_origin=100.0)
    m0, P0 = np.array([100.0, 5.0]), np.diag([4.0, 0.25])
    kf = IntermittentKF(model, params, m0, P0, t0=0.0)
    rng = np.random.default_rng(11)
    # events: odometer every 0.1 s (some lost), two balises in between, control changes
    events = []
    for k in range(1, 16):
        events.append(("odo", 0.1 * k, rng.random() < 0.6))
    events += [("bal", 0.35, True), ("bal", 1.12, True)]
    events.sort(key=lambda e: e[1])
    x_true = m0 + np.linalg.cholesky(P0) @ rng.normal(size=2)
    t, u = 0.0, 0.4
    times, A_list, c_list, Q_list, obs = [0.0], [], [], [], []  # obs: (state idx, C, R, y)
    kf_out = []
    seq = {"odo": 0, "bal": 0}
    for n, (kind, te, rec) in enumerate(events):
        if n == 6:
            u = -0.3
            kf.set_control(t, u)
        elif n == 0:
            kf.set_control(0.0, u)
        dt = te - t
        dm = model.discrete(dt)
        Q = model.q * np.outer(dm.E, dm.E)
        c = model.known_input(dm, 0.0, u)  # constant gradient: position does not matter
        A_list.append(dm.A)
        c_list.append(c)
        Q_list.append(Q)
        x_true = dm.A @ x_true + c + dm.E * math.sqrt(model.q) * rng.normal()  # Q rank one
        times.append(te)
        seq[kind] += 1
        if kind == "odo":
            y = np.array([x_true[1] + 0.1 * rng.normal(), x_true[0] - 100.0 +
                          math.sqrt(0.5) * rng.normal()])
            r = OdometerReading(te, seq["odo"], distance=y[1], speed=y[0], speed_variance=0.01,
                                received=rec)
            if rec:
                obs.append((len(times) - 1, np.array([[0.0, 1.0], [1.0, 0.0]]),
                            np.diag([0.01, 0.5]), np.array([y[0], y[1] + 100.0])))
        else:
            # A balise read "at" the true position plus noise; to keep the data from the model
            # itself, the filter's map entry for this id is set to the reading.
            bid = 1 if te < 1.0 else 2
            yb = x_true[0] + 0.3 * rng.normal()
            kf._balise_pos[bid] = yb
            r = BaliseReading(te, seq["bal"], bid, yb, 0.09)
            obs.append((len(times) - 1, np.array([[1.0, 0.0]]), np.array([[0.09]]),
                        np.array([yb])))
        d = kf.update(r)
        assert d.accepted, d
        kf_out.append(kf.estimate())
        t = te
    # dense joint Gaussian of X = (x_0, ..., x_N)
    N = len(times) - 1
    n = 2
    mean = np.zeros(n * (N + 1))
    cov = np.zeros((n * (N + 1), n * (N + 1)))
    mean[:2] = m0
    # x_k = Phi_k x_0 + sum_j Phi_{k,j} (c_j + w_j): build via the linear map
    Tm = np.zeros((n * (N + 1), n * (N + 1)))  # maps (x0, w_0..w_{N-1}) to X
    Tm[:2, :2] = np.eye(2)
    for k in range(N):
        mean[2 * k + 2:2 * k + 4] = A_list[k] @ mean[2 * k:2 * k + 2] + c_list[k]
        Tm[2 * k + 2:2 * k + 4, :] = A_list[k] @ Tm[2 * k:2 * k + 2, :]
        Tm[2 * k + 2:2 * k + 4, 2 * k + 2:2 * k + 4] += np.eye(2)
    base = np.zeros((n * (N + 1), n * (N + 1)))
    base[:2, :2] = P0
    for k in range(N):
        base[2 * k + 2:2 * k + 4, 2 * k + 2:2 * k + 4] = Q_list[k]
    cov = Tm @ base @ Tm.T
    for k in range(1, N + 1):
        rows = [o for o in obs if o[0] <= k]
        if not rows:
            continue
        Cbig = np.vstack([np.hstack([np.zeros((o[1].shape[0], 2 * o[0])), o[1],
                                     np.zeros((o[1].shape[0], 2 * (N - o[0])))]) for o in rows])
        Rbig = np.zeros((Cbig.shape[0], Cbig.shape[0]))
        i = 0
        for o in rows:
            m = o[1].shape[0]
            Rbig[i:i + m, i:i + m] = o[2]
            i += m
        yb = np.concatenate([o[3] for o in rows])
        Syy = Cbig @ cov @ Cbig.T + Rbig
        Kb = np.linalg.solve(Syy, Cbig @ cov).T
        post_m = mean + Kb @ (yb - Cbig @ mean)
        post_c = cov - Kb @ Cbig @ cov
        xk, Pk = kf_out[k - 1]
        np.testing.assert_allclose(xk, post_m[2 * k:2 * k + 2], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(Pk, post_c[2 * k:2 * k + 2, 2 * k:2 * k + 2], rtol=1e-9,
                                   atol=1e-12)


def test_kf_update_with_nothing_received_is_identity():
    meas = Measurement(y=np.zeros(1), C=np.array([[1.0, 0.0]]), R=np.eye(1), abar=np.ones(1),
                       group=np.zeros(1, int), mask=np.zeros(1, bool))
    x, P = np.array([1.0, 2.0]), np.eye(2)
    x2, P2 = kf_update(x, P, meas)
    assert x2 is x and P2 is P


# ---------------------------------------------------------------------------------------------
# Synthetic runs from the model itself
# ---------------------------------------------------------------------------------------------

def _profile(k):
    """Control acceleration (m/s^2) of a short run that keeps 0 <= v <= v_max."""
    return 0.6 if k < 25 else (0.0 if k < 45 else -0.5)


def _run(filters_factory, n_steps, rng, uncertainty="paper", abar=0.875, q=0.49,
         R=(1.0, 0.01), P0=(1.0, 0.01), dt=1.0):
    """One synthetic run; returns errors (n_filters, n_steps, 2) and bounds (…, 2, 2)."""
    model = WenModel.from_params(TRAIN, LINE, q=q, v_max=22.23, uncertainty=uncertainty)
    dm = model.discrete(dt)
    x = X0 + np.sqrt(P0) * rng.normal(size=2)
    filters = filters_factory(model)
    err = np.zeros((len(filters), n_steps, 2))
    bnd = np.zeros((len(filters), n_steps, 2, 2))
    seq = 0
    for k in range(n_steps):
        u = _profile(k)
        wind = math.sqrt(q) * rng.uniform(-1, 1)  # bounded: w^2 <= q
        x = model.step_exact(dm, x, u, wind)
        assert 0.0 <= x[1] <= 22.23
        t = dt * (k + 1)
        seq += 1
        y = x + np.sqrt(R) * rng.normal(size=2)
        rec = rng.random() < abar
        r = OdometerReading(t, seq, distance=y[0], speed=y[1], speed_variance=R[1],
                            received=rec)
        for i, f in enumerate(filters):
            f.predict_to(t, u)
            assert f.update(r).accepted
            xe, P = f.estimate()
            err[i, k] = xe - x
            bnd[i, k] = P
    return err, bnd


def test_sigma_stays_symmetric_positive_definite():
    rng = np.random.default_rng(5)
    for unc in ("paper", "velocity"):
        for gain in ("corrected", "paper"):
            params = FilterParams(actuator=False, gate=math.inf, gain=gain)
            _, bnd = _run(lambda m, p=params: [RobustFilter(m, p, X0, np.diag([1.0, 0.01]))],
                          60, rng, uncertainty=unc)
            for P in bnd[0]:
                assert _spd(P)


@pytest.mark.parametrize("uncertainty,gain", [("paper", "corrected"), ("velocity", "corrected"),
                                              ("velocity", "paper")])
def test_monte_carlo_mse_below_bound(uncertainty, gain):
    """Theorem 2: E[e e^T] <= Sigma(k|k). Sigma depends on x^ (lambda_bar), so the statistic
    is D = Sigma_ii - e_i^2 per run, whose mean must be >= 0 at every step. One-sided test of
    the MC mean with the standard error of D, Bonferroni over all (step, component) pairs at a
    family-wise false-alarm rate of 1e-3."""
    n_runs, n_steps = 300, 60
    rng = np.random.default_rng(12345)
    params = FilterParams(actuator=False, gate=math.inf, gain=gain)
    D = np.zeros((n_runs, n_steps, 2))
    for j in range(n_runs):
        err, bnd = _run(lambda m: [RobustFilter(m, params, X0, np.diag([1.0, 0.01]))],
                        n_steps, rng, uncertainty=uncertainty)
        D[j] = np.diagonal(bnd[0], axis1=1, axis2=2) - err[0] ** 2
    mean = D.mean(0)
    se = D.std(0, ddof=1) / math.sqrt(n_runs)
    z = norm.ppf(1 - 1e-3 / D[0].size)
    assert np.all(mean >= -z * se), (mean / se).min()


def test_filters_beat_foh_on_synthetic_data():
    """Direction of Table III on data from the model itself (both robust variants vs FOH)."""
    rng = np.random.default_rng(7)
    params = FilterParams(actuator=False, gate=math.inf)

    def make(m):
        return [RobustFilter(m, params, X0, np.diag([1.0, 0.01])), FOHFilter(m, params, X0)]

    v = []
    for _ in range(20):
        err, _ = _run(make, 70, rng, uncertainty="velocity")
        v.append(err.var(axis=1))
    v = np.mean(v, axis=0)  # (filter, component)
    assert v[0, 0] < v[1, 0] and v[0, 1] < v[1, 1]


def test_foh_extrapolates_linearly():
    model = WenModel.from_params(TRAIN, LINE)
    f = FOHFilter(model, FilterParams(odometer_origin=0.0), np.array([0.0, 0.0]), t0=0.0)
    f.update(OdometerReading(1.0, 1, distance=10.0, speed=2.0, speed_variance=0.01))
    f.update(OdometerReading(2.0, 2, distance=13.0, speed=2.5, speed_variance=0.01))
    f.update(OdometerReading(3.0, 3, received=False))
    np.testing.assert_allclose(f.estimate()[0], [16.0, 3.0])
    assert f.update(BaliseReading(3.001, 1, 1, 1400.0, 1.0)).reason == "ignored"
    np.testing.assert_allclose(f.estimate()[0], [16.003, 3.0005])
    f.predict_to(4.5)
    np.testing.assert_allclose(f.estimate()[0], [20.5, 3.75])
    assert np.all(np.isnan(f.estimate()[1]))


# ---------------------------------------------------------------------------------------------
# Bad input
# ---------------------------------------------------------------------------------------------

def _fresh(cls=RobustFilter):
    model = WenModel.from_params(TRAIN, LINE, uncertainty="velocity")
    params = FilterParams(gate=5.0, odometer_origin=1366.2)
    x0 = np.array([1399.5, 0.0])
    if cls is FOHFilter:
        f = FOHFilter(model, params, x0, t0=0.0)
    else:
        f = cls(model, params, x0, np.diag([1.0, 0.01]), 0.0, brake=TRAIN.brake)
    f.set_control(0.0, 0.5)
    assert f.update(OdometerReading(0.1, 1, distance=33.8, speed=0.0, speed_variance=0.01)) \
        == Decision(True, "ok")
    expect = "ignored" if cls is FOHFilter else "ok"  # FOH extrapolates the odometer only
    assert f.update(BaliseReading(0.15, 1, 1, 1400.0, 1.0)) == Decision(True, expect)
    return f


BAD = [
    (OdometerReading(0.2, 2, distance=math.nan, speed=0.0, speed_variance=0.01), "non_finite"),
    (OdometerReading(0.2, 2, distance=33.8, speed=math.inf, speed_variance=0.01), "non_finite"),
    (OdometerReading(math.nan, 2, distance=33.8, speed=0.0, speed_variance=0.01), "non_finite"),
    (OdometerReading(0.2, 2, distance=33.8, speed=0.0, speed_variance=0.0),
     "non_positive_variance"),
    (OdometerReading(0.2, 2, distance=33.8, speed=0.0, speed_variance=-1.0),
     "non_positive_variance"),
    (OdometerReading(0.1, 1, distance=33.8, speed=0.0, speed_variance=0.01), "out_of_order"),
    (OdometerReading(0.2, 1, distance=33.8, speed=0.0, speed_variance=0.01), "duplicate"),
    (OdometerReading(0.09, 3, distance=33.8, speed=0.0, speed_variance=0.01), "out_of_order"),
    (OdometerReading(1e6, 2, distance=33.8, speed=0.0, speed_variance=0.01), "future_stamp"),
    (BaliseReading(0.15, 1, 1, 1400.0, 1.0), "duplicate"),
    (OdometerReading(0.05, 2, distance=33.8, speed=0.0, speed_variance=0.01), "out_of_order"),
    (OdometerReading(0.2, 2, distance=533.8, speed=0.0, speed_variance=0.01), "outside_gate"),
    (OdometerReading(0.2, 2, distance=33.8, speed=9.0, speed_variance=0.01), "outside_gate"),
    (BaliseReading(0.2, 2, 99, 1400.0, 1.0), "unknown_balise"),
    (BaliseReading(0.2, 2, 2, 1400.0, 1.0), "balise_map_mismatch"),
    (BaliseReading(0.2, 2, 1, 1400.0, 0.0), "non_positive_variance"),
    (BaliseReading(0.2, 2, 1, math.nan, 1.0), "non_finite"),
    (BaliseReading(0.2, 2, 7, 1650.0, 1.0), "outside_gate"),
]


@pytest.mark.parametrize("cls", [RobustFilter, IntermittentKF, FOHFilter])
@pytest.mark.parametrize("reading,reason", BAD)
def test_bad_input_rejected_counted_state_untouched(cls, reading, reason):
    if cls is FOHFilter and reason == "outside_gate":
        pytest.skip("FOH has no model, hence no gate")
    f = _fresh(cls)
    before = (f.x.copy(), f.P.copy(), f.t, dict(f.counters))
    d = f.update(reading)
    assert not d.accepted and d.reason == reason
    np.testing.assert_array_equal(f.x, before[0])
    np.testing.assert_array_equal(f.P, before[1])
    assert f.t == before[2]
    assert f.counters[reason] == before[3].get(reason, 0) + 1


def test_bad_time_and_control_rejected():
    f = _fresh()
    x, P, t = f.x.copy(), f.P.copy(), f.t
    assert f.predict_to(0.05).reason == "out_of_order"
    assert f.predict_to(math.inf).reason == "non_finite"
    assert f.set_control(0.3, math.nan).reason == "non_finite"
    assert f.set_control(-1.0, 0.1).reason == "out_of_order"
    np.testing.assert_array_equal(f.x, x)
    np.testing.assert_array_equal(f.P, P)
    assert f.t == t
    assert f.counters["out_of_order"] == 2 and f.counters["non_finite"] == 2


def test_lost_packet_shrinks_bound_but_not_kf():
    rf, kf = _fresh(RobustFilter), _fresh(IntermittentKF)
    for f in (rf, kf):
        assert f.pop_measurement_used()  # the readings of _fresh
        f.predict_to(0.2)
    Sr, Pk = rf.P.copy(), kf.P.copy()
    assert rf.update(OdometerReading(0.2, 2, received=False)).reason == "missing"
    assert kf.update(OdometerReading(0.2, 2, received=False)).reason == "missing"
    assert np.trace(rf.P) < np.trace(Sr)  # expectation over alpha, eq. (22)
    np.testing.assert_array_equal(kf.P, Pk)
    assert not rf.pop_measurement_used()


# ---------------------------------------------------------------------------------------------
# Property-based: random sequences of good and bad readings
# ---------------------------------------------------------------------------------------------

_op = st.tuples(
    st.sampled_from(["odo", "lost", "balise", "nan", "negvar", "dup", "old", "unknown",
                     "outlier", "predict", "back", "control"]),
    st.floats(0.01, 2.0),  # time increment
    st.floats(-1.0, 1.0),  # noise / control value
)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(ops=st.lists(_op, min_size=1, max_size=40),
       cls=st.sampled_from([RobustFilter, IntermittentKF]),
       unc=st.sampled_from(["paper", "velocity"]))
def test_random_sequences_keep_state_finite_and_sigma_spd(ops, cls, unc):
    model = WenModel.from_params(TRAIN, LINE, uncertainty=unc)
    f = cls(model, FilterParams(gate=6.0, odometer_origin=0.0), X0, np.diag([1.0, 0.01]),
            0.0, brake=TRAIN.brake)
    seq = {"odo": 0, "bal": 0}
    t = 0.0
    n_rejected = 0
    for kind, dt, val in ops:
        before = (f.x.copy(), f.P.copy(), f.t)
        x_ref = f.x[0]
        if kind in ("odo", "lost", "nan", "negvar", "outlier"):
            t += dt
            seq["odo"] += 1
            dist = x_ref + val if kind != "outlier" else x_ref + 1e4
            r = OdometerReading(t, seq["odo"], distance=dist if kind != "nan" else math.nan,
                                speed=max(f.x[1] + 0.1 * val, 0.0),
                                speed_variance=0.01 if kind != "negvar" else -0.01,
                                received=kind != "lost")
            d = f.update(r)
        elif kind == "balise":
            t += dt
            seq["bal"] += 1
            d = f.update(BaliseReading(t, seq["bal"], 1, 1400.0, 1.0))
        elif kind == "unknown":
            t += dt
            d = f.update(BaliseReading(t, seq["bal"] + 1, 12345, 1400.0, 1.0))
        elif kind == "dup":
            d = f.update(OdometerReading(t + dt, max(seq["odo"], 1), distance=x_ref, speed=0.0,
                                         speed_variance=0.01))
            if seq["odo"] == 0:
                seq["odo"] = 1  # the first one was accepted as a new reading
        elif kind == "old":
            d = f.update(OdometerReading(f.t - dt, seq["odo"] + 100, distance=x_ref, speed=0.0,
                                         speed_variance=0.01))
        elif kind == "predict":
            t += dt
            d = f.predict_to(t)
        elif kind == "back":
            d = f.predict_to(f.t - dt)
        else:
            d = f.set_control(t, 1.5 * val)
        if not d.accepted:
            np.testing.assert_array_equal(f.x, before[0])
            np.testing.assert_array_equal(f.P, before[1])
            assert f.t == before[2]
        if kind in ("nan", "negvar", "unknown", "back", "old"):
            assert not d.accepted
        assert np.all(np.isfinite(f.x))
        assert _spd(f.P)
        n_rejected += not d.accepted
    rejected = {r: c for r, c in f.counters.items() if r not in ("ok", "missing", "ignored")}
    assert sum(rejected.values()) == n_rejected


def test_robust_filter_without_uncertainty_or_dropouts_is_the_kalman_filter():
    """c = 0 (H = 0: gamma = 0, no lambda_bar term) and abar = 1: (21)-(22) with the corrected
    gain are exactly the Kalman recursion with Q = q E E^T."""
    train = TrainParams(mass=288e3, rotary_allowance=0.16, davis=Davis(3481.8, 144.9, 0.0),
                        brake=Brake(0.4, 1.2))
    model = WenModel.from_params(train, LINE, q=2.5e5)
    p = FilterParams(alpha_bar=1.0, gate=math.inf, clamp_standstill=False, odometer_origin=0.0)
    P0 = np.diag([2.0, 0.05])
    rf = RobustFilter(model, p, X0, P0, 0.0, brake=train.brake)
    kf = IntermittentKF(model, p, X0, P0, 0.0, brake=train.brake)
    rng = np.random.default_rng(2)
    for k in range(1, 40):
        for f in (rf, kf):
            f.set_control(0.1 * (k - 1), 0.5 if k < 20 else -0.4)
        r = OdometerReading(0.1 * k, k, distance=X0[0] + rng.normal(),
                            speed=max(0.5 * 0.1 * k + 0.1 * rng.normal(), 0.0),
                            speed_variance=0.01)
        assert rf.update(r).accepted and kf.update(r).accepted
        np.testing.assert_allclose(rf.x, kf.x, rtol=1e-12, atol=1e-10)
        np.testing.assert_allclose(rf.P, kf.P, rtol=1e-10, atol=1e-14)


def test_make_robust_filter_and_covariance16():
    f = make_robust_filter(TRAIN, LINE, X0, 0.0, odometer_origin=0.0)
    assert f.model.uncertainty == "velocity"
    np.testing.assert_allclose(f.P, np.diag([1e-4, 0.01]))  # distance_std 0: floor 1e-4 m^2
    c = np.array(covariance16(f.P)).reshape(4, 4)
    np.testing.assert_array_equal(c[:2, :2], f.P)
    assert np.all(np.isnan(c[2:, :])) and np.all(np.isnan(c[:, 2:]))


def test_seq_reset_and_wraparound_accepted_and_counted():
    """Order is by stamp: seq 2**32 - 1 then a reset to 0 must not blind the filter."""
    f = _fresh()
    for i, seq in enumerate([2**32 - 1, 0, 1, 2]):
        d = f.update(OdometerReading(0.2 + 0.1 * i, seq, distance=33.8, speed=0.0,
                                     speed_variance=0.01))
        assert d.accepted, (seq, d)
    assert f.counters["seq_reset"] == 1
