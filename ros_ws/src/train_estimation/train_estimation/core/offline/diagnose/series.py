"""Series for the plots: residual acceleration of the believed model against position, speed
and time, the commands, the speed trace, the loss runs, and the accepted causes' curves."""

from __future__ import annotations

import functools

import numpy as np

from .causes import BY_NAME
from .motion import Motion
from .phases import grid_phase


def series(mo: Motion, accepted: list, own: dict) -> dict:
    """Residual acceleration of the believed model (smoothed odometer speed derivative minus the
    model's acceleration) against position, speed and time; f(t); the loss runs."""
    g = mo.grid
    v = mo.v_ref
    dv = np.gradient(v, g.dt)
    model = (mo.a_tr0 + mo.f0 * mo.a_br0 - (mo.alpha0 + (mo.beta0 + mo.gamma0 * v) * v)
             - mo.line.gradient_accel(mo.x_ref) * mo.k_grad)
    res = np.where(mo.moving > 0, dv - model, np.nan)
    step = max(1, int(round(0.5 / g.dt)))
    sl = slice(0, None, step)
    out = {"t": g.t[sl], "position": mo.x_ref[sl], "speed": v[sl], "residual_accel": res[sl],
           "phase": grid_phase(mo)[sl], "commanded_braking": mo.a_br0[sl],
           "commanded_traction": mo.a_tr0[sl],
           "odo_t": mo.run.odo_t, "odo_speed": mo.run.odo_v,
           "line_gradient": [(s.start, s.end, s.permille) for s in mo.line.gradients],
           "stations": [(s.name, s.position) for s in mo.line.stations],
           "balises": [b.position for b in mo.line.balises],
           "loss_runs": np.array([], int), "loss_fraction": None}
    for name, own_res in own.items():
        BY_NAME[name].own_series(own_res, out)
    for a in accepted:
        BY_NAME[a.cause].series(a.parameters, mo, out)
    if accepted:
        out["residual_accel_extended"] = res[sl] - extended_accel(mo, accepted)[sl]
        # the open-loop replays of the whole run (two runs of the simulator's physics per gain
        # block: two thirds of a diagnose run's replays) are for a plot only: made when it is
        # drawn (with_replay), not for a run without plots or for the fleet's rows
        out["replay"] = functools.partial(replay_series, mo, accepted)
    return out


def with_replay(s: dict) -> dict:
    """The series ``s`` with the replay's arrays (``replay_t``, ``replay_measured``,
    ``replay_believed``, ``replay_extended``, ``replay_block``: :func:`replay_series`) in
    place of the replay :func:`series` leaves to be made: what the plots take."""
    make = s.get("replay")
    if not callable(make):
        return s
    out = {k: v for k, v in s.items() if k != "replay"}
    out.update(make())
    return out


def _null_of(mo: Motion, accepted: list):
    from .stage import Null

    null = Null()
    for a in accepted:
        BY_NAME[a.cause].extend_null(null, a, mo)
    return null


def extended_accel(mo: Motion, accepted: list) -> np.ndarray:
    """m/s^2 on the grid: what the accepted causes add to the believed model's acceleration,
    the mean over each event interval of the drift they put into the null (the motion model's
    columns, so the extended residual is the believed one minus this)."""
    from .stage import Stage

    ev, g = mo.ev, mo.grid
    st = Stage(mo, _null_of(mo, accepted), mo.cfg, noise=(1.0, 1.0), big=False)
    dt = np.diff(ev.t, prepend=ev.t[0])
    with np.errstate(invalid="ignore", divide="ignore"):
        extra = np.where(dt > 0, (st.fv - mo.base_v) / dt, 0.0)
    k = np.clip(np.searchsorted(ev.t, g.t, side="right"), 1, ev.t.size - 1)
    return extra[k] * mo.moving


def replay_series(mo: Motion, accepted: list) -> dict:
    """The recorded commands replayed open loop through the believed and the extended model
    (the simulator's physics, train_core.motion), restarted from the measured state at the
    start of every gain block (cfg.gain_block s), against the odometer speed averaged over 1 s:
    the before/after picture of the held-out gain, over the whole run. The extended model is
    the held-out gain's (:func:`.gain.replayed_model`: every effect the simulator would run, the
    delays, the braking-rate schedule, a power limit and a low-adhesion section)."""
    from train_core.effects import Effects
    from train_core.motion import replay

    from .gain import replayed_model

    run, cfg = mo.run, mo.cfg
    fields = {}
    for a in accepted:
        cause = BY_NAME[a.cause]
        if cause.family == "motion":
            fields[cause.effect_field] = cause.effect(a.parameters, max(run.duration, 1e-9))
    if not fields:
        return {}
    train, line, effects = replayed_model(mo, Effects(**fields))
    shift = _null_of(mo, accepted).shift
    period = float(np.median(np.diff(run.odo_t))) if run.odo_t.size > 1 else 1.0
    t_all = run.odo_t[::max(1, int(round(0.5 / max(period, 1e-3))))]  # ~2 Hz: for a plot
    vb, va = np.full(t_all.size, np.nan), np.full(t_all.size, np.nan)
    for b in range(int(np.ceil((t_all[-1] - t_all[0]) / cfg.gain_block)) + 1):
        sel = np.flatnonzero((t_all >= t_all[0] + b * cfg.gain_block)
                             & (t_all < t_all[0] + (b + 1) * cfg.gain_block))
        if sel.size < 2:
            continue
        t_out = t_all[sel]
        v0 = float(np.interp(t_out[0], mo.grid.t, mo.v_ref))
        x0 = float(np.interp(t_out[0], mo.grid.t, mo.x_ref))
        v0 = 0.0 if v0 < 0.5 else v0
        vb[sel] = replay(mo.line, mo.train, run.ctrl_t, run.ctrl_a, t_out[0], t_out, x0, v0,
                         max_step=0.05)[1]
        va[sel] = replay(line, train, run.ctrl_t + shift, run.ctrl_a, t_out[0], t_out, x0, v0,
                         believed=mo.train, max_step=0.05, **effects)[1]
    return {"replay_t": t_all, "replay_measured": np.interp(t_all, mo.grid.t, mo.v_ref),
            "replay_believed": vb, "replay_extended": va, "replay_block": cfg.gain_block}
