"""`fleet`: analyse every bag of a fleet on Dask and tell line-map errors from train faults.

Every bag is read once: its topics' health, identify's fit and diagnose's ranking; the
consensus across trains follows.

    fleet --manifest manifest.csv --out DIR [--workers 2 | --scheduler ADDRESS]
    fleet --bags FOLDER --line line.yaml --train train.yaml --out DIR

Input: a manifest (CSV with columns train, bag, line, train_file and optionally time, day; paths
relative to the manifest) or a folder searched for bags (rosbag2 directories); a folder's bag
belongs to the train named by its parent directory (FOLDER/T07/run3) or, for bags directly in
FOLDER, by its name up to the first "_" (T07_run3). Time orders a train's runs: the manifest's
``time`` column (any unit; the fleet simulator writes hours) or else the bag's first log time
in hours.

Every bag is analysed by one Dask task (an embedded LocalCluster of --workers processes, its
dashboard at --dashboard, printed; or the cluster at --scheduler, e.g. tcp://host:8786,
started with `./run scheduler` and `./run worker tcp://host:8786` on every machine with a
checkout): check_bag's topic health, identify's fit (braking rate, mass) and diagnose's
ranking. Before submitting, every worker is asked to import the analysis and read the first
bag's line and train files; a worker that cannot stops the run with one line saying what is
missing and how to start workers. A task's result is cached in DIR/cache under the SHA-256 of
the bag's files, the line and train files and the tool's version, so a rerun only analyses new
or changed bags. A bag that cannot be read or diagnosed is listed with its reason and the
others go on.

Days: every run adds its bags to DIR/history.jsonl (one row per bag, by content, with its day:
the manifest's ``day`` column, else --day, else today's UTC date), and the consensus is over
the history (--days N: its N latest days; --no-history: this run's bags only). A map error
seen on several days is confirmed by the other days' runs or withdrawn as one day's artefact
(core/offline/fleet.py); trends use the ``time`` column, which must then be on one clock across
days.

Output (DIR is created):
  DIR/runs.csv        one row per bag: status, reason, check_bag's received fractions, the
                      diagnosed cause, the accepted causes, the fitted gradient section and
                      resistance (diagnose), braking rate and mass (identify; diagnose where
                      identify cannot identify them) and odometer scale (diagnose) with
                      standard errors, time taken
  DIR/fleet.json      the consensus (train_estimation.core.offline.fleet: every test and its
                      numbers)
  DIR/report.md       the fleet report: map errors (where, how large, how many trains and runs
                      agree, how sure), per-line resistance, train alerts (which parameter,
                      departure from the fleet or trend, z and p), per-train tables, failed bags
  DIR/line_<NAME>.png the line's gradient profile with the flagged sections and every run's
                      section; DIR/trends.png: braking rate, mass and odometer scale per train
                      against time, alerted trains highlighted

Criteria (core/offline/fleet.py): a map error = a section found by >= 2 trains, by more runs than
spurious detections explain (binomial test, Bonferroni), with consistent values (Cochran's Q);
a train alert = |z| above the two-sided Student-t quantile, on the statistic's
Welch-Satterthwaite degrees of freedom, of alpha / (2 x trains x parameters) (Bonferroni: a
family-wise false-alarm rate --alpha, default 0.01), for the departure from the other trains'
median (leave-one-out, MAD spread) or for a trend in time; the report lists the critical value
applied to each train.

Reliability: the report's first line says how many bags failed and why (reasons grouped);
the consensus says it is unreliable where too few runs were analysed to find or exclude a map
error (fewer than n_min runs on a line, see core/offline/fleet.py) or to test departures (fewer than
three trains with values).

Exit status: 0 when the report was written; 1 when it was written but more than --max-failed
(default 0.1) of the bags failed; 2 when there is no usable input (no manifest or folder, a
malformed manifest row, no bag, bad YAML) or the cluster cannot run the analysis (no
scheduler, no worker, a worker without the project's environment): one line on stderr.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import hashlib
import json
import math
import os
import re
import sys
import time
from datetime import datetime
from pathlib import Path

from train_estimation.tools.common import EXIT_CHECK_FAILED, EXIT_OK, fail, json_default
from train_estimation.tools.fleet_dask import VERSION, ClusterError, run_tasks
from train_estimation.tools.fleet_report import (
    failure_groups,
    failure_line,
    plot_line,
    plot_trends,
    report_md,
    write_csv,
)
from train_estimation.tools.fleet_row import BagRow, consensus_rows
from train_estimation.tools.report_html import write_report_html

# ------------------------------------------------------------------------------------------------
# Inputs
# ------------------------------------------------------------------------------------------------

class InputError(ValueError):
    """No usable input (exit 2)."""


def is_bag(p: Path) -> bool:
    return p.is_dir() and (p / "metadata.yaml").is_file()


# the manifest's columns -> the kind of value each holds (extra columns are allowed: the
# shared rule of every reader, train_core.config.unknown_key)
MANIFEST_COLUMNS = {"train": "string", "bag": "string", "line": "string",
                    "train_file": "string", "time": "number", "day": "string"}


def _check_columns(path: str, header: list, rows: list[dict]) -> None:
    """Extra columns: named in a warning with their near misses; a typo of an absent column
    whose cells hold that column's kind (``tmie`` with numbers, no ``time``) is an error."""
    from train_core.config import unknown_key, warn_unknown

    for col in header:
        if col in MANIFEST_COLUMNS or col is None:
            continue
        cell = next((r[col].strip() for r in rows if (r.get(col) or "").strip()), "")
        try:
            value = float(cell)
        except ValueError:
            value = cell
        msg = unknown_key(col, value, MANIFEST_COLUMNS, header, path, what="column")
        if msg is not None:
            warn_unknown(msg)


def read_manifest(path: str) -> list[dict]:
    """The manifest's tasks; a malformed row is an InputError naming its line (exit 2)."""
    base = Path(path).resolve().parent
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:  # a spreadsheet's BOM
            reader = csv.DictReader(fh)
            rows = [(reader.line_num, r) for r in reader]
            header = reader.fieldnames or []
    except OSError as exc:
        raise InputError(f"cannot read the manifest {path}: {exc.strerror}") from exc
    except (csv.Error, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not a CSV manifest ({exc})") from exc
    need = ("train", "bag", "line", "train_file")
    if rows:
        _check_columns(path, header, [r for _, r in rows])
    if not rows or not set(need) <= set(header):
        raise InputError(f"{path}: a manifest is a CSV with columns train, bag, line, "
                         f"train_file[, time][, day] (got {sorted(header) if rows else 'no rows'})")
    tasks = []
    for num, r in rows:
        if None in r:  # more cells than the header has columns
            raise InputError(f"{path} line {num}: {len(header) + len(r[None])} cells, the "
                             f"header has {len(header)} ({', '.join(header)})")
        empty = [k for k in need if not (r.get(k) or "").strip()]
        if empty:
            raise InputError(f"{path} line {num}: no {', '.join(empty)} (a row needs "
                             f"{', '.join(need)}; {len([v for v in r.values() if v])} of "
                             f"{len(header)} cells given)")
        t = {k: r[k].strip() if os.path.isabs(r[k].strip()) else str(base / r[k].strip())
             for k in ("bag", "line", "train_file")}
        t["train"] = r["train"].strip()
        tm = (r.get("time") or "").strip()
        try:
            t["time"] = float(tm) if tm else None
        except ValueError:
            raise InputError(f"{path} line {num}: time {tm!r} is not a number") from None
        if t["time"] is not None and not math.isfinite(t["time"]):
            raise InputError(f"{path} line {num}: time {tm!r} is not finite")
        day = (r.get("day") or "").strip()
        t["day"] = _day(day, f"{path} line {num}") if day else None
        t["where"] = f"{path} line {num}"
        tasks.append(t)
    return tasks


def _day(text: str, where: str) -> str:
    """A day label as YYYY-MM-DD (2026-11-8 written as 2026-11-08): the history's days are
    ordered as text, so another form (30.11.2026, or 2026-11-8 before 2026-11-10) would keep
    the wrong days in --days' window."""
    try:
        return datetime.strptime(text, "%Y-%m-%d").date().isoformat()
    except ValueError:
        raise InputError(f"{where}: day {text!r} is not a date YYYY-MM-DD") from None


def _cached(f: Path) -> BagRow | None:
    """The cached row in ``f``, or None: absent, or not a row this version wrote whole (a
    file cut off by a killed run, or edited): the bag is analysed again."""
    if not f.is_file():
        return None
    try:
        return BagRow.from_json(json.loads(f.read_text()))
    except (OSError, ValueError, TypeError, KeyError, AttributeError):
        return None


def _file_name(name: str) -> str:
    """A line's name as a file name: what is not a letter, digit, '-', '_' or '.' becomes '_'
    (a line named S1/S12 or ../x must not name a folder)."""
    out = re.sub(r"[^A-Za-z0-9._-]", "_", name).lstrip(".")
    return out or "line"


def read_folder(folder: str, line: str, train: str) -> list[dict]:
    root = Path(folder)
    if not root.is_dir():
        raise InputError(f"{folder}: not a directory")
    bags = sorted({p.parent for p in root.rglob("metadata.yaml")})
    tasks = []
    for b in bags:
        tid = b.parent.name if b.parent != root else b.name.split("_")[0]
        tasks.append({"train": tid, "bag": str(b), "line": str(Path(line).resolve()),
                      "train_file": str(Path(train).resolve()), "time": None})
    return tasks


def content_key(task: dict) -> str:
    """SHA-256 over the bag's files (names and bytes), the line and train files and VERSION."""
    h = hashlib.sha256(VERSION.encode())
    bag = Path(task["bag"])
    files = sorted(p for p in bag.rglob("*") if p.is_file()) if bag.is_dir() else [bag]
    for p in files:
        h.update(str(p.relative_to(bag) if bag.is_dir() else p.name).encode())
        try:
            with open(p, "rb") as fh:
                for chunk in iter(lambda: fh.read(1 << 20), b""):
                    h.update(chunk)
        except OSError:
            h.update(b"unreadable")
    for k in ("line", "train_file"):
        try:
            h.update(Path(task[k]).read_bytes())
        except OSError:
            h.update(b"missing " + task[k].encode())
    return h.hexdigest()


def merge_history(path: Path, rows: list[BagRow], day: str) -> list[BagRow]:
    """Add this run's rows to the history (one JSON row per bag, by content key; a bag seen
    before keeps its first day unless the manifest names one) and return every row, dated."""
    hist: dict = {}
    if path.is_file():
        with open(path) as fh:
            for n, line in enumerate(fh, 1):
                try:
                    d = json.loads(line)
                    hist[d["key"]] = BagRow.from_json(d)
                except (ValueError, KeyError, TypeError) as exc:
                    print(f"fleet: {path} line {n}: not a history row ({exc}), skipped",
                          file=sys.stderr)
    for r in rows:
        old = hist.get(r.key)
        hist[r.key] = dataclasses.replace(
            r, day=r.manifest_day or (old.day if old is not None else None) or day)
    tmp = path.with_suffix(".tmp")
    with open(tmp, "w") as fh:
        for r in hist.values():
            fh.write(json.dumps(r.to_json(), default=json_default) + "\n")
    os.replace(tmp, path)  # a killed run leaves the old history whole
    return list(hist.values())


def window(rows: list[BagRow], days: int) -> list[BagRow]:
    """The rows of the ``days`` latest days (day labels in sort order; 0: every day)."""
    if days <= 0:
        return rows
    keep = set(sorted({str(r.day) for r in rows})[-days:])
    return [r for r in rows if str(r.day) in keep]


# ------------------------------------------------------------------------------------------------
# CLI
# ------------------------------------------------------------------------------------------------

# failures of the worker rather than of the bag: analysed again next time
_NOT_CACHED = ("task failed", "ModuleNotFoundError", "ImportError", "MemoryError")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="fleet", description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="\n".join(__doc__.splitlines()[2:]))
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--manifest", help="CSV: train, bag, line, train_file[, time][, day]")
    src.add_argument("--bags", metavar="FOLDER", help="folder searched for bags")
    p.add_argument("--line", help="line.yaml for every bag of --bags")
    p.add_argument("--train", help="train.yaml for every bag of --bags")
    p.add_argument("--out", required=True, help="output directory (created)")
    p.add_argument("--workers", type=int, default=2,
                   help="worker processes of the embedded LocalCluster (default 2)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="use the Dask cluster at ADDRESS (e.g. tcp://host:8786) instead; start "
                        "it with ./run scheduler and its workers with ./run worker ADDRESS")
    p.add_argument("--dashboard", default="127.0.0.1:8787", metavar="HOST:PORT",
                   help="the embedded cluster's dashboard (default 127.0.0.1:8787; a taken "
                        "port is replaced by a free one; the link is printed)")
    p.add_argument("--no-dashboard", action="store_true", help="no dashboard")
    p.add_argument("--wait", type=float, default=60.0, metavar="S",
                   help="seconds to wait for the scheduler and a first worker (default 60)")
    p.add_argument("--max-failed", type=float, default=0.1, metavar="FRACTION",
                   help="exit 1 when more than this share of the bags failed (default 0.1; "
                        "the report is written all the same)")
    p.add_argument("--day", default=None,
                   help="the day these bags belong to in the history (default: the "
                        "manifest's day column, else today's UTC date)")
    p.add_argument("--days", type=int, default=0, metavar="N",
                   help="consensus over the N latest days of the history (default 0: all)")
    p.add_argument("--no-history", action="store_true",
                   help="consensus over this run's bags only; OUT/history.jsonl is not touched")
    p.add_argument("--cache", default=None, help="cache directory (default OUT/cache)")
    p.add_argument("--alpha", type=float, default=0.01,
                   help="family-wise false-alarm rate of the consensus tests (default 0.01)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    args = p.parse_args(argv)
    from train_core.config import ConfigError
    from train_core.model import load_line

    from train_estimation.core.offline.fleet import FleetConfig, consensus

    t0 = time.perf_counter()
    try:
        if not 0.0 <= args.max_failed <= 1.0:
            raise InputError(f"--max-failed {args.max_failed}: a fraction in [0, 1]")
        if args.day is not None:
            args.day = _day(args.day, "--day")
        if args.manifest:
            tasks = read_manifest(args.manifest)
        else:
            if not (args.line and args.train):
                raise InputError("--bags needs --line and --train")
            tasks = read_folder(args.bags, args.line, args.train)
        if not tasks:
            raise InputError("no bag found")
        lines = {}
        for t in tasks:
            if t["line"] not in lines:
                lines[t["line"]] = load_line(t["line"])
    except (InputError, ConfigError) as exc:
        return fail("fleet", str(exc))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cache = Path(args.cache) if args.cache else out / "cache"
    cache.mkdir(parents=True, exist_ok=True)
    rows, todo = [], []
    seen: dict = {}
    for t in tasks:
        t["key"] = content_key(t)
        if t["key"] in seen:  # one run under two rows: it would count twice, under one train
            first = seen[t["key"]]
            same = "the same bag as" if Path(first["bag"]) == Path(t["bag"]) else \
                f"{t['bag']} holds the same files as {first['bag']} at"
            return fail("fleet", f"{t.get('where', t['bag'])}: {same} "
                                 f"{first.get('where', first['bag'])} (train {first['train']}): "
                                 f"list each run once")
        seen[t["key"]] = t
    for t in tasks:
        f = cache / f"{t['key']}.json"
        cached = _cached(f)
        if cached is not None:
            row = dataclasses.replace(cached, train=t["train"], bag=t["bag"], cached=True)
            if t.get("time") is not None:
                row = dataclasses.replace(row, time=t["time"])
            rows.append(row)
        else:
            todo.append(t)
    where = (f"the cluster at {args.scheduler}" if args.scheduler else
             f"a local Dask cluster of {args.workers} worker processes")
    info = {"when": time.strftime("%Y-%m-%d %H:%M"), "cached": len(tasks) - len(todo),
            "computed": len(todo), "workers": where}
    if todo:
        print(f"fleet: {len(tasks)} bags, {len(tasks) - len(todo)} cached, {len(todo)} to "
              f"analyse on {where}", file=sys.stderr)
        t1 = time.perf_counter()
        try:
            new = run_tasks(todo, args.workers, args.scheduler, not args.quiet,
                            dashboard=None if args.no_dashboard else args.dashboard,
                            wait_s=args.wait, info=info)
        except ClusterError as exc:
            return fail("fleet", str(exc))
        wall = time.perf_counter() - t1
        new = [dataclasses.replace(r, cached=False) for r in new]
        for r in new:
            if not str(r.error or "").startswith(_NOT_CACHED):
                # written whole or not at all: a run killed mid-write leaves no half entry
                f = cache / f"{r.key}.json"
                tmp = f.with_suffix(".json.part")
                tmp.write_text(json.dumps(r.to_json(), default=json_default))
                os.replace(tmp, f)
        rows += new
    else:
        wall = 0.0
    info["wall_s"] = wall
    by_key = {t["key"]: t for t in tasks}
    rows = [dataclasses.replace(r, manifest_day=by_key[r.key].get("day")) for r in rows]
    day = args.day or time.strftime("%Y-%m-%d", time.gmtime())
    if args.no_history:
        rows = [dataclasses.replace(r, day=r.manifest_day or day) for r in rows]
        pool = rows
    else:
        pool = window(merge_history(out / "history.jsonl", rows, day), args.days)
    info["days"] = sorted({str(r.day) for r in pool})
    info["pool"] = len(pool)
    res = consensus(consensus_rows(pool), FleetConfig(alpha=args.alpha))
    write_csv(rows, out / "runs.csv")
    plots = []
    crow = consensus_rows([r for r in pool if not r.error])
    by_name = {}
    for ln in lines.values():
        by_name.setdefault(ln.name, ln)
    for name, d in res.lines.items():
        if name in by_name:
            fn = f"line_{_file_name(name)}.png"
            plot_line(name, by_name[name], dict(d, _runs=[r for r in crow if r["line"] == name]),
                      out / fn)
            plots.append(fn)
    if res.trains["parameters"]:
        plot_trends(res.trains, out / "trends.png")
        plots.append("trends.png")
    n_bad = sum(1 for r in rows if r.error)
    too_many = n_bad > args.max_failed * len(rows)
    info["max_failed"] = args.max_failed
    (out / "report.md").write_text(report_md(res, rows, info, plots))
    (out / "fleet.json").write_text(json.dumps(
        {"map_errors": res.map_errors, "train_alerts": res.train_alerts, "lines": res.lines,
         "trains": res.trains, "config": res.config, "reliability": res.reliability,
         "balise_readers": res.readers, "failures": failure_groups(rows), "run": info},
        indent=1, default=json_default))
    print(f"fleet: {len(rows)} bags ({n_bad} failed), {len(todo)} analysed in {wall:.0f} s, "
          f"total {time.perf_counter() - t0:.0f} s; consensus over {len(pool)} runs of "
          f"{len(info['days'])} days")
    for m in res.map_errors:
        print(f"map error: line {m['line']} [{m['start']:.0f}, {m['end']:.0f}) m "
              f"{m['permille']:+.2f} +- {m['se']:.2f} per mille ({len(m['trains_found'])} "
              f"trains, {m['runs_found']}/{m['runs_passed']} runs)")
    for a in sorted(res.train_alerts, key=lambda a: (a["train"], a["parameter"])):
        print(f"train alert: {a['train']} {a['parameter']} {a['kind']} (z = {a['z']:+.1f})")
    for a in res.readers.get("alerts", []):
        print(f"balise reader: {a['train']} {a['signature']} ({a['runs']} runs)")
    for why in res.reliability.get("reasons", []):
        print(f"unreliable: {why}")
    print(f"wrote {out / 'report.md'}, {write_report_html(out, 'fleet')}, {out / 'runs.csv'}, "
          f"{out / 'fleet.json'}")
    if too_many:
        print(f"fleet: {failure_line(rows)} (more than --max-failed {args.max_failed:g})",
              file=sys.stderr)
        return EXIT_CHECK_FAILED
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
