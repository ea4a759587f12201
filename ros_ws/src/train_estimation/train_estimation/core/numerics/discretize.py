"""Exact zero-order-hold discretisation of linear time-invariant models.

For ``dx/dt = A x + B u + w`` with ``u`` held constant over ``[0, dt)`` and ``w`` white with
power spectral density ``Qc``:

    x(t + dt) = Ad x(t) + Bd u + w_d,   Ad = e^{A dt},   Bd = (int_0^dt e^{A s} ds) B,
    Cov(w_d) = Qd = int_0^dt e^{A s} Qc e^{A^T s} ds.

Both integrals come out of one matrix exponential of an augmented matrix (Van Loan, 1978,
"Computing integrals involving the matrix exponential"), which is exact for any ``A`` (also
singular ones such as the double integrator of the train, where ``A^{-1}(e^{A dt} - I) B``
does not exist). This is eq. (6) of Wen et al. (2017): A1 = e^{A T}, B = int e^{A t} dt B,
E = int e^{A t} dt E -- ``E`` is just another input matrix, so ``zoh(A, E, dt)`` gives it.

Pure: numpy/scipy only.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import expm

__all__ = ["zoh", "van_loan"]


def zoh(A, B, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact ZOH discretisation: returns ``(Ad, Bd)`` with ``Ad = e^{A dt}``,
    ``Bd = int_0^dt e^{A s} ds B``.

    Uses ``expm([[A, B], [0, 0]] dt) = [[Ad, Bd], [0, I]]``. ``dt >= 0`` (``dt = 0`` gives
    ``(I, 0)``). ``B`` may be a vector (treated as one column; returned with the same shape).
    Batched: ``A (..., n, n)`` with ``B (..., n, m)`` (the same leading axes) gives the stack
    of discretisations in one call (scipy's expm is batched over leading axes); this is the
    one ZOH of the estimation core (the braking particles' per-f models use it too).
    """
    A = np.asarray(A, dtype=float)
    if A.ndim < 2:
        A = np.atleast_2d(A)
    B_in = np.asarray(B, dtype=float)
    lead, n = A.shape[:-2], A.shape[-1]
    B = B_in.reshape(lead + (n, -1)) if B_in.ndim == A.ndim else B_in.reshape(lead + (n, 1))
    if not np.isfinite(dt) or dt < 0:
        raise ValueError(f"zoh: dt must be finite and >= 0, got {dt!r}")
    m = B.shape[-1]
    M = np.zeros(lead + (n + m, n + m))
    M[..., :n, :n] = A
    M[..., :n, n:] = B
    F = expm(M * dt)
    return F[..., :n, :n], F[..., :n, n:].reshape(B_in.shape)


def van_loan(A, Qc, dt: float) -> np.ndarray:
    """Discrete process-noise covariance ``Qd = int_0^dt e^{A s} Qc e^{A^T s} ds``.

    Van Loan: ``expm([[-A, Qc], [0, A^T]] dt) = [[., F12], [0, F22]]`` with ``F22 = e^{A^T dt}``
    and ``Qd = F22^T F12``. The result is symmetrised (round-off only).
    """
    A = np.atleast_2d(np.asarray(A, dtype=float))
    Qc = np.atleast_2d(np.asarray(Qc, dtype=float))
    if not np.isfinite(dt) or dt < 0:
        raise ValueError(f"van_loan: dt must be finite and >= 0, got {dt!r}")
    n = A.shape[0]
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n] = -A
    M[:n, n:] = Qc
    M[n:, n:] = A.T
    F = expm(M * dt)
    Qd = F[n:, n:].T @ F[:n, n:]
    return 0.5 * (Qd + Qd.T)
