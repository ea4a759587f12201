"""Fleet consensus: tell a line map's error from one train's fault, across many runs.

Input: one row per analysed run (a plain dict, built by ``tools/fleet.py`` from ``diagnose``'s
report), with the train, the line, the run's time and what the run found::

    {"train": "T01", "line": "north", "time": 14.9, "coverage": [100.0, 4300.0],
     "gradient": {"start": 1000.0, "end": 1400.0, "permille": 4.9, "se": 0.8} or None,
     "resistance": {"value": 120.0, "se": 400.0},   # N, fitted minus believed force at v_ref
     "braking_rate": {"value": 0.85, "se": 0.03},
     "mass": {"value": 289000.0, "se": 900.0},
     "odometer_scale": {"value": 1.0001, "se": 0.0003}}

``gradient`` is the section ``diagnose`` *accepted* (None when it accepted none); the
parameters are fitted values with their standard errors whether or not the cause was accepted
(a fit is a measurement; the nominal value is a measurement near nominal).

Line consensus (per line):

- Gradient sections found by single runs are grouped when they overlap by at least
  ``overlap`` of the shorter one. A group is a *map error* when (1) runs of at least
  ``min_trains`` different trains found it, (2) so many of the runs that passed the section
  found it that a spurious detection cannot explain it: the one-sided binomial test against a
  per-run false-detection probability ``p_false`` (``diagnose``'s measured false-alarm rate on
  nominal bags, 5 %: a conservative bound for a section at one place) gives p < alpha / m
  (Bonferroni over the m groups of the fleet), and (3) the values agree: Cochran's
  Q = sum w_i (x_i - x_bar)^2 with w_i = 1/se_i^2 is below its chi-square(k - 1) quantile at
  1 - alpha. The report gives the inverse-variance combination x_bar = sum w_i x_i / sum w_i,
  se = (sum w_i)^-1/2 (e.g. Hartung, Knapp & Sinha, Statistical Meta-Analysis, eq. 4.2-4.3).
  Groups failing (2) or (1) are "single-train or spurious"; failing (3) "disputed". The
  spurious detections that happen to overlap a section join its group; so that a history of
  many runs does not turn a map error into "disputed", the consistency test and the
  combination leave out, most discordant first, at most as many detections as spurious ones
  can explain (the binomial 1 - alpha quantile of the runs that passed it at ``p_false``), and
  always fewer than half.
- Resistance: the fitted minus the believed resistance force at each run's speed, combined over
  the line's runs with a random-effects model (DerSimonian-Laird tau^2 between runs), so one odd
  train widens the interval instead of moving the line's value; flagged when |z| exceeds the
  normal quantile of alpha / (2 n_lines) and Cochran's Q does not reject agreement.

Several days (rows with a ``day`` label): a map error passed on two or more days is tested
once more without the day that found it most often. It is *confirmed* when the other days'
runs alone pass the binomial test; *withdrawn* (verdict "one day's artefact") when the other
days found it significantly less often than that day (one-sided Fisher exact test, alpha) and
alone do not pass; otherwise it stands, found on one day only ("unconfirmed").

Place against speed (several passes separate what one cannot): in one pass, a tunnel's drag is
a gradient the map lacks. Over passes at different speeds they differ: a map error is the same
gradient at any speed, a tunnel's extra aerodynamic drag ``c v^2`` reads as a gradient that grows
with the square of the pass's speed. Each detection carries ``v2``, the mean square speed over
the section in its pass; the two one-parameter models ``x_i = a`` and ``x_i = b v2_i`` are each
tested by their weighted residual sum of squares against chi-square(k - 1) at ``alpha``
(:func:`speed_test`). A group the first fits and the second does not is a map error at any speed;
the reverse is *drag growing with speed (a tunnel)*; when both fit the passes' speeds were too
alike to tell, and the report says which speeds would (where the two models differ by three of
the detections' standard errors). A wind acts on some days only: the day test above.

Reliability (``reliability``): a section needs ``n_min`` analysed runs, the fewest with which a
map error that ``diagnose`` finds in ``p_detect`` of the runs is declared with probability
``power`` by the binomial test above; a line with fewer analysed runs (or runs of fewer than
``min_trains`` trains) cannot exclude a map error, and a parameter with values of fewer than
three trains cannot show a departure: the consensus then says it is unreliable, and why.

Train consensus (per parameter: braking rate, mass, odometer scale):

- Per-run scatter beyond the stated standard errors (load, weather) is tau^2: the
  DerSimonian-Laird moment estimate within trains about their own means, pooled over the
  *other* trains (for the departure test less the quarter with the largest scatter: a degrading
  train's scatter neither hides its own fault nor another's). Every run then has variance
  se^2 + tau^2.
- Departure: a train's mean m_i against the *other* trains' median (leave-one-out: the
  reference, its tau^2 included, is computed without the train, so a faulty train neither pulls
  nor widens its own reference; a train whose own runs scatter more than their errors gets its
  se scaled by the Birge ratio sqrt(Q / df)),
  z_i = (m_i - med_-i) / sqrt(se_i^2 + s_-i^2 + se_med^2)
  with s_-i = 1.4826 MAD of the others (the fleet's train-to-train spread) and
  se_med = 1.2533 sqrt(s_-i^2 + mean se_j^2) / sqrt(n_others) (the median's standard error).
- Trend: the weighted least-squares slope of the parameter against time, z = slope / se.
- An alert when |z| exceeds the Student-t quantile of 1 - alpha / (2 n_trains n_parameters)
  (Bonferroni) on the Welch-Satterthwaite degrees of freedom of z's estimated variance parts
  (tau^2 on the pooled within-train degrees of freedom; the others' spread on n_others - 1;
  the normal quantile when nothing is estimated): with ``alpha`` = 0.01 the chance of one
  false alert in the whole fleet's table (each kind) is about 1 % or less, whatever the
  fleet's size; no threshold is tuned to a scenario.

Balise readers (per train, :mod:`.fleet_readers`): the runs' balise innovations pooled and
tested for correlation in time and dependence on speed and distance, alpha over the trains.

Pure: numpy/scipy only.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import asdict, dataclass, field

import numpy as np
from scipy import stats

from .fleet_readers import reader_consensus

PARAMETERS = ("braking_rate", "mass", "odometer_scale")
UNITS = {"braking_rate": "-", "mass": "kg", "odometer_scale": "-", "resistance": "N",
         "gradient": "per mille"}


@dataclass(frozen=True)
class FleetConfig:
    alpha: float = 0.01  # family-wise false-alarm rate of each family of tests
    min_trains: int = 2  # a map error needs detections by this many different trains
    overlap: float = 0.5  # sections overlapping by this fraction of the shorter are the same
    p_false: float = 0.05  # per-run probability of a spurious section (diagnose, nominal bags)
    min_runs_trend: int = 3  # runs a train needs for a trend test
    p_detect: float = 0.5  # per-run detection rate of the weakest map error not to be missed
    power: float = 0.9  # ... declared with this probability: sets the runs a section needs


# ------------------------------------------------------------------------------------------------
# Combinations
# ------------------------------------------------------------------------------------------------

def combine(values, ses) -> dict:
    """Fixed-effect inverse-variance combination with Cochran's Q.

    Returns mean, se, z (= mean / se), p (two-sided, against 0), q, df, p_consistency
    (chi-square survival of Q with k - 1 degrees of freedom; 1.0 for one value)."""
    x, s = np.asarray(values, float), np.asarray(ses, float)
    if x.size == 0:
        return {"n": 0}
    w = 1.0 / s**2
    mean = float(np.sum(w * x) / np.sum(w))
    se = float(1.0 / math.sqrt(np.sum(w)))
    q = float(np.sum(w * (x - mean) ** 2))
    df = int(x.size - 1)
    return {"n": int(x.size), "mean": mean, "se": se, "z": mean / se,
            "p": float(2 * stats.norm.sf(abs(mean / se))), "q": q, "df": df,
            "p_consistency": float(stats.chi2.sf(q, df)) if df > 0 else 1.0}


def _wmean(x: np.ndarray, s: np.ndarray) -> dict:
    """``combine``'s mean, se, q and df without its p-values (cheap: for inner loops)."""
    w = 1.0 / s**2
    sw = float(np.sum(w))
    mean = float(np.dot(w, x)) / sw
    return {"mean": mean, "se": 1.0 / math.sqrt(sw), "q": float(np.dot(w, (x - mean) ** 2)),
            "df": int(x.size - 1)}


def tau2_dl(values, ses) -> float:
    """DerSimonian-Laird between-measurement variance: max(0, (Q - df) / (S1 - S2 / S1)),
    S1 = sum w, S2 = sum w^2."""
    x, s = np.asarray(values, float), np.asarray(ses, float)
    if x.size < 2:
        return 0.0
    w = 1.0 / s**2
    c = combine(x, s)
    s1, s2 = float(np.sum(w)), float(np.sum(w * w))
    return max(0.0, (c["q"] - c["df"]) / (s1 - s2 / s1))


def combine_random(values, ses) -> dict:
    """Random-effects (DerSimonian-Laird) combination: every variance is se^2 + tau^2; the
    returned p_consistency is the fixed-effect Cochran's Q test."""
    x, s = np.asarray(values, float), np.asarray(ses, float)
    if x.size == 0:
        return {"n": 0}
    t2 = tau2_dl(x, s)
    out = combine(x, np.sqrt(s**2 + t2))
    out["tau"] = math.sqrt(t2)
    out["q"], out["p_consistency"] = combine(x, s)["q"], combine(x, s)["p_consistency"]
    return out


def weighted_trend(t, values, ses) -> dict:
    """Weighted least squares x = a + b t: slope b, its standard error and z = b / se."""
    t, x, s = (np.asarray(v, float) for v in (t, values, ses))
    if x.size < 2 or np.ptp(t) <= 0:
        return {"n": int(x.size)}
    w = 1.0 / s**2
    tm = np.sum(w * t) / np.sum(w)
    sxx = float(np.sum(w * (t - tm) ** 2))
    b = float(np.sum(w * (t - tm) * x) / sxx)
    se = 1.0 / math.sqrt(sxx)
    return {"n": int(x.size), "slope": b, "se": se, "z": b / se}


def t_critical(alpha: float, tests: int, df: float) -> float:
    """Two-sided Student-t quantile (normal for df = inf) with Bonferroni over ``tests``."""
    if not math.isfinite(df):
        return z_critical(alpha, tests)
    return float(stats.t.isf(alpha / (2.0 * max(tests, 1)), max(df, 1.0)))


def _p_two_sided(z: float, df: float) -> float:
    return float(2 * (stats.norm.sf(abs(z)) if not math.isfinite(df) else
                      stats.t.sf(abs(z), max(df, 1.0))))


def z_critical(alpha: float, tests: int) -> float:
    """Two-sided normal quantile with Bonferroni over ``tests`` tests."""
    return float(stats.norm.isf(alpha / (2.0 * max(tests, 1))))


# ------------------------------------------------------------------------------------------------
# Line consensus
# ------------------------------------------------------------------------------------------------

def _overlap(a0, a1, b0, b1) -> float:
    """Overlap of [a0, a1) and [b0, b1) as a fraction of the shorter one."""
    inter = max(0.0, min(a1, b1) - max(a0, b0))
    return inter / max(min(a1 - a0, b1 - b0), 1e-9)


def group_sections(dets: list[dict], overlap: float) -> list[list[int]]:
    """Indices of ``dets`` ({"start", "end", ...}) grouped: a section joins the first group
    whose median section it overlaps by >= ``overlap`` of the shorter; in order of start."""
    order = sorted(range(len(dets)), key=lambda i: (dets[i]["start"], dets[i]["end"]))
    groups: list[list[int]] = []
    # each group's starts and ends kept sorted, so that its median section costs O(1): the
    # fleet's history can hold thousands of detections of one section
    sorted_se: list[tuple[list, list]] = []
    for i in order:
        d = dets[i]
        for g, (st, en) in zip(groups, sorted_se):
            if _overlap(d["start"], d["end"], _median_sorted(st), _median_sorted(en)) \
                    >= overlap:
                g.append(i)
                bisect.insort(st, float(d["start"]))
                bisect.insort(en, float(d["end"]))
                break
        else:
            groups.append([i])
            sorted_se.append(([float(d["start"])], [float(d["end"])]))
    return groups


def _median_sorted(v: list) -> float:
    n = len(v)
    return v[n // 2] if n % 2 else 0.5 * (v[n // 2 - 1] + v[n // 2])


def _trimmed_combine(values, ses, k_max: int, alpha: float) -> tuple[dict, int]:
    """``combine`` after leaving out, one at a time, the value with the largest share of
    Cochran's Q, until Q is consistent at ``alpha`` or ``k_max`` values, or all but a
    majority, are left out (a minority cannot outvote the rest, nor the rest be trimmed to
    agree with it)."""
    x, s = np.asarray(values, float), np.asarray(ses, float)
    keep = np.ones(x.size, bool)
    c = combine(x, s)
    n_out = 0
    while c.get("p_consistency", 1.0) < alpha and n_out < min(k_max, (x.size - 1) // 2):
        w = np.where(keep, 1.0 / s**2, 0.0)
        keep[int(np.argmax(w * (x - c["mean"]) ** 2))] = False
        n_out += 1
        c = combine(x[keep], s[keep])
    return c, n_out


def speed_test(values, ses, v2, alpha: float) -> dict | None:
    """The group's detections (per mille, their standard errors, each pass's mean square
    speed over the section, m^2/s^2) against a gradient at any speed and a drag growing as v^2
    (module doc). None with fewer than two detections that carry a speed."""
    x, s, u = (np.asarray(a, float) for a in (values, ses, v2))
    ok = np.isfinite(x) & np.isfinite(s) & (s > 0) & np.isfinite(u) & (u > 0)
    x, s, u = x[ok], s[ok], u[ok]
    k = x.size
    if k < 2:
        return None
    w = 1.0 / s**2
    a = float(np.sum(w * x) / np.sum(w))
    b = float(np.sum(w * x * u) / np.sum(w * u * u))
    q_place, q_speed = float(np.sum(w * (x - a) ** 2)), float(np.sum(w * (x - b * u) ** 2))
    p_place, p_speed = (float(stats.chi2.sf(q, k - 1)) for q in (q_place, q_speed))
    place, speed = p_place >= alpha, p_speed >= alpha
    out = {"n": int(k), "v_min": float(np.sqrt(u.min())), "v_max": float(np.sqrt(u.max())),
           "permille_at_any_speed": a, "permille_per_v2": b,
           "p_place": p_place, "p_speed": p_speed,
           "decided": ("place" if place and not speed else "speed" if speed and not place
                       else "either" if place else "neither")}
    if out["decided"] in ("place", "speed"):
        # the passes that decided it: the fewest whose misfit under the model rejected (the
        # largest first) reaches the test's bar on its own (indices into the arguments)
        fit = b * u if out["decided"] == "place" else np.full(k, a)
        r = w * (x - fit) ** 2
        bar = float(stats.chi2.isf(alpha, k - 1))
        order = np.argsort(-r, kind="stable")
        n = int(np.searchsorted(np.cumsum(r[order]), bar)) + 1
        out["decided_by"] = [int(i) for i in np.flatnonzero(ok)[order[:min(n, k)]]]
    if out["decided"] == "either" and b != 0.0:
        # where the two models part by three standard errors of one detection
        sd = 3.0 * float(np.median(s))
        lo, hi = sorted(((a - sd) / b, (a + sd) / b))
        out["would_tell"] = {"below_m_s": math.sqrt(lo) if lo > 0 else None,
                             "above_m_s": math.sqrt(hi) if hi > 0 else None}
    return out


def _covers(row: dict, s0: float, s1: float) -> bool:
    cov = row.get("coverage")
    if not cov:
        return True  # unknown coverage: assume the run passed the whole line
    return min(cov[1], s1) - max(cov[0], s0) >= 0.5 * (s1 - s0)


def line_consensus(rows: list[dict], cfg: FleetConfig = FleetConfig()) -> dict:
    """{line: {"sections": [...], "resistance": {...}, "runs", "trains"}} (module docstring)."""
    lines = sorted({r["line"] for r in rows})
    out: dict = {}
    n_groups = 0
    for ln in lines:
        lr = [r for r in rows if r["line"] == ln]
        dets = [dict(r["gradient"], train=r["train"], bag=r.get("bag"), day=r.get("day"))
                for r in lr if r.get("gradient")]
        groups = group_sections(dets, cfg.overlap)
        n_groups += len(groups)
        # every run's coverage as arrays (unknown: the whole line), for _covers on all at once
        cov = np.array([r.get("coverage") or (-np.inf, np.inf) for r in lr], float)
        cov = cov.reshape(len(lr), 2)
        secs = []
        for g in groups:
            m = [dets[j] for j in g]
            s0 = float(np.median([d["start"] for d in m]))
            s1 = float(np.median([d["end"] for d in m]))
            hit = (np.minimum(cov[:, 1], s1) - np.maximum(cov[:, 0], s0) >= 0.5 * (s1 - s0))
            passed = [lr[i] for i in np.flatnonzero(hit)]
            # spurious detections that overlap the section join its group (more of them the
            # more runs the history holds): up to the number the runs passing it can explain
            # are left out of the consistency test, the most discordant first
            k_spur = int(stats.binom.isf(cfg.alpha, max(len(passed), len(m)), cfg.p_false))
            c, n_out = _trimmed_combine([d["permille"] for d in m], [d["se"] for d in m],
                                        k_spur, cfg.alpha)
            days: dict = {}
            for r in passed:
                days.setdefault(r.get("day"), [0, 0])[1] += 1
            for d in m:
                days.setdefault(d.get("day"), [0, 0])[0] += 1
            sp = speed_test([d["permille"] for d in m], [d["se"] for d in m],
                            [d.get("v2", math.nan) for d in m], cfg.alpha)
            if sp and "decided_by" in sp:  # those passes, as the report names them
                sp["decided_by"] = [{"train": m[i]["train"], "bag": m[i].get("bag"),
                                     "day": m[i].get("day"), "permille": m[i]["permille"],
                                     "v_m_s": math.sqrt(m[i]["v2"])}
                                    for i in sp["decided_by"]]
            secs.append({"start": s0, "end": s1, "permille": c["mean"], "se": c["se"],
                         "ci95": [c["mean"] - 1.96 * c["se"], c["mean"] + 1.96 * c["se"]],
                         "z": c["z"], "q": c["q"], "df": c["df"],
                         "p_consistency": c["p_consistency"], "left_out": n_out,
                         "runs_found": len(m), "runs_passed": max(len(passed), len(m)),
                         "trains_found": sorted({d["train"] for d in m}),
                         "trains_passed": sorted({r["train"] for r in passed}),
                         "bags": [d.get("bag") for d in m],
                         "speed_test": sp,
                         "days": {str(k): [f, max(n, f)] for k, (f, n) in days.items()
                                  if k is not None}})
        ltrains = sorted({r["train"] for r in lr})
        res = [r["resistance"] for r in lr if r.get("resistance")]
        rc = combine_random([x["value"] for x in res], [x["se"] for x in res]) if res else \
            {"n": 0}
        out[ln] = {"runs": len(lr), "trains": ltrains, "sections": secs, "resistance": rc}
    # decisions (need the number of groups of the whole fleet for the Bonferroni factor)
    zc_res = z_critical(cfg.alpha, len(lines))
    for d in out.values():
        for s in d["sections"]:
            s["p_binomial"] = float(stats.binom.sf(s["runs_found"] - 1, s["runs_passed"],
                                                   cfg.p_false))
            enough = len(s["trains_found"]) >= cfg.min_trains
            unlikely = s["p_binomial"] < cfg.alpha / max(n_groups, 1)
            agree = s["p_consistency"] >= cfg.alpha
            s["verdict"] = ("map error" if enough and unlikely and agree else
                            "disputed" if enough and unlikely else "single-train or spurious")
            sp = s.get("speed_test") or {}
            if s["verdict"] in ("map error", "disputed") and sp.get("decided") == "speed":
                # the passes' gradients grow as their speeds squared: not the map's
                s["verdict"] = "drag growing with speed (a tunnel)"
            if s["verdict"] == "map error" and len(s["days"]) >= 2:
                s.update(_day_test(s["days"], cfg, max(n_groups, 1)))
        rc = d["resistance"]
        if rc.get("n", 0) >= 2:
            rc["z_critical"] = zc_res
            rc["verdict"] = ("line resistance differs" if abs(rc["z"]) > zc_res
                             and rc["p_consistency"] >= cfg.alpha and
                             len(d["trains"]) >= cfg.min_trains else "consistent with the map")
    return out


# ------------------------------------------------------------------------------------------------
# Train consensus
# ------------------------------------------------------------------------------------------------

def _mad_sd(x: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(x - np.median(x)))) if x.size else 0.0


def train_consensus(rows: list[dict], cfg: FleetConfig = FleetConfig(),
                    parameters=PARAMETERS) -> dict:
    """{"parameters": {name: {"tau", "z_critical", "trains": {train: {...}}}}, "alerts": [...]}
    (module docstring)."""
    trains = sorted({r["train"] for r in rows})
    n_tests = max(len(trains) * len(parameters), 1)
    zc = z_critical(cfg.alpha, n_tests)
    out: dict = {"parameters": {}, "alerts": [], "z_critical": zc,
                 "tests": n_tests, "alpha": cfg.alpha}
    by_train: dict = {}
    for r in rows:
        by_train.setdefault(r["train"], []).append(r)
    for p in parameters:
        per: dict = {}
        for tr in trains:
            rr = sorted((r for r in by_train[tr] if r.get(p)
                         and _finite(r[p].get("value")) and _finite(r[p].get("se"))
                         and r[p]["se"] > 0), key=lambda r: r.get("time", 0.0))
            if rr:
                per[tr] = {"t": np.array([r.get("time", i) for i, r in enumerate(rr)], float),
                           "x": np.array([r[p]["value"] for r in rr], float),
                           "se": np.array([r[p]["se"] for r in rr], float),
                           "bags": [r.get("bag") for r in rr]}
        mom = {tr: _moments(v["x"], v["se"]) for tr, v in per.items()}
        tau2_all = _pooled_tau2(list(mom.values()))
        res: dict = {}
        for tr, v in per.items():
            # the scatter of the *other* trains' runs: a train's own fault must not hide itself
            # (trend: all other trains; trimming biases tau^2 low, which a trend test with
            # few runs turns into false alarms)
            oth = [m for o, m in mom.items() if o != tr] if len(mom) > 1 else list(mom.values())
            tau2, df_tau = _pooled_tau2(oth), sum(m[1] for m in oth)
            s_eff = np.sqrt(v["se"] ** 2 + tau2)
            # the share of each run's variance that is estimated (tau^2, on df_tau degrees of
            # freedom): Welch-Satterthwaite degrees of freedom of the train's statistics
            frac = tau2 / (float(np.mean(v["se"] ** 2)) + tau2) if tau2 > 0 else 0.0
            df_own = df_tau / frac**2 if frac > 0 and df_tau > 0 else math.inf
            c = combine(v["x"], s_eff)
            res[tr] = {"runs": int(v["x"].size), "mean": c["mean"], "se": c["se"],
                       "frac_estimated": frac, "df_tau": df_tau, "df_trend": df_own,
                       "t": v["t"].tolist(), "values": v["x"].tolist(),
                       "ses": v["se"].tolist(), "bags": v["bags"]}
            if v["x"].size >= max(cfg.min_runs_trend, 2):
                tr_ = weighted_trend(v["t"], v["x"], s_eff)
                res[tr].update({"slope": tr_.get("slope"), "slope_se": tr_.get("se"),
                                "z_trend": tr_.get("z")})
        for tr in res:
            others = [o for o in res if o != tr]
            if len(others) < 2:
                res[tr]["z_departure"] = None
                continue
            # leave-one-out: the reference (others' means, their run scatter tau^2) is computed
            # without train tr, so its own fault can neither move nor widen its reference
            oth = _trimmed([mom[o] for o in others])
            tau2, df_tau = _pooled_tau2(oth), max(sum(m[1] for m in oth), 1)
            loo = {o: _train_mean(per[o]["x"], per[o]["se"], tau2) for o in res}
            m = np.array([loo[o][0] for o in others])
            se_o = np.array([loo[o][1] for o in others])
            fr_o = float(np.mean([loo[o][2] for o in others]))
            mean_i, se_i, fr_i = loo[tr]
            med, s = float(np.median(m)), _mad_sd(m)
            n_o = len(m)
            k_med = 1.2533**2 / n_o  # variance of a median of n normal values: (pi/2) s^2 / n
            se_med = math.sqrt(k_med * (s**2 + float(np.mean(se_o**2))))
            den2 = se_i**2 + s**2 + se_med**2
            # Welch-Satterthwaite: the estimated parts are tau^2 (df_tau) in se_i and se_o,
            # and the others' spread s (n_others - 1 degrees of freedom)
            est = ((se_i**2 * fr_i) ** 2 + (k_med * float(np.mean(se_o**2)) * fr_o) ** 2) \
                / df_tau + (s**2 * (1 + k_med)) ** 2 / (n_o - 1)
            res[tr].update({"fleet": med, "fleet_spread": s, "fleet_se": se_med,
                            "loo_mean": mean_i, "loo_se": se_i,
                            "z_departure": (mean_i - med) / math.sqrt(den2),
                            "df_departure": den2**2 / est if est > 0 else math.inf})
        for tr, r in res.items():
            for kind, key in (("departs from the fleet", "z_departure"),
                              ("trends in time", "z_trend")):
                z = r.get(key)
                if z is None:
                    continue
                df = r["df_departure"] if key == "z_departure" else r["df_trend"]
                crit = t_critical(cfg.alpha, n_tests, df)
                r[key.replace("z_", "crit_")] = crit
                if abs(z) > crit:
                    out["alerts"].append({"train": tr, "parameter": p, "kind": kind,
                                          "z": z, "df": df, "critical": crit,
                                          "mean": r["mean"], "se": r["se"],
                                          "fleet": r.get("fleet"), "slope": r.get("slope"),
                                          "p": _p_two_sided(z, df)})
        out["parameters"][p] = {"tau": math.sqrt(tau2_all), "trains": res}
    return out


def _train_mean(x: np.ndarray, se: np.ndarray, tau2: float) -> tuple[float, float, float]:
    """(mean, se, estimated share of the variance) of one train's runs with variances
    se^2 + tau^2; the se is scaled up by the Birge ratio sqrt(Q / df) when the train's own runs
    scatter more than that (a train that changes between runs is less certain of its mean)."""
    s_eff = np.sqrt(se**2 + tau2)
    c = _wmean(x, s_eff)  # called n_trains^2 times per parameter: no p-values here
    birge = math.sqrt(c["q"] / c["df"]) if c["df"] > 0 and c["q"] > c["df"] else 1.0
    frac = tau2 / (float(np.mean(se**2)) + tau2) if tau2 > 0 else 0.0
    return c["mean"], c["se"] * birge, frac


def _moments(x: np.ndarray, se: np.ndarray) -> tuple[float, int, float]:
    """(Q, df, S1 - S2 / S1) of one train's runs about its own mean (DerSimonian-Laird)."""
    if x.size < 2:
        return 0.0, 0, 0.0
    w = 1.0 / se**2
    c = _wmean(x, se)
    s1, s2 = float(np.sum(w)), float(np.sum(w * w))
    return c["q"], c["df"], s1 - s2 / s1


def _trimmed(moments: list) -> list:
    """The trains' moments without the quarter (at least one of three or more) whose own
    scatter is largest: a second faulty train among the others must not widen the reference
    of the first (the pooled estimate is otherwise not robust)."""
    if len(moments) < 3:
        return moments
    k = max(1, len(moments) // 4)
    own = [(m[0] - m[1]) / m[2] if m[2] > 0 else 0.0 for m in moments]
    keep = np.argsort(own)[:len(moments) - k]
    return [moments[i] for i in sorted(keep)]


def _pooled_tau2(moments: list) -> float:
    """Pooled DerSimonian-Laird tau^2 = max(0, sum (Q_j - df_j) / sum c_j) over trains: the
    run-to-run scatter the stated standard errors miss, estimated with every train's degrees
    of freedom (a median of per-train estimates is biased low with few runs each)."""
    den = sum(m[2] for m in moments)
    return max(0.0, sum(m[0] - m[1] for m in moments) / den) if den > 0 else 0.0


def _finite(x) -> bool:
    return x is not None and isinstance(x, (int, float)) and math.isfinite(x)


def _day_test(days: dict, cfg: FleetConfig, n_groups: int) -> dict:
    """A map error seen on several days, tested without the day that found it most often
    (module docstring): {"day_status", "top_day", "p_rest", "p_fewer"}."""
    top = max(days, key=lambda k: (days[k][0] / max(days[k][1], 1), days[k][0], k))
    f_top, n_top = days[top]
    f_rest = sum(v[0] for k, v in days.items() if k != top)
    n_rest = sum(v[1] for k, v in days.items() if k != top)
    p_rest = float(stats.binom.sf(f_rest - 1, n_rest, cfg.p_false)) if n_rest else 1.0
    p_fewer = float(stats.fisher_exact([[f_top, n_top - f_top], [f_rest, n_rest - f_rest]],
                                       alternative="greater")[1]) if n_rest else 1.0
    found_days = sorted(k for k, v in days.items() if v[0] > 0)
    if p_rest < cfg.alpha / n_groups:
        status = f"confirmed on {len(found_days)} days"
    elif p_fewer < cfg.alpha:
        status = "withdrawn"
    else:
        status = "unconfirmed"
    out = {"day_status": status, "top_day": top, "p_rest": p_rest, "p_fewer": p_fewer,
           "days_found": found_days}
    if status == "withdrawn":
        out["verdict"] = "one day's artefact"
    return out


def runs_needed(cfg: FleetConfig, n_groups: int = 1) -> int:
    """n_min: the fewest runs over a section with which a map error found in ``p_detect`` of
    the runs passes the binomial test (alpha / n_groups) with probability >= ``power``."""
    for n in range(1, 10_000):
        k = np.arange(1, n + 1)
        ok = stats.binom.sf(k - 1, n, cfg.p_false) < cfg.alpha / max(n_groups, 1)
        if ok.any() and stats.binom.sf(k[ok][0] - 1, n, cfg.p_detect) >= cfg.power:
            return n
    return 10_000


def reliability(rows: list[dict], lines: dict, trains: dict,
                cfg: FleetConfig = FleetConfig()) -> dict:
    """Whether the consensus can be trusted where it finds nothing (module docstring):
    {"reliable", "reasons": [...], "n_min", "lines": {line: {...}}, "parameters": {...}}."""
    n_min = runs_needed(cfg)
    reasons = []
    per_line: dict = {}
    for ln in sorted({r["line"] for r in rows}):
        lr = [r for r in rows if r["line"] == ln]
        ok = [r for r in lr if not r.get("error")]
        n_tr = len({r["train"] for r in ok})
        good = len(ok) >= n_min and n_tr >= cfg.min_trains
        per_line[ln] = {"runs": len(lr), "analysed": len(ok), "failed": len(lr) - len(ok),
                        "trains": n_tr, "reliable": good}
        if not good:
            reasons.append(f"line {ln}: {len(ok)} of {len(lr)} runs analysed ({n_tr} trains); "
                           f"{n_min} runs of {cfg.min_trains} trains are needed to find or "
                           "exclude a map error")
        for s in (lines.get(ln) or {}).get("sections", []):
            s["too_few_runs"] = s["runs_passed"] < n_min
    per_par: dict = {}
    for p, d in trains.get("parameters", {}).items():
        n = len(d.get("trains", {}))
        per_par[p] = {"trains": n, "reliable": n >= 3}
        if n < 3:
            reasons.append(f"{p}: values of {n} trains; a departure needs 3")
    return {"reliable": not reasons, "reasons": reasons, "n_min": n_min, "lines": per_line,
            "parameters": per_par}


@dataclass
class FleetResult:
    lines: dict
    trains: dict
    map_errors: list  # [{"line", "start", "end", "permille", ...}]
    train_alerts: list  # [{"train", "parameter", "kind", "z", ...}]
    config: dict
    reliability: dict = field(default_factory=dict)  # see ``reliability``
    readers: dict = field(default_factory=dict)  # fleet_readers.reader_consensus


def consensus(rows: list[dict], cfg: FleetConfig = FleetConfig()) -> FleetResult:
    """Line and train consensus of the analysed runs (rows without an ``error``)."""
    ok = [r for r in rows if not r.get("error")]
    lines = line_consensus(ok, cfg)
    trains = train_consensus(ok, cfg)
    maps = [dict(s, line=ln) for ln, d in lines.items() for s in d["sections"]
            if s["verdict"] == "map error"]
    return FleetResult(lines=lines, trains=trains, map_errors=maps,
                       train_alerts=trains["alerts"], config=asdict(cfg),
                       reliability=reliability(rows, lines, trains, cfg),
                       readers=reader_consensus(ok, cfg.alpha))
