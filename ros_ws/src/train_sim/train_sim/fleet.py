"""A fleet scenario for ``fleet``: N trains x M runs on two lines, one hidden map error, a few
trains with degrading brakes.

    python -m train_sim.fleet OUTDIR [--trains 6] [--runs 4] [--degraded 2] [--seed 1]
                                     [--stops 2]

Writes (OUTDIR is created):

  OUTDIR/lines/north.yaml, south.yaml   the lines as the railway believes them
  OUTDIR/trains/metro_b6.yaml           the train as the railway believes it (every train)
  OUTDIR/bags/<train>_r<k>_<line>/      one measured bag per run (no ground truth)
  OUTDIR/manifest.csv                   train,bag,line,train_file,time (paths relative to it)
  OUTDIR/truth.yaml                     what is hidden: the map error, the degraded trains and
                                        their f per run, each run's true mass

The world: ``north`` is the shipped metro_demo line (A -> B -> C), ``south`` a 5.2 km line with
four stations written here (P -> Q -> R -> S); ``--stops 1`` ends every run at the first stop,
``--stops 3`` serves three (north B, C, D; south Q, R, S: 10-minute bags, a real day's runs).
Run k of train i is on ``north`` when i + k is even, else on ``south``: every train runs on
both lines. Hidden from the believed files:

- the map error: an unmapped gradient section (``--map-error START END PERMILLE`` on ``north``,
  default +5 per mille on [1000, 1400) m, which every run passes at speed);
- degraded brakes on the ``--degraded`` trains T01, T02, ...: braking rate f constant within a
  run, falling linearly over the runs from ``--f-first`` to ``--f-last``;
- passenger load: every run's true mass is the believed mass x (1 + N(0, ``--load-std``)).

Each run has its own seed, link draw and train-clock epoch. Deterministic in ``--seed``.
Pure module (numpy, PyYAML, train_core, train_sim).
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml
from train_core.config import load_yaml
from train_core.files import config_file
from train_core.progress import Progress

from .scenario import scenario_from_dict

SOUTH_LINE = {
    "name": "south",
    "length": 5200.0,
    "max_speed": 22.2,
    "speed_limits": [{"start": 0.0, "end": 400.0, "speed": 16.7}],
    "gradients": [
        {"start": 0.0, "end": 400.0, "permille": 0.0},
        {"start": 400.0, "end": 1100.0, "permille": 6.0},
        {"start": 1100.0, "end": 1700.0, "permille": -10.0},
        {"start": 1700.0, "end": 2300.0, "permille": 0.0},
        {"start": 2300.0, "end": 3000.0, "permille": -5.0},
        {"start": 3000.0, "end": 3600.0, "permille": 14.0},
        {"start": 3600.0, "end": 4300.0, "permille": 0.0},
        {"start": 4300.0, "end": 5200.0, "permille": -6.0},
    ],
    "stations": [{"name": "P", "position": 100.0, "dwell": 10.0},
                 {"name": "Q", "position": 2000.0, "dwell": 20.0},
                 {"name": "R", "position": 4100.0, "dwell": 20.0},
                 {"name": "S", "position": 5100.0, "dwell": 20.0}],
    # the balise 40 m before S is past R: runs that end at R (--stops 1, 2) never read it
    "balises": [{"id": i + 1, "position": p} for i, p in enumerate(
        (60.0, 500.0, 1000.0, 1500.0, 1960.0, 2500.0, 3100.0, 3600.0, 4060.0, 4700.0,
         5060.0))],
}
ROUTES = {"north": ("B", "C", "D"), "south": ("Q", "R", "S")}
DURATION = {1: 200.0, 2: 360.0, 3: 600.0}  # s, a run's record by the stations it serves
START = {"north": 100.0, "south": 100.0}


@dataclass
class FleetSpec:
    trains: int = 6
    runs: int = 4
    degraded: int = 2
    seed: int = 1
    map_error: tuple = ("north", 1000.0, 1400.0, 5.0)  # line, start m, end m, per mille
    f_first: float = 0.85  # braking rate of a degraded train in its first run
    f_last: float = 0.75  # ... and in its last run
    load_std: float = 0.01  # relative sd of the per-run true mass
    dwell: float = 15.0  # s at the intermediate station
    stops: int = 2  # stations served after the start: 3 (10-minute runs), 2 (6) or 1 (3.3)
    link_p: tuple = (0.2, 0.45)  # Bernoulli frame error rate range (r = 2)
    extra: dict = field(default_factory=dict)

    def train_ids(self) -> list[str]:
        return [f"T{i + 1:02d}" for i in range(self.trains)]

    def degraded_ids(self) -> list[str]:
        return self.train_ids()[:self.degraded]


def braking_rate(spec: FleetSpec, run: int) -> float:
    """f of a degraded train in run ``run`` (linear from f_first to f_last over the runs)."""
    if spec.runs <= 1:
        return spec.f_first
    return spec.f_first + (spec.f_last - spec.f_first) * run / (spec.runs - 1)


def plan(spec: FleetSpec) -> list[dict]:
    """Every run: train, run index, line, seed, effects, mass, epoch (deterministic)."""
    rng = np.random.default_rng([spec.seed, 14])
    believed = load_yaml(config_file("trains", "metro_b6"))
    runs = []
    for i, tid in enumerate(spec.train_ids()):
        for k in range(spec.runs):
            line = "north" if (i + k) % 2 == 0 else "south"
            eff: dict = {}
            mass = float(believed["mass"]) * (1.0 + spec.load_std * float(rng.normal()))
            eff["mass"] = {"mass": round(mass, 1)}
            if tid in spec.degraded_ids():
                f = round(braking_rate(spec, k), 4)
                eff["braking_rate"] = {"f_start": f, "f_end": f}
            ml, s0, s1, pm = spec.map_error
            if line == ml:
                eff["gradient"] = {"start": float(s0), "end": float(s1), "permille": float(pm)}
            runs.append({
                "train": tid, "run": k, "line": line, "effects": eff,
                "seed": int(rng.integers(2**31)),
                "epoch": round(float(rng.uniform(1e8, 2e9)), 3),
                "link_p": round(float(rng.uniform(*spec.link_p)), 3),
                # the day's time of the run (h): runs of a train are ordered in time
                "time": round(k * 24.0 + float(rng.uniform(6.0, 20.0)), 2)})
    return runs


def _scenario_dict(r: dict, spec: FleetSpec, line_path: Path, train_path: Path) -> dict:
    route = ROUTES[r["line"]]
    n_stops = max(1, min(spec.stops, 3))
    return {"name": f"fleet-{r['train']}-r{r['run']}-{r['line']}",
            "line": str(line_path), "train": str(train_path), "seed": r["seed"],
            "duration": DURATION[min(max(spec.stops, 1), 3)],
            "start": {"position": START[r["line"]], "speed": 0.0},
            "sensors": {"odometer_rate": 10.0, "stamp_epoch": r["epoch"]},
            "driver": {"mode": "ato", "control_period": 0.1, "initial_dwell": 5.0},
            # the first station spec.dwell, the later ones 30 s
            "timetable": [{"station": st, "dwell": spec.dwell if i == 0 else 30.0}
                          for i, st in enumerate(route[:n_stops])],
            "link": {"model": "bernoulli", "p": r["link_p"], "r": 2, "latency": 0.02,
                     "jitter": 0.005},
            "effects": r["effects"]}


def write_fleet(out: str | Path, spec: FleetSpec, progress=None) -> dict:
    """Write lines, train, bags, manifest.csv and truth.yaml; returns the truth dict."""
    from .generate import generate

    out = Path(out)
    (out / "lines").mkdir(parents=True, exist_ok=True)
    (out / "trains").mkdir(parents=True, exist_ok=True)
    (out / "bags").mkdir(parents=True, exist_ok=True)
    lines = {"north": out / "lines" / "north.yaml", "south": out / "lines" / "south.yaml"}
    north = load_yaml(config_file("lines", "metro_demo"))
    north["name"] = "north"
    lines["north"].write_text(yaml.safe_dump(north, sort_keys=False))
    lines["south"].write_text(yaml.safe_dump(SOUTH_LINE, sort_keys=False))
    train_path = out / "trains" / "metro_b6.yaml"
    train_path.write_text(config_file("trains", "metro_b6").read_text())
    rows, truth_runs = [], []
    runs = plan(spec)
    for n, r in enumerate(runs):
        name = f"{r['train']}_r{r['run']}_{r['line']}"
        bag = out / "bags" / name
        sc = scenario_from_dict(_scenario_dict(r, spec, lines[r["line"]].resolve(),
                                               train_path.resolve()), name, out)
        if not bag.exists():
            generate(sc, bag, measured=True)
        rows.append({"train": r["train"], "bag": f"bags/{name}",
                     "line": f"lines/{r['line']}.yaml", "train_file": "trains/metro_b6.yaml",
                     "time": r["time"]})
        truth_runs.append({"bag": f"bags/{name}", "train": r["train"], "line": r["line"],
                           "mass": r["effects"]["mass"]["mass"],
                           "braking_rate": r["effects"].get("braking_rate", {}).get("f_start",
                                                                                    1.0)})
        if progress is not None:
            progress(n + 1, len(runs), name)
    with open(out / "manifest.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=["train", "bag", "line", "train_file", "time"])
        w.writeheader()
        w.writerows(rows)
    ml, s0, s1, pm = spec.map_error
    truth = {"map_error": {"line": ml, "start": float(s0), "end": float(s1),
                           "permille": float(pm)},
             "degraded_trains": spec.degraded_ids(),
             "braking_rate_per_run": {f"r{k}": braking_rate(spec, k) for k in range(spec.runs)},
             "runs": truth_runs}
    (out / "truth.yaml").write_text(yaml.safe_dump(truth, sort_keys=False))
    return truth


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="train_sim.fleet", description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="\n".join(__doc__.splitlines()[2:]))
    p.add_argument("out", help="output directory (created; existing bags are kept)")
    p.add_argument("--trains", type=int, default=6, help="number of trains (default 6)")
    p.add_argument("--runs", type=int, default=4, help="runs per train (default 4)")
    p.add_argument("--degraded", type=int, default=2,
                   help="trains with degrading brakes: the first N (default 2)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--map-error", nargs=4, metavar=("LINE", "START", "END", "PERMILLE"),
                   default=None, help="hidden gradient section (default north 1000 1400 5)")
    p.add_argument("--f-first", type=float, default=0.85)
    p.add_argument("--f-last", type=float, default=0.75)
    p.add_argument("--load-std", type=float, default=0.01)
    p.add_argument("--stops", type=int, default=2, choices=(1, 2, 3),
                   help="stations served per run: 3 (10-minute bags), 2 (6-minute bags, "
                        "default) or 1 (200 s)")
    a = p.parse_args(argv)
    if a.degraded > a.trains or a.trains < 1 or a.runs < 1:
        print("train_sim.fleet: need 1 <= trains, 1 <= runs, degraded <= trains",
              file=sys.stderr)
        return 2
    spec = FleetSpec(trains=a.trains, runs=a.runs, degraded=a.degraded, seed=a.seed,
                     f_first=a.f_first, f_last=a.f_last, load_std=a.load_std, stops=a.stops)
    if a.map_error:
        spec.map_error = (a.map_error[0], *(float(x) for x in a.map_error[1:]))
    t0 = time.perf_counter()
    truth = write_fleet(a.out, spec, progress=Progress("train_sim.fleet", what_width=28))
    print(f"wrote {len(truth['runs'])} bags and {Path(a.out) / 'manifest.csv'} in "
          f"{time.perf_counter() - t0:.0f} s; hidden: gradient {truth['map_error']}, "
          f"degraded brakes on {', '.join(truth['degraded_trains']) or 'no train'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
