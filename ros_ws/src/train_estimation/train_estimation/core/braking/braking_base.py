"""The common step of the Rao-Blackwellised braking-rate filters (``braking_filters`` gives the
overview and the algorithms).

Joint posterior, Zheng et al. (2015) eq. (8)::

    p(theta_k, x_k | y_{1:k}) = p(x_k | theta_{1:k}, y_{1:k}) p(theta_{1:k} | y_{1:k})

The first factor is a Kalman filter per particle (leading particle axis: the family's own
``predict`` -- ``BrakingModel.predict``, the affine form -- or ``batched_kf.predict``, then
``batched_kf.update``, the one Kalman predict/update of the braking filters); the parameter
factor is carried by weighted particles ``{theta_i, log w_i}`` (``theta``: the family's
parameter vector; for ``BrakingModel`` the braking rate). Weights are normalised in log space
with ``smc.log_normalize``. One step (``RaoBlackwellFilter.step``):

1. validate the input (reject with a reason, count it, leave the state untouched);
2. ``informative = family.gate(u, E[x])``: can this step say anything about theta?
3. parameter transition (only if informative and with a reading, at most once per
   ``transition_interval`` of braking; else *frozen*): algorithm specific;
4. KF prediction of every particle with its own model (exact ZOH);
5. log predictive likelihood ``l_i = log N(y; H x_i, S_i)`` (Zheng (12)/(17), Q-GRBPF (5));
   ``log w_i += l_i``, normalised in log space (no underflow: no exp before the max is removed);
6. algorithm specific reduction (pruning / proposal selection);
7. estimate = moments of the Gaussian mixture (law of total covariance), then resampling /
   pruning / merging if the algorithm does (``_after``).

With numba (``numerics.jit``) steps 3-7 of an algorithm with a fused kernel are one compiled
call (``braking_compiled``: its transition, the particle bank of ``numerics.bank``, its
pruning, merging or resampling, the finiteness check) on the filter's own buffers
(``braking_inplace``: the set read from and written back into preallocated arrays, the
estimate into one flat array that ``Estimate`` reads lazily), with the random numbers drawn
here from ``rng`` as the numpy form draws them; without numba (or ``TRAIN_NO_JIT=1``) the numpy
form below runs, with the same particles for the same seed (``test_bank.py``).

Pure: numpy only; randomness only through the ``rng`` argument.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field, replace

import numpy as np

from ..numerics import bank
from ..numerics.bank import log_normalize
from ..numerics.batched_kf import predict, update
from ..numerics.kalman import _selectors
from . import braking_compiled, braking_inplace
from .braking_model import _CACHE_SIZE

__all__ = ["Estimate", "RaoBlackwellFilter"]


def _wsum(w, a):
    """``sum_i w_i a_i`` over the leading (particle) axis. Not ``w @ a``: numpy hands that to
    OpenBLAS's gemv, which splits it over threads from ~10^4 elements (1350 particles x 16
    covariance entries) and on a loaded machine then waits milliseconds for them (measured:
    GSMA's p99 step 8.4 ms with, 0.64 ms without); einsum's own loop stays in this thread."""
    return np.einsum("n,n...->...", w, a)


def _weights(logw):
    """Weights of a log-weight vector already checked by ``smc.log_normalize``: every ``_Set``
    the step hands on (after ``_reduce``) and every committed one was, so the NaN/inf checks
    are not repeated; the arithmetic is ``log_normalize``'s (equal log-weights give exactly
    equal weights, a single value exactly zero variance)."""
    e = np.exp(logw - logw.max())
    return e / e.sum()


_NAN = float("nan")


class Estimate:
    """Posterior summary after one step (or the last good one, if the step was rejected).

    Fields (read-only by convention, as the frozen record it replaces): ``accepted``;
    ``reason`` ("" if accepted, else why the input was rejected, for the node's log); ``t``
    (s, time of the estimate; None if the filter runs on implicit steps); ``mean (r + d,)``,
    e.g. (D m, v m/s, a_hat m/s^2, f -): report states + parameter; ``cov (r + d, r + d)``,
    the mixture covariance (with the f variance and cross terms); ``x_mean (n,)``, ``x_cov
    (n, n)``: the whole linear state, e.g. (D, v, a_hat, a_z); ``theta_mean (d,)``,
    ``theta_cov (d, d)``; ``n_particles``; ``n_eff``; ``informative`` (the step could inform
    theta: transition not frozen); ``measurement_used``; ``log_evidence`` (log p(y_k |
    y_{1:k-1}); NaN if no measurement).

    A compiled step (``braking_inplace``) writes the moments into one flat array and the
    fields are views of it, made when first read: a step does not pay for the fields its
    caller does not read (building them all was ~4 us of a ~25 us step).
    """

    __slots__ = ("accepted", "reason", "t", "informative", "measurement_used", "_E", "_lay",
                 "_mean", "_cov", "_x_mean", "_x_cov", "_theta_mean", "_theta_cov",
                 "_n_particles", "_n_eff", "_log_evidence")
    FIELDS = ("accepted", "reason", "t", "mean", "cov", "x_mean", "x_cov", "theta_mean",
              "theta_cov", "n_particles", "n_eff", "informative", "measurement_used",
              "log_evidence")

    def __init__(self, accepted, reason, t, mean, cov, x_mean, x_cov, theta_mean, theta_cov,
                 n_particles, n_eff, informative, measurement_used, log_evidence=_NAN):
        self.accepted = accepted
        self.reason = reason
        self.t = t
        self.informative = informative
        self.measurement_used = measurement_used
        self._E = None
        self._mean, self._cov, self._x_mean, self._x_cov = mean, cov, x_mean, x_cov
        self._theta_mean, self._theta_cov = theta_mean, theta_cov
        self._n_particles, self._n_eff, self._log_evidence = n_particles, n_eff, log_evidence

    @classmethod
    def _of(cls, E, lay, informative: bool, used: bool, t) -> Estimate:
        """An accepted step's estimate read from ``E`` (``braking_inplace``'s layout) with
        ``lay = (n, m, r)``: the linear state's size, the mixture's (n + d) and the report's."""
        e = cls.__new__(cls)
        e.accepted = True
        e.reason = ""
        e.t = t
        e.informative = informative
        e.measurement_used = used
        e._E = E
        e._lay = lay
        e._mean = e._cov = e._x_mean = e._x_cov = e._theta_mean = e._theta_cov = None
        e._n_particles = e._n_eff = e._log_evidence = None
        return e

    def _full_cov(self):
        n, m, r = self._lay
        return self._E[m:m + m * m].reshape(m, m)

    @property
    def mean(self) -> np.ndarray:
        v = self._mean
        if v is None:
            n, m, r = self._lay
            o = m + m * m
            v = self._mean = self._E[o:o + r]
        return v

    @property
    def cov(self) -> np.ndarray:
        v = self._cov
        if v is None:
            n, m, r = self._lay
            o = m + m * m + r
            v = self._cov = self._E[o:o + r * r].reshape(r, r)
        return v

    @property
    def x_mean(self) -> np.ndarray:
        v = self._x_mean
        if v is None:
            v = self._x_mean = self._E[:self._lay[0]]
        return v

    @property
    def x_cov(self) -> np.ndarray:
        v = self._x_cov
        if v is None:
            n = self._lay[0]
            v = self._x_cov = self._full_cov()[:n, :n]
        return v

    @property
    def theta_mean(self) -> np.ndarray:
        v = self._theta_mean
        if v is None:
            n, m, _ = self._lay
            v = self._theta_mean = self._E[n:m]
        return v

    @property
    def theta_cov(self) -> np.ndarray:
        v = self._theta_cov
        if v is None:
            n = self._lay[0]
            v = self._theta_cov = self._full_cov()[n:, n:]
        return v

    @property
    def n_particles(self) -> int:
        v = self._n_particles
        if v is None:
            v = self._n_particles = int(self._E[-1])
        return v

    @property
    def n_eff(self) -> float:
        v = self._n_eff
        if v is None:
            v = self._n_eff = float(self._E[-2])
        return v

    @property
    def log_evidence(self) -> float:
        v = self._log_evidence
        if v is None:
            v = self._log_evidence = float(self._E[-3]) if self.measurement_used else _NAN
        return v

    def _replace(self, **changes) -> Estimate:
        """A new estimate with ``changes`` (``dataclasses.replace`` of the frozen record)."""
        kw = {f: getattr(self, f) for f in self.FIELDS}
        kw.update(changes)
        return Estimate(**kw)

    def _copy(self) -> Estimate:
        """A copy whose arrays are copies (the filter's snapshots; FIELDS are the
        constructor's arguments in order)."""
        return Estimate(*[a.copy() if isinstance(a, np.ndarray) else a
                          for a in [getattr(self, f) for f in self.FIELDS]])

    def __repr__(self) -> str:
        return "Estimate(" + ", ".join(f"{f}={getattr(self, f)!r}" for f in self.FIELDS) + ")"


@dataclass
class _Set:
    """The particle set (new arrays each step; committed at the end)."""

    theta: np.ndarray  # (N, d)
    x: np.ndarray  # (N, n)
    P: np.ndarray  # (N, n, n)
    logw: np.ndarray  # (N,) normalised: logsumexp = 0
    idx: np.ndarray | None = None  # (N,) value index (discrete algorithms)
    extra: dict = field(default_factory=dict)


class _Buffers:
    """The particle set of the compiled steps (``braking_inplace``): preallocated arrays
    whose first ``n`` rows are the set, and the ``_Set`` of views of them (one per size)."""

    __slots__ = ("th", "x", "P", "lw", "idx", "discrete", "n", "cur", "views", "arrays")

    def __init__(self, cap: int, n: int, d: int, discrete: bool):
        self.th = np.empty((cap, d))
        self.x = np.empty((cap, n))
        self.P = np.empty((cap, n, n))
        self.lw = np.empty(cap)
        self.idx = np.zeros(cap, dtype=np.int64)
        self.discrete = discrete
        self.n = 0
        self.cur = None
        self.views: dict = {}

    def view(self, N: int) -> _Set:
        """The set of the first N rows (now the filter's set)."""
        v = self.views.get(N)
        if v is None:
            v = _Set(self.th[:N], self.x[:N], self.P[:N], self.lw[:N],
                     self.idx[:N] if self.discrete else None)
            self.views[N] = v
        self.n = N
        self.cur = v
        self.arrays = (v.theta, v.x, v.P, v.logw)
        return v

    def holds(self, s: _Set) -> bool:
        """``s`` is the buffers' current set, none of its arrays replaced."""
        th, x, P, lw = self.arrays
        return s is self.cur and s.x is x and s.P is P and s.theta is th and s.logw is lw


_BANK_REASONS = {bank.NAN_LIK: "numerical failure: NaN likelihood",
                 bank.BAD_WEIGHT: "numerical failure: NaN or +inf log-weight",
                 bank.ALL_INF: "numerical failure: all log-weights are -inf"}
_STEP_REASONS = {**_BANK_REASONS,
                 braking_compiled.NONFINITE: "numerical failure: non-finite particle state"}
_ONE = np.ones(1)  # the braking-rate argument of an informative step (unused: theta is)
# a step without prediction (dt = 0): bank_step's arguments
_NO_PREDICT = (False, *braking_inplace.pack_pred(bank._NO_PREDICT, np.zeros(1)))
_MASKS: dict = {}
_IMMUTABLE = frozenset({tuple, str, int, float, bool, type(None)})  # shared by __deepcopy__
_BAD = (None, None, None, None, None)  # a rejected input's other return values
_ALL_ROWS: dict = {}


def _rows_mask(p: int, value: bool) -> np.ndarray:
    """The read-only mask of ``p`` rows all ``value`` (a step with every row or none), one
    per size: not a new array per step."""
    hit = _MASKS.get((p, value))
    if hit is None:
        hit = np.full(p, value, dtype=bool)
        hit.flags.writeable = False
        _MASKS[p, value] = hit
        _ALL_ROWS[p] = np.arange(p, dtype=np.int64)
    return hit

# ----------------------------------------------------------------------------------------------
# base


class RaoBlackwellFilter:
    """Common step of all algorithms (module docstring). Subclasses override the hooks
    ``_initial_theta``, ``_transition``, ``_reduce`` and ``_after``."""

    name = "rb"
    #: s, minimum time between two parameter transitions (branching, sampling, redraw). 0: every
    #: step (the paper, dt = 1 s). The discrete kernels are *per transition*, so a live node
    #: stepping at every odometer/balise message (10 Hz and irregular) should set this to the
    #: step the kernel was designed for (1.0 s) to keep its meaning independent of the rate.
    transition_interval: float = 0.0

    def __init__(self, family):
        # the compiled kernels' first call (a load from numba's cache): here, not in a node's
        # first callback
        bank.warm_up("bank_step", "update", "log_normalize", "all_finite")
        braking_inplace.warm_up()
        self.family = family
        self.rejected: Counter = Counter()
        self.n_steps = 0
        self._s: _Set | None = None
        self._t: float | None = None
        self._last: Estimate | None = None
        self._since = 0.0  # s since the last parameter transition

    def __deepcopy__(self, memo):
        """A copy for the runner's snapshots (rewinding for a late reading), without
        ``copy.deepcopy``'s generic walk (it was the largest part of a node's callback): the
        particle set, the last estimate, the counters and every writeable array are copied;
        what ``memo`` holds (the shared model family) and read-only arrays are shared; tuples
        are the filter's constants and caches (Gauss-Hermite nodes, report index, compiled
        rows), never changed in place, and are shared; anything else goes through
        ``copy.deepcopy``."""
        import copy

        new = self.__class__.__new__(self.__class__)
        memo[id(self)] = new
        for k, v in self.__dict__.items():
            hit = memo.get(id(v))
            if hit is not None:
                v = hit
            elif type(v) in _IMMUTABLE and k != "_buf":
                pass  # (the last branch's, found before the instance tests: most of them)
            elif isinstance(v, np.ndarray):
                v = v if not v.flags.writeable else v.copy()
            elif isinstance(v, _Set):
                # (an empty extra, the usual one, is a new empty dict: deepcopy's walk for it
                # cost as much as the arrays' copies)
                v = _Set(*[None if a is None else a.copy()
                           for a in (v.theta, v.x, v.P, v.logw, v.idx)],
                         {} if type(v.extra) is dict and not v.extra else copy.deepcopy(v.extra))
            elif isinstance(v, Estimate):
                v = v._copy()
            elif k == "_buf":
                v = None  # the copy makes its own buffers on its first compiled step
            elif isinstance(v, Counter):
                v = Counter(v)
            elif not isinstance(v, (tuple, str, int, float, bool, type(None))):
                v = copy.deepcopy(v, memo)
            new.__dict__[k] = v
        return new

    # -- life cycle ------------------------------------------------------------------------
    def reset(self, x0, P0, rng: np.random.Generator | None = None, theta0=None,
              t0: float | None = None) -> Estimate:
        """Start from ``x_0 ~ N(x0, P0)`` for every particle and parameter particles ``theta0``
        (``(N,)`` or ``(N, d)``), or the algorithm's initial draw with ``rng`` if None."""
        fam = self.family
        x0 = np.asarray(x0, dtype=float).reshape(fam.n)
        P0 = np.asarray(P0, dtype=float).reshape(fam.n, fam.n)
        if not (np.all(np.isfinite(x0)) and np.all(np.isfinite(P0))):
            raise ValueError("reset: x0 and P0 must be finite")
        if np.any(np.linalg.eigvalsh(0.5 * (P0 + P0.T)) < 0):
            raise ValueError("reset: P0 must be positive semi-definite")
        if theta0 is None:
            if rng is None:
                raise ValueError("reset: give theta0 or an rng for the initial draw")
            theta, idx = self._initial_theta(rng)
        else:
            theta, idx = self._theta_from_values(np.asarray(theta0, dtype=float))
        N = theta.shape[0]
        lw0 = self._initial_logw(N) if theta0 is None else None
        self._s = _Set(theta=theta, x=np.repeat(x0[None], N, axis=0),
                       P=np.repeat(P0[None], N, axis=0),
                       logw=np.full(N, -np.log(N)) if lw0 is None else lw0, idx=idx)
        self._t = None if t0 is None else float(t0)
        self.rejected = Counter()
        self.n_steps = 0
        self._since = 0.0
        self._last = self._summary(self._s, True, "", False, False, float("nan"))
        return self._last

    def _theta_from_values(self, values):
        theta = values.reshape(values.shape[0], -1)
        return theta, None

    def _initial_theta(self, rng):
        raise NotImplementedError

    def _initial_logw(self, N):
        """Initial normalised log-weights of the initial draw; None: uniform."""
        return None

    # -- properties ------------------------------------------------------------------------
    @property
    def t(self) -> float | None:
        return self._t

    @property
    def particles(self) -> tuple[np.ndarray, np.ndarray]:
        """``(theta (N, d), log w (N,))`` copies, for tests and diagnostics."""
        return self._s.theta.copy(), self._s.logw.copy()

    def estimate(self) -> Estimate:
        return self._last

    def shift(self, dx: float, dv: float) -> Estimate:
        """Move every particle's (D, v) by ``dx`` m and ``dv`` m/s, covariances unchanged (the
        frame of the readings moved: the odometer's calibration,
        ``online/odometer_scale.py``); the summary moves with them."""
        def moved(a):
            a = np.array(a, dtype=float)
            a[..., :2] += (dx, dv)  # (D, v) lead both the state and the reported mean
            return a

        last = self._last
        self._s = replace(self._s, x=moved(self._s.x))
        self._last = last._replace(mean=moved(last.mean), x_mean=moved(last.x_mean))
        return self._last

    def inflate(self, Q: np.ndarray) -> Estimate:
        """Add ``Q`` (2x2: m^2, m^2/s, m^2/s^2) to every particle's (D, v) covariance: an error
        the readings' frame carries that the model does not (the odometer's scale since the
        last balise, ``online/estimators.py``); the summary's covariances with them."""
        Q = np.asarray(Q, dtype=float)
        P = np.array(self._s.P, dtype=float)
        P[:, :2, :2] += Q
        self._s = replace(self._s, P=P)
        last = self._last
        cov, x_cov = np.array(last.cov, dtype=float), np.array(last.x_cov, dtype=float)
        cov[:2, :2] += Q
        x_cov[:2, :2] += Q
        self._last = last._replace(cov=cov, x_cov=x_cov)
        return self._last

    # -- the step --------------------------------------------------------------------------
    def step(self, a_tar: float, y=None, mask=None, rng: np.random.Generator | None = None, *,
             t: float | None = None, meas_var=None, d: float = 0.0) -> Estimate:
        """Advance to the next measurement time and assimilate ``y``.

        ``a_tar`` (m/s^2): command held since the previous step (ZOH). ``y (3,)``: (D m, v m/s,
        a_z m/s^2) with ``mask (3,)`` bool saying which are measured (None: all; ``y`` None:
        predict only). ``t`` (s): absolute stamp; ``dt = t - t_prev`` (the first stamped step
        after a reset without ``t0`` only updates). Without ``t``, ``dt = family.default_dt()``.
        ``meas_var (3,)``: this step's variances (None: the model's). ``d`` (m/s^2): known extra
        acceleration on v (gradient/resistance; 0 in the paper).
        """
        if self._s is None:
            raise RuntimeError("call reset() first")
        fam = self.family
        reason, dt, y_arr, mask_arr, R, fused = self._validate(a_tar, y, mask, t, meas_var, d)
        if reason:
            return self._reject(reason)
        # the command as a pair of floats (the gate and the compiled step read its entries;
        # the numpy form below makes it an array)
        u = (float(a_tar), float(d))
        s = self._s
        informative = bool(fam.gate(u, self._last.x_mean))
        try:
            # seconds of braking since the last transition: f is only seen, and only forgotten,
            # while the brake acts (a random walk per second of braking, as the KF's; the
            # coasting before a brake application is not charged to it)
            since = self._since + (dt if informative else 0.0)
            # The transition (Zheng eq. (5); Q-GRBPF's redraw, eq. (9), a measurement-update
            # step) is the filters' forgetting, tuned for tracking (stay 0.9 per second), not
            # how fast a braking rate changes (wear, adhesion: minutes to hours; Zheng Section
            # 6: it "changes occasionally and slowly"). It is applied with a reading only: a
            # step without one (an output between readings, an outage) is the KF time update
            # alone, eq. (6), with f held -- forgetting with nothing to learn from would only
            # spread f (SMA's kernel: towards the middle of the value set, moving the predicted
            # stop) or add Monte-Carlo drift to its mean (redraws, sampling). A reading stamped
            # at the time an output already predicted to (dt = 0) takes the due transition.
            due = informative and fused and since > 0 and since >= self.transition_interval
            ok = self.__dict__.get("_fused_flag")  # (_fused_ok, inlined: once per step)
            if ok[1] if ok is not None and ok[0] == self.__dict__.get("_bank_ok") else (
                    self._fused_ok()):
                out = self._fused_step(s, u, dt, since, due, informative, y_arr, mask_arr, R,
                                       fused, t, rng)
                if isinstance(out, str):
                    return self._reject(out)
                s, est = out
                if due:
                    since = 0.0
            else:
                u = np.array(u)
                if due:
                    s = self._transition(s, True, rng, since)
                    since = 0.0
                elif dt > 0:
                    s = self._transition(s, False, rng, dt)
                if self._compiled():
                    s, est = self._bank_step(s, u, dt, informative, y_arr, mask_arr, R, fused,
                                             t)
                    if est.reason:
                        return self._reject(est.reason)
                else:
                    if dt > 0:
                        x, P = self._predict(s, u, dt, informative)
                        s = _Set(s.theta, x, P, s.logw, s.idx, s.extra)
                    x, P, loglik = self._update(s, y_arr, R, mask_arr)
                    if np.isnan(loglik).any():
                        return self._reject("numerical failure: NaN likelihood")
                    s = _Set(s.theta, x, P, s.logw, s.idx, s.extra)
                    s, log_ev = self._reduce(s, loglik, informative, rng)
                    est = self._summary(s, True, "", informative, fused,
                                        log_ev if fused else np.nan, t)
                s = self._after(s, informative, rng)
                if not (s.theta.shape[0] > 0 and bank.all_finite(s.x, s.P, s.theta)):
                    return self._reject("numerical failure: non-finite particle state")
        except (ValueError, np.linalg.LinAlgError) as exc:
            return self._reject(f"numerical failure: {exc}")
        self._s = s
        self._since = since
        if t is not None:
            self._t = float(t)
        self.n_steps += 1
        self._last = est
        return est

    # -- one compiled call per step ---------------------------------------------------------
    def _fused_ok(self) -> bool:
        """Whether :meth:`step` runs this algorithm's whole step as one compiled call
        (``braking_compiled``): the bank step runs compiled (:meth:`_compiled`), the algorithm
        has a fused kernel (:meth:`_fused`) and the family the braking model's affine
        prediction with one parameter."""
        compiled = self._compiled()  # (a test may switch it off: _bank_ok = False)
        ok = self.__dict__.get("_fused_flag")
        if ok is None or ok[0] != compiled:
            fam = self.family
            flag = bool(compiled and type(self)._fused is not RaoBlackwellFilter._fused
                        and hasattr(fam, "bank_pred") and getattr(fam, "d", 0) == 1)
            ok = (compiled, flag)
            self._fused_flag = ok
        return ok[1]

    def _fused_step(self, s, u, dt, since, due, informative, y, mask, R, fused, t, rng):
        """The step's transition, bank, reduction and finiteness check in one compiled call
        on the filter's buffers (:meth:`_fused`, ``braking_inplace``). Returns ``(set,
        estimate)`` or the rejection's reason."""
        buf = self._buf
        if buf is None or not buf.holds(s):
            buf = self._load(s)
        if dt > 0:
            hold = None
            if not informative and hasattr(self.family, "hold_gain"):
                hold = self._hold(u, informative)["hold"]
            # the prediction's arguments, kept for the next step (a command held, the train
            # standing: the same dt and command again)
            key = (dt, u[0], u[1], informative, hold)
            hit = self._pred_last
            if hit is None or hit[0] != key or hit[1] is not self.family.params:
                hit = self._pred_args(key, u, dt, informative, hold)
            pred = hit[2]
        else:
            pred = _NO_PREDICT
        kc = self._kc
        if kc[0] is not self.family.H:  # the family's rows changed: pack them again
            kc = self._pack()
        E = np.empty(self._esize)
        common = (*pred, y, R, kc[3] if mask is kc[2] else np.flatnonzero(mask), E)
        N = buf.n
        draws = self._draws(N, due, rng, since)
        status, N2 = self._fused(kc[1], buf, N, due, informative, common, draws)
        if status == braking_inplace.GROW:  # the same numbers again, into larger buffers
            buf = self._load(buf.view(N), N2)
            status, N2 = self._fused(kc[1], buf, N, due, informative, common, draws)
        if status != bank.OK:
            return _STEP_REASONS[status]
        if informative:
            self._after_fused(buf, N2, E, rng)
        return buf.view(N2), Estimate._of(E, self._lay, informative, fused,
                                          self._t if t is None else float(t))

    _buf = None  # the particle set's buffers (_Buffers), made on the first compiled step
    _pred_last = None

    def _pred_args(self, key, u, dt, informative, hold):
        """The compiled step's prediction arguments ``(do_predict, pi, pf)`` for this dt and
        command, kept for the next step: this dt's packed maps (``braking_inplace.PredPack``,
        made once per dt) with the command's ``B0 u | B1 u`` and braking rate written in."""
        fam = self.family
        fh = _ONE if informative else np.asarray(
            fam.braking_rates(None, u, False, **({} if hold is None else {"hold": hold})),
            dtype=float)
        pred = fam.bank_pred(u, dt)
        bu = pred[6]  # B0 u | B1 u: the only map that depends on the command
        pack = self._per_dt(dt, lambda: braking_inplace.PredPack(pred, fh))
        hit = (key, fam.params, (True, *pack.arrays(bu, fh)))
        self._pred_last = hit
        return hit

    _dt_cache = None  # (family.params, {dt: that dt's packed prediction}): _per_dt

    def _per_dt(self, dt, make):
        """``make()``: the compiled step's packed prediction for ``dt``, made once per dt of
        the family's parameters and kept (bounded, as the model's own caches). Why: a live
        filter meets a few dts (a period's, and the ulps its stamps differ by) while its
        command changes at every step. The tuple is shared with the runner's snapshots
        (``__deepcopy__``): its entries are only added, and never written."""
        params = self.family.params
        c = self._dt_cache
        if c is None or c[0] is not params or len(c[1]) >= _CACHE_SIZE:
            c = self._dt_cache = (params, {})
        hit = c[1].get(dt)
        if hit is None:
            hit = c[1][dt] = make()
        return hit

    def _load(self, s, cap=0):
        """Buffers holding the set ``s`` (a set the filter did not make itself: after a reset,
        a shift, a test's or a snapshot's), at least ``cap`` particles large."""
        N, n = s.x.shape
        d = s.theta.shape[1]
        buf = _Buffers(max(2 * N, cap, 16), n, d, s.idx is not None)
        buf.th[:N] = s.theta
        buf.x[:N] = s.x
        buf.P[:N] = s.P
        buf.lw[:N] = s.logw
        if s.idx is not None:
            buf.idx[:N] = s.idx
        buf.view(N)
        self._buf = buf
        self._fused_layout(self._report_index(n, d)[0], n, n + d)
        return buf

    _kc = None  # (family.H, the packed constants, the all-rows mask, its rows)

    def _fused_layout(self, ri, n, m):
        """The estimate's layout for ``braking_inplace`` (report index ``ri``, ``n`` linear
        states of ``m``) and the packed constants, if not packed yet for these rows."""
        self._ri_fused = ri
        self._lay = (n, m, ri.size)
        self._esize = braking_inplace.e_size(m, ri.size)
        if self._kc is None or self._kc[0] is not self.family.H:
            self._pack()

    def _pack(self):
        """The compiled step's constants (``braking_inplace.pack_const``: the family's rows,
        the report index, the algorithm's tables), with the all-rows mask and its rows."""
        fam = self.family
        H, sel = self._bank_rows()
        p = H.shape[0]
        self._kc = (fam.H, braking_inplace.pack_const(H, sel, self._ri_fused, *self._tables()),
                    _rows_mask(p, True), _ALL_ROWS[p])
        return self._kc

    def _tables(self):
        """``(floats, ints)``: this algorithm's constant tables, in the order its compiled
        step reads them (``braking_inplace``)."""
        return (), ()

    def _draws(self, N, due, rng, tdt):
        """The random numbers this step's kernel needs, drawn from ``rng`` as the numpy form
        draws them (N particles; the transition ``due`` over ``tdt`` seconds)."""
        return ()

    def _fused(self, kc, buf, N, due, informative, common, draws):
        """This algorithm's compiled step (``braking_inplace``) with its constants ``kc`` on
        the buffers ``buf`` holding N particles: its transition if ``due``, the bank with the
        prediction, update and estimate arguments ``common``, its reduction. Returns
        ``(status, N')``. Not here: the base class has none."""
        raise NotImplementedError

    def _after_fused(self, buf, N, E, rng) -> None:
        """After an informative compiled step (the RBPFs: resampling)."""

    def _resample_if(self, buf, N, E, rng, ess_frac):
        """Systematic resampling of a compiled step's set in place when ``N_eff < ess_frac N``
        (the RBPFs' ``_after``; the uniform drawn only then, as there)."""
        if E[-2] >= ess_frac * N:
            return
        U = rng.random((1, 1))
        hit = self.__dict__.get("_lwn_rs")  # -log N (numpy's log, as the numpy form's)
        if hit is None or hit[0] != N:
            hit = self._lwn_rs = (N, -np.log(N))
        braking_inplace.resample_run(float(U[0, 0]), hit[1], buf.th, buf.x, buf.P, buf.lw,
                                     buf.idx, N, buf.discrete)

    # -- the compiled step ------------------------------------------------------------------
    #: this class's _reduce is the base class's log-space reweighting (subclasses whose own
    #: _reduce only delegates to it, e.g. DiscreteRBPF with the prior proposal, set it True)
    _base_reduce = False

    def _compiled(self) -> bool:
        """Whether :meth:`step` runs the compiled bank step (``numerics.bank``): numba is there
        and this algorithm's reweighting and summary are the base class's (the kernel's)."""
        ok = self.__dict__.get("_bank_ok")
        if ok is None:
            cls = type(self)
            ok = bool(bank.COMPILED and cls._summary is RaoBlackwellFilter._summary
                      and (cls._reduce is RaoBlackwellFilter._reduce or self._base_reduce))
            self._bank_ok = ok
        return ok

    def _bank_step(self, s, u, dt, informative, y, mask, R, fused, t):
        """Prediction, update, reweighting and the mixture's moments in one compiled call
        (``numerics.bank.bank_step``, the same arithmetic as the numpy form: ``_predict``,
        ``batched_kf.update``, ``_reduce``, ``_summary``). Returns ``(set, estimate)``; the
        estimate's ``reason`` is the numpy form's rejection, if any."""
        fam = self.family
        pred = f = None
        if dt > 0:
            if hasattr(fam, "bank_maps"):
                pred, f = fam.bank_maps(s.theta, u, dt, informative,
                                        **self._hold(u, informative))
            else:
                x, P = self._predict(s, u, dt, informative)
                s = _Set(s.theta, x, P, s.logw, s.idx, s.extra)
        H, sel = self._bank_rows()
        tv = self._theta_var(s)
        status, x, P, lw, w, mean, cov, logz, ess = bank.bank_step(
            np.ascontiguousarray(s.x), np.ascontiguousarray(s.P), y[None], H,
            np.ascontiguousarray(R, dtype=float), np.flatnonzero(mask), sel,
            np.ascontiguousarray(s.logw), np.ascontiguousarray(s.theta),
            None if tv is None else np.ascontiguousarray(tv), pred, f)
        if status != bank.OK:
            return s, self._last._replace(reason=_BANK_REASONS[status])
        s = _Set(s.theta, x, P, lw, s.idx, s.extra)
        self._step_w = (lw, w, ess)  # for _after's N_eff test (weights_ess)
        n = x.shape[1]
        est = self._estimate(mean, cov, n, x.shape[0], ess, informative, fused,
                             logz if fused else np.nan, t)
        return s, est

    def _update(self, s, y, R, mask):
        """``batched_kf.update`` of every particle: compiled (``numerics.bank.update``, the
        same states bit for bit) when numba is there."""
        if not bank.COMPILED:
            return update(s.x, s.P, y, self.family.H, R, mask)
        rows = np.flatnonzero(mask)
        if rows.size == 0:
            return s.x, s.P, np.zeros(s.x.shape[0])
        H, sel = self._bank_rows()
        return bank.update(s.x, s.P, y[None], H, R, rows, sel)

    def weights_ess(self, s: _Set):
        """Normalised weights of ``s`` and ``N_eff = 1 / sum w^2``: the ones the compiled step
        computed for this very set if it did, else ``_weights`` (numpy)."""
        hit = self.__dict__.pop("_step_w", None)
        if hit is not None and hit[0] is s.logw:
            return hit[1], hit[2]
        w = _weights(s.logw)
        return w, float(1.0 / np.sum(w * w))

    def _bank_rows(self):
        fam = self.family
        hit = self.__dict__.get("_rows")
        if hit is None or hit[0] is not fam.H:
            H = np.ascontiguousarray(fam.H, dtype=float)
            hit = (fam.H, H, np.array(_selectors(H), dtype=np.int64))
            self._rows = hit
        return hit[1], hit[2]

    def _hold(self, u, informative) -> dict:
        fam = self.family
        if not informative and hasattr(fam, "hold_gain"):
            return {"hold": fam.hold_gain(u, self._last.x_mean,
                                          float(self._last.theta_mean[0]))}
        return {}

    def _validate(self, a_tar, y, mask, t, meas_var, d):
        fam = self.family
        p = fam.H.shape[0]
        bad = _BAD
        try:
            a = float(a_tar)
            dd = float(d)
        except (TypeError, ValueError):
            return ("non-numeric command", *bad)
        if not (math.isfinite(a) and math.isfinite(dd)):
            return (f"non-finite command: a_tar={a_tar!r}, d={d!r}", *bad)
        if t is None:
            dt = float(fam.default_dt())
        else:
            try:
                tf = float(t)
            except (TypeError, ValueError):
                return ("non-numeric time stamp", *bad)
            if not math.isfinite(tf):
                return (f"non-finite time stamp: {t!r}", *bad)
            if self._t is None:
                dt = 0.0
            elif tf < self._t or (tf == self._t and y is None):
                # A reading stamped at the time of the previous step (two sensors sampled at
                # one instant, or a command and a reading of the same cycle) is an update with
                # dt = 0; only an earlier stamp, or an empty step to the same time, is refused.
                return (f"out-of-order or duplicate time stamp: {tf!r} <= {self._t!r}", *bad)
            else:
                dt = tf - self._t
        # (the checks on a few entries as Python scalars: a numpy call per check cost more
        # than the compiled step itself)
        if y is None:
            y_arr = np.zeros(p)
            mask_arr = _rows_mask(p, False)
            fused = False
        else:
            # a new float64 C-contiguous array: the type the compiled steps were built for
            # (a read-only or strided one would be another compilation)
            y_arr = np.array(y, dtype=np.float64)
            if y_arr.ndim != 1:
                y_arr = y_arr.reshape(-1)
            if y_arr.shape != (p,):
                return (f"bad measurement shape: {y_arr.shape} != ({p},)", *bad)
            if mask is None:
                mask_arr = _MASKS.get((p, True))
                if mask_arr is None:
                    mask_arr = _rows_mask(p, True)
                fused = p > 0
                acc = 0.0
                for v in y_arr.tolist():
                    acc += v - v  # 0 for a finite v, NaN for an infinite or NaN one
                finite = acc == 0.0
            else:
                mask_arr = np.asarray(mask, dtype=bool).reshape(-1)
                if mask_arr.shape != (p,):
                    return (f"bad mask shape: {mask_arr.shape} != ({p},)", *bad)
                used = mask_arr.tolist()
                fused = any(used)
                finite = all(math.isfinite(v) for v, k in zip(y_arr.tolist(), used) if k)
            if not finite:
                return (f"non-finite measurement: {y_arr[mask_arr].tolist()}", *bad)
        if meas_var is None:
            R = self.__dict__.get("_r0")
            R = R[1] if R is not None and R[0] is fam.R else self._R0()
        else:
            R = np.array(meas_var, dtype=np.float64).reshape(-1)
            if R.shape != (p,):
                return (f"bad measurement variance shape: {R.shape} != ({p},)", *bad)
            Rm = R[mask_arr].tolist()
            if not all(math.isfinite(v) and v > 0 for v in Rm):
                return (f"non-positive or non-finite measurement variance: {Rm}", *bad)
        if dt == 0.0 and t is None:
            return ("zero default step", *bad)
        return "", dt, y_arr, mask_arr, R, fused

    def _R0(self) -> np.ndarray:
        """The family's measurement variances as a float64 C-contiguous array (kept while the
        family's ``R`` is the same object)."""
        fam = self.family
        hit = self.__dict__.get("_r0")
        if hit is None or hit[0] is not fam.R:
            hit = self._r0 = (fam.R, np.array(fam.R, dtype=np.float64).reshape(-1))
        return hit[1]

    def _reject(self, reason: str) -> Estimate:
        self.rejected[reason.split(":")[0]] += 1
        last = self._last
        return Estimate(False, reason, last.t, last.mean, last.cov, last.x_mean, last.x_cov,
                        last.theta_mean, last.theta_cov, last.n_particles, last.n_eff,
                        last.informative, False, float("nan"))

    def _summary(self, s: _Set, accepted, reason, informative, used, log_ev, t=None) -> Estimate:
        # Moments of the mixture over (x, theta) with per-particle covariance blkdiag(P_i,
        # theta_var_i): law of total covariance, written out so that no (N, n + d, n + d)
        # stack is built (the mean of P_i is one matrix-vector product over the flat P).
        w = _weights(s.logw)
        N, n = s.x.shape
        dth = s.theta.shape[1]
        xm = _wsum(w, s.x)
        tm = _wsum(w, s.theta)
        dx = s.x - xm
        dt_ = s.theta - tm
        wdx = dx * w[:, None]
        c = np.empty((n + dth, n + dth))
        c[:n, :n] = _wsum(w, s.P) + wdx.T @ dx
        c[:n, n:] = wdx.T @ dt_
        c[n:, :n] = c[:n, n:].T
        c[n:, n:] = (dt_ * w[:, None]).T @ dt_
        tv = self._theta_var(s)
        if tv is not None:
            c[n:, n:] += _wsum(w, tv)
        c = 0.5 * (c + c.T)
        m = np.concatenate([xm, tm])
        return self._estimate(m, c, n, N, float(1.0 / np.sum(w * w)), informative, used,
                              log_ev, t, accepted, reason)

    def _estimate(self, m, c, n, N, n_eff, informative, used, log_ev, t=None, accepted=True,
                  reason="") -> Estimate:
        """The ``Estimate`` of the mixture's mean ``m`` and covariance ``c`` over (x, theta)."""
        ri, rix = self._report_index(n, m.size - n)
        return Estimate(accepted, reason, self._t if t is None else float(t), m[ri], c[rix],
                        m[:n], c[:n, :n], m[n:], c[n:, n:], int(N), float(n_eff),
                        bool(informative), bool(used), float(log_ev))

    def _report_index(self, n, dth):
        hit = self.__dict__.get("_ri")
        if hit is None:
            ri = np.array(list(self.family.report_index) + list(range(n, n + dth)), dtype=int)
            hit = (ri, np.ix_(ri, ri))
            self._ri = hit
        return hit

    # -- hooks -----------------------------------------------------------------------------
    def _theta_var(self, s: _Set):
        """Per-particle variance of theta around the particle's value, ``(N, d, d)``, or None
        (point masses)."""
        return None

    def _predict(self, s: _Set, u, dt: float, informative: bool):
        """KF prediction of every particle with this step's model: the family's own
        ``predict`` if it has one (``BrakingModel.predict``: the affine form, no per-particle
        matrices), else ``batched_kf.predict`` on ``family.matrices``. A step that cannot
        inform theta uses one model shared by all particles (``family.hold_gain``)."""
        fam = self.family
        kw = self._hold(u, informative)
        if hasattr(fam, "predict"):
            return fam.predict(s.x, s.P, s.theta, u, dt, informative, **kw)
        return predict(s.x, s.P, *fam.matrices(s.theta, u, dt, informative, **kw))

    def _transition(self, s: _Set, informative: bool, rng, dt: float) -> _Set:
        """Parameter transition before the KF prediction (identity by default / when frozen or
        not due). ``dt``: time the transition covers (since the last one, for random walks)."""
        return s

    def _reduce(self, s: _Set, loglik, informative: bool, rng):
        """Weight by the likelihood (log space); return ``(set, log evidence)``; algorithms
        that prune or select return only the surviving particles."""
        lw = s.logw + loglik
        _, logz = log_normalize(lw)
        return _Set(s.theta, s.x, s.P, lw - logz, s.idx, s.extra), logz

    def _after(self, s: _Set, informative: bool, rng) -> _Set:
        return s
