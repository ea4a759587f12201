"""diagnose core against exact oracles.

- The augmented Kalman filter's W gives the exact Gaussian log-likelihood of any linear
  hypothesis: checked against a dense joint-Gaussian solve of the same state-space model.
- The prefix-sum section search equals brute force over every section.
- The link and clock likelihood ratios on sequences with known answers.
"""

import math

import numpy as np
import pytest

from train_estimation.core.numerics.augmented_kf import Events, augmented_kf, gls, kf2_loglik
from train_estimation.core.offline import diagnose as D


def _events(rng, n=40, with_balise=True):
    t = np.cumsum(rng.uniform(0.1, 0.4, n))
    kind = np.zeros(n, np.int8)
    if with_balise:
        kind[[7, 19, 31]] = 1
    y_d = rng.normal(size=n) * 3 + np.arange(n)
    y_v = rng.normal(size=n)
    r_v = np.where(kind == 1, rng.uniform(0.5, 2.0, n), rng.uniform(0.01, 0.05, n))
    held = np.zeros(n, bool)
    held[[3, 4]] = True
    return Events(t=t, kind=kind, y_d=y_d, y_v=y_v, r_v=r_v, held=held,
                     odo=np.flatnonzero(kind == 0), bal=np.flatnonzero(kind == 1))


def _dense_loglik(ev, q, r_s, q_held, Bv, Bs, Md, Mv, Mb, z):
    """Joint Gaussian of every measurement under the model with theta = z[1:], built densely:
    x_k = A x_{k-1} + b_k + w_k, x_0 ~ N(y_0 - M_0 z, R_0) as the filter initialises."""
    n = ev.t.size
    drift = np.stack([Bs @ z, Bv @ z], axis=1)  # (n, 2): increments into event k
    mean = np.zeros((n, 2))
    # initial state: the first (odometer) reading less its measurement columns
    mean[0] = [ev.y_d[0] - Md[0] @ z, ev.y_v[0] - Mv[0] @ z]
    Phi = [np.eye(2)]
    Qs = [np.diag([r_s, ev.r_v[0]])]
    for k in range(1, n):
        h = ev.t[k] - ev.t[k - 1]
        A = np.array([[1.0, h], [0.0, 1.0]])
        mean[k] = A @ mean[k - 1] + drift[k]
        qk = q_held if ev.held[k] else q
        Qs.append(qk * np.array([[h ** 3 / 3, h * h / 2], [h * h / 2, h]]))
        Phi.append(A)
    # covariance of the stacked states
    C = np.zeros((2 * n, 2 * n))
    trans = [[None] * n for _ in range(n)]
    for i in range(n):
        trans[i][i] = np.eye(2)
        for j in range(i + 1, n):
            trans[i][j] = Phi[j] @ trans[i][j - 1]
    for j in range(n):
        for k in range(n):
            s = np.zeros((2, 2))
            for i in range(min(j, k) + 1):
                s += trans[i][j] @ Qs[i] @ trans[i][k].T
            C[2 * j:2 * j + 2, 2 * k:2 * k + 2] = s
    rows, ys, mus, noise = [], [], [], []
    for k in range(1, n):
        if ev.kind[k] == 0:
            for c, (y, mcol, r) in enumerate(((ev.y_d[k], Md[k], r_s), (ev.y_v[k], Mv[k],
                                                                        ev.r_v[k]))):
                rows.append(2 * k + c)
                ys.append(y)
                mus.append(mean[k, c] + mcol @ z)
                noise.append(r)
        else:
            rows.append(2 * k)
            ys.append(ev.y_d[k])
            mus.append(mean[k, 0] + Mb[k] @ z)
            noise.append(ev.r_v[k])
    S = C[np.ix_(rows, rows)] + np.diag(noise)
    e = np.array(ys) - np.array(mus)
    sign, logdet = np.linalg.slogdet(S)
    return -0.5 * (logdet + len(ys) * math.log(2 * math.pi) + e @ np.linalg.solve(S, e))


@pytest.mark.parametrize("seed", [0, 1])
def test_augmented_kf_equals_dense_gaussian(seed):
    rng = np.random.default_rng(seed)
    ev = _events(rng)
    n, p1 = ev.t.size, 4
    Bv, Bs = rng.normal(size=(n, p1)) * 0.1, rng.normal(size=(n, p1)) * 0.05
    Md, Mv = rng.normal(size=(n, p1)) * 0.2, rng.normal(size=(n, p1)) * 0.1
    for M in (Bv, Bs, Md, Mv):
        M[:, 1] = 0.0  # column 1 is s0: it enters the balise readings only
    Mb = np.zeros((n, p1))
    Mb[:, 1] = 1.0
    q, r_s, q_held = 0.02, 0.3, 2.0
    kf = augmented_kf(ev, q, r_s, Bv, Bs, Md, Mv, Mb, q_held)
    for _ in range(3):
        z = np.concatenate([[1.0], rng.normal(size=p1 - 1)])
        assert kf.loglik(z) == pytest.approx(
            _dense_loglik(ev, q, r_s, q_held, Bv, Bs, Md, Mv, Mb, z), rel=1e-9, abs=1e-8)
    # the scalar two-column filter used for the noise fit is the same likelihood with s0
    # profiled out
    ll2 = kf2_loglik(ev, q, r_s, Bv[:, 0], Bs[:, 0], Md[:, 0], Mv[:, 0], q_held)
    th, cov, quad = gls(kf.W[:2, :2], np.eye(2))
    assert ll2 == pytest.approx(-0.5 * (kf.logdet + kf.m * math.log(2 * math.pi) + quad),
                                rel=1e-10)


def test_gls_maximises_the_likelihood():
    rng = np.random.default_rng(3)
    ev = _events(rng)
    n = ev.t.size
    Bv, Bs = rng.normal(size=(n, 3)) * 0.1, rng.normal(size=(n, 3)) * 0.05
    Md, Mv, Mb = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3))
    Mb[:, 1] = 1.0
    kf = augmented_kf(ev, 0.01, 0.2, Bv, Bs, Md, Mv, Mb, 1.0)
    th, cov, quad = gls(kf.W, np.eye(3))
    best = kf.loglik(np.concatenate([[1.0], th]))
    for _ in range(20):
        other = np.concatenate([[1.0], th + rng.normal(size=2) * 0.1])
        assert kf.loglik(other) <= best + 1e-9


def test_best_section_equals_brute_force():
    rng = np.random.default_rng(5)
    p = 12
    X = rng.normal(size=(60, p + 2))
    W = X.T @ X
    u = np.zeros(p + 2)
    u[0] = 1.0
    e1 = np.zeros(p + 2)
    e1[1] = 1.0
    idx = np.arange(2, p + 2)
    quad, a, b, th, se = D.best_section(W, u, e1, idx, 2)
    best = (np.inf, None)
    for i in range(p + 1):
        for j in range(i + 2, p + 1):
            col = np.zeros(p + 2)
            col[idx[i:j]] = 1.0
            _, _, q = gls(W, np.stack([u, e1, col], axis=1))
            best = min(best, (q, (i, j)))
    assert best[1] == (a, b)
    assert quad == pytest.approx(best[0], rel=1e-10)


def test_link_likelihoods():
    rng = np.random.default_rng(1)
    # Bernoulli losses: an alarm needs the loss-after-loss screen at p < 0.01 first, so at most
    # 1 % of the trials; Binomial(50, 0.01): P(>= 4 alarms) = 0.0016.
    scores = []
    for _ in range(50):
        recv = rng.random(3000) < 0.875
        r = D.gilbert_elliott_vs_bernoulli(recv)
        scores.append(2 * r["dll"] - r["k"] * math.log(r["n"]))
    assert sum(s > 0 for s in scores) < 4


@pytest.mark.parametrize("true", [(0.03, 0.25, 0.0, 1.0), (0.01, 0.1, 0.02, 0.8)],
                         ids=["hard", "soft"])
def test_link_is_fitted_as_a_hidden_two_state_chain(true):
    """The hidden chain's parameters, not the loss runs': a bad state that lets 20 % through
    and a good one that loses 2 % (the soft link) are recovered within 4 observed-information
    standard errors (|z| > 4: P = 6e-5 per parameter); a parameter at the boundary (0 or 1),
    which has no standard error, within 0.01."""
    from train_estimation.core.offline.link_hmm import GilbertElliott, simulate

    ge = GilbertElliott(*true)
    lost = simulate(ge, 6000, np.random.default_rng(5))
    r = D.gilbert_elliott_vs_bernoulli(~lost)
    assert 2 * r["dll"] - r["k"] * math.log(r["n"]) > 100
    for k, tv in ge.as_dict().items():
        est = r["parameters"][k]
        if tv in (0.0, 1.0):
            assert abs(est - tv) < 0.01, (k, est, tv)
        else:
            assert abs(est - tv) < 4 * r["std_errors"][k], (k, est, tv, r["std_errors"])
    # the held-out half is predicted better by the chain than by independent losses
    assert r["gain"]["after"] > r["gain"]["before"]


def _run(stamps, recv):
    return D.Run(t_first=0.0, duration=float(stamps[-1]), odo_t=stamps, odo_stamp=stamps,
                  odo_d=stamps,
                  odo_v=np.ones_like(stamps), odo_rv=np.ones_like(stamps),
                  odo_seq=np.arange(stamps.size), odo_recv=recv, ctrl_t=stamps,
                  ctrl_a=np.zeros_like(stamps), bal_t=stamps[:2], bal_p=stamps[:2],
                  bal_r=np.ones(2), bal_id=np.arange(2), clock={}, notes=[])


def test_clock_drift_test():
    rng = np.random.default_rng(2)
    t = np.arange(0.0, 600.0, 0.1)
    lat = 0.03 + rng.exponential(0.02, t.size)
    for drift in (0.0, 1e-3):
        stamps = t * (1 + drift)
        r = D.clock_test(_run(stamps - stamps[0], t + lat + 1.7e9))
        score = 2 * r["dll"] - math.log(r["n"])
        if drift == 0.0:
            assert score < 0
        else:
            assert score > 100
            assert abs(r["parameters"]["drift"] - drift) < 4 * r["std_errors"]["drift"]
    # a jitter-free log: no drift -> no evidence, not a division by zero
    r = D.clock_test(_run(t, t + 5.0))
    assert 2 * r["dll"] - math.log(r["n"]) < 0


def test_core_does_not_read_ground_truth():
    """The measured run has no ground-truth field: the core cannot read it by construction."""
    from train_estimation.core.offline.measured import TOPICS, MeasuredRun

    assert "ground_truth" not in TOPICS
    names = set(MeasuredRun.__dataclass_fields__)
    assert not any("truth" in n for n in names)


def test_fixed_lls_equal_one_gls_fit_each():
    """Stage.fixed_lls (every profile point of a grid in one gather) is Stage.fit(f, [])."""
    from types import SimpleNamespace

    from train_estimation.core.offline.diagnose.stage import Stage

    rng = np.random.default_rng(7)
    ev = _events(rng)
    n, p = ev.t.size, 5
    Bv, Bs = rng.normal(size=(n, p + 3)) * 0.1, rng.normal(size=(n, p + 3)) * 0.05
    Md, Mv = rng.normal(size=(n, p + 3)) * 0.2, rng.normal(size=(n, p + 3)) * 0.1
    for M in (Bv, Bs, Md, Mv):
        M[:, 1] = 0.0
    Mb = np.zeros((n, p + 3))
    Mb[:, 1] = 1.0
    st = Stage.__new__(Stage)
    st.p, st.mo = p, SimpleNamespace(col={f"c{i}": i for i in range(p)})
    st.kf = augmented_kf(ev, 0.02, 0.3, Bv, Bs, Md, Mv, Mb, 2.0)
    fixed = [{}, {"c0": 1.0}, {"c1": -1.0, "c3": 1.0, "scale": 0.5},
             {"c4": 2.0, "c2": -0.5, "c0": 1.5, "scale": -1.0}]
    want = [st.fit(f, [])[2] for f in fixed]
    assert st.fixed_lls(fixed) == pytest.approx(want, rel=1e-11)


def test_measured_run_gives_identify_each_series_in_stamp_order_once():
    """A bag holds messages in arrival order: a jittery link reorders them and may deliver one
    twice. identify gets each series sorted by stamp with a repeated stamp's first reading."""
    from train_estimation.core.offline.measured import MeasuredRun

    rng = np.random.default_rng(5)
    t = np.arange(0.0, 60.0, 0.1) + 1.7e9
    recv = t + 0.05 + rng.exponential(0.3, t.size)  # latency with a tail: reordered arrivals
    arrival = np.argsort(recv, kind="stable")
    arrival = np.insert(arrival, 100, arrival[99])  # one reading delivered twice
    ct = t[::5]
    c_arrival = np.argsort(ct + rng.exponential(0.3, ct.size), kind="stable")
    bt = np.array([t[50], t[300]])
    run = MeasuredRun(
        odo_stamp=t[arrival], odo_recv=recv[arrival], odo_seq=arrival.astype(np.int64),
        odo_distance=(2.0 * (t - t[0]))[arrival], odo_speed=np.full(arrival.size, 2.0),
        odo_speed_variance=np.full(arrival.size, 0.01), ctrl_stamp=ct[c_arrival],
        ctrl_a_tar=np.linspace(-1, 1, ct.size)[c_arrival], balise_stamp=bt[::-1],
        balise_recv=bt[::-1] + 0.1, balise_id=np.array([2, 1]),
        balise_position=np.array([600.0, 100.0]), balise_variance=np.array([1.0, 1.0]),
        ctrl_recv=(ct + 0.1)[c_arrival])
    si = run.to_identify()
    assert np.array_equal(si.odo_t, t)
    assert np.array_equal(si.odo_distance, 2.0 * (t - t[0]))
    assert np.array_equal(si.ctrl_t, ct)
    assert np.array_equal(si.ctrl_a_tar, np.linspace(-1, 1, ct.size))
    assert np.array_equal(si.balise_t, bt) and np.array_equal(si.balise_position, [100.0, 600.0])


def test_measured_run_takes_the_train_clocks_step_out_of_every_stamp():
    """The train clock jumps back 2.5 s at its 300th sample, in a bag in arrival order with
    reordering latency: the odometer readings from that sample on and the balise logged after
    it are put back on the clock before it (identify gets the unstepped stamps); without seq
    numbers nothing is judged."""
    import dataclasses

    from train_estimation.core.offline.measured import MeasuredRun

    rng = np.random.default_rng(6)
    t = np.arange(0.0, 60.0, 0.1) + 1.7e9
    stamped = t - np.where(np.arange(t.size) >= 300, 2.5, 0.0)
    recv = t + 0.05 + rng.exponential(0.05, t.size)
    arrival = np.argsort(recv, kind="stable")
    bt = np.array([t[100], t[450]])
    run = MeasuredRun(
        odo_stamp=stamped[arrival], odo_recv=recv[arrival], odo_seq=arrival.astype(np.int64),
        odo_distance=(2.0 * (t - t[0]))[arrival], odo_speed=np.full(t.size, 2.0),
        odo_speed_variance=np.full(t.size, 0.01), ctrl_stamp=t[::5],
        ctrl_a_tar=np.zeros(t[::5].size), balise_stamp=bt - [0.0, 2.5],
        balise_recv=bt + 0.1, balise_id=np.array([1, 2]),
        balise_position=np.array([20.0, 90.0]), balise_variance=np.array([1.0, 1.0]),
        ctrl_recv=t[::5] + 0.1)
    fixed, steps = run.without_clock_steps()
    assert len(steps) == 1 and abs(steps[0][1] + 2.5) < 1e-5, steps  # stamps at 1.7e9 s
    assert abs(steps[0][0] - t[300]) < 1e-5, steps
    assert np.allclose(fixed.odo_stamp, t[arrival], rtol=0, atol=1e-5)
    assert np.allclose(fixed.balise_stamp, bt, rtol=0, atol=1e-5)
    assert np.allclose(run.to_identify().odo_t, t, rtol=0, atol=1e-5)
    no_seq = dataclasses.replace(run, odo_seq=np.zeros(0, np.int64))
    same, none = no_seq.without_clock_steps()
    assert same is no_seq and none == []


def test_measured_run_puts_the_stamps_after_a_change_of_rate_on_the_rate_before():
    """The train clock runs 1000 ppm slow from 240 s on: the odometer's and the balise's
    stamps after the bend are put back on the rate before it (to within the bend's placement:
    a few seconds at 1000 ppm is a few ms), and identify gets them so."""
    import dataclasses

    from train_estimation.core.offline.measured import MeasuredRun

    rng = np.random.default_rng(9)
    t = np.arange(0.0, 600.0, 0.1)
    slow = np.where(t >= 240.0, -1e-3 * (t - 240.0), 0.0)
    recv = 5000.0 + t + 0.02 + rng.exponential(0.05, t.size)
    bt = np.array([100.0, 450.0])
    run = MeasuredRun(
        odo_stamp=1.7e9 + t + slow, odo_recv=recv, odo_seq=np.arange(t.size),
        odo_distance=2.0 * t, odo_speed=np.full(t.size, 2.0),
        odo_speed_variance=np.full(t.size, 0.01), ctrl_stamp=5000.0 + t[::5],
        ctrl_a_tar=np.zeros(t[::5].size), balise_stamp=1.7e9 + bt + [0.0, -0.21],
        balise_recv=5000.0 + bt + 0.1, balise_id=np.array([1, 2]),
        balise_position=np.array([200.0, 900.0]), balise_variance=np.array([1.0, 1.0]),
        ctrl_recv=5000.0 + t[::5] + 0.1)
    fixed, ch = run.without_rate_change()
    assert ch is not None and abs(ch["at"] - 1.7e9 - 240.0) < 10.0, ch
    assert np.abs(fixed.odo_stamp - 1.7e9 - t).max() < 0.01
    assert np.abs(fixed.balise_stamp - 1.7e9 - bt).max() < 0.01
    assert np.abs(run.to_identify().odo_t - 1.7e9 - t).max() < 0.01
    # log times that follow the stamps (one rate): nothing to take out
    steady = dataclasses.replace(run, odo_recv=run.odo_stamp - 1.7e9 + 5000.0 + 0.05)
    same, none = steady.without_rate_change()
    assert same is steady and none is None


def test_causes_with_parameters_no_train_has_are_not_plausible():
    """A braking rate, a mass, an odometer scale or a low-adhesion factor at or below 0 is a
    force of another kind fitted by a linear cause: never confirmed (Cause.plausible)."""
    from train_estimation.core.offline.diagnose.causes import BY_NAME
    from train_estimation.core.offline.diagnose.result import CauseFit

    bad = {"braking_rate": ({"f_start": 0.9, "f_end": -0.1}, {}),
           "mass": ({"mass": -3e5}, {"traction_gain": -1.0}),
           "odometer_scale": ({"scale": -0.2}, {}),
           "adhesion_section": ({"start": 10.0, "end": 300.0, "factor": -0.5}, {})}
    good = {"braking_rate": ({"f_start": 1.0, "f_end": 0.8}, {}),
            "mass": ({"mass": 3.3e5}, {"traction_gain": 0.9}),
            "odometer_scale": ({"scale": 1.02}, {}),
            "adhesion_section": ({"start": 10.0, "end": 300.0, "factor": 0.6}, {})}
    for name, (params, extra) in bad.items():
        assert BY_NAME[name].plausible(CauseFit(name, 50.0, params, extra=extra), None), name
    for name, (params, extra) in good.items():
        assert BY_NAME[name].plausible(CauseFit(name, 50.0, params, extra=extra), None) is None


def test_a_moved_balise_does_not_place_the_reference_trajectory():
    """place_on_line's fixes (motion.consistent_fixes): a balise 12 m from its map position is
    left out of the placement (every other fix then lies on its neighbours' track), while an
    odometer that counts 2 % more, or jumps 20 m in a slip between two fixes, keeps every fix
    (the piecewise placement is what follows them)."""
    from train_estimation.core.offline.diagnose.motion import consistent_fixes, place_on_line

    rng = np.random.default_rng(5)
    p = np.cumsum(rng.uniform(400.0, 900.0, 12))  # map positions of twelve balises
    noise = rng.normal(0.0, 0.8, p.size)
    d = 1.02 * (p - p[0]) + noise  # odometer distance at each reading: 2 % long
    k = 1.0 / 1.02  # map metres per odometer metre (place_on_line's least-squares scale)
    assert consistent_fixes(d, p, k).all()
    jump = d + 20.0 * (np.arange(p.size) >= 6)  # a slip of 20 m between fixes 5 and 6
    assert consistent_fixes(jump, p, k).all()
    moved = p.copy()
    moved[6] += 12.0  # balise 6 lies 12 m further on than the map says: read 12 m late
    d_moved = d.copy()
    d_moved[6] += 12.0 * 1.02
    keep = consistent_fixes(d_moved, p, k)
    assert keep.sum() == p.size - 1 and not keep[6]
    # the trajectory between its neighbours stays on the odometer's track
    dd = np.linspace(d_moved[5], d_moved[7], 50)
    x = place_on_line(dd, d_moved, p)
    truth = np.interp(dd, d, p)  # where the train was
    assert np.max(np.abs(x - truth)) < 3.0, np.max(np.abs(x - truth))


def test_the_command_offset_grid_reaches_a_long_latency_tail():
    from train_estimation.core.offline.diagnose.motion import shift_grid

    base = (-0.2, 0.4, 0.025)
    # a radio's jitter: the grid as configured
    np.testing.assert_allclose(shift_grid(base, 0.05), np.arange(-0.2, 0.4 + 1e-9, 0.025),
                               atol=1e-9)
    # a mean latency 0.5 s above the floor: up to 0.7 s at the same step
    g = shift_grid(base, 0.5)
    assert g[0] == -0.2 and g[-1] == pytest.approx(0.7) and np.allclose(np.diff(g), 0.025)
    # seconds: at most 49 offsets, the step a whole number of the configured one (the braking
    # columns are keyed by offset + delay on the configured step)
    g = shift_grid(base, 5.0)
    assert g.size <= 49 and g[-1] >= 5.0
    k = np.diff(g)[0] / 0.025
    assert abs(k - round(k)) < 1e-9 and np.allclose(np.diff(g), np.diff(g)[0])


def test_the_brakes_heat_state_is_the_first_order_response_to_the_braking_power():
    """heat_state against its closed form: braking at a constant power P per kg from t = 0
    heats the brakes as P tau (1 - exp(-t / tau)) (m^2/s^2), cooling as exp(-t / tau) once
    the braking ends; relative to the heat of one stop from the top speed, v_top^2 / 2."""
    from types import SimpleNamespace

    from train_estimation.core.offline.diagnose.laws import heat_state

    dt, tau, n = 0.05, 60.0, 4001  # 200 s
    t = dt * np.arange(n)
    braking = t < 100.0
    v = np.full(n, 20.0)  # m/s, held (the power, not the motion, is under test)
    a_br0 = np.where(braking, -0.5, 0.0)  # m/s^2 asked for
    mo = SimpleNamespace(f0=0.8, a_br0=a_br0, v_ref=v, moving=np.ones(n),
                         grid=SimpleNamespace(dt=dt))
    h = heat_state(mo, tau)
    p = 0.8 * 0.5 * 20.0  # m^2/s^3
    # the filter holds the heat taken before each grid point (the sum of P dt, cooled)
    exact = np.where(braking, p * tau * (1 - np.exp(-t / tau)),
                     p * tau * (1 - math.exp(-100.0 / tau)) * np.exp(-(t - 100.0) / tau))
    exact /= 0.5 * 20.0 ** 2
    # a rectangle sum of P exp(-s / tau) over steps of dt is within P dt of the integral
    assert np.max(np.abs(h - exact)) <= p * dt / (0.5 * 20.0 ** 2) + 1e-12
    assert h[0] == 0.0 and np.argmax(h) == np.flatnonzero(braking)[-1] + 1


def test_grid_integrals_are_the_midpoint_rule_in_either_memory_order():
    """motion.Grid.integrate: the interval integrals of grid columns (Bv: of r, Bs: of (t_k -
    tau) r, midpoint rule over the grid steps whose midpoint lies in interval k), checked
    against a loop over the steps; and the same bits whether the columns come stacked as
    columns or as rows (the Fortran-ordered view the motion model passes)."""
    from train_estimation.core.offline.diagnose.motion import Grid

    rng = np.random.default_rng(11)
    ev = _events(rng, n=60)
    g = Grid(ev, 0.02)
    cols = [rng.normal(size=g.t.size) for _ in range(7)]
    Bv, Bs = g.integrate(np.stack(cols, axis=1), ev.t.size)
    Fv, Fs = g.integrate(np.stack(cols).T, ev.t.size)
    assert np.array_equal(Bv, Fv) and np.array_equal(Bs, Fs)
    want_v, want_s = np.zeros_like(Bv), np.zeros_like(Bs)
    for j in range(g.t.size - 1):
        mid = g.t[j] + 0.01
        k = min(max(int(np.searchsorted(ev.t, mid, side="right")), 1), ev.t.size - 1)
        for c, col in enumerate(cols):
            inc = 0.5 * (col[j] + col[j + 1]) * 0.02
            want_v[k, c] += inc
            want_s[k, c] += inc * (ev.t[k] - mid)
    np.testing.assert_allclose(Bv, want_v, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(Bs, want_s, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("cause,params", [
    ("power_limit", {"p_spec": 4.0}),
    ("traction_delay", {"delay": 1.2}),
    ("adhesion_section", {"start": 500.0, "end": 900.0, "factor": 0.6}),
    ("brake_delay", {"delay": 0.8})])
def test_the_replay_plot_runs_the_effects_the_held_out_gain_runs(monkeypatch, cause, params):
    """The replay plot's extended model (``series.replay_series``) replays the recorded
    commands with every effect of the fitted cause that the simulator would run, the very
    keywords the held-out gain's replay takes (``gain.extended_model``): the plot once left a
    power limit, a traction delay and a low-adhesion section out, and drew the believed
    model's speed as the extended one's."""
    from types import SimpleNamespace

    import train_core.motion as motion

    from train_estimation.core.offline.diagnose import series
    from train_estimation.core.offline.diagnose.causes import BY_NAME
    from train_estimation.core.offline.diagnose.gain import extended_model
    from train_estimation.core.offline.diagnose.result import CauseFit
    from train_sim.scenario import load_scenario

    sc = load_scenario("metro_demo")
    t = np.arange(0.0, 120.0, 0.1)
    run = SimpleNamespace(duration=120.0, odo_t=t, ctrl_t=np.array([0.0, 60.0]),
                          ctrl_a=np.array([0.5, -0.5]))
    mo = SimpleNamespace(run=run, cfg=SimpleNamespace(gain_block=60.0), train=sc.train,
                         line=sc.line, grid=SimpleNamespace(t=t), v_ref=np.full(t.size, 10.0),
                         x_ref=10.0 * t)
    calls = []

    def fake_replay(line, train, t_cmd, a_cmd, t0, t_out, x0, v0, **kw):
        calls.append(kw)
        return np.zeros(len(t_out)), np.zeros(len(t_out))

    monkeypatch.setattr(motion, "replay", fake_replay)
    monkeypatch.setattr(series, "_null_of", lambda mo, acc: SimpleNamespace(shift=0.0))
    series.replay_series(mo, [CauseFit(cause, 10.0, dict(params))])
    extended = [kw for kw in calls if "believed" in kw]
    assert extended, calls
    want = extended_model(BY_NAME[cause], params, mo)[2]
    for kw in extended:
        assert {k: v for k, v in kw.items() if k not in ("believed", "max_step")} == want, kw


def test_drive_candidates_without_information_on_the_offset_are_finite():
    """The drive causes' candidate quadratic forms (``causes.drive.Candidates``) profile the
    speed offset s0 out (w_uu - w_u1^2 / w_11); on events that carry no information on it (w_11
    = 0, so its whole row is 0 in a PSD W: a fold without speeds updated) nothing is profiled
    out: w_uu, finite, as ``Stage`` takes it, where 0 / 0 gave NaN and ``argmax`` then chose
    the first NaN's candidate."""
    import warnings

    from train_estimation.core.offline.diagnose.causes.drive import Candidates

    rng = np.random.default_rng(3)
    A = rng.normal(size=(6, 5))
    W = A.T @ A
    W[1, :] = W[:, 1] = 0.0
    cand = Candidates.__new__(Candidates)
    cand.W, cand.k = W, 3
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        q = cand.quads_each()
        u = np.array([1.0, 0.0, 0.0, 1.0, 0.0])
        assert cand.quad_fixed(u) == pytest.approx(float(u @ W @ u), rel=1e-12)
    for i in range(3):
        u = np.zeros(5)
        u[0], u[2 + i] = 1.0, 1.0
        assert q[i] == pytest.approx(float(u @ W @ u), rel=1e-12)
    W2 = A.T @ A  # with information on s0: profiled
    cand.W = W2
    u = np.array([1.0, 0.0, 1.0, 0.0, 0.0])
    assert cand.quads_each()[0] == pytest.approx(
        float(u @ W2 @ u - (u @ W2[:, 1]) ** 2 / W2[1, 1]), rel=1e-12)
