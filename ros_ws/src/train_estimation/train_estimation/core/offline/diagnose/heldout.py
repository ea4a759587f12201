"""The held-out checks of a cause (pure): the data the fit did not see, and the fits on the
data's halves.

A cause is confirmed on data its fit did not see (check 1 of :mod:`.confirm`): a motion cause
on alternate blocks of the run (:func:`heldout_motion`, the blocks it acts in kept whole:
:func:`place_block`), an episode cause on its own episodes left out in turn
(:func:`heldout_episodes`), a cause with a test of its own (the clock, the link) by that test
(:func:`heldout_own`). The fits on the two folds must agree within their standard errors
(:func:`halves_test`): a cause that fits the halves differently is not what it says. The
thresholds are :class:`ConfirmConfig`'s, stated in report.json's evidence.

A fold's fit runs the filter over every reading and takes its own fold's innovations only
(``Stage(fit_on=...)``, ``augmented_kf``'s ``use``): innovations are independent of one
another, so the fit does not depend on the held-out fold's innovations, and the score below
is standard normal without the effect. A fit whose filter skipped the held-out readings saw
their state error in its own later innovations, and a cause at a place fitted it there: on 96
nominal bags Z > 2 for a gradient on 15 and a section on 13 (3 and 5 this way).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np

from train_estimation.core.numerics.augmented_kf import gls

from .causes import BY_NAME
from .contradict import slip_step
from .gain import GainContext
from .motion import Motion, slip_cols
from .result import CauseFit
from .run import DiagConfig
from .stage import Null, Stage


@dataclass(frozen=True)
class ConfirmConfig:
    """The confirmation's thresholds (stated in report.json's evidence)."""

    # -, held-out score Z above this (one-sided 2.3 % under no effect) and held-out gain > 0
    heldout_z: float = 2.0
    # -, false-alarm rate of the split test of a confirmed cause (chi-square, per partition)
    split_alpha: float = 1e-3
    # -, a cell of the split contradicts the cause when its multiplier moves by more than this
    split_min_share: float = 0.5
    # a cause that acts in every phase (Cause.phase_rival) seen in one phase only is not
    # confirmed: it cannot be told from an effect of that phase or of that moment
    one_phase: bool = False
    # a cause seen in one phase only whose place test is significant with a cell beyond 3 SE
    # (even below split_min_share) is not confirmed: some of it shows in that phase elsewhere
    one_phase_elsewhere: bool = True
    # the causes' physical bounds asked of the data (Cause.plausible_data: the Davis terms of a
    # resistance >= 0)
    data_bounds: bool = True
    # -, false-alarm rate of the halves' consistency test of a cause that is what it says
    # (two-sided, shared out over the quantities compared)
    halves_alpha: float = 1e-3
    # -, the fits on the two folds disagree only where they differ by more than this share of
    # the cause's size as well (its fitted change from nominal): a difference within the
    # model's own slack (discretisation, a command-time grid) is not another cause
    halves_min_share: float = 0.1
    # -, a place cause whose rival law (Cause.speed_rival: drag growing as v^2;
    # Cause.fixed_rival: a force fixed there) fits better by 2 ln LR more than this is not
    # confirmed (equal parameter counts, each on its own best stretch): with
    # b-hat ~ N(0, se^2) under the cause, 2 ln LR ~ (2 b-hat - 1) / se^2 exceeds T with at most
    # P(Z > sqrt(T)) whatever se: 0.13 % for 9
    law_lr: float = 9.0


CONFIRM = ConfirmConfig()


FOLDS = {"motion": "alternate {:g} s blocks", "odometer": "alternate odometer samples"}


# s, the shortest held-out block of a cause at a place (ten odometer samples at 5 Hz)
MIN_PLACE_BLOCK = 2.0


def _folds(mo: Motion, family: str, cfg: DiagConfig, block: float | None = None) -> np.ndarray:
    """Fold index (parity: 0 or 1) of every event (``block``: s, None for ``gain_block``)."""
    if family == "odometer":
        return np.cumsum(mo.ev.kind == 0)
    return np.floor((mo.ev.t - mo.ev.t[0]) / (block or cfg.gain_block)).astype(int)


def place_block(mo: Motion, cause, fit: CauseFit, cfg: DiagConfig) -> float | None:
    """The held-out block of a cause at a place (``Cause.beyond``), None for any other: a
    quarter of the time it acts on its stretch, within [``MIN_PLACE_BLOCK``, ``gain_block``].
    The train runs a stretch once, often in less than one ``gain_block``: a low-adhesion
    section braked over for 8 s at a stop lay in one 30 s block, the fold without it fitted
    another stretch of 7 m, and the check failed (gain -0.009) for a cause that scored 629.
    Four blocks or more on the stretch give each fold a part of it to fit and one to predict."""
    bey = cause.beyond(fit, mo)
    if bey is None:
        return None
    t_in = float(np.count_nonzero(bey[0] & (bey[1] != 0))) * mo.grid.dt
    return float(np.clip(t_in / 4.0, MIN_PLACE_BLOCK, cfg.gain_block))


def speed_innovations(mo: Motion, null: Null, cfg: DiagConfig, noise):
    """(e, S): the filter's speed innovation and its variance at every event of the model
    ``null`` at ``noise`` (s0 by GLS; NaN where no odometer speed was updated)."""
    st = Stage(mo, null, cfg, noise=noise, big=False)
    kf = st.augmented(st.fv, st.fs, keep_innov=True)
    s0 = gls(kf.W, np.eye(2))[0][0]
    return kf.E0[:, 0] + s0 * kf.E1[:, 0], kf.S_v


def heldout_motion(mo: Motion, others: Null, cause, cfg: DiagConfig, noise,
                   ccfg: ConfirmConfig = CONFIRM, block_s: float | None = None,
                   nominal: dict | None = None, fit: CauseFit | None = None) -> dict:
    """The two-fold held-out score test of the module docstring for a motion-model cause,
    against the model ``others`` (the other accepted causes); ``block_s``: the blocks' length
    (None: ``gain_block``; a cause at a place: :func:`place_block`). Its ``halves``: the
    folds' fits compared (:func:`halves_test`; ``nominal``: {quantity: its believed value},
    for the share of the cause's size), or the cause's own (``Cause.halves_own``, given the
    whole data's ``fit``)."""
    block = _folds(mo, cause.family, cfg, block_s)
    e0, s = speed_innovations(mo, others, cfg, noise)
    num = var = 0.0
    fitted = []
    for fold in (0, 1):
        train = block % 2 == fold
        # the fold's fit on a filter that uses every reading and takes the fold's innovations
        # only (module doc)
        st_f = Stage(mo, copy.deepcopy(others), cfg, noise=noise, fit_on=train)
        _, _, params, se, extra = cause.fit(st_f)
        fit_f = CauseFit(cause.name, 0.0, params, std_errors=se, extra=extra)
        ext = copy.deepcopy(others)
        try:
            cause.extend_null(ext, fit_f, mo)
        except (KeyError, IndexError, ValueError) as exc:  # a fold without the cause's data
            fitted.append({"fold": fold, "error": str(exc)})
            continue
        e1, _ = speed_innovations(mo, ext, cfg, noise)
        n, v = _score_terms(e0, e1, s, ~train)
        num, var = num + n, var + v
        fitted.append({"fold": fold, "parameters": params,
                       "halves": cause.halves_values(params, se, extra)})
    gain, sd, z, ok = _score(num, var, ccfg)
    out = {"test": "held-out score test on the filter's speed innovations, two folds of "
                   + FOLDS[cause.family].format(block_s or cfg.gain_block), "gain_loglik": gain,
           "sd_under_no_effect": sd, "z": z, "z_needed": ccfg.heldout_z,
           "fitted_on_folds": fitted}
    out["ok"] = ok
    own = cause.halves_own(mo, others, cfg, noise, ccfg.halves_alpha, ccfg.halves_min_share,
                           fit)
    out["halves"] = halves_test(fitted, ccfg, nominal=nominal) if own is None else own
    if not out["ok"]:
        out["why"] = (f"held-out log-likelihood gain {gain:+.3g} <= 0 (SD {sd:.3g} under no "
                      f"effect; score Z {z:.2f})" if gain <= 0 or sd == 0
                      else f"score Z {z:.2f} <= {ccfg.heldout_z:g}")
    return out


def halves_test(fitted: list, ccfg: ConfirmConfig = CONFIRM, nominal: dict | None = None) -> dict:
    """The fits of a cause on the held-out check's two folds (``fitted``: each with
    ``halves``, {quantity: (value, SE)} from :meth:`Cause.halves_values`) against each other:
    a cause that is what it says has one size in both halves of the data, and each
    difference over its standard error, z = (x0 - x1) / sqrt(se0^2 + se1^2), is standard
    normal. They disagree when some |z| exceeds the two-sided ``halves_alpha`` quantile shared
    out over the quantities (Bonferroni) and the difference is more than
    ``halves_min_share`` of the cause's size (the mean fit's change from ``nominal``, where
    known): an effect of another kind that a listed cause imitates fits it differently where
    the two halves of the run differ (an actuator's shape over other commands and speeds)."""
    from train_estimation.core.numerics.special import ndtri

    vals = [f.get("halves") for f in fitted if "error" not in f]
    if len(vals) != 2 or not vals[0] or not vals[1]:
        return {"tested": False, "consistent": True}
    keys = [k for k in vals[0] if k in vals[1]]
    if not keys:
        return {"tested": False, "consistent": True}
    zc = float(-ndtri(ccfg.halves_alpha / (2 * len(keys))))
    out = {"tested": True, "consistent": True, "z_needed": zc, "quantities": {}}
    for k in keys:
        (x0, e0), (x1, e1) = vals[0][k], vals[1][k]
        z = (x0 - x1) / math.hypot(e0, e1)
        size = abs(0.5 * (x0 + x1) - (nominal or {}).get(k, 0.0)) \
            if nominal is not None and k in nominal else None
        material = size is None or abs(x0 - x1) > ccfg.halves_min_share * size
        bad = bool(abs(z) > zc and material)
        out["quantities"][k] = {"folds": [x0, x1], "z": z, "disagree": bad}
        if bad:
            out["consistent"] = False
            out["why"] = (f"the data's halves fit it differently: {k} {x0:.4g} and {x1:.4g} "
                          f"(z {z:+.1f}, beyond {zc:.1f}: {ccfg.halves_alpha:g} two-sided)")
    return out


def _score_terms(e0, e1, s, held) -> tuple[float, float]:
    """The held-out events' terms of the score test (module docstring, check 1): sum e0 d / S
    and sum d^2 / S with d = e0 - e1, over the events ``held`` out where all are finite."""
    test = held & np.isfinite(s) & np.isfinite(e0) & np.isfinite(e1) & (s > 0)
    d = (e0 - e1)[test]
    return float(np.sum(e0[test] * d / s[test])), float(np.sum(d * d / s[test]))


def _score(num: float, var: float, ccfg: ConfirmConfig) -> tuple[float, float, float, bool]:
    """(gain D, its SD under no effect, score Z, confirmed: D > 0 and Z > heldout_z)."""
    gain, sd = num - 0.5 * var, math.sqrt(var)
    z = num / sd if sd > 0 else 0.0
    return gain, sd, z, bool(gain > 0 and z > ccfg.heldout_z)


def heldout_episodes(mo: Motion, others: Null, fit: CauseFit, cfg: DiagConfig, noise,
                     ccfg: ConfirmConfig = CONFIRM) -> list:
    """Each slip episode of ``fit`` held out on its own (check 1 per episode): against the
    model ``others`` plus the other episodes at their fitted coefficients, the episode's
    coefficient is fitted on alternate odometer samples and scored on the others (the score
    test of :func:`heldout_motion`, both folds), and its readings on their own must show its
    step: not contradict it, and support it against no step (:func:`.contradict.slip_step`).
    An episode that fails is dropped from ``fit`` (``WheelSlip.keep_episodes``: in place; the
    others keep the joint fit's values). Returns each episode's figures."""
    shapes = list(fit.extra.get("shapes") or [])
    ivs = [tuple(iv) for iv in fit.parameters.get("intervals", [])]
    if len(shapes) != len(ivs):
        shapes = ["step"] * len(ivs)
    th = list(fit.extra.get("column") or [])
    if not ivs or len(th) != len(ivs):
        return []
    fold = _folds(mo, "odometer", cfg) % 2
    out, keep = [], []
    for j, iv in enumerate(ivs):
        base = copy.deepcopy(others)
        base.slip += [(a, b, c, sh) for i, ((a, b), c, sh) in enumerate(zip(ivs, th, shapes))
                      if i != j]
        st = Stage(mo, base, cfg, noise=noise, big=False)
        e0, s = speed_innovations(mo, base, cfg, noise)
        md, mv = slip_cols(mo, [(iv[0], iv[1], shapes[j])])
        num = var = 0.0
        for f in (0, 1):
            train = fold == f
            W = st.augmented(st.fv, st.fs, meas=(md[:, None], mv[:, None]), use=train).W
            c = float(gls(W)[0][1])
            ext = copy.deepcopy(base)
            ext.slip.append((iv[0], iv[1], c, shapes[j]))
            e1, _ = speed_innovations(mo, ext, cfg, noise)
            n, v = _score_terms(e0, e1, s, ~train)
            num, var = num + n, var + v
        gain, _, z, ok = _score(num, var, ccfg)
        step = slip_step(mo, iv, th[j], others=[w for i, w in enumerate(ivs) if i != j],
                         shape=shapes[j])
        if step["contradicted"] or not step["supported"]:
            ok = False
        out.append({"interval": list(iv), "gain_loglik": gain, "z": z, "readings_step": step,
                    "confirmed": ok})
        if ok:
            keep.append(j)
    if len(keep) < len(ivs):
        BY_NAME[fit.cause].keep_episodes(fit, keep)
    return out


def heldout_own(cause, fit: CauseFit, ctx: GainContext, ccfg: ConfirmConfig = CONFIRM) -> dict:
    """A cause with a likelihood of its own (clock, link): its held-out gain must improve on
    the believed model (higher for a likelihood, lower for an error)."""
    g = cause.gain(fit, ctx) or {}
    b, a = g.get("before"), g.get("after")
    out = {"test": g.get("metric", "held-out gain"), "before": b, "after": a}
    if b is None or a is None or not (math.isfinite(b) and math.isfinite(a)):
        out.update(ok=False, why="no held-out data")
        return out
    better = a > b if "likelihood" in str(g.get("metric", "")) else a < b
    # a held-out score of its own test (the clock's), where it states one, and its halves
    own = ctx.own.get(cause.name) or {}
    z = own.get("heldout_z")
    out["z"] = z
    if own.get("halves_fits"):
        out["halves"] = halves_test(own["halves_fits"], ccfg, nominal=cause.nominal(ctx.mo))
    out["ok"] = bool(better and (z is None or z > ccfg.heldout_z))
    if not better:
        out["why"] = f"{g.get('metric', 'held-out gain')}: {b:.4g} -> {a:.4g} (no gain)"
    elif not out["ok"]:
        out["why"] = f"held-out score Z {z:.2f} <= {ccfg.heldout_z:g}"
    return out
