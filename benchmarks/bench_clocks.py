"""The train clock's model, its contract measured: what the runner's clocks and door do on a
clean jittery link and on a clock that steps, with no filter in the way.

A train at constant speed sends odometer readings (with or without a sample counter) and a
zone sends commands at 1 Hz; the readings go through the integrity campaign's own link
(``tools.faults.inject``: 50 ms latency, an exponential jitter of mean ``jitter``, readings lost
at random) with the train clock at a Unix epoch, and are replayed through ``EstimatorRunner``
with an adapter that only records what it is given (``tools/clock_runs.py``): every figure
below is the clocks' and the door's, not a filter's.

Per link (rate, counter, jitter), on a clean clock:

- **false steps per hour**: ``clock_reset`` events (a step declared where there is none), and
  readings refused (``future_stamp``, ``stale_stamp``, ...) per hour;
- **offset bias**: the train clock's centre (``StreamClock.value``, stamp minus arrival)
  against where the clock is with the least latency (the epoch less the link's 50 ms floor),
  in ms, beside the jitter's own spread (its standard deviation is ``jitter``);
- **held**: the share of estimates published while readings were held as a possible step;
- **clocks judged**: one (the commands taken on the readings' clock, as they are) or separate,
  and the train clock's **drift** as the runner estimates it (true 0).

On a link that queues (every 30 s it holds the readings for 1 s and then delivers them
``r`` times as fast as they were sampled: the integrity campaign's fault ``queue``), the same
figures and the **time error**: the largest move of (filter time - true sampling time) over
the run (ms). On a link whose latency rises by ``L`` s and stays (the fault ``route``: a
handover to a slower path), the false steps, the moves of the link's latency found
(``link_latency`` events), and the time error. A latency that moves by less than the step
watch's least move (10-30 ms either way, without a counter, several seeds) is the rate fit's
alone: its drift against its stated error, the clocks judged and the time error.

Per step of ``d`` s (at 600 s):

- **decided after**: the readings (of the new clock) that arrived before the step was declared
  (the detection delay), and that time in seconds;
- **shift error**: the step as re-anchored less ``d`` (ms);
- **time error**: the largest move of (filter time - true sampling time) of the readings fused
  after the step from the last one's before it (ms; the filter's time origin is its own);
- **doubted**: estimates published while the step was undecided (the integrity monitor's
  ``clock`` doubt).

    ./run bench clocks            # one hour per link, every step (16 min of CPU, loaded)
    ./run bench clocks --quick    # 10 minutes per link (under 2 min)
    ./run bench clocks --per-reading   # CPU per reading only, with and without a counter
"""

from __future__ import annotations

import argparse
import math
import sys
import time

from train_estimation.tools.clock_runs import FLOOR, STEP_AT, run_link


def per_reading(seed: int, loss: float) -> int:
    """The runner's clocks and door alone: CPU (``time.process_time``) per reading on a clean
    10 Hz link, the least of three runs (the load's share least)."""
    import os

    from train_estimation.core.numerics.count_fit import warm_up

    warm_up()  # (numba's cache loaded, as a node does while it starts)
    n = round(600.0 * 10.0 * (1.0 - loss))
    print(f"## CPU per reading, 10 min at 10 Hz, 50 ms jitter ({loss:.0%} lost; load average "
          f"{os.getloadavg()[0]:.1f})\n")
    print("| counter | ms per reading |\n|---|---|")
    for counter in (True, False):
        best = math.inf
        for _ in range(3):
            c0 = time.process_time()
            run_link(600.0, 10.0, counter, 0.05, loss, None, seed)
            best = min(best, time.process_time() - c0)
        print(f"| {'yes' if counter else 'no'} | {1e3 * best / n:.3f} |", flush=True)
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="10 minutes per link (else 1 hour)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--loss", type=float, default=0.05, help="share of readings lost")
    ap.add_argument("--step-jitter", type=float, nargs="+", default=[0.05], metavar="S",
                    help="mean jitter (s) of the link in the step table, one table per value "
                         "(default 0.05; 0.2 is the clean table's slowest link)")
    ap.add_argument("--steps", type=float, nargs="+", metavar="D",
                    help="the steps (s) of the step tables (default -10 -3 -0.5 -0.1 0.1 0.5 3 "
                         "10; with --quick -3 -0.1 0.1 3)")
    ap.add_argument("--count-noise", type=float, nargs=2, default=[0.0, 0.0],
                    metavar=("M", "V"), help="standard deviations of the odometer's count (m) "
                    "and speed (m/s) per reading (default 0 0: exact; a train's are 0.1-1 m "
                    "and about 0.1 m/s)")
    ap.add_argument("--per-reading", action="store_true",
                    help="only the runner's CPU per reading (10 minutes at 10 Hz, 50 ms "
                         "jitter, with and without a sample counter; the least of 3 runs)")
    args = ap.parse_args(argv)
    if args.per_reading:
        return per_reading(args.seed, args.loss)
    noise = tuple(args.count_noise)
    clean = 600.0 if args.quick else 3600.0
    t0 = time.process_time()
    links = [(10.0, True), (10.0, False), (1.0, True), (1.0, False)]
    jitters = (0.005, 0.05, 0.2)
    print(f"## The train clock on a clean link ({clean / 60:g} min per row, {args.loss:.0%} "
          f"lost, latency {FLOOR * 1e3:g} ms + Exp(jitter), seed {args.seed}; the count's and "
          f"the speed's noise {noise[0]:g} m and {noise[1]:g} m/s)\n")
    print("| rate (Hz) | counter | jitter (ms) | false steps / h | refused / h | "
          "held (share of estimates) | offset bias (ms) | clocks judged | drift (ppm) |")
    print("|---|---|---|---|---|---|---|---|---|")
    worst = 0.0
    for rate, counter in links:
        for jit in jitters:
            r = run_link(clean, rate, counter, jit, args.loss, None, args.seed, noise=noise)
            worst = max(worst, r["false_steps_per_h"])
            print(f"| {rate:g} | {'yes' if counter else 'no'} | {jit * 1e3:g} | "
                  f"{r['false_steps_per_h']:.1f} | {r['refused'] / (clean / 3600.0):.1f} | "
                  f"{r['held']:.4f} | "
                  f"{r['bias_ms']:+.1f} | {'separate' if r['separate'] else 'one'} | "
                  f"{r['drift_ppm']:+.1f} |", flush=True)
    steps = (-10.0, -3.0, -0.5, -0.1, 0.1, 0.5, 3.0, 10.0) if not args.quick else \
        (-3.0, -0.1, 0.1, 3.0)
    steps = tuple(args.steps) if args.steps else steps
    dur = STEP_AT + 300.0
    missed = 0
    for step_jit in args.step_jitter:
        print(f"\n## A step of d s at {STEP_AT:g} s (jitter {step_jit * 1e3:g} ms, "
              f"{args.loss:.0%} lost)\n")
        print("| rate (Hz) | counter | d (s) | decided after (readings) | (s) | "
              "shift error (ms) | time error after (ms) | doubted estimates | refused |")
        print("|---|---|---|---|---|---|---|---|---|")
        for rate, counter in links:
            for d in steps:
                r = run_link(dur, rate, counter, step_jit, args.loss, d, args.seed, noise=noise)
                missed += not math.isfinite(r["decided_s"])
                print(f"| {rate:g} | {'yes' if counter else 'no'} | {d:+g} | "
                      f"{r['decided_readings']} | {r['decided_s']:.2f} | "
                      f"{r['shift_err_ms']:+.1f} | {r['time_err_ms']:.1f} | {r['doubted']} | "
                      f"{r['refused']} |", flush=True)
    drains = (2.0, 1.5, 1.2)
    print(f"\n## A link that queues: every 30 s it holds the readings for 1 s, then delivers "
          f"them r times as fast as they were sampled (jitter 30 ms, {args.loss:.0%} lost, "
          f"{clean / 60:g} min per row)\n")
    print("| rate (Hz) | counter | r | false steps / h | refused / h | held (share of "
          "estimates) | time error (ms) | clocks judged | drift (ppm) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for rate, counter in links:
        for drain in drains:
            r = run_link(clean, rate, counter, 0.03, args.loss, None, args.seed,
                         queue=drain)
            worst = max(worst, r["false_steps_per_h"])
            print(f"| {rate:g} | {'yes' if counter else 'no'} | {drain:g} | "
                  f"{r['false_steps_per_h']:.1f} | {r['refused'] / (clean / 3600.0):.1f} | "
                  f"{r['held']:.4f} | {r['time_err_all_ms']:.1f} | "
                  f"{'separate' if r['separate'] else 'one'} | {r['drift_ppm']:+.1f} |",
                  flush=True)
    routes = (0.45, 1.5) if args.quick else (0.2, 0.45, 1.5, 3.0)
    print(f"\n## A link whose latency rises by L s at {STEP_AT:g} s and stays (jitter 30 ms, "
          f"{args.loss:.0%} lost)\n")
    print("| rate (Hz) | counter | L (s) | false steps | latency moves | refused | held "
          "(share of estimates) | time error (ms) |")
    print("|---|---|---|---|---|---|---|---|")
    for rate, counter in links:
        for L in routes:
            r = run_link(dur, rate, counter, 0.03, args.loss, None, args.seed, route=L)
            steps_n = round(r["false_steps_per_h"] * dur / 3600.0)
            worst = max(worst, r["false_steps_per_h"])
            print(f"| {rate:g} | {'yes' if counter else 'no'} | {L:g} | {steps_n} | "
                  f"{r['latency_moved']} | {r['refused']} | {r['held']:.4f} | "
                  f"{r['time_err_all_ms']:.1f} |", flush=True)
    # a latency move within the rate fit's band (below the step watch's least move): the rate
    # fit sees it as a level move of its envelope (StreamClock._level_move) or absorbs it
    moves = (-0.03, 0.01) if args.quick else (-0.03, -0.01, 0.01, 0.03)
    seeds = range(args.seed, args.seed + (1 if args.quick else 6))
    print(f"\n## A link whose latency moves by L s at {STEP_AT:g} s and stays, less than the "
          f"step watch's least move (no counter, jitter 50 ms, {args.loss:.0%} lost, "
          f"{2 * STEP_AT / 60:g} min per run, seed{'s' if len(seeds) > 1 else ''} "
          f"{seeds[0]}{f'-{seeds[-1]}' if len(seeds) > 1 else ''})\n")
    print("| rate (Hz) | L (s) | drift / its stated error, each seed | largest |drift| / "
          "error | clocks judged separate | time error, largest (ms) |")
    print("|---|---|---|---|---|---|")
    worst_z = 0.0
    for rate in (10.0, 1.0):
        for L in moves:
            rs = [run_link(2 * STEP_AT, rate, False, 0.05, args.loss, None, seed, route=L)
                  for seed in seeds]
            zs = [r["drift_ppm"] / r["drift_se_ppm"] for r in rs]
            worst_z = max(worst_z, max(abs(z) for z in zs))
            print(f"| {rate:g} | {L:+g} | {' '.join(f'{z:+.1f}' for z in zs)} | "
                  f"{max(abs(z) for z in zs):.1f} | {sum(r['separate'] for r in rs)} of "
                  f"{len(rs)} | {max(r['time_err_all_ms'] for r in rs):.1f} |", flush=True)
    print(f"\n(CPU {time.process_time() - t0:.0f} s)")
    print(f"{'PASS' if worst == 0 else 'FAIL'}  no false step on a clean, queueing or rerouted "
          f"link: worst {worst:.1f} per hour")
    print(f"{'PASS' if missed == 0 else 'FAIL'}  every step declared: {missed} missed")
    print(f"{'PASS' if worst_z <= 4.0 else 'FAIL'}  a latency that moves within the band is no "
          f"clock rate (drift within 4 stated errors): largest {worst_z:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
