#!/usr/bin/env python3
"""Verdict parity of `diagnose` through a bag and through a recorder's CSV log (`csv2bag`).

    ./run bench csv2bag [--quick] [--seeds N] [--causes a,b,...]

(``--causes`` and ``--first-seed`` run a subset and add its rows to the last results in
benchmarks/out/, e.g. more seeds after ``--quick``: ``--first-seed 1 --seeds 2 --causes ...``.)

For each cause of ``train_sim.cases`` (and ``none``) a case is simulated into a measured bag;
an independent writer (tests/helpers/recorder_csv.py: reads the bag's MCAP with the mcap
libraries, one CSV row per message in log-time order, a lost sample has no row) writes the same
run as a CSV log three ways, and `csv2bag` turns each back into a bag:

- **counter**: with the odometer's sample counter column;
- **missing rows**: without it: the link's losses are only rows missing from the log, and
  csv2bag numbers the samples from the train clock's period;
- **losses hidden**: a counter that numbers the log's rows (a log that counts what it wrote),
  which hides the losses, as a conversion by row number did.

`diagnose` then runs on the bag and on each converted bag, as a user runs it. Printed (and
written to benchmarks/out/csv2bag.md): per case the verdict each way, whether the CSV ways
agree with the bag, and the samples csv2bag counted lost against the bag's own count.
``--quick``: one seed per cause (13 cases, about 6 min on this 2-core machine).
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import io
import json
import os
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = os.path.join(HERE, "out")
sys.path.insert(0, os.path.join(HERE, "..", "tests", "helpers"))

from recorder_csv import write_csv  # noqa: E402
from train_core.progress import track  # noqa: E402

from train_sim.cases import CAUSES, make_case  # noqa: E402

WAYS = ("seq", "none", "rows")  # recorder_csv counters: counter, missing rows, losses hidden
LABEL = {"seq": "CSV, counter", "none": "CSV, losses as missing rows",
         "rows": "CSV, losses hidden"}


def _verdict(bag: str, paths: dict, out: str) -> str:
    from train_estimation.tools import diagnose

    with contextlib.redirect_stdout(io.StringIO()), \
            contextlib.redirect_stderr(io.StringIO()) as err:
        rc = diagnose.main(["--bag", bag, "--line", str(paths["line"]), "--train",
                            str(paths["train"]), "--out", out, "--quiet", "--no-plots"])
    if rc != 0:
        return f"exit {rc}: {err.getvalue().strip()[:80]}"
    with open(os.path.join(out, "report.json")) as fh:
        return json.load(fh)["cause"]


def _lost_in_bag(bag: str) -> int:
    from train_core.bagio import read_bag

    seq = np.array([f["seq"] for _, _, f in read_bag(bag).topics["odometer"]])
    u = np.unique(seq)
    return int(u[-1] - u[0] + 1 - u.size)


def run_case(cause: str, seed: int) -> dict:
    from train_estimation.tools import csv2bag
    from train_sim.generate import generate

    rng = np.random.default_rng([seed, 48, (CAUSES + ("none",)).index(cause)])
    case = make_case(rng, None if cause == "none" else cause, "plain")
    row = {"cause": cause, "seed": seed}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench_csv2bag_") as d:
        paths = case.write(os.path.join(d, "case"))
        bag = os.path.join(d, "bag")
        generate(case.scenario, bag, measured=True)
        row["bag"] = _verdict(bag, paths, os.path.join(d, "diag_bag"))
        row["lost_bag"] = _lost_in_bag(bag)
        for way in WAYS:
            csv, mp, out = (os.path.join(d, f"{way}{x}") for x in (".csv", ".yaml", "_bag"))
            write_csv(bag, csv, mp, counter=way)
            with contextlib.redirect_stdout(io.StringIO()), \
                    contextlib.redirect_stderr(io.StringIO()) as err:
                rc = csv2bag.main([csv, "--map", mp, "--out", out])
            if rc != 0:
                row[way] = f"csv2bag exit {rc}: {err.getvalue().strip()[:80]}"
                continue
            row[way] = _verdict(out, paths, os.path.join(d, f"diag_{way}"))
            row[f"lost_{way}"] = _lost_in_bag(out)
    row["time"] = time.perf_counter() - t0
    return row


def table(rows: list[dict]) -> str:
    head = ("| cause | seed | bag | " + " | ".join(LABEL[w] for w in WAYS)
            + " | lost samples: bag / counted from missing rows |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        cells = [r["bag"]] + [r[w] + ("" if r[w] == r["bag"] else " (differs)") for w in WAYS]
        lines.append(f"| {r['cause']} | {r['seed']} | " + " | ".join(cells)
                     + f" | {r['lost_bag']} / {r.get('lost_none', '-')} |")
    n = len(rows)
    same = {w: sum(r[w] == r["bag"] for r in rows) for w in WAYS}
    lines.append("")
    lines.append("Same verdict as through the bag: " + "; ".join(
        f"{LABEL[w]} {same[w]}/{n}" for w in WAYS) + ".")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="\n".join(__doc__.splitlines()[2:]))
    p.add_argument("--quick", action="store_true", help="one seed per cause (the default)")
    p.add_argument("--seeds", type=int, default=1, help="seeds per cause (default 1)")
    p.add_argument("--first-seed", type=int, default=0,
                   help="the seeds are FIRST .. FIRST + SEEDS - 1 (default 0)")
    p.add_argument("--causes", default=None,
                   help=f"comma-separated subset of none, {', '.join(CAUSES)}")
    args = p.parse_args(argv)
    causes = ("none",) + CAUSES
    if args.causes:
        causes = tuple(c.strip() for c in args.causes.split(","))
        bad = [c for c in causes if c not in ("none",) + CAUSES]
        if bad:
            p.error(f"unknown cause(s) {bad}")
    seeds = 1 if args.quick else args.seeds
    specs = [(c, s) for c in causes
             for s in range(args.first_seed, args.first_seed + seeds)]
    rows = [run_case(c, s) for c, s in track(specs, "csv2bag parity")]
    os.makedirs(OUT, exist_ok=True)
    raw = os.path.join(OUT, "csv2bag.json")
    partial = args.causes or args.first_seed
    if partial and os.path.exists(raw):  # a subset adds to (replaces in) the last results
        done = {(c, s) for c, s in specs}
        with open(raw) as fh:
            old = [r for r in json.load(fh) if (r["cause"], r["seed"]) not in done]
        order = ("none",) + CAUSES
        rows = sorted(old + rows, key=lambda r: (order.index(r["cause"]), r["seed"]))
    text = table(rows)
    print(text)
    stamp = datetime.date.today().isoformat()
    cmd = "./run bench csv2bag " + " ".join(argv if argv is not None else sys.argv[1:])
    with open(os.path.join(OUT, "csv2bag.md"), "w") as fh:
        fh.write(f"`{cmd.strip()}` ({stamp})\n\n{text}\n")
    with open(raw, "w") as fh:
        json.dump(rows, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
