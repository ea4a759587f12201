"""The train clock's model, its contract measured: what the runner's clocks and door do on a
clean jittery link and on a clock that steps, with no filter in the way.

A train at constant speed sends odometer readings (with or without a sample counter) and a
zone sends commands at 1 Hz; the readings go through the integrity campaign's own link
(``tools.faults.inject``: 50 ms latency, an exponential jitter of mean ``jitter``, readings lost
at random) with the train clock at a Unix epoch, and are replayed through
``EstimatorRunner`` with an adapter that only records what it is given (:class:`Recorder`):
every figure below is the clocks' and the door's, not a filter's.

Per link (rate, counter, jitter), on a clean clock:

- **false steps per hour**: ``clock_reset`` events (a step declared where there is none), and
  readings refused (``future_stamp``, ``stale_stamp``, ...) per hour;
- **offset bias**: the train clock's centre (``StreamClock.value``, stamp minus arrival)
  against where the clock is with the least latency (the epoch less the link's 50 ms floor),
  in ms, beside the jitter's own spread (its standard deviation is ``jitter``);
- **held**: the share of estimates published while readings were held as a possible step.

Per step of ``d`` s (at 600 s):

- **decided after**: the readings (of the new clock) that arrived before the step was declared
  (the detection delay), and that time in seconds;
- **shift error**: the step as re-anchored less ``d`` (ms);
- **time error**: the largest |filter time - true sampling time| of the readings fused after
  the step (ms; the mapping the filters then run on);
- **doubted**: estimates published while the step was undecided (the integrity monitor's
  ``clock`` doubt).

    ./run bench clocks            # one hour per link, every step (about 10 min of CPU)
    ./run bench clocks --quick    # 10 minutes per link (under 2 min)
"""

from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np

from train_estimation.core.online.replay import replay
from train_estimation.core.online.runner import EstimatorRunner, Output
from train_estimation.tools import faults as F

SPEED = 20.0  # m/s, the train's constant speed
FLOOR = F.LATENCY  # s, the link's least latency (faults.LATENCY)
STEP_AT = 600.0  # s, true time of a step


class Recorder:
    """An adapter with no filter: it records the odometer readings fused (filter time, seq) and
    publishes a fixed estimate, so that the runner's clocks and door alone are measured."""

    def __init__(self):
        self.fused: list = []

    def start(self, t0: float) -> None:
        pass

    def control(self, stamp: float, fields: dict) -> str:
        return ""

    def odometer(self, stamp: float, fields: dict) -> str:
        self.fused.append((stamp, fields["distance"]))
        return ""

    def balise(self, stamp: float, fields: dict) -> str:
        return ""

    def output(self, t: float) -> Output:
        return Output(t, SPEED * t, SPEED, 0.0, math.nan, tuple(np.eye(4).ravel() * 0.01), True)


def cruise(duration: float, rate: float, loss: float, counter: bool,
           rng: np.random.Generator) -> list:
    """``(topic, t, fields)`` of a train at :data:`SPEED`: odometer readings at ``rate`` Hz
    (``seq`` the sample counter, or 0 for every reading without one) of which ``loss`` are lost
    at random, and a command every second."""
    ev = []
    n = int(round(duration * rate))
    for k in np.flatnonzero(rng.random(n) >= loss):
        t = k / rate
        ev.append(("odometer", t, {"seq": int(k) if counter else 0, "distance": SPEED * t,
                                   "speed": SPEED, "speed_variance": 0.01}))
    ev += [("control", float(j), {"target_acceleration": 0.0})
           for j in range(int(duration) + 1)]
    return sorted(ev, key=lambda e: (e[1], e[0] != "control"))


def run_link(duration: float, rate: float, counter: bool, jitter: float, loss: float,
             step: float | None, seed: int) -> dict:
    """One replay (module doc); the figures of one row."""
    rng = np.random.default_rng(seed)
    events = cruise(duration, rate, loss, counter, rng)
    fault = F.Fault("none", jitter=jitter) if step is None else \
        F.Fault("step", step, STEP_AT, jitter=jitter)
    faulted = F.inject(events, fault, rng)
    rec = Recorder()
    runner = EstimatorRunner(rec, 1.0 / rate)
    arrived = {"new": 0}  # readings sampled at or after the step's instant, arrived so far
    decided = []  # (true arrival s, new readings arrived) when the step was declared

    def on_time(t_arr: float) -> None:
        if not decided and runner.events.get("odometer:clock_reset"):
            decided.append((t_arr - F.EPOCH, arrived["new"]))

    def stream():
        for ev in faulted.events:
            yield ev
            if ev[0] == "odometer" and ev[2]["distance"] / SPEED >= STEP_AT - 1e-9:
                arrived["new"] += 1

    outs, _ = replay(stream(), rec, 1.0 / rate, on_time=on_time, runner=runner)
    hours = duration / 3600.0
    doubted = sum("clock" in o.integrity_reason for o in outs)
    row = {"false_steps_per_h": runner.events.get("odometer:clock_reset", 0) / hours
           if step is None else math.nan,
           "refused": sum(runner.rejected.values()),
           "held": doubted / max(len(outs), 1), "doubted": doubted}
    # where the clock is with the least latency: stamp - arrival = -FLOOR on this link
    train = runner._offsets.get("train")
    row["bias_ms"] = 1e3 * (train.value + FLOOR) if train is not None else math.nan
    # one clock (the commands' and the readings' share the epoch and the rate): judged so?
    row["separate"] = runner.separate_clocks
    row["drift_ppm"] = 1e6 * train.rate()[0] if train is not None else math.nan
    if step is not None:
        row["shift_err_ms"] = 1e3 * (runner._steps.shift - step)
        t_dec, n_new = decided[0] if decided else (math.nan, math.nan)
        row["decided_readings"], row["decided_s"] = n_new, t_dec - STEP_AT
        # the filter time of each reading fused after the step against its true sampling time,
        # relative to the last one before it (the filter's time origin is its own)
        f = np.array([(s, d / SPEED) for s, d in rec.fused], float)
        e = f[:, 0] - f[:, 1] if f.size else f
        before, after = f[:, 1] < STEP_AT, f[:, 1] >= STEP_AT
        row["time_err_ms"] = 1e3 * float(np.max(np.abs(e[after] - e[before][-1]))) \
            if after.any() and before.any() else math.nan
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="10 minutes per link (else 1 hour)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--loss", type=float, default=0.05, help="share of readings lost")
    args = ap.parse_args(argv)
    clean = 600.0 if args.quick else 3600.0
    t0 = time.process_time()
    links = [(10.0, True), (10.0, False), (1.0, True), (1.0, False)]
    jitters = (0.005, 0.05, 0.2)
    print(f"## The train clock on a clean link ({clean / 60:g} min per row, {args.loss:.0%} "
          f"lost, latency {FLOOR * 1e3:g} ms + Exp(jitter), seed {args.seed})\n")
    print("| rate (Hz) | counter | jitter (ms) | false steps / h | refused / h | "
          "held (share of estimates) | offset bias (ms) | clocks judged | drift (ppm) |")
    print("|---|---|---|---|---|---|---|---|---|")
    worst = 0.0
    for rate, counter in links:
        for jit in jitters:
            r = run_link(clean, rate, counter, jit, args.loss, None, args.seed)
            worst = max(worst, r["false_steps_per_h"])
            print(f"| {rate:g} | {'yes' if counter else 'no'} | {jit * 1e3:g} | "
                  f"{r['false_steps_per_h']:.1f} | {r['refused'] / (clean / 3600.0):.1f} | "
                  f"{r['held']:.4f} | "
                  f"{r['bias_ms']:+.1f} | {'separate' if r['separate'] else 'one'} | "
                  f"{r['drift_ppm']:+.1f} |", flush=True)
    steps = (-10.0, -3.0, -0.5, -0.1, 0.1, 0.5, 3.0, 10.0) if not args.quick else \
        (-3.0, -0.1, 0.1, 3.0)
    dur = STEP_AT + 300.0
    print(f"\n## A step of d s at {STEP_AT:g} s (jitter 50 ms, {args.loss:.0%} lost)\n")
    print("| rate (Hz) | counter | d (s) | decided after (readings) | (s) | shift error (ms) | "
          "time error after (ms) | doubted estimates | refused |")
    print("|---|---|---|---|---|---|---|---|---|")
    missed = 0
    for rate, counter in links:
        for d in steps:
            r = run_link(dur, rate, counter, 0.05, args.loss, d, args.seed)
            missed += not math.isfinite(r["decided_s"])
            print(f"| {rate:g} | {'yes' if counter else 'no'} | {d:+g} | "
                  f"{r['decided_readings']} | {r['decided_s']:.2f} | {r['shift_err_ms']:+.1f} | "
                  f"{r['time_err_ms']:.1f} | {r['doubted']} | "
                  f"{r['refused']} |", flush=True)
    print(f"\n(CPU {time.process_time() - t0:.0f} s)")
    print(f"{'PASS' if worst == 0 else 'FAIL'}  no false step on a clean link: "
          f"worst {worst:.1f} per hour")
    print(f"{'PASS' if missed == 0 else 'FAIL'}  every step declared: {missed} missed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
