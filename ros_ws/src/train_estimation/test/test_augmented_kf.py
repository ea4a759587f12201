"""kf2_loglik is the two-column fast path of augmented_kf: the same profile log-likelihood."""

import json
import math
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from train_estimation.core.numerics import augmented_kf as A
from train_estimation.core.numerics.augmented_kf import Events, augmented_kf, gls, kf2_loglik
from train_estimation.core.numerics.kalman import balise_update, odometer_update, predict_cov


def _events(rng, n, balises, held):
    t = np.cumsum(rng.uniform(0.05, 0.5, n))
    kind = np.zeros(n, np.int8)
    kind[balises] = 1
    y_d = np.cumsum(rng.uniform(0.0, 5.0, n)) + rng.normal(size=n)
    y_v = rng.normal(5.0, 1.0, n)
    r_v = np.where(kind == 1, rng.uniform(0.5, 4.0, n), rng.uniform(0.005, 0.1, n))
    h = np.zeros(n, bool)
    h[held] = True
    return Events(t=t, kind=kind, y_d=y_d, y_v=y_v, r_v=r_v, held=h,
                  odo=np.flatnonzero(kind == 0), bal=np.flatnonzero(kind == 1))


@pytest.mark.parametrize("seed,balises,held,q,r_s", [
    (0, [5, 17, 30], [2, 3], 0.02, 0.3),
    (1, [1, 2, 40], [], 1e-5, 1e-4),  # small noise, balises back to back
    (2, [10], list(range(20, 30)), 0.5, 5.0),  # a long standstill
    (3, [], [7], 0.1, 0.05),  # no balise: s0 is not determined, the profile is the fixed fit
])
def test_kf2_loglik_equals_the_general_filter(seed, balises, held, q, r_s):
    rng = np.random.default_rng(seed)
    n = 45
    ev = _events(rng, n, balises, held)
    bv, bs = rng.normal(size=n) * 0.2, rng.normal(size=n) * 0.05
    md, mv = rng.normal(size=n) * 0.3, rng.normal(size=n) * 0.1
    Z = np.zeros((n, 2))
    Bv, Bs, Md, Mv, Mb = (Z.copy() for _ in range(5))
    Bv[:, 0], Bs[:, 0], Md[:, 0], Mv[:, 0] = bv, bs, md, mv
    Mb[:, 1] = 1.0  # column 1 is s0: it enters the balise readings only
    q_held = 1.0
    kf = augmented_kf(ev, q, r_s, Bv, Bs, Md, Mv, Mb, q_held)
    if balises:
        _, _, quad = gls(kf.W, np.eye(2))
    else:
        quad = kf.W[0, 0]
    general = kf.loglik(np.array([1.0, 0.0])) + 0.5 * (kf.W[0, 0] - quad)
    fast = kf2_loglik(ev, q, r_s, bv, bs, md, mv, q_held)
    assert fast == pytest.approx(general, rel=1e-10, abs=1e-9)


def _reference_augmented_kf(ev, q, r_s, Bv, Bs, Md, Mv, Mb, q_held, keep_innov=False,
                            update=None, q_per_event=None):
    """augmented_kf as one event loop over all the columns (the filter written out step by
    step, as before the two-pass form): the two-pass form must give the same."""
    n, p1 = ev.t.size, Bv.shape[1]
    Z = np.zeros((2 * n, p1))
    Xs, Xv = -Md[0].copy(), -Mv[0].copy()
    Xs[0] += ev.y_d[0]
    Xv[0] += ev.y_v[0]
    p00, p01, p11 = r_s, 0.0, float(ev.r_v[0])
    logdet, m, row = 0.0, 0, 0
    E0, E1, S_v = np.zeros((n, 2)), np.zeros((n, 2)), np.full(n, np.nan)
    for k in range(1, n):
        h = ev.t[k] - ev.t[k - 1]
        qk = q_per_event[k] if q_per_event is not None else (q_held if ev.held[k] else q)
        Xs = Xs + h * Xv + Bs[k]
        Xv = Xv + Bv[k]
        p00, p01, p11 = predict_cov(p00, p01, p11, h, qk)
        if update is not None and not update[k]:
            continue
        if ev.kind[k] == 0:
            s00, s01, s11, det, _, (k00, k01, k10, k11), pn = odometer_update(
                p00, p01, p11, r_s, ev.r_v[k])
            es, ev_ = -Xs - Md[k], -Xv - Mv[k]
            es[0] += ev.y_d[k]
            ev_[0] += ev.y_v[k]
            l00 = math.sqrt(s00)
            l10 = s01 / l00
            Z[row] = es / l00
            Z[row + 1] = (ev_ - l10 * Z[row]) / math.sqrt(s11 - l10 * l10)
            row, m, logdet = row + 2, m + 2, logdet + math.log(det)
            E0[k], E1[k], S_v[k] = (ev_[0], es[0]), (ev_[1], es[1]), s11
            Xs, Xv = Xs + k00 * es + k01 * ev_, Xv + k10 * es + k11 * ev_
        else:
            s, (k0, k1), pn = balise_update(p00, p01, p11, ev.r_v[k])
            eb = -Xs - Mb[k]
            eb[0] += ev.y_d[k]
            Z[row] = eb / math.sqrt(s)
            row, m, logdet = row + 1, m + 1, logdet + math.log(s)
            E0[k], E1[k] = (np.nan, eb[0]), (np.nan, eb[1])
            Xs, Xv = Xs + k0 * eb, Xv + k1 * eb
        p00, p01, p11 = pn
    Z = Z[:row]
    return Z.T @ Z, logdet, m, E0, E1, S_v


@pytest.mark.parametrize("seed,balises,held,update,per_event", [
    (0, [5, 17, 30], [2, 3], None, False),
    (1, [1, 2, 40], [], [4, 5, 6, 17, 40], False),  # held-out readings, balises back to back
    (2, [10], list(range(20, 30)), None, True),  # a standstill; noise per event
    (3, [], [7], [30], False),
    (4, [0, 44], [], None, False),  # balises at the first and the last event
])
def test_two_pass_filter_equals_the_step_by_step_filter(seed, balises, held, update, per_event):
    rng = np.random.default_rng(seed)
    n, p1 = 45, 7
    ev = _events(rng, n, balises, held)
    Bv, Bs = rng.normal(size=(n, p1)) * 0.1, rng.normal(size=(n, p1)) * 0.05
    Md, Mv = rng.normal(size=(n, p1)) * 0.2, rng.normal(size=(n, p1)) * 0.1
    Mb = np.zeros((n, p1))
    Mb[:, 1] = 1.0
    upd = None
    if update is not None:
        upd = np.ones(n, bool)
        upd[update] = False
    qpe = rng.uniform(0.0, 0.1, n) if per_event else None
    q, r_s, q_held = 0.02, 0.3, 2.0
    for _ in range(2):  # the second run reuses the first's gains
        kf = augmented_kf(ev, q, r_s, Bv, Bs, Md, Mv, Mb, q_held, keep_innov=True, update=upd,
                          q_per_event=qpe)
        W, logdet, m, E0, E1, S_v = _reference_augmented_kf(
            ev, q, r_s, Bv, Bs, Md, Mv, Mb, q_held, update=upd, q_per_event=qpe)
        # the same operations on every number: equal bit for bit
        assert kf.m == m and kf.logdet == logdet
        for a, b in ((kf.W, W), (kf.E0, E0), (kf.E1, E1), (kf.S_v, S_v)):
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("blocks", [False, True])
def test_a_fold_of_the_innovations_on_the_filter_of_every_reading(blocks):
    """``use``: the filter's state is updated by every reading, the normal equations, log det
    and count take the marked events' innovations only. So the innovations of the marked
    events are those of the filter without ``use`` (the same numbers), the others NaN, and the
    two folds' normal equations add up to the whole run's (to rounding: two sums of products
    instead of one). All marked: the whole run's W bit for bit."""
    rng = np.random.default_rng(5)
    n, p1 = 60, 5
    ev = _events(rng, n, [9, 31, 50], [])
    Bv, Bs = rng.normal(size=(n, p1)) * 0.1, rng.normal(size=(n, p1)) * 0.05
    Md, Mv = rng.normal(size=(n, p1)) * 0.2, rng.normal(size=(n, p1)) * 0.1
    Mb = np.zeros((n, p1))
    Mb[:, 1] = 1.0
    if blocks:  # the blocks form, with column 0 as the fixed part and 2..4 as drift columns
        fixed = (Bv[:, 0], Bs[:, 0], Md[:, 0], Mv[:, 0], Mb[:, 0])
        Bv[:, 1] = Bs[:, 1] = Md[:, 1] = Mv[:, 1] = 0.0
        Md[:, 2:] = Mv[:, 2:] = 0.0

        def run(**kw):
            return A.augmented_kf_blocks(ev, 0.02, 0.3, fixed, drift=(Bv[:, 2:], Bs[:, 2:]),
                                         q_held=2.0, keep_innov=True, **kw)
    else:
        def run(**kw):
            return augmented_kf(ev, 0.02, 0.3, Bv, Bs, Md, Mv, Mb, 2.0, keep_innov=True, **kw)
    whole = run()
    fold = (np.floor(ev.t / 1.0).astype(int) % 2) == 0
    a, b = run(use=fold), run(use=~fold)
    np.testing.assert_array_equal(run(use=np.ones(n, bool)).W, whole.W)
    upd = np.arange(n) > 0  # the events that updated the filter (all but the first)
    for kf, mask in ((a, fold), (b, ~fold)):
        np.testing.assert_array_equal(kf.E0[mask & upd], whole.E0[mask & upd])
        np.testing.assert_array_equal(kf.E1[mask & upd], whole.E1[mask & upd])
        np.testing.assert_array_equal(kf.S_v[mask], whole.S_v[mask])
        assert np.isnan(kf.E0[~mask & upd]).all() and np.isnan(kf.S_v[~mask]).all()
    np.testing.assert_allclose(a.W + b.W, whole.W, rtol=1e-12, atol=1e-12)
    assert a.m + b.m == whole.m and 0 < a.m < whole.m
    assert a.logdet + b.logdet == pytest.approx(whole.logdet, rel=1e-12, abs=1e-9)
    assert a.Z_bal.shape[0] + b.Z_bal.shape[0] == whole.Z_bal.shape[0]
    # not the filter that skips the other fold's readings: its innovations differ
    skip = run(update=fold)
    assert not np.allclose(skip.E0[fold & upd, 0], whole.E0[fold & upd, 0])


def test_compiled_loops_equal_the_interpreted_ones():
    """The loops as they run (compiled ahead of time, train_core.aot, or by numba's jit,
    numerics.jit) give what the same Python gives, bit for bit (no fast-math: the same IEEE
    operations in the same order)."""
    rng = np.random.default_rng(7)
    n = 300
    ev = _events(rng, n, [3, 50, 51, 200], list(range(100, 130)))
    vecs = [rng.normal(size=n) * 0.2 for _ in range(4)]
    arrays = (ev.t, ev.kind.astype(np.int64), ev.y_d, ev.y_v, ev.r_v, ev.held, *vecs)
    compiled = A._kf2_loop(*arrays, 0.02, 0.3, 1.0)
    interpreted = A.PY["kf2_loop"](*(a.tolist() for a in arrays), 0.02, 0.3, 1.0)
    assert compiled == interpreted

    h = np.diff(ev.t, prepend=ev.t[0])
    upd = rng.uniform(size=n) > 0.2
    outs = []
    for f in (A._gain_loop, A.PY["gain_loop"]):
        bufs = (np.zeros((n, 2, 2)), np.zeros((n, 3)), np.full(n, np.nan), np.zeros(n, np.int64),
                np.full(n, 2, np.int8))
        ld = f(h, ev.kind.astype(np.int64), ev.held, ev.r_v, upd, np.zeros(n), False, 0.02, 0.3,
               1.0, *bufs)
        outs.append((ld, bufs))
    assert outs[0][0] == outs[1][0]
    for a, b in zip(outs[0][1], outs[1][1]):
        np.testing.assert_array_equal(a, b)

    # the column pass: compiled, interpreted, and the numpy form without numba
    p1 = 5
    Bs, Bv, Md, Mv, Mb = (rng.normal(size=(n, p1)) for _ in range(5))
    gp = A._gain_pass(ev, 0.02, 0.3, 1.0, upd, None)
    res = []
    for f in (A._column_pass, A.PY["column_pass"]):
        Z, E = np.zeros((gp.m, p1)), np.zeros((n, 2, p1))
        f(gp.h, gp.code.astype(np.int64), Bs, Bv, Md, Mv, Mb, ev.y_d, ev.y_v, gp.K, gp.L,
          gp.row, Z, E, True)
        res.append((Z, E))
    E = np.zeros((n, 2, p1))
    A._column_pass_numpy(ev, gp, Bs, Bv, Md, Mv, Mb, E)
    for other in res[1:]:
        np.testing.assert_array_equal(res[0][0], other[0])
        np.testing.assert_array_equal(res[0][1], other[1])
    # the loop keeps the innovations of columns 0 and 1 only (E0, E1: all augmented_kf reads)
    np.testing.assert_array_equal(res[0][1][..., :2], E[..., :2])
    assert not res[0][1][..., 2:].any() and E[..., 2:].any()


def _same_bits(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and a.tobytes() == b.tobytes()  # -0.0 and NaN included


@pytest.mark.parametrize("kernel", ["as_it_runs", "interpreted", "filled_in"])
@pytest.mark.parametrize("seed,a,b,c,update,keep", [
    (0, 6, 2, 0, None, True),
    (1, 0, 3, 2, [4, 9, 30], False),  # no drift block; held-out readings
    (2, 12, 0, 0, None, False),  # the stage's big filter's shape: drift and no measurement
    (3, 0, 0, 0, [11], True),  # [fixed, s0] only
    (4, 5, 1, 3, None, True),
])
def test_blocks_equal_the_filled_matrices(monkeypatch, kernel, seed, a, b, c, update, keep):
    """augmented_kf_blocks is augmented_kf on the five matrices filled in from the blocks, bit
    for bit (signed zeros included: columns zero over stretches, and all zero), whichever
    kernel runs it (compiled, interpreted, or the matrices filled in without a compiled one)."""
    rng = np.random.default_rng(seed)
    n = 120
    ev = _events(rng, n, [3, 40, 41, 100], list(range(60, 70)))
    fixed = tuple(rng.normal(size=n) * 0.1 for _ in range(4)) + (rng.normal(size=n),)
    Dv, Ds = rng.normal(size=(n, a)) * 0.1, rng.normal(size=(n, a)) * 0.05
    Dv[:50], Ds[:50] = 0.0, 0.0  # zero until the train reaches a bin, as a gradient's
    if a:
        Dv[:, 0] = Ds[:, 0] = 0.0  # a column that never acts
        Ds[70:, 1] = -0.0
    Mdb, Mvb = rng.normal(size=(n, b)) * 0.2, rng.normal(size=(n, b)) * 0.1
    Mbb = rng.normal(size=(n, c))
    upd = None
    if update is not None:
        upd = np.ones(n, bool)
        upd[update] = False
    p1 = 2 + a + b + c
    Bv, Bs, Md, Mv, Mb = (np.zeros((n, p1)) for _ in range(5))
    Bv[:, 0], Bs[:, 0], Md[:, 0], Mv[:, 0], Mb[:, 0], Mb[:, 1] = *fixed, 1.0
    Bv[:, 2:a + 2], Bs[:, 2:a + 2] = Dv, Ds
    Md[:, a + 2:a + b + 2], Mv[:, a + 2:a + b + 2] = Mdb, Mvb
    Mb[:, a + b + 2:] = Mbb
    ref = augmented_kf(ev, 0.03, 0.2, Bv, Bs, Md, Mv, Mb, 1.5, keep_innov=keep, update=upd)
    if kernel == "interpreted":
        monkeypatch.setattr(A, "_column_pass_blocks", A.PY["column_pass_blocks"])
    elif kernel == "filled_in":
        monkeypatch.setattr(A, "COMPILED", False)
    kf = A.augmented_kf_blocks(ev, 0.03, 0.2, fixed, drift=(Dv, Ds) if a else None,
                               meas=(Mdb, Mvb) if b else None, bal=Mbb if c else None,
                               q_held=1.5, keep_innov=keep, update=upd)
    assert kf.m == ref.m and kf.logdet == ref.logdet
    for x, y in ((kf.W, ref.W), (kf.E0, ref.E0), (kf.E1, ref.E1), (kf.S_v, ref.S_v)):
        assert (x is None and y is None) or _same_bits(x, y)


def test_the_loops_run_without_numba():
    """Without numba (TRAIN_NO_JIT=1 stands in for a missing numba) the same functions run
    interpreted and give the same log-likelihood."""
    here = str(Path(__file__).parent)
    code = textwrap.dedent(f"""
        import json, sys
        import numpy as np
        sys.path.insert(0, {here!r})
        from test_augmented_kf import _events
        from train_estimation.core.numerics import augmented_kf as A, jit
        rng = np.random.default_rng(3)
        ev = _events(rng, 200, [5, 90], [40, 41])
        v = [rng.normal(size=200) for _ in range(4)]
        print(json.dumps([jit.COMPILED, A.kf2_loglik(ev, 0.05, 0.2, *v, 1.0)]))
        """)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env={**os.environ, "TRAIN_NO_JIT": "1"}, timeout=120)
    assert run.returncode == 0, run.stderr
    compiled_flag, ll = json.loads(run.stdout.strip().splitlines()[-1])
    assert compiled_flag is False
    rng = np.random.default_rng(3)
    ev = _events(rng, 200, [5, 90], [40, 41])
    v = [rng.normal(size=200) for _ in range(4)]
    assert kf2_loglik(ev, 0.05, 0.2, *v, 1.0) == ll


def test_the_loops_are_compiled_ahead_of_time_and_equal_numbas_jit():
    """``./run setup`` compiles the three loops ahead of time (train_core.aot) for this source,
    and they are what runs, so a short process never imports numba for them; numba's jit of
    the same loops (TRAIN_NO_AOT=1, what runs when the source was edited since) gives the same
    filter bit for bit."""
    if os.environ.get("TRAIN_NO_JIT") or os.environ.get("TRAIN_NO_AOT"):
        pytest.skip("compiled loops turned off in this environment")
    assert A._AOT is not None, "not compiled ahead of time: run ./run setup"
    assert A._kf2_loop is A._AOT.kf2_loop and A._column_pass is A._AOT.column_pass
    assert A._column_pass_blocks is A._AOT.column_pass_blocks
    here = str(Path(__file__).parent)
    code = textwrap.dedent(f"""
        import json, sys
        import numpy as np
        sys.path.insert(0, {here!r})
        from test_augmented_kf import _events
        from train_estimation.core.numerics import augmented_kf as A
        rng = np.random.default_rng(4)
        n, p1 = 250, 4
        ev = _events(rng, n, [7, 120, 121], [60, 61, 62])
        v = [rng.normal(size=n) for _ in range(4)]
        cols = [rng.normal(size=(n, p1)) for _ in range(5)]
        kf = A.augmented_kf(ev, 0.03, 0.2, *cols[:4], cols[4], 1.5, keep_innov=True)
        print(json.dumps([A._AOT is None, A.COMPILED, "numba" in sys.modules,
                          A.kf2_loglik(ev, 0.05, 0.2, *v, 1.0), kf.logdet,
                          kf.W.tolist(), kf.E0.tolist()]))
        """)
    outs = []
    for env in ({}, {"TRAIN_NO_AOT": "1"}):
        run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             env={**os.environ, **env}, timeout=120)
        assert run.returncode == 0, run.stderr
        outs.append(json.loads(run.stdout.strip().splitlines()[-1]))
    (no_aot0, comp0, numba0, *res0), (no_aot1, comp1, numba1, *res1) = outs
    assert (no_aot0, comp0, numba0) == (False, True, False)  # ahead of time, no numba
    assert (no_aot1, comp1, numba1) == (True, True, True)  # numba's jit
    assert json.dumps(res0) == json.dumps(res1)  # every number the same (NaN included)
