"""Fleet: each train's balise reader over its passes (pure: rows in, figures out).

One run has 3 to 17 balise readings, too few for ``diagnose`` to see a reader whose errors are
correlated from one reading to the next or grow with the speed (docs/diagnose.md, "The balise
readings against what they state"). The reader is the train's: its passes pooled give it the
readings. Each run's report keeps its readings' whitened innovations at the fitted origin
(``evidence._model.balise_readings.innovations``: z, the origin's column c and information
I_s0, the speed and position at each reading); under the stated readings the runs are
independent, so the pooled z is normal with the block-diagonal covariance of the runs'
I - c c^T / I_s0, and the same exact tests apply with lag-1 products inside each run only
(:func:`..offline.diagnose.residuals.balise_checks` with ``seg``). ``alpha`` is shared out over
the trains tested (Bonferroni). A train's latest runs are pooled up to ``MAX_READINGS``
readings: the reader as it is now (one repaired last month is another reader), and a test
whose eigenvalues take tens of milliseconds, not seconds, for each of a hundred trains.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import block_diag

from .diagnose.residuals import BALISE_MIN, balise_checks

# readings pooled per train at most (its latest runs): at 120 readings the tests find a
# correlation of 0.8 in 100 of 100 synthetic runs and a fivefold speed dependence in 96
MAX_READINGS = 240


def _pooled(runs: list[dict]):
    """(z, cov, speed, position, seg) of the runs' innovations, in the rows' order."""
    z, speed, pos, seg, blocks = [], [], [], [], []
    for k, r in enumerate(runs):
        zi = np.asarray(r["z"], float)
        ci = np.asarray(r["c"], float)
        z.append(zi)
        speed.append(np.asarray(r["speed"], float))
        pos.append(np.asarray(r["position"], float))
        seg.append(np.full(zi.size, k))
        blocks.append(np.eye(zi.size) - np.outer(ci, ci) / float(r["info"]))
    return (np.concatenate(z), block_diag(*blocks), np.concatenate(speed),
            np.concatenate(pos), np.concatenate(seg))


def _usable(b) -> bool:
    try:
        sizes = {len(b[k]) for k in ("z", "c", "speed", "position")}
        return len(sizes) == 1 and sizes.pop() > 0 and float(b["info"]) > 0 and all(
            np.all(np.isfinite(np.asarray(b[k], float)))
            for k in ("z", "c", "speed", "position"))
    except (KeyError, TypeError, ValueError):
        return False


def reader_consensus(rows: list[dict], alpha: float) -> dict:
    """{"trains": {train: {runs, readings, tested, correlation, speed, distance, finding,
    signature}}, "alerts": [{train, runs, readings, signature}]}: each train's latest runs with
    balise innovations (``row["balise"]``) pooled in time order (module docstring)."""
    by: dict = {}
    for r in sorted(rows, key=lambda r: (r["train"], r.get("time") or 0.0)):
        b = r.get("balise")
        if b and _usable(b):
            by.setdefault(r["train"], []).append(b)
    for train, runs in by.items():  # the latest runs, up to MAX_READINGS readings
        keep, total = [], 0
        for b in reversed(runs):
            if keep and total + len(b["z"]) > MAX_READINGS:
                break
            keep.append(b)
            total += len(b["z"])
        by[train] = keep[::-1]
    tested = [t for t, runs in by.items() if sum(len(b["z"]) for b in runs) >= BALISE_MIN]
    out, alerts = {}, []
    for train, runs in sorted(by.items()):
        z, cov, v, x, seg = _pooled(runs)
        res = balise_checks(z, cov, v, x, alpha / max(len(tested), 1), seg)
        res["runs"] = len(runs)
        out[train] = res
        if res["finding"]:
            alerts.append({"train": train, "runs": len(runs), "readings": res["readings"],
                           "signature": res["signature"]})
    return {"trains": out, "alerts": alerts}
