"""The costly part of the Gilbert-Elliott E-step (:func:`link_hmm.statistics`) as compiled loops.

``diagnose`` fits the link's hidden chain by EM: some 240 E-steps on a bursty bag, each a few
hundred numpy calls on arrays of a few hundred entries (the runs' block-matrix powers by
squaring, the two scans over the runs), which was a third of the CPU of such a bag. Those two
parts are written here as loops over the models, the runs and the entries (the posteriors from
them stay numpy's: a dozen whole-array calls).

The loops repeat :func:`link_hmm._powers_numpy` operation for operation, so they give its bits
wherever numpy's own arithmetic is what is repeated here:

- a product of two 4x4 blocks (``np.matmul``, BLAS's dgemm) is summed over k = 0..3 in order
  by fused multiply-adds (what OpenBLAS's kernels do on a machine with FMA; :func:`_fma` is
  LLVM's correctly rounded ``fma``), the terms with an exact zero of the blocks' structure left
  out (they add an exact 0: every entry is finite and >= 0);
- the scans' 2x2 products and the scalings are elementwise (no fused operations: numba
  compiles without fast-math);
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

_KERNELS = None  # (powers, log_sums) once loaded; False when there is no compiler
_HELPERS = False  # the helpers below replaced by their compiled forms


def kernels():
    """(the powers-and-scans loop, the log-sum loop) compiled, or None (``TRAIN_NO_JIT``, no
    numba)."""
    global _KERNELS
    if _KERNELS is None:
        from train_core import aot

        mod = aot.load("link_estep", [__file__])
        if mod is not None:
            _KERNELS = (mod.powers, mod.log_sums)
        else:
            jitted = _jitted()
            _KERNELS = jitted if jitted is not None else False
    return _KERNELS or None


def _jitted():
    from train_core.jit import COMPILED, jit

    if not COMPILED:
        return None
    _compile_helpers(jit)
    return jit(_powers), jit(_log_sums)


def _compile_helpers(jit):
    """The fused multiply-add and the helpers the two loops call, as numba compiles them (the
    loops look them up in this module's globals)."""
    global _HELPERS
    if _HELPERS:
        return
    _define_fma()
    g = globals()
    for name in ("_blockmul", "_divide", "_scan"):
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


def _scan(p, reverse, scales):
    """link_hmm._scan on one model's entries p (4, R) in place; the divisors of each level in
    ``scales`` (levels, R) when given (the forward scan's: their logs are summed later)."""
    n = p.shape[1]
    tmp = np.empty((4, n))
    d = 1
    level = 0
    tiny = np.finfo(np.float64).tiny
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
            s = max(s, tiny)
            for e in range(4):
                p[e, k] = p[e, k] / s
            if scales.shape[0] > 0:
                scales[level, k] = s
        d *= 2
        level += 1


def _powers(m_o, o_u, l_u, inv, sc_res, sc_blk, sc_scan, p_u, n_u, pf, pb):
    """link_hmm._powers_numpy for S models (their transfer matrices ``m_o`` (S, o, 2, 2)) over
    U run kinds and R >= 1 runs, without its logarithms: fills the runs' scaled M^L ``p_u``
    (S, U, 2, 2) and upper right blocks ``n_u`` (S, U, ab, 2, 2), the scans' entries ``pf``,
    ``pb`` (4, S, R), and the divisors: ``sc_res`` (bits, S, U) of the runs' powers (1 where a
    bit is not set), ``sc_blk`` (bits, S, 2) of the squared blocks (1 at the last bit),
    ``sc_scan`` (levels, S, R) of the forward scan."""
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
            pf[0, s, r] = rp[u, 0, 0]
            pf[1, s, r] = rp[u, 0, 1]
            pf[2, s, r] = rp[u, 1, 0]
            pf[3, s, r] = rp[u, 1, 1]
            for e in range(4):
                pb[e, s, r] = pf[e, s, r]
        _scan(pf[:, s, :], False, sc_scan[:, s, :])
        _scan(pb[:, s, :], True, none)


def _log_sums(l_u, o_u, log_res, log_blk, log_scan, log_r, lf):
    """The scale factors' logs added up as link_hmm._powers_numpy adds them: ``log_r``
    (S, U) of the runs' powers and ``lf`` (S,) the forward scan's at its last run."""
    bits, S, U = log_res.shape
    levels = log_scan.shape[0]
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
                logs[r] += log_scan[level, s, r]
            d *= 2
        lf[s] = logs[R - 1]


_C1, _C2, _C3 = "f8[::1]", "f8[:, ::1]", "f8[:, :, ::1]"
_I1 = "i8[::1]"
AOT_SIGNATURES = {
    "powers": f"void(f8[:, :, :, ::1], {_I1}, {_I1}, {_I1}, {_C3}, {_C3}, {_C3}, "
              f"f8[:, :, :, ::1], f8[:, :, :, :, ::1], {_C3}, {_C3})",
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
    return aot.build("link_estep", [__file__], {"powers": (_powers, AOT_SIGNATURES["powers"]),
                                                "log_sums": (_log_sums,
                                                             AOT_SIGNATURES["log_sums"])})
