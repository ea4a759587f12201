#!/usr/bin/env python3
"""Benchmark of the slip episodes ``diagnose`` reports (wheel_slip): where they are.

``--cases`` wheel_slip cases of train_sim.cases (random line family, train, driver, link) of
each kind:

- ``plain``, ``subtle``: the generator's cases (1-3 episodes of 2-3 s, one slip fraction of
  +-0.1 or +-0.05 for all of them, at > 6 m/s);
- ``long``: the plain case with every episode stretched to 5-8 s (which shows in the null's
  innovations at its onset and at its end only);
- ``varied``: 2-4 episodes placed on the pilot run wherever the train moves at > 3 m/s (in any
  phase, braking included), each 1-12 s long with its own depth, slip or slide, |fraction|
  0.03-0.25, at least 15 s apart;
- ``shaped``: the ``varied`` episodes with the slip building up and dying away as a half sine
  (``WheelSlipEffect.shape`` "sine"), the fraction its peak: a slip as adhesion is lost and
  regained, not a step. Its depth error is against the peak;
- ``deep``, ``deep_shaped`` (not run unless chosen with ``--kinds``): the ``varied`` and
  ``shaped`` episodes at the same places, each |fraction| 0.12-0.25 (deep slips, which came
  out shallow and long; ``./run bench diagnose`` judges its target on them).

Each case is simulated into a measured bag and diagnosed (the core's ``diagnose``, as the CLI
runs it); the wheel_slip entry of the ranking is compared with the truth on the stamp clock:
1 - IoU of the union of the found intervals and the union of the true ones (time), the number
of episodes found against the true number, and for each true episode the error of the depth of
the found episode that overlaps it most (|found - true| / |true|). The target: 1 - IoU <= 0.3
in every case.

Usage: bench_slip_episodes.py [--cases 3 | --quick] [--seed 0]
                              [--kinds plain,subtle,long,varied,shaped,deep,deep_shaped]
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


def varied(case, rng, shape: str = "step", depths=(0.03, 0.25)):
    """The case with 2-4 episodes of its own (see the module docstring), placed on a pilot run of
    the case's world without slip, and per-episode fractions (of ``shape``; |fraction| drawn
    uniformly within ``depths``)."""
    from train_core.effects import WheelSlipEffect

    from train_sim.world import simulate

    eff0 = dataclasses.replace(case.scenario.effects, wheel_slip=None)
    res = simulate(dataclasses.replace(case.scenario, effects=eff0))
    t, v = res.truth["t"], res.truth["velocity"]
    n = int(rng.integers(2, 5))
    ivs, fr = [], []
    for t0 in rng.permutation(t[(v > 3.0) & (t > 10.0) & (t < t[-1] - 15.0)]):
        dur = float(rng.uniform(1.0, 12.0))
        inside = (t >= t0) & (t <= t0 + dur)
        if v[inside].min() <= 3.0 or any(abs(t0 - a) < dur + 15.0 or abs(t0 - a) < b - a + 15.0
                                          for a, b in ivs):
            continue
        ivs.append((round(float(t0), 2), round(float(t0) + dur, 2)))
        fr.append(round(float(rng.choice([-1.0, 1.0]) * rng.uniform(*depths)), 4))
        if len(ivs) == n:
            break
    order = np.argsort([a for a, _ in ivs])
    ivs = tuple(ivs[i] for i in order)
    fr = tuple(fr[i] for i in order)
    eff = dataclasses.replace(case.scenario.effects,
                              wheel_slip=WheelSlipEffect(ivs, fr[0], fractions=fr, shape=shape))
    truth = {**case.truth, "wheel_slip": {"intervals": [list(iv) for iv in ivs]}}
    return dataclasses.replace(case, scenario=dataclasses.replace(case.scenario, effects=eff),
                               truth=truth)


def depth_errors(found, depths, true, fractions) -> list:
    """Per true episode: |depth - true depth| / |true depth| of the found episode that overlaps
    it most (None when none does). Depth = -slip fraction (docs/interfaces.md)."""
    out = []
    for (c, d), f in zip(true, fractions):
        ov = [max(0.0, min(b, d) - max(a, c)) for a, b in found]
        if not ov or max(ov) <= 0 or depths is None:
            out.append(None)
            continue
        out.append(abs(float(depths[int(np.argmax(ov))]) + f) / abs(f))
    return out


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
    ws = case.scenario.effects.wheel_slip
    fr = [ws.fraction(i) for i in range(len(truth["intervals"]))]
    return {"named": dg.cause == "wheel_slip", "found": len(found),
            "true": len(truth["intervals"]), "err": one_minus_iou(found, truth["intervals"]),
            "depth_err": depth_errors(found, est.get("depths"), truth["intervals"], fr),
            "time": secs}


TARGET = 0.3  # 1 - IoU of the found and the true slip time, in every case
KINDS = ("plain", "subtle", "long", "varied", "shaped", "deep", "deep_shaped")
DEFAULT_KINDS = KINDS[:5]
DEEP = (0.12, 0.25)  # |slip fraction| of the deep kinds (12-25 % depth: bench_diagnose's target)


def make_slip_case(kind: str, seed: int, i: int):
    """Case ``i`` of ``kind`` (seeded ``[seed, 77, i]``: the kinds share their line, train and
    places, ``varied`` and ``deep`` their episodes' times)."""
    from train_sim.cases import make_case

    rng = np.random.default_rng([seed, 77, i])
    case = make_case(rng, "wheel_slip", "subtle" if kind == "subtle" else "plain")
    if kind == "long":
        return stretched(case, rng)
    if kind in ("varied", "shaped", "deep", "deep_shaped"):
        return varied(case, rng, "sine" if kind.endswith("shaped") else "step",
                      DEEP if kind.startswith("deep") else (0.03, 0.25))
    return case


def kind_rows(kind: str, n: int, seed: int) -> list[dict]:
    """``run`` on cases 0..n-1 of ``kind`` (a progress bar on stderr)."""
    from train_core.progress import track

    return [run(make_slip_case(kind, seed, i))
            for i in track(range(n), f"slip_episodes: {kind}")]


HEAD = ("| kind | named | 1 - IoU median (max) | 1 - IoU <= 0.3 | target | episodes found / "
        "true (1 - IoU), each case | depth error median (share <= 0.2) | s/bag |\n"
        "|---|---|---|---|---|---|---|---|")


def kind_line(kind: str, rows: list[dict]) -> str:
    """The table's row (``HEAD``) of ``kind``'s cases."""
    err = [r["err"] for r in rows]
    de = [e for r in rows for e in r["depth_err"]]
    de_ok = [e is not None and e <= 0.2 for e in de]
    de_med = np.median([e if e is not None else np.inf for e in de]) if de else np.nan
    ok = sum(e <= TARGET for e in err)
    return (f"| {kind} | {sum(r['named'] for r in rows)}/{len(rows)} | {np.median(err):.2f} "
            f"({max(err):.2f}) | {ok}/{len(err)} | {'pass' if ok == len(err) else 'FAIL'} | "
            + ", ".join(f"{r['found']}/{r['true']} ({r['err']:.2f})" for r in rows)
            + f" | {de_med:.2f} ({sum(de_ok)}/{len(de)}) "
            f"| {np.median([r['time'] for r in rows]):.0f} |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=int, default=3, help="cases per kind")
    ap.add_argument("--quick", action="store_true", help="one case per kind (under 2 min)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--kinds", default=",".join(DEFAULT_KINDS),
                    help=f"comma-separated kinds of {','.join(KINDS)} "
                         f"(default {','.join(DEFAULT_KINDS)})")
    args = ap.parse_args()
    if args.quick:
        args.cases = 1
    kinds = [k for k in args.kinds.split(",") if k]
    if any(k not in KINDS for k in kinds):
        ap.error(f"--kinds: choose from {','.join(KINDS)}")
    print(f"{args.cases} wheel_slip cases per kind, seed {args.seed}; target: 1 - IoU <= "
          f"{TARGET:g} in every case\n")
    print(HEAD)
    every = []
    for kind in kinds:
        rows = kind_rows(kind, args.cases, args.seed)
        every += [r["err"] for r in rows]
        print(kind_line(kind, rows), flush=True)
    ok = sum(e <= TARGET for e in every)
    print(f"\nall kinds: 1 - IoU <= {TARGET:g} in {ok}/{len(every)} cases: "
          f"{'pass' if ok == len(every) else 'FAIL'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
