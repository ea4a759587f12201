"""The search over causes: greedy stages, prior odds, the refit at a cause's own noise and the
joint refit of the accepted linear causes.

Decision (the same for every cause): the score is the BIC-penalised log-likelihood ratio
against the current null with the prior odds of K causes against ``none``,
``2 (ll_cause - ll_null) - k ln n - 2 ln K`` (k = the cause's parameter count, profiled ones
included; n = number of scalar measurements of the likelihood it lives in; K = causes scored in
the stage). A cause is accepted when its score is > 0; ``none`` has score 0. Causes outside
the motion model have likelihoods of their own (the clock, the link). Greedy: the best cause is
put into the null (its fit fixed, noise refitted) and the rest are scored again; at the end the
accepted causes that are linear in their parameters are refitted jointly (a cause accepted
first must not keep the part of a later one it absorbed).
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from train_core.model import Line, TrainParams

from ..measured import MeasuredRun
from .causes import BY_NAME, REGISTRY, SCORING
from .causes.drive import parabola
from .confirm import CONFIRM, _null_of, confirm, unneeded, unpiece
from .contradict import place_seen
from .gain import GainContext
from .motion import Motion
from .phases import sensor_residuals, structure
from .residuals import sensor_entry
from .result import CauseFit, Diagnosis, clean, rounded
from .run import DiagConfig, prepare
from .series import series
from .stage import Null, Stage

# The score applied below, as stated in diagnose --help and in report.json (a test compares them)
SCORE_FORMULA = ("2 (ll_cause - ll_null) - k ln n - 2 ln K (BIC-penalised log-likelihood ratio; "
                 "k: the cause's parameter count, n: measurements, K: causes scored in the stage)")

# The structure test's thresholds (phases.structure): a family at 1e-3 / families (chi-square),
# its cells beyond 3 SE and 0.02 m/s^2 (about 2 per mille of gradient: a simulated bag whose
# world had no such effect showed a significant 0.010 m/s^2 in low-speed braking); a balise
# reading off the odometer's track by more than 3 SE and 2 m (a balise's location accuracy is
# metres: less is not a finding even where the reading's stated variance is smaller)
STRUCTURE = {"alpha": 1e-3, "cell_z": 3.0, "min_accel": 0.02, "max_entries": 3,
             "min_offset": 2.0}


@dataclass
class _Search:
    """The state of the greedy search over one run."""

    mo: Motion
    cfg: DiagConfig
    own: dict  # cause -> its own likelihood test (clock, link)
    skip: set  # untestable or already accepted causes of their own likelihood
    null: Null = field(default_factory=Null)
    accepted: list = field(default_factory=list)  # [CauseFit]
    merged: list = field(default_factory=list)  # [CauseFit] accepted, then replaced (merge)
    stages: list = field(default_factory=list)  # [{"null_loglik", "q", "r_s", "scores", ...}]
    first: tuple | None = None  # (first stage, its null)


def diagnose(data: MeasuredRun, line: Line, train: TrainParams, config: DiagConfig | None = None,
             progress: Callable[[int, int, str], None] | None = None) -> Diagnosis:
    """Diagnose one run (``config``: default :class:`DiagConfig`). Raises
    :class:`DiagnoseError` on unusable input."""
    cfg = config if config is not None else DiagConfig()
    total = 3 + 2 * cfg.stages

    def tick(i, what):
        if progress is not None:
            progress(i, total, what)

    run = prepare(data, line, cfg, train)
    tick(1, "clock and link")
    own = {c.name: res for c in REGISTRY if (res := c.own_test(run)) is not None}
    untestable = []
    for c in SCORING:
        why = c.untestable(run, cfg, own.get(c.name))
        if why is not None:
            untestable.append({"cause": c.name, "why": why})
    tick(2, "motion model")
    sr = _Search(Motion(run, line, train, cfg), cfg, own, {u["cause"] for u in untestable})
    st = None
    for stage_i in range(cfg.stages):
        st = _stage(sr, stage_i, tick)
        best = max(sr.stages[-1]["scores"].values(), key=lambda f: f.score, default=None)
        if best is None or best.score <= 0:
            break
        _accept(sr, best, stage_i)
    else:
        # every stage accepted a cause: the last stage's noise is that of the model without
        # the last one, which the unmodelled cause inflated (its process noise absorbs it, and
        # at that noise the held-out filter follows the odometer through what the cause
        # predicts: a resistance change that scored ~1,000 moved the held-out statistic by
        # 0.5-3.3 when it came third after the clock and the link). The joint refit and the
        # confirmation run at the noise of the model with every accepted cause.
        st = Stage(sr.mo, sr.null, cfg, big=False)
    before = {a.cause: BY_NAME[a.cause].resolution(a, sr.mo) for a in sr.accepted}
    joint_refit(sr.mo, sr.null, sr.accepted, cfg, (st.q, st.r_s))
    # Occam's steps: one cause for what two were fitted to, one over the run for a section
    # that holds every stop; a cause they bring in is resolved before its joint refit
    for step in (merge, unlocate):
        if step(sr, (st.q, st.r_s)):
            before.update({a.cause: BY_NAME[a.cause].resolution(a, sr.mo)
                           for a in sr.accepted if a.cause not in before})
            joint_refit(sr.mo, sr.null, sr.accepted, cfg, (st.q, st.r_s))
    tick(total - 1, "confirmation and gain")
    first_stage, first_null = sr.first
    first_stage.null = first_null
    gctx = GainContext(sr.mo, first_stage, cfg, own)
    return _verdict(sr, run, untestable, before, (st.q, st.r_s), gctx)


def _verdict(sr: _Search, run, untestable: list, before: dict, noise,
             gctx: GainContext) -> Diagnosis:
    """Confirm the accepted causes, test what the confirmed model leaves, rank, and the held-out
    gain of the cause named."""
    mo, beta = sr.mo, run.clock["beta"]
    # the command-time offset of the model of every accepted cause (a traction delay brings
    # the one profiled with it): every model compared below has it, so that a model with a
    # cause and one without it differ by that cause only, not by a re-timing of all commands
    shift = _null_of(mo, sr.null.shift, sr.accepted).shift
    checks = confirm(mo, shift, sr.accepted, before, sr.cfg, noise, sr.own, gctx)
    reconfirm(sr, before, noise, gctx, checks)
    confirmed = [a for a in sr.accepted if a.status == "confirmed"]
    found, tests = structure(mo, _null_of(mo, shift, confirmed), sr.cfg, noise,
                             beta, **STRUCTURE)
    if found:
        pieces = unpiece(mo, shift, confirmed, sr.cfg, noise, found)
        confirmed = [a for a in sr.accepted if a.status == "confirmed"]
        if unneeded(mo, shift, confirmed, sr.cfg, noise, found) or pieces:
            confirmed = [a for a in sr.accepted if a.status == "confirmed"]
            found, tests = structure(mo, _null_of(mo, shift, confirmed), sr.cfg, noise,
                                     beta, **STRUCTURE)
    for u in found:
        u.pop("mask")
        u.pop("meas", None)
    clock = [_clock_entry(c, _speeds(mo, beta, c["when"], c["when"]))
             for c in mo.run.clock.get("steps") or []]
    ch = mo.run.clock.get("rate_change")
    if ch is not None:
        end = mo.run.duration / beta
        clock.append(_rate_entry(ch, end, _speeds(mo, beta, ch["when"], end)))
    # the odometer's readings against what it states, under the confirmed model
    sens = sensor_residuals(mo, _null_of(mo, shift, confirmed), sr.cfg, noise)
    sensor = [sensor_entry(sens, _speeds(mo, beta, 0.0, mo.run.duration / beta))] \
        if sens["finding"] else []
    verdict = confirmed[0].cause if confirmed else \
        ("unexplained" if found or clock or sensor else "none")
    ranking = _ranking(sr, beta, "confirmed" if verdict == "none" else "rejected")
    top = ranking[0] if confirmed else None
    unexplained = clock + [_entry(u, ranking) for u in found] + sensor
    evidence = _evidence(sr, run)
    evidence["_model"]["sensors"] = sens
    evidence["_model"]["confirmation"] = {"checks": checks, "thresholds": vars(CONFIRM)}
    evidence["_model"]["structure"] = {"tests": tests, "found": found,
                                       "thresholds": STRUCTURE}
    gain = BY_NAME[top.cause].gain(top, gctx) if top is not None else \
        {"metric": f"{verdict}: no confirmed cause to extend the model with", "before": None,
         "after": None}
    plots = series(mo, confirmed, sr.own)
    plots["unexplained"] = unexplained
    return Diagnosis(cause=verdict, parameters=top.parameters if top is not None else {},
                     ranking=ranking, untestable=untestable, evidence=evidence, gain=gain,
                     accepted=confirmed, series=plots, unexplained=unexplained)


# how the reasons of a cause that is not confirmed for want of evidence begin (confirm.py):
# its fit is not shown beyond doubt, which contradicts nothing
WITHOUT_EVIDENCE = ("held-out check failed", "below resolution",
                    "parameters at nominal after the joint refit")


def reconfirm(sr: _Search, before: dict, noise, gctx: GainContext, checks: dict) -> None:
    """Confirm the confirmed causes again without the accepted causes that were not confirmed.

    A cause's held-out check runs against the model of every other accepted cause, and the
    greedy stages fitted it on top of the causes accepted before it: a cause that is then not
    confirmed (a low-adhesion section contradicted by the phase split) still shaped what was
    found beside it (a gradient that fills the section's excess at one stop). Every confirmed
    cause must hold in the model it is reported in: the confirmed ones are refitted jointly
    without the others (:func:`joint_refit`, on copies) and confirmed again; a cause that fails
    then is not confirmed, with the reason, and the step repeats until no more fall. The
    reported parameters stay those of the whole accepted model's refit.

    Only causes the checks contradicted are left out (``WITHOUT_EVIDENCE``: a cause whose fit
    is merely not shown beyond doubt, by its held-out check or its resolution, stays in the
    model the others are confirmed in): each cause is confirmed given the others, so a true
    cause whose held-out check lacked the power does not take a true one beside it down
    with it (a gradient fitted to 0.5 % was left unconfirmed once the resistance change
    beside it, which failed its held-out check, was taken out and the gradient's refit took
    the resistance's part)."""
    for _ in range(len(sr.accepted)):
        confirmed = [a for a in sr.accepted if a.status == "confirmed"]
        dropped = [a.cause for a in sr.accepted if a.status != "confirmed"
                   and not (a.why or "").startswith(WITHOUT_EVIDENCE)]
        kept = [a for a in sr.accepted if a.status != "confirmed" and a.cause not in dropped]
        if not dropped or not confirmed:
            return
        sub = copy.deepcopy(confirmed)
        rest = copy.deepcopy(kept)
        shift = _null_of(sr.mo, sr.null.shift, sub + rest).shift
        joint_refit(sr.mo, Null(shift=shift), sub + rest, sr.cfg, noise)
        again = confirm(sr.mo, shift, sub + rest, before, sr.cfg, noise, sr.own, gctx)
        fell = [(a, s) for a, s in zip(confirmed, sub) if s.status != "confirmed"]
        if not fell:
            return
        for a, s in fell:
            a.status = "not confirmed"
            a.why = f"without {', '.join(dropped)} (not confirmed): {s.why}"
            checks[a.cause]["without_unconfirmed"] = again[a.cause]


# how the reason of a balise latency entry begins (tools.diagnose tells the entry by it)
LATENCY_WHY = "the balise readings lie behind the odometer's position"


def _entry(u: dict, ranking: list) -> dict:
    """An ``unexplained`` entry: the signature and the listed cause that came closest (the
    first not confirmed in the ranking) with why it does not fit (for a balise reader's
    latency, the clock: the one listed cause about time stamps)."""
    if u.get("family") == "balise_latency":
        return {"phase": "all", "where": None, "when": None, "speed": u["speed"],
                "size": u["size"],
                "best_listed": {"cause": "clock_drift",
                                "why": f"{LATENCY_WHY} in proportion to the speed they were "
                                       f"read at ({u['size']:+.3f} s x speed): the balise "
                                       "reader stamps them late; the train's clock stamps "
                                       "the odometer and the balises alike"}}
    best = next((r for r in ranking if r.status != "confirmed" and r.cause != "none"), None)
    if best is None:
        listed = None
    elif best.status == "not confirmed":
        listed = {"cause": best.cause, "why": best.why}
    else:
        listed = {"cause": best.cause, "why": f"rejected: score {best.score:.1f} is not above "
                                              "none's 0 (not supported by the data)"}
    return {"phase": u["phase"], "where": u["where"], "when": u["when"], "speed": u["speed"],
            "size": u["size"], "best_listed": listed}


def _speeds(mo, beta: float, t0: float, t1: float) -> list:
    """[v0, v1] m/s: the train's speed from stamp t0 to t1 (s since the first odometer stamp;
    5th and 95th percentiles, or the speed at t0 when t0 == t1)."""
    t, v = mo.grid.t, mo.v_ref
    if t1 <= t0:
        x = float(np.interp(t0 * beta, t, v))
        return [x, x]
    m = (t >= t0 * beta) & (t <= t1 * beta)
    vv = v[m] if m.any() else v
    return [float(np.percentile(vv, 5)), float(np.percentile(vv, 95))]


def _clock_entry(step: dict, speed: list) -> dict:
    """An ``unexplained`` entry for a step of the train's clock (run.prepare): ``when`` the
    stamp it happened at (one point, on the clock before it), ``size`` the step in s (the
    readings after it are analysed on the clock before it)."""
    w, j = step["when"], step["step"]
    return {"phase": "all", "where": None, "when": [w, w], "speed": speed, "size": j,
            "best_listed": {"cause": "clock_drift",
                            "why": f"the train's clock jumped by {j:+.3f} s at once and held "
                                   "the new reading (the odometer's sample grid moved): a "
                                   "drift is a rate"}}


# how the reason of a clock rate entry begins (tools.diagnose tells the entry by it)
RATE_WHY = "the train clock's rate changes at"


def _rate_entry(ch: dict, end: float, speed: list) -> dict:
    """An ``unexplained`` entry for a change of the train clock's rate (run.prepare):
    ``when`` from the change to the end, ``size`` the s the clock reads more by the end than
    one rate says."""
    return {"phase": "all", "where": None, "when": [ch["when"], end], "speed": speed,
            "size": ch["offset"],
            "best_listed": {"cause": "clock_drift",
                            "why": f"{RATE_WHY} {ch['when']:.0f} s, from "
                                   f"{1e6 * ch['drift_before']:+.0f} to "
                                   f"{1e6 * ch['drift_after']:+.0f} ppm: a drift is one rate"}}


def _stage(sr: _Search, stage_i: int, tick) -> Stage:
    """Score every cause not yet accepted against the current null (one greedy stage)."""
    mo, cfg, null = sr.mo, sr.cfg, sr.null
    tick(3 + 2 * stage_i, f"stage {stage_i + 1}: noise and filter")
    st = Stage(mo, null, cfg)
    # the common command-time offset (nuisance) is re-estimated under every stage's null:
    # estimated under a null that misses a large effect it can be far off, and a wrong
    # offset would then pass for a brake delay. Where a long latency tail took the offset's
    # grid beyond the configured one (motion.shift_grid), the noise is fitted again at the
    # offset found and the offset profiled again at that noise until it settles: fitted at an
    # offset half a second off the process noise came out a hundred times too large and hid
    # every effect. Within the configured grid the noise fitted at the stage's start is kept
    # (fitting it again there too, a traction delay composed with a power limit was
    # contradicted by its split by command level, a check that does not yet allow for the
    # limit capping the re-timed traction)
    if not null.brake_extra:
        again = mo.shifts[-1] > cfg.shift_grid[1] + 1e-9
        for _ in range(3 if again else 1):
            s_hat, _ = st.nuisance_shift()
            if s_hat == null.shift:
                break
            null.shift = s_hat
            st = Stage(mo, null, cfg) if again else Stage(mo, null, cfg, noise=(st.q, st.r_s))
    tick(4 + 2 * stage_i, f"stage {stage_i + 1}: causes")
    ll0 = st.null_ll()
    done = {a.cause for a in sr.accepted}
    scores = {}
    for c in SCORING:
        if c.name in sr.skip or c.name in done:
            continue
        scores[c.name] = c.score(st, sr.own.get(c.name), ll0)
    _reprofile(sr, st, scores)
    _refit_noise(sr, st, scores, ll0)
    # Prior odds: `none` against K causes, each 1/K as likely a priori as some effect at
    # all (BIC is the log Bayes factor at even odds): 2 ln K off every score. Without it
    # every cause tested is a chance of a false alarm (10 % of nominal bags with K = 9).
    prior = 2.0 * math.log(max(len(scores), 1))
    for f in scores.values():
        f.score -= prior
        f.prior_odds_penalty = prior
    sr.stages.append({"null_loglik": ll0, "q": st.q, "r_s": st.r_s, "scores": scores,
                      "shift": null.shift})
    if sr.first is None:
        sr.first = (st, copy.deepcopy(null))
    return st


def _refit_noise(sr: _Search, st: Stage, scores: dict, ll0: float) -> None:
    """A cause's likelihood ratio with the noise re-maximised under it: an unmodelled effect
    inflates the null's process noise q, which understates the effect's own evidence. For the
    ``noise_refits`` causes of the motion model with the largest log-likelihood gain (in
    place). By gain, not by penalised score: at the inflated q a large effect's gain is small
    but still above the one-parameter causes' noise-level gains, while its penalty (a section
    has three parameters) can rank it below them, and a cause left out here is never
    reconsidered at its own noise."""
    n = st.n_meas
    prelim = sorted((c for c in scores if BY_NAME[c].in_motion_model),
                    key=lambda c: -scores[c].dll)[:sr.cfg.noise_refits]
    for name in prelim:
        f = scores[name]
        if f.score < -20.0:
            continue
        st_c = Stage(sr.mo, _extended(sr, f), sr.cfg, big=False, noise=None)
        dll_c = BY_NAME[name].dll_at_noise(st, st_c, ll0)
        if dll_c > f.dll:
            f.dll_common_noise = f.dll
            f.dll = dll_c
            f.score = 2 * dll_c - f.k * math.log(n)
            f.noise = (st_c.q, st_c.r_s)


def _reprofile(sr: _Search, st: Stage, scores: dict) -> None:
    """Linear causes scored with the accepted profiled causes profiled again (in place).

    A power limit accepted first takes the part of a resistance or mass change that shows in
    traction at speed; against that null the change's evidence left (coasting, braking) is
    small, and a braking-rate change can fit it better. The joint refit at the end corrects the
    limit, but only with the causes accepted. So each linear cause not accepted (and not placed
    by a search of its own, a gradient section) is also scored as the gain of the model with it
    over the model without it, each fitted by :func:`joint_model` (the limit re-profiled, the
    accepted linear causes free), and gets that gain where it is larger than its own, with its
    parameters from that fit and the re-profiled values in ``extra["reprofiled"]`` (acted on
    when it is accepted)."""
    nonlin = [a for a in sr.accepted if not BY_NAME[a.cause].linear]
    if not any(BY_NAME[a.cause].profiled for a in nonlin):
        return
    mo, cfg, noise = sr.mo, sr.cfg, (st.q, st.r_s)
    lin = [(a.cause, a.extra) for a in sr.accepted if BY_NAME[a.cause].linear]
    ll_without = joint_model(mo, sr.null.shift, nonlin, lin, cfg, noise)[0]
    for name, f in scores.items():
        c = BY_NAME[name]
        if not c.linear or c.located:
            continue
        ll, _, n, th, cov, blocks, fits = joint_model(mo, sr.null.shift, nonlin,
                                                      lin + [(name, None)], cfg, noise)
        dll = ll - ll_without
        if dll <= f.dll:
            continue
        stj, i, k = blocks[-1]
        f.parameters, f.std_errors, f.extra = c.params(stj, th[i:i + k], cov[i:i + k, i:i + k])
        f.extra = {**f.extra, "reprofiled": {a.cause: dict(a.parameters) for a in fits}}
        f.dll, f.k, f.n, f.noise = dll, k, n, None
        f.score = 2 * dll - k * math.log(n)


def _extended(sr: _Search, f: CauseFit) -> Null:
    """The current null with the cause ``f`` put in; where ``f`` was scored with the profiled
    causes re-profiled (:func:`_reprofile`), with them moved as its fit moved them."""
    moved = f.extra.get("reprofiled")
    if not moved:
        null = copy.deepcopy(sr.null)
        BY_NAME[f.cause].extend_null(null, f, sr.mo)
        return null
    fits = [dataclasses.replace(a, parameters=dict(moved.get(a.cause, a.parameters)))
            for a in sr.accepted]
    return _null_of(sr.mo, sr.null.shift, fits + [f])


def _accept(sr: _Search, best: CauseFit, stage_i: int) -> None:
    """Put the stage's best cause into the null (refitted at its own noise first, unless it was
    scored with the profiled causes re-profiled: then they move with it)."""
    cause = BY_NAME[best.cause]
    moved = best.extra.get("reprofiled")
    if best.noise is not None and not moved:
        refit_at_own_noise(sr.mo, sr.null, cause, best, sr.cfg)
    null = _extended(sr, best)
    for a in sr.accepted:
        if moved and a.cause in moved:
            a.parameters = dict(moved[a.cause])
    sr.accepted.append(CauseFit(best.cause, best.score, best.parameters,
                                std_errors=best.std_errors, extra=best.extra,
                                stage=stage_i + 1))
    sr.null = null
    if not cause.in_motion_model:
        sr.skip.add(best.cause)


def refit_at_own_noise(mo: Motion, null: Null, cause, fit: CauseFit, cfg: DiagConfig,
                       rounds: int = 2) -> None:
    """Re-fit an accepted cause's parameters at the noise of the model that includes it (in
    place). Its first fit ran at the null's noise, which the cause itself inflated (a slip
    episode not modelled makes q 100x too large, and at that q the filter follows the odometer
    and the slip fraction is barely determined): fit, re-maximise the noise under the extended
    null, fit again."""
    for _ in range(rounds):
        st = Stage(mo, null, cfg, noise=fit.noise)
        _, _, fit.parameters, fit.std_errors, fit.extra = cause.fit(st)
        null_c = copy.deepcopy(null)
        cause.extend_null(null_c, fit, mo)
        st_c = Stage(mo, null_c, cfg, big=False)
        fit.noise = (st_c.q, st_c.r_s)


def joint_refit(mo: Motion, null: Null, accepted: list, cfg: DiagConfig, noise) -> None:
    """Re-estimate the accepted linear causes' parameters jointly (in place).

    Greedy stages fit each cause on top of the earlier ones held fixed: a cause accepted first
    absorbs part of a later one's effect (a gradient section fitted before a resistance
    change is biased by it). Given the discrete choices (sections, delays, slip episodes,
    command offset), the accepted linear causes are one GLS problem: fit them together. An
    accepted cause with a profiled parameter (a power limit), fitted before the linear ones,
    took part of them: it is profiled again with them free (:func:`joint_model`)."""
    lin = [a for a in accepted if BY_NAME[a.cause].linear]
    nonlin = [a for a in accepted if not BY_NAME[a.cause].linear]
    if not lin or (len(lin) < 2 and not any(BY_NAME[a.cause].profiled for a in nonlin)):
        return
    _, _, _, th, cov, blocks, fits = joint_model(mo, null.shift, nonlin,
                                                 [(a.cause, a.extra) for a in lin], cfg, noise)
    for a, f in zip(nonlin, fits):
        a.parameters, a.std_errors = f.parameters, f.std_errors
    for a, (st, i, k) in zip(lin, blocks):
        a.parameters, a.std_errors, a.extra = BY_NAME[a.cause].params(
            st, th[i:i + k], cov[i:i + k, i:i + k], a.extra)


# rounds of the drive's gain (a mass change) with the drive increments scaled by it
GAIN_ROUNDS = 4


def joint_model(mo: Motion, shift: float, nonlinear: list, members: list, cfg: DiagConfig,
                noise) -> tuple:
    """One model fitted as the joint refit fits the accepted one: the ``nonlinear`` fits
    (copies) with their profiled parameters (a power limit's p_spec) profiled with the linear
    ``members`` ([(cause, extra)]) free, then those fitted jointly (GLS) on the null of the
    nonlinear fits, at ``noise``. Returns (ll, k, n, theta, cov, blocks [(stage, first, count)
    per member], the nonlinear fits).

    A mass change scales the whole delivered drive, the nonlinear causes' increments (a power
    limit's deficit, a traction delay's re-timing, a low-adhesion section) too: the truth is
    k a_delivered where the linear mass column is k a_believed. With a mass change among the
    members, the fit is repeated with those increments scaled by the mass change's gain
    (``Null.drive_gain``) until the gain settles: its fixed point is that product."""
    fits = copy.deepcopy(nonlinear)
    free_of = [CauseFit(c, 0.0, {}, extra=extra) for c, extra in members]
    gain = 1.0
    for _ in range(GAIN_ROUNDS):
        for f in fits:
            if BY_NAME[f.cause].profiled:
                _profile_jointly(mo, shift, fits, free_of, f, cfg, noise, gain)
        null = _null_of(mo, shift, fits)
        null.drive_gain = gain
        st = Stage(mo, null, cfg, noise=noise)
        free, blocks = [], []
        for c, extra in members:
            f = BY_NAME[c].free(st, extra)
            blocks.append((st, len(free), len(f)))
            free += f
        th, cov, ll, _ = st.fit({}, free)
        new = next((BY_NAME[c].params(st, th[i:i + k], cov[i:i + k, i:i + k], extra)[2]
                    ["traction_gain"] for (c, extra), (_, i, k) in zip(members, blocks)
                    if c == "mass"), None)
        if new is None or not null.extra or abs(new - gain) < 1e-5:
            break
        gain = new
    return ll, len(free), st.n_meas, th, cov, blocks, fits


def merge(sr: _Search, noise) -> bool:
    """Occam's step after the greedy stages: accepted linear causes that one other listed
    cause explains together are replaced by it when the whole model's score says so (in place;
    True when a merge was made).

    Greedy selection fixes each cause on top of the ones before: a power limit fitted first
    takes most of a heavier or lighter train's traction change, and what is left, in braking
    and coasting, is then fitted as a braking-rate change plus a resistance change (five
    parameters) where one mass change (one parameter) acts in every phase at once. Each
    alternative is the accepted model with a set S of two or more of its linear causes replaced
    by one linear cause C not accepted. Each model is fitted as the joint refit fits the
    accepted one: its profiled nonlinear parameters (a power limit's p_spec) profiled with its
    linear causes free, then those fitted jointly (GLS), at one noise; the models are compared
    by the search's own criterion for a whole model, ``2 ll - k ln n - 2 ln K`` per cause
    (:data:`SCORE_FORMULA`). The replaced fits go to ``sr.merged`` with the reason."""
    mo, cfg = sr.mo, sr.cfg
    names = {a.cause for a in sr.accepted}
    cands = [c for c in SCORING if c.linear and not c.located and c.name not in names
             and c.name not in sr.skip]
    lin = [a for a in sr.accepted if BY_NAME[a.cause].linear]
    if len(lin) < 2 or not cands:
        return False
    nonlin = [a for a in sr.accepted if not BY_NAME[a.cause].linear]
    prior = 2.0 * math.log(max(len(sr.stages[0]["scores"]), 1))

    def model(members):
        return joint_model(mo, sr.null.shift, nonlin, members, cfg, noise)

    ll_a, k_a, n, _, _, _, _ = model([(a.cause, a.extra) for a in lin])
    best = None
    for r in range(2, len(lin) + 1):
        for group in itertools.combinations(lin, r):
            rest = [(a.cause, a.extra) for a in lin if a not in group]
            for c in cands:
                ll_b, k_b, _, th, cov, blocks, _ = model(rest + [(c.name, None)])
                gain = 2.0 * (ll_b - ll_a) - (k_b - k_a) * math.log(n) + (r - 1) * prior
                if gain > 0 and (best is None or gain > best[0]):
                    best = (gain, group, c, ll_b, k_a - k_b, th, cov, blocks[-1], rest)
    if best is None:
        return False
    gain, group, c, ll_b, fewer, th, cov, (st, i, k), rest = best
    params, se, extra = c.params(st, th[i:i + k], cov[i:i + k, i:i + k], None)
    dll = ll_b - model(rest)[0]
    fit = CauseFit(c.name, 2.0 * dll - k * math.log(n) - prior, params, dll=dll, k=k, n=n,
                   std_errors=se, extra=extra, prior_odds_penalty=prior,
                   stage=min(a.stage for a in group))
    at = sr.accepted.index(group[0])
    for a in group:
        _retire(sr, a, f"one {c.name} change explains it and "
                       f"{', '.join(b.cause for b in group if b is not a)} together: the model "
                       f"with it scores {gain:.1f} above the one with them ({len(group) - 1} "
                       f"cause(s) and {fewer} parameter(s) fewer)")
    sr.accepted.insert(at, fit)
    merge(sr, noise)  # the merged model may merge again
    return True


def _retire(sr: _Search, a: CauseFit, why: str) -> None:
    """Take the accepted fit ``a`` out of the model: ``rejected`` with ``why``, kept in
    ``sr.merged`` for the ranking."""
    sr.accepted.remove(a)
    a.status, a.why = "rejected", why
    sr.merged.append(a)


def unlocate(sr: _Search, noise) -> bool:
    """Occam's step for a cause at a place whose "only here" the run cannot test (in place;
    True when a cause was replaced).

    A low-adhesion section says that braking is weaker on its stretch and only there. The
    second half is tested by the brake applications outside the stretch at its speeds (the
    place test's cells). Where the run has none that could show it (no cell where a departure
    of half the section would be a 3 SE result, :func:`.contradict.place_seen`: every stop of
    the run lies on the stretch), the section and a braking-rate change over the whole run
    make the same claim on these data, and the section's window search (one parameter more,
    the best of every stretch) wins by chance by leaving out the few light brake applications
    around it: on an independent simulator's bags with every brake x 0.82 and x 0.84 the
    sections covered 1.3-12.8 km and 0.3-6.6 km (every stop, but the last 3.5 m of one) and
    scored 2.8 and 3.2 above the braking-rate change. The
    section is then replaced by its ``global_rival`` (fitted jointly with the other accepted
    linear causes, shown with its first-stage score) when that cause alone scored above
    ``none`` in the first stage. The replaced fit goes to ``sr.merged`` with the reason."""
    mo, cfg = sr.mo, sr.cfg
    out = False
    for a in list(sr.accepted):
        cause = BY_NAME[a.cause]
        glob = cause.global_rival
        alone = sr.stages[0]["scores"].get(glob) if glob is not None else None
        if alone is None or alone.score <= 0 or glob in sr.skip \
                or (bey := cause.beyond(a, mo)) is None \
                or place_seen(mo, _null_of(mo, sr.null.shift, sr.accepted), cfg, noise, *bey,
                              CONFIRM.split_min_share):
            continue
        rest = [b for b in sr.accepted if b is not a]
        nonlin = [b for b in rest if not BY_NAME[b.cause].linear]
        members = [(b.cause, b.extra) for b in rest if BY_NAME[b.cause].linear]
        at = sr.accepted.index(a)
        _retire(sr, a, f"the run brakes too little outside [{a.parameters['start']:.0f}, "
                       f"{a.parameters['end']:.0f}) m at its speeds to show the braking normal "
                       f"anywhere else, and one {glob} change over the run says the same with "
                       f"a parameter fewer")
        out = True
        # the rival takes the section's place with its first-stage score (its score alone
        # against the believed model, as the section's was), fitted jointly with the other
        # accepted causes without the section: an accepted one held only what the section
        # left (a section over most stops, then f 0.98-0.995 for the stops outside it where
        # every brake was x 0.85-0.92), and a lone linear cause has no joint refit after this
        have = next((b for b in rest if b.cause == glob), None)
        if have is not None:
            at -= sr.accepted.index(have) < at
            sr.accepted.remove(have)
            members = [m for m in members if m[0] != glob]
        _, _, _, th, cov, blocks, _ = joint_model(mo, sr.null.shift, nonlin,
                                                  members + [(glob, None)], cfg, noise)
        st_b, i, k = blocks[-1]
        params, se, extra = BY_NAME[glob].params(st_b, th[i:i + k], cov[i:i + k, i:i + k],
                                                 None)
        sr.accepted.insert(at, CauseFit(glob, alone.score, params, dll=alone.dll, k=alone.k,
                                        n=alone.n, std_errors=se, extra=extra,
                                        prior_odds_penalty=alone.prior_odds_penalty,
                                        stage=a.stage))
    return out


def _profile_jointly(mo: Motion, shift: float, accepted: list, lin: list, fit: CauseFit,
                     cfg: DiagConfig, noise, gain: float = 1.0) -> bool:
    """Re-fit the profiled parameter of the accepted cause ``fit`` (``Cause.profile``) jointly
    with the free columns of the accepted linear causes ``lin`` (in place): one augmented
    filter over [the other nonlinear causes' null, s0, the linear causes' columns, the
    candidate columns]; per candidate the exact log-likelihood with s0 and the linear
    coefficients at their GLS values; the best refined by a parabola in log value. True when
    it was re-fitted."""
    cause = BY_NAME[fit.cause]
    others = [b for b in accepted if b is not fit and not BY_NAME[b.cause].linear]
    null = _null_of(mo, shift, others)
    null.drive_gain = gain  # the drive's gain from a mass change among lin (joint_model)
    st = Stage(mo, null, cfg, noise=noise, big=False)
    prof = cause.profile(st)
    if prof is None:
        return False
    name, values, R = prof
    n_ev = mo.ev.t.size
    dv, ds, mv_d, mv_v = [], [], [], []
    for b in lin:
        for combo in BY_NAME[b.cause].free(st, b.extra):
            if all(c in mo.col for c in combo):
                dv.append(sum(w * mo.Dv[:, mo.col[c]] for c, w in combo.items()))
                ds.append(sum(w * mo.Ds[:, mo.col[c]] for c, w in combo.items()))
            elif set(combo) == {"scale"}:
                mv_d.append(combo["scale"] * mo.sc_d)
                mv_v.append(combo["scale"] * mo.sc_v)
            else:  # a column the profile does not know how to free
                return False
    Cv, Cs = mo.grid.integrate(R, n_ev)
    nf, k = len(dv), len(values)
    drift = (np.column_stack(dv + [Cv]), np.column_stack(ds + [Cs]))
    meas = (np.column_stack(mv_d), np.column_stack(mv_v)) if mv_d else None
    W = st.augmented(st.fv, st.fs, drift=drift, meas=meas).W
    free = [1] + list(range(2, 2 + nf)) + list(range(2 + nf + k, W.shape[0]))
    A = W[np.ix_(free, free)]
    ll = np.empty(k)
    for j in range(k):
        u = np.zeros(W.shape[0])
        u[0] = u[2 + nf + j] = 1.0
        b = W[free] @ u
        ll[j] = -0.5 * (u @ W @ u - b @ np.linalg.lstsq(A, b, rcond=None)[0])
    i = int(np.argmax(ll))
    x_hat, se_x = parabola(np.log(values), ll, i)
    value = math.exp(x_hat)
    fit.parameters = {**fit.parameters, name: value}
    fit.std_errors = {**fit.std_errors, name: value * se_x}
    return True


def _reported(fit: CauseFit, beta: float, status: str | None = None) -> CauseFit:
    """A ranking entry: score rounded, parameters as docs/interfaces.md reports them."""
    return CauseFit(fit.cause, rounded(fit.score),
                    BY_NAME[fit.cause].report(clean(fit.parameters), beta),
                    status=status or fit.status, why=fit.why, extra=fit.extra)


def _ranking(sr: _Search, beta: float, none_status: str) -> list:
    """Confirmed causes in the order accepted, then the accepted ones not confirmed, then the
    rest (rejected) by their last score, ``none`` (with ``none_status``) among them."""
    ranking = [_reported(a, beta) for a in sr.accepted if a.status == "confirmed"]
    ranking += [_reported(a, beta) for a in sr.accepted if a.status != "confirmed"]
    ranking += [_reported(a, beta) for a in sr.merged]
    seen = {a.cause for a in sr.accepted + sr.merged}
    first, last = sr.stages[0]["scores"], sr.stages[-1]["scores"]
    rest = [_reported(last.get(c.name, first[c.name]), beta, "rejected") for c in REGISTRY
            if c.name not in seen and c.name in first]
    rest.append(CauseFit("none", 0.0, {}, status=none_status))
    rest.sort(key=lambda r: -r.score)
    return ranking + rest


def _evidence(sr: _Search, run) -> dict:
    """Per cause: its fit alone at the first stage; the model's clocks, noise and notes."""
    evidence = {}
    for cause, f in sr.stages[0]["scores"].items():
        evidence[cause] = {"score_alone": rounded(f.score), "loglik_gain": rounded(f.dll),
                           "n_params": f.k, "n": f.n,
                           "parameters_alone": clean(f.parameters),
                           "std_errors": clean(f.std_errors),
                           "details": clean({k: v for k, v in f.extra.items()
                                             if k != "profile"})}
    for a in sr.accepted:
        evidence.setdefault(a.cause, {})["accepted_at_stage"] = a.stage
        evidence[a.cause]["std_errors"] = clean(a.std_errors)
    clock = sr.own.get("clock_drift", {})
    evidence["_model"] = {"clock": {"offset_s": run.clock["alpha"], "rate": run.clock["beta"],
                                    "jitter_std_s": clock.get("jitter_std")},
                          "command_offset_s": sr.stages[0]["shift"],
                          "stages": [{"null_loglik": rounded(s["null_loglik"]), "q": s["q"],
                                      "r_s": s["r_s"]} for s in sr.stages],
                          "samples": int(sr.mo.ev.odo.size), "balises": int(sr.mo.ev.bal.size),
                          "duration_s": run.duration,
                          "score": SCORE_FORMULA, "notes": run.notes}
    return evidence
