"""The typed result of a diagnosis: one :class:`CauseFit` per cause, the :class:`Diagnosis`,
and its one JSON form (docs/interfaces.md ``report.json``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

REPORT_KEYS = ("cause", "parameters", "ranking", "unexplained", "untestable", "evidence",
               "gain")


@dataclass
class CauseFit:
    """One cause fitted against one null: its score and parameters (docs/interfaces.md units)."""

    cause: str
    score: float  # 2 (ll_cause - ll_null) - k ln n - prior odds penalty
    parameters: dict  # docs/interfaces.md's parameters of the cause
    dll: float = 0.0  # log-likelihood gain over the null
    k: int = 0  # parameter count (profiled ones included)
    n: int = 1  # scalar measurements of the likelihood the cause lives in
    std_errors: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)  # fit details (section bins, profiles, ...)
    dll_common_noise: float | None = None  # dll at the null's noise, when refitted at its own
    noise: tuple | None = None  # (q, r_s) of the model that includes the cause
    prior_odds_penalty: float = 0.0
    stage: int | None = None  # greedy stage that accepted it (None: not accepted)
    status: str | None = None  # the confirmation's verdict, when one is made
    why: str | None = None  # the reason for ``status``
    # the fit of a rival law that explains the cause's effect better (confirm.rival_fit: brakes
    # that fade as they heat for a braking-rate drift), which takes its place in the model
    rival: dict | None = None

    def to_json(self) -> dict:
        """A ranking entry: cause, score, parameters (status when set; why when set, never
        with ``confirmed``: a fit refused at one greedy stage and accepted at a later one
        carries no stale reason)."""
        out = {"cause": self.cause, "score": self.score}
        if self.status is not None:
            out["status"] = self.status
        if self.why is not None and self.status != "confirmed":
            out["why"] = self.why
        out["parameters"] = self.parameters
        return out


@dataclass
class Diagnosis:
    cause: str  # first confirmed entry of ranking, else unexplained or none
    parameters: dict  # its parameters (docs/interfaces.md units)
    ranking: list  # [CauseFit], best first, "none" included
    untestable: list  # [{"cause", "why"}]
    evidence: dict  # per cause: log-likelihood gain, penalty, n, standard errors, ...
    gain: dict  # {"metric", "before", "after", ...} for the top cause
    accepted: list  # [CauseFit] confirmed (what DIR/model holds), in the order accepted
    series: dict = field(default_factory=dict)  # arrays for the plots
    # [{"phase", "where", "when", "speed", "size", "best_listed"}]: what the confirmed model
    # leaves in the data that no listed cause explains
    unexplained: list = field(default_factory=list)

    def to_json(self) -> dict:
        """docs/interfaces.md report: exactly REPORT_KEYS, in plain JSON types (numpy to
        Python, NaN/inf to null, tuples to lists)."""
        return jsonable({"cause": self.cause, "parameters": self.parameters,
                         "ranking": [r.to_json() for r in self.ranking],
                         "unexplained": self.unexplained,
                         "untestable": self.untestable, "evidence": self.evidence,
                         "gain": self.gain})


def jsonable(obj):
    """Plain JSON types: numpy scalars/arrays to Python, NaN/inf to null, tuples to lists."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if obj is None or isinstance(obj, str):
        return obj
    return str(obj)


def rounded(x):
    """A score as reported: 3 decimals (non-finite kept)."""
    return float(round(float(x), 3)) if x is not None and math.isfinite(float(x)) else x


def clean(d: dict) -> dict:
    """Parameters and details as reported: numpy to Python, non-finite floats to None."""
    out = {}
    for k, v in d.items():
        if isinstance(v, (list, tuple)):
            out[k] = [_clean_v(x) for x in v]
        else:
            out[k] = _clean_v(v)
    return out


def _clean_v(v):
    if isinstance(v, (list, tuple)):
        return [_clean_v(x) for x in v]
    if isinstance(v, (float, np.floating)):
        return float(v) if math.isfinite(float(v)) else None
    if isinstance(v, (np.integer,)):
        return int(v)
    return v
