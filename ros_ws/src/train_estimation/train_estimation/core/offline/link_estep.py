"""The Gilbert-Elliott E-step on runs (:func:`link_hmm.statistics`) as compiled loops.

``diagnose`` fits the link's hidden chain by EM: some 240 E-steps on a bursty bag, each a few
hundred numpy calls on arrays of a few hundred entries (the runs' block-matrix powers by
squaring, the two scans over the runs, the posteriors), which was a third of the CPU of such a
bag. The E-step is written here as loops over the models, the runs and the entries.

The loops repeat :func:`link_hmm._powers_numpy` and :func:`link_hmm._posteriors_numpy`
operation for operation, so they give their bits wherever numpy's own arithmetic is what is
repeated here:

- a product of two 4x4 blocks (``np.matmul``, BLAS's dgemm) is summed over k = 0..3 in order
  by fused multiply-adds (what OpenBLAS's kernels do on a machine with FMA; :func:`_fma` is
  LLVM's correctly rounded ``fma``), the terms with an exact zero of the blocks' structure left
  out (they add an exact 0: every entry is finite and >= 0);
- the scans' 2x2 products and the scalings are elementwise (no fused operations: numba
  compiles without fast-math), and the posteriors' sums are in the order written there;
- the logarithms are not taken here: numpy's ``log`` (its own SIMD code) and the C library's
  differ in the last bit now and then, so the loops return the scale factors, the caller takes
  numpy's log of them and :func:`_log_sums` adds them up in numpy's order.

Where BLAS sums otherwise (no FMA) the two agree to rounding (tested either way). Compiled
ahead of time by ``./run setup`` (:mod:`train_core.aot`) where that was built for this source,
else by numba at the first call; without numba :func:`kernels` returns None and the caller
runs numpy.

Pure: numpy; numba (or the module it compiled ahead of time) for the loops.
"""

from __future__ import annotations

import numpy as np

_KERNELS = None  # (estep, log_sums) once loaded; False when there is no compiler
_HELPERS = False  # the helpers below replaced by their compiled forms


def kernels():
    """(the E-step's loop, the log-sum loop) compiled, or None (``TRAIN_NO_JIT``, no
    numba)."""
    global _KERNELS
    if _KERNELS is None:
        from train_core import aot

        mod = aot.load("link_estep", [__file__])
        if mod is not None:
            _KERNELS = (mod.estep, mod.log_sums)
        else:
            jitted = _jitted()
            _KERNELS = jitted if jitted is not None else False
    return _KERNELS or None


def _jitted():
    from train_core.jit import COMPILED, jit

    if not COMPILED:
        return None
    _compile_helpers(jit)
    return jit(_estep), jit(_log_sums)


def _compile_helpers(jit):
    """The fused multiply-add and the helpers the two loops call, as numba compiles them (the
    loops look them up in this module's globals)."""
    global _HELPERS
    if _HELPERS:
        return
    _define_fma()
    g = globals()
    for name in ("_blockmul", "_divide", "_scan", "_posteriors"):
        g[name] = jit(g[name])
    _HELPERS = True


def _define_fma():
    """:func:`_fma` as numba's intrinsic for LLVM's ``llvm.fma.f64`` (a machine instruction
    where the CPU has one, else the C library's correctly rounded ``fma``: the same bits)."""
    global _fma
    from llvmlite import ir
    from numba.core import types
    from numba.extending import intrinsic

    @intrinsic
    def fma(typingctx, a, b, c):
        sig = types.float64(types.float64, types.float64, types.float64)

        def codegen(context, builder, signature, args):
            f64 = ir.DoubleType()
            fn = builder.module.declare_intrinsic("llvm.fma", [f64],
                                                  ir.FunctionType(f64, [f64, f64, f64]))
            return builder.call(fn, args)

        return sig, codegen

    _fma = fma


def _fma(a, b, c):  # replaced by the intrinsic before compiling (_define_fma)
    raise RuntimeError("link_estep._fma runs only compiled")


def _blockmul(xp, xt, yp, yt, op, ot):
    """[[XP, XT_ab], [0, XP]] @ [[YP, YT_ab], [0, YP]] for the four ab at once, as the 4x4
    product np.matmul computes it (each entry summed over k = 0..3 in order by fused multiply-
    adds): the bottom blocks stay 0 and a copy of the top left one, and the terms with a 0 of
    them add an exact 0 (everything here is >= 0 and finite), so they are left out. Returns
    the largest entry (np.max over the 4x4 blocks, whose zeros it includes)."""
    mx = 0.0
    for i in range(2):
        for j in range(2):
            acc = xp[i, 0] * yp[0, j]
            acc = _fma(xp[i, 1], yp[1, j], acc)
            op[i, j] = acc
            mx = max(mx, acc)
    for ab in range(4):
        for i in range(2):
            for j in range(2):
                acc = xp[i, 0] * yt[ab, 0, j]
                acc = _fma(xp[i, 1], yt[ab, 1, j], acc)
                acc = _fma(xt[ab, i, 0], yp[0, j], acc)
                acc = _fma(xt[ab, i, 1], yp[1, j], acc)
                ot[ab, i, j] = acc
                mx = max(mx, acc)
    return mx


def _divide(p, t, sc):
    for i in range(2):
        for j in range(2):
            p[i, j] = p[i, j] / sc
            for ab in range(4):
                t[ab, i, j] = t[ab, i, j] / sc


_TINY = np.finfo(np.float64).tiny


def _scan(p, reverse, scales):
    """link_hmm._scan on one model's entries p (4, R) in place; the divisors of each level in
    ``scales`` (levels, R) when given (the forward scan's: their logs are summed later)."""
    n = p.shape[1]
    tmp = np.empty((4, n))
    d = 1
    level = 0
    while d < n:
        for k in range(n - d):
            a0, a1, a2, a3 = p[0, k], p[1, k], p[2, k], p[3, k]
            b0, b1, b2, b3 = p[0, k + d], p[1, k + d], p[2, k + d], p[3, k + d]
            tmp[0, k] = a0 * b0 + a1 * b2
            tmp[1, k] = a0 * b1 + a1 * b3
            tmp[2, k] = a2 * b0 + a3 * b2
            tmp[3, k] = a2 * b1 + a3 * b3
        off = 0 if reverse else d
        for k in range(n - d):
            for e in range(4):
                p[e, k + off] = tmp[e, k]
        for k in range(n):
            s = max(max(p[0, k], p[1, k]), max(p[2, k], p[3, k]))
            s = max(s, _TINY)
            for e in range(4):
                p[e, k] = p[e, k] / s
            if scales.shape[0] > 0:
                scales[level, k] = s
        d *= 2
        level += 1


def _estep(m_o, o_u, l_u, inv, sc_res, sc_blk, sc_scan, p_u, n_u, pf, pb, v0, o_r, lost0, g0,
           xi, occ, hit, last):
    """link_hmm.statistics for S models (their transfer matrices ``m_o`` (S, o, 2, 2)) over U
    run kinds and R >= 1 runs, without its logarithms (:func:`_powers_numpy` and
    :func:`_posteriors_numpy` there): fills the runs' scaled M^L ``p_u``
    (S, U, 2, 2) and upper right blocks ``n_u`` (S, U, ab, 2, 2), the scans' entries ``pf``,
    ``pb`` (S, 4, R), and the divisors: ``sc_res`` (bits, S, U) of the runs' powers (1 where a
    bit is not set), ``sc_blk`` (bits, S, 2) of the squared blocks (1 at the last bit),
    ``sc_scan`` (S, levels, R) of the forward scan; then the posteriors (:func:`_posteriors`)."""
    S = m_o.shape[0]
    R = inv.shape[0]
    U = o_u.shape[0]
    bits = sc_res.shape[0]
    none = np.zeros((0, 0))
    bp = np.empty((2, 2, 2))
    bt = np.empty((2, 4, 2, 2))
    rp = np.empty((U, 2, 2))
    rt = np.empty((U, 4, 2, 2))
    tp = np.empty((2, 2))
    tt = np.empty((4, 2, 2))
    for s in range(S):
        # the blocks [[M, E_ab], [0, M]]: their top left block M and the four top right ones
        bt[:] = 0.0
        for o in range(2):
            for i in range(2):
                for j in range(2):
                    bp[o, i, j] = m_o[s, o, i, j]
            for ab in range(4):
                bt[o, ab, ab // 2, ab % 2] = 1.0
        rp[:] = 0.0
        rt[:] = 0.0
        for u in range(U):
            rp[u, 0, 0] = 1.0
            rp[u, 1, 1] = 1.0
        for k in range(bits):
            for u in range(U):
                if (l_u[u] >> k) & 1:
                    o = o_u[u]
                    sc = _blockmul(rp[u], rt[u], bp[o], bt[o], tp, tt)
                    _divide(tp, tt, sc)
                    rp[u] = tp
                    rt[u] = tt
                    sc_res[k, s, u] = sc
                else:
                    sc_res[k, s, u] = 1.0
            for o in range(2):
                if k + 1 < bits:
                    sc = _blockmul(bp[o], bt[o], bp[o], bt[o], tp, tt)
                    _divide(tp, tt, sc)
                    bp[o] = tp
                    bt[o] = tt
                    sc_blk[k, s, o] = sc
                else:
                    sc_blk[k, s, o] = 1.0
        p_u[s] = rp
        n_u[s] = rt
        for r in range(R):
            u = inv[r]
            pf[s, 0, r] = rp[u, 0, 0]
            pf[s, 1, r] = rp[u, 0, 1]
            pf[s, 2, r] = rp[u, 1, 0]
            pf[s, 3, r] = rp[u, 1, 1]
            for e in range(4):
                pb[s, e, r] = pf[s, e, r]
        _scan(pf[s], False, sc_scan[s])
        _scan(pb[s], True, none)
        _posteriors(s, v0[s], m_o[s], o_r, inv, p_u[s], n_u[s], pf[s], pb[s], lost0, g0, xi,
                    occ, hit, last)


def _posteriors(s, v0, m_o, o_r, inv, p_u, n_u, pf, pb, lost0, g0, xi, occ, hit, last):
    """link_hmm._posteriors_numpy for model ``s``: its gamma_0, xi sums, occupancy, lost
    samples per state and ``last`` (the likelihood before its scale factors) from the runs'
    powers and the scans, every sum in the order written there."""
    R = o_r.shape[0]
    alpha = np.empty((R, 2))
    alpha[0, 0], alpha[0, 1] = v0[0], v0[1]
    for r in range(1, R):
        alpha[r, 0] = v0[0] * pf[0, r - 1] + v0[1] * pf[2, r - 1]
        alpha[r, 1] = v0[0] * pf[1, r - 1] + v0[1] * pf[3, r - 1]
    for r in range(R):
        tot = alpha[r, 0] + alpha[r, 1]
        alpha[r, 0] = alpha[r, 0] / tot
        alpha[r, 1] = alpha[r, 1] / tot
    beta = np.ones((R, 2))
    for r in range(R - 1):
        beta[r, 0] = pb[0, r + 1] + pb[1, r + 1]
        beta[r, 1] = pb[2, r + 1] + pb[3, r + 1]
    for r in range(R):
        mx = max(beta[r, 0], beta[r, 1])
        beta[r, 0] = beta[r, 0] / mx
        beta[r, 1] = beta[r, 1] / mx
    x00 = x01 = x10 = x11 = 0.0
    oc0 = oc1 = h0 = h1 = 0.0
    nr = np.empty((2, 2))
    for r in range(R):
        u = inv[r]
        o = o_r[r]
        z = 0.0
        for i in range(2):
            for j in range(2):
                z += alpha[r, i] * p_u[u, i, j] * beta[r, j]
        for i in range(2):
            for j in range(2):
                acc = 0.0
                for k in range(4):
                    acc += (beta[r, k // 2] * alpha[r, k % 2]) * n_u[u, k, i, j]
                nr[i, j] = acc / z
        x00 += m_o[o, 0, 0] * nr[0, 0]
        x01 += m_o[o, 0, 1] * nr[1, 0]
        x10 += m_o[o, 1, 0] * nr[0, 1]
        x11 += m_o[o, 1, 1] * nr[1, 1]
        c0 = nr[0, 0] * m_o[o, 0, 0] + nr[0, 1] * m_o[o, 1, 0]
        c1 = nr[1, 0] * m_o[o, 0, 1] + nr[1, 1] * m_o[o, 1, 1]
        oc0 += c0
        oc1 += c1
        h0 += c0 * o
        h1 += c1 * o
    xi[s, 0, 0], xi[s, 0, 1], xi[s, 1, 0], xi[s, 1, 1] = x00, x01, x10, x11
    ga = v0[0] * (pb[0, 0] + pb[1, 0])
    gb = v0[1] * (pb[2, 0] + pb[3, 0])
    tot = ga + gb
    g0[s, 0] = ga / tot
    g0[s, 1] = gb / tot
    occ[s, 0] = oc0 + g0[s, 0]
    occ[s, 1] = oc1 + g0[s, 1]
    lo = 1.0 if lost0 else 0.0
    hit[s, 0] = h0 + g0[s, 0] * lo
    hit[s, 1] = h1 + g0[s, 1] * lo
    last[s] = (v0[0] * (pf[0, R - 1] + pf[1, R - 1])
               + v0[1] * (pf[2, R - 1] + pf[3, R - 1]))


def _log_sums(l_u, o_u, log_res, log_blk, log_scan, log_r, lf):
    """The scale factors' logs added up as link_hmm._powers_numpy adds them: ``log_r``
    (S, U) of the runs' powers and ``lf`` (S,) the forward scan's at its last run."""
    bits, S, U = log_res.shape
    levels = log_scan.shape[1]
    R = log_scan.shape[2]
    logs = np.empty(R)
    lg = np.empty(R)
    for s in range(S):
        lb0 = 0.0
        lb1 = 0.0
        for u in range(U):
            log_r[s, u] = 0.0
        for k in range(bits):
            for u in range(U):
                if (l_u[u] >> k) & 1:
                    log_r[s, u] += lb1 if o_u[u] else lb0
                    log_r[s, u] += log_res[k, s, u]
            if k + 1 < bits:
                lb0 = 2.0 * lb0
                lb1 = 2.0 * lb1
                lb0 += log_blk[k, s, 0]
                lb1 += log_blk[k, s, 1]
        for r in range(R):
            logs[r] = 0.0
        d = 1
        for level in range(levels):
            for k in range(R - d):
                lg[k] = logs[k] + logs[k + d]
            for k in range(R - d):
                logs[k + d] = lg[k]
            for r in range(R):
                logs[r] += log_scan[s, level, r]
            d *= 2
        lf[s] = logs[R - 1]


_C1, _C2, _C3 = "f8[::1]", "f8[:, ::1]", "f8[:, :, ::1]"
_I1 = "i8[::1]"
AOT_SIGNATURES = {
    "estep": f"void(f8[:, :, :, ::1], {_I1}, {_I1}, {_I1}, {_C3}, {_C3}, {_C3}, "
             f"f8[:, :, :, ::1], f8[:, :, :, :, ::1], {_C3}, {_C3}, {_C2}, {_I1}, b1, {_C2}, "
             f"{_C3}, {_C2}, {_C2}, {_C1})",
    "log_sums": f"void({_I1}, {_I1}, {_C3}, {_C3}, {_C3}, {_C2}, {_C1})",
}


def build_aot():
    """Compile the two loops ahead of time for this source (``./run setup``; 10-30 s): the next
    process loads them without numba. Needs numba."""
    from train_core import aot
    from train_core.jit import COMPILED, jit

    if not COMPILED:
        raise RuntimeError("compiling ahead of time needs numba (TRAIN_NO_JIT is set or numba "
                           "is missing)")
    _compile_helpers(jit)
    return aot.build("link_estep", [__file__], {"estep": (_estep, AOT_SIGNATURES["estep"]),
                                                "log_sums": (_log_sums,
                                                             AOT_SIGNATURES["log_sums"])})
