"""diagnose on bags from an independent simulator (benchmarks/foreign_sim.py): no shared physics.

    ./run bench foreign --seeds 4 --jobs 2        # quick: 4 seeds x 11 kinds, about 2 min

Each seed draws a line and a believed train (``train_sim.cases.make_case``: metro, regional,
high-speed, metro_demo families), then runs the foreign simulator on them nominally and with one
effect the believed files lack, of a plain case's size: a gradient section of 4-6 per mille over
300-500 m of track run at speed; Davis terms x 0.6-0.75 or x 1.3-1.5; f 0.75-0.85; mass x
0.85-0.9 or x 1.1-1.2; odometer scale 1 +- 0.01-0.02; brake delay + 0.4-0.8 s; clock drift
+-2e-5 to 1e-4; a stretch of 200-400 m of a braking approach braking x 0.5-0.7; a power limit
with its knee at 40-60 % of the top speed; a traction delay + 0.6-1.0 s. Its driver,
integrator, sensors, link (Gilbert-Elliott losses, latency with an exponential tail) and clock
(an arbitrary epoch) are its own. Printed: per kind, how often the reported cause is the hidden
one, confirmed and alone (nominal: ``none``), and what was reported instead (with an entry one
run cannot tell from a rival law: a low-adhesion section braked over at one command, which a
force fixed there fits as well, "adhesion_section or its rival: not told apart").

    ./run bench foreign --subtle --seeds 4 --jobs 2   # the same effects at half their size

``--subtle``: each listed effect of the same draw and place at half its deviation from the
believed train (``train_sim.cases``' subtle size): 2-3 per mille, Davis x 0.8-0.88 or x
1.15-1.25, f 0.88-0.93, and so on; a power limit's knee at 70-80 % of the top speed.

    ./run bench foreign --estimators --seeds 4 --jobs 2   # every estimator, about 12 min
    ./run bench foreign --unlisted --seeds 8 --jobs 2     # effects outside the list, 4 min

``--unlisted``: effects that no cause of diagnose's list describes, written in the foreign
simulator's own terms (``foreign_sim.Effect``) and placed from its own nominal run, of a plain
listed effect's size: a traction x 0.7-0.8 or x 1.2-1.3; x 0.6-0.75 above 40-60 % of the top
speed; x 0.4-0.6 on a 300-600 m stretch where the train accelerates, or for 60-120 s from a
traction onset; braking x 0.6-0.75 below 35-50 % of the top speed, or limited to P / v with the
knee at 45-65 % of it; aerodynamic drag added in a 500-900 m tunnel run above 60 % of the top
speed, a constant force for 60-120 s (wind), a drag while coasting, a resistance above 60-80 %
of the top speed (hunting), a resistance decaying from the start (warming up), each 0.04-0.08
m/s^2 where it acts; an odometer reading 0.04-0.1 m/s more or less while moving, or a radar
odometer whose error grows as the square of the speed (1-2 % at the top speed), or whose
speed readings lag the train by 0.2-0.4 s while its count does not; a payload of 5-12 % of
the mass taken on at the middle stop, the brakes not load-weighed; every balise 5-10 m off
its map position, the same way (a datum shift against the gradients); a balise 8-20
m from its map position, or every balise stamped 0.2-0.5 s late; a train clock that jumps by
0.5-3 s; brakes that fade as they heat (30-45 % weaker once they hold a stop from the top
speed, cooling in 60-150 s). Printed: how often diagnose says
`unexplained` and confirms no listed cause, how often it confirms a listed one, and whether
its signature names the effect's phase (a coasting drag is scored only where the nominal run
coasts 10 s or more). With ``--estimators``: every estimator's integrity on those runs.

Variants of the driver and the link (``--odo-rate``, ``--cmd-rate``, ``--notch``,
``--on-change``, ``--link-tail``, ``--coast``): the same seeds and effects with an odometer
sampling at another rate, a driver commanding at another rate, in notches or logged only on
change, a driver who coasts from the cruise speed down to a fraction of it and motors back up,
and a link whose latency has a longer tail; results go to a file named after the variant.

``--family freight|mountain|tram``: lines and trains that our cases never draw
(``foreign_sim.OTHER_FAMILIES``): a 1,200-2,500 t freight train with an air brake of 2-4 s
delay on an 18-26 km line with stops 6-10 km apart; a light railcar on gradients up to 35 per
mille; a tram of 40-70 t with stops every 350-700 m and a balise every 150-400 m.

``--estimators``: every estimator on the same runs instead (the believed model, whatever the
world had), the clean stream the link delivered put on the integrity campaign's clocks and
latency (``tools.faults``, no fault) and replayed through the runner the nodes use with the node
defaults: wrong-side estimates, availability, error, as ``./run bench integrity`` scores them.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import json
import math
import os
import shutil
import sys
import tempfile
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from types import SimpleNamespace

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import foreign_sim as FS  # noqa: E402
from bench_diagnose import pct  # noqa: E402
from bench_integrity import ESTIMATORS, add_prior_args, make_adapter, stated_priors  # noqa: E402
from train_core.progress import Progress  # noqa: E402

from train_estimation.core.online.integrity import IntegrityParams  # noqa: E402

KINDS = ("none", "gradient", "resistance", "braking_rate", "mass", "odometer_scale",
         "brake_delay", "clock_drift", "adhesion_section", "power_limit", "traction_delay")
# effects no listed cause describes (``--unlisted``), each with the phase diagnose's
# ``unexplained`` signature should name
UNLISTED = {"traction_gain": "traction", "traction_fade": "traction", "traction_cut": "traction",
            "traction_trip": "traction", "brake_fade": "braking", "brake_power": "braking",
            "tunnel": "all", "wind": "all", "coast_drag": "coasting", "hunting": "all",
            "warmup": "all", "odometer_bias": "all", "balise_moved": "all", "clock_step": "all",
            "odometer_speed": "all", "brake_heat": "braking", "balise_late": "all",
            "odometer_lag": "all", "payload": "all", "balise_datum": "all"}
STAMP_KINDS = ("clock_drift", "clock_step")  # effects on the train clock's stamps only
COAST_MIN = 10.0  # s the nominal run must coast for a coasting drag to be scored
OUT = os.path.join(HERE, "out")


def _sign(rng) -> float:
    return 1.0 if rng.random() < 0.5 else -1.0


def effect_of(kind: str, line: dict, train: dict, rng, pilot) -> FS.Effect:
    """One plain effect of ``kind`` (module doc); ``pilot`` = (x, v, command) of the nominal
    run at its commands."""
    if kind == "none":
        return FS.Effect()
    if kind == "gradient":
        x, v, _ = pilot
        length = float(rng.uniform(300.0, 500.0))
        starts = [s for s in np.arange(x.min(), x.max() - length, 10.0)
                  if np.all(v[(x >= s) & (x <= s + length)] > 3.0)]
        s0 = float(rng.choice(starts))
        return FS.Effect(gradient=(s0, s0 + length, _sign(rng) * float(rng.uniform(4.0, 6.0))))
    if kind == "resistance":
        k = float(rng.uniform(1.3, 1.5)) if rng.random() < 0.5 else float(rng.uniform(0.6, 0.75))
        d = train["davis"]
        return FS.Effect(davis=(d["a"] * k, d["b"] * k, d["c"] * k))
    if kind == "braking_rate":
        return FS.Effect(braking_rate=float(rng.uniform(0.75, 0.85)))
    if kind == "mass":
        return FS.Effect(mass=float(rng.uniform(1.1, 1.2)) if rng.random() < 0.5
                         else float(rng.uniform(0.85, 0.9)))
    if kind == "odometer_scale":
        return FS.Effect(odometer_scale=1.0 + _sign(rng) * float(rng.uniform(0.01, 0.02)))
    if kind == "brake_delay":
        return FS.Effect(brake_delay=float(train["brake"]["delay"]) + float(rng.uniform(0.4, 0.8)))
    if kind == "clock_drift":
        return FS.Effect(clock_drift=_sign(rng) * float(rng.uniform(2e-5, 1e-4)))
    if kind == "adhesion_section":
        # a stretch of 200-400 m inside a braking approach
        x, v, cmd = pilot
        brake = np.flatnonzero((cmd < -0.1) & (v > 5.0))
        length = float(rng.uniform(200.0, 400.0))
        for _ in range(100):
            s0 = float(x[rng.choice(brake)])
            if np.all(cmd[(x >= s0) & (x <= s0 + length)] < 0.0):
                break
        return FS.Effect(adhesion=(s0, s0 + length, float(rng.uniform(0.5, 0.7))))
    if kind == "power_limit":
        # the knee at 40-60 % of the top speed for the largest traction command
        x, v, cmd = pilot
        a_max = float(train.get("performance", {}).get("max_traction", 0.8))
        return FS.Effect(p_spec=a_max * float(rng.uniform(0.4, 0.6)) * float(v.max()))
    if kind == "traction_delay":
        return FS.Effect(traction_delay=float(train["brake"]["delay"])
                         + float(rng.uniform(0.6, 1.0)))
    raise ValueError(kind)


def subtle(eff: FS.Effect, train: dict, v_top: float) -> FS.Effect:
    """``eff`` at half its deviation from the believed train (``--subtle``), as
    ``train_sim.cases``' subtle size is half its plain one: the same draw and place, each
    quantity half-way between the believed value and the plain effect's (a gradient's per mille
    and a clock's drift halved). A power limit is half-way between the plain one and the limit
    whose knee is the run's top speed ``v_top`` (m/s): one that binds over half the speeds.
    (Halving 1 / p_spec instead puts the knee at 80-120 % of the top speed: on seeds 0 and 1 it
    bound for 1 s and never; no data can show it.)"""
    def mid(true: float, believed: float) -> float:
        return believed + 0.5 * (true - believed)

    d, delay = train["davis"], float(train["brake"]["delay"])
    return dataclasses.replace(
        eff,
        gradient=None if eff.gradient is None else (*eff.gradient[:2], 0.5 * eff.gradient[2]),
        davis=None if eff.davis is None else tuple(
            mid(v, float(d[k])) for v, k in zip(eff.davis, ("a", "b", "c"))),
        braking_rate=mid(eff.braking_rate, 1.0), mass=mid(eff.mass, 1.0),
        odometer_scale=mid(eff.odometer_scale, 1.0),
        brake_delay=None if eff.brake_delay is None else mid(eff.brake_delay, delay),
        clock_drift=0.5 * eff.clock_drift,
        adhesion=None if eff.adhesion is None else (*eff.adhesion[:2],
                                                    mid(eff.adhesion[2], 1.0)),
        p_spec=None if eff.p_spec is None else mid(
            eff.p_spec, float(train.get("performance", {}).get("max_traction", 0.8)) * v_top),
        traction_delay=None if eff.traction_delay is None else mid(eff.traction_delay, delay))


def unlisted_effect_of(kind: str, line: dict, train: dict, rng, pilot) -> FS.Effect:
    """One effect outside the list (``UNLISTED``), of a plain listed effect's size (an extra
    0.04-0.08 m/s^2 where it acts, or 20-60 % of the traction or braking), placed where the
    nominal ``pilot`` run = (x, v, command, t) at its commands exercises it."""
    x, v, cmd, t = pilot
    v_top = float(v.max())
    m_eff = (1.0 + float(train.get("rotary_allowance", 0.0))) * float(train["mass"])
    acc = float(rng.uniform(0.04, 0.08))  # m/s^2
    span = float(t[-1] - t[0])

    def mid_time(lo, hi):
        return float(t[0] + rng.uniform(lo, hi) * span)

    if kind == "traction_gain":
        f = float(rng.uniform(0.2, 0.3))
        return FS.Effect(traction_gain=1.0 + f if rng.random() < 0.5 else 1.0 - f)
    if kind == "traction_fade":
        return FS.Effect(traction_fade=(float(rng.uniform(0.4, 0.6)) * v_top,
                                        float(rng.uniform(0.6, 0.75))))
    if kind == "traction_cut":
        ok = np.flatnonzero((cmd > 0.15) & (v > 3.0))
        s0 = float(x[rng.choice(ok)]) - 100.0
        return FS.Effect(traction_cut=(s0, s0 + float(rng.uniform(300.0, 600.0)),
                                       float(rng.uniform(0.4, 0.6))))
    if kind == "traction_trip":
        on = np.flatnonzero((cmd[1:] > 0.05) & (cmd[:-1] <= 0.05)) + 1
        mid = [i for i in on if 0.2 * span <= t[i] - t[0] <= 0.7 * span] or list(on)
        t0 = float(t[rng.choice(mid)])
        return FS.Effect(traction_trip=(t0, t0 + float(rng.uniform(60.0, 120.0)),
                                        float(rng.uniform(0.4, 0.6))))
    if kind == "brake_fade":
        return FS.Effect(brake_fade=(float(rng.uniform(0.35, 0.5)) * v_top,
                                     float(rng.uniform(0.6, 0.75))))
    if kind == "brake_power":
        brake = -cmd[(cmd < -0.05) & (v > 1.0)]
        a_ref = float(np.median(brake)) if brake.size else 0.5
        return FS.Effect(brake_power=float(rng.uniform(0.45, 0.65)) * v_top * a_ref)
    if kind == "tunnel":
        fast = np.flatnonzero(v > 0.6 * v_top)
        length = float(rng.uniform(500.0, 900.0))
        s0 = float(np.clip(x[rng.choice(fast)] - 0.5 * length, x.min(), x.max() - length))
        inside = (x >= s0) & (x < s0 + length)
        v_in = float(np.mean(v[inside])) if inside.any() else v_top
        return FS.Effect(tunnel=(s0, s0 + length, acc * m_eff / max(v_in, 1.0) ** 2))
    if kind == "wind":
        dur = float(rng.uniform(60.0, 120.0))
        moving = t[(v > 2.0) & (t > t[0] + 10.0) & (t < t[-1] - dur)]
        t0 = float(rng.choice(moving)) if moving.size else mid_time(0.2, 0.5)
        return FS.Effect(wind=(t0, t0 + dur, _sign(rng) * acc * m_eff))
    if kind == "coast_drag":
        return FS.Effect(coast_drag=acc)
    if kind == "hunting":
        return FS.Effect(hunting=(float(rng.uniform(0.6, 0.8)) * v_top, acc * m_eff))
    if kind == "warmup":
        return FS.Effect(warmup=(float(rng.uniform(0.2, 0.35)) * span, 1.5 * acc * m_eff))
    if kind == "odometer_bias":
        return FS.Effect(odometer_bias=_sign(rng) * float(rng.uniform(0.04, 0.1)))
    if kind == "brake_heat":
        # brakes 30-45 % weaker once they hold the heat of a stop from the top speed, cooling
        # with a time constant of 60-150 s
        return FS.Effect(brake_heat=(0.5 * v_top * v_top, float(rng.uniform(60.0, 150.0)),
                                     float(rng.uniform(0.3, 0.45))))
    if kind == "balise_late":
        return FS.Effect(balise_late=float(rng.uniform(0.2, 0.5)))
    if kind == "odometer_lag":  # a speed filtered or computed over a gate, the count on time
        return FS.Effect(odometer_lag=float(rng.uniform(0.2, 0.4)))
    if kind == "balise_datum":  # the balise map surveyed on another datum than the gradients
        return FS.Effect(balise_datum=_sign(rng) * float(rng.uniform(5.0, 10.0)))
    if kind == "payload":  # a load taken on at a middle stop, the brake not load-weighed
        k = len(line["stations"]) // 2
        return FS.Effect(payload=(k, float(rng.uniform(1.05, 1.12))))
    if kind == "odometer_speed":
        # a radar whose error grows as the square of the speed: 1-2 % at the top speed
        return FS.Effect(odometer_speed=(v_top, _sign(rng) * float(rng.uniform(0.01, 0.02))))
    if kind == "balise_moved":
        xb = sorted((float(b["position"]), int(b["id"])) for b in line.get("balises", [])
                    if x.min() < float(b["position"]) < x.max())
        inner = [(p, i) for p, i in xb[1:-1] if np.interp(p, x, v) > 3.0]
        _, bid = inner[int(rng.integers(len(inner)))]
        return FS.Effect(balise_moved=(bid, _sign(rng) * float(rng.uniform(8.0, 20.0))))
    if kind == "clock_step":
        return FS.Effect(clock_step=(mid_time(0.3, 0.7), _sign(rng) * float(rng.uniform(0.5, 3.0))))
    raise ValueError(kind)


def foreign_case(seed: int, kind: str, directory: str, family: str | None = None,
                 sim: dict | None = None, effect: dict | None = None,
                 size: str = "plain") -> tuple:
    """Seed ``seed``'s line and believed train (``make_case``; with ``family``, one of
    ``foreign_sim.OTHER_FAMILIES`` instead), written to ``directory``, and the effect of
    ``kind`` placed from a nominal pilot run with the same driver and link options ``sim``:
    (case, paths, line dict, train dict, the pilot's (x, v, command) at its commands,
    effect, with the fields of ``effect`` set: ``--set``); ``case.family`` names the family.
    ``size`` "subtle": a listed effect at half its plain deviation (:func:`subtle`)."""
    if family is None:
        from train_sim.cases import make_case

        case = make_case(np.random.default_rng([seed, 5]), None, "plain")
        paths = case.write(directory)
    else:
        import yaml

        drawn = FS.other_line_train(family, np.random.default_rng(
            [seed, 5, 1 + list(FS.OTHER_FAMILIES).index(family)]))
        os.makedirs(directory, exist_ok=True)
        paths = {k: os.path.join(directory, f"{k}.yaml") for k in ("line", "train")}
        for k, d in zip(("line", "train"), drawn):
            with open(paths[k], "w") as f:
                yaml.safe_dump(d, f, sort_keys=False)
        case = SimpleNamespace(family=family)
    line, train = FS.load(str(paths["line"])), FS.load(str(paths["train"]))
    trace: list = []
    FS.simulate(line, train, FS.Effect(), np.random.default_rng([seed, 1]), trace=trace,
                **(sim or {}))
    pilot = tuple(np.array([r[i] for r in trace]) for i in (1, 2, 3, 0))
    if kind in UNLISTED:
        eff = unlisted_effect_of(kind, line, train, np.random.default_rng(
            [seed, 4, list(UNLISTED).index(kind)]), pilot)
    else:
        eff = effect_of(kind, line, train, np.random.default_rng([seed, 2, KINDS.index(kind)]),
                        pilot[:3])
        if size == "subtle":
            eff = subtle(eff, train, float(pilot[1].max()))
    if effect:
        eff = dataclasses.replace(eff, **effect)
    return case, paths, line, train, pilot, eff


def run_case(spec: dict) -> dict:
    from train_estimation.tools import diagnose as tool

    seed, kind = spec["seed"], spec["kind"]
    keep = spec.get("keep")
    if keep:  # the case's files, its bag and diagnose's output kept in KEEP/KIND-SEED
        keep = os.path.join(keep, f"{kind}-{seed}")
        shutil.rmtree(keep, ignore_errors=True)
        os.makedirs(keep)
    with contextlib.nullcontext(keep) if keep else \
            tempfile.TemporaryDirectory(prefix="bench_foreign_") as d:
        case, paths, line, train, pilot, eff = foreign_case(seed, kind,
                                                            os.path.join(d, "case"),
                                                            spec.get("family"),
                                                            spec.get("sim"),
                                                            spec.get("effect"),
                                                            spec.get("size", "plain"))
        out = {**spec, "family": case.family, "effect": repr(eff)}
        if kind == "coast_drag":
            # a drag while coasting acts only where the run coasts: this driver holds its speed
            # with small commands and coasts little on some lines (a high-speed one under 1 s)
            x, v, cmd, t = pilot
            coast = float(np.sum(np.diff(t)[((cmd == 0.0) & (v > 0.5))[:-1]]))
            if coast < COAST_MIN:
                return {**out, "na": f"the run coasts {coast:.1f} s"}
        try:
            events = FS.simulate(line, train, eff, np.random.default_rng([seed, 3]),
                                 **spec.get("sim", {}))
        except RuntimeError as exc:  # the foreign driver failed: shown, not a diagnose result
            return {**out, "rc": f"sim: {exc}"}
        bag = os.path.join(d, "bag")
        FS.write_bag(events, bag)
        t0 = time.perf_counter()
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            rc = tool.main(["--bag", bag, "--line", str(paths["line"]), "--train",
                            str(paths["train"]), "--out", os.path.join(d, "diag"), "--quiet"])
        out["time"] = time.perf_counter() - t0
        out["rc"] = rc
        if rc != 0:
            return out
        rep = json.load(open(os.path.join(d, "diag", "report.json")))
    out["reported"] = rep["cause"]
    out["confirmed"] = [r["cause"] for r in rep["ranking"] if r.get("status") == "confirmed"
                        and r["cause"] != "none"]
    out["unexplained"] = [u.get("phase") for u in rep.get("unexplained", [])]
    # entries one run cannot tell from a rival law (a low-adhesion section from a force fixed
    # at its place): not confirmed, shown beside what was reported
    from train_estimation.core.offline.diagnose.confirm import UNDECIDED

    out["undecided"] = [r["cause"] for r in rep["ranking"]
                        if (r.get("why") or "").startswith(UNDECIDED)]
    if kind in UNLISTED:
        # right: no listed cause confirmed and the remainder named, in the effect's phase first
        out["phase"] = UNLISTED[kind]
        out["right"] = rep["cause"] == "unexplained" and not out["confirmed"]
        out["phase_right"] = bool(out["unexplained"]) and out["unexplained"][0] == out["phase"]
        return out
    out["right"] = (rep["cause"] == kind and (kind == "none" or kind in out["confirmed"])
                    and len(out["confirmed"]) == (0 if kind == "none" else 1))
    return out


def run_estimators(spec: dict) -> list[dict]:
    """Every estimator on one foreign run (``--estimators``): the clean stream the link delivered,
    on the fault campaign's clocks and latency (``tools.faults``, no fault), replayed through the
    runner the nodes use with the node defaults and scored as the integrity campaign scores.
    ``spec["config"]``: estimator parameters other than the defaults (``--no-distance``:
    ``use_distance: false``); ``spec["priors"]``: the integrity monitor's stated priors.
    With ``spec["recorded"]`` (``--as-recorded``) the messages as
    the ground logged them instead: the train's own clock (its epoch, drift and step), the
    link's own latency and losses (:func:`recorded_stream`)."""
    from train_core.model import load_line, load_train

    from train_estimation.core.online.estimators import NodeConfig
    from train_estimation.tools import faults as F

    seed, kind = spec["seed"], spec["kind"]
    if kind in STAMP_KINDS and not spec.get("recorded"):
        # the stream is stamped again on the campaign's clocks from the true sample times: the
        # foreign clock is not carried (clock faults: ./run bench integrity)
        return [{**spec, "estimator": name, "na": "stamps not carried"} for name in ESTIMATORS]
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_foreign_") as d:
        case, paths, line_d, train_d, _, eff = foreign_case(seed, kind,
                                                           os.path.join(d, "case"),
                                                           spec.get("family"),
                                                           spec.get("sim"),
                                                           spec.get("effect"))
        line, train = load_line(str(paths["line"])), load_train(str(paths["train"]))
    sent, truth, clock = [], [], {}
    logged = FS.simulate(line_d, train_d, eff, np.random.default_rng([seed, 3]), sent=sent,
                         truth=truth, clock=clock, **spec.get("sim", {}))
    tr = np.array(truth)
    tr_d = {"t": tr[:, 0], "position": tr[:, 1], "velocity": tr[:, 2]}
    rate = 10.0
    cfg = NodeConfig()
    if spec.get("recorded"):
        fl = recorded_stream(logged, sent, clock)
    else:
        sent.sort(key=lambda e: e[1])
        fl = F.inject(sent, F.Fault("none"), np.random.default_rng(seed))  # the same for each
    sc = SimpleNamespace(train=train, line=line, start_position=float(tr[0, 1]),
                         odometer_rate=rate)
    for name in spec.get("estimators", ESTIMATORS):
        row = {**spec, "family": case.family, "estimator": name, "effect": repr(eff)}
        try:
            # as the integrity campaign makes it, with spec["config"]'s parameters
            ad = make_adapter(sc, name, **spec.get("config", {}))
        except ValueError as exc:  # the estimator cannot model this train
            row["na"] = str(exc)
            rows.append(row)
            continue
        try:
            outs, emitted, _ = F.run(fl.events, ad, 1 / rate, delay=cfg.output_delay,
                                     tick_period=cfg.tick_period,
                                     control_clock=cfg.control_clock,
                                     max_future=cfg.max_future, slot_grace=cfg.slot_grace,
                                     integrity=IntegrityParams(**spec.get("priors", {})))
        except Exception as exc:  # counted and shown
            row["exception"] = f"{type(exc).__name__}: {exc}"
            rows.append(row)
            continue
        row.update(F.score(outs, emitted, fl, tr_d, rate, float(tr[-1, 0]) + F.LATENCY))
        row["events"] = dict(ad.counters)  # the adapter's events (relocated, balise_latency...)
        row["balise_latency"] = ad.balise_latency()
        rows.append(row)
    return rows


def recorded_stream(logged: list, sent: list, clock: dict):
    """A foreign run as the ground logged it, as ``tools.faults.Faulted`` for the runner and
    the scoring: ``logged`` = ``foreign_sim.simulate``'s [(log time, topic, stamp, fields)],
    ``sent`` its true sample times (one per logged message, in the same order), ``clock`` its
    clocks. Odometer and balise keep the train's stamps (an epoch of 1e8-1e9 s, the drift, the
    step); the reference clock (log time, the commands' stamps) is moved from the foreign
    epoch to ``faults.EPOCH``, which only names its zero, so that the scoring's true time is
    the simulator's. Arrivals carry the foreign link's own latency; the lost messages are
    absent."""
    from train_estimation.tools import faults as F

    shift = F.EPOCH - clock["ref_epoch"]
    rows = sorted(((log + shift, topic, stamp + shift if topic == "control" else stamp, fields,
                    t) for (log, topic, stamp, fields), (_, t, _) in zip(logged, sent)),
                  key=lambda r: r[0])
    events = [(topic, stamp, fields, recv) for recv, topic, stamp, fields, _ in rows]
    step = clock.get("step")
    steps, seen = (), ()
    if step is not None:
        steps = ((float(step[0]), float(step[1])),)
        # the step is known from the arrival of its first reading on (faults.TrainClock)
        seen = (min((recv - F.EPOCH for recv, topic, _, _, t in rows
                     if topic in F.TRAIN_TOPICS and t >= step[0]), default=math.inf),)
    tc = F.TrainClock(epoch=clock["train_epoch"], drift=clock["drift"], steps=steps, seen=seen)
    onset = steps[0][0] if steps else 0.0
    return F.Faulted(events, tc, onset, math.inf if steps or clock["drift"] else onset)


def estimator_table(rows: list) -> str:
    """Per hidden effect and estimator, the integrity campaign's figures (``faults.score``):
    misleading estimates (the true position outside the published protection levels, not
    ALARM), wrong-side ones (OK with an error beyond the alert limit), availability (both
    levels within the alert limit), the median protection level, the errors."""
    md = ["| hidden | estimator | runs | misleading | wrong-side | availability % (min) | "
          "median PL m (max) | max err m | RMS err m (max) | non-PD cov | exceptions |",
          "|---|---|---|---|---|---|---|---|---|---|---|"]
    for k in KINDS + tuple(UNLISTED):
        for name in ESTIMATORS:
            sel = [r for r in rows if r["kind"] == k and r["estimator"] == name
                   and "na" not in r]
            if not sel:
                continue
            ok = [r for r in sel if "exception" not in r]
            mis = sum(r["misleading"] for r in ok)
            ws = sum(r["wrong_side"] for r in ok)
            av = min((100 * r["availability"] for r in ok), default=float("nan"))
            pl = max((r["pl_median"] for r in ok), default=float("nan"))
            me = max((r["max_err"] for r in ok), default=float("nan"))
            rm = max((r["rms_err"] for r in ok), default=float("nan"))
            pd = sum(r["bad_cov"] for r in ok)
            md.append(f"| {k} | {name} | {len(sel)} | {mis} | {ws} | {av:.1f} | {pl:.1f} | "
                      f"{me:.2f} | {rm:.2f} | {pd} | {len(sel) - len(ok)} |")
    n = sum(r.get("outputs", 0) for r in rows)
    mis = sum(r.get("misleading", 0) for r in rows)
    ws = sum(r.get("wrong_side", 0) for r in rows)
    md.append(f"\nmisleading estimates: {mis} of {n}; wrong-side: {ws}")
    return "\n".join(md)


def right_beside_link(r: dict) -> bool:
    """Right when a ``bursty_link`` confirmed beside the hidden cause is counted as true: this
    simulator's link is a Gilbert-Elliott chain in every run (``foreign_sim.simulate``), so
    the link's bursts are there to be found whatever effect is hidden."""
    if r.get("rc") != 0 or "confirmed" not in r:
        return False
    want = [] if r["kind"] == "none" else [r["kind"]]
    return ([c for c in r["confirmed"] if c != "bursty_link"] == want
            and r["reported"] in (r["kind"], "bursty_link"))


def table(results: list) -> str:
    md = ["| hidden | right | right, the link's bursts beside it allowed | reported instead |",
          "|---|---|---|---|"]
    for k in KINDS:
        rows = [r for r in results if r["kind"] == k]
        if not rows:
            continue
        ok = sum(bool(r.get("right")) for r in rows)
        ok_link = sum(right_beside_link(r) for r in rows)
        other = Counter(f"{r.get('reported', 'rc ' + str(r.get('rc')))}"
                        + (f" (+{'+'.join(c for c in r['confirmed'] if c != r['reported'])})"
                           if len([c for c in r.get("confirmed", []) if c != r["reported"]])
                           else "")
                        + "".join(f" ({c} or its rival: not told apart)"
                                  for c in r.get("undecided", []))
                        for r in rows if not r.get("right"))
        md.append(f"| {k} | {ok}/{len(rows)} | {ok_link}/{len(rows)} | "
                  + (", ".join(f"{n} x{c}" for n, c in other.most_common()) or "-") + " |")
    n = len(results)
    ok = sum(bool(r.get("right")) for r in results)
    ok_link = sum(right_beside_link(r) for r in results)
    md.append(f"| all | {ok}/{n} | {ok_link}/{n} | |")
    t = [r["time"] for r in results if "time" in r]
    md.append(f"\ntime per bag (diagnose): mean {np.mean(t):.1f} s, max {np.max(t):.1f} s")
    return "\n".join(md)


def unlisted_table(results: list) -> str:
    """Effects outside the list: ``unexplained`` with no listed cause confirmed, a listed cause
    confirmed, the signature's phase right (its first entry)."""
    md = ["| effect (phase) | n | `unexplained` | listed cause confirmed | phase right | "
          "reported |", "|---|---|---|---|---|---|"]

    for k in list(UNLISTED) + [None]:
        rows = [r for r in results if r["kind"] in UNLISTED and (k is None or r["kind"] == k)
                and "na" not in r]
        na = [r for r in results if "na" in r and (k is None or r["kind"] == k)]
        if not rows:
            continue
        n = len(rows)
        conf = Counter(c for r in rows for c in r.get("confirmed", []))
        rep = Counter(r.get("reported", f"rc {r.get('rc')}") for r in rows)
        md.append(f"| {k + ' (' + UNLISTED[k] + ')' if k else '**all**'} | {n} | "
                  f"{pct(sum(bool(r.get('right')) for r in rows), n)} | "
                  f"{pct(sum(bool(r.get('confirmed')) for r in rows), n)}"
                  + (f" ({', '.join(f'{c} {m}' for c, m in conf.most_common())})"
                     if conf else "")
                  + f" | {pct(sum(bool(r.get('phase_right')) for r in rows), n)} | "
                  + ", ".join(f"{c} {m}" for c, m in rep.most_common())
                  + (f"; not scored: {len(na)} ({na[0]['na']})" if na else "") + " |")
    md.append("\ntargets (diagnose): `unexplained` >= 80 %, a listed cause confirmed <= 10 %, "
              "the phase right >= 80 %")
    t = [r["time"] for r in results if "time" in r]
    md.append(f"\ntime per bag (diagnose): mean {np.mean(t):.1f} s, max {np.max(t):.1f} s")
    return "\n".join(md)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="bench_foreign", description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="\n".join(__doc__.splitlines()[2:]))
    p.add_argument("--seeds", type=int, default=6, help="lines and trains drawn (default 6)")
    p.add_argument("--first", type=int, default=0, help="first seed (default 0)")
    p.add_argument("--kinds", nargs="*", default=None, choices=KINDS + tuple(UNLISTED),
                   help="effects (default: the listed causes and none; with --unlisted, the "
                        "effects outside the list)")
    p.add_argument("--unlisted", action="store_true",
                   help="effects outside diagnose's list instead: how often it says "
                        "`unexplained` and confirms no listed cause (with --estimators: "
                        "the estimators' integrity on them)")
    p.add_argument("--subtle", action="store_true",
                   help="listed effects at half their plain deviation from the believed train "
                        "(the same draws and places; train_sim.cases' subtle size), results in "
                        "foreign_subtle")
    p.add_argument("--jobs", type=int, default=1, help="parallel processes (default 1)")
    p.add_argument("--estimators", action="store_true",
                   help="run every estimator on the runs instead of diagnose (the integrity "
                        "campaign's figures: misleading, wrong-side, availability, "
                        "protection level, error)")
    p.add_argument("--no-distance", action="store_true",
                   help="with --estimators: the estimators with use_distance: false (the "
                        "odometer's speed and the balises, its distance unread)")
    p.add_argument("--as-recorded", action="store_true",
                   help="with --estimators: the messages as the ground logged them (the "
                        "train's own clock, epoch, drift and step; the link's own latency) "
                        "instead of the clean stream on the campaign's clocks")
    # driver and link variants: None keeps foreign_sim.simulate's own default (the bench's)
    p.add_argument("--odo-rate", type=float, help="odometer samples per second (default 10)")
    p.add_argument("--cmd-rate", type=float, help="driver commands per second (default 5)")
    p.add_argument("--notch", type=float,
                   help="m/s^2: commands rounded to a master controller's notches (default: "
                        "continuous)")
    p.add_argument("--on-change", type=float,
                   help="s: a command is logged only when it changes or this long after the "
                        "last one logged (default: every command)")
    p.add_argument("--link-tail", type=float,
                   help="s: mean of the link latency's exponential tail (default 0.015)")
    p.add_argument("--coast", type=float,
                   help="coast-and-motor driving: coast from the cruise speed down to this "
                        "fraction of it, then motor back up (default: hold the speed)")
    p.add_argument("--family", choices=tuple(FS.OTHER_FAMILIES),
                   help="lines and trains of another family than our cases' (foreign_sim."
                        "OTHER_FAMILIES: freight, mountain, tram; default: train_sim.cases')")
    p.add_argument("--keep", metavar="DIR",
                   help="keep each case in DIR/KIND-SEED (line.yaml and train.yaml in case/, "
                        "the bag in bag/, diagnose's output in diag/; replaced if there) "
                        "instead of a temporary directory: the bags to run diagnose on again")
    p.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                   help="set a field of every drawn effect (foreign_sim.Effect), e.g. "
                        "balise_late=1.0 with --kinds balise_late: a size the draw does not "
                        "reach")
    add_prior_args(p)  # with --estimators
    p.add_argument("--quick", action="store_true",
                   help="about 70 s: 2 seeds on 2 processes (each option given overrides), results "
                        "in NAME_quick")
    if p.parse_known_args(argv)[0].quick:  # the quick values as defaults: given ones win
        p.set_defaults(seeds=2, jobs=2)
    args = p.parse_args(argv)
    priors = stated_priors(p, args)
    if priors and not args.estimators:
        p.error("--balise-map-prior and --start-fault-prior go with --estimators")
    try:
        fields = {f.name for f in dataclasses.fields(FS.Effect)}
        override = {k: float(v) for k, v in (a.split("=", 1) for a in args.set)}
    except ValueError:
        p.error("--set takes FIELD=VALUE pairs with a number for VALUE")
    if not set(override) <= fields:
        p.error(f"--set: unknown field(s) {sorted(set(override) - fields)} (foreign_sim.Effect "
                f"has {', '.join(sorted(fields))})")
    sim = {k: v for k, v in (("odo_rate", args.odo_rate), ("cmd_rate", args.cmd_rate),
                             ("notch", args.notch), ("on_change", args.on_change),
                             ("tail", args.link_tail), ("coast", args.coast))
           if v is not None}
    if args.kinds is None:
        args.kinds = list(UNLISTED) if args.unlisted else list(KINDS)
    if args.subtle and args.unlisted:
        p.error("--subtle halves the listed effects; the effects outside the list have one size")
    if (args.as_recorded or args.no_distance) and not args.estimators:
        p.error("--as-recorded and --no-distance go with --estimators")
    specs = [{"seed": s, "kind": k, **({"sim": sim} if sim else {}),
              **({"family": args.family} if args.family else {}),
              **({"recorded": True} if args.as_recorded else {}),
              **({"config": {"use_distance": False}} if args.no_distance else {}),
              **({"priors": priors} if priors else {}),
              **({"effect": override} if override else {}),
              **({"size": "subtle"} if args.subtle else {}),
              **({"keep": os.path.abspath(args.keep)} if args.keep else {})}
             for s in range(args.first, args.first + args.seeds) for k in args.kinds]
    fn, name = (run_estimators, "foreign_estimators") if args.estimators else \
        (run_case, "foreign")
    name += "_unlisted" if args.unlisted else ""
    name += "_subtle" if args.subtle else ""
    name += "".join(f"_{k}{v:g}" for k, v in sim.items())  # a variant's own file
    name += f"_{args.family}" if args.family else ""
    name += "_as_recorded" if args.as_recorded else ""
    name += "_no_distance" if args.no_distance else ""
    name += "_quick" if args.quick else ""
    name += "".join(f"_{k}{v:g}" for k, v in override.items())
    prog = Progress(f"bench {name.replace('_', ' ')}")
    results = []
    prog(0, len(specs), "")
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as ex:
        for i, r in enumerate(ex.map(fn, specs)):
            results += r if args.estimators else [r]
            prog(i + 1, len(specs), specs[i]["kind"])
    print(estimator_table(results) if args.estimators else
          unlisted_table(results) if args.unlisted else table(results))
    os.makedirs(OUT, exist_ok=True)
    with open(os.path.join(OUT, f"{name}.json"), "w") as f:
        json.dump(results, f, indent=1, default=str)
    return 0


if __name__ == "__main__":
    sys.exit(main())
