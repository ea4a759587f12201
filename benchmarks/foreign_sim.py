"""A second, independent train simulator: measured bags that our simulator did not make.

``diagnose`` is meant for data from other physics code (another driver, other numerics, another
link and clock). This module writes such bags from the contract's meanings alone
(docs/interfaces.md, the project's public interface) and shares no physics with ``train_core`` or
``train_sim``: its own integrator (semi-implicit Euler, 5 ms, where ours is RK4 with an exact
actuator), its own driver (a trapezoid speed profile between the line's stations, a P speed
controller, a braking curve aimed at the stopping point), its own sensors, link and clock. Only
the map (``line.yaml``) and the believed train (``train.yaml``) are shared, read as plain YAML,
and the bag is written with ``train_core.bagio`` (the file format, not the physics).

Physics (per unit effective mass; the meanings the contract gives the files)::

    dv/dt = kappa a_hat - (a + b v + c v^2) / M_eff - g sin(theta(x)) / (1 + lambda)
    a_hat' = (u(t - T) - a_hat) / tau,   u = a_Tar (traction) or f a_Tar (braking)

with ``kappa`` = believed / true effective mass (the controller asks for the force of the train it
believes in). The train never rolls back; at rest it stays until the drive beats the static
resistance ``a``.

Pure module: numpy, yaml and the bag writer.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from collections import deque
from dataclasses import dataclass

import numpy as np
import yaml

G = 9.81  # m/s^2


@dataclass(frozen=True)
class Effect:
    """What the world has that the believed files do not (None / 1.0: as believed)."""

    gradient: tuple | None = None  # (start m, end m, permille): a section the map lacks
    davis: tuple | None = None  # (a N, b N/(m/s), c N/(m/s)^2): the true resistance
    braking_rate: float = 1.0  # -, f (braking delivered / asked)
    mass: float = 1.0  # -, true / believed mass
    odometer_scale: float = 1.0  # -, counted / true distance (and speed)
    brake_delay: float | None = None  # s, the brake's true transport delay
    clock_drift: float = 0.0  # s/s, the train clock's rate minus 1
    adhesion: tuple | None = None  # (start m, end m, factor): braking delivered x factor there
    p_spec: float | None = None  # m^2/s^3: traction acceleration delivered at most p_spec / v
    traction_delay: float | None = None  # s, the traction's true transport delay
    # what no cause of diagnose's list describes (bench_foreign --unlisted); each in its own
    # physical terms, not in the terms of train_sim.unlisted
    traction_gain: float = 1.0  # -, traction delivered / asked, everywhere
    traction_fade: tuple | None = None  # (v m/s, factor): traction x factor above v
    traction_cut: tuple | None = None  # (start m, end m, factor): traction x factor there
    traction_trip: tuple | None = None  # (t0 s, t1 s, factor): traction x factor meanwhile
    brake_fade: tuple | None = None  # (v m/s, factor): braking x factor below v
    brake_power: float | None = None  # m^2/s^3: braking deceleration at most P / v
    tunnel: tuple | None = None  # (start m, end m, c N/(m/s)^2): aerodynamic drag added there
    wind: tuple | None = None  # (t0 s, t1 s, N): a force against the motion meanwhile
    coast_drag: float = 0.0  # m/s^2 more deceleration while no command is delivered
    hunting: tuple | None = None  # (v m/s, N): a resistance added above v
    warmup: tuple | None = None  # (tau s, N): a resistance of N exp(-t / tau) added
    odometer_bias: float = 0.0  # m/s the odometer reads more while moving (and counts)
    # (v m/s, k): a radar odometer reads v (1 + k (v / v_ref)^2) and counts it
    odometer_speed: tuple | None = None
    # (E0 m^2/s^2, tau s, f_max): brakes that fade as they heat, braking x (1 - f_max min(E /
    # E0, 1)) with E the braking energy per kg, d E / dt = braking power / kg - E / tau
    brake_heat: tuple | None = None
    balise_late: float = 0.0  # s the balise reader stamps its readings late
    balise_moved: tuple | None = None  # (balise id, m): that balise lies m further on
    balise_datum: float = 0.0  # m every balise lies further on than the map (its telegram) says
    clock_step: tuple | None = None  # (t s, s): the train clock jumps by s at t
    odometer_lag: float = 0.0  # s the odometer's speed reading lags the train (its count not)
    # (stop index k, factor): from the arrival at station k on the train carries factor x its
    # believed mass (a payload taken on; translational, its traction and brake forces as asked
    # for the believed train: neither load-weighed)
    payload: tuple | None = None


def _radar(effect: Effect, v: float) -> float:
    """m/s a radar odometer reads beyond the speed ``v`` (0 without ``odometer_speed``)."""
    if effect.odometer_speed is None:
        return 0.0
    v_ref, k = effect.odometer_speed
    return k * (v / v_ref) ** 2 * v


def _profile(sections, x: float) -> float:
    for s in sections:
        if s["start"] <= x < s["end"]:
            return float(s.get("permille", s.get("speed", 0.0)))
    return 0.0


def _table(f, cuts) -> tuple[list, list]:
    """(bounds, values) with ``f(x) == values[bisect_right(bounds, x)]`` for every x, for an
    ``f`` that can change only at the points ``cuts`` (each of its tests ``start <= x < end``
    with start and end among them): ``f`` evaluated once per piece, at the piece's left end, so
    a lookup gives the very float ``f`` gives, at a bisection's cost instead of a scan."""
    bounds = sorted(set(cuts) | {math.inf})
    return bounds, [f(-math.inf)] + [f(b) for b in bounds]


def _cuts(sections) -> list:
    return [s[k] for s in sections for k in ("start", "end")]


def simulate(line: dict, train: dict, effect: Effect, rng: np.random.Generator,
             dt: float = 0.005, odo_rate: float = 10.0, cmd_rate: float = 5.0,
             dwell: float = 25.0, trace: list | None = None, sent: list | None = None,
             truth: list | None = None, notch: float = 0.0, on_change: float = 0.0,
             tail: float = 0.015, coast: float = 0.0, clock: dict | None = None) -> list:
    """The run from the first station to the last: [(log time s, topic, stamp s, fields)] as
    a ground recorder would log it (measured: no ground truth). ``trace`` gets (t, x, v,
    command, leg) at every command; ``sent`` the messages the link delivered as (topic, true
    sample time s, fields) in sampling order (the clean stream of ``tools.faults.inject``);
    ``truth`` (t, x, v) at every odometer sample; ``clock`` gets the clocks (``train_epoch``,
    ``drift``, ``step`` (t, s) or None: the train's stamp is ``train_epoch + (1 + drift) t``
    plus the step once ``t`` passes it; ``ref_epoch``: the log time is ``ref_epoch`` + t plus
    the link's latency).

    Variants of the driver and link (the defaults are the bench's): ``notch`` m/s^2 > 0 rounds
    each command to a master controller's notches; ``on_change`` s > 0 logs a command only when
    it changes or this long after the last one logged (a lever logged on change with a
    keep-alive); ``tail`` s is the mean of the link latency's exponential tail; ``coast`` in
    (0, 1) drives coast-and-motor (energy-saving driving): having reached its cruise speed the
    driver coasts until the speed falls to ``coast`` times it, then motors back up."""
    m_b = float(train["mass"])
    lam = float(train.get("rotary_allowance", 0.0))
    meff_b = (1 + lam) * m_b
    meff = meff_b * effect.mass
    kappa = meff_b / meff
    a0, b0, c0 = (float(train["davis"][k]) for k in "abc")
    a, b, c = effect.davis if effect.davis is not None else (a0, b0, c0)
    br = train["brake"]
    tau, delay = float(br["time_constant"]), float(br["delay"])
    b_delay = effect.brake_delay if effect.brake_delay is not None else delay
    t_delay = effect.traction_delay if effect.traction_delay is not None else delay
    perf = train.get("performance", {})
    a_max = float(perf.get("max_traction", 0.8))
    b_serv = float(perf.get("service_brake", 0.8))
    odo = train.get("odometer", {})
    s_std, d_std = float(odo.get("speed_std", 0.1)), float(odo.get("distance_std", 0.1))
    p_std = float(train.get("balise", {}).get("position_std", 0.5))
    lag = math.exp(-dt / tau)  # the first-order lag over one step

    def grad_acc(x):
        pm = _profile(line.get("gradients", []), x)
        if effect.gradient is not None and effect.gradient[0] <= x < effect.gradient[1]:
            pm += effect.gradient[2]
        th = math.atan(pm / 1000.0)
        return G * math.sin(th) / (1 + lam)

    limits = line.get("speed_limits", [])
    v_line = float(line.get("max_speed", 20.0))

    def v_limit(x):
        v = _profile(limits, x)
        return v if v > 0 else v_line

    # both as lookup tables (a scan of the sections at every step would be most of the
    # loop's time)
    g_bounds, g_values = _table(grad_acc, _cuts(line.get("gradients", []))
                                + list(effect.gradient[:2] if effect.gradient is not None else ()))
    l_bounds, l_values = _table(v_limit, _cuts(limits))

    stations = sorted(float(s["position"]) for s in line.get("stations", []))
    if len(stations) < 2:
        stations = [0.0, float(line["length"])]
    moved = dict([effect.balise_moved]) if effect.balise_moved is not None else {}
    # where each balise lies (the train reads it there) and what its telegram says
    balises = sorted((float(bl["position"]) + moved.get(int(bl["id"]), 0.0) + effect.balise_datum,
                      int(bl["id"]), float(bl["position"])) for bl in line.get("balises", []))

    # clocks: the train's stamps at an arbitrary epoch (at the effect's drift); the ground's
    # log time at another epoch
    epoch_train = float(rng.uniform(1e8, 1e9))
    drift = effect.clock_drift
    epoch_ref = 1.75e9
    if clock is not None:
        clock.update(train_epoch=epoch_train, drift=drift, step=effect.clock_step,
                     ref_epoch=epoch_ref)

    def stamp(t):
        jump = effect.clock_step[1] if effect.clock_step is not None and \
            t >= effect.clock_step[0] else 0.0
        return epoch_train + (1.0 + drift) * t + jump

    # the radio link: Gilbert-Elliott losses, latency with an exponential tail
    state = {"bad": False}

    def link(t):
        st = state["bad"]
        state["bad"] = (rng.random() < 0.25) if st else (rng.random() > 0.98)
        lost = rng.random() < (0.5 if state["bad"] else 0.02)
        return None if lost else t + 0.04 + float(rng.exponential(tail))

    out = []

    def send(t_sample, topic, fields):
        """A train message sampled at ``t_sample`` through the link (lost: not logged)."""
        tr = link(t_sample)
        if tr is not None:
            out.append((epoch_ref + tr, topic, stamp(t_sample), fields))
            if sent is not None:
                sent.append((topic, t_sample, fields))

    x, v = stations[0], 0.0
    ah_tr = ah_br = 0.0
    pipe_tr: deque = deque()
    pipe_br: deque = deque()
    u_tr = u_br = 0.0
    t, t_end_dwell = 0.0, dwell * 0.4
    leg, seq_odo, seq_bal = 1, 0, 0
    next_cmd, next_odo = 0.0, 0.0
    stopping = coasting = False
    last_cmd, last_logged = math.nan, -math.inf  # the last command logged, when (on_change)
    bi = next((i for i, (p, _, _) in enumerate(balises) if p > x), len(balises))
    odo_extra = 0.0  # m the odometer's bias has counted
    lag_t, lag_v = [0.0], [0.0]  # the speed's recent past, for a speed reading that lags
    heat = 0.0  # m^2/s^2, the brakes' heat as braking energy per kg (brake_heat)
    # the effect's fields as locals, and the next activation and balise as plain floats: the
    # step loop runs some 10^5 times per run
    f_br, gain, coast_drag = effect.braking_rate, effect.traction_gain, effect.coast_drag
    fade, cut, trip, p_spec = (effect.traction_fade, effect.traction_cut, effect.traction_trip,
                               effect.p_spec)
    adhesion, b_fade, b_heat, b_power = (effect.adhesion, effect.brake_fade, effect.brake_heat,
                                         effect.brake_power)
    extra = (effect.tunnel, effect.wind, effect.hunting, effect.warmup) != (None,) * 4
    radar = effect.odometer_speed is not None
    o_bias, o_lag, o_scale = effect.odometer_bias, effect.odometer_lag, effect.odometer_scale
    n_st, n_bal = len(stations), len(balises)
    next_bal = balises[bi][0] if bi < n_bal else math.inf
    due_tr = due_br = math.inf  # activation time of the head of each pipe
    while leg < n_st:
        if t >= next_cmd - 1e-9:
            target = stations[leg]
            if t < t_end_dwell:
                cmd = -0.3  # holding brake while dwelling
            else:
                rem = target - x
                vc = 0.9 * min(l_values[bisect_right(l_bounds, x)],
                               l_values[bisect_right(l_bounds, x + 50.0)], v_line)
                # the braking curve: latched once the distance left is what a braking at 60 %
                # of the service rate needs, plus the actuator's reaction
                if not stopping and rem < v * v / (1.2 * b_serv) + v * (delay + tau) + 10.0:
                    stopping = True
                elif stopping and v < 0.05 and rem >= 20.0:
                    stopping = False  # stopped short (a drag it did not expect): creep on
                if stopping:
                    need = v * v / (2.0 * max(rem - 1.0, 0.5))
                    cmd = -0.3 if v < 0.05 else -min(b_serv, 1.1 * need)
                else:
                    if coast > 0.0:  # coast-and-motor: coast from the cruise speed down
                        coasting = v < vc and (coasting or v >= 0.98 * vc) and v > coast * vc
                    # (a clip; a zero it gives is made 0.0 below whatever its sign)
                    cmd = 0.0 if coasting else min(max(0.6 * (vc - v), -0.5 * b_serv), a_max)
                    if abs(cmd) < 0.03:
                        cmd = 0.0
            if notch > 0.0:
                cmd = notch * round(cmd / notch)
            if trace is not None:
                trace.append((t, x, v, cmd, leg))
            if on_change <= 0.0 or cmd != last_cmd or t - last_logged >= on_change - 1e-9:
                out.append((epoch_ref + t + 0.005, "control", epoch_ref + t,
                            {"target_acceleration": cmd}))
                last_cmd, last_logged = cmd, t
                if sent is not None:
                    sent.append(("control", t, {"target_acceleration": cmd}))
            pipe_tr.append((t + t_delay, max(cmd, 0.0)))
            pipe_br.append((t + b_delay, min(cmd, 0.0)))
            due_tr, due_br = pipe_tr[0][0], pipe_br[0][0]
            next_cmd += 1.0 / cmd_rate
        if due_tr <= t + 1e-9:
            while pipe_tr and pipe_tr[0][0] <= t + 1e-9:
                u_tr = pipe_tr.popleft()[1]
            due_tr = pipe_tr[0][0] if pipe_tr else math.inf
        if due_br <= t + 1e-9:
            while pipe_br and pipe_br[0][0] <= t + 1e-9:
                u_br = pipe_br.popleft()[1]
            due_br = pipe_br[0][0] if pipe_br else math.inf
        # one first-order lag (linear): its traction and braking parts lag separately
        ah_tr = u_tr + (ah_tr - u_tr) * lag
        ah_br = f_br * u_br + (ah_br - f_br * u_br) * lag
        drive_tr = ah_tr * gain
        if fade is not None and v > fade[0]:
            drive_tr *= fade[1]
        if cut is not None and cut[0] <= x < cut[1]:
            drive_tr *= cut[2]
        if trip is not None and trip[0] <= t < trip[1]:
            drive_tr *= trip[2]
        if p_spec is not None and v > 0.0:
            drive_tr = min(drive_tr, p_spec / v)
        drive_br = ah_br
        if adhesion is not None and adhesion[0] <= x < adhesion[1]:
            drive_br *= adhesion[2]
        if b_fade is not None and 0.0 < v < b_fade[0]:
            drive_br *= b_fade[1]
        if b_heat is not None:
            e0, tau_h, f_max = b_heat
            drive_br *= 1.0 - f_max * min(heat / e0, 1.0)
            heat += (-drive_br * v - heat / tau_h) * dt
        if b_power is not None and v > 0.0:
            drive_br = max(drive_br, -b_power / v)
        acc = kappa * (drive_tr + drive_br) - g_values[bisect_right(g_bounds, x)]
        if v > 0.0:
            acc -= (a + b * v + c * v * v + (_extra_resistance(effect, t, x, v) if extra
                                             else 0.0)) / meff
            if coast_drag and u_tr == 0.0 and u_br == 0.0:
                acc -= coast_drag
            v_new = v + acc * dt
            if v_new < 0.0:  # (max(v_new, 0.0) without its call)
                v_new = 0.0
        else:
            v_new = acc * dt if acc > a / meff else 0.0
        x_old = x
        x += v_new * dt
        v = v_new
        if v > 0.0:
            odo_extra += (o_bias + (_radar(effect, v) if radar else 0.0)) * dt
        t += dt
        if o_lag > 0.0:
            lag_t.append(t)
            lag_v.append(v)
            if len(lag_t) > 4096:  # the last 20 s at 5 ms are more than any lag needs
                del lag_t[:2048], lag_v[:2048]
        if next_bal <= x:
            while bi < n_bal and balises[bi][0] <= x:
                p, bid, told = balises[bi]
                tb = t - dt + dt * (p - x_old) / max(x - x_old, 1e-12)
                seq_bal += 1
                send(tb + effect.balise_late, "balise",
                     {"seq": seq_bal, "balise_id": bid, "position": told,
                      "position_variance": p_std * p_std})
                bi += 1
            next_bal = balises[bi][0] if bi < n_bal else math.inf
        if t >= next_odo - 1e-9:
            if truth is not None:
                truth.append((t, x, v))
            # the train never rolls back: the distance run is how far it is from the start
            d = o_scale * (x - stations[0]) + odo_extra + float(rng.normal(0.0, d_std))
            vr = float(np.interp(t - o_lag, lag_t, lag_v)) if o_lag > 0.0 else v
            sp = o_scale * vr + float(rng.normal(0.0, s_std)) \
                + (o_bias if vr > 0.0 else 0.0) + _radar(effect, vr)
            send(t, "odometer", {"seq": seq_odo, "distance": d, "speed": sp,
                                 "speed_variance": s_std * s_std})
            seq_odo += 1
            next_odo += 1.0 / odo_rate
        if stopping and v < 0.01 and stations[leg] - x < 20.0:
            if effect.payload is not None and leg == effect.payload[0]:
                meff = meff_b * effect.mass + (effect.payload[1] - 1.0) * m_b
                kappa = meff_b / meff
            leg += 1
            t_end_dwell = t + dwell
            stopping = False
        if t > 4000.0:
            raise RuntimeError("the driver did not reach the last station in 4000 s")
    out.sort(key=lambda e: e[0])
    return out


def _extra_resistance(effect: Effect, t: float, x: float, v: float) -> float:
    """N of resistance the believed train lacks at time ``t``, place ``x``, speed ``v`` > 0."""
    f = 0.0
    if effect.tunnel is not None and effect.tunnel[0] <= x < effect.tunnel[1]:
        f += effect.tunnel[2] * v * v
    if effect.wind is not None and effect.wind[0] <= t < effect.wind[1]:
        f += effect.wind[2]
    if effect.hunting is not None and v > effect.hunting[0]:
        f += effect.hunting[1]
    if effect.warmup is not None:
        f += effect.warmup[1] * math.exp(-t / effect.warmup[0])
    return f


def write_bag(events: list, path: str) -> None:
    """The events as a measured bag (log time = arrival on the ground's clock)."""
    from train_core.bagio import BagWriter

    with BagWriter(path, namespace="/train") as w:
        for t_log, topic, st, fields in events:
            w.write(topic, st, fields, t_ns=int(round(t_log * 1e9)))


def load(path: str) -> dict:
    with open(path) as f:
        return yaml.safe_load(f)


# Lines and trains that no case of ours draws (``train_sim.cases`` has metro, regional and
# high-speed families): a heavy freight train with a slow air brake on a long line with few
# stops, a light railcar on a steep line, a tram with stops every 350-700 m. Ranges are those
# of such trains, not fitted to anything of ours.
OTHER_FAMILIES = {
    # line: length m, top speed m/s, steepest gradient per mille, stop spacing m, balise
    # spacing m; train: mass kg, rotary allowance, Davis a, b, c per tonne (N, N/(m/s),
    # N/(m/s)^2), brake time constant s, delay s, max traction, service brake m/s^2
    "freight": {"length": (18000.0, 26000.0), "vmax": (20.0, 25.0), "gmax": 10.0,
                "spacing": (6000.0, 10000.0), "balise": (1500.0, 3000.0),
                "mass": (1.2e6, 2.5e6), "lam": (0.04, 0.07),
                "davis": ((6.0, 10.0), (0.04, 0.08), (0.004, 0.008)),
                "tau": (1.5, 3.0), "delay": (2.0, 4.0), "traction": (0.15, 0.3),
                "brake": (0.3, 0.45)},
    "mountain": {"length": (6000.0, 10000.0), "vmax": (16.0, 22.0), "gmax": 35.0,
                 "spacing": (1500.0, 3000.0), "balise": (200.0, 800.0),
                 "mass": (120e3, 220e3), "lam": (0.08, 0.14),
                 "davis": ((10.0, 16.0), (0.3, 0.6), (0.02, 0.04)),
                 "tau": (0.3, 0.6), "delay": (0.5, 1.2), "traction": (1.0, 1.3),
                 "brake": (0.8, 1.1)},
    "tram": {"length": (3000.0, 6000.0), "vmax": (12.0, 16.0), "gmax": 20.0,
             "spacing": (350.0, 700.0), "balise": (150.0, 400.0),
             "mass": (40e3, 70e3), "lam": (0.08, 0.14),
             "davis": ((12.0, 20.0), (0.3, 0.7), (0.03, 0.06)),
             "tau": (0.2, 0.4), "delay": (0.3, 0.7), "traction": (1.0, 1.3),
             "brake": (1.0, 1.3)},
}


def other_line_train(family: str, rng: np.random.Generator) -> tuple[dict, dict]:
    """A line (``line.yaml``) and the believed train (``train.yaml``) of ``family`` (one of
    ``OTHER_FAMILIES``), as plain dicts in the contract's keys: stations over the line (at
    most eight), gradient sections of 300-1500 m (level around the stations), balises, a
    speed limit of 12 m/s out of the first station."""
    f = OTHER_FAMILIES[family]

    def u(lo_hi):
        return float(rng.uniform(*lo_hi))

    length, vmax = round(u(f["length"]), 1), u(f["vmax"])
    first, last = u((100.0, 300.0)), length - u((200.0, 400.0))
    pos = [first]
    while pos[-1] + f["spacing"][1] < last - 0.5 * f["spacing"][0]:
        pos.append(pos[-1] + u(f["spacing"]))
    pos = [round(p, 1) for p in pos[:7] + [last]]
    cuts = [0.0]
    while cuts[-1] < length:
        cuts.append(round(min(length, cuts[-1] + u((300.0, 1500.0))), 1))
    grads = []
    for a, b in zip(cuts, cuts[1:]):
        level = any(abs(0.5 * (a + b) - p) < 150.0 + 0.5 * (b - a) for p in pos)
        grads.append({"start": a, "end": b,
                      "permille": 0.0 if level else round(u((-f["gmax"], f["gmax"])), 1)})
    balises, bx = [], u((20.0, 300.0))
    while bx < length:
        balises.append({"id": len(balises) + 1, "position": round(bx, 1)})
        bx += u(f["balise"])
    line = {"name": f"{family}-line", "length": length, "max_speed": round(vmax, 2),
            "speed_limits": [{"start": 0.0, "end": pos[0] + 300.0,
                              "speed": round(min(vmax, 12.0), 2)}],
            "gradients": grads, "balises": balises,
            "stations": [{"name": f"S{i}", "position": p, "dwell": 30.0}
                         for i, p in enumerate(pos)]}
    mass = u(f["mass"])
    tonnes = mass / 1000.0
    train = {"name": f"{family}-train", "mass": round(mass),
             "rotary_allowance": round(u(f["lam"]), 3),
             "davis": {k: round(u(r) * tonnes, 4) for k, r in zip("abc", f["davis"])},
             "brake": {"time_constant": round(u(f["tau"]), 2), "delay": round(u(f["delay"]), 2),
                       "braking_rate": 1.0},
             "odometer": {"speed_std": round(u((0.05, 0.15)), 3),
                          "distance_std": round(u((0.1, 0.5)), 3)},
             "balise": {"position_std": round(u((0.5, 1.5)), 3)},
             "performance": {"max_traction": round(u(f["traction"]), 3),
                             "service_brake": round(u(f["brake"]), 3),
                             "emergency_brake": round(1.5 * f["brake"][1], 3),
                             "max_jerk": 0.5}}
    return line, train
