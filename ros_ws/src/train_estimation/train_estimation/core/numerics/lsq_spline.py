"""Weighted least-squares B-splines on given knots: ``scipy.interpolate.make_lsq_spline`` (its
QR method: FITPACK's Givens rotations on the banded observation matrix), the spline's values
and its design matrix, through the same compiled FITPACK routines scipy calls, without importing
``scipy.interpolate``.

Importing ``scipy.interpolate`` imports ``scipy.optimize``, ``scipy.linalg``, ``scipy.sparse``
and more: about 0.3 s of CPU, more than a short ``diagnose`` process spends on its splines. The
routines live in one compiled module (``scipy.interpolate._dierckx``) that needs only numpy; it
is loaded from scipy's installation without running the package's ``__init__`` (where
``scipy.interpolate`` is already imported, or that load fails, the package's own module is
used). The calls are those of scipy's Python wrappers, with the same checks before them, so the
coefficients and values are the same bits (tested against ``make_lsq_spline``,
``BSpline.__call__`` and ``BSpline.design_matrix``).

Pure: numpy (and scipy's compiled FITPACK).
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import os
import sys

import numpy as np

_MODULE = "scipy.interpolate._dierckx"
_LOADED = None


def _dierckx():
    """scipy's compiled FITPACK module, loaded once (see the module's docstring)."""
    global _LOADED
    if _LOADED is None:
        mod = sys.modules.get(_MODULE)
        if mod is None and "scipy.interpolate" not in sys.modules:
            mod = _load_alone()
        if mod is None:
            from scipy.interpolate import _dierckx as mod
        _LOADED = mod
    return _LOADED


def _load_alone():
    """The extension module from scipy's ``interpolate`` folder, taken out of sys.modules
    again (the package, imported later, then loads it as its own, bound to the package as
    usual); None where it is not there as expected."""
    try:
        import scipy

        folder = os.path.join(os.path.dirname(scipy.__file__), "interpolate")
        for suffix in importlib.machinery.EXTENSION_SUFFIXES:
            path = os.path.join(folder, "_dierckx" + suffix)
            if os.path.exists(path):
                spec = importlib.util.spec_from_file_location(_MODULE, path)
                mod = importlib.util.module_from_spec(spec)
                spec.loader.exec_module(mod)
                if sys.modules.get(_MODULE) is mod:
                    del sys.modules[_MODULE]
                needed = ("data_matrix", "qr_reduce", "fpback", "evaluate_spline")
                return mod if all(hasattr(mod, f) for f in needed) else None
    except (ImportError, OSError, AttributeError):
        pass
    return None


def _float_array(x) -> np.ndarray:
    """C-contiguous float64, finite (make_lsq_spline's ``check_finite``): ValueError if not."""
    x = np.ascontiguousarray(x, dtype=np.float64)
    if not np.isfinite(x).all():
        raise ValueError("Array must not contain infs or nans.")
    return x


def lsq_coefficients(x, y, t, k: int = 3, w=None) -> np.ndarray:
    """The B-spline coefficients of the weighted least-squares spline of degree ``k`` on the
    knots ``t`` through (x, y) (1-D real ``y``; weights ``w`` multiply the residuals):
    ``make_lsq_spline(x, y, t, k, w).c``. ValueError for the inputs it refuses (non-finite
    values, knots out of order, data outside the base interval, x decreasing)."""
    x, y, t = _float_array(x), _float_array(y), _float_array(t)
    w = np.ones_like(x) if w is None else _float_array(w)
    if x.ndim != 1 or y.ndim != 1:
        raise ValueError("Expect x and y to be 1-D sequences.")
    if x.shape[0] < k + 1:
        raise ValueError("Need more x points.")
    if t.ndim != 1 or np.any(t[1:] - t[:-1] < 0):
        raise ValueError("Expect t to be a 1D strictly increasing sequence.")
    if x.size != y.size or x.size != w.size:
        raise ValueError(f"Shapes of x {x.shape}, y {y.shape} and w {w.shape} are incompatible")
    if k > 0 and np.any((x < t[k]) | (x > t[-k])):
        raise ValueError("Out of bounds: x outside the knots' base interval.")
    if np.any(x[1:] - x[:-1] < 0):
        raise ValueError("Expect x to be a 1D non-decreasing sequence.")
    d = _dierckx()
    yy = y.reshape(-1, 1)
    y_w = yy * w[:, None]
    A, offset, nc = d.data_matrix(x, t, k, w)
    d.qr_reduce(A, offset, nc, y_w)  # in place
    c, _, _ = d.fpback(A, nc, x, yy, t, k, w, y_w)
    return np.ascontiguousarray(c.reshape(t.size - k - 1))


def evaluate(t, c, k: int, x) -> np.ndarray:
    """The spline (knots ``t``, coefficients ``c``, degree ``k``) at ``x``, extrapolated beyond
    the base interval: ``BSpline(t, c, k)(x)``."""
    x = np.asarray(x)
    xs = np.ascontiguousarray(x.ravel(), dtype=np.float64)
    c = np.ascontiguousarray(c, dtype=np.float64)
    out = _dierckx().evaluate_spline(np.ascontiguousarray(t, dtype=np.float64),
                                     c.reshape(c.shape[0], -1), k, xs, 0, True)
    return out.reshape(x.shape)


def design_matrix(x, t, k: int) -> np.ndarray:
    """The B-spline basis of degree ``k`` on the knots ``t`` at ``x`` (inside the base
    interval) as a dense (len(x), len(t) - k - 1) array: ``BSpline.design_matrix(x, t,
    k).toarray()``."""
    x = _float_array(x)
    t = _float_array(t)
    n = t.size - k - 1
    if x.size and (x.min() < t[k] or x.max() > t[n]):
        raise ValueError("Out of bounds: x outside the knots' base interval.")
    data, offsets, _ = _dierckx().data_matrix(x, t, k, np.ones_like(x), False)
    A = np.zeros((x.size, n))
    rows = np.arange(x.size)[:, None]
    cols = np.asarray(offsets, np.int64)[:, None] + np.arange(k + 1)
    A[rows, cols] = data
    A += 0.0  # the sparse matrix's toarray adds its entries to zeros: a -0.0 comes out +0.0
    return A
