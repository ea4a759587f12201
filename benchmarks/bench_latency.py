#!/usr/bin/env python3
"""Latency at 1x real time: odometer reading received -> its estimate published (p50/p99), and
what a radio link with latency and jitter does to the estimates.

**Live** (per link: none, then ``--latency`` + Exp(``--jitter``) per message on odometer and
balise): one node algorithm at a time -- ``robust_filter``, then ``gsma_estimator`` once per
algorithm (``--algorithms``: gsma, sma, rbpf, qgrbpf, kf) -- runs with the simulator (metro_demo,
1x, ``--duration`` s) and a bare rclpy echo node (``latency_echo.py``: publishes the same two
messages per reading with no estimation, the floor) on a private ROS domain (localhost only),
so that on a small machine the estimators do not wait for each other's cores and each row has
the floor measured beside it, in the same run. Each run is stopped with SIGINT and the
latency each node measured on its steady clock is printed (from the callback of the odometer
sample to the publication of the estimate stamped with it), split into waiting for the cycle's
other inputs (a sample is released once the control watermark passes it) and processing (the
runner's work and publishing, from the tick that released it); with the readings fused late
(``fused_late``: out of sequence, fused by rewinding) and the input dropped (any rejection). The
p50/p99 are the steady state; the first min_judged + 3 samples (the runner starts on the third
odometer sample and judges each clock's stamps once it has min_judged arrivals: they wait by
design, ~0.1-0.2 s) are reported apart as the start-up maximum. ``--together`` runs every
estimator node at once instead (one floor for all: the nodes then contend for the cores).
``--clocks`` (default ``wall,sim``) runs each group once per clock the nodes (estimators and
echo alike) run on: the system clock (``use_sim_time`` false, as on a train's computer, which
has no /clock; the simulator at 1x still publishes /clock, which they then do not take) and the
simulator's /clock (``use_sim_time`` true; its rate: ``--clock-period``, the simulator's
``clock_period``). Each row gives its p50 and p99 over its own floor's and each process's CPU
per s of the run (``/proc``).

With ``--trace`` the estimator nodes record their callbacks and their executor's waits
(``train_core.realtime.CallbackTrace``) and each estimate's time is split into stages, each on
the steady clock and on the thread's CPU clock (wall above CPU: it waited for a core); and what
/clock costs them (:func:`clock_costs`: CPU per /clock, how many readings queued behind one)
and each reading's wait in the node's queue before its callback and its time from DDS
reception to its estimate published (the subscriptions' MessageInfo stamps), the echo's beside.

**Stages** (in process, ``--stage-duration`` s of metro_demo, fed back to back, or at 1x real
time with ``--paced``): where an odometer callback's
CPU time goes, per estimator: the runner's input checks, the estimator's own calls, its
snapshots for rewinding, the rest of the runner, and the two output messages built; and, apart,
the garbage collection the node runs after publishing (``train_core.realtime``), with the heap
settled as the node settles it once built.

**Offline** (accuracy with latency vs without): metro_demo simulated for ``--seeds`` seeds with
and without the link latency (the delays come from a generator of their own, so the same
messages are lost and only their arrival changes), each replayed in arrival order through the
runner the nodes use (``tests/test_replay.py``: a node publishes what the replay computes);
position RMSE against the truth, readings fused late and dropped, per estimator.

Usage::

    ./run bench latency                        # 60 s per link live, 10 seeds x 600 s offline
    ./run bench latency --no-link --seeds 0    # every algorithm beside the floor, no link
    ./run bench latency --duration 20 --seeds 3
    ./run bench latency --latency 0.05 --jitter 0.1
    ./run bench latency --no-live --seeds 0 --profile 25   # where the in-process time goes
    ./run bench latency --no-live --seeds 0 --paced        # in process, fed at 1x real time
    ./run bench latency --no-link --seeds 0 --trace        # live, per stage, wall and CPU
    ./run bench latency --no-link --seeds 0 --clocks sim --clock-period 0   # /clock every step
    ./run bench latency --no-link --seeds 0 --clocks wall --realtime 50     # nodes SCHED_FIFO
"""

from __future__ import annotations

import argparse
import ast
import bisect
import glob
import json
import math
import os
import random
import re
import shutil
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
from train_core.realtime import TRACE_VARIABLE, collect_due, settle_heap  # noqa: E402

from train_estimation.core.online.replay import replay  # noqa: E402
from train_estimation.nodes.estimate_cdr import EstimateCdr  # noqa: E402
from train_sim.scenario import load_scenario, scenario_path  # noqa: E402
from train_sim.world import simulate  # noqa: E402

NODES = ("robust_filter", "gsma_estimator")
OFFLINE = ("robust_filter", "kf")  # the two nodes' defaults
ALGORITHMS = ("gsma", "sma", "rbpf", "qgrbpf", "kf")  # gsma_estimator's `algorithm`
ECHO = "echo (bare rclpy)"
CLOCKS = {"wall": "system", "sim": "simulated"}  # --clocks -> the table's "node clock"


def live_nodes(algorithms) -> list[tuple[str, str | None, list[str]]]:
    """(label, executable, extra ROS arguments): robust_filter, gsma_estimator once per
    algorithm (own node name and output topics, the same inputs), and the bare echo node."""
    nodes = [("robust_filter", "robust_filter", [])]
    for alg in algorithms:
        nodes.append((f"gsma_estimator ({alg})", "gsma_estimator",
                      ["-r", f"__node:=est_{alg}", "-p", f"algorithm:={alg}",
                       "-r", f"estimate/gsma:=estimate/{alg}", "-r", f"odom/gsma:=odom/{alg}"]))
    nodes.append((ECHO, None, []))
    return nodes


def scenario_with_link(path: Path, latency: float, jitter: float) -> Path:
    """metro_demo's YAML with the link's latency and jitter set (the simulator's input)."""
    doc = yaml.safe_load(scenario_path("metro_demo").read_text())
    doc["link"] = dict(doc.get("link") or {}, latency=latency, jitter=jitter)
    doc["name"] = "metro_demo_latency"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def _log_name(label: str) -> str:
    return re.sub(r"[^a-z0-9_]+", "_", label.lower()).strip("_") + ".log"


def _cpu_seconds(pid: int) -> float:
    """s of CPU (user + system) the process has used so far (/proc; nan if unreadable)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return math.nan


def run_live(scenario: str, duration: float, logs: Path, nodes, trace: bool = False,
             sim_time: bool = True, clock_period: float | None = None,
             realtime: int = 0) -> dict:
    """One live run; returns each process's CPU per s of the run (ms/s; from the simulator's
    first progress line, 5 % into the run, to its end: the nodes' start-up left out).
    ``sim_time``: the nodes (estimators and echo alike) on the simulator's /clock
    (``use_sim_time``) or on the system clock, as a train's computer runs them (the simulator
    at 1x keeps publishing /clock, which they then do not subscribe to). ``clock_period``:
    the simulator's parameter (None: its default). ``realtime`` > 0: the estimator and echo
    nodes start under ``chrt -f realtime`` (SCHED_FIFO at that priority, every thread of the
    process, the middleware's included, as a launch ``prefix`` sets it on a train's computer);
    the simulator, the world, keeps the default scheduler."""
    prefix = ["chrt", "-f", str(realtime)] if realtime > 0 else []
    # domain 91-101: above the test sessions' (conftest.py: 1-90 + the worker's index) and
    # within the 0-101 whose DDS ports stay below Linux's ephemeral range (ROS 2 docs, "About
    # Domain ID": above it a participant's port can be one the kernel gave another socket)
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               ROS_DOMAIN_ID=str(random.randint(91, 101)), PYTHONUNBUFFERED="1")
    env.pop(TRACE_VARIABLE, None)
    if trace:  # the estimator nodes trace their callbacks (train_core.realtime.CallbackTrace)
        env[TRACE_VARIABLE] = str(logs)
    logs.mkdir(parents=True, exist_ok=True)
    procs = {}
    try:
        for label, exe, extra in nodes:
            if exe is None:  # the echo node: a script of this folder
                cmd = [sys.executable, str(Path(__file__).with_name("latency_echo.py"))]
            else:
                path = resolve_executable("train_estimation", exe)
                cmd = [path or sys.executable,
                       *([] if path else ["-m", f"train_estimation.nodes.{exe}"])]
            procs[label] = subprocess.Popen(
                [*prefix, *cmd, "--ros-args", "-r", "__ns:=/lat",
                 "-p", f"use_sim_time:={'true' if sim_time else 'false'}",
                 *([] if exe is None else ["-p", "use_demo_line:=true"]), *extra],
                env=env, stdout=open(logs / _log_name(label), "w"), stderr=subprocess.STDOUT)
        sim = resolve_executable("train_sim", "simulator")
        n_est = sum(1 for _, exe, _ in nodes if exe is not None)
        procs["simulator"] = subprocess.Popen(
            [sim, "--ros-args", "-r", "__ns:=/lat", "-p", f"scenario:={scenario}",
             "-p", "rate_factor:=1.0", "-p", f"duration:={duration}",
             "-p", f"wait_for_subscribers:={n_est}",
             *([] if clock_period is None else ["-p", f"clock_period:={clock_period}"])],
            env=env, stdout=open(logs / "simulator.log", "w"), stderr=subprocess.STDOUT)
        sim, t_end = procs["simulator"], time.monotonic() + duration + 180
        while sim.poll() is None and time.monotonic() < t_end and \
                "simulated" not in (logs / "simulator.log").read_text():
            time.sleep(0.1)
        first = {label: (_cpu_seconds(p.pid), time.monotonic()) for label, p in procs.items()}
        last = dict(first)
        while sim.poll() is None and time.monotonic() < t_end:
            last = {label: (_cpu_seconds(p.pid), time.monotonic()) for label, p in procs.items()}
            time.sleep(0.2)
        time.sleep(1.0)
    finally:
        for p in procs.values():
            stop_process(p)
    return {label: 1e3 * (last[label][0] - c0) / (last[label][1] - t0)
            if last[label][1] > t0 else math.nan for label, (c0, t0) in first.items()}


def _dict(text: str) -> dict:
    return {} if text.strip() == "none" else ast.literal_eval(text)  # the node's repr of a dict


def _echo_line(text: str):
    m = re.search(r"echo published: p50 ([\d.]+) ms, p99 ([\d.]+) ms, max ([\d.]+) ms "
                  r"over (\d+) samples", text)
    return m.groups() if m else None


def live_rows(link: str, logs: Path, nodes, clock: str = "simulated",
              cpu: dict | None = None) -> list[str]:
    """One row per node of a run (``logs``: its logs), the floor (the echo node of the same
    run) beside each estimator's, with the ratios of the node's p50 and p99 to the floor's
    and each one's CPU per s of the run (``cpu``: label -> ms/s, :func:`run_live`)."""
    cpu = cpu or {}
    echo = next((lb for lb, exe, _ in nodes if exe is None), None)
    floor = None
    if echo is not None:
        log = logs / _log_name(echo)
        floor = _echo_line(log.read_text()) if log.exists() else None
    c_floor = cpu.get(echo, math.nan)
    rows = []
    for label, exe, _ in nodes:
        log = logs / _log_name(label)
        text = log.read_text() if log.exists() else ""
        if exe is None:
            continue
        fl = f"{floor[0]}/{floor[1]}" if floor else "-"
        c = (f"{cpu.get(label, math.nan):.0f} / {c_floor:.0f} / "
             f"{cpu.get('simulator', math.nan):.0f}")
        m = re.search(r"p50 ([\d.]+) ms, p99 ([\d.]+) ms, max ([\d.]+) ms over (\d+) samples"
                      r" \(steady state; start-up: max ([\d.]+) ms.*?waiting for inputs p50 "
                      r"([\d.]+) ms, p99 ([\d.]+) ms; processing p50 ([\d.]+) ms, p99 ([\d.]+)",
                      text)
        r = re.search(r"rejected (.*); events (.*)$", text, re.M)
        if not m or not r:
            rows.append(f"| {label} | {link} | {clock} | - | - | - | - | {fl} | - | - | - | - | "
                        f"- | {c} | - | (no latency line; see {log}) |")
            continue
        g = m.groups()
        ratio = (f"{float(g[0]) / float(floor[0]):.1f} / {float(g[1]) / float(floor[1]):.1f}"
                 if floor and float(floor[0]) > 0 and float(floor[1]) > 0 else "-")
        rejected, events = _dict(r.group(1)), _dict(r.group(2))
        late = sum(v for k, v in events.items() if k.endswith("fused_late"))
        rows.append(f"| {label} | {link} | {clock} | {g[0]} | {g[1]} | {g[2]} | {g[3]} | {fl} | "
                    f"{ratio} | {g[5]}/{g[6]} | {g[7]}/{g[8]} | {g[4]} | {c} | {late} | "
                    f"{sum(rejected.values())} | {r.group(1)}; {r.group(2)} |")
    if floor is None and echo is not None:
        rows.append(f"| {echo} | {link} | {clock} | - | - | - | - | - | - | - | - | - | "
                    f"- / {c_floor:.0f} | - | - | (no latency line; see "
                    f"{logs / _log_name(echo)}) |")
    return rows


LIVE_HEADER = ("| node | link latency | node clock | p50 (ms) | p99 (ms) | max (ms) | samples | "
               "floor p50/p99 (ms) | p50 / p99 over the floor's | waiting p50/p99 (ms) | "
               "processing p50/p99 (ms) | start-up max (ms) | "
               "CPU node / floor / simulator (ms/s) | fused late | dropped | "
               "rejected; events |\n" + "|---" * 16 + "|")


TRACE_STAGES = (
    ("reading's push", "the reading's callback from its start to the runner's push done"),
    ("to the release", "from there to the runner's advance in the callback that released the "
                       "estimate: the reading's own (its tick), or the cycle's command's (the "
                       "reading's tick that released nothing, the executor taking the command, "
                       "the command's push)"),
    ("advance", "the runner's advance that released the estimate"),
    ("messages", "TrainState and Odometry written and published"),
    ("total", "the reading's callback start -> the estimate's Odometry published"),
)


def trace_breakdown(marks: list, skip: int = 12) -> dict:
    """A live node's callback trace (``CallbackTrace`` marks: label, steady ns, thread CPU ns,
    value) split per estimate into ``TRACE_STAGES``, each a list of (wall, CPU) in s, over the
    estimates of a reading after the first ``skip`` (the start-up's); the executor's CPU per
    wait (``before_wait``: from a callback's end to the wait; ``after_wait``: from the
    wake-up to the next callback, s); ``cpu_per_s`` (in callbacks, in the executor between
    them) in s of CPU per s of the run; ``released_by`` (callback name -> count);
    ``from_reception``: per estimate, s from its reading's DDS reception (the subscription's
    MessageInfo, :meth:`~train_core.realtime.CallbackTrace.wrap`) to its Odometry published,
    the queue wait before the callback included (wall time)."""
    cbs, cur = [], None
    for m in marks:
        if m[0].startswith("B:"):
            cur = [m]
        elif m[0].startswith("E:"):
            if cur is not None:
                cbs.append(cur + [m])
            cur = None
        elif cur is not None:
            cur.append(m)
    readings = {}  # stamp -> (callback index, its "pushed" mark)
    for i, cb in enumerate(cbs):
        for j, m in enumerate(cb):
            if m[0] == "reading":
                readings[m[3]] = (i, next(x for x in cb[j:] if x[0] == "pushed"))
    out = {name: [] for name, _ in TRACE_STAGES}
    received = []  # s, the reading's DDS reception -> the estimate's Odometry published
    released, n = {}, 0
    for cb in cbs:
        ticks = [m for m in cb if m[0] in ("tick", "advanced")]
        for m in cb:
            if m[0] != "published" or m[3] not in readings:
                continue
            n += 1
            if n <= skip:
                continue
            ri, pushed = readings[m[3]]
            start = cbs[ri][0]
            # the tick of this callback that released the estimate: the last one before it
            tick, adv = [t for t in ticks if t[1] <= m[1]][-2:]
            for name, a, b in (("reading's push", start, pushed), ("to the release", pushed, tick),
                               ("advance", tick, adv), ("messages", adv, m),
                               ("total", start, m)):
                out[name].append(((b[1] - a[1]) * 1e-9, (b[2] - a[2]) * 1e-9))
            if isinstance(start[3], list | tuple) and start[3][1]:  # the MessageInfo stamps
                received.append((m[1] - start[1] + start[3][2] - start[3][1]) * 1e-9)
            name = cb[0][0][2:]
            released[name] = released.get(name, 0) + 1
    # the executor between callbacks: before its wait (the last callback's task retired, a
    # wait set built) and after it (the ready entities found, the message taken), CPU s
    before, after, last = [], [], None
    for m in marks:
        if m[0].startswith("E:") or m[0] == "woken":
            last = m
        elif m[0] == "wait" and last is not None and last[0].startswith("E:"):
            before.append((m[2] - last[2]) * 1e-9)
        elif m[0].startswith("B:") and last is not None and last[0] == "woken":
            after.append((m[2] - last[2]) * 1e-9)
    span = (marks[-1][1] - marks[0][1]) * 1e-9 if marks else 0.0
    in_cbs = sum((cb[-1][2] - cb[0][2]) * 1e-9 for cb in cbs)
    between = sum((b[0][2] - a[-1][2]) * 1e-9 for a, b in zip(cbs, cbs[1:]))
    return dict(out, before_wait=before, after_wait=after, released_by=released,
                from_reception=received,
                cpu_per_s=(in_cbs / span if span else float("nan"),
                           between / span if span else float("nan")))


def trace_rows(label: str, logs: Path) -> list[str]:
    """The per-stage row of each estimator node's trace in ``logs`` (medians, wall / CPU ms)."""
    rows = []
    for path in sorted(glob.glob(str(logs / "trace_*.json"))):
        b = trace_breakdown(json.loads(Path(path).read_text()))
        if not b["total"]:
            continue

        def med(v):
            w, c = np.median(np.asarray(v), axis=0) * 1e3
            return f"{w:.3f} / {c:.3f}"
        by = ", ".join(f"{k.split()[-1].rsplit('/', 1)[-1]} {v}"
                       for k, v in sorted(b["released_by"].items()))
        rows.append(f"| {label} | {len(b['total'])} | {by} | "
                    + " | ".join(med(b[name]) for name, _ in TRACE_STAGES)
                    + f" | {1e3 * np.median(b['before_wait']):.3f} / "
                    f"{1e3 * np.median(b['after_wait']):.3f} ({len(b['after_wait'])}) | "
                    f"{1e3 * b['cpu_per_s'][0]:.0f} / {1e3 * b['cpu_per_s'][1]:.0f} |")
    return rows


def clock_costs(marks: list, topic: str = "sub /clock", reading: str = "/odometer") -> dict:
    """What /clock costs a live node and what it does to the readings, from its callback trace:
    per wake-up of the executor (from ``woken`` to its next ``wait``: taking the messages,
    the callbacks, retiring them and building the next wait set) the callbacks it ran. Returns
    the thread's CPU of each wake-up that ran ``topic``'s callback alone (``alone``, s), of
    each of ``topic``'s callbacks (``callback``, s), their count per s of the run (``per_s``)
    and the CPU per s they cost (``cpu_per_s``: the wake-ups for ``topic`` alone, whole, and
    the callback's own time in the others); and for each callback of a topic named ``reading``
    (in any namespace) the time its
    message waited in the node's queue (``queue``: DDS reception -> callback start, s, from
    the MessageInfo stamps :meth:`~train_core.realtime.CallbackTrace.wrap` keeps) and whether
    a wake-up that ran ``topic``'s callback was under way in that time (``behind``:
    booleans)."""
    wakes, cur = [], None  # each wake-up: [woken mark, [(B, E) of its callbacks], wait mark]
    for m in marks:
        if m[0] == "woken":
            cur = [m, [], None]
        elif cur is None:
            continue
        elif m[0] == "wait":
            cur[2] = m
            wakes.append(cur)
            cur = None
        elif m[0].startswith("B:"):
            cur[1].append([m, None])
        elif m[0].startswith("E:") and cur[1] and cur[1][-1][1] is None:
            cur[1][-1][1] = m
    alone, callback, spans, in_mixed = [], [], [], 0.0
    for woken, cbs, wait in wakes:
        own = [(e[2] - b[2]) * 1e-9 for b, e in cbs if b[0] == "B:" + topic and e is not None]
        if own:  # the wake-up's steady span: the executor's work for it is in the way too
            spans.append((woken[1], wait[1]))
        callback += own
        if cbs and all(b[0] == "B:" + topic for b, _ in cbs):
            alone.append((wait[2] - woken[2]) * 1e-9)
        else:
            in_mixed += sum(own)
    span = (marks[-1][1] - marks[0][1]) * 1e-9 if marks else 0.0
    ends = [e for _, e in spans]  # in order, as the wake-ups are
    queue, behind = [], []
    for m in marks:
        if m[0].startswith("B:sub ") and m[0].endswith(reading) and \
                isinstance(m[3], list | tuple) and m[3][1]:
            _, received, now = m[3]
            queue.append((now - received) * 1e-9)
            arrived = m[1] - (now - received)  # the reception on the steady clock
            # a wake-up that ran the topic's callback and was under way while it queued
            i = bisect.bisect_right(ends, arrived)
            behind.append(i < len(spans) and spans[i][0] < m[1])
    return dict(alone=alone, callback=callback, queue=queue, behind=behind,
                per_s=len(callback) / span if span else math.nan,
                cpu_per_s=(sum(alone) + in_mixed) / span if span else math.nan)


def clock_rows(label: str, logs: Path) -> list[str]:
    """The /clock row of each estimator node's trace in ``logs`` (:func:`clock_costs`), with
    the echo node's queue wait (its log) beside the node's."""
    log = logs / _log_name(ECHO)
    m = re.search(r"queue wait .*?: p50 ([\d.]+) ms, p99 ([\d.]+) ms(?:; DDS reception -> "
                  r"echo published: p50 ([\d.]+) ms, p99 ([\d.]+) ms)?",
                  log.read_text() if log.exists() else "")
    floor = f"{m.group(1)} / {m.group(2)}" if m else "-"
    floor_whole = f"{m.group(3)} / {m.group(4)}" if m and m.group(3) else "-"
    rows = []
    for path in sorted(glob.glob(str(logs / "trace_*.json"))):
        marks = json.loads(Path(path).read_text())
        c = clock_costs(marks)
        whole = trace_breakdown(marks)["from_reception"]

        def q(v, p):
            return f"{1e3 * np.percentile(v, p):.3f}" if len(v) else "-"
        behind = [w for w, b in zip(c["queue"], c["behind"]) if b]
        rest = [w for w, b in zip(c["queue"], c["behind"]) if not b]
        rows.append(f"| {label} | {c['per_s']:.1f} | {q(c['callback'], 50)} | "
                    f"{q(c['alone'], 50)} / {q(c['alone'], 99)} ({len(c['alone'])}) | "
                    f"{1e3 * c['cpu_per_s']:.0f} | {q(c['queue'], 50)} / {q(c['queue'], 99)} | "
                    f"{floor} | {len(behind)} of {len(c['behind'])} | {q(behind, 50)} / "
                    f"{q(rest, 50)} | {q(whole, 50)} / {q(whole, 99)} | {floor_whole} |")
    return rows


def _timed(fn, acc: list, clock):
    """``fn`` that appends its own duration on ``clock`` to ``acc``."""
    def timed(*a, **k):
        t0 = clock()
        try:
            return fn(*a, **k)
        finally:
            acc.append(clock() - t0)
    return timed


def stages(names, duration: float, seed: int = 0, profile: int = 0, paced: bool = False
           ) -> tuple[list[str], list[str]]:
    """Where a callback's time goes, in process (CPU time of this thread, so another job's
    load does not count): metro_demo's received messages fed to each estimator's runner as
    the node feeds them (``estimator_node``: push, advance to the ready time, tick), and each
    estimate turned into the node's two messages (TrainState, Odometry, written as CDR bytes
    from templates as the node writes them; not published: the echo node's row measures
    publishing).
    Per odometer callback: p50 / p99 in ms of each stage; "step" = the core's estimator step
    inside the advance. ``paced``: each message fed at its arrival time at 1x real time
    (sleeping until then, as a live node waits for its next message) instead of right
    after the previous one, so that each callback starts with what the machine left in
    the caches meanwhile, as a live node's does. Returns the table's rows and, with
    ``profile`` = N > 0, per estimator the N functions of most own time in a second pass
    of the same messages under cProfile (its overhead inflates the many small calls:
    compare within a profile, not with the table)."""
    import cProfile
    import io
    import pstats

    from train_estimation.core.online.runner import EstimatorRunner

    sc = load_scenario("metro_demo")
    res = simulate(sc, seed=seed, duration=duration)
    events = [(topic, stamp, fields, t_recv)
              for t_recv, topic, stamp, fields in res.received_events()
              if topic in ("odometer", "control", "balise")]
    delay = 0.05  # the nodes' output_delay default (config/*.yaml)
    rows, profiles = [], []
    clock = time.thread_time
    for name in names:
        if profile > 0:
            prof = cProfile.Profile()
            runner = EstimatorRunner(make_adapter(sc, name), 1 / sc.odometer_rate)
            cdr = EstimateCdr(runner.adapter.source)
            prof.enable()
            for topic, stamp, fields, recv in events:
                runner.push(topic, stamp, fields, recv)
                for out in runner.advance_to(runner.ready_time(recv, delay, 4 * delay)) + \
                        runner.tick(recv):
                    _messages(out, cdr, runner)
            prof.disable()
            text = io.StringIO()
            pstats.Stats(prof, stream=text).strip_dirs().sort_stats("tottime") \
                .print_stats(profile)
            profiles.append(f"cProfile of {name}'s callbacks (top {profile} by own time):\n"
                            + text.getvalue().split("\n\n", 1)[-1].strip())
        adapter = make_adapter(sc, name)
        runner = EstimatorRunner(adapter, 1 / sc.odometer_rate)
        steps, snaps = [], []
        # the adapter's own work (the estimator: its input and output calls) and its
        # snapshots (kept by the runner to rewind for a late reading), timed from outside
        for attrs, acc in ((("control", "odometer", "balise", "output"), steps),
                           (("snapshot", "restore"), snaps)):
            for attr in attrs:
                setattr(adapter, attr, _timed(getattr(adapter, attr), acc, clock))
        cdr = EstimateCdr(runner.adapter.source)
        settle_heap()  # as the node, once built
        push, core, conv, total, core_steps, core_snaps, after = [], [], [], [], [], [], []
        w0, r0 = time.monotonic(), events[0][3]
        for topic, stamp, fields, recv in events:
            if paced:
                time.sleep(max(0.0, w0 + recv - r0 - time.monotonic()))
            del steps[:], snaps[:]
            t0 = clock()
            runner.push(topic, stamp, fields, recv)
            t1 = clock()
            outs = runner.advance_to(runner.ready_time(recv, delay, 4 * delay))
            outs += runner.tick(recv)
            t2 = clock()
            snapped = sum(snaps)  # (settle's copy below is after the estimate: not in it)
            for out in outs:
                _messages(out, cdr, runner)
            t3 = clock()
            runner.settle()  # as the node, after publishing
            collect_due()
            t4 = clock()
            if topic == "odometer" and outs:
                push.append(t1 - t0)
                core.append(t2 - t1)
                core_steps.append(sum(steps))
                core_snaps.append(snapped)
                conv.append(t3 - t2)
                total.append(t3 - t0)
                after.append(t4 - t3)

        def q(v):
            a = 1e3 * np.asarray(v)
            return f"{np.percentile(a, 50):.3f} / {np.percentile(a, 99):.3f}"

        rest = np.asarray(core) - np.asarray(core_steps) - np.asarray(core_snaps)
        rows.append(f"| {name} | {len(total)} | {q(push)} | {q(core)} | {q(core_steps)} | "
                    f"{q(core_snaps)} | {q(rest)} | {q(conv)} | {q(total)} | {q(after)} |")
    return rows, profiles


def _messages(out, cdr: EstimateCdr, runner) -> bytes:
    """An estimate as the node's two messages' bytes, as ``EstimatorNode._publish`` writes
    them."""
    return cdr.encode(out, runner.integrity.integrity_risk)


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
    ap.add_argument("--duration", type=float, default=60.0,
                    help="s of each live run (one per node algorithm and link)")
    ap.add_argument("--latency", type=float, default=0.02,
                    help="s, fixed link delay of odometer and balise messages")
    ap.add_argument("--jitter", type=float, default=0.05,
                    help="s, mean of the exponential random delay (> period/2: reordering)")
    ap.add_argument("--seeds", type=int, default=10, help="offline seeds (0: no offline part)")
    ap.add_argument("--offline-duration", type=float, default=600.0, help="s per offline run")
    ap.add_argument("--no-live", action="store_true", help="offline part only")
    ap.add_argument("--algorithms", default=",".join(ALGORITHMS),
                    help="gsma_estimator algorithms run live (each its own node, after "
                         "robust_filter's) and in the stage table, comma separated")
    ap.add_argument("--stage-duration", type=float, default=120.0,
                    help="s of metro_demo for the in-process stage table (0: none)")
    ap.add_argument("--paced", action="store_true",
                    help="stage table: the messages fed at 1x real time (sleeping between "
                         "them as a live node does) instead of back to back")
    ap.add_argument("--trace", action="store_true",
                    help="live: the estimator nodes trace their callbacks "
                         "(train_core.realtime.CallbackTrace); a table of where each "
                         "estimate's time goes, wall and CPU")
    ap.add_argument("--profile", type=int, default=0, metavar="N",
                    help="stage table: also a pass under cProfile per estimator, its N "
                         "functions of most own time printed (0: none)")
    ap.add_argument("--no-link", action="store_true",
                    help="live: only the runs without link latency")
    ap.add_argument("--clocks", default="wall,sim",
                    help="live: the clocks the nodes (estimators and echo alike) run on, "
                         "comma separated, each its own runs: wall = the system clock, as on "
                         "a train (use_sim_time false; the simulator at 1x still publishes "
                         "/clock); sim = the simulator's /clock (use_sim_time true)")
    ap.add_argument("--clock-period", type=float, default=None,
                    help="live: the simulator's clock_period (s of simulated time between two "
                         "/clock messages at most; default: the simulator's)")
    ap.add_argument("--realtime", type=int, default=0, metavar="PRIORITY",
                    help="live: start the estimator and echo nodes under SCHED_FIFO at this "
                         "priority (1-99, `chrt -f`), as a train's computer would run them; "
                         "needs the right to (root, CAP_SYS_NICE or an rtprio limit). "
                         "0 (default): the default scheduler")
    ap.add_argument("--together", action="store_true",
                    help="live: every estimator node in one run beside one echo node (they "
                         "contend for the cores) instead of one at a time")
    ap.add_argument("--quick", action="store_true",
                    help="under 2 min: 15 s live runs on the wall clock without link latency, "
                         "the first algorithm, 2 offline seeds of 120 s, a 30 s stage table "
                         "(each given option overrides)")
    if ap.parse_known_args(argv)[0].quick:  # the quick values as defaults: given ones win
        ap.set_defaults(duration=15.0, seeds=2, offline_duration=120.0, stage_duration=30.0,
                        no_link=True, clocks="wall", algorithms=ALGORITHMS[0])
    args = ap.parse_args(argv)
    if not 0 <= args.realtime <= 99:
        ap.error("--realtime: a SCHED_FIFO priority, 1-99 (0: off)")
    if args.realtime > 0 and not args.no_live:
        probe = subprocess.run(["chrt", "-f", str(args.realtime), "true"], capture_output=True,
                               text=True) if shutil.which("chrt") else None
        if probe is None or probe.returncode != 0:
            ap.error("--realtime: cannot run under SCHED_FIFO here ("
                     + ("no chrt: install util-linux" if probe is None else
                        probe.stderr.strip() or "chrt failed")
                     + "); run as root, give CAP_SYS_NICE, or raise the rtprio limit "
                     "(ulimit -r, /etc/security/limits.conf)")
    algorithms = [a for a in args.algorithms.split(",") if a]
    nodes = live_nodes(algorithms)
    echo = nodes[-1]
    # one estimator node with the echo at a time (module doc), or all of them at once
    groups = [nodes] if args.together else [[n, echo] for n in nodes[:-1]]
    logs = Path(tempfile.mkdtemp(prefix="bench_latency_"))
    lag = f"{1e3 * args.latency:g} ms + Exp({1e3 * args.jitter:g} ms)"
    if not args.no_live:
        links = [("none", "metro_demo")]
        if not args.no_link:
            links.append((lag, str(scenario_with_link(logs / "metro_demo_latency.yaml",
                                                      args.latency, args.jitter))))
        clocks = [c for c in args.clocks.split(",") if c]
        unknown = [c for c in clocks if c not in CLOCKS]
        if unknown:
            ap.error(f"--clocks: unknown {unknown} (allowed: {', '.join(CLOCKS)})")
        rows, traced, clocked = [], [], []
        load = [os.getloadavg()[0]]
        for i, (name, scenario) in enumerate(links):
            for clock in clocks:
                for j, group in enumerate(groups):
                    where = logs / f"link{i}" / clock / f"run{j}"
                    cpu = run_live(scenario, args.duration, where, group, trace=args.trace,
                                   sim_time=clock == "sim", clock_period=args.clock_period,
                                   realtime=args.realtime)
                    rows += live_rows(name, where, group, CLOCKS[clock], cpu)
                    if args.trace:
                        what = f"{group[0][0]}, link {name}, {CLOCKS[clock]}"
                        traced += trace_rows(what, where)
                        clocked += clock_rows(what, where)
                    load.append(os.getloadavg()[0])
        how = (f"{len(nodes) - 1} estimator nodes and the echo node side by side"
               if args.together else "each estimator node in turn, with the echo node beside it")
        if args.realtime > 0:
            how += (f", the estimator and echo nodes under SCHED_FIFO priority {args.realtime}"
                    " (chrt)")
        print(f"metro_demo at 1x for {args.duration:g} s per link and run, {how} (logs in "
              f"{logs}); load average (1 min) {', '.join(f'{v:.1f}' for v in load)} before "
              "the first run / after each. node clock: the clock the estimator and the "
              "echo node of a row run on (system: use_sim_time false, as on a train; "
              "simulated: the simulator's /clock, use_sim_time true); p50 / p99 over the "
              "floor's: the row's p50 and p99 divided by its own floor's; CPU: each "
              "process's CPU time per s of the run (ms/s; /proc, from 5 % into the run to "
              "its end)\n")
        print(LIVE_HEADER)
        print("\n".join(rows))
        if args.trace:
            print("\nWhere each estimate's time goes, live (the nodes' callback traces; "
                  "median wall / CPU time of the thread, ms, over the estimates of a reading "
                  "after the start-up's): "
                  + "; ".join(f"{name} = {text}" for name, text in TRACE_STAGES)
                  + "; executor = rclpy's executor, the thread's CPU from a callback's end to "
                  "its next wait (the task retired, a wait set built) / from the wake-up to the "
                  "next callback (the ready entities found, the message taken: before the "
                  "reading's callback starts, so in no latency above), median (and count of "
                  "wake-ups); CPU per s = the thread's CPU in callbacks / in the executor "
                  "between them, ms per s of the run\n")
            print("| node | estimates | released by | "
                  + " | ".join(name for name, _ in TRACE_STAGES)
                  + " | executor before / after a wait (n) | CPU per s |")
            print("|---" * (len(TRACE_STAGES) + 5) + "|")
            print("\n".join(traced))
            print("\n/clock in the estimator nodes (their traces): /clock callbacks per s; "
                  "the CPU of one (the TimeSource's callback; median, ms) and of the "
                  "executor's wake-ups that ran it alone (taking it, the callback, the next "
                  "wait set; median / p99, ms, and their count); the CPU per s they cost "
                  "(those wake-ups whole, and the callback in the others); each odometer "
                  "reading's wait in the node's queue (DDS reception -> its callback's start, "
                  "median / p99, ms: before the latency above starts; the echo node's "
                  "beside it), how many of them "
                  "queued while a wake-up that ran a /clock callback was under way, the "
                  "median queue wait of those and of the others; and from each reading's DDS "
                  "reception to its estimate's Odometry published (the queue wait and the "
                  "latency above; median / p99 over the estimates after the start-up's, "
                  "ms), the echo node's beside it\n")
            print("| node | /clock per s | its callback (ms) | wake-ups for it alone (ms) | "
                  "CPU on /clock (ms/s) | reading's queue wait (ms) | the floor's (ms) | "
                  "readings behind a /clock | their queue wait / the others' (ms) | "
                  "reading received -> estimate published (ms) | the floor's (ms) |")
            print("|---" * 11 + "|")
            print("\n".join(clocked))
    if args.stage_duration > 0:
        pace = ("fed at 1x real time" if args.paced else "fed back to back")
        print("\nWhere an odometer callback's time goes, in process (metro_demo "
              f"{args.stage_duration:g} s, no link latency, messages {pace}; CPU time of the"
              " thread, p50 / p99 in ms over the callbacks that released an estimate): push"
              " = the runner's input checks; advance = the runner's release of the "
              "estimate, of which estimator = the adapter's input and output calls (the "
              "core filter), snapshots = the state copied inside it to rewind for a late "
              "reading (where no copy settled after the last estimate stands), "
              "runner = the rest (clock mapping, integrity monitor); messages = TrainState "
              "and Odometry written as the node writes them (publishing: the floor above); "
              "total = push to messages; after = what the node does once the estimates are "
              "out: the state copied for a later reading's rewind (EstimatorRunner.settle) "
              "and the garbage collection due (train_core.realtime.collect_due); not in "
              "total\n")
        print("| estimator | callbacks | push | advance | of which estimator | snapshots | "
              "runner | messages | total | after (copy, gc) |")
        print("|---|---|---|---|---|---|---|---|---|---|")
        rows, profiles = stages(["robust_filter", *algorithms], args.stage_duration,
                                profile=args.profile, paced=args.paced)
        print("\n".join(rows))
        for text in profiles:
            print(f"\n{text}")
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
