"""Bounded scalar minimisation: Brent's method on an interval (Brent 1973, "Algorithms for
Minimization without Derivatives", ch. 5; Forsythe, Malcolm and Moler's FMIN), golden-section
steps where a parabola through the three best points is not acceptable.

The same arithmetic as ``scipy.optimize.minimize_scalar(method="bounded")`` in the same order
(its points, its tolerances, its step rules): the same evaluations and the same minimum, bit
for bit (tested against scipy). It exists so that a short process (``diagnose``, whose noise
fits are Brent searches) need not import ``scipy.optimize``: about 0.2 s of CPU at start-up,
more than the searches themselves.

Pure: math only.
"""

from __future__ import annotations

import math

_SQRT_EPS = math.sqrt(2.2e-16)
_GOLDEN = 0.5 * (3.0 - math.sqrt(5.0))


def _sign(x: float) -> float:
    """numpy.sign of a float: -1, 0 or +1, NaN for NaN."""
    if x > 0.0:
        return 1.0
    if x < 0.0:
        return -1.0
    return 0.0 if x == 0.0 else math.nan


def _max(a: float, b: float) -> float:
    """numpy.maximum of two floats: NaN if either is NaN."""
    if a != a or b != b:
        return math.nan
    return a if a >= b else b


def minimize_bounded(func, lo: float, hi: float, xatol: float = 1e-5,
                     maxiter: int = 500) -> tuple[float, float, int]:
    """The minimum of ``func`` on [lo, hi]: (x, func(x), evaluations). Stops when the bracket
    around x is within ``xatol`` (plus a relative sqrt(eps) of x) or after ``maxiter``
    evaluations. ``lo`` and ``hi`` must be finite with lo <= hi (ValueError otherwise)."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError("bounds must be finite")
    if lo > hi:
        raise ValueError("the lower bound exceeds the upper bound")
    a, b = lo, hi
    # xf: the best point so far, nfc the second best, fulc the previous second best
    fulc = a + _GOLDEN * (b - a)
    nfc = xf = fulc
    rat = e = 0.0
    x = xf
    fx = func(x)
    num = 1
    ffulc = fnfc = fx
    xm = 0.5 * (a + b)
    tol1 = _SQRT_EPS * abs(xf) + xatol / 3.0
    tol2 = 2.0 * tol1
    while abs(xf - xm) > (tol2 - 0.5 * (b - a)):
        golden = True
        if abs(e) > tol1:  # try a parabola through the three points
            golden = False
            r = (xf - nfc) * (fx - ffulc)
            q = (xf - fulc) * (fx - fnfc)
            p = (xf - fulc) * q - (xf - nfc) * r
            q = 2.0 * (q - r)
            if q > 0.0:
                p = -p
            q = abs(q)
            r = e
            e = rat
            if abs(p) < abs(0.5 * q * r) and p > q * (a - xf) and p < q * (b - xf):
                rat = (p + 0.0) / q  # + 0.0: a -0.0 step is +0.0, as in FMIN
                x = xf + rat
                if (x - a) < tol2 or (b - x) < tol2:  # too close to a bound
                    rat = tol1 * (_sign(xm - xf) + (1.0 if xm - xf == 0 else 0.0))
            else:
                golden = True
        if golden:
            e = (a - xf) if xf >= xm else (b - xf)
            rat = _GOLDEN * e
        si = _sign(rat) + (1.0 if rat == 0 else 0.0)
        x = xf + si * _max(abs(rat), tol1)
        fu = func(x)
        num += 1
        if fu <= fx:
            if x >= xf:
                a = xf
            else:
                b = xf
            fulc, ffulc = nfc, fnfc
            nfc, fnfc = xf, fx
            xf, fx = x, fu
        else:
            if x < xf:
                a = x
            else:
                b = x
            if fu <= fnfc or nfc == xf:
                fulc, ffulc = nfc, fnfc
                nfc, fnfc = x, fu
            elif fu <= ffulc or fulc == xf or fulc == nfc:
                fulc, ffulc = x, fu
        xm = 0.5 * (a + b)
        tol1 = _SQRT_EPS * abs(xf) + xatol / 3.0
        tol2 = 2.0 * tol1
        if num >= maxiter:
            break
    return xf, fx, num
