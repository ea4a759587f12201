"""The link's E-step compiled (offline/link_estep.py) against the numpy E-step it repeats: the
same bits where numpy's 4x4 product is summed by fused multiply-adds (BLAS on this kind of
machine), to rounding elsewhere; the fit the same; loaded without numba once built."""

import os
import subprocess
import sys
import textwrap
from fractions import Fraction

import numpy as np
import pytest
from train_core import aot
from train_core.link import Link, LinkParams

from train_estimation.core.offline import link_estep
from train_estimation.core.offline import link_hmm as L

OFF = bool(os.environ.get("TRAIN_NO_JIT"))


def _blas_sums_by_fma() -> bool:
    """Whether np.matmul of 4x4 blocks sums k = 0..3 in order by fused multiply-adds here
    (what the compiled E-step repeats): checked exactly with fractions on random blocks."""
    rng = np.random.default_rng(7)
    x, y = rng.random((64, 4, 4)), rng.random((64, 4, 4))
    out = np.matmul(x, y)
    for s in range(64):
        for i in range(4):
            for j in range(4):
                acc = 0.0
                for k in range(4):
                    acc = float(Fraction(x[s, i, k]) * Fraction(y[s, k, j]) + Fraction(acc))
                if acc != out[s, i, j]:
                    return False
    return True


FMA = _blas_sums_by_fma()


def _same(x, y):
    """Bit for bit where BLAS sums by FMA, else to rounding."""
    for a, b in zip(x, y):
        if FMA:
            assert np.array_equal(a, b), np.max(np.abs(a - b))
        else:
            assert np.allclose(a, b, rtol=1e-12, atol=1e-300)


def numpy_e_step(lost, pi, a, q):
    """link_hmm.statistics with the powers and scans in numpy (as without numba)."""
    saved = link_estep._KERNELS
    try:
        link_estep._KERNELS = False
        return L.statistics(lost, pi, a, q)
    finally:
        link_estep._KERNELS = saved


def losses(p_gb, p_bg, q_g, q_b, n, seed):
    lk = Link(LinkParams(model="gilbert_elliott", p_good_bad=p_gb, p_bad_good=p_bg,
                         loss_good=q_g, loss_bad=q_b), np.random.default_rng(seed))
    return ~lk.transmit_many(n)


def random_models(rng, s):
    """``s`` models with probabilities over the whole range, some at the EM's clip bounds."""
    p = rng.uniform(0.0, 1.0, (s, 4))
    p[rng.random((s, 4)) < 0.1] = L.EPS
    p[rng.random((s, 4)) < 0.05] = 1.0 - L.EPS
    a = L._matrix(p[:, 0], p[:, 1])
    pb = p[:, 0] / (p[:, 0] + p[:, 1])
    return np.stack([1.0 - pb, pb], axis=1), a, p[:, 2:4].copy()


SEQUENCES = {
    "bursty, 10 minutes": lambda: losses(0.03, 0.25, 0.01, 0.6, 6000, 1),
    "rare losses": lambda: losses(0.002, 0.5, 0.001, 0.9, 5000, 2),
    "one loss run": lambda: np.r_[np.zeros(30, bool), np.ones(4, bool)],
    "two samples": lambda: np.array([True, False]),
    "alternating": lambda: np.arange(501) % 2 == 0,
    "long runs (2^12 and more)": lambda: np.r_[np.zeros(5000, bool), np.ones(4097, bool),
                                               np.zeros(3, bool)],
    "lost first": lambda: np.r_[np.ones(3, bool), losses(0.05, 0.3, 0.0, 1.0, 800, 3)],
}


@pytest.mark.skipif(OFF, reason="TRAIN_NO_JIT: the E-step runs in numpy only")
@pytest.mark.parametrize("name", list(SEQUENCES))
def test_compiled_e_step_is_numpys(name):
    lost = SEQUENCES[name]()
    assert link_estep.kernels() is not None
    rng = np.random.default_rng(len(name))
    for s in (1, 6, 33):
        pi, a, q = random_models(rng, s)
        _same(L.statistics(lost, pi, a, q), numpy_e_step(lost, pi, a, q))
    pi, a, q = L._starts(lost, 6, rng)  # the EM's own starting points
    _same(L.statistics(lost, pi, a, q), numpy_e_step(lost, pi, a, q))


def einsum_posteriors(lost, pi, a, q):
    """The posteriors as link_hmm summed them before they were written in a stated order (numpy's
    einsum and sum, whose order follows the arrays' layout): the reference of the bound below."""
    e0 = np.where(lost[0], q, 1.0 - q)
    v0 = pi * e0
    o_r, l_r = L._runs_of(lost)
    em = np.stack([1.0 - q, q], axis=1)
    m_o = a[:, None, :, :] * em[:, :, None, :]
    uniq, inv = np.unique(l_r * 2 + o_r, return_inverse=True)
    p_u, n_u, log_r, pf, pb, lf = L._powers_numpy(m_o, uniq % 2, uniq // 2, inv)
    S, R = pi.shape[0], o_r.size
    p_r = p_u[:, inv]
    alpha = np.empty((S, R, 2))
    alpha[:, 0] = v0
    alpha[:, 1:, 0] = v0[:, 0, None] * pf[0][:, :-1] + v0[:, 1, None] * pf[2][:, :-1]
    alpha[:, 1:, 1] = v0[:, 0, None] * pf[1][:, :-1] + v0[:, 1, None] * pf[3][:, :-1]
    alpha /= alpha.sum(axis=2, keepdims=True)
    beta = np.ones((S, R, 2))
    beta[:, :-1, 0] = pb[0][:, 1:] + pb[1][:, 1:]
    beta[:, :-1, 1] = pb[2][:, 1:] + pb[3][:, 1:]
    beta /= beta.max(axis=2, keepdims=True)
    z = np.einsum("sri,srij,srj->sr", alpha, p_r, beta)
    c = beta[:, :, :, None] * alpha[:, :, None, :]
    n_r = np.einsum("srk,srkij->srij", c.reshape(S, R, 4), n_u[:, inv])
    n_r /= z[..., None, None]
    m_r = m_o[:, o_r]
    xi = (m_r * np.swapaxes(n_r, 2, 3)).sum(axis=1)
    occ_r = np.einsum("srij,srji->sri", n_r, m_r)
    beta0 = np.stack([pb[0][:, 0] + pb[1][:, 0], pb[2][:, 0] + pb[3][:, 0]], axis=1)
    g0 = v0 * beta0
    g0 /= g0.sum(axis=1, keepdims=True)
    occ = occ_r.sum(axis=1) + g0
    hit = (occ_r * o_r[None, :, None]).sum(axis=1) + g0 * float(lost[0])
    last = (v0[:, 0] * (pf[0][:, -1] + pf[1][:, -1]) + v0[:, 1] * (pf[2][:, -1] + pf[3][:, -1]))
    ll = np.log(last) + lf + log_r[:, inv].sum(axis=1)
    return g0, xi, occ, hit, ll


@pytest.mark.parametrize("name", list(SEQUENCES))
def test_a_stated_order_moves_the_e_step_by_rounding_only(name):
    """Summed in a stated order the statistics are those of numpy's einsum and sum to
    rounding: a few ulp of each sum of positive terms (relative 1e-13 holds with a margin for
    runs of thousands), and the same bits where numpy's order was that one (the 729 E-steps of
    three diagnose runs, docs/benchmarks.md)."""
    lost = SEQUENCES[name]()
    rng = np.random.default_rng(len(name) + 1)
    for s in (1, 2, 6, 33):
        pi, a, q = random_models(rng, s)
        new, old = L.statistics(lost, pi, a, q), einsum_posteriors(lost, pi, a, q)
        for x, y in zip(new, old):
            assert np.allclose(x, y, rtol=1e-13, atol=0.0), np.max(np.abs(x - y) / np.abs(y))


@pytest.mark.skipif(OFF, reason="TRAIN_NO_JIT: the E-step runs in numpy only")
def test_the_fit_is_the_same_without_the_compiled_loops(monkeypatch):
    lost = losses(0.02, 0.3, 0.01, 0.5, 5000, 4)
    fit = L.fit_link(lost, np.random.default_rng(0), max_iter=120)
    monkeypatch.setattr(link_estep, "_KERNELS", False)  # as without numba
    assert link_estep.kernels() is None
    ref = L.fit_link(lost, np.random.default_rng(0), max_iter=120)
    assert fit.iterations == ref.iterations and fit.bursty == ref.bursty
    a = [fit.log_likelihood, *fit.hmm.as_dict().values(), *fit.std_errors.values()]
    b = [ref.log_likelihood, *ref.hmm.as_dict().values(), *ref.std_errors.values()]
    _same([np.array(a)], [np.array(b)])


@pytest.mark.skipif(OFF, reason="TRAIN_NO_JIT: the E-step runs in numpy only")
def test_the_jit_is_the_module_compiled_ahead_of_time():
    """numba's jit of the loops (an edited source, before ./run setup) gives what the module
    compiled ahead of time gives."""
    if aot.load("link_estep", [link_estep.__file__]) is None:
        pytest.skip("not compiled ahead of time (./run setup)")
    jitted = link_estep._jitted()
    lost = SEQUENCES["bursty, 10 minutes"]()
    pi, a, q = random_models(np.random.default_rng(5), 6)
    ahead = L.statistics(lost, pi, a, q)
    saved = link_estep._KERNELS
    try:
        link_estep._KERNELS = jitted
        _same(L.statistics(lost, pi, a, q), ahead)
    finally:
        link_estep._KERNELS = saved


def test_the_e_step_runs_compiled_ahead_of_time_without_numba():
    """./run setup builds the loops ahead of time: a diagnose process loads them in a
    millisecond and imports no numba (its import and type system: 0.6 s)."""
    if os.environ.get("TRAIN_NO_JIT") or os.environ.get("TRAIN_NO_AOT"):
        pytest.skip("compiled loops turned off in this environment")
    assert aot.load("link_estep", [link_estep.__file__]) is not None, \
        "not compiled ahead of time: ./run setup"
    code = textwrap.dedent("""
        import sys
        import numpy as np
        from train_estimation.core.offline import link_hmm as L, link_estep
        lost = np.arange(60) % 7 < 2
        pi, a, q = L._starts(lost, 2, np.random.default_rng(0))
        ll = L.statistics(lost, pi, a, q)[-1]
        print("numba" in sys.modules, link_estep.kernels() is not None, ll.tolist())
        """)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60)
    assert run.returncode == 0, run.stderr
    numba_imported, compiled, _ = run.stdout.split(" ", 2)
    assert (numba_imported, compiled) == ("False", "True")
