#!/usr/bin/env python3
"""Benchmark of the Gilbert-Elliott link fit (train_estimation.core.offline.link_hmm).

For several true links, ``--reps`` sequences of ``--n`` odometer samples (default 6000: a
10-minute run at 10 Hz) from the simulator's own link (train_core.link.Link), each fitted by
``fit_link``. Prints a markdown table: per parameter the median relative error |fit - true| /
true and the share of runs within 30 % of the truth (loss_good = 0 and loss_bad = 1 are judged
by the absolute error, within 0.03, as a relative error to 0 is not defined), the share of
runs called bursty, the expected number of bad spells in a run (n p_good_bad (1 - stationary
bad): it bounds the precision, the relative standard error of p_bad_good is about one over its
square root), the share of runs with all four parameters within 30 % and pass/fail against the
target (all four within 30 % in every run), and the median time per fit.

Usage: bench_link_hmm.py [--reps 20] [--n 6000] [--seed 0]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
from train_core.progress import track  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:0] = [os.path.join(HERE, "..", "ros_ws", "src", "train_estimation"),
                os.path.join(HERE, "..", "ros_ws", "src", "train_core")]

from train_core.link import Link, LinkParams  # noqa: E402

from train_estimation.core.offline.link_hmm import GilbertElliott, fit_link  # noqa: E402

SETS = {
    "0/1 losses, bursts of 4": GilbertElliott(0.02, 0.25, 0.0, 1.0),
    "0/1 losses, bursts of 8 (cases: plain)": GilbertElliott(0.0125, 0.125, 0.0, 1.0),
    "soft: bad lets 20 % through": GilbertElliott(0.01, 0.1, 0.02, 0.8),
    "soft: 5 % lost in good": GilbertElliott(0.03, 0.2, 0.05, 0.7),
    "rare long bursts": GilbertElliott(0.005, 0.05, 0.01, 0.9),
}
ABS_OK = 0.03  # -, "within" for a true loss probability of 0 or 1: 3 percentage points
NAMES = ("p_good_bad", "p_bad_good", "loss_good", "loss_bad")


def losses(p: GilbertElliott, n: int, seed: int) -> np.ndarray:
    lk = Link(LinkParams(model="gilbert_elliott", p_good_bad=p.p_good_bad,
                         p_bad_good=p.p_bad_good, loss_good=p.loss_good, loss_bad=p.loss_bad),
              np.random.default_rng(seed))
    return ~lk.transmit_many(n)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--n", type=int, default=6000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true",
                    help="under 2 min: 3 runs per link (unless --reps is given)")
    if ap.parse_known_args()[0].quick:  # the quick value as the default: a given one wins
        ap.set_defaults(reps=3)
    args = ap.parse_args()
    print(f"{args.reps} runs of {args.n} samples per link; cells: median |error| "
          f"(relative, or absolute where the truth is 0 or 1) and share within 30 %\n")
    print("| link | p_gb, p_bg, loss_g, loss_b | " + " | ".join(NAMES)
          + " | bursty | bad spells per run | all four within | target | s/fit |")
    print("|---|---|" + "---|" * (len(NAMES) + 5))
    for label, true in SETS.items():
        errs = {k: [] for k in NAMES}
        ok = {k: [] for k in NAMES}
        bursty, secs = [], []
        for r in track(range(args.reps), "link hmm"):
            lost = losses(true, args.n, 1000 * args.seed + r)
            t0 = time.perf_counter()
            fit = fit_link(lost, np.random.default_rng([args.seed, r]))
            secs.append(time.perf_counter() - t0)
            bursty.append(fit.bursty)
            est = fit.hmm or fit.params
            for k in NAMES:
                tv, ev = getattr(true, k), getattr(est, k)
                if tv in (0.0, 1.0):
                    e = abs(ev - tv)
                    errs[k].append(e)
                    ok[k].append(e <= ABS_OK)
                else:
                    e = abs(ev - tv) / tv
                    errs[k].append(e)
                    ok[k].append(e <= 0.3)
        all_ok = np.all([ok[k] for k in NAMES], axis=0)
        spells = args.n * true.p_good_bad * (1.0 - true.stationary_bad)
        cells = []
        for k in NAMES:
            tv = getattr(true, k)
            med = float(np.median(errs[k]))
            cells.append(f"{med:.3f} abs, {100 * np.mean(ok[k]):.0f} %" if tv in (0.0, 1.0)
                         else f"{100 * med:.0f} %, {100 * np.mean(ok[k]):.0f} %")
        print(f"| {label} | {true.p_good_bad:g}, {true.p_bad_good:g}, {true.loss_good:g}, "
              f"{true.loss_bad:g} | " + " | ".join(cells)
              + f" | {100 * np.mean(bursty):.0f} % | {spells:.0f} | "
              f"{100 * np.mean(all_ok):.0f} % | {'pass' if all_ok.all() else 'FAIL'} | "
              f"{np.median(secs):.2f} |", flush=True)


if __name__ == "__main__":
    main()
