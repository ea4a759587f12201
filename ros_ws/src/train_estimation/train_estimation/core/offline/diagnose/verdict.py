"""The verdict of a search (:mod:`.search`): the accepted causes confirmed (:mod:`.confirm`), what
the confirmed model leaves (``unexplained``: the structure test, the clock's steps and rate
changes, the odometer's readings), the ranking, the evidence and the held-out gain of the cause
named, as report.json states them.
"""

from __future__ import annotations

import copy
from typing import TYPE_CHECKING

import numpy as np

from .causes import BY_NAME, REGISTRY
from .confirm import (
    CONFIRM,
    NOT_SHOWN,
    _null_of,
    confirm,
    refit_rivals,
    undecided,
    unneeded,
    unpiece,
    without_evidence,
)
from .gain import GainContext
from .phases import balise_residuals, sensor_residuals, structure
from .refit import joint_refit
from .residuals import balise_entry, sensor_entry
from .result import CauseFit, Diagnosis, clean, rounded
from .series import series
from .stage import Null, Stage

if TYPE_CHECKING:  # the search's state (search.py imports this module)
    from .search import _Search

# The score the search applies (search._stage), as stated in diagnose --help and in report.json
# (a test compares them)
SCORE_FORMULA = ("2 (ll_cause - ll_null) - k ln n - 2 ln K (BIC-penalised log-likelihood ratio; "
                 "k: the cause's parameter count, n: measurements, K: causes scored in the stage)")

# The structure test's thresholds (phases.structure): a family at 1e-3 / families (chi-square),
# its cells beyond 3 SE and 0.02 m/s^2 (about 2 per mille of gradient: a simulated bag whose
# world had no such effect showed a significant 0.010 m/s^2 in low-speed braking); a balise
# reading off the odometer's track by more than 3 SE and 2 m (a balise's location accuracy is
# metres: less is not a finding even where the reading's stated variance is smaller)
STRUCTURE = {"alpha": 1e-3, "cell_z": 3.0, "min_accel": 0.02, "max_entries": 3,
             "min_offset": 2.0}


def conclude(sr: _Search, run, untestable: list, before: dict, noise,
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
    noise, left_out = verdict_noise(sr, shift, noise)
    confirmed = [a for a in sr.accepted if a.status == "confirmed"]
    # the rival laws that took an accepted cause's effect (brakes that fade as they heat for a
    # braking-rate drift) are part of the model what is left is tested in: the effect is in
    # the data, and is reported as the law's entry (below), not found again in pieces
    rivals = refit_rivals(mo, shift, confirmed, _rivals(sr), sr.cfg, noise)
    found, tests = structure(mo, _null_of(mo, shift, confirmed, rivals), sr.cfg, noise,
                             beta, **STRUCTURE)
    if found:
        pieces = unpiece(mo, shift, confirmed, sr.cfg, noise, found, rivals)
        confirmed = [a for a in sr.accepted if a.status == "confirmed"]
        if unneeded(mo, shift, confirmed, sr.cfg, noise, found, rivals=rivals) or pieces:
            confirmed = [a for a in sr.accepted if a.status == "confirmed"]
            found, tests = structure(mo, _null_of(mo, shift, confirmed, rivals), sr.cfg,
                                     noise, beta, **STRUCTURE)
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
    model = _null_of(mo, shift, confirmed, rivals)
    whole = _speeds(mo, beta, 0.0, mo.run.duration / beta)
    sens = sensor_residuals(mo, model, sr.cfg, noise)
    sensor = [sensor_entry(sens, whole)] if sens["finding"] else []
    # and the balise readings', unless the structure found their shape already
    bal = balise_residuals(mo, model, sr.cfg, noise, found)
    if bal["finding"]:
        sensor.append(balise_entry(bal, whole))
    law = [_rival_entry(a, r) for a, r in zip(
        [a for a in sr.accepted if a.status != "confirmed" and a.rival is not None], rivals)]
    verdict = confirmed[0].cause if confirmed else \
        ("unexplained" if found or clock or sensor or law else "none")
    ranking = _ranking(sr, beta, "confirmed" if verdict == "none" else "rejected")
    top = ranking[0] if confirmed else None
    unexplained = clock + law + [_entry(u, ranking) for u in found] + sensor
    evidence = _evidence(sr, run)
    evidence["_model"]["sensors"] = sens
    evidence["_model"]["balise_readings"] = bal
    evidence["_model"]["confirmation"] = {"checks": checks, "thresholds": vars(CONFIRM)}
    evidence["_model"]["structure"] = {"tests": tests, "found": found,
                                       "thresholds": STRUCTURE}
    if left_out:
        evidence["_model"]["structure"]["noise"] = {"q": noise[0], "r_s": noise[1],
                                                    "without": left_out}
    gain = BY_NAME[top.cause].gain(top, gctx) if top is not None else \
        {"metric": f"{verdict}: no confirmed cause to extend the model with", "before": None,
         "after": None}
    plots = series(mo, confirmed, sr.own)
    plots["unexplained"] = unexplained
    return Diagnosis(cause=verdict, parameters=top.parameters if top is not None else {},
                     ranking=ranking, untestable=untestable, evidence=evidence, gain=gain,
                     accepted=confirmed, series=plots, unexplained=unexplained)


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

    Only causes the checks contradicted are left out (:func:`.confirm.without_evidence`: a
    cause whose fit is merely not shown beyond doubt, by its held-out check or its resolution,
    stays in the model the others are confirmed in): each cause is confirmed given the
    others, so a true cause whose held-out check lacked the power does not take a true one
    beside it down with it (a gradient fitted to 0.5 % was left unconfirmed once the
    resistance change beside it, which failed its held-out check, was taken out and the
    gradient's refit took the resistance's part). A cause that lost to a rival law leaves the
    law's fit (``CauseFit.rival``) in its place, fitted again beside the refitted causes (a
    true gradient beside a braking-rate drift that brakes fading as they heat explain better
    was contradicted by the split with no weaker braking in the model)."""
    for _ in range(len(sr.accepted)):
        # a section one run cannot tell from a fixed force (confirm.UNDECIDED) was judged so
        # beside the others: it is judged again with them, as a confirmed cause is (a section
        # undecided beside a gradient and a resistance that the split then contradicted
        # predicted nothing without them: held out at Z -0.46)
        confirmed = [a for a in sr.accepted if a.status == "confirmed" or undecided(a)]
        dropped = [a.cause for a in sr.accepted if a.status != "confirmed"
                   and not without_evidence(a) and not undecided(a)]
        kept = [a for a in sr.accepted if a.status != "confirmed" and a.cause not in dropped
                and not undecided(a)]
        if not dropped or not confirmed:
            return
        # a cause that lost to a rival law leaves that law's fit in its place: its effect is
        # in the data, and the others are judged with it explained as the data prefer
        rivals = [r for r in _rivals(sr) if not r.get("undecided")]
        sub = copy.deepcopy(confirmed)
        for s in sub:
            s.rival = None
        rest = copy.deepcopy(kept)
        shift = _null_of(sr.mo, sr.null.shift, sub + rest).shift
        joint_refit(sr.mo, Null(shift=shift), sub + rest, sr.cfg, noise, rivals)
        # and the laws given the causes so refitted (the law was fitted beside the cause it
        # displaced)
        rivals = refit_rivals(sr.mo, shift, sub + rest, rivals, sr.cfg, noise)
        again = confirm(sr.mo, shift, sub + rest, before, sr.cfg, noise, sr.own, gctx,
                        rivals=rivals)
        fell = [(a, s) for a, s in zip(confirmed, sub) if s.status != "confirmed"
                and not (undecided(a) and undecided(s))]
        if not fell:
            return
        laws = "".join(f"; {r['label']}" for r in rivals)
        for a, s in fell:
            without = f"without {', '.join(dropped)} (not confirmed{laws})"
            a.status = "not confirmed"
            # an undecided reason keeps its beginning (the report and the bench tell it by it)
            a.why = f"{s.why} ({without})" if undecided(s) else f"{without}: {s.why}"
            a.rival = s.rival
            checks[a.cause]["without_unconfirmed"] = again[a.cause]


def _rivals(sr: _Search) -> list:
    """The fits of the rival laws that took the effect of an accepted cause that is not
    confirmed (``CauseFit.rival``, :func:`.confirm.rival_fit`)."""
    return [a.rival for a in sr.accepted if a.status != "confirmed" and a.rival is not None]


def _rival_entry(a: CauseFit, r: dict) -> dict:
    """An ``unexplained`` entry for the effect of the accepted cause ``a`` that a rival law
    explains better (``r``: its fit in the confirmed model, :func:`.confirm.rival_fit`;
    brakes that fade as they heat for a braking-rate drift): the
    effect is in the data (the cause passed its held-out check and its resolution) and is no
    listed cause. Phase ``braking`` (the heat law acts there), no ``where`` nor ``when`` (it
    acts at every braking), ``speed`` the speeds braked at, ``size`` the law's largest change
    of the acceleration (m/s^2; > 0: the brakes deliver less than believed), ``best_listed``
    the cause with why the law fits better. A cause that a rival law fits as well (a
    low-adhesion section and a force fixed at its place, :func:`.confirm.undecided_fit`):
    its own effect, with its stretch (``where``; no ``when``: an entry with both spans is the
    odometer's count, tools.diagnose_unexplained)."""
    acc = np.asarray(r["acc"], float)
    i = int(np.argmax(np.abs(acc))) if acc.size else 0
    return {"phase": "braking", "where": r.get("where"), "when": None,
            "speed": r["law"]["speeds"],
            "size": float(acc[i]) if acc.size else 0.0,
            "best_listed": {"cause": a.cause, "why": a.why}}


# how the reasons of a cause not confirmed because the data contradict its fitted effect begin
# (confirm.py): the phase split needs it changed by more than half of itself in a cell, or the
# odometer's readings do not step at a slip episode's ends
# a slip whose readings show no step is among them: whether its effect is in the data is
# not shown, and it took its part of the residuals out of the process noise all the same
CONTRADICTED = ("contradicted by the phase split", "not a slip", NOT_SHOWN)


def verdict_noise(sr: _Search, shift: float, noise) -> tuple:
    """The noise at which what the confirmed model leaves is tested: that of the model with
    every accepted cause (``noise``), unless one was not confirmed because the data contradict
    its fitted effect (``CONTRADICTED``); then that of the model without those, as if the
    search had not accepted them: where they were accepted after every other one (and none was
    merged or replaced since) the noise of the stage that accepted the first of them, else the
    noise fitted again without them. Returns (noise, the causes left out).

    An accepted cause takes its part of the residuals out of the process noise it is fitted
    with. A cause whose effect is not in the data still takes it (a slip episode of 2.6 s at
    the end of a traction cut, contradicted by the phase split, made the process noise 5x
    smaller), and at that noise the structure test of the model without it finds cells beside
    the remainder that only make up for its edges falling inside cells (a remainder on
    2,130-2,590 m was reported over 1,725-3,024 m, and over 2,049-2,699 m without the slip). A
    cause not confirmed for want of evidence, or for a size the railway could not have, still
    describes what the data hold, and stays (without the gradient that took most of that
    traction cut, the noise would hide the cut's place)."""
    out = [a for a in sr.accepted
           if a.status != "confirmed" and (a.why or "").startswith(CONTRADICTED)]
    if not out:
        return noise, []
    kept = [a for a in sr.accepted if all(a is not b for b in out)]
    first = min(a.stage for a in out)
    if not sr.merged and all(a.stage < first for a in kept) and first <= len(sr.stages):
        s = sr.stages[first - 1]
        return (s["q"], s["r_s"]), [a.cause for a in out]
    st = Stage(sr.mo, _null_of(sr.mo, shift, kept), sr.cfg, big=False)
    return (st.q, st.r_s), [a.cause for a in out]


# how the reason of a balise latency entry begins (tools.diagnose_unexplained tells the entry by it)
LATENCY_WHY = "the balise readings lie off the odometer's position"


# how the reason of a datum entry begins (tools.diagnose_unexplained tells the entry by it)
DATUM_WHY = "the map's gradients and the balises lie apart"


# how the reason of a balise scatter entry begins (tools.diagnose_unexplained tells it by it)
SCATTER_WHY = "the balise readings scatter about the odometer's track more than they state"


def _entry(u: dict, ranking: list) -> dict:
    """An ``unexplained`` entry: the signature and the listed cause that came closest (the
    first not confirmed in the ranking) with why it does not fit (for a balise reader's
    latency, the clock: the one listed cause about time stamps)."""
    if u.get("family") == "balise_latency":
        return _whole_run(u, "clock_drift", _latency_why(u["size"]))
    if u.get("family") == "balise_scatter":
        return _whole_run(u, "odometer_scale", (
            f"{SCATTER_WHY}: their SD is {u['size']:.2f} times the stated one over "
            f"{u['readings']} readings (p {u['p']:.2g}): the reader's timing or the balises' "
            "survey is worse than the readings' position_variance says; an odometer scale "
            "moves the readings in proportion to the distance, one misplaced balise moves one "
            "reading, not every one at random"))
    if u.get("family") == "datum":
        return _whole_run(u, "gradient", (
            f"{DATUM_WHY}: every gradient change acts {abs(u['size']):.1f} m "
            f"{'further on' if u['size'] > 0 else 'earlier'} than the balises place the run (a "
            "balise map and a gradient profile surveyed on two datums); a gradient the map "
            "lacks acts on one stretch, not at every change"))
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


def _whole_run(u: dict, cause: str, why: str) -> dict:
    """An ``unexplained`` entry of every reading (phase ``all``, no ``where`` nor ``when``) with
    the closest listed ``cause`` and ``why`` it does not fit."""
    return {"phase": "all", "where": None, "when": None, "speed": u["speed"], "size": u["size"],
            "best_listed": {"cause": cause, "why": why}}


def _latency_why(tau: float) -> str:
    """The reason of a balise latency entry (``tau`` s: the balises lie ``tau`` x speed behind
    the odometer's position at their stamps). Behind: the balise reader stamps them late.
    Ahead: the reader stamps them early, or the odometer's readings are older than their
    stamps (a sensor or link that sends them late, stamped when sent): one run's balises and
    odometer cannot tell which of the two streams is off, only that they are off each other."""
    if tau >= 0.0:
        side = ("behind", "the balise reader stamps them late")
    else:
        side = ("ahead of", "the balise reader stamps them early, or the odometer's readings "
                            "are older than their stamps (sent late, stamped when sent)")
    return (f"{LATENCY_WHY} in proportion to the speed they were read at ({tau:+.3f} s x "
            f"speed; {side[0]} it): {side[1]}; the train's clock stamps the odometer and the "
            "balises alike")


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


# how the reason of a clock rate entry begins (tools.diagnose_unexplained tells the entry by it)
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
