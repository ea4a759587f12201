"""Rao-Blackwellised estimation of a braking rate (or any parameter of a linear-Gaussian family).

Joint posterior, Zheng et al. (2015) eq. (8)::

    p(theta_k, x_k | y_{1:k}) = p(x_k | theta_{1:k}, y_{1:k}) p(theta_{1:k} | y_{1:k})

The first factor is a Kalman filter per particle (``batched_kf``, leading particle axis); the
parameter factor is carried by weighted particles ``{theta_i, log w_i}``. All algorithms share one
step (``RaoBlackwellFilter.step``):

1. validate the input (reject with a reason, count it, leave the state untouched);
2. ``informative = family.gate(u, E[x])``: can this step say anything about theta?
3. parameter transition (only if informative and with a reading, at most once per
   ``transition_interval`` of braking; else *frozen*): algorithm specific, see below;
4. KF prediction of every particle with its own ``Phi(theta_i)`` (exact ZOH);
5. log predictive likelihood ``l_i = log N(y; H x_i, S_i)`` (Zheng (12)/(17), Q-GRBPF (5));
   ``log w_i += l_i``, normalised in log space (no underflow: no exp before the max is removed);
6. algorithm specific reduction (pruning / proposal selection), then KF update of survivors;
7. estimate = moments of the Gaussian mixture (mean and covariance of (D, v, a_hat, f) with the
   between-particle spread, law of total covariance), then resampling if the algorithm does.

Algorithms (theta = braking rate f):

* ``DiscreteRBPF`` -- particles on a discrete set, transition matrix ``T[j, m] = p(theta_k =
  v_m | theta_{k-1} = v_j)`` (eq. (5)). ``proposal="prior"``: sample from ``T`` and weight by the
  likelihood (bootstrap). ``proposal="optimal"``: sample from eq. (12),
  ``q(m) ∝ T[j, m] N(y; y_hat(v_m), S(v_m))``, weight with eq. (13),
  ``w ∝ w_prev sum_m T[j, m] N(...)``. Systematic resampling when ``N_eff < ess_frac * N``.
* ``SMA`` -- every particle branches to all values (uniform prior over children), the best
  ``n_keep`` (by weight) are kept when the count exceeds ``q_max`` (Section 3.4).
* ``GSMA`` -- every particle branches only to the group whose member mean is closest to its value;
  default groups: overlapping neighbour triples (Section 3.5); same pruning.
* ``QGRBPF`` -- continuous theta. Guan et al., steps (1)-(6): weights (1), Gaussian moments of the
  parameter posterior (2) (7)-(8), new parameters drawn from ``N(theta_hat, P + Q_theta dt)``
  (3) (9), the KF states paired with them by the paper's search algorithm (5) (17) (see
  ``QGRBPF``), KF update (4) and prediction (6). No weight-based resampling step of its own.
  ``quadrature=True``: the same Gaussian over theta carried by N Gauss-Hermite nodes whose KF
  states are the joint Gaussian's conditional -- no random draw, no resampling, few particles.
* ``RandomWalkRBPF`` -- continuous theta, Gaussian random-walk kernel, systematic resampling:
  the "RBPF" the Q-GRBPF paper compares with.
* ``BrakingKF`` -- one Kalman filter on (D, v, a_hat, a_z, f), f a random walk: the exact
  Bayesian estimator of the braking model (f enters linearly given the known command;
  ``braking_model.augmented_model``), the reference every table compares with.
* ``OracleKF`` -- one Kalman filter told the true theta_k.

**Priors and calibration.** ``prior = (mean, std)``: discrete algorithms draw their
initial values from the Gaussian's mass on each value's cell (``grid_prior``), continuous ones
from the Gaussian (reflected into the bounds); None = the papers' uniform prior. A discrete
value stands for its cell, so each particle carries the cell's variance ``h^2 / 12``
(``cell_variance``) in the reported f variance, and SMA/GSMA form the estimate from *every*
evaluated branch before pruning to the N best (``_after``) -- otherwise the reported f variance
collapses to exactly 0 whenever the survivors share one value. ``merge=True`` (SMA/GSMA) replaces
pruning by merging the particles of each value into one Gaussian (at most values x children KFs
per step).

**Standstill, coasting, traction.** When ``informative`` is False (``BrakingModel.gate``: no
braking command, or standstill) every particle has the same model, so the likelihood is flat in
f *given the same state*; any f transition would only act on the f marginal: a random walk would
spread it step after step, SMA/GSMA branching with top-N pruning would collapse it onto
whichever children sort first, resampling would add Monte-Carlo drift. So the transition is
**frozen**: no sampling, branching, redraw, pruning or resampling; the particles keep their f and
their weights are only multiplied by the (state-dependent) likelihood. The f marginal therefore
holds exactly when the particles' KF states agree, and otherwise changes only by what the data
say about past braking through the states (legitimate evidence, decaying as the states
converge). ``test_braking_filters.py`` checks both.

**Between readings** (outputs between samples, an outage) the same holds while braking: the
transition is the filters' forgetting (tuned for tracking), not the physical rate of change of f
(wear, adhesion: minutes to hours), so a step without a reading is the KF time update alone with
f held, and the due transition comes with the next reading (``RaoBlackwellFilter.step``).

**Bad input** never reaches the state: non-finite command/measurement/variance, bad mask,
non-finite or non-increasing time stamps are rejected with a reason (``Estimate.reason``,
counted in ``filter.rejected``); a numerical failure inside a step (all likelihoods -inf,
non-positive-definite innovation covariance) rejects the step the same way. Steps work on new
arrays and commit at the end (a compiled step writes the filter's buffers only once it has
succeeded), so a rejection cannot leave a half-updated particle set.

Pure: numpy/scipy only; randomness only through the ``rng`` argument.

**Modules.** ``braking_base`` (the common step, ``Estimate``), ``braking_discrete`` (RBPF, SMA,
GSMA, discrete priors), ``braking_continuous`` (Q-GRBPF, random-walk RBPF), ``braking_kf`` (the
exact reference KF and the oracle); ``braking_compiled`` and ``braking_inplace`` (each
algorithm's step as one compiled call on the filter's buffers); this module re-exports the
filters, so importers need one name.
Shared numerics: ``smc`` (log-normalisation, systematic resampling, N_eff), ``batched_kf`` (the
Kalman predict/update over a leading particle axis), ``braking_model`` (the model, its affine
prediction).
"""

from __future__ import annotations

from .braking_base import Estimate, RaoBlackwellFilter
from .braking_continuous import QGRBPF, RandomWalkRBPF
from .braking_discrete import (
    GSMA,
    SMA,
    DiscreteRBPF,
    cell_variance,
    grid_prior,
    neighbour_groups,
    sma_transition,
    sticky_transition,
)
from .braking_kf import BrakingKF, OracleKF

__all__ = [
    "Estimate",
    "RaoBlackwellFilter",
    "DiscreteRBPF",
    "SMA",
    "GSMA",
    "QGRBPF",
    "RandomWalkRBPF",
    "OracleKF",
    "BrakingKF",
    "grid_prior",
    "cell_variance",
    "neighbour_groups",
    "sma_transition",
    "sticky_transition",
]
