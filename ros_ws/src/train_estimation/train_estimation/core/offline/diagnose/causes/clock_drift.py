"""``clock_drift``: the train's clock runs at a rate other than the reference clock's.

A likelihood of its own: log time r = alpha + beta s + jitter. Null beta = 1 (no drift),
alternative beta free; Gaussian jitter with its variance profiled, floor 1 us^2 (time
resolution) so a jitter-free log does not divide by zero. drift = 1 / beta - 1 (stamp rate
minus 1, docs/interfaces.md)."""

from __future__ import annotations

import math

import numpy as np
from train_core.effects import ClockDriftEffect

from .base import Cause, resolved


class ClockDrift(Cause):
    name = "clock_drift"
    family = "clock"
    # the drift fitted on each half of the run (clock_test's ``halves_fits``)
    halves = ("drift",)

    def nominal(self, mo) -> dict:
        return {"drift": 0.0}

    def own_test(self, run) -> dict:
        return clock_test(run)

    def resolution(self, fit, mo) -> str | None:
        """A drift below 10 ppm (36 ms an hour) is within a stamp's own jitter."""
        return resolved("drift", fit.parameters["drift"], fit.std_errors.get("drift"), 1e-5,
                        " s/s")

    def plausible(self, fit, mo) -> str | None:
        """A drift is one rate for the run: where the stamps show the rate changing once
        (offline.clock_fit.clock_rate_change, run.prepare), the fitted rate is an average of
        two and predicts neither."""
        ch = mo.run.clock.get("rate_change")
        if ch is None:
            return None
        return (f"not one rate: the train's clock runs {1e6 * ch['drift_before']:+.0f} ppm "
                f"before {ch['when']:.0f} s and {1e6 * ch['drift_after']:+.0f} ppm after "
                f"(2 ln LR {ch['lr']:.0f} against one rate)")

    def extend_null(self, null, fit, mo) -> None:
        """The stamps are not part of the motion model: nothing to add."""

    def clock_drift(self, fit) -> float:
        return float(fit.parameters["drift"])

    def effect(self, params: dict, duration: float) -> ClockDriftEffect:
        return ClockDriftEffect(float(params["drift"]))

    def gain(self, fit, ctx) -> dict:
        return ctx.own[self.name].get("gain") or {"metric": "stamp residual", "before": None,
                                                  "after": None}


def clock_test(run) -> dict:
    """Train clock rate against the reference clock (see the module's docstring); the held-out
    gain fits on the first half and predicts the second half's log times."""
    s, r = run.odo_stamp, run.odo_recv
    n = s.size
    res0 = r - s
    rss0 = float(np.sum((res0 - res0.mean()) ** 2))
    A = np.stack([np.ones_like(s), s], axis=1)
    coef, *_ = np.linalg.lstsq(A, r, rcond=None)
    res1 = r - A @ coef
    rss1 = float(np.sum(res1 ** 2))
    floor = n * 1e-12
    dll = 0.5 * n * (math.log(max(rss0, floor)) - math.log(max(rss1, floor)))
    beta = float(coef[1])
    sig2 = max(rss1, floor) / max(n - 2, 1)
    se_beta = math.sqrt(sig2 / max(float(np.sum((s - s.mean()) ** 2)), 1e-12))
    drift = 1.0 / beta - 1.0
    half = s < 0.5 * s[-1]
    gain = z = halves = None
    if half.sum() > 10 and (~half).sum() > 10:
        c1, *_ = np.linalg.lstsq(A[half], r[half], rcond=None)
        # the offset of no drift fitted as the drift's fit fits it (least squares: the mean);
        # a median against a mean gave the drift a held-out gain on every nominal bag, since
        # a link's latency is skewed (a tail of late logs) and the second half's residuals
        # scatter less about a mean than about a median
        off0 = float(np.mean(r[half] - s[half]))
        before = float(np.sqrt(np.mean((r[~half] - s[~half] - off0) ** 2)))
        after = float(np.sqrt(np.mean((r[~half] - A[~half] @ c1) ** 2)))
        # the held-out score: the second half's own rate against the direction the first
        # half's fit predicts, z = sign(b1 - 1) (b2 - 1) / se2 (b: log-time per stamp s).
        # The halves' jitters are independent, so without a drift z is standard normal; a
        # lower held-out RMS alone is a coin toss when there is no drift
        c2, *_ = np.linalg.lstsq(A[~half], r[~half], rcond=None)
        s2 = s[~half]
        sig2h = float(np.sum((r[~half] - A[~half] @ c2) ** 2)) / max(int((~half).sum()) - 2, 1)
        se2 = math.sqrt(max(sig2h, 1e-12) / max(float(np.sum((s2 - s2.mean()) ** 2)), 1e-12))
        z = float(np.sign(c1[1] - 1.0) * (c2[1] - 1.0) / se2)
        gain = {"metric": "held-out stamp residual RMS (s), second half predicted from the first",
                "before": before, "after": after}
        # each half's drift with its standard error, for the halves test (confirm.halves_test:
        # one rate for the run fits both halves alike; on ten nominal seeded bags the halves'
        # z was within +-1.91)
        s1 = s[half]
        sig2f = float(np.sum((r[half] - A[half] @ c1) ** 2)) / max(int(half.sum()) - 2, 1)
        se1 = math.sqrt(max(sig2f, 1e-12) / max(float(np.sum((s1 - s1.mean()) ** 2)), 1e-12))
        halves = [{"halves": {"drift": (1.0 / c[1] - 1.0, e / c[1] ** 2)}}
                  for c, e in ((c1, se1), (c2, se2))]
    return {"dll": dll, "k": 1, "n": n, "parameters": {"drift": drift},
            "std_errors": {"drift": se_beta / beta ** 2}, "jitter_std": math.sqrt(sig2),
            "gain": gain, "heldout_z": z, "halves_fits": halves}


CAUSE = ClockDrift()
