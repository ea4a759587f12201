"""kf2_loglik is the two-column fast path of augmented_kf: the same profile log-likelihood."""

import numpy as np
import pytest

from train_estimation.core.numerics.augmented_kf import Events, augmented_kf, gls, kf2_loglik


def _events(rng, n, balises, held):
    t = np.cumsum(rng.uniform(0.05, 0.5, n))
    kind = np.zeros(n, np.int8)
    kind[balises] = 1
    y_d = np.cumsum(rng.uniform(0.0, 5.0, n)) + rng.normal(size=n)
    y_v = rng.normal(5.0, 1.0, n)
    r_v = np.where(kind == 1, rng.uniform(0.5, 4.0, n), rng.uniform(0.005, 0.1, n))
    h = np.zeros(n, bool)
    h[held] = True
    return Events(t=t, kind=kind, y_d=y_d, y_v=y_v, r_v=r_v, held=h,
                  odo=np.flatnonzero(kind == 0), bal=np.flatnonzero(kind == 1))


@pytest.mark.parametrize("seed,balises,held,q,r_s", [
    (0, [5, 17, 30], [2, 3], 0.02, 0.3),
    (1, [1, 2, 40], [], 1e-5, 1e-4),  # small noise, balises back to back
    (2, [10], list(range(20, 30)), 0.5, 5.0),  # a long standstill
    (3, [], [7], 0.1, 0.05),  # no balise: s0 is not determined, the profile is the fixed fit
])
def test_kf2_loglik_equals_the_general_filter(seed, balises, held, q, r_s):
    rng = np.random.default_rng(seed)
    n = 45
    ev = _events(rng, n, balises, held)
    bv, bs = rng.normal(size=n) * 0.2, rng.normal(size=n) * 0.05
    md, mv = rng.normal(size=n) * 0.3, rng.normal(size=n) * 0.1
    Z = np.zeros((n, 2))
    Bv, Bs, Md, Mv, Mb = (Z.copy() for _ in range(5))
    Bv[:, 0], Bs[:, 0], Md[:, 0], Mv[:, 0] = bv, bs, md, mv
    Mb[:, 1] = 1.0  # column 1 is s0: it enters the balise readings only
    q_held = 1.0
    kf = augmented_kf(ev, q, r_s, Bv, Bs, Md, Mv, Mb, q_held)
    if balises:
        _, _, quad = gls(kf.W, np.eye(2))
    else:
        quad = kf.W[0, 0]
    general = kf.loglik(np.array([1.0, 0.0])) + 0.5 * (kf.W[0, 0] - quad)
    fast = kf2_loglik(ev, q, r_s, bv, bs, md, mv, q_held)
    assert fast == pytest.approx(general, rel=1e-10, abs=1e-9)
