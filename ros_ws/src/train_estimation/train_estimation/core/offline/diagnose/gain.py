"""The held-out gain of a motion cause: how much better the believed model extended by the
cause (as the simulator runs it: its ``train_core.effects`` dataclass) predicts speed on data
not used for the fit."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from train_core.effects import Effects, replay_effects, true_line, true_train

from .motion import Motion
from .result import clean
from .run import DiagConfig
from .stage import Stage


@dataclass
class GainContext:
    """What a cause's gain may use: the motion model, the first stage (with its null), the
    configuration and the likelihoods of their own (clock, link) by cause."""

    mo: Motion
    st: Stage
    cfg: DiagConfig
    own: dict


def replayed_model(mo: Motion, eff: Effects):
    """(train, line, the other effects as train_core.motion.replay takes them) of the believed
    model extended by the effects ``eff``, as the simulator runs them (the held-out gain's and
    the replay plot's extended model)."""
    return true_train(mo.train, eff), true_line(mo.line, eff), replay_effects(eff)


def extended_model(cause, params: dict, mo: Motion):
    """:func:`replayed_model` of the believed model extended by the fitted cause, through the
    effect the simulator runs."""
    return replayed_model(mo, Effects(**{cause.effect_field: cause.effect(
        params, max(mo.run.duration, 1e-9))}))


def gain_motion(cause, ctx: GainContext) -> dict:
    """Fit the cause on alternate blocks (even), replay the recorded commands open loop through
    the believed and the extended model over the held-out (odd) blocks, each from the measured
    state at its start, and compare with the odometer speed."""
    mo, st, cfg = ctx.mo, ctx.st, ctx.cfg
    block = np.floor(mo.ev.t / cfg.gain_block).astype(int)
    st_a = Stage(mo, st.null, cfg, noise=(st.q, st.r_s), update=(block % 2 == 0))
    _, _, params, _, extra = cause.fit(st_a)
    # both models replay the commands with the analysis' command-time offset (the link's mean
    # latency, a nuisance of the alignment, not a cause)
    ctrl_t = mo.run.ctrl_t + st.null.shift
    ctrl_t_ext = mo.run.ctrl_t + cause.replay_offset(extra, st.null.shift)
    sq_b, sq_a, cnt, moved = _replay_blocks(mo, cfg, int(block.max()) + 1, ctrl_t, ctrl_t_ext,
                                            extended_model(cause, params, mo))
    if cnt.sum() == 0:
        return {"metric": "held-out speed RMSE (m/s)", "before": None, "after": None}
    all_b = float(np.sqrt(sq_b.sum() / cnt.sum()))
    all_a = float(np.sqrt(sq_a.sum() / cnt.sum()))
    # The blocks where the extension changes the prediction (selected on the two models'
    # predictions alone, never on their errors): a local effect (a 300 m section) is diluted
    # to nothing in a whole-run RMSE dominated by the odometer's noise elsewhere.
    changed = moved > cfg.gain_min_change
    out = {"metric": "held-out speed RMSE (m/s) against the odometer speed averaged over 1 s: "
                     "the recorded commands replayed open loop "
                     f"over alternate {cfg.gain_block:g} s blocks (cause fitted on the others), "
                     "in the blocks where the extended model's prediction moves by > "
                     f"{cfg.gain_min_change:g} m/s RMS",
           "blocks": int(cnt.size), "changed_blocks": int(changed.sum()),
           "before_all_blocks": all_b, "after_all_blocks": all_a,
           "fitted_on_half": clean(params)}
    if changed.any():
        out["before"] = float(np.sqrt(sq_b[changed].sum() / cnt[changed].sum()))
        out["after"] = float(np.sqrt(sq_a[changed].sum() / cnt[changed].sum()))
    else:
        out["before"] = out["after"] = None
        out["note"] = "the cause fitted on half the data changes no held-out block"
    return out


def _replay_blocks(mo: Motion, cfg: DiagConfig, nb: int, ctrl_t, ctrl_t_ext, ext):
    """Per held-out block: squared speed errors of the believed and the extended model, the
    sample count and the RMS difference of the two predictions."""
    from train_core.motion import replay

    run, believed = mo.run, mo.train
    extended, line_ext, effects = ext
    sq_b, sq_a, cnt, moved = [], [], [], []
    for b in range(1, nb, 2):
        t0, t1 = b * cfg.gain_block, (b + 1) * cfg.gain_block
        sel = (run.odo_t >= t0) & (run.odo_t < t1)
        if sel.sum() < 10:
            continue
        t_out = run.odo_t[sel]
        # the speed to predict: the odometer's, averaged over 1 s (centred), so that the
        # comparison is not floored by its sample noise, which both models share
        y = np.interp(t_out, mo.grid.t, mo.v_ref)
        v0 = float(y[0])
        x0 = float(np.interp(t_out[0], mo.grid.t, mo.x_ref))
        tt = t_out[0]
        if v0 < 0.5:
            v0 = 0.0
        # the simulator's physics (train_core.motion) at 50 ms RK4 steps: the motion is smooth
        # between command changes, and replay cuts its steps at every one of them
        _, vb = replay(mo.line, believed, ctrl_t, run.ctrl_a, tt, t_out, x0, v0,
                       max_step=0.05)
        _, va = replay(line_ext, extended, ctrl_t_ext, run.ctrl_a, tt, t_out, x0, v0,
                       believed=believed, max_step=0.05, **effects)
        sq_b.append(float(np.sum((vb - y) ** 2)))
        sq_a.append(float(np.sum((va - y) ** 2)))
        cnt.append(int(sel.sum()))
        moved.append(float(np.sqrt(np.mean((va - vb) ** 2))))
    return np.array(sq_b), np.array(sq_a), np.array(cnt), np.array(moved)
