"""Batched Kalman filter over a leading particle axis, with measurement masks.

The steps themselves (:func:`predict`, :func:`update`: the sequential update by scalar rows that
gives the Rao-Blackwellised particle weight, Zheng eq. (12), (17); Q-GRBPF eq. (3)-(5)) live in
``kalman.py``, written once for every filter; re-exported here with the particle filters' mixture
moments.

Pure: numpy only.
"""

from __future__ import annotations

import numpy as np

from .kalman import predict, update

# the steps live in kalman.py (one implementation); re-exported for the particle filters
__all__ = ["predict", "update", "mixture_moments"]


def mixture_moments(w, means, covs=None):
    """Mean and covariance of the mixture ``sum_i w_i N(means_i, covs_i)``.

    ``cov = sum_i w_i (covs_i + (m_i - m)(m_i - m)^T)`` (law of total covariance). ``covs``
    None means point masses.
    """
    w = np.asarray(w, dtype=float)
    m = w @ means
    dev = means - m
    cov = np.einsum("k,ki,kj->ij", w, dev, dev)
    if covs is not None:
        cov = cov + np.einsum("k,kij->ij", w, covs)
    return m, 0.5 * (cov + cov.T)
