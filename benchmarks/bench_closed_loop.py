#!/usr/bin/env python3
"""Braking-rate estimation in and out of the loop on ``metro_drift``.

    PYTHONPATH=ros_ws/src/train_sim:ros_ws/src/train_estimation \\
        python3 benchmarks/bench_closed_loop.py [--seeds 20] [--quick]

Scenario ``metro_drift``: metro_demo (A -> B -> C -> D, 10 Hz odometer, Bernoulli link with
P(received) = 0.875) with the true braking rate drifting linearly from 1.0 at t = 0 to 0.7 at
t = 600 s (Zheng eq. (23) shape). The estimators get only the believed line/train and the received
``control``, ``odometer`` and ``balise`` messages, through the same ``BrakingAdapter`` and
``EstimatorRunner`` as the ``gsma_estimator`` node (default ``BrakingConfig``; the particle seed is
the run's seed).

1. Open loop. The ATO plans with the nominal f = 1 (the world is exactly ``simulate``); each
   algorithm replays the received messages. Error e(t) = f_hat(t) - f(t) at every output time
   (10 Hz; no clock drift in this scenario, so stamps are true times). Columns: MAE over the whole
   run; MAE after the first braking phase (from the stop at B on: the prior before it is the
   uniform initial particle set, which says nothing); MAE while braking (a_Tar < -0.1 m/s^2 and
   v > 0.3 m/s, the estimator's own informative gate); |e| at the end of the run; and the share of
   output times after B where |e| <= 2 sigma (sigma: the reported posterior std of f), i.e. whether
   the std that the ATO rule below trusts is calibrated.

2. Closed loop. The world is stepped one odometer period (0.1 s) at a time. After each chunk
   ending at t the received messages are pushed into the runner, the runner is advanced to t, and
   the ATO is given a braking-rate belief that it uses from its next cycle (t + 0.1 s) on: only
   information available at t enters. ATO rules (``--rules``):

   * ``gate``  : belief = f_hat if f_hat is finite and > 0 and its posterior std < ``--std-max``
     (default 0.1), else the nominal 1.0.
   * ``hold``  : as ``gate``, but when the std is not below the threshold the ATO keeps the last
     belief it accepted (nominal 1.0 until the first accepted estimate).

   Compared with the baseline (belief fixed at nominal 1.0) and the oracle (belief = the true
   f(t) at each chunk end). Stopping error = stop position - stopping point (m, > 0 overshoot) at
   B, C, D, as recorded by the simulator's ATO. The ATO is perfectly localised and the sensors do
   not act on the motion, so the baseline and the oracle are deterministic: their interval is a
   point. Extra columns: |braking_rate_belief - f| when braking for each station starts (the
   moment that
   decides the overshoot: once the service-brake limit is reached the belief cannot help any
   more), and the arrival time at D (a too pessimistic belief brakes early and creeps).

Intervals: mean [2.5 %, 97.5 %] percentiles over seeds (spread of one run's result, as in
``bench_braking.py``; not a confidence interval of the mean). Outputs: the markdown tables on
stdout and in ``benchmarks/out/bench_closed_loop.md``; ``benchmarks/out/closed_loop_f.png`` (f_hat
with +-2 sigma per algorithm for one seed vs the truth, and the mean |e| over seeds vs time).
"""

from __future__ import annotations

import argparse
import math
import shlex
import sys
import time
from pathlib import Path

import numpy as np
from train_core.progress import track  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
for sub in ("ros_ws/src/train_sim", "ros_ws/src/train_estimation"):
    sys.path.insert(0, str(ROOT / sub))

from train_estimation.core.online.estimators import (  # noqa: E402
    ALGORITHMS,
    BrakingAdapter,
    BrakingConfig,
    StartState,
)
from train_estimation.core.online.replay import INPUT_TOPICS  # noqa: E402
from train_estimation.core.online.runner import EstimatorRunner  # noqa: E402
from train_sim.scenario import load_scenario  # noqa: E402
from train_sim.world import World  # noqa: E402

STATIONS = ("B", "C", "D")
RULES = ("gate", "hold")
NOMINAL_F = 1.0


# ----------------------------------------------------------------------------------------------
# helpers

def make_runner(sc, algorithm: str, seed: int) -> EstimatorRunner:
    adapter = BrakingAdapter(sc.train, sc.line, StartState(sc.start_position),
                             BrakingConfig(algorithm=algorithm, seed=seed))
    return EstimatorRunner(adapter, 1.0 / sc.odometer_rate)


def braking_mask(res, standstill_speed: float, min_brake: float) -> tuple[np.ndarray, np.ndarray]:
    """(t, mask) on the sample grid: a braking command on a moving train (the informative gate
    of ``BrakingModel.gate``, evaluated on the truth)."""
    t = res.truth["t"]
    mask = (res.control["target_acceleration"] < -min_brake) & \
        (res.truth["velocity"] > standstill_speed)
    return t, mask


def fmt(a, digits: int = 3) -> str:
    a = np.asarray(a, dtype=float)
    a = a[np.isfinite(a)]
    if a.size == 0:
        return "n/a"
    m, lo, hi = np.mean(a), np.percentile(a, 2.5), np.percentile(a, 97.5)
    return f"{m:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


# ----------------------------------------------------------------------------------------------
# 1. open loop

def open_loop(sc, algorithms, seeds, plot_seed):
    """Per algorithm: dict of per-seed metric arrays; plus the traces to plot."""
    cfg = BrakingConfig()
    metrics = {a: {k: [] for k in ("mae", "mae_after", "mae_brake", "final", "cover", "nees",
                                   "step_ms")}
               for a in algorithms}
    abs_err = {a: [] for a in algorithms}  # per seed, on the common output grid
    trace = {}
    for seed in track(seeds, f"closed loop {sc.name}"):
        world = World(sc, seed)
        events = world.advance(sc.duration)
        res = world.result()
        t_b = res.stops[0]["t"] if res.stops else math.inf  # end of the first braking phase
        ts_s, brk = braking_mask(res, cfg.standstill_speed, cfg.min_brake)
        for alg in algorithms:
            runner = make_runner(sc, alg, seed)
            for topic, stamp, fields in events:
                if topic in INPUT_TOPICS:
                    runner.push(topic, stamp, fields)
            t_run = time.perf_counter()
            outs = runner.advance_to(sc.duration)
            t_run = time.perf_counter() - t_run
            assert not runner.rejected, f"{alg} seed {seed}: rejected {dict(runner.rejected)}"
            t = np.array([o.stamp for o in outs])
            f_hat = np.array([o.braking_rate for o in outs])
            sd = np.sqrt(np.array([o.covariance[15] for o in outs]))
            f_true = np.array([world.braking_rate(x) for x in t])
            e = f_hat - f_true
            after = t >= t_b
            on_brake = np.interp(t, ts_s, brk.astype(float)) > 0.5
            m = metrics[alg]
            m["mae"].append(np.mean(np.abs(e)))
            m["mae_after"].append(np.mean(np.abs(e[after])) if after.any() else math.nan)
            m["mae_brake"].append(np.mean(np.abs(e[on_brake])) if on_brake.any() else math.nan)
            m["final"].append(abs(e[-1]))
            m["cover"].append(np.mean(np.abs(e[after]) <= 2 * sd[after]) if after.any()
                              else math.nan)
            with np.errstate(divide="ignore", invalid="ignore"):
                m["nees"].append(np.mean(e[after] ** 2 / sd[after] ** 2) if after.any()
                                 else math.nan)
            m["step_ms"].append(1e3 * t_run / max(len(outs), 1))
            abs_err[alg].append((t, np.abs(e)))
            if seed == plot_seed:
                trace[alg] = (t, f_hat, sd, f_true, ts_s, brk)
    return metrics, abs_err, trace


def open_loop_table(metrics, n_seeds) -> str:
    lines = [f"### Open loop (ATO plans with nominal f = 1): braking-rate error, "
             f"mean [2.5 %, 97.5 %] over {n_seeds} seeds",
             "",
             "| algorithm | MAE whole run | MAE after stop at B | MAE while braking | "
             "final abs error (t = 600 s) | share abs error <= 2 sigma after B | NEES after B | "
             "MAE after B / kf | time per output (ms) |",
             "|---|---|---|---|---|---|---|---|---|"]
    ref = np.mean(metrics["kf"]["mae_after"]) if "kf" in metrics else math.nan
    for alg, m in metrics.items():
        lines.append(f"| {alg} | {fmt(m['mae'])} | {fmt(m['mae_after'])} | "
                     f"{fmt(m['mae_brake'])} | {fmt(m['final'])} | {fmt(m['cover'], 2)} | "
                     f"{fmt(m['nees'], 2)} | {np.mean(m['mae_after']) / ref:.2f} | "
                     f"{fmt(m['step_ms'], 3)} |")
    return "\n".join(lines)


def plot(trace, abs_err, path: Path, plot_seed: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    algs = list(trace)
    fig, axes = plt.subplots(len(algs) + 1, 1, figsize=(10, 2.3 * (len(algs) + 1)), sharex=True)
    for ax, alg in zip(axes, algs):
        t, f_hat, sd, f_true, ts_s, brk = trace[alg]
        ax.fill_between(ts_s, 0, 1.1, where=brk, color="0.9", step="mid", label="braking")
        ax.fill_between(t, f_hat - 2 * sd, f_hat + 2 * sd, color="C0", alpha=0.25,
                        label="+-2 sigma")
        ax.plot(t, f_hat, color="C0", lw=1.2, label=f"{alg} f_hat")
        ax.plot(t, f_true, color="k", lw=1.0, ls="--", label="true f")
        ax.set_ylim(0.0, 1.1)
        ax.set_ylabel("f")
        ax.legend(loc="lower left", fontsize=7, ncol=4)
    ax = axes[-1]
    for i, alg in enumerate(algs):
        t = abs_err[alg][0][0]
        e = np.mean([np.interp(t, tt, ee) for tt, ee in abs_err[alg]], axis=0)
        ax.plot(t, e, color=f"C{i}", lw=1.0, label=alg)
    ax.set_ylabel("mean |f_hat - f|")
    ax.set_xlabel("t (s)")
    ax.legend(fontsize=7, ncol=4)
    axes[0].set_title(f"metro_drift, open loop: f_hat per algorithm (seed {plot_seed}) and "
                      f"mean abs error over {len(abs_err[algs[0]])} seeds")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ----------------------------------------------------------------------------------------------
# 2. closed loop

def closed_loop(sc, source: str, rule: str, seed: int, std_max: float) -> dict:
    """One run; ``source`` in {'nominal', 'oracle', *ALGORITHMS}."""
    world = World(sc, seed)
    runner = make_runner(sc, source, seed) if source in ALGORITHMS else None
    rate = sc.odometer_rate
    n = int(round(sc.duration * rate))
    belief = NOMINAL_F  # what the ATO currently plans with (the scenario's nominal belief)
    was_braking = False
    onset = {}  # station -> |belief - f| when braking for it started
    cal = []  # (t, f_hat, var, f_true) of every output: calibration in the loop
    for k in range(1, n + 1):
        t = k / rate  # the world's own sample grid: chunks end on sample times
        msgs = world.advance(t)
        drv = world.driver
        if drv.braking and not was_braking and drv.queue:
            st = drv.queue[0].station
            onset.setdefault(st, abs(drv.braking_rate_belief - world.braking_rate(t)))
        was_braking = drv.braking
        if source == "oracle":
            belief = world.braking_rate(t)
        elif runner is not None:
            for topic, stamp, fields in msgs:
                if topic in INPUT_TOPICS:
                    runner.push(topic, stamp, fields)
            outs = runner.advance_to(t)
            cal += [(o.stamp, o.braking_rate, o.covariance[15], world.braking_rate(o.stamp))
                    for o in outs]
            if outs:
                o = outs[-1]
                var = o.covariance[15]
                ok = (math.isfinite(o.braking_rate) and o.braking_rate > 0.0
                      and math.isfinite(var) and 0.0 <= var < std_max ** 2)
                if ok:
                    belief = o.braking_rate
                elif rule == "gate":
                    belief = NOMINAL_F
                # rule "hold": keep the last accepted belief
        if source != "nominal":
            world.set_braking_rate_belief(belief)  # used by the ATO from its next cycle on
    res = world.result()
    errs = {s["station"]: s["stopping_error"] for s in res.stops}
    t_d = next((s["t"] for s in res.stops if s["station"] == STATIONS[-1]), math.nan)
    rejected = dict(runner.rejected) if runner is not None else {}
    cover = nees = math.nan
    if cal and res.stops:
        c = np.array(cal)
        c = c[c[:, 0] >= res.stops[0]["t"]]  # after the first braking phase, as in open loop
        if c.size:
            e2 = (c[:, 1] - c[:, 3]) ** 2
            cover = float(np.mean(e2 <= 4.0 * c[:, 2]))
            with np.errstate(divide="ignore", invalid="ignore"):
                nees = float(np.mean(e2 / c[:, 2]))
    return {"err": errs, "t_D": t_d, "onset": onset, "rejected": rejected,
            "emergency": res.emergency_brakes, "cover": cover, "nees": nees}


def closed_loop_table(rows, n_seeds, std_max) -> str:
    lines = [f"### Closed loop: |stopping error| (m), mean [2.5 %, 97.5 %] over {n_seeds} seeds "
             f"(ATO takes f_hat when its std < {std_max})",
             "",
             "| ATO belief | rule | B | C | D | all stations | max abs error | "
             "abs(braking_rate_belief - f) at brake onset | arrival at D (s) | "
             "2-sigma coverage of f "
             "after B | NEES after B |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for (source, rule), runs in rows.items():
        per = {s: np.array([abs(r["err"].get(s, math.nan)) for r in runs]) for s in STATIONS}
        allst = np.nanmean(np.column_stack([per[s] for s in STATIONS]), axis=1)
        mx = np.nanmax(np.column_stack([per[s] for s in STATIONS]), axis=1)
        ons = np.array([np.mean([r["onset"].get(s, math.nan) for s in STATIONS]) for r in runs])
        t_d = np.array([r["t_D"] for r in runs])
        lines.append(f"| {source} | {rule} | {fmt(per['B'], 2)} | {fmt(per['C'], 2)} | "
                     f"{fmt(per['D'], 2)} | {fmt(allst, 2)} | {fmt(mx, 2)} | {fmt(ons, 3)} | "
                     f"{fmt(t_d, 1)} | {fmt([r['cover'] for r in runs], 2)} | "
                     f"{fmt([r['nees'] for r in runs], 2)} |")
    return "\n".join(lines)


def signed_table(rows) -> str:
    lines = ["### Closed loop: signed stopping error (m, > 0 = overshoot), mean over seeds",
             "",
             "| ATO belief | rule | B | C | D |",
             "|---|---|---|---|---|"]
    for (source, rule), runs in rows.items():
        cells = [np.nanmean([r["err"].get(s, math.nan) for r in runs]) for s in STATIONS]
        lines.append(f"| {source} | {rule} | " + " | ".join(f"{c:+.2f}" for c in cells) + " |")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------
# 3. step fault

STEP_T, STEP_F = 200.0, 0.6


def step_fault_section(sc, algorithms, seeds, std_max) -> str:
    """The scenario with its braking-rate effect replaced by a step 1.0 -> 0.6 at t = 200 s
    (after the stop at B, before braking for C: the step can only be seen once the train brakes
    again). Open loop: time to detect (the first output after the step with f_hat below the
    midpoint 0.8), MAE and 2-sigma coverage after the step; closed loop ("hold" rule): parking."""
    import dataclasses

    from train_core.effects import BrakingRateEffect

    eff = BrakingRateEffect(1.0, STEP_F, mode="step", t_step=STEP_T)
    scf = dataclasses.replace(sc, effects=dataclasses.replace(sc.effects, braking_rate=eff))
    mid = 0.5 * (1.0 + STEP_F)
    rows = []
    for alg in algorithms:
        ttd, mae, cov, park = [], [], [], []
        for seed in track(seeds, f"closed loop {alg}"):
            world = World(scf, seed)
            events = world.advance(scf.duration)
            runner = make_runner(scf, alg, seed)
            for topic, stamp, fields in events:
                if topic in INPUT_TOPICS:
                    runner.push(topic, stamp, fields)
            outs = runner.advance_to(scf.duration)
            t = np.array([o.stamp for o in outs])
            f_hat = np.array([o.braking_rate for o in outs])
            sd = np.sqrt(np.array([o.covariance[15] for o in outs]))
            f_true = np.array([world.braking_rate(x) for x in t])
            after = t >= STEP_T
            hit = np.flatnonzero(after & (f_hat <= mid))
            ttd.append(t[hit[0]] - STEP_T if hit.size else math.nan)
            e = np.abs(f_hat - f_true)[after]
            mae.append(np.mean(e))
            cov.append(np.mean(e <= 2 * sd[after]))
            r = closed_loop(scf, alg, "hold", seed, std_max)
            park.append([abs(r["err"].get(st, math.nan)) for st in STATIONS])
        park = np.array(park)
        rows.append((alg, ttd, mae, cov, park))
    ref = np.mean(dict((a, m) for a, _, m, _, _ in rows).get("kf", [math.nan]))
    base = [closed_loop(scf, "nominal", "-", s, std_max) for s in seeds]
    orc = [closed_loop(scf, "oracle", "-", s, std_max) for s in seeds]
    lines = [f"### Step fault: f = 1.0 -> {STEP_F} at t = {STEP_T:.0f} s (after B; seen only "
             f"when braking for C), mean [2.5 %, 97.5 %] over {len(seeds)} seeds",
             "",
             "| algorithm | time to detect (s, f_hat < 0.8) | MAE after the step | / kf | "
             "2-sigma coverage after | abs stopping error C (m, hold) | D (m, hold) |",
             "|---|---|---|---|---|---|---|"]
    for alg, ttd, mae, cov, park in rows:
        lines.append(f"| {alg} | {fmt(ttd, 1)} | {fmt(mae)} | {np.mean(mae) / ref:.2f} | "
                     f"{fmt(cov, 2)} | {fmt(park[:, 1], 2)} | {fmt(park[:, 2], 2)} |")
    for name, runs in (("nominal f = 1", base), ("oracle (true f)", orc)):
        c = [abs(r["err"].get("C", math.nan)) for r in runs]
        d = [abs(r["err"].get("D", math.nan)) for r in runs]
        lines.append(f"| {name} | | | | | {fmt(c, 2)} | {fmt(d, 2)} |")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------

def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=20, help="seeds 0..N-1 (default 20)")
    ap.add_argument("--quick", action="store_true", help="3 seeds")
    ap.add_argument("--scenario", default="metro_drift")
    ap.add_argument("--algorithms", default=",".join(ALGORITHMS))
    ap.add_argument("--rules", default=",".join(RULES), help="ATO rules: gate, hold")
    ap.add_argument("--std-max", type=float, default=0.1,
                    help="the ATO takes f_hat only if its posterior std is below this")
    ap.add_argument("--plot-seed", type=int, default=0)
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "out"))
    ap.add_argument("--skip-open-loop", action="store_true")
    ap.add_argument("--skip-closed-loop", action="store_true")
    ap.add_argument("--step-fault", action="store_true",
                    help="also: f steps 1.0 -> 0.6 at t = 200 s (brake cylinder failure)")
    args = ap.parse_args(argv)
    n_seeds = 3 if args.quick else args.seeds
    seeds = list(range(n_seeds))
    algorithms = [a for a in args.algorithms.split(",") if a]
    rules = [r for r in args.rules.split(",") if r]
    for a in algorithms:
        if a not in ALGORITHMS:
            ap.error(f"unknown algorithm {a!r}")
    for r in rules:
        if r not in RULES:
            ap.error(f"unknown rule {r!r}")
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    sc = load_scenario(args.scenario)
    cmd = ("PYTHONPATH=ros_ws/src/train_sim:ros_ws/src/train_estimation python3 "
           + " ".join(shlex.quote(x) for x in ["benchmarks/bench_closed_loop.py",
                                                *sys.argv[1:]]))
    br = sc.effects.braking_rate
    head = [f"# Closed-loop braking-rate benchmark ({args.scenario})", "",
            f"Command: `{cmd}`", "",
            f"seeds {seeds[0]}..{seeds[-1]}; true f: "
            + (f"{br.mode} {br.f_start} -> {br.f_end} over t = {br.t_start}..{br.t_end} s"
               if br else "constant")
            + f"; duration {sc.duration} s; estimators: default BrakingConfig, particle seed = "
            f"run seed. ATO rules: gate = take f_hat iff std < {args.std_max}, else nominal 1.0; "
            f"hold = take f_hat iff std < {args.std_max}, else keep the last accepted belief. "
            "Intervals: 2.5 / 97.5 percentiles over seeds."]
    print("\n".join(head), flush=True)
    sections = ["\n".join(head)]
    t0 = time.perf_counter()
    if not args.skip_open_loop:
        metrics, abs_err, trace = open_loop(sc, algorithms, seeds, args.plot_seed)
        tab = open_loop_table(metrics, n_seeds)
        print("\n" + tab, flush=True)
        sections.append(tab)
        if trace:
            png = out_dir / "closed_loop_f.png"
            plot(trace, abs_err, png, args.plot_seed)
            print(f"\nplot: {png} (open loop {time.perf_counter() - t0:.0f} s)", flush=True)
    if not args.skip_closed_loop:
        t1 = time.perf_counter()
        rows = {("nominal f = 1 (baseline)", "-"): [
            closed_loop(sc, "nominal", "-", s, args.std_max) for s in seeds]}
        for alg in algorithms:
            for rule in rules:
                rows[(alg, rule)] = [closed_loop(sc, alg, rule, s, args.std_max) for s in seeds]
        rows[("oracle (true f)", "-")] = [closed_loop(sc, "oracle", "-", s, args.std_max)
                                          for s in seeds]
        tab = closed_loop_table(rows, n_seeds, args.std_max)
        tab2 = signed_table(rows)
        notes = []
        for key, runs in rows.items():
            missing = sum(len(r["err"]) < len(STATIONS) for r in runs)
            rej = sum(sum(r["rejected"].values()) for r in runs)
            em = sum(r["emergency"] for r in runs)
            if missing or rej or em:
                notes.append(f"- {key[0]} / {key[1]}: {missing} runs with a missing stop, "
                             f"{rej} rejected messages, {em} emergency brakes")
        print("\n" + tab + "\n\n" + tab2, flush=True)
        sections += [tab, tab2]
        if notes:
            print("\n" + "\n".join(notes))
            sections.append("\n".join(notes))
        print(f"\n(closed loop {time.perf_counter() - t1:.0f} s)")
    if args.step_fault:
        tab = step_fault_section(sc, algorithms, seeds, args.std_max)
        print("\n" + tab, flush=True)
        sections.append(tab)
    (out_dir / "bench_closed_loop.md").write_text("\n\n".join(sections) + "\n")


if __name__ == "__main__":
    main()
