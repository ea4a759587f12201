"""Protection levels (pure): the interval that holds the true position except with a stated risk.

What a railway asks of a position source is one interval with a stated risk, as GNSS integrity
monitoring publishes it (Blanch, Walter, Enge et al., "Baseline advanced RAIM user algorithm",
IEEE TAES 2015) and as ETCS states the max and min safe front end. Along the track::

    P( x_true > x + PL_ahead  or  x_true < x - PL_behind,  no ALARM )  <=  P_HMI

with ``P_HMI`` the estimator's integrity risk per estimate (``integrity_risk``, 1e-7 by
default). The alert limit ``AL`` (``alert_limit``) is the widest interval the operation can
use: an estimate is OK when both protection levels are within it, DEGRADED when it is bounded
but wider (the zone controller still bounds the train with it), ALARM when nothing bounds it
(the protection levels are +inf).

**Solution separation.** The estimate ``x`` (the filter's, with its position variance ``s0^2``
after every fault-free widening: a silence, an inconsistency, the odometer's calibration) is the
fault-free solution H0. Each fault the data have not excluded is a hypothesis ``H_i`` carried
beside it as a solution of its own: the truth lies ``shift_i`` from ``x`` with the variance
``s0^2 + extra_i`` (a clock step of the size the held readings imply: the estimate read on
either side of it; the distance's track biased from the filter's; a balise and the odometer
that disagree: the train on the odometer's track or on the balise's). Every solution gets the
same multiplier, the two-sided normal quantile of the risk::

    K = Phi^-1(1 - P_HMI / 2)                               (5.33 for 1e-7)

    PL_ahead  = max_i ( shift_i + K sqrt(s0^2 + extra_i))    (i = 0: shift 0, extra 0)
    PL_behind = max_i (-shift_i + K sqrt(s0^2 + extra_i))

One fault at a time is true (or none), and which one is not known: whichever ``H_j`` it is, the
train lies outside ``[x_j - K s_j, x_j + K s_j]`` with probability ``2 Q(K) = P_HMI``, and the
interval holds that one, so the error leaves it with at most ``P_HMI`` whichever hypothesis
is true; averaged over any prior on the hypotheses it is still at most ``P_HMI``. (Splitting it
evenly over the ``n`` solutions, as if each were certain at once, would count ``n``
probabilities of one and widen every level by ``Phi^-1(1 - P_HMI / 2n) / K``, 5 % with five
solutions, for nothing.)

**Rare faults with a stated prior** (the risk allocation of ARAIM, Blanch, Walter, Enge et al.
2015, in one dimension). A hypothesis that the data raised (a clock step the held readings
imply, a balise and the odometer that disagree) has no prior: it is live because the data point
at it. A fault that is there before any data, such as a balise whose surveyed position is wrong,
has one when its source states it (``Hypothesis.prior``, per hypothesis; 1 = not stated). With
the rare ones ``R`` (prior ``p_j < 1``, at most one of them true, each exclusive of the others)
the risk on each side, ``P_HMI / 2``, is split: the share ``RARE_SHARE`` goes to ``R`` in
equal parts ``a = RARE_SHARE P_HMI / (2 |R|)``, the rest to the others::

    K_N = Phi^-1(1 - (1 - RARE_SHARE) P_HMI / 2)            every hypothesis without a prior
    K_j = Phi^-1(1 - a / p_j)                               a rare one, if p_j > a
    P(miss on a side) <= 1 x Q(K_N) + sum_j p_j Q(K_j) <= P_HMI / 2

A rare fault whose prior is within its share (``p_j <= a``) needs no solution at all: even
certain to miss while it holds, it adds at most ``a`` (ARAIM leaves such faults unmonitored).
The split is fixed, not chosen per estimate (a minimum over allocations chosen after seeing
the solutions would not be a bound at the stated risk); with no rare hypothesis live, or none
stated, ``K_N = K`` and the levels are the ones above. Two rare faults at once are not a
hypothesis: with their priors stated, that is about ``p_i p_j`` (1e-10 at 1e-5 each), well inside
the risk.

Simultaneous faults are not a hypothesis: no solution is carried for them. While two live
hypotheses disagree, the interval covers both: a 0.1 s clock step at 20 m/s costs 2 m of
protection level, not availability, and a doubt whose separation still fits the alert limit
leaves the estimate OK. Which hypotheses are live is the integrity monitor's business
(``integrity.py``: each check's doubt is one of them, dropped when its test clears it).
"""

from __future__ import annotations

import math
from functools import lru_cache
from statistics import NormalDist
from typing import NamedTuple

OK, DEGRADED, ALARM = 0, 1, 2


class Hypothesis(NamedTuple):
    """One fault the data have not excluded, as a solution beside the estimate (a named tuple:
    immutable like a frozen dataclass, and built several times per estimate at a tenth of its
    cost)."""

    name: str  # the check that raised it (``clock``, ``balise``, ``position``, ``origin``)
    shift: float  # m, where it puts the train relative to the estimate (+ ahead)
    extra: float = 0.0  # m^2, its position variance beyond the estimate's
    prior: float = 1.0  # -, its stated prior probability, a rare fault's (module doc); 1 = none
    #   stated (a hypothesis the data raised, or a fault whose source states no rate)


FAULT_FREE = Hypothesis("fault-free", 0.0, 0.0)  # the estimate itself, the first solution

RARE_SHARE = 0.5  # -, the share of the integrity risk allotted to the rare faults whose priors
#   are stated (module doc): half, since a rare fault's solution lies further from the
#   estimate than the fault-free one (it leaves a balise out) and gains most from a smaller
#   multiplier, while the others' multiplier grows from 5.33 to 5.45 at 1e-7


def k_factor(risk: float) -> float:
    """The multiplier of each solution's standard deviation (module doc): the two-sided normal
    quantile of the risk, the same for every solution."""
    if not (0.0 < risk < 1.0):
        raise ValueError(f"integrity risk must be in (0, 1), got {risk!r}")
    return _k(float(risk))


@lru_cache(maxsize=64)
def _k(risk: float) -> float:
    # every estimate asks for the same one or two risks: the quantile is computed once each
    # (NormalDist's inverse is a rational approximation whose evaluation cost a tenth of an
    # estimate's protection levels)
    return NormalDist().inv_cdf(1.0 - risk / 2.0)


def protection_levels(variance: float, hypotheses=(), risk: float = 1e-7
                      ) -> tuple[float, float]:
    """``(PL_ahead, PL_behind)`` in m of an estimate whose fault-free position variance is
    ``variance`` (m^2), with the live ``hypotheses`` (module doc); (inf, inf) when the variance
    is not a finite positive number or a hypothesis is not finite (nothing bounds it)."""
    if not (math.isfinite(variance) and variance > 0.0):
        return math.inf, math.inf
    live = (FAULT_FREE, *hypotheses)
    n_rare = 0
    for h in live:
        if not (math.isfinite(h.shift) and math.isfinite(h.extra) and h.extra >= 0.0
                and 0.0 <= h.prior <= 1.0):
            return math.inf, math.inf
        n_rare += h.prior < 1.0
    k = k_factor(risk) if not n_rare else k_factor((1.0 - RARE_SHARE) * risk)
    share = RARE_SHARE * risk / (2.0 * n_rare) if n_rare else 0.0  # one side's, each
    ahead = behind = 0.0
    for h in live:
        if h.prior < 1.0:
            if h.prior <= share:
                continue  # unmonitored: within its share even if it always missed
            kj = _k(2.0 * share / h.prior)  # one side's tail share / p_j
        else:
            kj = k
        half = kj * math.sqrt(variance + h.extra)
        ahead, behind = max(ahead, h.shift + half), max(behind, -h.shift + half)
    return ahead, behind


def label(ahead: float, behind: float, alert_limit: float, alarm: bool = False) -> int:
    """OK (both protection levels within the alert limit), DEGRADED (bounded, wider) or ALARM
    (``alarm``, or no finite bound)."""
    if alarm or not (math.isfinite(ahead) and math.isfinite(behind)):
        return ALARM
    return OK if max(ahead, behind) <= alert_limit else DEGRADED
