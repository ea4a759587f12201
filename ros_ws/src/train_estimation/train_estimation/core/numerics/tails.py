"""Far tails of test statistics (pure: math and scipy).

Choosing the strongest of several tests by p-value needs the p-values where they are tiny.
The chi-square survival function's log (``scipy.stats.chi2.logsf``) is ``-inf`` once the
survival function underflows (a statistic of about 1,500 with three degrees of freedom), and
every strong test then ties with every other; :func:`chi2_logsf` stays finite there.
"""

from __future__ import annotations

import math

from .special import chdtr, chdtrc, gammaln


def _logsf(x: float, k: float) -> float:
    """log P(chi-square(k) > x) from scipy.special (scipy.stats takes ~1 s to import, and
    every ``diagnose`` run asks for this): log1p of the distribution function where the
    survival function is near 1, its log elsewhere (-inf once it underflows); NaN where
    ``x`` or ``k`` is NaN or ``k <= 0``, as scipy.stats gives."""
    if not (k > 0) or math.isnan(x):
        return math.nan
    if x <= 0:
        return 0.0
    sf = float(chdtrc(k, x))
    if sf > 0.5:
        return math.log1p(-float(chdtr(k, x)))
    return math.log(sf) if sf > 0 else -math.inf


def chi2_logsf(x: float, k: float) -> float:
    """log P(chi-square with ``k`` degrees of freedom > ``x``), finite however far ``x`` lies in
    the tail.

    Where scipy's value is finite it is returned. Beyond, with ``s = k / 2`` and ``z = x / 2``
    (``P = Q(s, z)``, the regularised upper incomplete gamma function), its asymptotic expansion
    (Abramowitz and Stegun 6.5.32) for ``z >> s``::

        Q(s, z) = z^(s-1) e^(-z) / Gamma(s) * (1 + (s-1)/z + (s-1)(s-2)/z^2 + ...)

    summed until a term is below 1e-16 of the sum or starts to grow (the series is asymptotic).
    For even ``k`` the series ends by itself and is exact: ``k = 2`` gives ``-x / 2``.
    """
    x, k = float(x), float(k)
    v = _logsf(x, k)
    if math.isfinite(v) or not (x > 0 and k > 0) or not math.isfinite(x):
        return v
    s, z = 0.5 * k, 0.5 * x
    term = total = 1.0
    for j in range(1, 64):
        nxt = term * (s - j) / z
        if nxt == 0.0 or abs(nxt) < 1e-16 * abs(total) or abs(nxt) > abs(term):
            break
        term = nxt
        total += term
    return (s - 1.0) * math.log(z) - z - float(gammaln(s)) + math.log(total)
