"""Braking model of Zheng et al. (2015), eq. (1)-(4), discretised exactly and batched over f.

Continuous model (eq. (4)), state ``x = (D, v, a_hat, a_z)``, input ``a_Tar``::

    dD/dt     = v
    dv/dt     = a_hat + d(t)                                  (2), d = known offset + Omega
    da_hat/dt = -a_hat / tau + (f / tau) (a_z - a_Tar)       (1) with the Pade delay below
    da_z/dt   = -lambda a_z + 2 lambda a_Tar

The transport delay ``e^{-T s}`` is replaced by the first-order Pade approximant
``(lambda - s) / (lambda + s) = -1 + 2 lambda / (s + lambda)``, ``lambda = 2 / T``, so
``a_z = 2 lambda / (s + lambda) a_Tar`` and the delayed command is ``a_z - a_Tar``. Hence
``A[2, 3] = f / tau`` and ``b = (0, 0, -f / tau, 2 lambda)`` exactly as printed in eq. (4).
(Paper slip: eq. (1) writes ``a_Tar(t - tau)``; the delay is ``T``, as the text and eq. (4) say.)

Exact discretisation (zero-order hold on ``a_Tar`` and on the known acceleration offset ``d``)::

    x_{k+1} = Phi(f) x_k + B(f) (a_Tar, d) + w_k,   [Phi B; 0 I] = expm([[A, [b e]]; 0 0] dt).

**f enters affinely, exactly.** ``f`` only scales the single edge ``(a_z, a_Tar) -> a_hat`` of a
cascade that never feeds back into ``a_z`` (``M1 M0^k M1 = 0`` for ``M = M0 + f M1``), so the
matrix exponential has no term of order ``f^2``::

    Phi(f) = Phi(0) + f (Phi(1) - Phi(0)),   B(f) = B(0) + f (B(1) - B(0)).

Two 6x6 ``expm`` per ``dt`` therefore give the exact model of every particle (any number of
distinct, even continuous, f values) with one fused multiply-add: this is what makes the filters
vectorised. ``test_braking_model.py`` checks this against a batched expm and a fine-step RK4.

Process noise. ``Omega`` enters ``v`` only (``E = (0, 1, 0, 0)``). Its columns ``e^{A s} E =
(s, 1, 0, 0)`` do not involve ``f``, so ``Qd`` is the same for every particle. Two readings:

* ``"zoh"`` (paper, Section 4: "Omega_k is the value of the Gaussian at moment k"): one
  acceleration draw ``Omega_k ~ N(0, accel_var)`` held over the step,
  ``Qd = accel_var * g g^T``, ``g = (dt^2/2, dt, 0, 0)``.
* ``"white"`` (dt-consistent, for the live system): white acceleration noise of power spectral
  density ``accel_var`` [m^2/s^3], ``Qd`` by Van Loan (``[[dt^3/3, dt^2/2], [dt^2/2, dt]]``).

An optional ``ahat_var`` adds white noise (PSD) on ``a_hat`` (actuator model error).

Measurement ``y = C x + e``: the paper's ``C`` picks ``(D, v, a_z)``. In the live system ``a_z``
follows from the known command (mask it out), ``D`` comes from odometer distance or a balise and
``v`` from the odometer, at different times: every filter takes a per-step boolean mask over the
three rows and optional per-step variances.

Pure: numpy/scipy only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..numerics.bank import csr
from ..numerics.discretize import van_loan, zoh

__all__ = [
    "BrakingParams",
    "BrakingModel",
    "continuous_matrices",
    "discretize",
    "process_noise",
    "augmented_model",
    "MEAS_NAMES",
]

MEAS_NAMES = ("D", "v", "a_z")  # rows of C, in this order
C_ROWS = np.array([[1.0, 0.0, 0.0, 0.0],
                   [0.0, 1.0, 0.0, 0.0],
                   [0.0, 0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class BrakingParams:
    """Parameters of the braking model (Zheng et al. 2015, Section 4 defaults)."""

    tau: float = 0.4  # s, actuator time constant
    delay: float = 1.2  # s, transport delay T; Pade lambda = 2 / T (1.6667 1/s in the paper)
    dt: float = 1.0  # s, default filter step (paper: 1.0 s)
    accel_var: float = 0.05  # (m/s^2)^2 for "zoh" (Var(Omega) = 0.05), m^2/s^3 PSD for "white"
    noise_model: str = "zoh"  # "zoh" (paper) or "white"
    ahat_var: float = 0.0  # m^2/s^5, PSD of extra white noise on a_hat (0 = none)
    meas_var: tuple[float, float, float] = (0.25, 0.09, 1e-4)  # m^2, (m/s)^2, (m/s^2)^2: D, v, a_z
    standstill_speed: float | None = None  # m/s; |v| at or below with a_Tar <= 0 = standstill
    min_brake: float = 0.0  # m/s^2; braking commands weaker than this do not inform f (a tiny
    #   brake trim during cruising says more about unmodelled resistance than about f)
    #   (None: never; the paper's open-loop toy lets v go negative and must keep estimating f)

    @property
    def lam(self) -> float:
        """1/s, Pade coefficient lambda = 2 / T."""
        return 2.0 / self.delay

    def __post_init__(self):
        for name in ("tau", "delay", "dt"):
            val = getattr(self, name)
            if not (np.isfinite(val) and val > 0):
                raise ValueError(f"BrakingParams.{name} must be finite and > 0, got {val!r}")
        if not (np.isfinite(self.accel_var) and self.accel_var >= 0):
            raise ValueError(f"BrakingParams.accel_var must be >= 0, got {self.accel_var!r}")
        if not (np.isfinite(self.ahat_var) and self.ahat_var >= 0):
            raise ValueError(f"BrakingParams.ahat_var must be >= 0, got {self.ahat_var!r}")
        if self.noise_model not in ("zoh", "white"):
            raise ValueError(f"BrakingParams.noise_model must be 'zoh' or 'white', "
                             f"got {self.noise_model!r}")
        mv = np.asarray(self.meas_var, dtype=float)
        if mv.shape != (3,) or not np.all(np.isfinite(mv)) or np.any(mv <= 0):
            raise ValueError(f"BrakingParams.meas_var must be 3 positive numbers, got {mv!r}")


def continuous_matrices(braking_rate, params: BrakingParams) -> tuple[np.ndarray, np.ndarray]:
    """Eq. (4) for a vector of braking rates: ``A (K, 4, 4)`` and input matrix ``B (K, 4, 2)``.

    Input columns: ``a_Tar`` (``b`` of eq. (4)) and a known acceleration offset on ``v``
    (``E`` of eq. (4): gradient, running resistance; 0 in the paper).
    """
    f = np.atleast_1d(np.asarray(braking_rate, dtype=float))
    K = f.shape[0]
    tau, lam = params.tau, params.lam
    A = np.zeros((K, 4, 4))
    A[:, 0, 1] = 1.0
    A[:, 1, 2] = 1.0
    A[:, 2, 2] = -1.0 / tau
    A[:, 2, 3] = f / tau
    A[:, 3, 3] = -lam
    B = np.zeros((K, 4, 2))
    B[:, 2, 0] = -f / tau
    B[:, 3, 0] = 2.0 * lam
    B[:, 1, 1] = 1.0
    return A, B


def process_noise(params: BrakingParams, dt: float) -> np.ndarray:
    """``Qd (4, 4)`` for one step of length ``dt``; independent of f (see module docstring)."""
    Qd = np.zeros((4, 4))
    if params.noise_model == "zoh":
        g = np.array([0.5 * dt * dt, dt, 0.0, 0.0])
        Qd += params.accel_var * np.outer(g, g)
    else:
        Qd[:2, :2] += params.accel_var * np.array([[dt**3 / 3.0, dt**2 / 2.0],
                                                   [dt**2 / 2.0, dt]])
    if params.ahat_var > 0:
        # Van Loan for white noise on a_hat; A evaluated at f = 0 (the a_hat column of e^{As}
        # never reaches a_z, so f does not matter).
        A, _ = continuous_matrices(0.0, params)
        A = A[0]
        Qc = np.zeros((4, 4))
        Qc[2, 2] = params.ahat_var
        Qd += van_loan(A, Qc, dt)
    return 0.5 * (Qd + Qd.T)


def discretize(braking_rate, params: BrakingParams, dt: float | None = None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact discrete model for a vector of f: ``Phi (K,4,4)``, ``Bd (K,4,2)``, ``Qd (4,4)``.

    Uses the exact affine dependence on f (module docstring); ``numerics.discretize.zoh``, batched
    over f, is the reference.
    """
    dt = params.dt if dt is None else float(dt)
    f = np.atleast_1d(np.asarray(braking_rate, dtype=float))
    P0, P1, B0, B1, Qd = _affine_pieces(params, dt)
    Phi = P0 + f[:, None, None] * P1
    Bd = B0 + f[:, None, None] * B1
    return Phi, Bd, Qd


_CACHE: dict = {}
# entries of _CACHE before it is emptied: a few kinds per dt, and a live filter meets a few
# dts (a period's, and the ulps its stamps differ by); on a drifting train clock or with
# commands on another clock nearly every dt is new, and a bound this small was emptied
# every twenty steps
_CACHE_SIZE = 1024


def _cached(key, make):
    """``_CACHE[key]``, made by ``make()`` when missing (the cache emptied when full)."""
    hit = _CACHE.get(key)
    if hit is None:
        hit = make()
        if len(_CACHE) >= _CACHE_SIZE:
            _CACHE.clear()
        _CACHE[key] = hit
    return hit


def _affine_pieces(params: BrakingParams, dt: float):
    """``Phi(0), Phi(1) - Phi(0), B(0), B(1) - B(0), Qd`` for one dt, cached (bounded)."""
    def make():
        A, B = continuous_matrices(np.array([0.0, 1.0]), params)
        Phi, Bd = zoh(A, B, dt)  # the core's one ZOH, batched over f
        return Phi[0], Phi[1] - Phi[0], Bd[0], Bd[1] - Bd[0], process_noise(params, dt)

    return _cached((params, float(dt)), make)


class BrakingModel:
    """The braking model as a *linear-Gaussian family* for the Rao-Blackwellised filters.

    The filters only use: ``n`` (state size), ``d`` (parameter size), ``H`` (all measurement
    rows), ``R`` (default measurement variances), ``report_index`` (states reported next to the
    parameter), ``gate(u, x_mean)`` and ``matrices(theta, u, dt, informative)``.

    Input ``u = (a_Tar, d_known)`` in m/s^2 (``d_known``: known extra acceleration, default 0).

    **When f is (not) observable.** f multiplies the *braking* command only. The family reports a
    step as informative about f iff ``a_Tar < 0`` (braking commanded) and the train is not at
    standstill (``standstill_speed`` set and ``|v| <= standstill_speed``). Otherwise:
      * traction/coasting (``a_Tar >= 0``): the actuator gain is the nominal 1 for all particles
        (f is the *braking* rate; traction performance is not estimated here);
      * standstill under a braking command: gain 0 -- the brakes hold the train, the command
        produces no acceleration, so ``a_hat`` relaxes to 0.
    Every particle then has the same model, so the likelihood cannot tell f values apart, and
    the filters freeze the f transition (see ``braking_filters``): the f marginal holds.
    """

    n = 4
    d = 1
    report_index = (0, 1, 2)  # D, v, a_hat

    def __init__(self, params: BrakingParams = BrakingParams()):
        self.params = params
        self.H = C_ROWS.copy()
        self.R = np.asarray(params.meas_var, dtype=float)

    def default_dt(self) -> float:
        return self.params.dt

    def gate(self, u, x_mean) -> bool:
        a_tar = float(u[0])
        if not a_tar < -self.params.min_brake:
            return False
        vs = self.params.standstill_speed
        return not (vs is not None and abs(float(x_mean[1])) <= vs)

    def hold_gain(self, u, x_mean, braking_rate_mean: float) -> float:
        """Gain of a step that does not inform f (one model shared by every particle).

        Traction or coasting: 1 (f scales braking only). Braking at standstill: 0 (the train is
        held; the brake produces no acceleration). A weak brake trim while moving (below
        ``min_brake``): the current estimate of f -- the brake acts, we just learn nothing.
        """
        if float(u[0]) >= 0.0:
            return 1.0
        vs = self.params.standstill_speed
        if vs is not None and abs(float(x_mean[1])) <= vs:
            return 0.0
        return float(braking_rate_mean)

    def braking_rates(self, theta, u, informative: bool, hold: float | None = None
                      ) -> np.ndarray:
        """The braking rate each particle's model uses this step: ``theta`` if informative, else
        the one shared gain (``hold`` if given, else 1 for traction and 0 for braking)."""
        if informative:
            return np.asarray(theta, dtype=float).reshape(-1)
        if hold is not None:
            return np.array([float(hold)])
        return np.array([1.0 if float(u[0]) >= 0.0 else 0.0])

    def predict(self, x, P, theta, u, dt: float, informative: bool, hold: float | None = None):
        """KF prediction of every particle, ``batched_kf.predict(x, P, *self.matrices(...))``
        computed through the affine form (module docstring) instead of per-particle matrices.

        With ``Phi(f) = Phi0 + f E`` the prediction is a quadratic polynomial in f whose
        coefficients are *linear maps of (x, P) that do not depend on f*::

            x' = Phi0 x + B0 u + f (E x + B1 u)
            P' = Phi0 P Phi0^T + f (E P Phi0^T + Phi0 P E^T) + f^2 E P E^T + Qd

        so one matrix product (``KP``: the three linear maps, cached per dt) gives all three for
        every particle, combined by Horner's rule with each particle's f: no (N, 4, 4) model
        stack, no batched 4x4 matmuls. Only the 10 distinct entries of the symmetric P' are
        computed and copied to both (i, j) and (j, i): P' is exactly symmetric. Internally the
        particles are on the last axis (long contiguous rows for the elementwise Horner steps).
        Equal to the generic path up to rounding (``test_braking_model.py``).
        """
        f = self.braking_rates(theta, u, informative, hold)
        Kx, KP, Qd, full = _predict_maps(self.params, float(dt))
        u = np.asarray(u, dtype=float)
        N = x.shape[0]
        bu = (u @ Kx[4:])[:, None]  # (8, 1): B0 u | B1 u
        Xt = _matmul_cols(Kx[:4].T, x.T)  # (8, N): Phi0 x | E x
        xt = Xt[4:] + bu[4:]
        xt *= f
        xt += Xt[:4]
        xt += bu[:4]
        Yt = _matmul_cols(KP, P.reshape(N, 16).T)  # (30, N): f^0, f^1, f^2 coefficients
        Pu = Yt[20:] * f
        Pu += Yt[10:20]
        Pu *= f
        Pu += Yt[:10]
        Pu += Qd
        return xt.T.copy(), Pu.T[:, full].reshape(N, 4, 4)

    def bank_maps(self, theta, u, dt: float, informative: bool, hold: float | None = None):
        """:meth:`predict` as arguments of the compiled bank step (``numerics.bank``): ``(maps,
        f)``, ``maps`` as :meth:`bank_pred`, ``f`` each particle's rate (N or 1)."""
        return self.bank_pred(u, dt), self.braking_rates(theta, u, informative, hold)

    def bank_pred(self, u, dt: float):
        """The sparse rows of :meth:`predict`'s linear maps (cached per dt) and ``B0 u | B1 u``
        computed as :meth:`predict` computes it: the prediction's arguments of the compiled
        steps (``numerics.bank``, ``braking_compiled``), without the braking rates."""
        dt = float(dt)
        # this model's maps by dt, without hashing its parameters at each step (a live filter
        # alternates a few dts: the reading's step, the command's)
        own = self.__dict__.get("_bank_own")
        if own is None or own[0] is not self.params or len(own[1]) >= _CACHE_SIZE:
            own = self._bank_own = (self.params, {})
        hit = own[1].get(dt)
        if hit is None:
            hit = own[1][dt] = (_predict_maps(self.params, dt)[0][4:],
                                _bank_maps(self.params, dt))
        xp, xc, xv, kp, kc, kv, qd, full = hit[1]
        bu = np.asarray(u, dtype=float) @ hit[0]
        return (xp, xc, xv, kp, kc, kv, bu, qd, full)

    def matrices(self, theta, u, dt: float, informative: bool, hold: float | None = None):
        """``Phi (K,4,4)``, ``Bu (K,4)``, ``Qd (4,4)``; ``K = len(theta)`` if informative else 1
        (with gain ``hold`` if given, else 1 for traction and 0 for braking)."""
        u = np.asarray(u, dtype=float)
        Phi, Bd, Qd = discretize(self.braking_rates(theta, u, informative, hold), self.params, dt)
        return Phi, Bd @ u, Qd


_MAX_MNK = 200_000


def _matmul_cols(K, A):
    """``K @ A`` for a small ``K`` and many columns (particles), in blocks of columns small
    enough (``m n k`` below ``_MAX_MNK``) that OpenBLAS keeps each product in the calling
    thread. Why: above ~2.6 x 10^5 multiply-adds it splits a product over threads, and on a
    loaded machine the calling thread then waits milliseconds for them (measured for
    (30 x 16) @ (16 x 1350): 6 ms median, 23 us in one thread). A loop over blocks of
    particles, not over particles."""
    n = A.shape[1]
    block = max(1, _MAX_MNK // (K.shape[0] * K.shape[1]))
    if n <= block:
        return K @ A
    out = np.empty((K.shape[0], n))
    for i in range(0, n, block):
        np.matmul(K, A[:, i:i + block], out=out[:, i:i + block])
    return out


# the 10 distinct entries (i <= j) of a symmetric 4 x 4 matrix, and where each of the 16 goes
_UPPER = [(i, j) for i in range(4) for j in range(i, 4)]
_FULL = np.array([_UPPER.index((min(i, j), max(i, j))) for i in range(4) for j in range(4)])


def _predict_maps(params: BrakingParams, dt: float):
    """Linear maps of ``BrakingModel.predict`` for one dt, cached (bounded): ``Kx (6, 8)``
    (rows 0-3: ``x -> (Phi0 x, E x)`` as right factors; rows 4-5: ``u -> (B0 u, B1 u)``),
    ``KP (30, 16)`` (``vec(P)`` -> the 10 distinct entries of the f^0, f^1 and f^2
    coefficients of P', row-major vec), ``Qd``'s 10 distinct entries (a column) and the
    index that spreads 10 distinct entries over the 16 of a symmetric matrix."""
    def make():
        P0, E, B0, B1, Qd = _affine_pieces(params, dt)
        Kx = np.zeros((6, 8))
        Kx[:4, :4] = P0.T
        Kx[:4, 4:] = E.T
        Kx[4:, :4] = B0.T
        Kx[4:, 4:] = B1.T
        # vec(A P B^T) = kron(A, B) vec(P) for row-major vec: the rows of (i, j) in _UPPER,
        # kron(A, B)[4 i + j, 4 k + l] = A[i, k] B[j, l], each one product as np.kron forms it
        K0 = _kron_upper(P0, P0)
        K1 = _kron_upper(E, P0) + _kron_upper(P0, E)
        K2 = _kron_upper(E, E)
        return Kx, np.vstack([K0, K1, K2]), Qd.reshape(16)[_UP][:, None], _FULL

    return _cached(("maps", params, float(dt)), make)


_UI = np.array([i for i, _ in _UPPER])
_UJ = np.array([j for _, j in _UPPER])
_UP = 4 * _UI + _UJ


def _kron_upper(A, B):
    """``np.kron(A, B)[_UP]`` for 4 x 4 ``A, B``: the 10 rows of the upper triangle's entries."""
    return (A[_UI][:, :, None] * B[_UJ][:, None, :]).reshape(10, 16)


def _bank_maps(params: BrakingParams, dt: float):
    """``_predict_maps`` as the compiled step's sparse rows (``numerics.bank.csr``), cached."""
    def make():
        Kx, KP, qd, full = _predict_maps(params, dt)
        return (*csr(Kx[:4].T), *csr(KP), np.ascontiguousarray(qd[:, 0]),
                full.astype(np.int64))

    return _cached(("bank", params, float(dt)), make)


def augmented_model(params: BrakingParams, u, dt: float, az_mean: float, informative: bool,
                    hold: float | None = None, q_braking_rate: float = 0.0):
    """The braking model with f as a fifth state, ``z = (D, v, a_hat, a_z, f)``: ``z' = F z + b +
    w``, ``w ~ N(0, Q)``, exactly linear when ``a_z`` is known.

    Why this is exact. ``Phi(f) x + B(f) u = Phi(0) x + B(0) u + f (Phi(1) - Phi(0)) x +
    f (B(1) - B(0)) u`` (the affine form above). ``Phi(1) - Phi(0)`` has a single non-zero
    column, ``a_z``'s (f scales only the edge ``a_z -> a_hat``), and ``Phi(0)`` has no path from
    ``a_z`` to ``(D, v, a_hat)``. So, with ``a_z`` known over the step (it is the Pade response
    to the *known* command; ``az_mean`` is its value at the start of the step), the f column is
    the known vector ``c = (Phi(1) - Phi(0))[:, 3] az_mean + (B(1) - B(0)) u`` and a Kalman
    filter on ``z`` is the exact Bayesian estimator for a Gaussian prior on f and the random walk
    ``f' = f + N(0, q_braking_rate dt)``. (``a_z`` itself evolves independently of
    everything else; its row and column are carried unchanged, and an ``a_z`` reading updates
    it alone.)

    Steps that cannot inform f (``informative`` False: traction, standstill, weak trim) use the
    shared model of gain ``hold`` (``BrakingModel.matrices``) with no f column and no f noise: the
    f marginal is frozen, as in the particle filters.

    Returns ``F (5, 5)``, ``b (5,)``, ``Q (5, 5)``.
    """
    u = np.asarray(u, dtype=float)
    F = np.zeros((5, 5))
    b = np.zeros(5)
    Q = np.zeros((5, 5))
    F[4, 4] = 1.0
    if informative:
        P0, P1, B0, B1, Qd = _affine_pieces(params, float(dt))
        F[:4, :4] = P0
        F[:4, 4] = P1[:, 3] * float(az_mean) + B1 @ u
        b[:4] = B0 @ u
        Q[4, 4] = float(q_braking_rate) * float(dt)
    else:
        g = (1.0 if u[0] >= 0.0 else 0.0) if hold is None else float(hold)
        Phi, Bd, Qd = discretize(np.array([g]), params, dt)
        F[:4, :4] = Phi[0]
        b[:4] = Bd[0] @ u
    Q[:4, :4] = Qd
    return F, b, Q
