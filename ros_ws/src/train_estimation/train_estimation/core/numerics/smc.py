"""Sequential Monte Carlo helpers shared by every particle filter of the project: weights
normalised in log space and systematic resampling, batched over trailing axes (leading axis =
particles), each written once.

Pure: numpy only.
"""

from __future__ import annotations

import numpy as np

__all__ = ["log_normalize", "systematic_resample", "effective_sample_size"]


def log_normalize(logw):
    """Normalised weights and ``log sum exp`` of log-weights over axis 0, underflow-safe.

    Returns ``(w, logZ)``: ``w`` sums to one along axis 0; ``logZ`` is a float for 1-D input,
    else an array over the trailing axes. Entries of ``-inf`` get weight 0. Raises
    ``ValueError`` if there is no particle, any entry is NaN/+inf, or all entries of a batch
    element are -inf (nothing to normalise).
    """
    logw = np.asarray(logw, dtype=float)
    if logw.size == 0:
        raise ValueError("no particles")
    if np.any(np.isnan(logw)) or np.any(logw == np.inf):
        raise ValueError("NaN or +inf log-weight")
    m = np.max(logw, axis=0)
    if not np.all(np.isfinite(m)):
        raise ValueError("all log-weights are -inf")
    e = np.exp(logw - m)
    s = e.sum(axis=0)
    logz = m + np.log(s)
    return e / s, (float(logz) if np.ndim(logz) == 0 else logz)


def effective_sample_size(logw) -> float:
    """``N_eff = 1 / sum w_i^2`` of normalised weights (Zheng 3.2 step 4; the paper prints the
    *unnormalised* weights there and squares the denominator of step 3: both slips)."""
    w, _ = log_normalize(logw)
    return float(1.0 / np.sum(w * w))


def systematic_resample(w, rng: np.random.Generator, n: int | None = None) -> np.ndarray:
    """Systematic resampling: ``n`` ancestor indices per batch element (default: as many as
    particles) from normalised weights ``w`` (N, *b), with ``u_j = (U + j) / n``, ``U ~ U[0, 1)``
    drawn once per element.

    Each index ``i`` is drawn ``floor(n w_i)`` or ``ceil(n w_i)`` times (equal weights with
    n = N give every index once); zero weights are never drawn (searchsorted side="right" skips
    a bin whose cumulative weight equals its predecessor's). One searchsorted serves all batch
    elements: element m's cumulative weights are shifted by m, which keeps the concatenation
    monotone, and the offsets are removed afterwards. Returns (n, *b).
    """
    w = np.asarray(w, dtype=float)
    N = w.shape[0]
    n = N if n is None else int(n)
    wb = np.moveaxis(w, 0, -1).reshape(-1, N)
    M = wb.shape[0]
    cw = np.cumsum(wb, axis=1)
    cw[:, -1] = 1.0  # guard against round-off: the last bin must catch u < 1
    off = np.arange(M)[:, None]
    pos = (rng.random((M, 1)) + np.arange(n)[None, :]) / n
    idx = np.searchsorted((cw + off).ravel(), (pos + off).ravel(), side="right")
    idx = np.minimum(idx.reshape(M, n) - off * N, N - 1)
    shape = np.moveaxis(w, 0, -1).shape[:-1] + (n,)
    return np.moveaxis(idx.reshape(shape), -1, 0)
