"""``wheel_slip``: episodes in which the odometer's axle turns faster (slip) or slower (slide)
than the train moves; the counted distance keeps the excess afterwards.

Candidate episodes are where the null's standardised speed innovation is large; each is fitted
as an interval [t0, t1) with its own peak slip fraction and a shape of the fraction over the
interval (motion.SLIP_SHAPES: held, or built up and died away as adhesion is lost and
regained), the shape chosen by the likelihood with its ramp charged as one parameter more
(ln n), the boundaries profiled at the decimated odometer rate (per-sample measurement columns,
contiguous weighted sums); then neighbours that are one episode are merged and episodes that do
not pay for themselves in the joint fit are dropped (:func:`refine_episodes`). Each episode's
depth is reported at its peak: 1 - odometer speed / train speed (> 0: the odometer misses
speed, a slide; < 0: it reads too much, a slip); its shape is in the details (``shapes``)."""

from __future__ import annotations

import functools
import math

import numpy as np
from train_core.effects import WheelSlipEffect

from train_estimation.core.numerics.augmented_kf import gls
from train_estimation.core.offline.identify import moving_average

from ..motion import counted, odometer_speed, slip_cols, slip_shape
from .base import Cause, resolved

# s: neighbouring episodes closer than this are tested as one (refine_episodes)
MERGE_GAP = 10.0
# s: the longest episode searched as one interval (a wheel slide under wheel-slide protection
# can last a whole brake application, tens of seconds)
MAX_EPISODE = 30.0
# s: a window's samples reach this far before its first and after its last large innovation
# (the filter reacts within a sample or two; a step's onset is found to a sample)
PAD_BEFORE, PAD_AFTER = 2.0, 3.0
# s: as far for a shaped episode: a slip that builds up as a half sine crosses the threshold
# seconds after its onset (2 s cut 4 s off a 12 s one). A step keeps the narrower pads: wider,
# a 1.6 % step fitted a drag on a stretch (a motion misfit) at a departure.
PAD_SHAPED = 5.0
# -, the smallest slip fraction an episode is reported with: the odometer's speed is good to
# about 1 % (wheel diameter, calibration), so a smaller one is not a slip
MIN_DEPTH = 0.01


class WheelSlip(Cause):
    name = "wheel_slip"
    family = "odometer"
    # No halves test, by what the cause is: episodes each with a depth and shape of their own
    # (the rail's adhesion at that moment), so the episodes of the run's two halves are not two
    # estimates of one quantity, and the held-out folds (alternate odometer samples) each hold
    # every episode whole, so their fits agree whatever the odometer does. What a halves test
    # asks of one size is asked of each episode instead: held out on its own, and its readings
    # must show its step where it begins and ends (heldout.heldout_episodes,
    # contradict.slip_step).
    halves = ()

    def fit(self, st) -> tuple:
        cands = _candidates(st)
        null_ll = st.null_ll()
        if not cands:
            return null_ll, 3, {"intervals": []}, {}, {"candidates": 0}
        wins = _windows(cands)
        samples, Md, Mv = _sample_columns(st, wins)
        kf = st.augmented(st.fv, st.fs, meas=(Md, Mv))
        nc = samples.size
        u = np.zeros(nc + 2)
        u[0] = 1.0
        e1 = np.zeros(nc + 2)
        e1[1] = 1.0
        base_quad = gls(kf.W, np.stack([u, e1], axis=1))[2]
        pen = 3 * math.log(st.n_meas)
        # a shaped episode's ramp is one parameter more than a step's (module docstring)
        extra = {"step": 0.0, "sine": math.log(st.n_meas)}
        t = st.mo.ev.t[st.mo.ev.odo]
        ts = t[samples]
        runs = {sh: [2 + np.flatnonzero((ts >= w0 - pb) & (ts <= w1 + pa)) for w0, w1 in wins]
                for sh, (pb, pa) in _pads(extra).items()}
        chosen = [(float(t[samples[c[0] - 2]]), float(t[samples[c[-1] - 2] + 1]), shape)
                  for c, shape in _forward_selection(
                      kf.W, u, e1, {sh: [r for r in rs if r.size] for sh, rs in runs.items()},
                      pen, extra)]
        if not chosen:
            return null_ll, 3, {"intervals": []}, {}, {"candidates": len(cands)}
        ivs, th, se_th, quad_now = refine_episodes(st, chosen, pen, extra)
        eps, se = _fractions(th, se_th)
        return null_ll + 0.5 * (base_quad - quad_now), \
            3 * len(ivs) + sum(iv[2] != "step" for iv in ivs), \
            {"intervals": [[iv[0], iv[1]] for iv in ivs], "depths": [-e for e in eps]}, \
            {"slip_fraction": se, "depths": se}, \
            {"slip_fraction": eps, "column": th, "shapes": [iv[2] for iv in ivs],
             "candidates": len(cands), "found": len(chosen)}

    def resolution(self, fit, mo) -> str | None:
        """An episode is resolved when its slip fraction is more than ``MIN_DEPTH`` and 3 SE
        from 0 and it lasts at least one odometer period."""
        t = mo.ev.t[mo.ev.odo]
        period = float(np.median(np.diff(t))) if t.size > 1 else 0.0
        eps = fit.extra.get("slip_fraction", [])
        se = fit.std_errors.get("slip_fraction", [None] * len(eps))
        why = "below resolution: no episode"
        for (t0, t1), e, s in zip(fit.parameters.get("intervals", []), eps, se):
            r = resolved(f"slip fraction on [{t0:.1f}, {t1:.1f}] s", e, s, MIN_DEPTH)
            if r is None and t1 - t0 >= period:
                return None
            why = r or f"below resolution: episode shorter than one odometer period ({period:g} s)"
        return why

    def keep_episodes(self, fit, keep: list) -> None:
        """Keep only the episodes ``keep`` (indices) of ``fit``, in place: their intervals,
        depths, fractions (and standard errors) and columns."""
        n = len(fit.parameters.get("intervals", []))
        for d in (fit.parameters, fit.std_errors, fit.extra):
            for k in ("intervals", "depths", "shapes", "slip_fraction", "column"):
                if isinstance(d.get(k), list) and len(d[k]) == n:
                    d[k] = [d[k][i] for i in keep]

    def extend_null(self, null, fit, mo) -> None:
        """The episodes' columns at their fitted coefficients (see :func:`_fractions`)."""
        th = fit.extra.get("column")
        if th is None:
            th = [e / (1.0 + e) for e in fit.extra.get("slip_fraction", [])]
        shapes = _shapes(fit)
        for (t0, t1), c, shape in zip(fit.parameters["intervals"], th, shapes):
            null.slip.append((t0, t1, c, shape))

    def report(self, params: dict, beta: float) -> dict:
        params["intervals"] = [[a / beta, b / beta] for a, b in params.get("intervals", [])]
        return params

    def effect(self, params: dict, duration: float) -> WheelSlipEffect:
        fr = [-x for x in params.get("depths", []) if x is not None]
        return WheelSlipEffect(tuple(tuple(iv) for iv in params.get("intervals", [])),
                               float(np.mean(fr)) if fr else 0.0)

    def model_effect(self, fit, ctx):
        """One slip fraction for all episodes (as the simulator's effect has), times on true
        time from the start of the run."""
        k = 1.0 + ctx.drift
        ivs = [[round(float(t0) / k, 3), round(float(t1) / k, 3)]
               for t0, t1 in fit.parameters.get("intervals", []) if t1 > t0 >= 0.0]
        if not ivs:
            return None, None
        frac = float(np.clip(slip_fraction(fit, ctx), -0.9, 1.0))
        return WheelSlipEffect(tuple(tuple(iv) for iv in ivs), round(frac, 5),
                               shape=_one_shape(fit)), None

    def gain(self, fit, ctx) -> dict:
        """Odometer speed minus the model's smoothed speed inside the episodes, raw against
        corrected by the fitted slip (the episodes are local: nothing to hold out)."""
        run = ctx.mo.run
        ivs = fit.parameters.get("intervals", [])
        if not ivs:
            return {"metric": "odometer speed error in the slip episodes (m/s)", "before": None,
                    "after": None}
        inside = np.zeros(run.odo_t.size, bool)
        corr = np.ones(run.odo_t.size)
        for (t0, t1) in ivs:
            inside |= (run.odo_t >= t0) & (run.odo_t < t1)
        w = max(1, int(round(3.0 / max(np.median(np.diff(run.odo_t)), 1e-3))))
        ref = moving_average(run.odo_v, w)
        # the reference outside the episodes: interpolate across them
        ref_i = np.interp(run.odo_t, run.odo_t[~inside], ref[~inside]) if (~inside).any() \
            else ref
        eps = float(np.mean(run.odo_v[inside] / np.maximum(ref_i[inside], 0.1) - 1.0))
        corr[inside] = 1.0 + eps
        before = float(np.sqrt(np.mean((run.odo_v[inside] - ref_i[inside]) ** 2)))
        after = float(np.sqrt(np.mean((run.odo_v[inside] / corr[inside] - ref_i[inside]) ** 2)))
        return {"metric": "odometer speed error in the slip episodes (m/s), raw vs corrected "
                          "by the fitted slip (local: not held out)", "before": before,
                "after": after}

    def series(self, params: dict, mo, out: dict) -> None:
        out["slip_intervals"] = params["intervals"]


def _candidates(st) -> list:
    """[t0, t1] of the candidate episodes, strongest first (at most max_slip_candidates)."""
    cfg, ev = st.cfg, st.mo.ev
    o = ev.odo
    s0_hat = st.fit({}, [])[3]
    nu = (st.kf.E0[o, 0] + s0_hat * st.kf.E1[o, 0]) / np.sqrt(st.kf.S_v[o])
    t = ev.t[o]
    cands = []
    for k in np.flatnonzero(np.abs(nu) > cfg.slip_threshold):
        if cands and t[k] - cands[-1][1] < 3.0:
            cands[-1][1] = t[k]
        else:
            cands.append([t[k], t[k]])
    cands = sorted(cands, key=lambda c: -np.max(np.abs(nu[(t >= c[0]) & (t <= c[1])])))
    return cands[:cfg.max_slip_candidates]


def _windows(cands: list) -> list:
    """The windows searched for one episode each: every candidate, and every span from one
    candidate to a later one within ``MAX_EPISODE`` s. A long episode shows in the null's speed
    innovations at its onset and at its end only (in between, the filter follows the odometer),
    so its two candidates are far apart and neither window alone holds the whole episode."""
    out = [(float(c0), float(c1)) for c0, c1 in cands]
    by_time = sorted(out)
    for i, (a0, _) in enumerate(by_time):
        for _, b1 in by_time[i + 1:]:
            if b1 - a0 <= MAX_EPISODE:
                out.append((a0, b1))
    return out


def _pads(shapes) -> dict:
    """shape -> (s before, s after) a window's first and last large innovation searched."""
    return {sh: (PAD_BEFORE, PAD_AFTER) if sh == "step" else (PAD_SHAPED, PAD_SHAPED)
            for sh in shapes}


def _sample_columns(st, wins: list):
    """Per-sample slip columns over every window (each odometer sample once): (odometer event
    index i of each column (ascending), Md, Mv) with column j the slip of bin [t_i, t_i+1) at
    unit fraction. A window's samples are a contiguous run of columns."""
    mo, ev = st.mo, st.mo.ev
    o = ev.odo
    t = ev.t[o]
    keep = np.zeros(t.size, bool)
    pb, pa = max(PAD_BEFORE, PAD_SHAPED), max(PAD_AFTER, PAD_SHAPED)
    for w0, w1 in wins:
        keep |= (t >= w0 - pb) & (t <= w1 + pa)
    keep[-1] = False  # the last sample has no bin after it
    samples = np.flatnonzero(keep)
    n, nc = ev.t.size, samples.size
    Md = np.zeros((n, nc))
    Mv = np.zeros((n, nc))
    # as motion.slip_cols: the odometer's own speed and counted distance (they hold the slip)
    v = odometer_speed(mo, t[samples])
    d = counted(mo, t[samples + 1]) - counted(mo, t[samples])
    for j, i in enumerate(samples):
        Mv[o[i], j] = v[j]
        Md[o[i + 1:], j] = d[j]
    return samples, Md, Mv


def _forward_selection(W, u, e1, runs: dict, pen: float, extra: dict) -> list:
    """Episodes added one at a time, each a contiguous run of columns within one window
    (``runs``: shape -> each window's column indices, in time order) weighted by a shape
    (motion.SLIP_SHAPES: all alike, or a half sine over the run), the one that most improves the
    joint fit of the episodes chosen so far, while it pays its BIC penalty ``pen`` (plus
    ``extra[shape]``). Returns the chosen episodes as (column indices, shape).

    Every episode's distance excess persists in the counted distance, so episodes compete for
    the same evidence: an episode's gain and its best boundaries are those given the episodes
    already chosen (the chosen columns and s0 are profiled out of W, a Schur complement), not
    those it has alone -- alone, a short episode after a long slide would take its window's
    whole width to explain the slide's persisting distance deficit."""
    chosen: list[tuple] = []
    nuis = [e1]
    quad_now = gls(W, np.stack([u, e1], axis=1))[2]
    while True:
        N = np.stack(nuis, axis=1)
        WN = W @ N
        P = W - WN @ np.linalg.solve(N.T @ WN, WN.T)
        best = None
        taken = np.zeros(W.shape[0], bool)
        for c, _ in chosen:
            taken[c] = True
        for shape, charge in extra.items():
            for idx in runs[shape]:
                # episodes do not overlap (two at once would be one episode of varying
                # depth): a window gives runs outside the chosen ones
                free = idx[~taken[idx]]
                if free.size == 0:
                    continue
                cut = np.flatnonzero(np.diff(free) > 1) + 1
                for part in np.split(free, cut):
                    q, a, b = _best_run(P, u, part) if shape == "step" else \
                        _best_shaped(P, u, part, shape)
                    if best is None or q + charge < best[0] + best[3]:
                        best = (q, part[a:b], shape, charge)
        if best is None or not math.isfinite(best[0]) or \
                quad_now - best[0] - pen - best[3] <= 0:
            return chosen
        col = np.zeros(W.shape[0])
        col[best[1]] = _run_weights(best[2], best[1].size)
        chosen.append((best[1], best[2]))
        nuis.append(col)
        quad_now = best[0]


@functools.lru_cache(maxsize=4096)
def _run_weights(shape: str, n: int) -> np.ndarray:
    """The shape's weights of the n per-sample columns of a run (at each bin's middle; cached:
    the search asks for the same lengths over and over; read-only)."""
    w = slip_shape(shape, (np.arange(n) + 0.5) / n)
    w.flags.writeable = False
    return w


# the shaped runs searched: start and end on a lattice of at most this many samples of a run,
# then every sample within one lattice step of the best
SHAPED_LATTICE = 40


def _best_shaped(P: np.ndarray, u: np.ndarray, idx: np.ndarray, shape: str) -> tuple:
    """:func:`_best_run` for a run weighted by ``shape`` (no prefix sums: the weights depend on
    the run's length): the runs starting and ending on a lattice first, then every run within
    one lattice step of the best at each end. (quad, a, b)."""
    n = idx.size
    pu = P[idx] @ u
    C = P[np.ix_(idx, idx)]
    uPu = float(u @ P @ u)
    D = np.abs(np.diag(C))

    def score(pairs):
        pairs = [(a, b) for a, b in pairs if 0 <= a < b <= n]
        if not pairs:
            return math.inf, 0, 0
        Wm = np.zeros((len(pairs), n))
        for r, (a, b) in enumerate(pairs):
            Wm[r, a:b] = _run_weights(shape, b - a)
        aS = Wm @ pu
        cS = np.einsum("ij,ij->i", Wm @ C, Wm)
        ok = cS > 1e-9 * (Wm * Wm) @ D
        quad = np.where(ok, uPu - aS * aS / np.where(ok, cS, 1.0), np.inf)
        k = int(np.argmin(quad))
        return float(quad[k]), pairs[k][0], pairs[k][1]

    step = max(1, math.ceil(n / SHAPED_LATTICE))
    ends = sorted(set(range(0, n, step)) | {n})
    q, a, b = score([(a, b) for i, a in enumerate(ends) for b in ends[i + 1:]])
    if step > 1 and math.isfinite(q):
        q, a, b = score([(a + i, b + j) for i in range(-step, step + 1)
                         for j in range(-step, step + 1)])
    return q, a, b


def _best_run(P: np.ndarray, u: np.ndarray, idx: np.ndarray) -> tuple:
    """The contiguous run [a, b) of the columns ``idx`` whose sum, with one free coefficient,
    best explains the data with the nuisances already profiled out of ``P``: (quad, a, b);
    quad = u'Pu - (c'Pu)^2 / c'Pc, all runs at once from prefix sums. A run that the nuisances
    already span (c'Pc ~ 0 relative to c'Wc's diagonal part) is skipped."""
    pu = P[idx] @ u
    C = P[np.ix_(idx, idx)]
    A = np.concatenate([[0.0], np.cumsum(pu)])
    S = np.zeros((idx.size + 1, idx.size + 1))
    S[1:, 1:] = np.cumsum(np.cumsum(C, axis=0), axis=1)
    D = np.concatenate([[0.0], np.cumsum(np.abs(np.diag(C)))])
    i, j = np.triu_indices(idx.size + 1, k=1)
    aS = A[j] - A[i]
    cS = S[j, j] - S[i, j] - S[j, i] + S[i, i]
    ok = cS > 1e-9 * (D[j] - D[i])
    quad = np.where(ok, float(u @ P @ u) - aS * aS / np.where(ok, cS, 1.0), np.inf)
    k = int(np.argmin(quad))
    return float(quad[k]), int(i[k]), int(j[k])


def refine_episodes(st, intervals: list, pen: float, extra: dict | None = None) -> tuple:
    """One episode where the data say one, and only episodes that pay for themselves.

    A long episode shows in the null's speed innovations at its onset and its end (in between
    the filter, its noise inflated by the episode, follows the odometer), so the search can
    return it as two or more pieces. Here, on the joint fit of all episodes (one filter run per
    round over each episode's columns and each merge of neighbours closer than ``MERGE_GAP``,
    the merge in each shape), the merge that costs least is made while it costs less than the
    parameters it saves (an episode's BIC penalty ``pen``, 3 ln n, plus ``extra[shape]`` for a
    shaped one), then the episode whose removal costs least is dropped while that costs less
    than its penalty, then the shallowest episode below the resolution (|slip fraction| <=
    ``MIN_DEPTH`` or within 3 standard errors of 0: a piece that only trims a neighbour's
    edge) while there is one. ``intervals``: (t0, t1) or (t0, t1, shape). Returns (intervals
    as (t0, t1, shape), column coefficients (:func:`_fractions`; with a shape, at its peak),
    their standard errors, quadratic form of the final joint fit)."""
    extra = extra or {"step": 0.0}
    ivs = sorted((float(iv[0]), float(iv[1]), iv[2] if len(iv) > 2 else "step")
                 for iv in intervals)

    def cost(iv):
        return pen + extra.get(iv[2], 0.0)

    for _ in range(2 * len(ivs) + 1):
        pairs = [(i, sh) for i in range(len(ivs) - 1) if ivs[i + 1][0] - ivs[i][1] < MERGE_GAP
                 for sh in extra]
        W, cols = _episode_filter(st, ivs + [(ivs[i][0], ivs[i + 1][1], sh)
                                             for i, sh in pairs])
        n = len(ivs)
        q_all = _quad(W, cols, range(n))
        merges = [(_quad(W, cols, [j for j in range(n) if j not in (i, i + 1)] + [n + m])
                   - q_all - cost(ivs[i]) - cost(ivs[i + 1]) + cost((0, 0, sh)), i, sh)
                  for m, (i, sh) in enumerate(pairs)]
        if merges and min(merges)[0] < 0:
            _, i, sh = min(merges)
            ivs[i:i + 2] = [(ivs[i][0], ivs[i + 1][1], sh)]
            continue
        drops = [(_quad(W, cols, [j for j in range(n) if j != i]) - q_all - cost(ivs[i]), i)
                 for i in range(n)] if n > 1 else []
        if drops and min(drops)[0] < 0:
            del ivs[min(drops)[1]]
            continue
        th, cov, q = gls(W, cols[:, :2 + n])
        se = np.sqrt(np.clip(np.diag(cov)[1:], 0, None))
        th = th[1:]
        eps, se_eps = _fractions(th, se)
        weak = [(abs(e), i) for i, (e, s) in enumerate(zip(eps, se_eps))
                if resolved("", e, s, MIN_DEPTH) is not None]
        if n > 1 and weak:
            del ivs[min(weak)[1]]
            continue
        return ivs, th.tolist(), se.tolist(), float(q)
    raise RuntimeError("episode refinement did not settle")  # pragma: no cover - bounded


def _shapes(fit) -> list:
    """Each episode's shape of ``fit`` (motion.SLIP_SHAPES, in its details: the report's
    parameters are the contract's; ``step`` where it gives none)."""
    n = len(fit.parameters.get("intervals", []))
    sh = list(fit.extra.get("shapes") or [])
    return sh if len(sh) == n else ["step"] * n


def _one_shape(fit) -> str:
    """The one shape of a simulator's effect: ``sine`` if every episode is one, else ``step``."""
    sh = _shapes(fit)
    return "sine" if sh and all(x == "sine" for x in sh) else "step"


def _fractions(th, se_th) -> tuple[list, list]:
    """Slip fractions (and standard errors) from the coefficients of the episode columns.

    A column is the odometer's own speed (and counted distance) inside the episode
    (motion.slip_cols), which already holds the episode: there it reads (1 + eps) v. The
    odometer's excess eps v is then theta (1 + eps) v, so eps = theta / (1 - theta) (a 10 %
    slip would be read as 9.1 %, a 25 % slide as 33 % without it); d eps / d theta =
    1 / (1 - theta)^2."""
    eps, se = [], []
    for t, s in zip(th, se_th):
        d = 1.0 - float(t)
        eps.append(float(t) / d if d > 0 else math.inf)
        se.append(float(s) / d**2 if d > 0 else math.inf)
    return eps, se


def _quad(W, cols, sel) -> float:
    """Quadratic form of the joint fit of the episodes ``sel`` (indices of the columns)."""
    return gls(W, cols[:, [0, 1] + [2 + j for j in sel]])[2]


def _episode_filter(st, ivs: list) -> tuple:
    """The augmented filter over [null, s0, one measurement column per interval (unit slip
    fraction)]: (W, identity selector over its columns)."""
    n_ev = st.mo.ev.t.size
    Md = np.zeros((n_ev, len(ivs)))
    Mv = np.zeros((n_ev, len(ivs)))
    for j, iv in enumerate(ivs):
        Md[:, j], Mv[:, j] = slip_cols(st.mo, [iv])
    kf = st.augmented(st.fv, st.fs, meas=(Md, Mv), update=st.update)
    return kf.W, np.eye(len(ivs) + 2)


def slip_fraction(fit, ctx) -> float:
    """The slip fraction of an accepted wheel_slip for a model (one value for all episodes):
    the mean of the fitted per-episode fractions the diagnosis reports, else measured from the
    odometer speed inside the episodes against the speed just around them."""
    ev = (ctx.evidence or {}).get("wheel_slip", {})
    for src in (ev.get("details", {}) if isinstance(ev, dict) else {}, ev):
        v = src.get("slip_fraction") if isinstance(src, dict) else None
        if v is not None and not isinstance(v, dict):
            vals = [float(x) for x in np.atleast_1d(v) if x is not None and math.isfinite(x)]
            if vals and all(abs(x) < 1.0 for x in vals):
                return float(np.mean(vals))
    t = np.asarray(ctx.odo_stamp, float) - ctx.t_first
    v = np.asarray(ctx.odo_speed, float)
    order = np.argsort(t)
    t, v = t[order], v[order]
    ratios = []
    for t0, t1 in fit.parameters.get("intervals", []):
        inside = (t >= t0) & (t < t1)
        around = ((t >= t0 - 3.0) & (t < t0)) | ((t >= t1) & (t < t1 + 3.0))
        if inside.any() and around.sum() >= 2:
            ref = np.interp(t[inside], t[around], v[around])
            ok = ref > 1.0
            if ok.any():
                ratios.append(float(np.mean(v[inside][ok] / ref[ok] - 1.0)))
    return float(np.mean(ratios)) if ratios else 0.0


CAUSE = WheelSlip()
