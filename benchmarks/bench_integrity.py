#!/usr/bin/env python3
"""Integrity benchmark: a seeded fault campaign over every estimator and the zone controller.

Each fault of ``train_estimation.tools.faults`` (one or a few readings with wrong stamps, clock
steps, drift, odometer outages while accelerating / cruising / braking, the command stream
stopping, link latency tails, recorder and node stalls, the fuzz mix with stamps inside
``max_future``, a balise lying metres from its map position, an odometer whose scale is up to
2 % off, a sample counter that skips or repeats samples), at several sizes and times, on
metro_demo, crh3_high_speed and wen2017_subway (and the real lines yizhuang_metro and
zurich_stadelhofen where their TTOBench files are: docs/real_lines.md; a note says where to put
an absent one), is replayed through the runner the nodes use
(node defaults: ``NodeConfig``), arrival = stamp + 50 ms. Per fault and estimator (seeds
pooled) the table gives:

- wrong-side: estimates with integrity OK (0) while |error| > 1 m and > 5 sigma (sigma: the
  published position variance); off-run: OK estimates stamped > 1 s outside the simulated run;
- time to alarm (s): from the first estimate whose error exceeds that bound to the first
  non-OK estimate published since the fault's onset ("-": the bound was never exceeded;
  "never": no alarm);
- availability: OK estimates published within 1 s of the time they claim, over the odometer
  slots from the onset on; the longest silence;
- max and RMS |error| from the onset on, and the largest |error| until 10 s after the fault's
  end (the outage figure); non-PD (negative or non-finite) covariances; exceptions.

Zone-controller rows (``train_sim.zone``, pure logic): bad reports and report streams (a
negative or NaN braking-rate variance, a stamp 1e6 s ahead, an estimator's clock reset, ALARM,
DEGRADED (bounded by its protection levels: no brake due), reports stopping, fuzzed reports),
counting crashes, bad reports accepted, lock-ups (emergency brake still on 5 s after good
reports are back) and the time to brake.

Then one line per target of the integrity issue with PASS/FAIL.

Usage::

    ./run bench integrity --quick          # robust_filter and kf, one size per class (< 2 min)
    ./run bench integrity --jobs 2         # all estimators, sizes and times, fuzz >= 1e6 / est.
    ./run bench integrity --only step drift --estimators kf
"""

from __future__ import annotations

import argparse
import functools
import math
import random
import sys
import traceback
import zlib
from collections import defaultdict
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import fields as dc_fields
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
for _p in (ROOT / "ros_ws/src/train_sim", ROOT / "ros_ws/src/train_estimation",
           ROOT / "ros_ws/src/train_core"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

from train_core.realtime import single_threaded_blas  # noqa: E402

single_threaded_blas()

import numpy as np  # noqa: E402
from train_core.progress import track  # noqa: E402

from train_estimation.core.online.estimators import (  # noqa: E402
    BrakingAdapter,
    BrakingConfig,
    NodeConfig,
    RobustAdapter,
    RobustConfig,
    StartState,
)
from train_estimation.core.online.integrity import IntegrityParams  # noqa: E402
from train_estimation.tools import faults as F  # noqa: E402
from train_sim.scenario import load_scenario  # noqa: E402
from train_sim.world import simulate  # noqa: E402
from train_sim.zone import TrainReport, ZoneController, ZoneParams  # noqa: E402

ESTIMATORS = ("robust_filter", "kf", "gsma", "sma", "rbpf", "qgrbpf")
QUICK_ESTIMATORS = ("robust_filter", "kf")
SCENARIOS = ("metro_demo", "crh3_high_speed", "wen2017_subway")
AFTER = 60.0  # s of run kept after a fault's end (the recovery)
QUICK_REAL = 600.0  # s of a real line's run in the quick campaign (Yizhuang: 4 stops, 8 km)
JITTER = 0.05  # s, mean exponential extra latency of the jittery-link step faults


# -- runs ------------------------------------------------------------------------------------------

@functools.lru_cache(maxsize=4)
def _sim(scenario: str, seed: int, duration: float, groups: float = 0.0,
         rate: float | None = None):
    sc = load_scenario(scenario)
    if rate:  # another odometer: its samples (and the commands, the truth, the radio's
        sc = sc.with_changes(odometer_rate=rate)  # cycle) at ``rate`` Hz
    if groups:
        sc = with_balise_groups(sc, groups)
    return sc, simulate(sc, seed, duration)


def with_balise_groups(sc, spacing: float):
    """The scenario with a second balise ``spacing`` m after each of its line's, in the map
    and on the track (a group of two at each place, as ETCS lays them; the new ids follow the
    line's highest): what references of another kind than the line's single balises give."""
    line = sc.line
    top = max((b.id for b in line.balises), default=0)
    twins = [replace(b, id=top + 1 + i, position=b.position + spacing)
             for i, b in enumerate(line.balises) if b.position + spacing < line.length]
    both = tuple(sorted((*line.balises, *twins), key=lambda b: b.position))
    return replace(sc, line=line.with_changes(balises=both)).with_effects(sc.effects)


def make_adapter(sc, name: str, fault=None, **config):
    """The estimator ``name`` with its node defaults, or ``config``'s parameters instead; its
    start where ``fault`` puts it (``start_offset``: off the train's)."""
    st = StartState(sc.start_position if fault is None else
                    F.start_position(fault, sc.start_position))
    if name == "robust_filter":
        return RobustAdapter(sc.train, sc.line, st,
                             RobustConfig(period=1 / sc.odometer_rate, **config))
    return BrakingAdapter(sc.train, sc.line, st, BrakingConfig(algorithm=name, **config))


def phases(truth: dict) -> dict:
    """True times (s) at which the train starts accelerating, cruising and braking (first
    occurrence): a fault placed there meets that motion."""
    t, v, a = (np.asarray(truth[k], float) for k in ("t", "velocity", "acceleration"))
    vmax = v.max()

    def first(mask, default):
        i = np.flatnonzero(mask)
        return float(t[i[0]]) if i.size else default

    acc = first((a > 0.3) & (v > 1.0), t[len(t) // 4])
    cruise = first((t > acc) & (v > 0.8 * vmax) & (np.abs(a) < 0.25), t[len(t) // 2])
    brake = first((t > cruise) & (a < -0.25) & (v > 0.5 * vmax), t[3 * len(t) // 4])
    return {"accelerating": round(acc, 1), "cruising": round(cruise, 1),
            "braking": round(brake, 1)}


def run_task(task: dict) -> dict:
    """One fault on one scenario and seed through one estimator: the scores (faults.score)."""
    sc, res = _sim(task["scenario"], task["seed"], task["sim_duration"],
                   task.get("balise_groups", 0.0), task.get("odometer_rate"))
    fault = task["fault"]
    end = task["duration"]
    events = [e for e in res.events() if e[1] <= end]
    # the truth a second past the end where simulated: estimates stamped up to a second past
    # the last reading (a corrupted stamp's slot) are judged against the train, not its last
    # position (F.score judges none past the truth's end)
    tr = {k: np.asarray(v)[np.asarray(res.truth["t"]) <= end + 1.0]
          for k, v in res.truth.items()}
    row = dict(task, exceptions=0, error="")
    try:
        adapter = make_adapter(sc, task["estimator"], fault, **task.get("config", {}))
    except ValueError as exc:  # the estimator cannot model this train (no brake delay, ...)
        row["na"] = str(exc)
        return row
    case = zlib.crc32(f"{task['scenario']}|{fault.label}|{fault.at}".encode())
    rng = np.random.default_rng([task["seed"], case])
    faulted = F.inject(events, fault, rng)
    if task.get("no_counter"):  # a producer that leaves seq at 0: no sample counter
        faulted.events = F.uncounted(faulted.events)
    if task.get("count_noise"):  # a producer whose count is read with noise
        faulted.events = F.noisy_count(faulted.events, task["count_noise"],
                                       np.random.default_rng([task["seed"], 7, case]))
    cfg = NodeConfig()
    rate = sc.odometer_rate
    try:
        outs, emitted, runner = F.run(faulted.events, adapter, 1 / rate, delay=cfg.output_delay,
                                      tick_period=cfg.tick_period,
                                      control_clock=cfg.control_clock,
                                      max_future=cfg.max_future, slot_grace=cfg.slot_grace,
                                      stalled=faulted.stalled,
                                      **({"integrity": task["integrity"]}
                                         if "integrity" in task else {}))
    except Exception as exc:  # counted and shown: the campaign must see every failure
        row["exceptions"] = 1
        row["error"] = f"{type(exc).__name__}: {exc}"
        row["trace"] = traceback.format_exc(limit=3)
        return row
    row.update(F.score(outs, emitted, faulted, tr, rate, end + F.LATENCY))
    row.update(zone_in_loop(outs, emitted, tr))
    row["corrupted"] = sum(faulted.counts.values())
    return row


FOLLOWER_AT = 1.0  # m, where the follower of zone_in_loop stands
FOLLOWER_GAP = 10.0  # m, at least between the follower's front and the leader's true rear at the
#   leader's first estimate (zone_in_loop lifts the leader's line coordinates to make room)


def zone_in_loop(outs: list, emitted, truth: dict) -> dict:
    """The run's estimates as the leader's reports to a zone controller, a follower standing behind
    it: at every estimate's publication the follower's end of authority against the leader's
    true rear then. ``past_rear``: authorities granted (no emergency brake) that reach past it;
    ``granted``: authorities granted. The zone's margin is 0 (the authority is the leader's min
    safe rear itself: only its protection level guards it) and it judges stamps by arrival (the
    train clock may step or drift: ``check_stamp_age`` false).
    The follower stands ``FOLLOWER_GAP`` behind the leader's true rear at its first estimate:
    where the leader starts nearer the line's origin than that (a real line's first station
    at 0 m, the train's rear 120 m before it), the leader's reports and its truth are lifted
    along the line by the difference (the zone's rules do not depend on where the origin is;
    a follower placed ahead of the leader would be the zone's first train, never limited by it).
    ``stop_short``: reports the zone bounds (not ALARM, fresh) whose worst-case stopping point
    (max safe front carried to the present plus the stop from the worst-case speed at the
    nominal emergency braking: what the zone brakes on) lies short of the train's true one (true
    front plus the stop from its true speed): the supervision of the leader's own authority
    would brake too late."""
    p = ZoneParams(check_stamp_age=False, margin=0.0)
    zc = ZoneController(p)
    em = np.asarray(emitted, float)
    tr_t, tr_x = np.asarray(truth["t"], float), np.asarray(truth["position"], float)
    tr_v = np.asarray(truth["velocity"], float)
    x0 = float(np.interp(em[0] - F.EPOCH, tr_t, tr_x)) if em.size else 0.0
    lift = max(0.0, FOLLOWER_AT + FOLLOWER_GAP + p.train_length - x0)
    tr_x = tr_x + lift
    past = granted = short = 0
    for o, e in zip(outs, em):
        c = o.covariance
        zc.report("leader", TrainReport(
            t_received=float(e), stamp=float(o.stamp), position=float(o.position) + lift,
            velocity=float(o.velocity), var_position=float(c[0]), var_velocity=float(c[5]),
            cov_position_velocity=float(c[1]), cov_velocity_position=float(c[4]),
            measurement_used=bool(getattr(o, "measurement_used", True)),
            integrity=int(o.integrity), pl_ahead=float(o.protection_level_ahead),
            pl_behind=float(o.protection_level_behind)))
        zc.report("follower", TrainReport(
            t_received=float(e), stamp=float(e), position=FOLLOWER_AT, velocity=0.0,
            var_position=0.01, var_velocity=0.01, pl_ahead=0.5, pl_behind=0.5))
        lead, auth = zc.authorities(float(e), ["leader", "follower"])
        x_true = float(np.interp(e - F.EPOCH, tr_t, tr_x))
        if lead.state in ("ok", "overrun"):  # bounded and fresh: supervised by its bounds
            v_true = max(float(np.interp(e - F.EPOCH, tr_t, tr_v)), 0.0)
            short += zc.worst_stop("leader", zc.reports["leader"], float(e)) < \
                x_true + v_true * v_true / (2.0 * p.emergency_decel)
        if auth.emergency_brake:
            continue
        granted += 1
        past += auth.end_of_authority > x_true - p.train_length
    return dict(past_rear=int(past), granted=int(granted), stop_short=int(short))


def scenarios_here() -> tuple:
    """SCENARIOS and the real-line ones (train_sim.real_lines) whose track file is here; a
    note on stdout for each that is not (where to put it, how to get it)."""
    from train_sim.real_lines import available

    ok, missing = available()
    for name, why in missing.items():
        print(f"note: scenario {name} skipped: {why}")
    return SCENARIOS + tuple(ok)


def plan(quick: bool, seeds: int, estimators, only, phase_names=None, long: float | None = None,
         fuzz_rate: float | None = None, scenarios=SCENARIOS) -> list[dict]:
    """The campaign: tasks (scenario, seed, fault, estimator, run duration). A reduced full
    campaign: ``phase_names`` (the phases the stamp, step and command faults start in),
    ``long`` (s, the longest drift and fuzz run), ``fuzz_rate`` (corrupted per clean one)."""
    from train_sim.real_lines import REAL_SCENARIOS

    tasks = []
    for scenario in scenarios:
        sc = load_scenario(scenario)
        full = sc.duration
        if quick and scenario in REAL_SCENARIOS:
            full = min(full, QUICK_REAL)  # a real line's first stops: quick stays quick
        ph = phases(_sim(scenario, 0, full)[1].truth)
        cruise = ph["cruising"]
        times = [cruise] if quick else [v for k, v in ph.items()
                                        if not phase_names or k in phase_names]
        # quick: metro_demo's first leg (A to B and the dwell) for the whole-run faults
        short = min(full, 240.0) if quick else full
        faults = [(F.Fault("none"), short)]

        def add(f, extent, faults=faults, full=full):
            faults.append((f, min(full, f.at + extent + AFTER)))

        stamp_sizes = (60.0, -5.0) if quick else (0.1, -0.1, 1.0, -1.0, 10.0, -10.0, 60.0,
                                                    -60.0, 599.0, -599.0, 1e6, -1e6, 1e9, -1e9)
        step_sizes = (-3.0, 3.0) if quick else (-10.0, -6.0, -3.0, -0.5, -0.1, 0.1, 0.5, 3.0,
                                                 6.0, 10.0)
        if quick and scenario != "metro_demo":
            stamp_sizes, step_sizes = (60.0,), (-3.0,)
        for at in times:
            for s in stamp_sizes:
                add(F.Fault("stamp", s, at), 0.0)
            if not quick:
                for s in (60.0, 1e6):
                    add(F.Fault("stamp", s, at, count=3), 0.0)
            for s in step_sizes:
                add(F.Fault("step", s, at), 0.0)
            # the same steps on a jittery link (arrivals out of order: the step's readings
            # among the old clock's late ones)
            for s in (((-0.5,) if scenario == "metro_demo" else ()) if quick else
                      (-3.0, -0.5, -0.1, 0.1, 0.5, 3.0)):
                add(F.Fault("step", s, at, jitter=JITTER), 0.0)
            # a sample counter that skips (or repeats) samples while the clock runs on: no
            # clock step, whatever the grid says
            for s in (((1.0,) if scenario == "metro_demo" else ()) if quick else
                      (-1.0, 1.0, 3.0)):
                add(F.Fault("seq_skip", s, at), 0.0)
            add(F.Fault("command_stop", 0.0, at), 120.0 if quick else 400.0)
            # a balise that lies elsewhere than the map says: refused by the gate or fused,
            # never an estimate that claims the balise's position with the odometer's certainty
            for s in (((10.0,) if scenario == "metro_demo" else ()) if quick else
                      (-30.0, -10.0, -3.0, 3.0, 10.0, 30.0)):
                add(F.Fault("balise", s, at), 60.0)
        outage_at = list(ph.items()) if (not quick or scenario == "metro_demo") else \
            [("cruising", cruise)]
        for _, at in outage_at:
            for L in ((60.0,) if quick else (10.0, 30.0, 60.0, 120.0)):
                add(F.Fault("outage", L, at), L)
        # an odometer that stops counting and reads standstill: while the train runs (the
        # filter refuses it), and during the first dwell (the filter would follow it away)
        dwell = 0.5 * ph["accelerating"]
        for _, at in ([("cruising", cruise)] if quick and scenario != "metro_demo" else
                      [("dwell", dwell)] + list(ph.items())):
            add(F.Fault("stuck", 0.0, at), 240.0)
        # a count that freezes, or advances at half the distance, while its speed reads on:
        # each reading within its noise of the last one's course, nothing refuses it
        for _, at in ([("cruising", cruise)] if quick else list(ph.items())):
            for r in (0.0, 0.5):
                add(F.Fault("count_rate", r, at), 240.0)
        # an odometer that reboots: its counter and count begin again after a gap
        for _, at in ([("cruising", cruise)] if quick else list(ph.items())):
            for L in ((3.0,) if quick else (0.5, 3.0, 10.0)):
                add(F.Fault("reboot", L, at), L + 60.0)
            # and one whose clock steps with it (a unit that rebooted with its clock): after
            # the silence a step back reads as a link whose latency rose as much
            for d in ((-3.0,) if quick else (-10.0, -3.0, -0.5, 3.0)):
                add(F.Fault("reboot", 5.0, at, clock_step=d, jitter=JITTER), 65.0)
            # one whose clock resumed where it stopped (stepped back by the silence: the
            # stamps run on without a gap, a latency that rose as much reads the same), and
            # on a full run the same twice, 20 s apart, before a balise can tell the first
            add(F.Fault("reboot", 3.0, at, clock_step=-3.0), 65.0)
            if not quick:
                add(F.Fault("reboot", 3.0, at, clock_step=-3.0, again=20.0), 85.0)
        for L in ((8.0,) if quick else (2.0, 8.0, 20.0)):
            add(F.Fault("recorder_stall", L, cruise), L)
            add(F.Fault("node_stall", L, cruise), L)
        for cap in ((5.0,) if quick else (1.0, 5.0)):
            faults.append((F.Fault("latency", cap, 0.0), short))
        # a link that queues a second's readings every 30 s and then delivers them faster
        # than they were sampled, on a jittery link: their lateness falls reading after
        # reading, which no clock step does
        for r in (((1.5,) if scenario == "metro_demo" else ()) if quick else (1.2, 1.5, 2.0)):
            faults.append((F.Fault("queue", r, 0.5 * F.QUEUE_EVERY, jitter=JITTER), short))
        # a link whose latency rises and stays (a slower route): the offsets fall as a
        # backward clock step's would, the stamps run on
        for L in ((1.5,) if quick else (0.45, 1.5, 3.0)):
            add(F.Fault("route", L, cruise, jitter=JITTER), 120.0)
        # links whose latency wanders (3 ms to 0.3 s over about 20 s), each topic's on its
        # own, the commands' too: no clock step, no drift, no second clock
        for w in (((0.01, 0.1) if scenario == "metro_demo" else (0.1,)) if quick else
                  (0.003, 0.01, 0.03, 0.1, 0.3)):
            faults.append((F.Fault("wander", w, 0.0), short))
        drift_duration = short if quick else min(3600.0, long or math.inf)
        for d in ((-1e-2,) if quick else (-1e-2, -1e-3, 1e-3, 1e-2)):
            faults.append((F.Fault("drift", d, 0.0), drift_duration))
        if not quick:
            # the clock's faults on links whose latency wanders: a step, a reboot with its
            # clock and a drift, each to be told from the latency's own moves
            for s in (-3.0, -0.5, 0.5, 3.0):
                add(F.Fault("step", s, cruise, wander=0.1), 0.0)
            add(F.Fault("reboot", 5.0, cruise, clock_step=-3.0, wander=0.1), 65.0)
            for d in (-1e-3, 1e-3):
                faults.append((F.Fault("drift", d, 0.0, wander=0.03), drift_duration))
        # a wheel diameter off by up to 2 %, from the start: the odometer's distance and
        # speed both scaled, nothing but the balises to tell
        for s in (((0.02,) if scenario == "metro_demo" else ()) if quick else
                  (-0.02, -0.01, -0.005, 0.005, 0.01, 0.02)):
            faults.append((F.Fault("odometer_scale", s, 0.0), short if quick else full))
        # a first count that is not the distance run (not reset at the start: 0-1,000 m), and
        # an initial_position off the train's (0-50 m): the two readings of a count
        for s in (((30.0,) if scenario == "metro_demo" else ()) if quick else
                  (5.0, 26.0, 30.0, 39.0, 41.0, 100.0, 1000.0)):
            faults.append((F.Fault("first_count", s, 0.0), short))
        for s in (((20.0,) if scenario == "metro_demo" else ()) if quick else
                  (-50.0, -20.0, -5.0, 5.0, 20.0, 50.0)):
            faults.append((F.Fault("start_offset", s, 0.0), short))
        # a recorder that rounds the count to whole metres (decimetres) and the speed to whole
        # km/h: at 4 m/s and 10 Hz a whole-metre count stays put for two or three samples
        for s in (((1.0,) if scenario == "metro_demo" else ()) if quick else (0.1, 1.0)):
            faults.append((F.Fault("rounded", s, 0.0), short))
        fuzz_duration = short if quick or scenario != "metro_demo" else 3000.0
        fuzz_duration = min(fuzz_duration, long or math.inf)
        faults.append((F.Fault("fuzz", fuzz_rate or (0.5 if quick else 10.0), 0.0),
                       fuzz_duration))
        for fault, duration in faults:
            if only and fault.kind not in only:
                continue
            phase = next((k for k, v in ph.items() if v == fault.at), "")
            for seed in range(seeds):
                sim_duration = max(full, duration)
                for est in estimators:
                    if quick and scenario == "wen2017_subway" and est != "robust_filter":
                        continue
                    tasks.append(dict(scenario=scenario, seed=seed, fault=fault, phase=phase,
                                      estimator=est, duration=duration,
                                      sim_duration=sim_duration))
    return tasks


# -- zone controller -------------------------------------------------------------------------------

ZONE_FAULTS = ("none", "braking_rate_var -0.01", "braking_rate_var NaN", "stamp +1e6",
               "clock_reset -1000", "integrity ALARM", "integrity DEGRADED", "reports stop",
               "fuzz")


def zone_case(kind: str, seed: int = 0, duration: float = 60.0, onset: float = 20.0) -> dict:
    """One train at 10 m/s reporting at 10 Hz (position variance 1 m^2), authorities at 10 Hz on
    one clock; ``kind`` from ``onset`` on (one report, or every later report: clock reset,
    integrity, reports stop; fuzz: 5 bad reports per good one all along). Clear line (no danger
    point): with good reports the brake is never due."""
    p = ZoneParams()
    zc = ZoneController(p)
    names = {f.name for f in dc_fields(TrainReport)}
    rng = random.Random(seed)
    row = dict(kind=kind, crashes=0, bad_accepted=0, false_brakes=0, locked=0, brake_after=math.nan,
               error="")

    def report(t, **kw):
        base = dict(t_received=t, stamp=t, position=10.0 * t, velocity=10.0, var_position=1.0,
                    var_velocity=0.01, braking_rate=1.0, var_braking_rate=0.01,
                    measurement_used=True, pl_ahead=5.33, pl_behind=5.33)
        base.update(kw)
        # a TrainReport without an integrity field: the zone controller never sees it (the
        # node converts only the fields it knows), the report looks good
        try:
            return zc.report("t1", TrainReport(**{k: v for k, v in base.items() if k in names}))
        except Exception as exc:  # counted: the zone controller must refuse, never crash
            row["crashes"] += 1
            row["error"] = row["error"] or f"{type(exc).__name__}: {exc}"
            return "crash"

    bad_kinds = [dict(var_position=math.nan), dict(var_velocity=-1.0), dict(position=math.inf),
                 dict(var_braking_rate=-0.01), dict(var_braking_rate=math.nan),
                 dict(braking_rate=-math.inf), dict(stamp_shift=1e6), dict(stamp_shift=-1e6),
                 dict(stamp_shift=math.nan), dict(velocity=1e9), dict(velocity=-1e9),
                 dict(integrity=7), dict(pl_ahead=math.nan), dict(pl_behind=-1.0),
                 dict(pl_ahead=math.inf), dict(position=1e12), dict(position=-1e9),
                 dict(velocity=-149.0), dict(braking_rate=1e6)]
    # (a NaN braking rate is "not estimated": not bad)
    n = int(duration * 10)
    brakes = []
    for k in range(n + 1):
        t = 0.1 * k
        after = t >= onset - 1e-9
        first = after and t < onset + 0.05
        kw = {}
        if kind == "clock_reset -1000" and after:
            kw["stamp"] = t - 1000.0
        if kind == "integrity ALARM" and after:
            kw["integrity"] = 2
        if kind == "integrity DEGRADED" and after:  # bounded: 60 m either way, used as it is
            kw.update(integrity=1, pl_ahead=60.0, pl_behind=60.0)
        if not (kind == "reports stop" and after):
            if first and kind in ("braking_rate_var -0.01", "braking_rate_var NaN",
                                  "stamp +1e6"):
                bad = {"braking_rate_var -0.01": dict(var_braking_rate=-0.01),
                       "braking_rate_var NaN": dict(var_braking_rate=math.nan),
                       "stamp +1e6": dict(stamp=t + 1e6)}[kind]
                row["bad_accepted"] += report(t, **bad) == ""
            else:
                report(t, **kw)
            if kind == "fuzz":
                for _ in range(5):
                    b = dict(rng.choice(bad_kinds))
                    shift = b.pop("stamp_shift", None)
                    if shift is not None:
                        b["stamp"] = t + shift
                    row["bad_accepted"] += report(t, **b) == ""
        try:
            auth = zc.authorities(t, ["t1"])[0]
        except Exception as exc:
            row["crashes"] += 1
            row["error"] = row["error"] or f"{type(exc).__name__}: {exc}"
            brakes.append((t, True))
            continue
        brakes.append((t, bool(auth.emergency_brake)))
    expect_brake = kind in ("integrity ALARM", "reports stop")
    t0 = brakes[0][0]
    settled = [(t, b) for t, b in brakes if t >= t0 + p.stale_timeout]
    if expect_brake:
        row["false_brakes"] = sum(b for t, b in settled if t < onset)
        hit = [t for t, b in brakes if t >= onset and b]
        row["brake_after"] = hit[0] - onset if hit else math.inf
    else:
        row["false_brakes"] = sum(b for _, b in settled)
        recovered = onset + 5.0 if kind != "fuzz" else t0 + p.stale_timeout
        row["locked"] = int(any(b for t, b in brakes if t >= recovered and t >= duration - 5.0))
    return row


# -- report ----------------------------------------------------------------------------------------

def _fmt(v, nd=2):
    if isinstance(v, float):
        if math.isnan(v):
            return "-"
        if math.isinf(v):
            return "never"
        return f"{v:.{nd}f}" if abs(v) < 1e4 else f"{v:.3g}"
    return str(v)


def aggregate(rows: list[dict]) -> list[dict]:
    groups = defaultdict(list)
    for r in rows:
        f = r["fault"]
        groups[(r["scenario"], f.kind, f.label, f.at, r["phase"], r["estimator"])].append(r)
    out = []
    for (scn, kind, label, at, phase, est), rs in groups.items():
        ok = [r for r in rs if "outputs" in r]
        g = dict(scenario=scn, kind=kind, label=label, at=at, phase=phase, estimator=est,
                 size=rs[0]["fault"].size, runs=len(rs),
                 na=next((r["na"] for r in rs if "na" in r), ""),
                 exceptions=sum(r["exceptions"] for r in rs),
                 error=next((r["error"] for r in rs if r["error"]), ""))
        for k in ("wrong_side", "off_run", "hazards", "bad_cov", "corrupted", "outputs",
                  "misleading", "hazardous", "past_rear", "granted", "stop_short"):
            g[k] = sum(r[k] for r in ok)
        g["pl_median"] = max((r["pl_median"] for r in ok), default=math.nan)
        g["twice_given"] = sum(r.get("twice_given", 0) for r in ok)
        for k in ("tta", "silence", "max_err", "rms_err", "window_err", "max_ratio"):
            vals = [r[k] for r in ok if not math.isnan(r[k])]
            g[k] = max(vals) if vals else math.nan
        g["availability"] = min((r["availability"] for r in ok), default=math.nan)
        for k in ("p95_err", "pl_p50", "al99", "etcs_p50"):  # the worst run's
            vals = [r[k] for r in ok if not math.isnan(r.get(k, math.nan))]
            g[k] = max(vals) if vals else math.nan
        # tightness is each run's own ratio (one seed's level over the same seed's error: the
        # worst level over the worst error would pair a seed whose first balises leave the
        # scale unfixed with another whose balise readings lie 3 sd off), the loosest run's
        # and the median run's
        tight = sorted(r["pl_p50"] / r["p95_err"] for r in ok
                       if r.get("p95_err", 0.0) > 0 and math.isfinite(r.get("pl_p50", math.nan)))
        g["tight_max"] = tight[-1] if tight else math.nan
        g["tight_med"] = tight[len(tight) // 2] if tight else math.nan
        out.append(g)
    return out


def print_table(groups: list[dict]) -> None:
    print("| scenario | fault | at | estimator | misleading | hazardous | median PL m | "
          "wrong-side | off-run | max err/sigma | "
          "time to alarm s | availability (PL <= AL) % | longest silence s | max err m | "
          "RMS err m | max err, onset to the fault's end + 10 s, m | non-PD cov | exceptions |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for g in groups:
        at = "-" if g["kind"] in ("none", "drift", "fuzz", "latency", "queue", "first_count",
                                      "start_offset", "odometer_scale", "rounded", "wander") else \
            f"{g['at']:g} s {g['phase']}".strip()
        if g["na"]:
            print(f"| {g['scenario']} | {g['label']} | {at} | {g['estimator']} | n/a: "
                  f"{g['na'][:60]} ||||||||||||||")
            continue
        print(f"| {g['scenario']} | {g['label']} | {at} | {g['estimator']} | "
              f"{g['misleading']} | {g['hazardous']} | {_fmt(g['pl_median'], 1)} | "
              f"{g['wrong_side']} | "
              f"{g['off_run']} | {_fmt(g['max_ratio'], 0)} | {_fmt(g['tta'])} | "
              f"{_fmt(100 * g['availability'], 1)} | {_fmt(g['silence'], 1)} | "
              f"{_fmt(g['max_err'])} | {_fmt(g['rms_err'])} | {_fmt(g['window_err'])} | "
              f"{g['bad_cov']} | {g['exceptions']} |")


def print_tightness(groups: list[dict]) -> None:
    """The clean runs' levels against their errors and ETCS's interval (faults.score)."""
    rows = [g for g in groups if g["kind"] == "none" and not g["na"]]
    if not rows:
        return
    print("\nTightness on clean runs, after the first balise (each column the worst seed's; "
          "the ratio each seed's own, the loosest and the median seed's):")
    print("| scenario | estimator | seeds | p95 abs err m | median PL m | PL / p95 err, loosest "
          "| PL / p95 err, median | median ETCS interval m | alert limit for 99 % OK m |")
    print("|---|---|---|---|---|---|---|---|---|")
    for g in rows:
        print(f"| {g['scenario']} | {g['estimator']} | {g['runs']} | {_fmt(g['p95_err'])} | "
              f"{_fmt(g['pl_p50'], 1)} | {_fmt(g['tight_max'], 1)} | "
              f"{_fmt(g['tight_med'], 1)} | {_fmt(g['etcs_p50'], 1)} | {_fmt(g['al99'], 1)} |")


def targets(groups: list[dict], zone: list[dict]) -> bool:
    real = [g for g in groups if not g["na"]]
    ws = sum(g["wrong_side"] for g in real)
    off = sum(g["off_run"] for g in real)
    lines = []
    mis = sum(g["misleading"] for g in real)
    haz_ok = sum(g["hazardous"] for g in real)
    lines.append((mis == 0, f"zero misleading estimates (|error| beyond the protection level, "
                            f"not ALARM): {mis}; hazardous (OK, |error| > the alert limit): "
                            f"{haz_ok}"))
    twice = sum(g["twice_given"] for g in real)
    lines.append((ws + off == 0, f"zero wrong-side estimates: {ws} wrong-side + {off} off-run "
                                 f"in {sum(g['outputs'] for g in real)} estimates ({twice} "
                                 f"judged by the other meaning of a stamp the clock gave "
                                 f"twice within 1 s)"))
    haz = [g for g in real if g["hazards"]]
    never = sum(1 for g in haz if math.isinf(g["tta"]))
    finite = [g["tta"] for g in haz if math.isfinite(g["tta"])]
    lines.append((all(g["tta"] <= 1.0 for g in haz),
                  f"time to alarm <= 1 s: the error exceeded the bound in {len(haz)} rows; "
                  f"{sum(1 for g in haz if g['tta'] > 1.0)} of them alarmed later than 1 s, "
                  f"{never} never; slowest alarm {_fmt(max(finite, default=math.nan))} s"))
    bad = sum(g["bad_cov"] for g in real)
    lines.append((bad == 0, f"no negative or non-PD covariance: {bad}"))
    exc = sum(g["exceptions"] for g in real)
    lines.append((exc == 0, f"no exception: {exc}"))
    av = [g for g in real if g["kind"] in ("drift", "latency", "wander")
          or (g["kind"] == "step" and abs(g["size"]) <= 10.0)]
    worst = min(av, key=lambda g: g["availability"], default=None)
    lines.append((bool(av) and worst["availability"] >= 0.99,
                  "availability >= 99 % through drift, steps <= 10 s, latency tails and wanders: "
                  + (f"lowest {100 * worst['availability']:.1f} % ({worst['scenario']}, "
                     f"{worst['label']}, {worst['estimator']})" if worst else "no rows")))
    clean = [g for g in real if g["kind"] == "none" and g["tight_max"] > 0]
    loose = max(clean, key=lambda g: g["tight_max"], default=None)
    lines.append((bool(clean) and loose["tight_max"] <= 5.0,
                  "tightness: median protection level <= 5 x the p95 |error| on clean runs: "
                  + (f"loosest {loose['tight_max']:.1f} x ({loose['scenario']}, "
                     f"{loose['estimator']}, a run's own level over its error)"
                     if loose else "no rows")))
    out60 = [g for g in real if g["scenario"] == "metro_demo" and g["kind"] == "outage"
             and g["size"] == 60.0]
    w60 = max(out60, key=lambda g: g["window_err"], default=None)
    lines.append((bool(out60) and w60["window_err"] <= 10.0,
                  "60 s outage on metro_demo: error <= 10 m: "
                  + (f"largest {w60['window_err']:.1f} m ({w60['phase']}, {w60['estimator']})"
                     if w60 else "no rows")))
    if zone:
        stale = ZoneParams().stale_timeout
        crash = sum(z["crashes"] for z in zone)
        locked = sum(z["locked"] for z in zone)
        lines.append((crash == 0, f"zone controller never crashes: {crash} crashes"))
        lines.append((locked == 0, f"zone controller never locks: {locked} lock-ups"))
        alarm = next(z for z in zone if z["kind"] == "integrity ALARM")
        lines.append((alarm["brake_after"] <= stale,
                      f"zone controller brakes on ALARM within its staleness time ({stale:g} s): "
                      f"{_fmt(alarm['brake_after'])} s"))
    past = sum(g["past_rear"] for g in real)
    lines.append((past == 0, f"zone controller in the loop (each run's estimates as a leader's "
                             f"reports, margin 0): no authority past the leader's true rear: "
                             f"{past} of {sum(g['granted'] for g in real)} granted"))
    short = sum(g["stop_short"] for g in real)
    lines.append((short == 0, f"zone controller in the loop: no worst-case stopping point short "
                              f"of the true one (position level, speed + K sigma, nominal "
                              f"braking): {short}"))
    ok = True
    print()
    for passed, text in lines:
        ok &= passed
        print(f"{'PASS' if passed else 'FAIL'}  {text}")
    return ok


PRIORS = ("balise_map_prior", "start_fault_prior")  # IntegrityParams' stated priors


def add_prior_args(ap) -> None:
    """``--balise-map-prior`` and ``--start-fault-prior``: the estimators' stated priors of a
    map fault and a start fault (IntegrityParams; protection.py, rare faults)."""
    ap.add_argument("--balise-map-prior", type=float, default=None,
                    help="the estimators' balise_map_prior: the stated prior probability that "
                         "a balise's surveyed position is wrong (default: the node's, 1 = not "
                         "stated)")
    ap.add_argument("--start-fault-prior", type=float, default=None,
                    help="the estimators' start_fault_prior: the stated prior probability "
                         "that the start is wrong (default: the node's, 1 = not stated)")


def stated_priors(ap, args) -> dict:
    """{IntegrityParams field: value} of the priors given on the command line."""
    priors = {k: getattr(args, k) for k in PRIORS if getattr(args, k) is not None}
    for k, v in priors.items():
        if not 0.0 <= v <= 1.0:
            ap.error(f"--{k.replace('_', '-')} must be in [0, 1]")
    return priors


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="robust_filter and kf, one or two sizes per fault class, one seed")
    ap.add_argument("--seeds", type=int, default=None, help="seeds per case (quick 1, full 2)")
    ap.add_argument("--estimators", nargs="*", default=None)
    ap.add_argument("--only", nargs="*", default=None, help=f"fault kinds ({', '.join(F.KINDS)})")
    ap.add_argument("--jobs", type=int, default=2, help="worker processes")
    ap.add_argument("--scenarios", nargs="*", default=None,
                    help="only these scenarios (default: every one here, the real lines "
                         "where their files are)")
    ap.add_argument("--no-zone", action="store_true")
    ap.add_argument("--no-distance", action="store_true",
                    help="the estimators with use_distance: false (the odometer's speed and "
                         "the balises, its distance unread)")
    ap.add_argument("--no-counter", action="store_true",
                    help="every odometer and balise seq set to 0 (a producer without a sample "
                         "counter: the estimators judge the readings by their stamps)")
    ap.add_argument("--count-noise", type=float, default=0.0, metavar="M",
                    help="white Gaussian noise (standard deviation, m) on every odometer "
                         "distance, unstated in the messages (a producer whose count is read "
                         "with noise; default 0)")
    ap.add_argument("--phases", nargs="*", default=None,
                    help="reduced full campaign: stamp, step and command faults only in these "
                         "phases (accelerating, cruising, braking)")
    ap.add_argument("--long", type=float, default=None,
                    help="reduced full campaign: drift and fuzz runs at most this long (s)")
    ap.add_argument("--fuzz-rate", type=float, default=None,
                    help="corrupted messages per clean one (quick 0.5, full 10)")
    ap.add_argument("--stanford", default="benchmarks/out/stanford",
                    help="folder for one Stanford diagram per estimator (|error| against the "
                         "protection level, every run pooled): stanford_ESTIMATOR.png")
    add_prior_args(ap)
    ap.add_argument("--balise-latency-std", type=float, default=None, metavar="S",
                    help="the estimators' balise_latency_std (s): how late the balise reader "
                         "is stated to stamp (default: the node's, 0.1 s)")
    ap.add_argument("--balise-groups", type=float, default=0.0, metavar="D",
                    help="a second balise D m after each of the line's, in the map and on the "
                         "track (groups of two, as ETCS lays them; default 0: the line's own)")
    ap.add_argument("--odometer-rate", type=float, default=None, metavar="HZ",
                    help="every scenario's odometer (and command, truth, radio cycle) at HZ "
                         "instead of its own rate (default: the scenario's, 1-10 Hz); the "
                         "estimators told the same rate, as their node's odometer_rate")
    args = ap.parse_args(argv)
    priors = stated_priors(ap, args)
    if args.odometer_rate is not None and not 0.1 <= args.odometer_rate <= 200:
        ap.error("--odometer-rate must be in [0.1, 200] Hz")
    if args.balise_latency_std is not None and not args.balise_latency_std >= 0:
        ap.error("--balise-latency-std must be >= 0")
    if not 0 <= args.balise_groups < 1e3:
        ap.error("--balise-groups must be in [0, 1000) m")
    if not 0 <= args.count_noise < 1e3:
        ap.error("--count-noise must be in [0, 1000) m")
    seeds = args.seeds or (1 if args.quick else 2)
    estimators = args.estimators or (QUICK_ESTIMATORS if args.quick else ESTIMATORS)
    scenarios = scenarios_here()
    if args.scenarios:
        unknown = sorted(set(args.scenarios) - set(scenarios))
        if unknown:
            print(f"bench_integrity: --scenarios: {', '.join(unknown)} not available here "
                  f"(available: {', '.join(scenarios)})", file=sys.stderr)
            return 2
        scenarios = tuple(args.scenarios)
    tasks = plan(args.quick, seeds, estimators, args.only, args.phases, args.long,
                 args.fuzz_rate, scenarios)
    config = {"use_distance": False} if args.no_distance else {}
    if args.balise_latency_std is not None:
        config["balise_latency_std"] = args.balise_latency_std
    for t in tasks:
        t["config"] = config
        t["balise_groups"] = args.balise_groups
        t["no_counter"] = args.no_counter
        t["count_noise"] = args.count_noise
        t["odometer_rate"] = args.odometer_rate
        if priors:
            t["integrity"] = IntegrityParams(**priors)
    # the longest first: the pool finishes together
    tasks.sort(key=lambda t: -t["duration"] * (3 if t["fault"].kind == "fuzz" else 1))
    rows = []
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        futs = [pool.submit(run_task, t) for t in tasks]
        for fut in track(as_completed(futs), "fault runs", total=len(futs)):
            rows.append(fut.result())
    order = {k: i for i, k in enumerate(F.KINDS)}
    rows.sort(key=lambda r: (scenarios.index(r["scenario"]), order[r["fault"].kind],
                             r["fault"].at, r["fault"].size, r["fault"].count,
                             ESTIMATORS.index(r["estimator"]), r["seed"]))
    groups = aggregate(rows)
    mode = "quick" if args.quick else "full"
    if not args.quick and (args.phases or args.long or args.fuzz_rate):
        mode = (f"reduced full: phases {', '.join(args.phases or ['all'])}, drift and fuzz "
                f"<= {args.long or 'full'} s, fuzz {args.fuzz_rate or 10.0:g} per clean message")
    stated = "".join(f", {k} {v:g}" for k, v in priors.items())
    if args.balise_latency_std is not None:
        stated += f", balise_latency_std {args.balise_latency_std:g} s"
    if args.balise_groups:
        stated += f", balises in groups of two {args.balise_groups:g} m apart"
    if args.odometer_rate:
        stated += f", every odometer at {args.odometer_rate:g} Hz"
    print(f"Integrity campaign ({mode}): {len(tasks)} runs, {seeds} seed(s), estimators "
          f"{', '.join(estimators)}"
          f"{' with use_distance: false' if args.no_distance else ''}"
          f"{', every seq 0 (no sample counter)' if args.no_counter else ''}"
          f"{f', the count {args.count_noise:g} m noisy' if args.count_noise else ''}"
          f"{stated}; "
          f"node defaults (NodeConfig: control_clock "
          f"{NodeConfig().control_clock!r}, max_future {NodeConfig().max_future:g} s), "
          f"arrival = stamp + {F.LATENCY:g} s\n")
    print_table(groups)
    print_tightness(groups)
    corrupted = defaultdict(int)
    for r in rows:
        if r["fault"].kind == "fuzz":
            corrupted[r["estimator"]] += r.get("corrupted", 0)
    if corrupted:
        print("\ncorrupted messages per estimator (fuzz): "
              + ", ".join(f"{k} {v}" for k, v in corrupted.items()))
    for r in rows:
        if r["error"]:
            print(f"exception: {r['scenario']} {r['fault'].label} {r['estimator']} seed "
                  f"{r['seed']}: {r['error']}", file=sys.stderr)
    zone = []
    if not args.no_zone and not args.only:
        zone = [zone_case(k) for k in ZONE_FAULTS]
        print("\n| zone controller fault | crashes | bad reports accepted | false brakes "
              "(authorities at 10 Hz) | locked | time to brake s |")
        print("|---|---|---|---|---|---|")
        for z in zone:
            print(f"| {z['kind']} | {z['crashes']} | {z['bad_accepted']} | {z['false_brakes']} | "
                  f"{'yes' if z['locked'] else 'no'} | {_fmt(z['brake_after'])} |")
        for z in zone:
            if z["error"]:
                print(f"zone {z['kind']}: {z['error']}", file=sys.stderr)
    if args.stanford:
        out = Path(args.stanford)
        out.mkdir(parents=True, exist_ok=True)
        print()
        for est in estimators:
            hist = sum((r["stanford"] for r in rows if r["estimator"] == est and
                        "stanford" in r), start=np.zeros((60, 60), np.int64))
            path = out / f"stanford_{est}.png"
            reg = F.plot_stanford(hist, 10.0, f"{est}: {mode} campaign", path)
            print(f"Stanford diagram {path}: " + ", ".join(f"{k} {v}" for k, v in reg.items()))
    ok = targets(groups, zone)
    print("RESULT:", "PASS" if ok else "FAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
