#!/usr/bin/env python3
"""Benchmark of the slip episodes ``diagnose`` reports (wheel_slip): where they are.

``--cases`` wheel_slip cases of train_sim.cases at each size (plain, subtle) and as many
``long`` ones (the plain case with every episode stretched to 5-8 s, which shows in the null's
innovations at its onset and its end). Each case is simulated into a measured bag and diagnosed
(the core's ``diagnose``, as the CLI runs it); the wheel_slip entry of the ranking is compared
with the truth on the stamp clock: 1 - IoU of the union of the found intervals and the union of
the true ones (time), and the number of episodes found against the true number.

Usage: bench_slip_episodes.py [--cases 3] [--seed 0]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))


def union_length(ivs) -> float:
    out, cur = 0.0, None
    for a, b in sorted((float(a), float(b)) for a, b in ivs):
        if cur is None or a > cur[1]:
            if cur is not None:
                out += cur[1] - cur[0]
            cur = [a, b]
        else:
            cur[1] = max(cur[1], b)
    return out + (cur[1] - cur[0] if cur is not None else 0.0)


def one_minus_iou(found, true) -> float:
    inter = sum(max(0.0, min(b, d) - max(a, c)) for a, b in _merged(found)
                for c, d in _merged(true))
    union = union_length(list(found) + list(true))
    return 1.0 - inter / union if union > 0 else 0.0


def _merged(ivs):
    out = []
    for a, b in sorted((float(a), float(b)) for a, b in ivs):
        if out and a <= out[-1][1]:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b])
    return out


def stretched(case, rng):
    """The case with every slip episode lengthened to 5-8 s (same starts, same fraction)."""
    from train_core.effects import WheelSlipEffect

    ws = case.scenario.effects.wheel_slip
    ivs = tuple((t0, round(t0 + float(rng.uniform(5.0, 8.0)), 2)) for t0, _ in ws.intervals)
    eff = dataclasses.replace(case.scenario.effects,
                              wheel_slip=WheelSlipEffect(ivs, ws.slip_fraction))
    truth = {**case.truth, "wheel_slip": {"intervals": [list(iv) for iv in ivs]}}
    return dataclasses.replace(case, scenario=dataclasses.replace(case.scenario, effects=eff),
                               truth=truth)


def run(case) -> dict:
    from train_core.bagio import read_bag

    from train_estimation.core.offline.diagnose import diagnose
    from train_estimation.core.offline.measured import MeasuredRun
    from train_estimation.tools.diagnose import TOPICS
    from train_sim.generate import generate

    with tempfile.TemporaryDirectory(prefix="bench_slip_") as d:
        generate(case.scenario, os.path.join(d, "bag"), measured=True)
        bag = read_bag(os.path.join(d, "bag"), topics=TOPICS)
        stamps = np.array([s for _, s, _ in bag.topics["odometer"]])
        truth = case.truth_in_bag(float(stamps.min()), float(stamps.max()))["wheel_slip"]
        t0 = time.perf_counter()
        dg = diagnose(MeasuredRun.from_bag(bag), case.scenario.line, case.scenario.train)
        secs = time.perf_counter() - t0
    est = next(r.parameters for r in dg.ranking if r.cause == "wheel_slip")
    found = est.get("intervals", [])
    return {"named": dg.cause == "wheel_slip", "found": len(found),
            "true": len(truth["intervals"]), "err": one_minus_iou(found, truth["intervals"]),
            "time": secs}


def main() -> None:
    from train_core.progress import track

    from train_sim.cases import make_case

    ap = argparse.ArgumentParser()
    ap.add_argument("--cases", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    print(f"{args.cases} wheel_slip cases per kind, seed {args.seed}\n")
    print("| kind | named | 1 - IoU median | 1 - IoU <= 0.3 | episodes found / true (each) "
          "| s/bag |")
    print("|---|---|---|---|---|---|")
    for kind in ("plain", "subtle", "long"):
        rows = []
        for i in track(range(args.cases), f"slip_episodes: {kind}"):
            rng = np.random.default_rng([args.seed, 77, i])
            case = make_case(rng, "wheel_slip", "subtle" if kind == "subtle" else "plain")
            if kind == "long":
                case = stretched(case, rng)
            rows.append(run(case))
        err = [r["err"] for r in rows]
        print(f"| {kind} | {sum(r['named'] for r in rows)}/{len(rows)} | {np.median(err):.2f} | "
              f"{sum(e <= 0.3 for e in err)}/{len(err)} | "
              + ", ".join(f"{r['found']}/{r['true']}" for r in rows)
              + f" | {np.median([r['time'] for r in rows]):.0f} |", flush=True)


if __name__ == "__main__":
    sys.exit(main())
