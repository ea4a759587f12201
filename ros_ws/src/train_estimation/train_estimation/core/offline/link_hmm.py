"""The radio link as a hidden two-state Markov chain (Gilbert-Elliott), fitted to lost seq numbers.

Model (docs/interfaces.md ``bursty_link``; :mod:`train_core.link` draws it this way): a
hidden state s_k in {good, bad} per odometer sample k; sample k is lost with probability
``loss_good`` or ``loss_bad`` in its state; then the state moves good -> bad with ``p_good_bad``
and bad -> good with ``p_bad_good``. So bursts are not the loss runs themselves: a bad spell may
let some samples through and a good one may lose some.

Fit: Baum-Welch (EM for hidden Markov models; Rabiner 1989, eq. (18)-(27) for the forward and
backward messages, (37)-(40) for the re-estimation). The E-step works on runs: between changes of
the observation the transfer matrix M[i, j] = A[i, j] P(o | j) is constant, so a run of L equal
observations is the matrix power M^L and its sums of posteriors come from one block-matrix power
(:func:`statistics`); powers by squaring are shared by all runs of the same length. The messages
over the runs are prefix and suffix products computed at once by a parallel (Hillis-Steele) scan,
every partial product divided by its largest entry and the log of the divisor carried along (the
scaling of Rabiner's Sec. V.A, per product rather than per step). The cost grows with the number
of loss bursts, not of samples, with no Python loop over either; all starts of a fit run side by
side as a batch. :func:`forward_backward` is the same E-step per sample (the reference the tests
check it against).

EM never decreases the likelihood (Dempster, Laird and Rubin 1977); the M-step keeps every
probability in [EPS, 1 - EPS], which is the exact maximiser of the (concave, per-parameter) EM
objective on that box, so this still holds. The initial state distribution is fitted too (on one
sequence it goes to the state of the first sample).

Identifiability: the labels are arbitrary, so "bad" is the state with the larger loss
probability. Under a Bernoulli link (losses independent, one loss probability) the two states
merge and the transitions are not determined; :func:`fit_link` then reports the Bernoulli
link as the memoryless chain p_good_bad = q, p_bad_good = 1 - q, loss_good = 0, loss_bad = 1
(the state is the loss itself and does not depend on the previous one). Whether the data are
bursty: the likelihood ratio of Gilbert-Elliott against Bernoulli (:func:`lr_test`) has its null
on the boundary of the larger model with the transitions unidentified there, so the chi-square
approximation does not hold and its p-value comes from a parametric bootstrap under the fitted
Bernoulli link (exact, a fit per replicate). The default decision uses the instant, calibrated
likelihood-ratio test of Bernoulli against a Markov chain of the losses (:func:`markov_test`,
chi-square with one degree of freedom), which a bursty link fails.

Pure module: numpy (the E-step compiled by numba where it is there: :mod:`.link_estep`). Inputs
are explicit (the lost/received sequence, ``rng``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from . import link_estep

EPS = 1e-10  # -, every fitted probability stays in [EPS, 1 - EPS]
MIN_SAMPLES = 20  # odometer samples: fewer and the fit is not attempted


@dataclass(frozen=True)
class GilbertElliott:
    """A Gilbert-Elliott link (docs/interfaces.md ``bursty_link`` parameters)."""

    p_good_bad: float  # -, per odometer sample: P(next state bad | good)
    p_bad_good: float  # -, per odometer sample: P(next state good | bad)
    loss_good: float  # -, P(sample lost | good)
    loss_bad: float  # -, P(sample lost | bad)

    @property
    def stationary_bad(self) -> float:
        """-, long-run fraction of samples in the bad state."""
        s = self.p_good_bad + self.p_bad_good
        return 0.0 if s == 0.0 else self.p_good_bad / s

    @property
    def loss_rate(self) -> float:
        """-, long-run fraction of samples lost."""
        pb = self.stationary_bad
        return (1.0 - pb) * self.loss_good + pb * self.loss_bad

    def as_dict(self) -> dict:
        return {"p_good_bad": self.p_good_bad, "p_bad_good": self.p_bad_good,
                "loss_good": self.loss_good, "loss_bad": self.loss_bad}

    @staticmethod
    def bernoulli(q: float) -> GilbertElliott:
        """The Bernoulli link with loss probability q as a (memoryless) two-state chain."""
        return GilbertElliott(q, 1.0 - q, 0.0, 1.0)


@dataclass(frozen=True)
class LinkFit:
    """Result of :func:`fit_link`."""

    params: GilbertElliott  # the link reported (Bernoulli as a memoryless chain when not bursty)
    bursty: bool  # the likelihood-ratio test prefers Gilbert-Elliott to Bernoulli
    hmm: GilbertElliott | None  # the Gilbert-Elliott maximum-likelihood fit (None: not fitted)
    loss_rate: float  # -, fraction of samples lost (the Bernoulli fit)
    n: int  # samples in the sequence (received + lost)
    n_lost: int
    log_likelihood: float  # of ``hmm`` (nan when not fitted)
    log_likelihood_bernoulli: float
    lr: float  # 2 (log L_GE - log L_Bernoulli) >= 0 (nan when not fitted)
    p_value: float  # p-value of the test against Bernoulli (fit_link: which test)
    iterations: int  # EM iterations of the best start
    std_errors: dict = field(default_factory=dict)  # observed-information standard errors of
    # ``hmm``'s parameters off the boundary (name -> -)
    reason: str = ""  # why the Bernoulli link is reported, when it is


# ------------------------------------------------------------------------------------------------
# Data
# ------------------------------------------------------------------------------------------------

def lost_from_seq(seq) -> np.ndarray:
    """Lost indicator (bool, True = lost) of every sample from the first to the last received
    ``seq`` number, in any order, with duplicates, and across the uint32 wrap-around (each step
    between consecutive received numbers is read modulo 2^32 as the shortest signed step).
    Samples before the first and after the last received one cannot be seen and are not in it."""
    s = np.asarray(seq, dtype=np.int64).ravel()
    if s.size == 0:
        return np.zeros(0, dtype=bool)
    step = np.diff(s) % (1 << 32)
    step = np.where(step >= (1 << 31), step - (1 << 32), step)
    k = np.concatenate(([0], np.cumsum(step)))
    k = np.unique(k)
    lost = np.ones(int(k[-1] - k[0]) + 1, dtype=bool)
    lost[k - k[0]] = False
    return lost


def bernoulli_log_likelihood(lost) -> float:
    """Maximised Bernoulli log-likelihood of a lost sequence (0 log 0 = 0)."""
    lost = np.asarray(lost, bool)
    n, m = lost.size, int(lost.sum())
    out = 0.0
    for count in (m, n - m):
        if count:
            out += count * math.log(count / n)
    return out


def simulate(params: GilbertElliott, n: int, rng: np.random.Generator) -> np.ndarray:
    """A lost sequence of ``n`` samples from ``params`` (stationary start; each sample: the
    loss in the current state, then the move, as :class:`train_core.link.Link` draws them)."""
    u = rng.random((n, 2))
    lost = np.empty(n, dtype=bool)
    bad = bool(rng.random() < params.stationary_bad)
    for k in range(n):
        lost[k] = u[k, 0] < (params.loss_bad if bad else params.loss_good)
        bad = (u[k, 1] >= params.p_bad_good) if bad else (u[k, 1] < params.p_good_bad)
    return lost


# ------------------------------------------------------------------------------------------------
# Forward-backward by a scaled parallel scan
# ------------------------------------------------------------------------------------------------

def _mul(a, b):
    """Product of batches of 2x2 matrices given as their four entries (m00, m01, m10, m11)."""
    a00, a01, a10, a11 = a
    b00, b01, b10, b11 = b
    return (a00 * b00 + a01 * b10, a00 * b01 + a01 * b11,
            a10 * b00 + a11 * b10, a10 * b01 + a11 * b11)


def _scan(m, reverse: bool):
    """Inclusive prefix products M_1 ... M_k (``reverse``: suffix products M_k ... M_n) along
    the last axis, each divided by its largest entry; returns (entries, log of the divisors)."""
    p = [x.copy() for x in m]
    logs = np.zeros(p[0].shape)
    n = p[0].shape[-1]
    d = 1
    while d < n:
        new = _mul(tuple(x[..., :-d] for x in p), tuple(x[..., d:] for x in p))
        lg = logs[..., :-d] + logs[..., d:]
        sl = np.s_[..., :-d] if reverse else np.s_[..., d:]
        for x, y in zip(p, new):
            x[sl] = y
        logs[sl] = lg
        s = np.maximum(np.maximum(p[0], p[1]), np.maximum(p[2], p[3]))
        s = np.maximum(s, np.finfo(float).tiny)
        for x in p:
            x /= s
        logs += np.log(s)
        d *= 2
    return p, logs


def _emissions(lost, q):
    """P(o_k | state) for a batch of loss probabilities q (S, 2): (S, n, 2)."""
    return np.where(lost[None, :, None], q[:, None, :], 1.0 - q[:, None, :])


def _transfer(a, e):
    """M_k[i, j] = A[i, j] e_k[j] for k = 1..n-1, entries of shape (S, n - 1)."""
    return (a[:, 0, 0, None] * e[:, 1:, 0], a[:, 0, 1, None] * e[:, 1:, 1],
            a[:, 1, 0, None] * e[:, 1:, 0], a[:, 1, 1, None] * e[:, 1:, 1])


def log_likelihood(lost, pi, a, q) -> np.ndarray:
    """log P(lost sequence) for a batch of models: pi (S, 2), A (S, 2, 2), q (S, 2)."""
    lost = np.asarray(lost, bool)
    e = _emissions(lost, q)
    v0 = pi * e[:, 0, :]
    if lost.size == 1:
        return np.log(v0.sum(axis=1))
    p, logs = _scan(_transfer(a, e), False)
    last = (v0[:, 0] * (p[0][:, -1] + p[1][:, -1]) + v0[:, 1] * (p[2][:, -1] + p[3][:, -1]))
    return np.log(last) + logs[:, -1]


def forward_backward(lost, pi, a, q):
    """E-step for a batch of models: (gamma (S, n, 2), xi sums (S, 2, 2), log-likelihood (S,)).

    gamma[s, k, j] = P(state_k = j | data); xi[s, i, j] = sum_k P(state_k = i, state_k+1 = j |
    data) (Rabiner eq. (27), (37))."""
    lost = np.asarray(lost, bool)
    S, n = pi.shape[0], lost.size
    e = _emissions(lost, q)
    v0 = pi * e[:, 0, :]
    alpha = np.empty((S, n, 2))
    beta = np.ones((S, n, 2))
    alpha[:, 0] = v0
    xi = np.zeros((S, 2, 2))
    if n == 1:
        ll = np.log(v0.sum(axis=1))
    else:
        m = _transfer(a, e)
        pf, lf = _scan(m, False)
        pb, _ = _scan(m, True)
        alpha[:, 1:, 0] = v0[:, 0, None] * pf[0] + v0[:, 1, None] * pf[2]
        alpha[:, 1:, 1] = v0[:, 0, None] * pf[1] + v0[:, 1, None] * pf[3]
        beta[:, :-1, 0] = pb[0] + pb[1]
        beta[:, :-1, 1] = pb[2] + pb[3]
        ll = np.log(alpha[:, -1].sum(axis=1)) + lf[:, -1]
        alpha /= alpha.sum(axis=2, keepdims=True)
        beta /= beta.max(axis=2, keepdims=True)
        # xi_k[i, j] proportional to alpha_{k-1}[i] M_k[i, j] beta_k[j], normalised per k
        x = [alpha[:, :-1, i] * m[2 * i + j] * beta[:, 1:, j] for i in (0, 1) for j in (0, 1)]
        tot = x[0] + x[1] + x[2] + x[3]
        for idx, xx in enumerate(x):
            xi[:, idx // 2, idx % 2] = (xx / tot).sum(axis=1)
    gamma = alpha * beta
    gamma /= gamma.sum(axis=2, keepdims=True)
    return gamma, xi, ll


def _runs_of(lost):
    """Samples 1..n-1 as maximal runs of one observation: (observation (R,), length (R,))."""
    o = np.asarray(lost[1:], np.int8)
    if o.size == 0:
        return o, np.zeros(0, np.int64)
    cut = np.flatnonzero(np.diff(o)) + 1
    starts = np.concatenate(([0], cut))
    lengths = np.diff(np.concatenate((starts, [o.size])))
    return o[starts], lengths


def statistics(lost, pi, a, q):
    """E-step on runs for a batch of models: the sufficient statistics (gamma_0 (S, 2), xi sums
    (S, 2, 2), state occupancy (S, 2), lost samples per state (S, 2), log-likelihood (S,)).

    Equal to :func:`forward_backward` summed over samples, at a cost set by the number of loss
    runs rather than of samples: within a run of L equal observations the transfer matrix M is
    constant, the forward messages are alpha M^r and the backward ones M^(L-1-r) beta, and the
    sums over the run are sum_r M^(L-1-r) C M^r with C = beta alpha -- the upper right block of
    [[M, C], [0, M]]^L (powers by squaring, shared by all runs of the same length and
    observation; all entries are non-negative, so nothing cancels).

    The E-step is loops compiled where numba (or the module it compiled ahead of time) is
    there (:mod:`.link_estep`: the operations of :func:`_powers_numpy` and
    :func:`_posteriors_numpy` in their order, the logarithms by numpy: the same bits where BLAS
    sums a 4x4 product by fused multiply-adds, tested), else those two in numpy."""
    lost = np.asarray(lost, bool)
    S = pi.shape[0]
    e0 = np.where(lost[0], q, 1.0 - q)
    v0 = pi * e0
    o_r, l_r = _runs_of(lost)
    R = o_r.size
    if R == 0:
        g0 = v0 / v0.sum(axis=1, keepdims=True)
        return (g0, np.zeros((S, 2, 2)), g0.copy(), g0 * float(lost[0]),
                np.log(v0.sum(axis=1)))
    # M_o[s, o, i, j] = A[i, j] P(o | j)
    em = np.stack([1.0 - q, q], axis=1)  # (S, o, j)
    m_o = a[:, None, :, :] * em[:, :, None, :]
    key = l_r * 2 + o_r
    uniq, inv = np.unique(key, return_inverse=True)
    inv = inv.ravel()
    o_u, l_u = uniq % 2, uniq // 2
    kern = link_estep.kernels()
    if kern is None:
        p_u, n_u, log_r, pf, pb, lf = _powers_numpy(m_o, o_u, l_u, inv)
        g0, xi, occ, hit, last = _posteriors_numpy(lost, v0, m_o, o_r, inv, p_u, n_u, pf, pb)
    else:
        g0, xi, occ, hit, last, log_r, lf = _estep_compiled(kern, lost, v0, m_o, o_r, o_u, l_u,
                                                            inv)
    ll = np.log(last) + lf + log_r[:, inv].sum(axis=1)
    return g0, xi, occ, hit, ll


def _powers_numpy(m_o, o_u, l_u, inv):
    """The runs' block powers [[M, E_ab], [0, M]]^L by squaring (scaled: their largest entry
    1, the log of the scale in ``log_r``) and the scaled forward and backward scans of the
    runs' M^L: (M^L (S, U, 2, 2), the upper right blocks (S, U, ab, 2, 2), log_r (S, U), the
    scans' entries (4 x (S, R)) forward and backward, the forward scan's log scale at the
    last run (S,))."""
    S, U = m_o.shape[0], l_u.size
    # block matrices per (s, o, ab): [[M, E_ab], [0, M]]
    blk = np.zeros((S, 2, 4, 4, 4))
    blk[..., :2, :2] = m_o[:, :, None]
    blk[..., 2:, 2:] = m_o[:, :, None]
    for ab in range(4):
        blk[:, :, ab, ab // 2, 2 + ab % 2] = 1.0
    log_b = np.zeros((S, 2))
    res = np.broadcast_to(np.eye(4), (S, U, 4, 4, 4)).copy()
    log_r = np.zeros((S, U))
    bits = int(l_u.max()).bit_length()
    for k in range(bits):
        sel = ((l_u >> k) & 1).astype(bool)
        if sel.any():
            res[:, sel] = np.matmul(res[:, sel], blk[:, o_u[sel]])
            log_r[:, sel] += log_b[:, o_u[sel]]
            sc = res[:, sel].max(axis=(2, 3, 4))
            res[:, sel] /= sc[..., None, None, None]
            log_r[:, sel] += np.log(sc)
        if k + 1 < bits:
            blk = np.matmul(blk, blk)
            log_b = 2.0 * log_b
            sc = blk.max(axis=(2, 3, 4))
            blk /= sc[..., None, None, None]
            log_b += np.log(sc)
    p_u = res[:, :, 0, :2, :2]  # M^L (scaled by exp(log_r))
    n_u = res[:, :, :, :2, 2:]  # (S, U, ab, 2, 2): sum_r M^(L-1-r) E_ab M^r, same scale
    p_r = p_u[:, inv]
    entries = (p_r[..., 0, 0], p_r[..., 0, 1], p_r[..., 1, 0], p_r[..., 1, 1])
    pf, lf = _scan(entries, False)
    pb, _ = _scan(entries, True)
    return p_u, n_u, log_r, pf, pb, lf[:, -1]


def _posteriors_numpy(lost, v0, m_o, o_r, inv, p_u, n_u, pf, pb):
    """gamma_0, the xi sums, the occupancy, the lost samples per state and the likelihood
    before its scale factors, from :func:`_powers_numpy`. Every sum in a stated order (over
    (i, j) row by row, over ab, over the runs one after another: ``cumsum``), the order the
    compiled E-step follows, so that the two agree bit for bit whatever the shapes (numpy's
    einsum and sum choose their order by the arrays' layout)."""
    S, R = v0.shape[0], o_r.size
    p_r = p_u[:, inv]
    n_rr = n_u[:, inv]
    alpha = np.empty((S, R, 2))  # forward message entering each run
    alpha[:, 0] = v0
    alpha[:, 1:, 0] = v0[:, 0, None] * pf[0][:, :-1] + v0[:, 1, None] * pf[2][:, :-1]
    alpha[:, 1:, 1] = v0[:, 0, None] * pf[1][:, :-1] + v0[:, 1, None] * pf[3][:, :-1]
    alpha /= alpha.sum(axis=2, keepdims=True)
    beta = np.ones((S, R, 2))  # backward message leaving each run
    beta[:, :-1, 0] = pb[0][:, 1:] + pb[1][:, 1:]
    beta[:, :-1, 1] = pb[2][:, 1:] + pb[3][:, 1:]
    beta /= beta.max(axis=2, keepdims=True)
    z = np.zeros((S, R))  # alpha M^L beta
    for i in range(2):
        for j in range(2):
            z += alpha[..., i] * p_r[..., i, j] * beta[..., j]
    c = beta[:, :, :, None] * alpha[:, :, None, :]  # C[a, b] = beta_a alpha_b
    n_r = np.zeros((S, R, 2, 2))
    for ab in range(4):
        n_r += c[..., ab // 2, ab % 2, None, None] * n_rr[:, :, ab]
    n_r /= z[..., None, None]
    m_r = m_o[:, o_r]  # (S, R, 2, 2)
    xi = np.cumsum(m_r * np.swapaxes(n_r, 2, 3), axis=1)[:, -1]
    occ_r = np.stack([n_r[..., i, 0] * m_r[..., 0, i] + n_r[..., i, 1] * m_r[..., 1, i]
                      for i in range(2)], axis=2)
    beta0 = np.stack([pb[0][:, 0] + pb[1][:, 0], pb[2][:, 0] + pb[3][:, 0]], axis=1)
    g0 = v0 * beta0
    g0 /= g0.sum(axis=1, keepdims=True)
    occ = np.cumsum(occ_r, axis=1)[:, -1] + g0
    hit = np.cumsum(occ_r * o_r[None, :, None], axis=1)[:, -1] + g0 * float(lost[0])
    last = (v0[:, 0] * (pf[0][:, -1] + pf[1][:, -1]) + v0[:, 1] * (pf[2][:, -1] + pf[3][:, -1]))
    return g0, xi, occ, hit, last


def _estep_compiled(kern, lost, v0, m_o, o_r, o_u, l_u, inv):
    """:func:`_powers_numpy` and :func:`_posteriors_numpy` by the compiled loops
    (:mod:`.link_estep`); the logarithms of their scale factors by numpy, added up in numpy's
    order by the second loop: (g0, xi, occ, hit, last, log_r, lf)."""
    estep, log_sums = kern
    f8, i8 = np.float64, np.int64
    S, U, R = m_o.shape[0], l_u.size, inv.size
    bits = int(l_u.max()).bit_length()
    levels = (R - 1).bit_length()
    o_u, l_u, inv, o_r = (np.ascontiguousarray(x, i8) for x in (o_u, l_u, inv, o_r))
    sc_res, sc_blk, sc_scan = np.empty((bits, S, U)), np.empty((bits, S, 2)), np.empty(
        (S, levels, R))
    p_u, n_u = np.empty((S, U, 2, 2)), np.empty((S, U, 4, 2, 2))
    pf, pb = np.empty((S, 4, R)), np.empty((S, 4, R))
    g0, xi, occ, hit, last = (np.empty((S, 2)), np.empty((S, 2, 2)), np.empty((S, 2)),
                              np.empty((S, 2)), np.empty(S))
    estep(np.ascontiguousarray(m_o, f8), o_u, l_u, inv, sc_res, sc_blk, sc_scan, p_u, n_u, pf,
          pb, np.ascontiguousarray(v0, f8), o_r, bool(lost[0]), g0, xi, occ, hit, last)
    log_r, lf = np.empty((S, U)), np.empty(S)
    log_sums(l_u, o_u, np.log(sc_res), np.log(sc_blk), np.log(sc_scan), log_r, lf)
    return g0, xi, occ, hit, last, log_r, lf


def _sums(lost, gamma, xi):
    """The sufficient statistics of :func:`statistics` from per-sample posteriors."""
    return (gamma[:, 0], xi, gamma.sum(axis=1),
            (gamma * np.asarray(lost, bool)[None, :, None]).sum(axis=1))


def _m_step(g0, xi, occ, hit, q_old):
    """Rabiner eq. (40a-c) for the transitions, the initial state and the loss probabilities,
    clipped to [EPS, 1 - EPS] (see the module docstring)."""
    pi = np.clip(g0, EPS, 1.0 - EPS)
    pi /= pi.sum(axis=1, keepdims=True)
    rows = xi.sum(axis=2, keepdims=True)
    a = np.where(rows > 0, xi / np.where(rows > 0, rows, 1.0), 0.5)
    p_gb = np.clip(a[:, 0, 1], EPS, 1.0 - EPS)
    p_bg = np.clip(a[:, 1, 0], EPS, 1.0 - EPS)
    a = _matrix(p_gb, p_bg)
    q = np.where(occ > 0, hit / np.where(occ > 0, occ, 1.0), q_old)  # an empty state keeps q
    return pi, a, np.clip(q, EPS, 1.0 - EPS)


def _matrix(p_gb, p_bg):
    a = np.empty((np.size(p_gb), 2, 2))
    a[:, 0, 0], a[:, 0, 1] = 1.0 - p_gb, p_gb
    a[:, 1, 0], a[:, 1, 1] = p_bg, 1.0 - p_bg
    return a


def baum_welch(lost, pi, a, q, max_iter: int = 500, tol: float = 1e-8,
               prune: tuple[int, float] | None = (40, 10.0)):
    """EM from a batch of starts until the log-likelihood of every start gains less than
    ``tol`` (1 + |log L|) in an iteration. ``prune = (k, d)``: after k iterations a start more
    than d below the best start's log-likelihood is stopped (EM from a poor start creeps; it
    rarely overtakes by that much). Returns (pi, A, q, log-likelihood (S,), history
    (iterations, S): the log-likelihood of the model entering each iteration, iterations done
    per start)."""
    lost = np.asarray(lost, bool)
    pi, a, q = (np.array(x, dtype=float) for x in (pi, a, q))
    hist = []
    done = np.zeros(pi.shape[0], bool)
    iters = np.zeros(pi.shape[0], int)
    ll = None
    for _ in range(max_iter):
        g0, xi, occ, hit, ll = statistics(lost, pi, a, q)
        if hist:
            done |= (ll - hist[-1]) <= tol * (1.0 + np.abs(ll))
        if prune is not None and len(hist) == prune[0]:
            done |= ll < ll.max() - prune[1]
        hist.append(ll)
        if done.all():
            break
        iters += ~done
        pi_n, a_n, q_n = _m_step(g0, xi, occ, hit, q)
        keep = done[:, None]
        pi = np.where(keep, pi, pi_n)
        a = np.where(keep[:, :, None], a, a_n)
        q = np.where(keep, q, q_n)
    else:
        ll = statistics(lost, pi, a, q)[-1]
        hist.append(ll)
    return pi, a, q, ll, np.array(hist), iters


def _starts(lost, n_starts: int, rng: np.random.Generator):
    """Starting points: two from the loss runs (a 0/1 link whose bursts are the runs, and a
    softer one), the rest drawn at random with the bad state lossier."""
    r = float(np.clip(lost.mean(), 0.01, 0.99))
    runs = _runs(lost)
    mean_run = float(runs.mean()) if runs.size else 1.0
    p_bg = float(np.clip(1.0 / max(mean_run, 1.0), 0.02, 0.98))
    p_gb = float(np.clip(r * p_bg / (1.0 - r), 0.001, 0.5))
    starts = [(p_gb, p_bg, 0.01 * r, 0.95), (0.05, 0.3, 0.5 * r, min(0.99, 0.5 + r))]
    while len(starts) < n_starts:
        starts.append((float(rng.uniform(0.002, 0.2)), float(rng.uniform(0.05, 0.9)),
                       float(rng.uniform(0.0, r)), float(rng.uniform(r, 1.0))))
    s = np.array(starts[:max(n_starts, 1)])
    a = _matrix(s[:, 0], s[:, 1])
    q = np.clip(s[:, 2:4], 1e-3, 1.0 - 1e-3)
    pb = s[:, 0] / (s[:, 0] + s[:, 1])
    pi = np.stack([1.0 - pb, pb], axis=1)
    return pi, a, q


def _runs(lost) -> np.ndarray:
    x = np.concatenate(([0], np.asarray(lost, np.int8), [0]))
    d = np.diff(x)
    return np.flatnonzero(d == -1) - np.flatnonzero(d == 1)


def _labelled(a, q) -> GilbertElliott:
    """The fit with "bad" = the state with the larger loss probability."""
    p_gb, p_bg = float(a[0, 1]), float(a[1, 0])
    qg, qb = float(q[0]), float(q[1])
    if qg > qb:
        p_gb, p_bg, qg, qb = p_bg, p_gb, qb, qg
    return GilbertElliott(p_gb, p_bg, qg, qb)


def fit_gilbert_elliott(lost, rng: np.random.Generator, n_starts: int = 6,
                        max_iter: int = 500, tol: float = 1e-8):
    """Maximum-likelihood Gilbert-Elliott link of one lost sequence: (params, log-likelihood,
    iterations, history of the best start). Several starts (:func:`_starts`) run as one batch;
    the best final likelihood wins."""
    lost = np.asarray(lost, bool)
    pi, a, q = _starts(lost, n_starts, rng)
    pi, a, q, ll, hist, iters = baum_welch(lost, pi, a, q, max_iter, tol)
    best = int(np.argmax(ll))
    return _labelled(a[best], q[best]), float(ll[best]), int(iters[best]), hist[:, best]


def _batch_lr(seqs, n_starts: int, max_iter: int, tol: float, rng) -> np.ndarray:
    """LR statistic of each sequence (each sequence's starts run as one batch)."""
    out = np.empty(len(seqs))
    for i, lost in enumerate(seqs):
        pi, a, q = _starts(lost, n_starts, rng)
        *_, ll, _, _ = baum_welch(lost, pi, a, q, max_iter, tol)
        out[i] = 2.0 * max(float(ll.max()) - bernoulli_log_likelihood(lost), 0.0)
    return out


def markov_test(lost) -> tuple[float, float]:
    """Likelihood-ratio test of Bernoulli against a first-order Markov chain of the losses
    themselves (P(lost | previous lost) vs P(lost | previous received)): (statistic, p-value).
    The null is interior here, so the statistic is chi-square with 1 degree of freedom
    (p = erfc(sqrt(x / 2))). A Gilbert-Elliott link with loss_bad > loss_good and
    p_good_bad + p_bad_good < 1 makes losses follow losses more often, which this test sees;
    it is the cheap, calibrated test :func:`fit_link` uses by default."""
    x = np.asarray(lost, bool)
    if x.size < 3:
        return 0.0, 1.0
    prev, nxt = x[:-1], x[1:]
    ll0 = bernoulli_log_likelihood(nxt)
    ll1 = bernoulli_log_likelihood(nxt[prev]) + bernoulli_log_likelihood(nxt[~prev])
    stat = 2.0 * max(ll1 - ll0, 0.0)
    return stat, math.erfc(math.sqrt(stat / 2.0))


def lr_test(lost, lr: float, rng: np.random.Generator, n_boot: int = 99, n_starts: int = 2,
            max_iter: int = 150, tol: float = 1e-7) -> float:
    """Parametric-bootstrap p-value of the likelihood ratio ``lr`` (Gilbert-Elliott against
    Bernoulli) of ``lost``: the fraction of ``n_boot`` Bernoulli sequences (the fitted loss
    probability, the same length) whose own ratio reaches it, (1 + count) / (1 + n_boot)."""
    lost = np.asarray(lost, bool)
    q = float(lost.mean())
    seqs = [rng.random(lost.size) < q for _ in range(n_boot)]
    boot = _batch_lr(seqs, n_starts, max_iter, tol, rng)
    return float((1 + np.sum(boot >= lr - 1e-9)) / (1 + n_boot))


def observed_std_errors(lost, params: GilbertElliott, h: float = 1e-3) -> dict:
    """Standard errors from the observed information (the negative Hessian of the log-
    likelihood, by central differences in logit coordinates, then the delta method) of the
    parameters off the boundary (within 1e-6 of 0 or 1 a parameter is held: its Hessian is
    not defined there). Empty when the information matrix is not positive definite."""
    lost = np.asarray(lost, bool)
    names = ("p_good_bad", "p_bad_good", "loss_good", "loss_bad")
    p = np.array([getattr(params, k) for k in names])
    free = np.flatnonzero((p > 1e-6) & (p < 1.0 - 1e-6))
    if free.size == 0:
        return {}
    th0 = np.log(p / (1.0 - p))
    steps = [np.zeros(4)]
    for i in free:
        for si in (1, -1):
            steps.append(np.eye(4)[i] * si * h)
    pairs = [(i, j) for ii, i in enumerate(free) for j in free[ii + 1:]]
    for i, j in pairs:
        for si in (1, -1):
            for sj in (1, -1):
                steps.append(np.eye(4)[i] * si * h + np.eye(4)[j] * sj * h)
    th = th0[None, :] + np.array(steps)
    pp = 1.0 / (1.0 + np.exp(-th))
    a = _matrix(pp[:, 0], pp[:, 1])
    pb = pp[:, 0] / (pp[:, 0] + pp[:, 1])
    pi = np.stack([1.0 - pb, pb], axis=1)  # the stationary start (the first sample barely counts)
    ll = statistics(lost, pi, a, pp[:, 2:4])[-1]
    f0 = ll[0]
    k = free.size
    hess = np.zeros((k, k))
    pos = {int(i): n for n, i in enumerate(free)}
    idx = 1
    for i in free:
        hess[pos[int(i)], pos[int(i)]] = (ll[idx] - 2 * f0 + ll[idx + 1]) / h**2
        idx += 2
    for i, j in pairs:
        fpp, fpm, fmp, fmm = ll[idx:idx + 4]
        v = (fpp - fpm - fmp + fmm) / (4 * h * h)
        hess[pos[int(i)], pos[int(j)]] = hess[pos[int(j)], pos[int(i)]] = v
        idx += 4
    info = -hess
    try:
        np.linalg.cholesky(info)
    except np.linalg.LinAlgError:
        return {}
    cov = np.linalg.inv(info)
    se_th = np.sqrt(np.diag(cov))
    return {names[i]: float(se_th[pos[int(i)]] * p[i] * (1.0 - p[i])) for i in free}


# ------------------------------------------------------------------------------------------------
# The whole fit
# ------------------------------------------------------------------------------------------------

def fit_link(lost, rng: np.random.Generator, *, alpha: float = 0.01, n_boot: int = 0,
             n_starts: int = 6, max_iter: int = 500) -> LinkFit:
    """Gilbert-Elliott or Bernoulli, whichever the data support, for a lost sequence (see
    :func:`lost_from_seq`).

    The Gilbert-Elliott fit is reported when a test rejects Bernoulli at level ``alpha``: the
    likelihood ratio of the fit against Bernoulli with its bootstrap p-value when ``n_boot`` >
    0 (exact, but every replicate is a fit: seconds each), else :func:`markov_test` (chi-square,
    instant); otherwise the Bernoulli link as a memoryless chain, with the reason. Degenerate
    input (fewer than ``MIN_SAMPLES`` samples, no loss at all, every sample lost) gives the
    Bernoulli link without a fit, with the reason."""
    lost = np.asarray(lost, bool)
    n, m = int(lost.size), int(lost.sum())
    q = m / n if n else 0.0
    llb = bernoulli_log_likelihood(lost)
    nan = math.nan

    def bern(reason, hmm=None, ll=nan, lr=nan, p=nan, iters=0, se=None):
        return LinkFit(GilbertElliott.bernoulli(q), False, hmm, q, n, m, ll, llb, lr, p, iters,
                       se or {}, reason)

    if n < MIN_SAMPLES:
        return bern(f"too short: {n} samples (at least {MIN_SAMPLES})")
    if m == 0:
        return bern("no sample lost")
    if m == n:
        return bern("every sample lost")
    hmm, ll, iters, _ = fit_gilbert_elliott(lost, rng, n_starts, max_iter)
    lr = 2.0 * max(ll - llb, 0.0)
    if n_boot > 0:
        p = lr_test(lost, lr, rng, n_boot)
        test = f"likelihood ratio {lr:.3g} against Bernoulli, bootstrap p = {p:.3g}"
    else:
        stat, p = markov_test(lost)
        test = f"loss-after-loss test {stat:.3g}, p = {p:.3g}"
    se = observed_std_errors(lost, hmm)
    if not p < alpha:
        return bern(f"not bursty: {test} >= {alpha:g}", hmm, ll, lr, p, iters, se)
    return LinkFit(hmm, True, hmm, q, n, m, ll, llb, lr, p, iters, se, "")
