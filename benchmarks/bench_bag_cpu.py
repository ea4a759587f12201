#!/usr/bin/env python3
"""CPU time of one bag's analysis (check_bag's topic health + identify + diagnose, as ``fleet``
runs it) on a fixed set of bags, and the reports it gives, for comparing two versions.

    ./run bench bag_cpu --make DIR            write the bags (train_sim.cases, train_sim.fleet
                                              --stops 3) and DIR/bags.json
    ./run bench bag_cpu --run DIR --out F     analyse every bag of DIR/bags.json (and the
                                              shipped bags), CPU seconds per bag
                                              (time.process_time) and the full reports -> F
    ./run bench bag_cpu --compare A B         the CPU table of A against B and the largest
                                              relative difference between their reports
    ./run bench bag_cpu --quick [--out F]     two cases (nominal, gradient) made in a
                                              temporary folder and the shipped bags (1 min)

Run two versions side by side (a second git worktree) on the same DIR to compare them; the
machine's load average is printed with each run.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)

# (label, causes, size, line family) of train_sim.cases (8-12 minute bags)
CASES = [("nominal", (), "plain", "metro_demo"), ("gradient", ("gradient",), "plain", "regional"),
         ("braking_rate", ("braking_rate",), "plain", "regional"),
         ("clock_drift", ("clock_drift",), "plain", "highspeed"),
         ("odometer_scale", ("odometer_scale",), "plain", "metro_demo"),
         ("brake_delay+resistance", ("brake_delay", "resistance"), "plain", "regional"),
         ("power_limit", ("power_limit",), "plain", "regional"),
         ("wheel_slip", ("wheel_slip",), "plain", "regional"),
         ("mass", ("mass",), "subtle", "metro"),
         ("adhesion_section", ("adhesion_section",), "plain", "highspeed")]
# the shipped bags (main job recordings, 2 minutes): (bag, line, train)
SHIPPED = [("metro_demo_short", "metro_demo", "metro_b6"),
           ("wen2017_subway", "wen2017", "wen2017_subway")]


def make(d: str, cases: list = CASES, fleet: bool = True) -> None:
    from train_core.progress import track

    from train_sim.cases import make_case
    from train_sim.fleet import FleetSpec, write_fleet
    from train_sim.generate import generate

    os.makedirs(d, exist_ok=True)
    bags = []
    for label, causes, size, family in track(cases, "bag_cpu: cases"):
        case = make_case(np.random.default_rng([24, len(bags)]), causes or None, size, family)
        sub = os.path.join(d, label)
        paths = case.write(sub)
        generate(case.scenario, os.path.join(sub, "bag"), measured=True)
        bags.append({"label": f"{label} ({case.family}, {case.scenario.duration:.0f} s)",
                     "bag": os.path.join(sub, "bag"), "line": str(paths["line"]),
                     "train_file": str(paths["train"]), "train": label,
                     "duration": case.scenario.duration})
    fd = os.path.join(d, "fleet")
    if not fleet:
        json.dump(bags + _shipped(), open(os.path.join(d, "bags.json"), "w"), indent=1)
        return
    write_fleet(fd, FleetSpec(trains=2, runs=2, degraded=1, seed=3, stops=3, dwell=40.0,
                              map_error=("north", 1000.0, 1400.0, 5.0)))
    from train_estimation.tools import fleet as tool

    for t in tool.read_manifest(os.path.join(fd, "manifest.csv")):
        bags.append({"label": f"fleet {t['train']} {os.path.basename(t['bag'])}",
                     "bag": t["bag"], "line": t["line"], "train_file": t["train_file"],
                     "train": t["train"]})
    bags += _shipped()
    json.dump(bags, open(os.path.join(d, "bags.json"), "w"), indent=1)


def _shipped() -> list[dict]:
    cfg = os.path.join(REPO, "ros_ws", "src", "train_core", "config")
    return [{"label": f"shipped {bag}", "bag": os.path.join(REPO, "bags", bag),
             "line": os.path.join(cfg, "lines", f"{line}.yaml"),
             "train_file": os.path.join(cfg, "trains", f"{train}.yaml"), "train": bag}
            for bag, line, train in SHIPPED]


def analyse(d: str, out: str, only: list | None) -> None:
    from train_core.progress import track

    import train_estimation.core.offline.diagnose as dmod
    import train_estimation.core.offline.identify as imod
    from train_estimation.tools import fleet_dask as runner

    bags = json.load(open(os.path.join(d, "bags.json")))
    if only:
        bags = [b for b in bags if any(o in b["label"] for o in only)]
    captured = {}
    diag0, ident0 = dmod.diagnose, imod.identify

    spent = {}  # CPU s of identify and diagnose within the bag's analysis

    def diag(*a, **k):
        c = time.process_time()
        r = diag0(*a, **k)
        spent["diagnose"] = time.process_time() - c
        captured["diagnose"] = r.to_json()
        return r

    def ident(*a, **k):
        c = time.process_time()
        r = ident0(*a, **k)
        spent["identify"] = time.process_time() - c
        captured["identify"] = _plain(r)
        return r

    dmod.diagnose, imod.identify = diag, ident
    runner.analyse_bag(dict(bags[0], time=None))  # warm-up: imports, caches of the interpreter
    res = {"load_before": os.getloadavg()[0], "bags": []}
    print(f"load average {res['load_before']:.2f}", flush=True)
    for b in track(bags, "bag_cpu: bags"):
        captured.clear()
        spent.clear()
        c0, w0 = time.process_time(), time.perf_counter()
        row = runner.analyse_bag(dict(b, time=None))
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
        res["bags"].append({"label": b["label"], "cpu": cpu, "wall": wall, "row": row.to_json(),
                            "cpu_parts": dict(spent), **captured})
        parts = ", ".join(f"{k} {v:.2f}" for k, v in spent.items())
        print(f"{b['label']}: {cpu:.2f} CPU s ({parts}), {wall:.2f} wall s, {row.cause}",
              flush=True)
    res["load_after"] = os.getloadavg()[0]
    dmod.diagnose, imod.identify = diag0, ident0
    from train_estimation.core.offline.diagnose.result import jsonable

    json.dump(jsonable(res), open(out, "w"))


def _plain(x):
    """Dataclasses as dicts, recursively (for the JSON of the captured results)."""
    import dataclasses

    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return {f.name: _plain(getattr(x, f.name)) for f in dataclasses.fields(x)}
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    return x


def _diff(a, b, path, worst):
    """Largest relative difference of numbers; any difference in structure or strings is
    recorded as inf."""
    if isinstance(a, dict) and isinstance(b, dict):
        if set(a) != set(b):
            worst.append((math.inf, f"{path}: keys {sorted(set(a) ^ set(b))}"))
        for k in set(a) & set(b):
            _diff(a[k], b[k], f"{path}.{k}", worst)
    elif isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            worst.append((math.inf, f"{path}: lengths {len(a)} {len(b)}"))
        for i, (x, y) in enumerate(zip(a, b)):
            _diff(x, y, f"{path}[{i}]", worst)
    elif isinstance(a, (int, float)) and isinstance(b, (int, float)) and \
            not isinstance(a, bool):
        if a == b or (a != a and b != b):
            return
        den = max(abs(a), abs(b))
        worst.append((abs(a - b) / den if den > 0 else math.inf, f"{path}: {a!r} {b!r}"))
    elif a != b:
        worst.append((math.inf, f"{path}: {a!r} {b!r}"))


def compare(fa: str, fb: str) -> int:
    A, B = json.load(open(fa)), json.load(open(fb))
    print(f"load average: A {A['load_before']:.1f}-{A['load_after']:.1f}, "
          f"B {B['load_before']:.1f}-{B['load_after']:.1f}")
    print("| bag | A (CPU s) | B (CPU s) | B / A | max rel. difference of the reports |")
    print("|---|---|---|---|---|")
    overall = []
    ta = tb = 0.0
    for x, y in zip(A["bags"], B["bags"]):
        assert x["label"] == y["label"]
        worst = []
        for key in ("row", "diagnose", "identify"):
            _diff(x.get(key), y.get(key), key, worst)
        for w in ("seconds",):  # wall time in the row
            worst = [v for v in worst if not v[1].startswith(f"row.{w}")]
        m = max(worst, default=(0.0, ""))
        md = max((w for w in worst if not w[1].startswith("identify")), default=(0.0, ""))
        overall.append((m[0], x["label"], m[1]))
        overall.append((md[0], x["label"], md[1]))
        ta, tb = ta + x["cpu"], tb + y["cpu"]
        print(f"| {x['label']} | {x['cpu']:.2f} | {y['cpu']:.2f} | {y['cpu'] / x['cpu']:.2f} "
              f"| {m[0]:.1e} (diagnose and row: {md[0]:.1e}) |")
    print(f"| total | {ta:.2f} | {tb:.2f} | {tb / ta:.2f} | "
          f"{max(o[0] for o in overall):.1e} |")
    for o in sorted(overall, reverse=True)[:5]:
        if o[0] > 0:
            print(f"  {o[0]:.2e} {o[1]}: {o[2]}")
    return 0


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--make")
    p.add_argument("--run")
    p.add_argument("--out")
    p.add_argument("--only", nargs="*")
    p.add_argument("--compare", nargs=2)
    p.add_argument("--quick", action="store_true",
                   help="two cases made in a temporary folder and the shipped bags, "
                        "reports to --out")
    a = p.parse_args()
    if a.quick:
        import tempfile

        d = tempfile.mkdtemp(prefix="bag_cpu_")
        make(d, CASES[:2], fleet=False)
        analyse(d, a.out or os.path.join(d, "quick.json"), a.only)
    if a.make:
        make(a.make)
    if a.run:
        analyse(a.run, a.out, a.only)
    if a.compare:
        return compare(*a.compare)
    return 0


if __name__ == "__main__":
    sys.exit(main())
