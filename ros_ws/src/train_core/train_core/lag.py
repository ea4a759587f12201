"""A first-order recurrence on a grid, compiled (pure: numpy, numba when installed).

y[0] = 0, y[k] = a y[k-1] + b x[k-1]: the exact discretisation of a first-order lag (the
actuator's, :func:`train_core.actuator.grid_output`) or of a leaky integral (a brake's heat).
It is the arithmetic of ``scipy.signal.lfilter([0, b], [1, -a], x)`` bit for bit (tested),
without scipy.signal's import, which was 0.4 s of every ``diagnose`` run.

The loop is compiled ahead of time (:mod:`train_core.aot`, :func:`build_aot`) where that was
built for this source, else by numba at the first call (numba's import and type system take
~0.6 s of a short process), else interpreted.
"""

from __future__ import annotations

import numpy as np

_COMPILED = None  # made at the first call


def first_order(x, a: float, b: float) -> np.ndarray:
    """y with y[0] = 0 and y[k] = a y[k-1] + b x[k-1] for k >= 1 (``x`` 1-D, float)."""
    global _COMPILED
    if _COMPILED is None:
        from . import aot

        mod = aot.load("lag", [__file__])
        if mod is not None:
            _COMPILED = mod.first_order
        else:
            from .jit import jit
            _COMPILED = jit(_first_order)
    return _COMPILED(np.ascontiguousarray(x, dtype=float), float(a), float(b))


def _first_order(x, a, b):
    y = np.zeros_like(x)
    for k in range(1, x.shape[0]):
        y[k] = b * x[k - 1] + a * y[k - 1]
    return y


def build_aot():
    """Compile :func:`_first_order` ahead of time for :func:`first_order` (``./run setup``)."""
    from . import aot

    return aot.build("lag", [__file__], {"first_order": (_first_order,
                                                         "f8[::1](f8[::1], f8, f8)")})
