#!/usr/bin/env python3
"""Power and false-alarm rate of diagnose's test of the balise readings' scatter.

    ./run bench balise_scatter --quick         # 8 bags per row: about 1 min
    ./run bench balise_scatter --seeds 20      # 20 bags per row
    ./run bench balise_scatter --checks --seeds 20   # the correlation and dependence tests

The scatter test (docs/diagnose.md, "What is left"; ``balise_rounds.scatter_round``) on its own, in
the first round of the structure test under the believed model, at its share of diagnose's
alpha (0.001 over the round's nine tests): bags of ``train_sim.cases`` (case seed [S, 31],
family drawn: metro, metro_demo, regional, high-speed) whose balise reader's errors are k
times the SD the readings state (k = 1: nominal, the false-alarm rate; k = 2, 3: power). The
readings keep stating the believed train's variance. Per row: bags, found, the sum of squares
over its degrees of freedom (the variance scale; k^2 expected) and the p-values' range.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import io
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

# the round's share of diagnose's alpha: 1e-3 over its families (5), the odometer's, the two
# balise tests, the latency's and the datum's (phases.structure)
ROUND_ALPHA = 1e-3 / 9


@functools.lru_cache(maxsize=12)
def nominal_bag(seed: int):
    """``(case, data)``: case ``seed`` (``train_sim.cases``, [seed, 31], its family drawn) and
    its nominal bag as diagnose reads it. Kept, with its arrays read-only: the false-alarm tests
    of the balise and odometer checks read the same twelve bags (generating each took about a
    second, three times over)."""
    from train_sim.cases import make_case

    case = make_case(np.random.default_rng([seed, 31]), None, "plain")
    data = _bag(case.scenario)
    for f in dataclasses.fields(data):
        a = getattr(data, f.name)
        if isinstance(a, np.ndarray):
            a.flags.writeable = False
    return case, data


def _bag(scenario):
    """The measured data of ``scenario``'s bag, generated into a temporary folder and read back as
    diagnose reads a bag."""
    from train_estimation.tools.diagnose import read_measured
    from train_sim.generate import generate

    with tempfile.TemporaryDirectory() as d:
        with contextlib.redirect_stdout(io.StringIO()):
            generate(scenario, Path(d) / "bag", measured=True)
        return read_measured(Path(d) / "bag")


def _case(seed: int, k: float = 1.0, error=None):
    """(Motion, Stage under the believed model, family) of case ``seed``'s bag, its balise
    reader's errors ``k`` times the stated SD; ``error(rng, speed, sd)``: instead, the reader
    reads without error and each reading gets ``error``'s value (m) added, ``speed`` the
    odometer's speed at the readings, ``sd`` the stated SD (rng: [seed, 37])."""
    from train_estimation.core.offline.diagnose.motion import Motion
    from train_estimation.core.offline.diagnose.run import DiagConfig, prepare
    from train_estimation.core.offline.diagnose.stage import Null, Stage
    from train_sim.cases import make_case

    if k == 1.0 and error is None:  # the reader as stated: the nominal bag
        case, data = nominal_bag(seed)
        sc, train = case.scenario, case.scenario.train
    else:
        case = make_case(np.random.default_rng([seed, 31]), None, "plain")
        sc, train = case.scenario, case.scenario.train
        sd = k * train.balise_position_std if error is None else 1e-6
        data = _bag(sc.with_changes(train=dataclasses.replace(train, balise_position_std=sd)))
    pos = data.balise_position
    if error is not None:
        v = np.interp(data.balise_stamp, data.odo_stamp, data.odo_speed)
        pos = pos + error(np.random.default_rng([seed, 37]), v, train.balise_position_std)
    data = dataclasses.replace(data, balise_position=pos, balise_variance=np.full(
        data.balise_variance.size, train.balise_position_variance))
    cfg = DiagConfig()
    run = prepare(data, sc.line, cfg, train)
    mo = Motion(run, sc.line, train, cfg)
    null = Null(shift=Stage(mo, Null(), cfg).nuisance_shift()[0])
    return mo, Stage(mo, null, cfg, big=False), case.family


def scatter_on_case(seed: int, k: float = 1.0, alpha: float = ROUND_ALPHA) -> dict:
    """The scatter test's figures (``scatter_round``) on case ``seed``'s bag, its balise
    reader's errors ``k`` times the stated SD; plus ``family``."""
    from train_estimation.core.offline.diagnose.balise_rounds import scatter_round

    mo, st, family = _case(seed, k)
    out = scatter_round(mo, st, None, [], alpha)
    out["family"] = family
    return out


def _ar1(rho: float):
    """A reader error that varies slowly: AR(1) from one reading to the next, correlation
    ``rho``, the stated SD as its marginal SD (the scatter as stated)."""
    def error(rng, v, sd):
        e = np.empty(v.size)
        x = sd * rng.standard_normal()
        for j in range(v.size):
            e[j] = x
            x = rho * x + math.sqrt(1.0 - rho * rho) * sd * rng.standard_normal()
        return e
    return error


def _jitter(rng, v, sd):
    """A reader's timing jitter: each error's SD in proportion to the speed the balise was
    passed at, the stated SD at the readings' RMS speed (the scatter as stated on the whole)."""
    return sd * v / math.sqrt(float(np.mean(v * v))) * rng.standard_normal(v.size)


# the balise readings' residual checks' effects (none: the reader as stated)
EFFECTS = {"none": None, "ar1_0.9": _ar1(0.9), "ar1_0.7": _ar1(0.7), "jitter": _jitter}


def checks_on_case(seed: int, effect: str = "none", alpha: float = 1e-3) -> dict:
    """diagnose's balise readings' checks (``phases.balise_residuals``, at its ``alpha``) under
    the believed model on case ``seed``'s bag with the reader's ``effect`` (:data:`EFFECTS`);
    plus ``family``."""
    from train_estimation.core.offline.diagnose.phases import balise_residuals

    mo, st, family = _case(seed, error=EFFECTS[effect])
    out = balise_residuals(mo, st.null, st.cfg, (st.q, st.r_s), [], alpha)
    out["family"] = family
    return out


def _checks_table(n: int) -> int:
    from train_estimation.core.offline.fleet_readers import reader_consensus

    print("| reader | bags | tested (>= 8 readings) | readings | found (alpha 1e-3) | "
          "correlation | speed | distance | the bags pooled (fleet): readings, p corr / speed "
          "/ dist |")
    print("|---|---|---|---|---|---|---|---|---|")
    for effect in EFFECTS:
        rows = []
        for seed in range(n):
            r = checks_on_case(seed, effect)
            rows.append(r)
            print(f"  seed {seed} {r['family']}: {r['readings']} readings, "
                  + (", ".join(f"{k} p {r[k]['p']:.2g}" for k in ("correlation", "speed",
                                                                    "distance") if "p" in r[k])
                     if r["tested"] else r.get("note", "")), file=sys.stderr, flush=True)
        tested = [r for r in rows if r["tested"]]
        k = [r["readings"] for r in rows]
        hits = {c: sum(r[c]["finding"] for r in tested) for c in ("correlation", "speed",
                                                                  "distance")}
        # the same bags as one reader's passes (core.offline.fleet_readers, alpha 1e-3)
        pool = reader_consensus([{"train": "T", "time": float(i), "balise": r["innovations"]}
                                 for i, r in enumerate(rows) if r.get("innovations")], 1e-3)
        pr = pool["trains"].get("T") or {}
        ps = " / ".join(f"{pr[c]['p']:.2g}" if "p" in pr.get(c, {}) else "-"
                        for c in ("correlation", "speed", "distance"))
        print(f"| {effect} | {n} | {len(tested)} | {min(k)}-{max(k)} | "
              f"{sum(r['finding'] for r in tested)} | {hits['correlation']} | {hits['speed']} | "
              f"{hits['distance']} | {pr.get('readings', 0)}, {ps} |", flush=True)
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="8 bags per row")
    ap.add_argument("--seeds", type=int, default=20, help="bags per row (default 20)")
    ap.add_argument("--k", type=float, nargs="*", default=[1.0, 2.0, 3.0],
                    help="the reader's errors over the stated SD, one row each")
    ap.add_argument("--checks", action="store_true",
                    help="instead, the readings' correlation in time and dependence on speed "
                         "and distance (phases.balise_residuals, alpha 1e-3), one row per "
                         "reader effect: " + ", ".join(EFFECTS))
    args = ap.parse_args(argv)
    n = 8 if args.quick else args.seeds
    if n < 1 or any(not k > 0 for k in args.k):
        ap.error("--seeds must be >= 1 and every --k > 0")
    if args.checks:
        return _checks_table(n)
    print(f"| k (errors / stated SD) | bags | found (alpha {ROUND_ALPHA:.2g}) | families | "
          "variance scale | p |")
    print("|---|---|---|---|---|---|")
    for k in args.k:
        rows = []
        for seed in range(n):
            r = scatter_on_case(seed, k)
            rows.append(r)
            print(f"  seed {seed} {r['family']}: {r['readings']} readings, scale "
                  f"{r.get('ratio', float('nan')):.2f}, p {r.get('p', float('nan')):.2g}",
                  file=sys.stderr, flush=True)
        tested = [r for r in rows if "chi2" in r]
        fams = sorted({r["family"] for r in rows})
        ratio = [r["ratio"] for r in tested]
        ps = [r["p"] for r in tested]
        print(f"| {k:g} | {len(tested)} of {n} tested | {sum(r['significant'] for r in tested)}"
              f" | {', '.join(fams)} | {min(ratio):.2f}-{max(ratio):.2f} (median "
              f"{np.median(ratio):.2f}) | {min(ps):.2g} - {max(ps):.2g} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
