"""Compiled scalar loops for the offline analysis (numba, when it is installed).

A Kalman filter's recursion is sequential: each step needs the last one's state, so it cannot
be written as whole-array numpy operations, and a scalar loop in Python costs about 2 us per
event. ``diagnose`` evaluates such a loop some 300 times per bag (the noise fits' searches),
which was 40 % of its time. The few loops that matter are written once, as plain Python on
numpy arrays, and decorated with :func:`jit`: numba compiles them to machine code at their first
call (cached on disk next to the source) with the same IEEE arithmetic (no fast-math, so no
reassociation: the compiled and the interpreted loop agree to the last bit or to rounding,
tested). Without numba the decorator returns the function unchanged and it runs interpreted.

Pure: no ROS; numba is an optional accelerator, not a modelling dependency. It lives in
train_core so that the simulator's model (:func:`train_core.actuator.grid_output`) and the
estimators share it; import it lazily where start-up time matters (numba takes ~0.3 s, and its
type system another 0.3 s at the first call). A short process's loops are also compiled ahead
of time (:mod:`train_core.aot`), which needs no numba at run time.
"""

from __future__ import annotations

import os

try:  # numba is pinned in requirements.txt; TRAIN_NO_JIT=1 runs the loops interpreted
    if os.environ.get("TRAIN_NO_JIT"):
        raise ImportError("TRAIN_NO_JIT is set")
    from numba import njit as _njit
except ImportError:  # pragma: no cover - exercised by the fallback test in a subprocess
    _njit = None

COMPILED = _njit is not None


def jit(fn, inline: bool = False):
    """``fn`` compiled by numba (``nopython``, cached, GIL released), or ``fn`` itself without
    numba. The interpreted original stays reachable as ``.py_func`` in both cases. ``inline``:
    numba puts its body into each compiled caller (its IR, before LLVM: the same operations in
    the same order) instead of calling it, for a small step called per element of a loop."""
    if _njit is None:
        fn.py_func = fn
        return fn
    if inline:
        return _njit(cache=True, nogil=True, inline="always")(fn)
    return _njit(cache=True, nogil=True)(fn)
