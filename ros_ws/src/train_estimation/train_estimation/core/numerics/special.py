"""The few ``scipy.special`` functions the analysis calls, without importing ``scipy.special``.

Importing ``scipy.special`` sets up its array-API support (``scipy._lib._array_api``, which
imports numpy's testing, f2py and masked-array modules): 0.15-0.19 s of CPU at the start of
every ``diagnose`` process. The functions themselves are numpy ufuncs of one compiled module,
``scipy.special._ufuncs`` (and the two modules of compiled functions it imports), which loads
in about 0.02 s. It is loaded from scipy's ``special`` folder under a bare stand-in for the
package (its ``__init__`` not run), the global import lock held, and the stand-in is removed
again: the compiled modules stay in ``sys.modules``, so ``scipy.special``, imported later,
takes them as its own. The names below are then the very ufunc objects ``scipy.special``
exports (tested), so every value is the same bits. Where ``scipy.special`` is already
imported, or the load fails, the package's own functions are used.

Pure: numpy (and scipy's compiled special functions).
"""

from __future__ import annotations

import importlib
import os
import sys
import types

import numpy as np

_NAMES = ("chdtr", "chdtrc", "chdtri", "fdtrc", "gammaln", "ndtr", "ndtri", "stdtrit",
          "_lambertw")


def _load_alone():
    """scipy.special._ufuncs, loaded without the package's ``__init__``; None where that
    fails (the package is then imported as usual)."""
    import _imp

    import scipy

    _imp.acquire_lock()  # no other thread may import scipy.special while the stand-in is in
    try:
        if "scipy.special" in sys.modules:
            return None
        folder = os.path.join(os.path.dirname(scipy.__file__), "special")
        stand_in = types.ModuleType("scipy.special")
        stand_in.__path__ = [folder]
        stand_in.__package__ = "scipy.special"
        # the compiled modules import their siblings by attribute from ``scipy``
        had = "special" in vars(scipy)
        sys.modules["scipy.special"] = stand_in
        if not had:
            scipy.special = stand_in
        try:
            mod = importlib.import_module("scipy.special._ufuncs")
        except ImportError:
            mod = None
        finally:
            if sys.modules.get("scipy.special") is stand_in:
                del sys.modules["scipy.special"]
            if not had and vars(scipy).get("special") is stand_in:
                del scipy.special
        return mod if mod is not None and all(hasattr(mod, f) for f in _NAMES) else None
    finally:
        _imp.release_lock()


def _ufuncs():
    mod = _load_alone()
    if mod is None:
        from scipy.special import _ufuncs as mod
    return mod


_U = _ufuncs()
chdtr, chdtrc, chdtri, fdtrc = _U.chdtr, _U.chdtrc, _U.chdtri, _U.fdtrc
gammaln, ndtr, ndtri, stdtrit = _U.gammaln, _U.ndtr, _U.ndtri, _U.stdtrit


def lambertw(z, k=0, tol=1e-8):
    """``scipy.special.lambertw``: its two lines on the same compiled function."""
    k = np.asarray(k, dtype=np.dtype("long"))
    return _U._lambertw(z, k, tol)
