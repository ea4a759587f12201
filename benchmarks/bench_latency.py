#!/usr/bin/env python3
"""Latency at 1x real time: odometer reading received -> its estimate published (p50/p99).

Starts the simulator (metro_demo, 1x, ``--duration`` s) and the ``robust_filter`` and
``gsma_estimator`` nodes on a private ROS domain (localhost only), stops them with SIGINT and
prints the latency each node measured on its steady clock (from the callback of the odometer
sample to the publication of the estimate stamped with it), with the counts of accepted and
rejected input and of late readings fused by rewinding. The p50/p99 are the steady state, split
into waiting for the cycle's other inputs (a sample is released once the control watermark
passes it) and processing (the runner's work and publishing, from the tick that released it); the
first min_judged + 3 samples (the runner starts on the third odometer sample and judges each
clock's stamps once it has min_judged arrivals: they wait by design, ~0.1-0.2 s) are reported
apart as the start-up maximum.

Usage::

    ./run bench latency                 # 60 s
    ./run bench latency --duration 20
"""

from __future__ import annotations

import argparse
import os
import random
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
for _p in (ROOT / "ros_ws/src/train_sim", ROOT / "ros_ws/src/train_estimation"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

from train_core.procs import resolve_executable, stop_process  # noqa: E402

NODES = ("robust_filter", "gsma_estimator")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0)
    args = ap.parse_args(argv)
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               ROS_DOMAIN_ID=str(random.randint(101, 200)), PYTHONUNBUFFERED="1")
    logs = Path(tempfile.mkdtemp(prefix="bench_latency_"))
    procs = {}
    try:
        for exe in NODES:
            path = resolve_executable("train_estimation", exe)
            procs[exe] = subprocess.Popen(
                [path or sys.executable, *([] if path else ["-m", f"train_estimation.nodes.{exe}"]),
                 "--ros-args", "-r", "__ns:=/lat", "-p", "use_sim_time:=true"],
                env=env, stdout=open(logs / f"{exe}.log", "w"), stderr=subprocess.STDOUT)
        sim = resolve_executable("train_sim", "simulator")
        procs["simulator"] = subprocess.Popen(
            [sim, "--ros-args", "-r", "__ns:=/lat", "-p", "scenario:=metro_demo",
             "-p", "rate_factor:=1.0", "-p", f"duration:={args.duration}",
             "-p", f"wait_for_subscribers:={len(NODES)}"],
            env=env, stdout=open(logs / "simulator.log", "w"), stderr=subprocess.STDOUT)
        procs["simulator"].wait(args.duration + 120)
        time.sleep(1.0)
    finally:
        for p in procs.values():
            stop_process(p)
    print(f"metro_demo at 1x for {args.duration:g} s (logs in {logs})\n")
    print("| node | p50 (ms) | p99 (ms) | max (ms) | samples | waiting p50/p99 (ms) | "
          "processing p50/p99 (ms) | start-up max (ms) | rejected | events |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for exe in NODES:
        text = (logs / f"{exe}.log").read_text()
        m = re.search(r"p50 ([\d.]+) ms, p99 ([\d.]+) ms, max ([\d.]+) ms over (\d+) samples"
                      r" \(steady state; start-up: max ([\d.]+) ms.*?waiting for inputs p50 "
                      r"([\d.]+) ms, p99 ([\d.]+) ms; processing p50 ([\d.]+) ms, p99 ([\d.]+)",
                      text)
        c = re.search(r"rejected (.*); events (.*)$", text, re.M)
        if not m:
            print(f"| {exe} | - | - | - | - | - | - | - | (no latency line; see log) | |")
            continue
        g = m.groups()
        print(f"| {exe} | {g[0]} | {g[1]} | {g[2]} | {g[3]} | {g[5]}/{g[6]} | {g[7]}/{g[8]} | "
              f"{g[4]} | {c.group(1) if c else '?'} | {c.group(2) if c else '?'} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
