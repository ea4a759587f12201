#!/usr/bin/env python3
"""Zone-controller fuzz benchmark: a clean report stream with corrupted reports mixed in.

The clean stream is the ground truth of a simulated ``metro_demo`` run at the odometer rate,
reported as an estimator would (sigma_x growing from 0.5 m, sigma_v 0.1 m/s, a position/velocity
correlation, arrival = stamp + 0.05 s); :func:`train_sim.zone_fuzz.corrupt_reports` mixes in
about ``--per-report`` corrupted copies per clean one (NaN/inf fields and variances, negative and
zero variances, NaN and negative braking-rate variances, a non-symmetric or non-positive-definite
covariance, an unknown integrity value, stamps +3.5 s to +1e9 s ahead and 0.5 to 500 s behind).
Both clock modes (``check_stamp_age`` true and false) are run.

Prints per mode: corrupted reports, exceptions, good reports refused (a corruption that got in
shows as good reports refused after it), corrupted reports accepted, refusals whose kind differs
from the expected one, clock resets followed (0 expected: garbage is interleaved with good
reports), authorities that differ from the clean run's, and the time per report.

Usage::

    ./run bench zone_fuzz                 # 3 seeds x 3600 s x 10 per report: >= 1e6 per mode
    ./run bench zone_fuzz --quick         # 1 seed x 300 s
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
for _p in (ROOT / "ros_ws/src/train_sim", ROOT / "ros_ws/src/train_core"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

import numpy as np  # noqa: E402
from train_core.progress import track  # noqa: E402

from train_sim.scenario import load_scenario  # noqa: E402
from train_sim.world import simulate  # noqa: E402
from train_sim.zone import TrainReport, ZoneController, ZoneParams  # noqa: E402
from train_sim.zone_fuzz import EXPECTED, corrupt_reports  # noqa: E402

LATENCY = 0.05  # s


def clean_reports(duration: float, seed: int) -> list:
    sc = load_scenario("metro_demo")
    res = simulate(sc, duration=duration, seed=seed)
    t, x, v = (np.asarray(res.truth[k], dtype=float) for k in ("t", "position", "velocity"))
    out = []
    for k in range(len(t)):
        vx = 0.25 + 1e-3 * k
        out.append(TrainReport(t_received=t[k] + LATENCY, stamp=t[k], position=x[k],
                               velocity=v[k], var_position=vx, var_velocity=0.01,
                               cov_position_velocity=0.02, cov_velocity_position=0.02))
    return out


def authority_key(zc, now):
    (a,) = zc.authorities(now, ["A"])
    return (round(a.end_of_authority, 6), a.emergency_brake, a.state)


def run(clean, seed, per_report, check_stamp_age):
    params = ZoneParams(danger_points=(load_scenario("metro_demo").line.length,),
                        check_stamp_age=check_stamp_age)
    ref = ZoneController(params)
    want = []
    for r in clean:
        ref.report("A", r)
        want.append(authority_key(ref, r.t_received))
    stream, counts = corrupt_reports(clean, np.random.default_rng(seed), per_report)
    zc = ZoneController(params)
    exceptions = good_refused = bad_accepted = wrong_kind = differ = 0
    k = 0
    t0 = time.perf_counter()
    for kind, r in stream:
        try:
            got = zc.report("A", r)
        except Exception:  # counted: the zone controller must never raise
            exceptions += 1
            continue
        if kind:
            bad_accepted += got == ""
            wrong_kind += bool(got) and got != EXPECTED[kind]
        else:
            good_refused += got != ""
            differ += authority_key(zc, r.t_received) != want[k]
            k += 1
    dt = time.perf_counter() - t0
    expected = Counter()
    for kind, n in counts.items():
        expected[EXPECTED[kind]] += n
    return {"corrupted": sum(counts.values()), "exceptions": exceptions,
            "good_refused": good_refused, "bad_accepted": bad_accepted,
            "wrong_kind": wrong_kind, "resets": sum(zc.clock_resets.values()),
            "authorities_differ": differ, "counts_match": dict(expected) == zc.rejected,
            "us_per_report": 1e6 * dt / len(stream)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--duration", type=float, default=3600.0, help="s of simulated run")
    ap.add_argument("--per-report", type=float, default=10.0)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    if args.quick:
        args.seeds, args.duration = 1, 300.0
    cols = ("corrupted", "exceptions", "good_refused", "bad_accepted", "wrong_kind", "resets",
            "authorities_differ", "counts_match", "us_per_report")
    w = [len(c) + 2 for c in cols]
    print(f"{'mode':<10}" + "".join(f"{c:>{n}}" for c, n in zip(cols, w)))
    ok = True
    for check_stamp_age in (True, False):
        tot: Counter = Counter()
        match = True
        for seed in track(range(args.seeds), f"zone fuzz (stamp age {check_stamp_age})"):
            clean = clean_reports(args.duration, seed)
            r = run(clean, 1000 + seed, args.per_report, check_stamp_age)
            match &= r.pop("counts_match")
            us = r.pop("us_per_report")
            tot.update(r)
            tot["us"] += us / args.seeds
        mode = "one clock" if check_stamp_age else "separate"
        row = [tot[c] for c in cols[:-2]]
        print(f"{mode:<10}" + "".join(f"{v:>{n}}" for v, n in zip(row, w))
              + f"{str(match):>{w[-2]}}" + f"{tot['us']:>{w[-1]}.1f}")
        ok &= match and not any(tot[c] for c in cols[1:-2])
    print("PASS" if ok else "FAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
