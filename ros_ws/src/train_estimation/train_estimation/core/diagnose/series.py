"""Series for the plots: residual acceleration of the believed model against position, speed
and time, the commands, the speed trace, the loss runs, and the accepted causes' curves."""

from __future__ import annotations

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
    for name, res in own.items():
        BY_NAME[name].own_series(res, out)
    for a in accepted:
        BY_NAME[a.cause].series(a.parameters, mo, out)
    return out
