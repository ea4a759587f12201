"""Braking-rate filters on a discrete set of values (Zheng et al. 2015): RBPF with a transition
matrix (Section 3.3), SMA (3.4), GSMA (3.5), plus the discrete prior and cell variance
(``braking_filters`` gives the overview).

Pure: numpy/scipy only; randomness only through the ``rng`` argument.
"""

from __future__ import annotations

import numpy as np
from scipy.special import ndtr

from ..numerics.bank import log_normalize
from ..numerics.smc import systematic_resample
from . import braking_inplace
from .braking_base import RaoBlackwellFilter, _Set

_NO_DRAW = np.zeros(0)  # a step's random numbers when it draws none

__all__ = ["DiscreteRBPF", "SMA", "GSMA", "grid_prior", "cell_variance", "neighbour_groups",
           "sma_transition", "sticky_transition"]


def neighbour_groups(n_values: int) -> list[tuple[int, ...]]:
    """Groups of three overlapping neighbours ``{i-1, i, i+1}``, ``i = 1..M-1`` (Section 3.5).

    With ``M + 1`` values there are ``M - 1`` such groups (the paper says at most ``M - 2``, and
    Section 4 lists eight groups for eleven values, omitting ``{1.0, 0.9, 0.8}`` -- then a particle
    at 1.0 could never stay at 1.0 although f_0 = 1: both slips; we use all ``M - 1``).
    """
    if n_values < 3:
        return [tuple(range(n_values))]
    return [(i - 1, i, i + 1) for i in range(1, n_values - 1)]


def sticky_transition(n_values: int, p_move: float) -> np.ndarray:
    """Transition matrix on an ordered grid: stay with ``1 - p_move``, move to each neighbour
    with ``p_move / 2``; at the two ends the missing neighbour's mass stays (rows sum to one).
    ``p_move = 0`` is the static parameter the paper's RBPF suffers from."""
    T = np.eye(n_values) * (1.0 - p_move)
    for j in range(n_values):
        for m in (j - 1, j + 1):
            if 0 <= m < n_values:
                T[j, m] += p_move / 2.0
            else:
                T[j, j] += p_move / 2.0
    return T


def sma_transition(n_values: int, p_move: float, p_jump: float) -> np.ndarray:
    """SMA's children prior on an ordered grid: ``sticky_transition(n_values, p_move)`` (drift to
    a neighbour) with probability ``1 - p_jump``, a jump to one of the values beyond the
    neighbours (evenly) with ``p_jump``. Every value is a child when ``p_jump > 0`` (SMA's
    branching); rows sum to one. On three values or fewer there is nothing beyond the
    neighbours and the kernel is the sticky one."""
    T = sticky_transition(n_values, p_move)
    if n_values <= 3 or p_jump <= 0:
        return T
    idx = np.arange(n_values)
    far = (np.abs(idx[:, None] - idx[None, :]) > 1).astype(float)
    return (1.0 - p_jump) * T + p_jump * far / far.sum(axis=1, keepdims=True)


# ----------------------------------------------------------------------------------------------
# discrete parameter set


def grid_prior(values, prior) -> np.ndarray:
    """Probabilities of the discrete values under ``prior = (mean, std)``: the Gaussian's mass
    on each value's cell (the half-way points to its neighbours; the outer cells are open, so
    the tails pile on the end values). ``prior`` None: uniform (Zheng Section 4)."""
    v = np.asarray(values, dtype=float).reshape(-1)
    if prior is None:
        return np.full(v.size, 1.0 / v.size)
    m, sd = (float(a) for a in prior)
    if not (np.isfinite(m) and np.isfinite(sd) and sd > 0):
        raise ValueError(f"prior must be a finite (mean, std > 0), got {prior!r}")
    order = np.argsort(v)
    vs = v[order]
    edges = np.concatenate([[-np.inf], 0.5 * (vs[1:] + vs[:-1]), [np.inf]])
    p_sorted = np.diff(ndtr((edges - m) / sd))
    p = np.empty_like(p_sorted)
    p[order] = p_sorted
    if not p.sum() > 0:
        raise ValueError("prior has no mass on the discrete set")
    return p / p.sum()


def cell_variance(values) -> np.ndarray:
    """Variance ``h^2 / 12`` of a uniform spread over each value's cell, ``h`` the distance
    between the half-way points to its neighbours (an end value: twice its inner half-width).
    A discrete value stands for a continuous f anywhere in its cell (Sheppard's correction):
    without it a grid posterior on one value reports std 0 while f can be up to h / 2 away.
    One value: 0 (no grid, nothing to spread)."""
    v = np.asarray(values, dtype=float).reshape(-1)
    if v.size < 2:
        return np.zeros(v.size)
    order = np.argsort(v)
    vs = v[order]
    half = 0.5 * np.diff(vs)
    lo = np.concatenate([[half[0]], half])
    hi = np.concatenate([half, [half[-1]]])
    out = np.empty(v.size)
    out[order] = (lo + hi) ** 2 / 12.0
    return out


class _DiscreteBase(RaoBlackwellFilter):
    def __init__(self, family, values, n_init: int, prior=None, cell_var: bool = True):
        super().__init__(family)
        self.values = np.asarray(values, dtype=float).reshape(-1)
        if self.values.size == 0 or not np.all(np.isfinite(self.values)):
            raise ValueError("values must be a non-empty finite set")
        self.n_init = int(n_init)
        self.prior_p = grid_prior(self.values, prior)
        self.prior = prior
        self._cell_var = cell_variance(self.values) if cell_var else np.zeros(self.values.size)
        self._freeze("values", "prior_p", "_cell_var")

    def _freeze(self, *names: str) -> None:
        """Make the named arrays read-only copies: parameters fixed at construction, which a
        snapshot for rewinding may share rather than copy (``_shared`` in the online
        adapters), and which nothing can then change in place by mistake."""
        for name in names:
            a = np.array(getattr(self, name))
            a.flags.writeable = False
            setattr(self, name, a)

    def _initial_theta(self, rng):
        # Zheng Section 4: initial particles sampled in the discrete space (uniform prior);
        # with ``prior`` = (mean, std) from the Gaussian's mass on each value's cell. Drawn
        # systematically (each value n p or n p + 1 times), not one by one: the particles' f is
        # frozen until the first braking, and an outage there is predicted with their mean.
        # Independent draws put that mean 0.15 / sqrt(250) = 0.01 off the prior's at random
        # (3 m of a 60 s outage's braking distance per 0.01; the RBPF was 14 m off on one seed)
        if self.prior is None:
            idx = rng.integers(0, self.values.size, self.n_init)
        else:
            idx = rng.permutation(systematic_resample(self.prior_p, rng, self.n_init))
        return self.values[idx][:, None], idx

    def _theta_var(self, s):
        if s.idx is None:
            return None
        return self._cell_var[s.idx][:, None, None]

    def _theta_from_values(self, values):
        v = values.reshape(-1)
        idx = np.argmin(np.abs(v[:, None] - self.values[None, :]), axis=1)
        if not np.allclose(self.values[idx], v, rtol=0, atol=1e-12):
            raise ValueError("theta0 must be members of the discrete set")
        return self.values[idx][:, None], idx


class DiscreteRBPF(_DiscreteBase):
    """RBPF on a discrete parameter set (Zheng 3.3), see the module docstring.

    ``transition (M, M)``: per-step kernel (eq. (5)); for variable ``dt`` it is applied per
    step, not per second. ``ess_frac``: resample when ``N_eff < ess_frac * N``.
    """

    name = "rbpf"

    def __init__(self, family, values, transition, n_particles: int = 250,
                 proposal: str = "prior", ess_frac: float = 0.5, prior=None,
                 cell_var: bool = True):
        super().__init__(family, values, n_particles, prior, cell_var)
        T = np.asarray(transition, dtype=float)
        M = self.values.size
        if T.shape != (M, M) or np.any(T < 0) or not np.allclose(T.sum(axis=1), 1.0):
            raise ValueError("transition must be a row-stochastic (M, M) matrix")
        if proposal not in ("prior", "optimal"):
            raise ValueError("proposal must be 'prior' or 'optimal'")
        self.T = T
        self.cdf = np.cumsum(T, axis=1)
        self.cdf[:, -1] = 1.0
        self.proposal = proposal
        self._base_reduce = proposal == "prior"  # _reduce then only delegates to the base's
        self.ess_frac = float(ess_frac)
        # padded children table for the optimal proposal: support of each row
        kmax = int(np.max(np.sum(T > 0, axis=1)))
        self._child = np.zeros((M, kmax), dtype=int)
        self._logp = np.full((M, kmax), -np.inf)
        for j in range(M):  # setup only (M rows), not per particle
            sup = np.flatnonzero(T[j] > 0)
            self._child[j, :sup.size] = sup
            self._child[j, sup.size:] = j  # padding: a valid model, zero prior mass
            self._logp[j, :sup.size] = np.log(T[j, sup])
        self._freeze("T", "cdf", "_child", "_logp")

    def _transition(self, s, informative, rng, dt):
        if not informative:
            return s
        if self.proposal == "prior":
            # theta_k ~ T[theta_{k-1}, :] by inverse CDF, all particles at once
            u = rng.random(s.idx.size)
            idx = np.minimum((self.cdf[s.idx] < u[:, None]).sum(axis=1), self.values.size - 1)
            return _Set(self.values[idx][:, None], s.x, s.P, s.logw, idx)
        # optimal proposal (eq. (12)): branch to the support, choose after the likelihood
        N, kmax = s.idx.size, self._child.shape[1]
        parent = np.repeat(np.arange(N), kmax)
        idx = self._child[s.idx].reshape(-1)
        logp = self._logp[s.idx].reshape(-1)
        return _Set(self.values[idx][:, None], s.x[parent], s.P[parent], s.logw[parent], idx,
                    {"logp": logp, "N": N, "kmax": kmax})

    def _draws(self, N, due, rng, tdt):
        # the numpy form's draws: the transition's uniforms (the resampling's one uniform:
        # _after_fused, only when it resamples)
        return rng.random(N) if due else _NO_DRAW

    def _tables(self):
        return (self.values, self._cell_var, self.cdf), ()

    def _fused(self, kc, buf, N, due, informative, common, draws):
        return braking_inplace.discrete_run(*kc, draws, buf.th, buf.x, buf.P, buf.lw, buf.idx,
                                            N, due, informative, *common)

    def _after_fused(self, buf, N, E, rng):
        self._resample_if(buf, N, E, rng, self.ess_frac)

    def _reduce(self, s, loglik, informative, rng):
        if "logp" not in s.extra:
            return super()._reduce(s, loglik, informative, rng)
        N, kmax = s.extra["N"], s.extra["kmax"]
        lq = (s.extra["logp"] + loglik).reshape(N, kmax)  # log T + log N(y; ...)
        mx = np.max(lq, axis=1, keepdims=True)  # finite: every row has prior mass
        lsum = mx[:, 0] + np.log(np.sum(np.exp(lq - mx), axis=1))  # eq. (13), per parent
        # sample one child per parent from q ∝ exp(lq) (Gumbel-max: exact, vectorised)
        g = rng.gumbel(size=lq.shape)
        choice = np.argmax(np.where(np.isfinite(lq), lq + g, -np.inf), axis=1)
        keep = np.arange(N) * kmax + choice
        lw = s.logw[keep] + lsum
        _, logz = log_normalize(lw)
        out = _Set(s.theta[keep], s.x[keep], s.P[keep], lw - logz, s.idx[keep])
        return out, logz

    def _after(self, s, informative, rng):
        if not informative:
            return s  # frozen: no resampling noise on the f marginal
        N = s.idx.size
        w, ess = self.weights_ess(s)
        if ess >= self.ess_frac * N:
            return s
        a = systematic_resample(w, rng, N)
        return _Set(s.theta[a], s.x[a], s.P[a], np.full(N, -np.log(N)), s.idx[a])


def _merge_by_value(s: _Set, values) -> _Set:
    """Collapse the particles that share a value into one Gaussian (moment matching: weight sum,
    weighted mean, law of total covariance). Particles on one value have the same model from now
    on, so their KF states only differ by their past; merging them keeps the mixture's first two
    moments per value and bounds the particle count by the number of values (GPB1-style)."""
    w, _ = log_normalize(s.logw)
    present = np.flatnonzero(np.bincount(s.idx, weights=w, minlength=values.size) > 0)
    G = (s.idx[None, :] == present[:, None]) * w[None, :]  # (K, N) weights per value
    W = G.sum(axis=1)
    Gn = G / W[:, None]
    x = Gn @ s.x
    dev = s.x[None, :, :] - x[:, None, :]  # (K, N, n)
    P = np.einsum("kj,jab->kab", Gn, s.P) + np.einsum("kj,kja,kjb->kab", Gn, dev, dev)
    lw = np.log(W)
    return _Set(values[present][:, None], x, 0.5 * (P + np.swapaxes(P, -1, -2)),
                lw - log_normalize(lw)[1], present)


class _BranchingFilter(_DiscreteBase):
    """SMA/GSMA: branch every particle to its allowed children, keep the best ``n_keep`` when
    the count exceeds ``q_max`` (Zheng 3.4-3.5). ``kernel[j, m] >= 0``: value j may go to value
    m iff positive; the prior over the children of one parent is the row normalised (uniform
    over the allowed children for a 0/1 kernel, as in the paper)."""

    def __init__(self, family, values, kernel, n_init: int = 50, n_keep: int = 50,
                 q_max: int = 500, prior=None, cell_var: bool = True, merge: bool = False):
        super().__init__(family, values, n_init, prior, cell_var)
        self.merge = bool(merge)
        kernel = np.asarray(kernel, dtype=float)
        M = self.values.size
        if kernel.shape != (M, M) or np.any(kernel < 0) or not np.all((kernel > 0).any(axis=1)):
            raise ValueError("kernel: non-negative (M, M), every value needs an allowed child")
        if not (1 <= n_keep <= q_max):
            raise ValueError("need 1 <= n_keep <= q_max")
        self.allowed = kernel > 0
        with np.errstate(divide="ignore"):
            self._logprior = np.log(kernel / kernel.sum(axis=1, keepdims=True))
        self.n_keep = int(n_keep)
        self.q_max = int(q_max)
        self._freeze("allowed", "_logprior")

    def _tables(self):
        # the children of each value as CSR rows of the allowed kernel
        rows = [np.flatnonzero(r) for r in self.allowed]
        ptr = np.zeros(len(rows) + 1, dtype=np.int64)
        ptr[1:] = np.cumsum([r.size for r in rows])
        return (self.values, self._cell_var, self._logprior), (ptr, np.concatenate(rows))

    def _fused(self, kc, buf, N, due, informative, common, draws):
        return braking_inplace.branching_run(*kc, self.merge, self.q_max, self.n_keep, buf.th,
                                             buf.x, buf.P, buf.lw, buf.idx, N, due,
                                             informative, *common)

    def _transition(self, s, informative, rng, dt):
        if not informative:
            return s
        parent, child = np.nonzero(self.allowed[s.idx])  # all (particle, child value) pairs
        lw = s.logw[parent] + self._logprior[s.idx[parent], child]
        return _Set(self.values[child][:, None], s.x[parent], s.P[parent],
                    lw - log_normalize(lw)[1], child)

    def _initial_theta(self, rng):
        if not self.merge:
            return super()._initial_theta(rng)
        # merged form: one hypothesis per value, weighted by the prior (see _initial_logw)
        idx = np.arange(self.values.size)
        return self.values[:, None], idx

    def _initial_logw(self, N):
        if not self.merge:
            return None
        with np.errstate(divide="ignore"):
            lw = np.log(self.prior_p)
        return lw - log_normalize(lw)[1]

    def _after(self, s, informative, rng):
        # Reduction happens *after* the estimate of this step is formed (base step): the
        # estimate uses every evaluated branch. Pruning before it (as the paper's loop reads)
        # throws away the branches' probability mass and reports a too narrow f posterior --
        # with all kept particles on one value, a variance of exactly 0.
        if not informative:
            return s
        if self.merge:
            return _merge_by_value(s, self.values)
        if s.logw.size > self.q_max:
            # keep the n_keep largest weights, ties to the lower index (the copies of one
            # parent's branch are equal: which copy stays must not depend on a partition's
            # pivots), in index order
            keep = np.sort(np.argsort(-s.logw, kind="stable")[: self.n_keep])
            lw = s.logw[keep] - log_normalize(s.logw[keep])[1]
            return _Set(s.theta[keep], s.x[keep], s.P[keep], lw, s.idx[keep])
        return s


class SMA(_BranchingFilter):
    """Stochastic M-algorithm: every particle branches to every value (Section 3.4), with a
    uniform prior over the children, or ``transition[j, m]`` if given (its support decides the
    children)."""

    name = "sma"

    def __init__(self, family, values, n_init: int = 50, n_keep: int = 50, q_max: int = 500,
                 transition=None, prior=None, cell_var: bool = True, merge: bool = False):
        M = np.asarray(values).size
        kernel = np.ones((M, M)) if transition is None else transition
        super().__init__(family, values, kernel, n_init, n_keep, q_max, prior, cell_var, merge)


class GSMA(_BranchingFilter):
    """Group SMA (Section 3.5): a particle at value ``v`` branches to the members of the group
    whose mean is closest to ``v`` (first such group on ties). ``groups``: lists of value
    indices; default ``neighbour_groups``. Prior over the children: uniform in the group (paper)
    or ``transition`` restricted to the group and renormalised."""

    name = "gsma"

    def __init__(self, family, values, groups=None, n_init: int = 50, n_keep: int = 50,
                 q_max: int = 500, transition=None, prior=None, cell_var: bool = True,
                 merge: bool = False):
        vals = np.asarray(values, dtype=float).reshape(-1)
        groups = neighbour_groups(vals.size) if groups is None else [tuple(g) for g in groups]
        means = np.array([vals[list(g)].mean() for g in groups])
        M = vals.size
        member = np.zeros((M, M))
        closest = np.argmin(np.abs(vals[:, None] - means[None, :]), axis=1)
        for j in range(M):  # setup only
            member[j, list(groups[closest[j]])] = 1.0
        kernel = member if transition is None else member * np.asarray(transition, dtype=float)
        self.groups = groups
        super().__init__(family, vals, kernel, n_init, n_keep, q_max, prior, cell_var, merge)
