#!/usr/bin/env python3
"""Benchmark of the SI front end.

For each case -- no effect (control), Davis c +30 %, all Davis -30 %, all Davis +30 %, mass
+20 % -- on ``metro_demo`` and, as a second column, ``crh3_high_speed`` (far wider speed range):

1. a training run (seed s) and a held-out run (seed s', a different route, see below) of the
   world = scenario + effect (``Scenario.with_effects``);
2. ``identify`` on the training run's RECEIVED odometer and balise samples and the control
   commands (what a bag holds), prior = the scenario's ``train.yaml``;
3. table: truth vs fitted (mean over seeds [2.5 %, 97.5 % quantiles], or +- SE for one seed),
   the mean standard error, the error, z = (fit - truth) / SE and how often it was identifiable,
   for a, b, c (N), mass (kg), rotary allowance and braking rate;
4. prediction on the held-out run: the simulator with the nominal (prior) train and with the
   fitted train, driven OPEN LOOP by the held-out run's recorded a_Tar sequence from the held-out
   start state; RMSE of speed and position against the held-out truth over the run, and the
   stopping-point error of every braking phase (per leg, i.e. the change of the position error
   between consecutive stops, so earlier legs do not count twice; and at the last stop).

Open-loop replay: the prediction runs the simulator's own ``World`` (same Actuator, Dynamics,
GradientLookup, RK4 grid and start state) on a scenario whose true train is the model train
(believed train = the prior, so the drive force is calibrated for the prior mass exactly as in
the world) with no effects, and whose ATO is replaced by a playback of the recorded commands
(one per ATO cycle, issued at the same instants). No second physics model. The ATO closes the
loop on the train's state, so replaying its *commands* (not re-running the ATO) is the fair test
of the model. Sanity check printed with the tables: replaying with the TRUE train reproduces the
held-out truth (error ~1e-9 m).

Held-out run. In ``simulate`` the seed only drives sensor noise, balise offsets and link losses:
the ATO reads the exact state and has no randomness, so two seeds give the SAME true trajectory.
A held-out run that differs only by its seed would test the fit on the training trajectory. So
the held-out run also draws, from its seed, another route and driving style: metro_demo: the
full timetable, or skip B, or skip C (express), dwells U(15, 45) s; both: speed margin below the
limit U(0.5, 4) m/s (metro) / U(0.5, 25) m/s (crh3), braking margin U(0.70, 0.95). ``--holdout
seed`` gives the literal "another seed only" variant.

Found with this script and fixed in identify.py: on metro_demo the fit was biased even with no
effect (8 seeds: a -40 %, c +31 %, f +0.7 %, |z| up to 7) because the delayed-command lookup
landed one 0.1 s step late at ~11 % of its grid points (floating-point round-off). The core now
looks up with a tolerance; ``--nudge-control-stamps 1e-6`` (control stamps 1 us earlier) is kept
as a check that the default and nudged runs agree.

Coverage (``--coverage N``): the standard errors against the spread of the fits. N seeds of the
no-effect training run of each scenario (the same true trajectory: the seed draws the sensor
noise, balise offsets and link losses), identify on each; per parameter the mean and standard
deviation of z = (fitted - truth) / SE and the share of |z| < 1.96 (honest standard errors:
sd(z) about 1 and 95 %; sd(z) below 1 where the fitted process noise holds a misfit that is the
same in every seed). With ``--no-placement`` the run's place on the line is taken as exact.

Usage: bench_identify.py [--seeds 8] [--quick] [--holdout varied|seed] [--scenarios ...]
                         [--nudge-control-stamps 1e-6] [--coverage N [--no-placement]]
"""

from __future__ import annotations

import argparse
import bisect
import dataclasses
import os
import sys
import time

import numpy as np
from train_core.progress import track  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:0] = [os.path.join(HERE, "..", "ros_ws", "src", "train_estimation"),
                os.path.join(HERE, "..", "ros_ws", "src", "train_sim")]

from train_core.effects import Effects, MassEffect, ResistanceEffect  # noqa: E402
from train_core.model import TrainParams  # noqa: E402

from train_estimation.core.offline.identify import IdentificationError, SIConfig, SIData, identify  # noqa: E402
from train_sim.driver import TimetableStop  # noqa: E402
from train_sim.scenario import Scenario, load_scenario  # noqa: E402
from train_sim.world import World, simulate  # noqa: E402

OUT = os.path.join(HERE, "out")
SCENARIOS = ("metro_demo", "crh3_high_speed")
# case name -> (scale of a, b, c; scale of the mass)
CASES = {
    "none (control)": ((1.0, 1.0, 1.0), 1.0),
    "c +30 %": ((1.0, 1.0, 1.3), 1.0),
    "Davis -30 %": ((0.7, 0.7, 0.7), 1.0),
    "Davis +30 %": ((1.3, 1.3, 1.3), 1.0),
    "mass +20 %": ((1.0, 1.0, 1.0), 1.2),
}
PARAMS = (  # (name in SIResult, label, getter on TrainParams, unit)
    ("davis.a", "a", lambda t: t.davis.a, "N"),
    ("davis.b", "b", lambda t: t.davis.b, "N s/m"),
    ("davis.c", "c", lambda t: t.davis.c, "N s2/m2"),
    ("mass", "mass", lambda t: t.mass, "kg"),
    ("rotary_allowance", "lambda", lambda t: t.rotary_allowance, "-"),
    ("braking_rate", "f", lambda t: t.brake.braking_rate, "-"),
)
HOLDOUT = {  # per scenario: speed-margin range (m/s), held-out duration (s)
    "metro_demo": ((0.5, 4.0), 600.0),
    "crh3_high_speed": ((0.5, 25.0), 1100.0),
}


# ---------------------------------------------------------------------------------------------
# runs
# ---------------------------------------------------------------------------------------------

def world_scenario(sc: Scenario, case: str) -> Scenario:
    """Scenario whose world is the believed train with the case's effect."""
    (ka, kb, kc), km = CASES[case]
    d, eff = sc.train.davis, Effects()
    if (ka, kb, kc) != (1.0, 1.0, 1.0):
        eff = dataclasses.replace(eff, resistance=ResistanceEffect(ka * d.a, kb * d.b, kc * d.c))
    if km != 1.0:
        eff = dataclasses.replace(eff, mass=MassEffect(km * sc.train.mass))
    return sc.with_effects(eff)


def holdout_scenario(sc: Scenario, seed: int, mode: str) -> Scenario:
    """Another route/driving style drawn from ``seed`` (mode 'varied'), or the same ('seed')."""
    if mode == "seed":
        return sc
    rng = np.random.default_rng([seed, 7])
    (m_lo, m_hi), duration = HOLDOUT.get(sc.name, ((0.5, 4.0), sc.duration))
    driver = dataclasses.replace(sc.driver, speed_margin=float(rng.uniform(m_lo, m_hi)),
                                 brake_margin=float(rng.uniform(0.70, 0.95)))
    timetable = sc.timetable
    if len(timetable) > 2:  # metro: full, or skip one intermediate station (express)
        skip = int(rng.integers(0, len(timetable)))  # 0: none; k: drop stop k - 1 (not last)
        stops = [s for i, s in enumerate(timetable) if skip == 0 or i != skip - 1]
        timetable = tuple(TimetableStop(s.station, s.position, float(rng.uniform(15.0, 45.0)))
                          for s in stops)
    return sc.with_changes(driver=driver, timetable=timetable, duration=duration)


def si_data(res, nudge: float = 0.0) -> SIData:
    """What a bag holds: received odometer and balise samples, all control commands.

    ``nudge`` (s, diagnostic only, default 0) is subtracted from the control stamps: with the
    core's lookup tolerance, the result must not change (it did before the fix).
    """
    o, b, c = res.odometer, res.balise, res.control
    m, mb = o["received"], b["received"]
    return SIData(odo_t=o["stamp"][m], odo_distance=o["distance"][m], odo_speed=o["speed"][m],
                  odo_speed_variance=o["speed_variance"][m], ctrl_t=c["stamp"] - nudge,
                  ctrl_a_tar=c["target_acceleration"], balise_t=b["stamp"][mb],
                  balise_position=b["position"][mb])


class ReplayDriver:
    """Stands in for the ATO: returns the recorded a_Tar in force at t (zero-order hold)."""

    def __init__(self, t, a_tar, u0: float):
        self.t, self.a, self.u0 = list(map(float, t)), list(map(float, a_tar)), float(u0)
        self.stops: list = []
        self.emergency_brakes = 0

    def update(self, t: float, x: float, v: float, stopped: bool) -> float:
        i = bisect.bisect_right(self.t, t + 1e-9) - 1
        return self.a[i] if i >= 0 else self.u0

    def set_movement_authority(self, *args) -> None:  # pragma: no cover - not used offline
        pass


def model_scenario(sc_hold: Scenario, model: TrainParams, effects: Effects | None = None) -> dict:
    """Open-loop run of the simulator with train ``model`` on the held-out run's commands.

    The world of a scenario with true train = ``model``, believed train = the prior (force
    calibration, dynamics.py kappa), the believed line, no effects (unless given: the sanity
    check passes the held-out world's own effects), the held-out start state and ATO period.
    """
    eff = Effects() if effects is None else effects
    sc_m = dataclasses.replace(sc_hold, true_train=model, true_line=sc_hold.line, effects=eff,
                               true_link=sc_hold.link)
    if effects is not None:
        sc_m = dataclasses.replace(sc_m, true_line=sc_hold.true_line)
    return sc_m


def run_replay(sc_m: Scenario, ctrl: dict) -> dict:
    world = World(sc_m, 0)
    # the recorded control is the ATO's a_Tar at every sample; here control_period equals the
    # sample period, so it is exactly the command sequence (checked in main)
    world.driver = ReplayDriver(ctrl["t"], ctrl["target_acceleration"],
                                sc_m.start_target_acceleration)
    world.advance(sc_m.duration)
    tr = world.result().truth
    return {"t": tr["t"], "x": tr["position"], "v": tr["velocity"]}


def stop_indices(v: np.ndarray) -> list[tuple[int, int]]:
    """(index where the truth comes to rest, index mid-way through the following dwell)."""
    out = []
    moving = v > 0.0
    n = v.size
    for i in range(1, n):
        if moving[i - 1] and not moving[i]:
            j = i
            while j < n and not moving[j]:
                j += 1
            out.append((i, (i + j - 1) // 2 if j < n else n - 1))
    return out


def prediction_errors(truth: dict, pred: dict) -> dict:
    x, v = truth["position"], truth["velocity"]
    n = min(x.size, pred["x"].size)
    ex, ev = pred["x"][:n] - x[:n], pred["v"][:n] - v[:n]
    stops = stop_indices(v[:n])
    # stopping-point error: model position mid-dwell (it has come to rest under the holding
    # brake by then) minus the truth's stop position
    e_stop = np.array([pred["x"][k] - x[i] for i, k in stops])
    legs = np.diff(np.concatenate([[0.0], e_stop])) if e_stop.size else np.array([np.nan])
    return {"rmse_v": float(np.sqrt(np.mean(ev ** 2))), "rmse_x": float(np.sqrt(np.mean(ex ** 2))),
            "leg_stop": float(np.mean(np.abs(legs))),
            "last_stop": float(abs(e_stop[-1])) if e_stop.size else float("nan"),
            "n_stops": len(stops)}


def run_case(sc: Scenario, case: str, seed_train: int, seed_hold: int, holdout: str,
             nudge: float = 0.0) -> dict:
    sc_w = world_scenario(sc, case)
    res_train = simulate(sc_w, seed=seed_train)
    sc_hold = holdout_scenario(sc_w, seed_hold, holdout)
    res_hold = simulate(sc_hold, seed=seed_hold)
    out = {"truth": sc_w.true_train, "prior": sc.train, "hold": res_hold}
    try:
        fit = identify(si_data(res_train, nudge), sc.line, sc.train)
    except IdentificationError as exc:
        out["error"] = str(exc)
        return out
    out["fit"] = fit
    ctrl = res_hold.control
    preds = {"nominal": run_replay(model_scenario(sc_hold, sc.train), ctrl),
             "fitted": run_replay(model_scenario(sc_hold, fit.train), ctrl)}
    out["pred"] = preds
    out["err"] = {k: prediction_errors(res_hold.truth, p) for k, p in preds.items()}
    return out


def sanity_check(sc: Scenario, seed: int, holdout: str) -> tuple[float, float]:
    """Replay with the true train and effects must reproduce the held-out truth; the
    simulator's ``open_loop`` driver mode must give the same replay."""
    sc_w = world_scenario(sc, "mass +20 %")
    sc_hold = holdout_scenario(sc_w, seed, holdout)
    res = simulate(sc_hold, seed=seed)
    sc_m = model_scenario(sc_hold, sc_hold.true_train, sc_hold.effects)
    p = run_replay(sc_m, res.control)
    # the simulator's own open-loop driver mode on the same profile must agree (ReplayDriver
    # is the independent stand-in it is checked against)
    prof = tuple(zip(res.control["t"].tolist(), res.control["target_acceleration"].tolist()))
    sc_ol = dataclasses.replace(sc_m, driver=dataclasses.replace(sc_m.driver, mode="open_loop",
                                                                 profile=prof))
    x_ol = simulate(sc_ol, seed=0).truth["position"]
    n = min(p["x"].size, res.truth["t"].size, x_ol.size)
    return (float(np.max(np.abs(p["x"][:n] - res.truth["position"][:n]))),
            float(np.max(np.abs(x_ol[:n] - p["x"][:n]))))


# ---------------------------------------------------------------------------------------------
# tables
# ---------------------------------------------------------------------------------------------

def summary(x, fmt="{:.4g}") -> str:
    """mean [2.5 %, 97.5 %] over seeds (just the value for one seed)."""
    x = np.asarray([u for u in x if np.isfinite(u)], float)
    if x.size == 0:
        return "-"
    if x.size == 1:
        return fmt.format(x[0])
    lo, hi = np.percentile(x, [2.5, 97.5])
    return f"{fmt.format(x.mean())} [{fmt.format(lo)}, {fmt.format(hi)}]"


def param_cells(runs: list, name: str, get) -> list[str]:
    ok = [r for r in runs if "fit" in r]
    if not ok:
        return ["-"] * 5
    truth = get(ok[0]["truth"])
    # identify() substitutes the prior for unidentifiable parameters only in specific form
    # (per effective mass); report what the fitted train.yaml actually says
    fitted = np.array([get(r["fit"].train) for r in ok])
    se = np.array([r["fit"].std_errors[name] for r in ok])
    ident = np.array([r["fit"].identifiable[name] for r in ok])
    rel = 100.0 * (fitted / truth - 1.0)
    if len(ok) == 1:
        s = f"{fitted[0]:.4g}" + (f" +- {se[0]:.2g}" if np.isfinite(se[0]) else "")
    else:
        s = summary(fitted)
    z = (fitted - truth) / se
    return [f"{truth:.4g}", s, summary(rel, "{:+.1f}"), summary(z[ident], "{:+.1f}"),
            f"{ident.sum()}/{len(ok)}"]


def print_param_table(results: dict, scenarios, cases, nseeds: int) -> None:
    print(f"\n### Fitted vs truth ({nseeds} seed(s); fitted = mean [2.5 %, 97.5 %] over seeds, "
          "or value +- SE for one seed; err = fitted/truth - 1; z = (fitted - truth)/SE over "
          "the seeds where identifiable; id = identifiable in k of n seeds)\n")
    head = "| case | param |"
    sep = "|---|---|"
    for s in scenarios:
        head += f" {s} truth | fitted | err % | z | id |"
        sep += "---:|---:|---:|---:|---:|"
    print(head)
    print(sep)
    for case in cases:
        for name, label, get, unit in PARAMS:
            row = f"| {case} | {label} ({unit}) |"
            for s in scenarios:
                row += " " + " | ".join(param_cells(results[s][case], name, get)) + " |"
            print(row)
    for s in scenarios:
        for case in cases:
            errs = [r["error"] for r in results[s][case] if "error" in r]
            if errs:
                print(f"\n{s} / {case}: identify refused {len(errs)} run(s): {errs[0]}")


def print_pred_table(results: dict, scenarios, cases, nseeds: int) -> None:
    print(f"\n### Held-out prediction, open-loop replay of the recorded a_Tar ({nseeds} "
          "seed(s); nominal -> fitted, mean [95 % interval] over seeds)\n")
    metrics = (("rmse_v", "speed RMSE (m/s)"), ("rmse_x", "position RMSE (m)"),
               ("leg_stop", "mean abs stop error per leg (m)"),
               ("last_stop", "abs error at last stop (m)"))
    for s in scenarios:
        print(f"\n**{s}**\n")
        print("| case | " + " | ".join(lbl for _, lbl in metrics) + " |")
        print("|---|" + "---:|" * len(metrics))
        for case in cases:
            ok = [r for r in results[s][case] if "err" in r]
            cells = []
            for key, _ in metrics:
                nom = [r["err"]["nominal"][key] for r in ok]
                fit = [r["err"]["fitted"][key] for r in ok]
                cells.append(f"{summary(nom, '{:.3g}')} -> {summary(fit, '{:.3g}')}")
            print(f"| {case} | " + " | ".join(cells) + " |")


def plot(results: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [(s, c) for s, c in (("metro_demo", "mass +20 %"), ("crh3_high_speed", "Davis +30 %"))
              if s in results and c in results[s] and "pred" in results[s][c][0]]
    if not panels:
        return
    fig, axes = plt.subplots(2, len(panels), figsize=(7 * len(panels), 7), squeeze=False)
    for j, (s, c) in enumerate(panels):
        r = results[s][c][0]
        tr = r["hold"].truth
        ax = axes[0, j]
        ax.plot(tr["t"], tr["velocity"], "k", lw=1.5, label="held-out truth")
        for k, st in (("nominal", "--"), ("fitted", ":")):
            p = r["pred"][k]
            ax.plot(p["t"], p["v"], st, lw=1.2, label=f"{k} train (open loop)")
        ax.set_title(f"{s}, world = {c}: held-out speed")
        ax.set_ylabel("speed (m/s)")
        ax.legend(fontsize=8)
        ax = axes[1, j]
        for k in ("nominal", "fitted"):
            p = r["pred"][k]
            n = min(p["x"].size, tr["position"].size)
            ax.plot(p["t"][:n], p["x"][:n] - tr["position"][:n], label=k)
        ax.set_yscale("symlog", linthresh=1.0)  # the fitted error is ~100x smaller
        ax.set_ylabel("predicted - true position (m, symlog)")
        ax.set_xlabel("time (s)")
        ax.legend(fontsize=8)
        for a in axes[:, j]:
            a.grid(alpha=0.3)
    fig.tight_layout()
    os.makedirs(os.path.dirname(path), exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def coverage(scenarios, seeds: int, placement: bool) -> None:
    """The coverage table (module doc)."""
    cfg = SIConfig(placement_doubt=placement)
    print(f"\n### Coverage of the standard errors ({seeds} seeds of the no-effect run; "
          f"placement doubt {'on' if placement else 'off'})\n")
    print("| scenario | parameter | identifiable | mean z | sd z | abs z < 1.96 |")
    print("|---|---|---:|---:|---:|---:|")
    for s in scenarios:
        sc = load_scenario(s)
        sc_w = world_scenario(sc, "none (control)")
        z: dict = {name: [] for name, *_ in PARAMS}
        ident = dict.fromkeys(z, 0)
        for seed in track(range(seeds), f"coverage {s}"):
            try:
                fit = identify(si_data(simulate(sc_w, seed=seed)), sc.line, sc.train, cfg)
            except IdentificationError:
                continue
            for name, _, get, _ in PARAMS:
                se = fit.std_errors[name]
                if np.isfinite(se) and se > 0:
                    z[name].append((get(fit.train) - get(sc_w.true_train)) / se)
                ident[name] += bool(fit.identifiable[name])
        for name, label, *_ in PARAMS:
            zz = np.asarray(z[name])
            if zz.size < 2:
                continue
            print(f"| {s} | {label} | {ident[name]}/{seeds} | {zz.mean():+.2f} | "
                  f"{zz.std(ddof=1):.2f} | {np.mean(np.abs(zz) < 1.96):.2f} |")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=8, help="seed pairs (training, held-out)")
    p.add_argument("--quick", action="store_true", help="2 seeds")
    p.add_argument("--holdout", choices=("varied", "seed"), default="varied",
                   help="held-out run: another route and driving style (default), or only "
                        "another seed (same true trajectory as training)")
    p.add_argument("--scenarios", nargs="+", default=list(SCENARIOS))
    p.add_argument("--no-plot", action="store_true")
    p.add_argument("--nudge-control-stamps", type=float, default=0.0, metavar="S",
                   help="diagnostic: give identify control stamps S seconds early (1e-6 "
                        "sidesteps the round-off in its command lookup; default 0 = as recorded)")
    p.add_argument("--coverage", type=int, default=0, metavar="N",
                   help="only the standard errors' coverage over N seeds of the no-effect run")
    p.add_argument("--no-placement", action="store_true",
                   help="with --coverage: the run's place on the line taken as exact")
    args = p.parse_args(argv)
    if args.coverage:
        coverage(args.scenarios, args.coverage, not args.no_placement)
        return
    if args.quick:
        args.seeds = min(args.seeds, 2)
    cases = list(CASES)
    print("# bench_identify: " + " ".join(
        ["PYTHONPATH=ros_ws/src/train_sim:ros_ws/src/train_estimation python3",
         "benchmarks/bench_identify.py"] + (argv if argv is not None else sys.argv[1:])))
    print(f"seeds={args.seeds} holdout={args.holdout} scenarios={' '.join(args.scenarios)} "
          f"nudge_control_stamps={args.nudge_control_stamps:g} s")
    t0 = time.perf_counter()
    results: dict = {}
    for s in args.scenarios:
        sc = load_scenario(s)
        if abs(sc.driver.control_period * sc.odometer_rate - 1.0) > 1e-9:
            raise SystemExit(f"{s}: control is recorded per odometer sample but the ATO cycle is "
                             f"{sc.driver.control_period} s: the record is not the command "
                             "sequence; replay would be approximate")
        err, err_ol = sanity_check(sc, 1000, args.holdout)
        print(f"{s}: replay with the true train (world mass +20 %) reproduces the held-out truth "
              f"to max |dx| = {err:.2g} m; driver mode open_loop agrees to {err_ol:.2g} m")
        results[s] = {c: [] for c in cases}
        for i in track(range(args.seeds), f"identify {s}"):
            for c in cases:
                results[s][c].append(run_case(sc, c, 100 + i, 1000 + i, args.holdout,
                                              args.nudge_control_stamps))
        hold = results[s][cases[0]][0]["hold"]
        print(f"{s}: held-out run of seed 1000 stops at "
              f"{[st['station'] for st in hold.stops]}, "
              f"{time.perf_counter() - t0:.0f} s so far")
    print_param_table(results, args.scenarios, cases, args.seeds)
    print_pred_table(results, args.scenarios, cases, args.seeds)
    if not args.no_plot:
        name = "identify_holdout_nudged.png" if args.nudge_control_stamps else \
            "identify_holdout.png"
        path = os.path.join(OUT, name)
        plot(results, path)
        print(f"\nwrote {os.path.relpath(path, os.path.join(HERE, '..'))}")
    print(f"\nwall time {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
