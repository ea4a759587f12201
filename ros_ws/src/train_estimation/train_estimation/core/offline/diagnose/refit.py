"""The accepted model refitted as a whole, after the greedy stages of :mod:`.search`: the joint
refit of the accepted linear causes (with the profiled parameters of the nonlinear ones profiled
again), and Occam's steps: accepted causes replaced by one listed cause that explains them
together (:func:`merge`), a cause at a place replaced by the same change over the whole run
where the run cannot test its "only here" (:func:`unlocate`).
"""

from __future__ import annotations

import copy
import itertools
import math
from typing import TYPE_CHECKING

import numpy as np

from .causes import BY_NAME, SCORING
from .causes.drive import parabola
from .confirm import CONFIRM, _null_of
from .contradict import place_seen
from .motion import Motion
from .result import CauseFit
from .run import DiagConfig
from .stage import Null, Stage, combo_drift

if TYPE_CHECKING:  # the search's state (search.py imports this module)
    from .search import _Search


def refit_given_others(sr: _Search, noise) -> None:
    """Where two or more motion causes are accepted and none of them is linear (so that
    :func:`joint_refit` has nothing to refit), each one that is not profiled (a delay, a
    section, slips) fitted again on the model of all the others at ``noise``, the noise of the
    model with every accepted cause, as the held-out check's folds fit it on half the data.
    A cause accepted at a greedy stage was fitted on that stage's null, at its noise and
    command-time offset, before the causes after it: a traction delay accepted after a power
    limit came out 1.73 s where the folds' fits gave 1.86 and 1.91 s (the truth 1.85 s), and
    its effect, too small, was contradicted by its phase split (needed x1.34 in traction);
    fitted again so, 1.92 +- 0.05 s. A profiled cause keeps its fit (a subtle power limit
    refitted beside a brake delay below resolution was contradicted by its split by command
    level). The null is rebuilt from the accepted causes."""
    motion = [a for a in sr.accepted if BY_NAME[a.cause].in_motion_model]
    if len(motion) < 2 or any(BY_NAME[a.cause].linear for a in motion):
        return
    shift = sr.null.shift
    for a in motion:
        if BY_NAME[a.cause].profiled:
            continue  # (a power limit: profiled again at its acceptance, refit_at_own_noise)
        others = [b for b in sr.accepted if b is not a]
        st = Stage(sr.mo, _null_of(sr.mo, shift, others), sr.cfg, noise=noise)
        _, _, a.parameters, a.std_errors, extra = BY_NAME[a.cause].fit(st)
        a.extra = {**a.extra, **extra}
    sr.null = _null_of(sr.mo, shift, sr.accepted)


def joint_refit(mo: Motion, null: Null, accepted: list, cfg: DiagConfig, noise,
                rivals: list = ()) -> None:
    """Re-estimate the accepted linear causes' parameters jointly (in place).

    Greedy stages fit each cause on top of the earlier ones held fixed: a cause accepted first
    absorbs part of a later one's effect (a gradient section fitted before a resistance
    change is biased by it). Given the discrete choices (sections, delays, slip episodes,
    command offset), the accepted linear causes are one GLS problem: fit them together. An
    accepted cause with a profiled parameter (a power limit), fitted before the linear ones,
    took part of them: it is profiled again with them free (:func:`joint_model`). ``rivals``:
    rival laws' fits held in the model (:func:`.confirm.rival_fit`)."""
    lin = [a for a in accepted if BY_NAME[a.cause].linear]
    nonlin = [a for a in accepted if not BY_NAME[a.cause].linear]
    if not lin or (len(lin) < 2 and not any(BY_NAME[a.cause].profiled for a in nonlin)):
        return
    _, _, _, th, cov, blocks, fits = joint_model(mo, null.shift, nonlin,
                                                 [(a.cause, a.extra) for a in lin], cfg, noise,
                                                 rivals)
    for a, f in zip(nonlin, fits):
        a.parameters, a.std_errors = f.parameters, f.std_errors
    for a, (st, i, k) in zip(lin, blocks):
        a.parameters, a.std_errors, a.extra = BY_NAME[a.cause].params(
            st, th[i:i + k], cov[i:i + k, i:i + k], a.extra)


# rounds of the drive's gain (a mass change) with the drive increments scaled by it
GAIN_ROUNDS = 4


def joint_model(mo: Motion, shift: float, nonlinear: list, members: list, cfg: DiagConfig,
                noise, rivals: list = ()) -> tuple:
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
                _profile_jointly(mo, shift, fits, free_of, f, cfg, noise, gain, rivals)
        null = _null_of(mo, shift, fits, rivals)
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
        if new is None or not (null.extra or null.brake_sections) or abs(new - gain) < 1e-5:
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
    (:data:`.verdict.SCORE_FORMULA`). The replaced fits go to ``sr.merged`` with the reason."""
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
                     cfg: DiagConfig, noise, gain: float = 1.0, rivals: list = ()) -> bool:
    """Re-fit the profiled parameter of the accepted cause ``fit`` (``Cause.profile``) jointly
    with the free columns of the accepted linear causes ``lin`` (in place): one augmented
    filter over [the other nonlinear causes' null, s0, the linear causes' columns, the
    candidate columns]; per candidate the exact log-likelihood with s0 and the linear
    coefficients at their GLS values; the best refined by a parabola in log value. True when
    it was re-fitted."""
    cause = BY_NAME[fit.cause]
    others = [b for b in accepted if b is not fit and not BY_NAME[b.cause].linear]
    null = _null_of(mo, shift, others, rivals)
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
            if (drift := combo_drift(mo, combo)) is not None:
                dv.append(drift[0])
                ds.append(drift[1])
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
