"""Synthetic runs for the identification tests: the model of train_core.model integrated finely,
with the delayed first-order-lag actuator and a simple station-to-station driver (pure numpy)."""

from __future__ import annotations

import bisect
import math

import numpy as np
from train_core.model import Balise, Brake, Davis, GradientSection, Line, TrainParams

METRO = TrainParams(mass=288000.0, rotary_allowance=0.16,
                    davis=Davis(a=3481.8, b=144.92, c=8.52),
                    brake=Brake(time_constant=0.4, delay=1.2, braking_rate=1.0))


def hilly_line(length: float = 40000.0, rng=None) -> Line:
    """Gradients alternating every 400-900 m between -8 and +8 permille; balises every 500 m."""
    rng = np.random.default_rng(7) if rng is None else rng
    secs, x = [], 0.0
    while x < length:
        e = min(length, x + rng.uniform(400, 900))
        secs.append(GradientSection(x, e, float(rng.uniform(-8, 8))))
        x = e
    bal = tuple(Balise(i, float(p)) for i, p in enumerate(np.arange(0.0, length, 500.0)))
    return Line(name="hilly", length=length, balises=bal, gradients=tuple(secs))


def simulate_run(train: TrainParams, line: Line, rng: np.random.Generator, duration: float,
                 targets=(12.0, 20.0, 16.0, 22.0, 9.0), cruise_only: bool = False,
                 never_moves: bool = False, dt: float = 0.01, odo_rate: float = 10.0,
                 speed_std: float = 0.1, start: float = 100.0):
    """Returns dict of arrays like the bag would give (odometer, control, balise) + truth."""
    n = int(duration / dt)
    g_start = [g.start for g in line.gradients]
    g_end = [g.end for g in line.gradients]
    g_val = [float(line.gradient_accel(0.5 * (g.start + g.end))) for g in line.gradients]
    da, db, dc = train.davis.a, train.davis.b, train.davis.c
    noise = rng.standard_normal(int(duration * odo_rate) + 2) * speed_std
    meff = train.effective_mass
    lam = train.rotary_allowance
    f = train.brake.braking_rate
    tau, delay = train.brake.time_constant, train.brake.delay
    e = math.exp(-dt / tau)
    v, s = (15.0 if cruise_only else 0.0), 0.0
    a_tr = a_br = 0.0
    ctrl_every = int(round(0.2 / dt))
    odo_every = int(round(1.0 / (odo_rate * dt)))
    leg, phase, timer = 0, "acc", 0.0
    cmd_hist = []  # (t, a_tar)
    cmd = 0.0
    odo = {"t": [], "distance": [], "speed": []}
    truth_v = []
    for k in range(n):
        t = k * dt
        if k % ctrl_every == 0:
            tgt = targets[leg % len(targets)]
            if never_moves:
                cmd = 0.0
            elif cruise_only:
                cmd = float(np.clip(0.5 * (15.0 - v) + 0.03, -0.5, 0.5))
            elif phase == "acc":
                cmd = 0.8
                if v >= tgt:
                    phase, timer = "cruise", rng.uniform(40, 120)
            elif phase == "cruise":
                cmd = float(np.clip(0.5 * (tgt - v) + 0.04, -0.3, 0.6))
                timer -= ctrl_every * dt
                if timer <= 0:
                    phase, timer = "coast", rng.uniform(20, 60)
            elif phase == "coast":
                cmd = 0.0
                timer -= ctrl_every * dt
                if timer <= 0:
                    phase = "brake"
            elif phase == "brake":
                cmd = -0.7 if v > 3 else -0.4
                if v <= 0.0:
                    phase, timer = "dwell", rng.uniform(15, 30)
            elif phase == "dwell":
                cmd = -0.4
                timer -= ctrl_every * dt
                if timer <= 0:
                    phase, leg = "acc", leg + 1
            cmd_hist.append((t, cmd))
        # delayed command (zero before the first one)
        td = t - delay
        j = int(np.floor(td / (ctrl_every * dt))) if td >= 0 else -1
        c_d = cmd_hist[j][1] if 0 <= j < len(cmd_hist) else 0.0
        if k % odo_every == 0:
            odo["t"].append(t)
            odo["distance"].append(s)
            odo["speed"].append(max(v + noise[len(truth_v)], 0.0))
            truth_v.append(v)
        def accel(vv, ss, atr, abr):
            gi = bisect.bisect_right(g_start, start + ss) - 1
            g_acc = g_val[gi] if gi >= 0 and start + ss < g_end[gi] else 0.0
            return atr + f * abr - (da + db * vv + dc * vv * vv) / meff - g_acc / (1 + lam)

        # Heun (RK2) step; the actuator outputs at the step midpoint from the exact lag
        acc1 = accel(v, s, a_tr, a_br)
        if v <= 0.0 and acc1 <= 0.0:  # brake holds the standing train
            v = 0.0
            a_tr = e * a_tr + (1 - e) * max(c_d, 0.0)
            a_br = e * a_br + (1 - e) * min(c_d, 0.0)
            continue
        n_tr = e * a_tr + (1 - e) * max(c_d, 0.0)
        n_br = e * a_br + (1 - e) * min(c_d, 0.0)
        v1 = v + acc1 * dt
        acc2 = accel(max(v1, 0.0), s + v * dt, n_tr, n_br)
        v_new = max(v + 0.5 * (acc1 + acc2) * dt, 0.0)
        s += 0.5 * (v + v_new) * dt
        v, a_tr, a_br = v_new, n_tr, n_br
    ct = np.array([c[0] for c in cmd_hist])
    ca = np.array([c[1] for c in cmd_hist])
    ot = np.array(odo["t"])
    od = np.array(odo["distance"])
    bpos = np.array([b.position for b in line.balises])
    bpos = bpos[(bpos > start) & (bpos < start + od[-1])]
    bt = np.interp(bpos - start, od, ot)
    return {"odo_t": ot, "odo_distance": od, "odo_speed": np.array(odo["speed"]),
            "ctrl_t": ct, "ctrl_a_tar": ca, "balise_t": bt, "balise_position": bpos,
            "truth_v": np.array(truth_v)}
