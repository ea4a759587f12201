#!/usr/bin/env python3
"""Latency at 1x real time: odometer reading received -> its estimate published (p50/p99), and
what a radio link with latency and jitter does to the estimates.

**Live** (per link: none, then ``--latency`` + Exp(``--jitter``) per message on odometer and
balise): starts the simulator (metro_demo, 1x, ``--duration`` s) and the ``robust_filter`` and
``gsma_estimator`` nodes on a private ROS domain (localhost only), stops them with SIGINT and
prints the latency each node measured on its steady clock (from the callback of the odometer
sample to the publication of the estimate stamped with it), split into waiting for the cycle's
other inputs (a sample is released once the control watermark passes it) and processing (the
runner's work and publishing, from the tick that released it); with the readings fused late
(``fused_late``: out of sequence, fused by rewinding) and the input dropped (any rejection). The
p50/p99 are the steady state; the first min_judged + 3 samples (the runner starts on the third
odometer sample and judges each clock's stamps once it has min_judged arrivals: they wait by
design, ~0.1-0.2 s) are reported apart as the start-up maximum.

**Offline** (accuracy with latency vs without): metro_demo simulated for ``--seeds`` seeds with
and without the link latency (the delays come from a generator of their own, so the same
messages are lost and only their arrival changes), each replayed in arrival order through the
runner the nodes use (``tests/test_replay.py``: a node publishes what the replay computes);
position RMSE against the truth, readings fused late and dropped, per estimator.

Usage::

    ./run bench latency                        # 60 s per link live, 10 seeds x 600 s offline
    ./run bench latency --duration 20 --seeds 3
    ./run bench latency --latency 0.05 --jitter 0.1
"""

from __future__ import annotations

import argparse
import ast
import os
import random
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import yaml
from train_core.progress import track  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
for _p in (ROOT / "ros_ws/src/train_sim", ROOT / "ros_ws/src/train_estimation",
           ROOT / "ros_ws/src/train_core"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

from bench_fuzz import make_adapter, position_errors  # noqa: E402
from train_core.procs import resolve_executable, stop_process  # noqa: E402

from train_estimation.core.online.replay import replay  # noqa: E402
from train_sim.scenario import load_scenario, scenario_path  # noqa: E402
from train_sim.world import simulate  # noqa: E402

NODES = ("robust_filter", "gsma_estimator")
OFFLINE = ("robust_filter", "kf")  # the two nodes' defaults


def scenario_with_link(path: Path, latency: float, jitter: float) -> Path:
    """metro_demo's YAML with the link's latency and jitter set (the simulator's input)."""
    doc = yaml.safe_load(scenario_path("metro_demo").read_text())
    doc["link"] = dict(doc.get("link") or {}, latency=latency, jitter=jitter)
    doc["name"] = "metro_demo_latency"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def run_live(scenario: str, duration: float, logs: Path) -> None:
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               ROS_DOMAIN_ID=str(random.randint(101, 200)), PYTHONUNBUFFERED="1")
    logs.mkdir(parents=True, exist_ok=True)
    procs = {}
    try:
        for exe in NODES:
            path = resolve_executable("train_estimation", exe)
            procs[exe] = subprocess.Popen(
                [path or sys.executable, *([] if path else ["-m", f"train_estimation.nodes.{exe}"]),
                 "--ros-args", "-r", "__ns:=/lat", "-p", "use_sim_time:=true",
                 "-p", "use_demo_line:=true"],
                env=env, stdout=open(logs / f"{exe}.log", "w"), stderr=subprocess.STDOUT)
        sim = resolve_executable("train_sim", "simulator")
        procs["simulator"] = subprocess.Popen(
            [sim, "--ros-args", "-r", "__ns:=/lat", "-p", f"scenario:={scenario}",
             "-p", "rate_factor:=1.0", "-p", f"duration:={duration}",
             "-p", f"wait_for_subscribers:={len(NODES)}"],
            env=env, stdout=open(logs / "simulator.log", "w"), stderr=subprocess.STDOUT)
        procs["simulator"].wait(duration + 120)
        time.sleep(1.0)
    finally:
        for p in procs.values():
            stop_process(p)


def _dict(text: str) -> dict:
    return {} if text.strip() == "none" else ast.literal_eval(text)  # the node's repr of a dict


def live_rows(link: str, logs: Path) -> list[str]:
    rows = []
    for exe in NODES:
        text = (logs / f"{exe}.log").read_text()
        m = re.search(r"p50 ([\d.]+) ms, p99 ([\d.]+) ms, max ([\d.]+) ms over (\d+) samples"
                      r" \(steady state; start-up: max ([\d.]+) ms.*?waiting for inputs p50 "
                      r"([\d.]+) ms, p99 ([\d.]+) ms; processing p50 ([\d.]+) ms, p99 ([\d.]+)",
                      text)
        c = re.search(r"rejected (.*); events (.*)$", text, re.M)
        if not m or not c:
            rows.append(f"| {exe} | {link} | - | - | - | - | - | - | - | - | - | "
                        f"(no latency line; see {logs / (exe + '.log')}) |")
            continue
        g = m.groups()
        rejected, events = _dict(c.group(1)), _dict(c.group(2))
        late = sum(v for k, v in events.items() if k.endswith("fused_late"))
        rows.append(f"| {exe} | {link} | {g[0]} | {g[1]} | {g[2]} | {g[3]} | {g[5]}/{g[6]} | "
                    f"{g[7]}/{g[8]} | {g[4]} | {late} | {sum(rejected.values())} | "
                    f"{c.group(1)}; {c.group(2)} |")
    return rows


def offline(seeds: int, duration: float, latency: float, jitter: float) -> list[str]:
    base = load_scenario("metro_demo")
    lagged = base.with_changes(link=replace(base.link, latency=latency, jitter=jitter))
    acc = {(name, lag): [] for name in OFFLINE for lag in (False, True)}
    for seed in track(range(seeds), "latency"):
        for lag, sc in ((False, base), (True, lagged)):
            res = simulate(sc, seed=seed, duration=duration)
            events = [(topic, stamp, fields, t_recv)
                      for t_recv, topic, stamp, fields in res.received_events()]
            n_odo = sum(1 for e in events if e[0] == "odometer")
            for name in OFFLINE:
                outs, runner = replay(events, make_adapter(sc, name), 1 / sc.odometer_rate)
                e = position_errors(outs, res, sc.stamp_epoch, 0.0)
                late = sum(v for k, v in runner.events.items() if k.endswith("fused_late"))
                acc[name, lag].append((float(np.sqrt(np.mean(e ** 2))), late,
                                       sum(runner.rejected.values()), n_odo))
    rows = []
    for name in OFFLINE:
        r0, r1 = np.array(acc[name, False]), np.array(acc[name, True])
        d = r1[:, 0] - r0[:, 0]
        se = d.std(ddof=1) / np.sqrt(len(d)) if len(d) > 1 else float("nan")
        rows.append(f"| {name} | {r0[:, 0].mean():.3f} | {r1[:, 0].mean():.3f} | "
                    f"{d.mean():+.2g} +- {se:.1g} | {int(r1[:, 1].sum())} | "
                    f"{int(r1[:, 2].sum())} | {int(r0[:, 2].sum())} | {int(r1[:, 3].sum())} |")
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0, help="s of each live run")
    ap.add_argument("--latency", type=float, default=0.02,
                    help="s, fixed link delay of odometer and balise messages")
    ap.add_argument("--jitter", type=float, default=0.05,
                    help="s, mean of the exponential random delay (> period/2: reordering)")
    ap.add_argument("--seeds", type=int, default=10, help="offline seeds (0: no offline part)")
    ap.add_argument("--offline-duration", type=float, default=600.0, help="s per offline run")
    ap.add_argument("--no-live", action="store_true", help="offline part only")
    args = ap.parse_args(argv)
    logs = Path(tempfile.mkdtemp(prefix="bench_latency_"))
    lag = f"{1e3 * args.latency:g} ms + Exp({1e3 * args.jitter:g} ms)"
    if not args.no_live:
        links = (("none", "metro_demo"),
                 (lag, str(scenario_with_link(logs / "metro_demo_latency.yaml", args.latency,
                                              args.jitter))))
        rows = []
        for i, (name, scenario) in enumerate(links):
            run_live(scenario, args.duration, logs / f"link{i}")
            rows += live_rows(name, logs / f"link{i}")
        print(f"metro_demo at 1x for {args.duration:g} s per link (logs in {logs})\n")
        print("| node | link latency | p50 (ms) | p99 (ms) | max (ms) | samples | "
              "waiting p50/p99 (ms) | processing p50/p99 (ms) | start-up max (ms) | "
              "fused late | dropped | rejected; events |")
        print("|---|---|---|---|---|---|---|---|---|---|---|---|")
        print("\n".join(rows))
    if args.seeds > 0:
        print(f"\nAccuracy with link latency {lag} vs without, offline: metro_demo, "
              f"{args.seeds} seeds x {args.offline_duration:g} s, replayed in arrival order "
              "(position RMSE in m, mean over seeds; difference with its standard error)\n")
        print("| estimator | RMSE, no latency | RMSE, latency | difference | fused late | "
              "dropped (latency) | dropped (none) | odometer received |")
        print("|---|---|---|---|---|---|---|---|")
        print("\n".join(offline(args.seeds, args.offline_duration, args.latency, args.jitter)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
