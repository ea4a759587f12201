#!/usr/bin/env python3
"""Benchmark of `fleet`: throughput on Dask and consensus accuracy.

    ./run bench fleet [--trains 8] [--runs 2] [--degraded 2] [--stops 1] [--timing-bags 6]
                      [--draws 20] [--seed 3] [--permille 5] [--f-first 0.85] [--f-last 0.75]
                      [--no-timing]
    ./run bench fleet --day [--day-trains 4] [--day-runs 4] [--seed 3]
    ./run bench fleet --quick     (about 2 min: 4 trains x 2 runs, 2 timing bags, 5 draws)


1. A fleet from ``train_sim.fleet`` (trains x runs on two lines, the hidden map error on
   ``north``, degraded brakes on the first --degraded trains) is written once.
2. Throughput: the same --timing-bags bags are analysed (check_bag + identify + diagnose, no
   cache) on a LocalCluster of 1 and then of 2 worker processes, in this one run (each cluster
   started and its workers' imports done before the clock starts): bags per minute each and
   the ratio (the machine's other load is printed beside it).
3. Accuracy against the number of trains: every bag is analysed once (2 workers); then for
   n trains (always including degraded trains in proportion) --draws random subsets of the
   fleet's trains are given to the consensus: the map error right (exactly one map error, on
   north, overlapping the hidden section by >= 50 %) and the train alerts right (exactly the
   degraded trains of the subset). The subsets are drawn from one simulated fleet: they share
   runs, so the rates are of the consensus on these runs, not of independent fleets.

--day: a scaled-down simulated day instead. A railway's day is 100 trains x 20 runs of 10
minutes (2,000 bags); --day-trains x --day-runs of them (default 4 x 4 = 16 bags, 0.8 % of the
day) are written by ``train_sim.fleet`` with three stations per run (10-minute bags: 6-8
minutes of driving and station stops, then standing at the terminus; the map error and
--degraded trains as above) and analysed as ``fleet`` does (check_bag's topic health +
identify + diagnose, no cache) on a LocalCluster of 1 and then of 2 single-threaded worker
processes, in this one run: bags per minute, seconds per bag, the workers' CPU time per bag,
each worker's peak memory (RSS), and the time of 2,000 bags extrapolated from each rate with
its arithmetic. On a quiet 2-core machine the default takes about 10 minutes.

Prints the tables (and writes benchmarks/out/fleet.md, --day: benchmarks/out/fleet_day.md).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = os.path.join(HERE, "out")

from train_estimation.core.offline.fleet import consensus  # noqa: E402
from train_estimation.tools import fleet as tool  # noqa: E402
from train_estimation.tools import fleet_dask as runner  # noqa: E402
from train_estimation.tools.fleet_row import consensus_rows  # noqa: E402
from train_sim.fleet import FleetSpec, write_fleet  # noqa: E402


def tasks_of(d: str) -> list[dict]:
    tasks = tool.read_manifest(os.path.join(d, "manifest.csv"))
    for t in tasks:
        t["key"] = tool.content_key(t)
    return tasks


def _warm() -> bool:
    """Imports a task needs (numpy, scipy, the project's modules), done before timing."""
    import train_estimation.core.offline.diagnose  # noqa: F401
    import train_estimation.core.offline.identify  # noqa: F401
    import train_estimation.tools.check_bag  # noqa: F401

    return True


def _peak_rss_mb() -> float:
    """This process's peak resident memory (MB; Linux reports ru_maxrss in KiB)."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def throughput(tasks, workers: int, memory: bool = False):
    """Wall time of the bags on a started, warmed-up cluster (start-up excluded) and bags per
    minute; with ``memory`` also each worker's peak RSS (MB) after the run and the CPU time
    the workers spent (s, all workers)."""
    from dask.distributed import Client

    with runner.local_cluster(workers) as cluster, Client(cluster) as client:
        client.run(_warm)
        c0 = client.run(time.process_time)
        t0 = time.perf_counter()
        rows = runner.run_tasks(tasks, workers, None, progress=False, client=client)
        wall = time.perf_counter() - t0
        c1 = client.run(time.process_time)
        rss = sorted(client.run(_peak_rss_mb).values()) if memory else []
    assert not any(r.error for r in rows), [r.error for r in rows if r.error]
    if memory:
        return wall, 60.0 * len(tasks) / wall, rss, sum(c1[w] - c0[w] for w in c1)
    return wall, 60.0 * len(tasks) / wall


DAY_BAGS = 2000  # 100 trains x 20 runs of 10 minutes


def day(a, say) -> None:
    """The --day mode (module docstring)."""
    with tempfile.TemporaryDirectory(prefix="bench_fleet_day_") as d:
        t0 = time.perf_counter()
        spec = FleetSpec(trains=a.day_trains, runs=a.day_runs,
                         degraded=min(a.degraded, a.day_trains), seed=a.seed, stops=3,
                         dwell=40.0, map_error=("north", 1000.0, 1400.0, a.permille),
                         f_first=a.f_first, f_last=a.f_last)
        write_fleet(d, spec)
        tasks = tasks_of(d)
        n = len(tasks)
        say(f"./run bench fleet --day --day-trains {a.day_trains} --day-runs {a.day_runs} "
            f"--seed {a.seed} ({time.strftime('%Y-%m-%d', time.gmtime())})")
        say(f"day sample: {a.day_trains} trains x {a.day_runs} runs = {n} bags of 600 s "
            f"({100.0 * n / DAY_BAGS:.1f} % of a {DAY_BAGS}-bag day), written in "
            f"{time.perf_counter() - t0:.0f} s")
        say(f"machine: {os.cpu_count()} cores, load average before timing "
            f"{os.getloadavg()[0]:.2f}")
        say()
        res = {w: throughput(tasks, w, memory=True) for w in (1, 2)}
        say("| workers | bags | wall (s) | bags per minute | s per bag per worker "
            "| CPU s per bag | peak RSS per worker (MB) | 2,000 bags (extrapolated) |")
        say("|---|---|---|---|---|---|---|---|")
        for w, (wall, rate, rss, cpu) in res.items():
            say(f"| {w} | {n} | {wall:.0f} | {rate:.2f} | {w * wall / n:.1f} | {cpu / n:.1f} | "
                f"{', '.join(f'{m:.0f}' for m in rss)} | {DAY_BAGS / rate:.0f} min |")
        say()
        cpu = res[1][3] / n
        say(f"CPU time: {cpu:.1f} s per bag (1 worker); 2 workers with a core each: "
            f"{DAY_BAGS} x {cpu:.1f} s / 2 / 60 = {DAY_BAGS * cpu / 120.0:.0f} min for "
            f"{DAY_BAGS} bags (the wall times above include the machine's other load)")
        r1, r2 = res[1][1], res[2][1]
        say(f"extrapolation: {DAY_BAGS} bags / {r1:.2f} bags per minute = "
            f"{DAY_BAGS / r1:.0f} min on 1 worker; {DAY_BAGS} / {r2:.2f} = "
            f"{DAY_BAGS / r2:.0f} min ({DAY_BAGS / r2 / 60.0:.1f} h) on 2 workers "
            f"(target < 60 min); 2 / 1 workers {r2 / r1:.2f}x (target >= 1.8x); load average "
            f"after {os.getloadavg()[0]:.2f}")


def judge(rows, truth, trains) -> tuple[bool, bool]:
    sub = [r for r in rows if r.train in trains]
    res = consensus(consensus_rows(sub))
    t = truth["map_error"]
    ok_map = len(res.map_errors) == 1 and res.map_errors[0]["line"] == t["line"] and (
        min(res.map_errors[0]["end"], t["end"]) - max(res.map_errors[0]["start"], t["start"])
        >= 0.5 * (t["end"] - t["start"]))
    want = set(truth["degraded_trains"]) & set(trains)
    ok_trains = {a["train"] for a in res.train_alerts} == want
    return ok_map, ok_trains


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trains", type=int, default=8)
    p.add_argument("--runs", type=int, default=2)
    p.add_argument("--degraded", type=int, default=2)
    p.add_argument("--stops", type=int, default=1, choices=(1, 2))
    p.add_argument("--timing-bags", type=int, default=6)
    p.add_argument("--draws", type=int, default=20)
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--permille", type=float, default=5.0, help="size of the map error")
    p.add_argument("--f-first", type=float, default=0.85, help="degraded f in the first run")
    p.add_argument("--f-last", type=float, default=0.75, help="degraded f in the last run")
    p.add_argument("--no-timing", action="store_true", help="accuracy only")
    p.add_argument("--day", action="store_true",
                   help="a scaled-down simulated day of 10-minute bags on 1 and 2 workers: "
                        "bags per minute, peak memory per worker and the extrapolation to "
                        "2,000 bags (about 10 minutes with the defaults)")
    p.add_argument("--day-trains", type=int, default=4, help="--day: trains (default 4)")
    p.add_argument("--day-runs", type=int, default=4, help="--day: runs per train (default 4)")
    p.add_argument("--quick", action="store_true",
                   help="about 2 min: 4 trains x 2 runs (one degraded), 2 timing bags, 5 "
                        "draws (each option given overrides); written to fleet_quick.md")
    if p.parse_known_args()[0].quick:  # the quick values as defaults: given ones win
        p.set_defaults(trains=4, degraded=1, timing_bags=2, draws=5)
    a = p.parse_args()
    lines = []

    def say(s=""):
        print(s, flush=True)
        lines.append(s)

    if a.day:
        day(a, say)
        os.makedirs(OUT, exist_ok=True)
        with open(os.path.join(OUT, "fleet_day.md"), "w") as fh:
            fh.write("\n".join(lines) + "\n")
        return 0

    with tempfile.TemporaryDirectory(prefix="bench_fleet_") as d:
        t0 = time.perf_counter()
        spec = FleetSpec(trains=a.trains, runs=a.runs, degraded=a.degraded, seed=a.seed,
                         stops=a.stops, map_error=("north", 1000.0, 1400.0, a.permille),
                         f_first=a.f_first, f_last=a.f_last)
        truth = write_fleet(d, spec)
        tasks = tasks_of(d)
        say(f"fleet: {a.trains} trains x {a.runs} runs ({len(tasks)} bags, "
            f"{'200 s' if a.stops == 1 else '360 s'} each), map error {truth['map_error']}, "
            f"degraded {truth['degraded_trains']} (f {a.f_first} -> {a.f_last}); written in "
            f"{time.perf_counter() - t0:.0f} s")
        say(f"machine: {os.cpu_count()} cores, load average before timing "
            f"{os.getloadavg()[0]:.2f}")
        say()
        if not a.no_timing:
            sub = tasks[:a.timing_bags]
            w1, r1 = throughput(sub, 1)
            w2, r2 = throughput(sub, 2)
            say("| workers | bags | wall (s) | bags per minute |")
            say("|---|---|---|---|")
            say(f"| 1 | {len(sub)} | {w1:.1f} | {r1:.1f} |")
            say(f"| 2 | {len(sub)} | {w2:.1f} | {r2:.1f} |")
            say(f"ratio 2 / 1 workers: {r2 / r1:.2f} (load average after: "
                f"{os.getloadavg()[0]:.2f})")
            say()
        t1 = time.perf_counter()
        rows = runner.run_tasks(tasks, 2, None, progress=False)
        say(f"all {len(rows)} bags analysed on 2 workers in {time.perf_counter() - t1:.0f} s "
            f"({sum(1 for r in rows if r.error)} failed)")
        say()
        all_trains = truth_trains = sorted({r.train for r in rows})
        deg = truth["degraded_trains"]
        rng = np.random.default_rng(a.seed)
        say("| trains | degraded among them | draws | map error right | train alerts right "
            "| both |")
        say("|---|---|---|---|---|---|")
        for n in range(3, len(all_trains) + 1):
            n_deg = max(1, round(n * len(deg) / len(all_trains)))
            nom = [t for t in truth_trains if t not in deg]
            draws = a.draws if n < len(all_trains) else 1
            res = []
            for _ in range(draws):
                pick = list(rng.choice(deg, size=min(n_deg, len(deg)), replace=False)) + list(
                    rng.choice(nom, size=n - min(n_deg, len(deg)), replace=False))
                res.append(judge(rows, truth, pick))
            m = np.mean([r[0] for r in res])
            t = np.mean([r[1] for r in res])
            b = np.mean([r[0] and r[1] for r in res])
            say(f"| {n} | {min(n_deg, len(deg))} | {draws} | {100 * m:.0f} % | {100 * t:.0f} % "
                f"| {100 * b:.0f} % |")
    os.makedirs(OUT, exist_ok=True)
    with open(os.path.join(OUT, "fleet_quick.md" if a.quick else "fleet.md"), "w") as fh:
        fh.write("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
