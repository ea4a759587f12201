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
import hashlib
import json
import math
import os
import sys
import time
import traceback
from pathlib import Path

import numpy as np

from train_estimation.tools.common import EXIT_CHECK_FAILED, EXIT_OK, fail, json_default
from train_estimation.tools.report_html import write_report_html

VERSION = "fleet-3"  # part of the cache key: bump when a task's result changes meaning
PARAMS = ("braking_rate", "mass", "odometer_scale")


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
        with open(path, newline="") as fh:
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
        t["day"] = day or None
        tasks.append(t)
    return tasks


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


# ------------------------------------------------------------------------------------------------
# One bag (a Dask task: pure Python, no rclpy)
# ------------------------------------------------------------------------------------------------

def analyse_bag(task: dict) -> dict:
    """check_bag + identify + diagnose of one bag -> one flat row. Never raises: a failure is
    a row with ``error`` set (the reason in one line)."""
    t0 = time.perf_counter()
    row = {"train": task["train"], "bag": task["bag"], "line_file": task["line"],
           "train_file": task["train_file"], "time": task.get("time"), "key": task.get("key"),
           "error": None}
    try:
        row.update(_analyse(task))
    except Exception as exc:  # noqa: BLE001 - any failure of one bag is reported, not fatal
        row["error"] = f"{type(exc).__name__}: {' '.join(str(exc).split())}"[:300]
        row["traceback_at"] = traceback.extract_tb(exc.__traceback__)[-1].name
    row["seconds"] = round(time.perf_counter() - t0, 2)
    return row


def _analyse(task: dict) -> dict:
    """One bag, read once: its topics' health, identify's fit and diagnose's ranking."""
    from train_core.bagio import read_bag
    from train_core.model import load_line, load_train

    from train_estimation.core.offline.diagnose import diagnose
    from train_estimation.core.offline.measured import TOPICS, MeasuredRun, topic_health

    line, train = load_line(task["line"]), load_train(task["train_file"])
    out: dict = {"line": line.name}
    bag = read_bag(task["bag"], topics=TOPICS)
    # topic health (check_bag's received fractions, gaps)
    for tp in TOPICS:
        h = topic_health(bag, tp)
        out[f"{tp}_count"] = h.get("count", 0)
        if "received_fraction" in h:
            out[f"{tp}_received"] = round(h["received_fraction"], 4)
    data = MeasuredRun.from_bag(bag)
    if task.get("time") is None:
        out["time"] = float(np.min(data.odo_recv)) / 3600.0 if data.odo_recv.size else 0.0
    out["duration_s"] = float(np.ptp(data.odo_stamp)) if data.odo_stamp.size else 0.0
    out.update(_identify(data, line, train))
    dg = diagnose(data, line, train)
    out.update(diagnosis_row(dg, train))
    # braking rate and mass for the trends: identify's (one constant f per run, the quantity
    # tracked over runs; diagnose fits f at the first and last message, which one braking
    # phase leaves poorly determined), diagnose's where identify cannot identify them
    for p in ("braking_rate", "mass"):
        out[f"{p}_source"] = "diagnose" if out.get(f"{p}_se") else None
        v, se = out.get(f"identify_{p}"), out.get(f"identify_{p}_se")
        if v is not None and se is not None and math.isfinite(se) and se > 0:
            out[p], out[f"{p}_se"], out[f"{p}_source"] = v, se, "identify"
    pos = np.asarray(dg.series.get("position", []), float)
    pos = pos[np.isfinite(pos)]
    out["coverage"] = [float(pos.min()), float(pos.max())] if pos.size else None
    return out


def _identify(data, line, train) -> dict:
    """identify's braking rate and mass (its record puts control on the train clock)."""
    from train_estimation.core.offline.identify import IdentificationError, identify

    d = data.to_identify()  # a bag without odometer or control fails here, as a row
    try:
        res = identify(d, line, train)
    except (IdentificationError, np.linalg.LinAlgError, ValueError) as exc:
        return {"identify_error": " ".join(str(exc).split())[:200]}
    out = {}
    for name, key in (("braking_rate", "braking_rate"), ("mass", "mass")):
        if res.identifiable.get(key):
            out[f"identify_{name}"] = float(res.values[key]) if key in res.values else None
            out[f"identify_{name}_se"] = float(res.std_errors.get(key, math.nan))
    return out


def diagnosis_row(dg, train) -> dict:
    """The consensus inputs of one diagnosis (plain JSON types): its verdict, the accepted
    causes, and what each ranked cause says the fleet tracks of it (``Cause.fleet_row``: an
    accepted gradient section, the braking rate, mass, odometer scale and resistance force with
    their standard errors)."""
    from train_estimation.core.offline.diagnose import BY_NAME, jsonable

    accepted = [a.cause for a in dg.accepted]
    out = {"cause": dg.cause, "accepted": "+".join(accepted)}
    ranked = {r.cause: r for r in dg.ranking if r.cause in BY_NAME}
    for name, fit in ranked.items():
        out.update(BY_NAME[name].fleet_row(fit, dg.evidence.get(name) or {}, name in accepted,
                                           train))
    return jsonable(out)


def consensus_rows(rows: list[dict]) -> list[dict]:
    """The table's rows in core.offline.fleet's input format."""
    out = []
    for r in rows:
        c = {"train": r["train"], "line": r.get("line") or Path(r["line_file"]).stem,
             "time": r.get("time") or 0.0, "bag": r["bag"], "error": r.get("error"),
             "coverage": r.get("coverage"), "day": r.get("day")}
        if r.get("gradient_se"):
            c["gradient"] = {"start": r["gradient_start"], "end": r["gradient_end"],
                             "permille": r["gradient_permille"], "se": r["gradient_se"],
                             "v2": r.get("gradient_v2")}
        if r.get("resistance_dforce_se"):
            c["resistance"] = {"value": r["resistance_dforce"],
                               "se": r["resistance_dforce_se"]}
        for p in PARAMS:
            if r.get(f"{p}_se"):
                c[p] = {"value": r[p], "se": r[f"{p}_se"]}
        out.append(c)
    return out


# ------------------------------------------------------------------------------------------------
# Dask
# ------------------------------------------------------------------------------------------------

WORKER_HINT = "./run worker {address}"  # how a worker is started with the project's environment


class ClusterError(RuntimeError):
    """The cluster cannot run the analysis (exit 2, one line)."""


def local_cluster(workers: int, dashboard: str | None = None):
    """The embedded cluster: ``workers`` processes of one thread each (the tasks are
    numpy-heavy; the workers are the parallelism, so BLAS threads are limited to one).
    ``dashboard``: the dashboard's address (e.g. 127.0.0.1:8787; a taken port is replaced by
    a free one), None for none."""
    from dask.distributed import LocalCluster

    for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(v, "1")
    # without a dashboard the scheduler still serves HTTP (health, metrics): on a free port of
    # the loopback interface, not on the dashboard's default port
    return LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                        dashboard_address=dashboard,
                        scheduler_kwargs=None if dashboard else
                        {"dashboard_address": "127.0.0.1:0"})


def worker_check(paths: dict) -> dict:
    """Run on a worker: import everything a task imports and read the first task's line and
    train files (the paths every worker must see, like the bags). {"version", "problem"}."""
    out: dict = {"version": VERSION, "problem": None}
    try:
        import train_core.bagio  # noqa: F401
        from train_core.model import load_line, load_train

        import train_estimation.core.offline.diagnose  # noqa: F401
        import train_estimation.core.offline.identify  # noqa: F401
        import train_estimation.core.offline.measured  # noqa: F401
        import train_estimation.tools.common  # noqa: F401
    except Exception as exc:  # noqa: BLE001 - reported, as what the worker lacks
        out["problem"] = f"{type(exc).__name__}: {exc}"
        return out
    for what in ("bag", "line", "train_file"):
        if not os.path.exists(paths[what]):
            out["problem"] = (f"cannot see {paths[what]} (every worker needs the bags and "
                              "YAML files at the paths of the manifest)")
            return out
    try:
        load_line(paths["line"])
        load_train(paths["train_file"])
    except Exception as exc:  # noqa: BLE001
        out["problem"] = f"cannot load the line or train: {type(exc).__name__}: {exc}"
    return out


def _probe_function(paths: dict):
    """A function for ``client.run`` that is shipped by value (a closure): it must run on a
    worker that cannot import this module, to say so."""
    def probe():
        import sys as _sys
        try:
            from train_estimation.tools import fleet as _fleet
        except Exception as exc:  # noqa: BLE001
            return {"version": None, "python": _sys.executable,
                    "problem": f"{type(exc).__name__}: {exc}"}
        return dict(_fleet.worker_check(paths), python=_sys.executable)
    return probe


def probe_workers(client, task: dict, address: str, wait_s: float = 60.0) -> int:
    """Check before submitting that every worker can run the analysis; the number of workers.
    Raises ClusterError with one line: which workers, what is missing, how to start them."""
    hint = WORKER_HINT.format(address=address)
    try:
        client.wait_for_workers(1, timeout=wait_s)
    except (TimeoutError, OSError) as exc:
        raise ClusterError(f"no worker connected to the scheduler at {address} within "
                           f"{wait_s:.0f} s; start workers with: {hint}") from exc
    res = client.run(_probe_function({k: task[k] for k in ("bag", "line", "train_file")}),
                     on_error="return")
    bad = {}
    for w, r in sorted(res.items()):
        if isinstance(r, BaseException):
            bad[w] = f"{type(r).__name__}: {r}"
        elif r.get("problem"):
            bad[w] = f"{r['problem']} (python {r.get('python')})"
        elif r.get("version") != VERSION:
            bad[w] = f"runs analysis version {r.get('version')}, this client {VERSION}"
    if bad:
        w, why = next(iter(bad.items()))
        more = f" (and {len(bad) - 1} more)" if len(bad) > 1 else ""
        raise ClusterError(f"{len(bad)} of {len(res)} workers cannot run the analysis: {w}: "
                           f"{' '.join(why.split())}{more}; start every worker from a checkout "
                           f"of this project with: {hint}")
    return len(res)


def run_tasks(tasks: list[dict], workers: int, scheduler: str | None, progress: bool,
              client=None, dashboard: str | None = None, wait_s: float = 60.0,
              info: dict | None = None) -> list:
    """Analyse ``tasks`` on Dask (``client``, else the cluster at ``scheduler``, else an
    embedded LocalCluster of ``workers`` processes with its dashboard at ``dashboard``,
    closed afterwards); rows in completion order. A task whose worker died is a row with the
    error too. Every worker is probed first (``probe_workers``: ClusterError when one cannot
    run the analysis). ``info`` (a dict) receives the dashboard link and the worker count."""
    from dask.distributed import Client

    info = {} if info is None else info
    if client is not None:
        return _run(client, tasks, progress, client.scheduler.address, wait_s, info)
    if scheduler:
        try:
            c = Client(scheduler, timeout=wait_s)
        except (OSError, TimeoutError) as exc:
            raise ClusterError(f"no scheduler answers at {scheduler} ({type(exc).__name__}); "
                               "start one with: ./run scheduler, and workers with: "
                               f"{WORKER_HINT.format(address=scheduler)}") from exc
        with c:
            return _run(c, tasks, progress, scheduler, wait_s, info)
    with local_cluster(workers, dashboard) as cluster, Client(cluster) as c:
        return _run(c, tasks, progress, cluster.scheduler_address, wait_s, info,
                    show=dashboard is not None)


def _run(client, tasks, progress, address, wait_s, info, show=True) -> list:
    info["workers_n"] = probe_workers(client, tasks[0], address, wait_s)
    link = client.dashboard_link if show and _has_dashboard(client) else None
    info["dashboard"] = link
    if link:
        print(f"fleet: dashboard at {link}", file=sys.stderr)
    return _collect(client, tasks, progress, info)


def _has_dashboard(client) -> bool:
    try:
        return "dashboard" in client.scheduler_info().get("services", {})
    except Exception:  # noqa: BLE001 - no dashboard link is not a failure
        return False


def _collect(client, tasks: list[dict], progress: bool, info: dict | None = None) -> list:
    from dask.distributed import as_completed
    from train_core.progress import bar as progress_bar

    rows = []
    futs = client.map(analyse_bag, tasks, key=[f"bag-{t['key']}" for t in tasks], pure=False)
    by_key = {f.key: t for f, t in zip(futs, tasks)}
    where: dict = {}
    with progress_bar(len(futs), "fleet", disable=not progress) as bar:
        for fut in as_completed(futs):
            try:
                where.update({k: sorted(v) for k, v in client.who_has([fut]).items()})
                row = fut.result()
            except Exception as exc:  # noqa: BLE001 - a lost worker loses one bag only
                t = by_key[fut.key]
                row = {"train": t["train"], "bag": t["bag"], "line_file": t["line"],
                       "train_file": t["train_file"], "time": t.get("time"),
                       "key": t["key"], "error": f"task failed: {type(exc).__name__}: "
                       f"{exc}"[:300]}
            row["worker"] = (where.get(fut.key) or [None])[0]
            rows.append(row)
            bar.set_postfix_str(Path(row["bag"]).name[-24:])
            bar.update(1)
    if info is not None:
        per: dict = {}
        for r in rows:
            per[r["worker"]] = per.get(r["worker"], 0) + 1
        info["bags_per_worker"] = per
    return rows


def failure_groups(rows: list[dict]) -> list[tuple[int, str]]:
    """The failed bags' reasons grouped (paths and numbers blanked), most frequent first."""
    import re

    groups: dict = {}
    for r in rows:
        if r.get("error"):
            why = re.sub(r"(?:[A-Za-z]:)?(?:/[^\s:'\",()]+)+", "<path>", r["error"])
            why = re.sub(r"\b\d+(?:\.\d+)?\b", "#", why)
            groups[why] = groups.get(why, 0) + 1
    return sorted(((n, w) for w, n in groups.items()), key=lambda x: (-x[0], x[1]))


def failure_line(rows: list[dict], top: int = 3) -> str:
    """'N of M bags failed: k x reason; ...' (empty when none failed)."""
    g = failure_groups(rows)
    n = sum(c for c, _ in g)
    if not n:
        return ""
    parts = [f"{c} x {w[:120]}" for c, w in g[:top]]
    if len(g) > top:
        parts.append(f"{len(g) - top} other reasons")
    return f"{n} of {len(rows)} bags failed: {'; '.join(parts)}"


def merge_history(path: Path, rows: list[dict], day: str) -> list[dict]:
    """Add this run's rows to the history (one JSON row per bag, by content key; a bag seen
    before keeps its first day unless the manifest names one) and return every row."""
    hist: dict = {}
    if path.is_file():
        with open(path) as fh:
            for n, line in enumerate(fh, 1):
                try:
                    r = json.loads(line)
                    hist[r["key"]] = r
                except (ValueError, KeyError, TypeError):
                    print(f"fleet: {path} line {n}: not a history row, skipped", file=sys.stderr)
    for r in rows:
        old = hist.get(r["key"])
        r["day"] = r.get("manifest_day") or (old or {}).get("day") or day
        hist[r["key"]] = r
    tmp = path.with_suffix(".tmp")
    with open(tmp, "w") as fh:
        for r in hist.values():
            fh.write(json.dumps(r, default=json_default) + "\n")
    os.replace(tmp, path)  # a killed run leaves the old history whole
    return list(hist.values())


def window(rows: list[dict], days: int) -> list[dict]:
    """The rows of the ``days`` latest days (day labels in sort order; 0: every day)."""
    if days <= 0:
        return rows
    keep = set(sorted({str(r.get("day")) for r in rows})[-days:])
    return [r for r in rows if str(r.get("day")) in keep]


# ------------------------------------------------------------------------------------------------
# Output
# ------------------------------------------------------------------------------------------------

def speed_note(section: dict) -> str:
    """What the passes' speeds say of a section found as a gradient (core.offline.fleet's
    place-against-speed test), in words, or ''."""
    sp = section.get("speed_test")
    if not sp or section["verdict"] not in ("map error", "disputed",
                                            "drag growing with speed (a tunnel)"):
        return ""
    kmh = f"{3.6 * sp['v_min']:.0f}-{3.6 * sp['v_max']:.0f} km/h"
    if sp["decided"] == "place":
        return f" (the same at {kmh}: not a drag growing with speed)"
    if sp["decided"] == "speed":
        return (f" ({sp['permille_per_v2'] * 1e3:+.3f} per mille per 1000 m^2/s^2 over "
                f"passes at {kmh}: not the same at every speed, as a map error is)")
    if sp["decided"] == "either":
        tell = sp.get("would_tell") or {}
        ways = [f"below {3.6 * tell['below_m_s']:.0f} km/h" if tell.get("below_m_s") else "",
                f"above {3.6 * tell['above_m_s']:.0f} km/h" if tell.get("above_m_s") else ""]
        ways = " or ".join(w for w in ways if w)
        return (f" (passes at {kmh} cannot tell it from a tunnel's drag"
                + (f"; passes {ways} would" if ways else "") + ")")
    return ""


COLUMNS = ("train", "bag", "line", "time", "error", "cached", "seconds", "duration_s",
           "odometer_received", "balise_received", "cause", "accepted", "gradient_start",
           "gradient_end", "gradient_permille", "gradient_se", "gradient_score", "gradient_v2",
           "resistance_v_ref", "resistance_dforce", "resistance_dforce_se", "braking_rate",
           "braking_rate_se", "braking_rate_source", "mass", "mass_se", "mass_source",
           "odometer_scale", "odometer_scale_se",
           "identify_braking_rate", "identify_braking_rate_se", "identify_mass",
           "identify_mass_se", "identify_error", "key")


def write_csv(rows: list[dict], path: Path) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=COLUMNS, extrasaction="ignore")
        w.writeheader()
        for r in sorted(rows, key=lambda r: (r["train"], r.get("time") or 0.0, r["bag"])):
            w.writerow({k: _fmt_cell(r.get(k)) for k in COLUMNS})


def _fmt_cell(v):
    if isinstance(v, float):
        return "" if not math.isfinite(v) else f"{v:.6g}"
    return "" if v is None else v


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


# Colours of trains in the plots: matplotlib's cycle without red (C3) and orange (C1), which
# mean "map error" / "train with an alert" and "found by too few" here; a train without an
# alert is never drawn in them.
TRAIN_COLORS = ("C0", "C2", "C4", "C5", "C6", "C7", "C8", "C9")


def train_color(i: int) -> str:
    """The plot colour of the i-th train (never red nor orange)."""
    return TRAIN_COLORS[i % len(TRAIN_COLORS)]


def plot_line(name: str, line, d: dict, path: Path) -> None:
    """Believed gradient profile with the flagged sections; every run's section below."""
    plt = _plt()
    fig, (a0, a1) = plt.subplots(2, 1, figsize=(10, 6), sharex=True,
                                 gridspec_kw={"height_ratios": [1, 1.3]})
    for s in line.gradients:
        a0.plot([s.start, s.end], [s.permille, s.permille], color="C2", lw=1.5)
    for st in line.stations:
        for ax in (a0, a1):
            ax.axvline(st.position, color="0.6", lw=0.6, ls=":")
        a0.text(st.position, a0.get_ylim()[1], st.name, fontsize=8, va="top")
    y_b = min([s.permille for s in line.gradients] + [0.0]) - 3.0
    a0.plot([b.position for b in line.balises], [y_b] * len(line.balises), "|", color="0.3",
            ms=6, label="balises")
    trains = sorted({t for s in d["sections"] for t in s["trains_found"]})
    colors = {t: train_color(i) for i, t in enumerate(trains)}
    y = 0
    for s in d["sections"]:
        err = s["verdict"] == "map error"
        for ax in (a0, a1):
            ax.axvspan(s["start"], s["end"], color="C3" if err else "C1",
                       alpha=0.25 if err else 0.1)
        if err:
            a0.annotate(f"map error {s['permille']:+.1f}+-{1.96 * s['se']:.1f} per mille\n"
                        f"{len(s['trains_found'])}/{len(s['trains_passed'])} trains, "
                        f"{s['runs_found']}/{s['runs_passed']} runs",
                        ((s["start"] + s["end"]) / 2, 0), fontsize=8, ha="center",
                        color="C3", xytext=(0, 18), textcoords="offset points")
        a1.errorbar([(s["start"] + s["end"]) / 2], [s["permille"]], yerr=[1.96 * s["se"]],
                    fmt="s", color="k", ms=5, capsize=4, zorder=5,
                    label="combined +-95 %" if y == 0 else None)
        y += 1
    seen = set()
    for r in d.get("_runs", []):
        g = r.get("gradient")
        if not g:
            continue
        lab = r["train"] if r["train"] not in seen else None
        seen.add(r["train"])
        a1.plot([g["start"], g["end"]], [g["permille"]] * 2, color=colors.get(r["train"], "0.4"),
                lw=2, alpha=0.8, label=lab)
    a1.axhline(0, color="k", lw=0.6)
    a0.set_ylabel("mapped gradient (per mille)")
    a1.set_ylabel("found: true - mapped (per mille)")
    a1.set_xlabel("track position (m)")
    a0.set_title(f"line {name}: {d['runs']} runs of {len(d['trains'])} trains; red = map "
                 "error the fleet agrees on, orange = found by too few")
    if a1.get_legend_handles_labels()[0]:
        a1.legend(fontsize=7, ncol=4)
    for ax in (a0, a1):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_trends(trains: dict, path: Path) -> None:
    plt = _plt()
    pars = trains["parameters"]
    alerted = {(a["train"], a["parameter"]) for a in trains["alerts"]}
    fig, axes = plt.subplots(len(pars), 1, figsize=(10, 3.2 * len(pars)), sharex=True)
    axes = np.atleast_1d(axes)
    for ax, (p, d) in zip(axes, pars.items()):
        for i, (tr, r) in enumerate(sorted(d["trains"].items())):
            bad = (tr, p) in alerted
            ax.errorbar(r["t"], r["values"], yerr=1.96 * np.asarray(r["ses"]), fmt="o-",
                        ms=4 if bad else 3, lw=2 if bad else 0.8, capsize=2,
                        color="C3" if bad else train_color(i), alpha=1.0 if bad else 0.6,
                        label=f"{tr} (alert)" if bad else tr)
        means = [r["mean"] for r in d["trains"].values()]
        if means:
            ax.axhline(float(np.median(means)), color="k", lw=1, ls="--",
                       label="median of the trains' means")
        ax.set_ylabel(p.replace("_", " "))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=6, loc="best")
    axes[-1].set_xlabel("time of the run (manifest units; the simulator: hours)")
    axes[0].set_title("per-train parameters per run (+-95 %); red: trains with an alert")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _f(x, fmt=".3g"):
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else \
        format(x, fmt)


def findings(res, rows: list[dict], rel: dict) -> list[str]:
    """The report's first lines: what was found (map errors, train alerts, failed bags), each
    with its size, or that nothing was, with the reason it may still be there."""
    L = ["**Findings:**", ""]
    for m in res.map_errors:
        L.append(f"- **map error** on line {m['line']}, [{m['start']:.0f}, {m['end']:.0f}) m: "
                 f"{m['permille']:+.2f} +- {m['se']:.2f} per mille (true minus mapped; found "
                 f"by {len(m['trains_found'])} of {len(m['trains_passed'])} trains, "
                 f"{m['runs_found']} of {m['runs_passed']} runs)")
    if not res.map_errors:
        weak = [ln for ln, d in (rel.get("lines") or {}).items() if not d["reliable"]]
        L.append("- no map error" + (f" (but too few runs on {', '.join(weak)} to exclude one)"
                                     if weak else ""))
    for a in sorted(res.train_alerts, key=lambda a: (a["train"], a["parameter"])):
        L.append(f"- **train {a['train']}**: {a['parameter'].replace('_', ' ')} {a['kind']}: "
                 f"{_f(a['mean'], '.4g')} +- {_f(a['se'], '.2g')} against the fleet's "
                 f"{_f(a['fleet'], '.4g')} (z = {a['z']:+.1f}, p = {a['p']:.1e})")
    if not res.train_alerts:
        few = [p for p, d in (rel.get("parameters") or {}).items() if not d["reliable"]]
        L.append("- no train departs from the fleet or trends"
                 + (f" (but too few trains to test {', '.join(few)})" if few else ""))
    bad = [r for r in rows if r.get("error")]
    if bad:
        L.append(f"- **{len(bad)} of {len(rows)} bags could not be analysed** (listed below)")
    return L


def report_md(res, rows: list[dict], info: dict, plots: list[str]) -> str:
    ok = [r for r in rows if not r.get("error")]
    bad = [r for r in rows if r.get("error")]
    cfg = res.config
    rel = getattr(res, "reliability", None) or {}
    days = info.get("days") or []
    # the first line says what failed, so that nobody reads "no map error" off a failed run
    head = f"# Fleet report ({info['when']})"
    if bad:
        too_many = len(bad) > info.get("max_failed", 1.0) * len(rows)
        head += f": {'FAILED, ' if too_many else ''}{failure_line(rows)}"
    L = [head, ""] + findings(res, rows, rel) + [""]
    if rel and not rel.get("reliable", True):
        L += ["**The consensus is unreliable** (too few analysed runs; \"no map error\" or "
              "\"no train departs\" below does not mean that there is none): "
              + "; ".join(rel["reasons"]) + ".", ""]
    per = info.get("bags_per_worker") or {}
    L += [f"{len(rows)} bags of {len({r['train'] for r in rows})} trains on "
          f"{len(res.lines)} lines: {len(ok)} analysed, {len(bad)} failed; "
          f"{info['cached']} from the cache, {info['computed']} computed in "
          f"{info.get('wall_s', 0.0):.0f} s on {info['workers']}"
          + (f" ({len(per)} workers: {', '.join(str(n) for n in per.values())} bags)"
             if per else "") + ".", ""]
    if len(days) > 1 or info.get("pool", len(rows)) != len(rows):
        L += [f"The consensus is over {info.get('pool')} runs of {len(days)} days "
              f"({days[0]} to {days[-1]}) from the history (OUT/history.jsonl).", ""]
    L += [
         "## Map errors", ""]
    if res.map_errors:
        L += ["| line | section (m) | true - mapped (per mille), 95 % | trains | runs | "
              "binomial p | consistency p |", "|---|---|---|---|---|---|---|"]
        for m in res.map_errors:
            L.append(f"| {m['line']} | [{m['start']:.0f}, {m['end']:.0f}) | "
                     f"{m['permille']:+.2f} [{m['ci95'][0]:+.2f}, {m['ci95'][1]:+.2f}] | "
                     f"{len(m['trains_found'])} of {len(m['trains_passed'])} "
                     f"({', '.join(m['trains_found'])}) | {m['runs_found']} of "
                     f"{m['runs_passed']} | {m['p_binomial']:.2g} | "
                     f"{m['p_consistency']:.2f} |")
        L.append("")
        for m in res.map_errors:
            L.append(f"- **Line {m['line']}, [{m['start']:.0f}, {m['end']:.0f}) m: the map is "
                     f"wrong by {m['permille']:+.2f} +- {m['se']:.2f} per mille** "
                     f"({m['runs_found']} of {m['runs_passed']} runs and "
                     f"{len(m['trains_found'])} of {len(m['trains_passed'])} trains that passed "
                     f"found it; by chance at {cfg['p_false']:.0%} false detections per run: "
                     f"p = {m['p_binomial']:.2g}; the values agree: Cochran's Q = {m['q']:.1f} "
                     f"on {m['df']} df, p = {m['p_consistency']:.2f})"
                     + (f"; over {len(m['days'])} days: {m['day_status']}, without "
                        f"{m['top_day']} p = {m['p_rest']:.2g}" if m.get("day_status") else "")
                     + ".")
    else:
        L.append("No section is found by enough trains to be a map error.")
    weak = [ln for ln, d in (rel.get("lines") or {}).items() if not d["reliable"]]
    if weak:
        L.append(f"Too few analysed runs on {', '.join(weak)} to exclude one (a section needs "
                 f"{rel['n_min']} runs: the fewest with which a map error that diagnose finds "
                 f"in {cfg.get('p_detect', 0.5):.0%} of the runs is declared with probability "
                 f"{cfg.get('power', 0.9):.0%}).")
    L += ["", "### Every section found, per line", "",
          "| line | section (m) | per mille +- se | found by runs (trains) | days: found/passed "
          "| verdict |", "|---|---|---|---|---|---|"]
    for ln, d in res.lines.items():
        for s in d["sections"]:
            dd = ", ".join(f"{k}: {f}/{n}" for k, (f, n) in sorted(s.get("days", {}).items()))
            v = s["verdict"] + (f" ({s['day_status']})" if s.get("day_status") else "") + \
                (" (too few runs)" if s.get("too_few_runs") and s["verdict"] != "map error"
                 else "") + speed_note(s)
            L.append(f"| {ln} | [{s['start']:.0f}, {s['end']:.0f}) | {s['permille']:+.2f} +- "
                     f"{s['se']:.2f} | {s['runs_found']}/{s['runs_passed']} "
                     f"({', '.join(s['trains_found'])}) | {dd or '-'} | {v} |")
    L += ["", "### Resistance per line (fitted minus believed force at each run's speed)", "",
          "| line | runs | combined (N) +- se | tau (N) | z | consistency p | verdict |",
          "|---|---|---|---|---|---|---|"]
    for ln, d in res.lines.items():
        rc = d["resistance"]
        if rc.get("n", 0):
            L.append(f"| {ln} | {rc['n']} | {rc['mean']:+.0f} +- {rc['se']:.0f} | "
                     f"{rc.get('tau', 0):.0f} | {rc['z']:+.2f} | {rc['p_consistency']:.2f} | "
                     f"{rc.get('verdict', 'too few runs')} |")
    tr = res.trains
    L += ["", "## Train alerts", "",
          "Criterion: |z| > the two-sided Student-t quantile of "
          f"{tr['alpha']:g} / (2 x {tr['tests']}) (family-wise false-alarm rate "
          f"{tr['alpha']:g} over {tr['tests']} train-parameter pairs, Bonferroni) on each "
          "statistic's Welch-Satterthwaite degrees of freedom: the critical value applied is "
          "in the tables (crit); it is at least the normal quantile "
          f"{tr['z_critical']:.2f}, reached when no variance is estimated.", ""]
    if res.train_alerts:
        L += ["| train | parameter | alert | train mean +- se | fleet (others' median) | z | "
              "crit | p |", "|---|---|---|---|---|---|---|---|"]
        for a in sorted(res.train_alerts, key=lambda a: (a["train"], a["parameter"])):
            L.append(f"| **{a['train']}** | {a['parameter']} | {a['kind']} | "
                     f"{_f(a['mean'], '.4g')} +- {_f(a['se'], '.2g')} | "
                     f"{_f(a['fleet'], '.4g')} | {a['z']:+.2f} | {a['critical']:.2f} | "
                     f"{a['p']:.1e} |")
        names = sorted({a["train"] for a in res.train_alerts})
        L += ["", f"Trains with an alert: **{', '.join(names)}**."]
    else:
        L.append("No train departs from the fleet or trends.")
    few = [p for p, d in (rel.get("parameters") or {}).items() if not d["reliable"]]
    if few:
        L.append(f"Too few trains with values of {', '.join(few)} to test departures (3 "
                 "needed).")
    for p, d in tr["parameters"].items():
        L += ["", f"### {p.replace('_', ' ')} per train (run-to-run scatter beyond the "
              f"standard errors: tau = {_f(d['tau'], '.3g')})", "",
              "| train | runs | mean +- se | others' median | z departure (crit) | slope per "
              "time unit +- se | z trend (crit) |", "|---|---|---|---|---|---|---|"]
        for t, r in sorted(d["trains"].items()):
            L.append(f"| {t} | {r['runs']} | {_f(r['mean'], '.5g')} +- {_f(r['se'], '.2g')} | "
                     f"{_f(r.get('fleet'), '.5g')} | {_f(r.get('z_departure'), '+.2f')} "
                     f"({_f(r.get('crit_departure'), '.2f')}) | "
                     f"{_f(r.get('slope'), '.2g')} +- {_f(r.get('slope_se'), '.2g')} | "
                     f"{_f(r.get('z_trend'), '+.2f')} ({_f(r.get('crit_trend'), '.2f')}) |")
    if bad:
        L += ["", "## Bags that could not be analysed", "", "| train | bag | reason |",
              "|---|---|---|"]
        for r in sorted(bad, key=lambda r: r["bag"]):
            L.append(f"| {r['train']} | {r['bag']} | {r['error']} |")
    L += ["", "## Plots", ""] + [f"![{p}]({p})" for p in plots]
    L += ["", "## How to read it", "",
          "Each bag was checked (check_bag), fitted (identify) and diagnosed (diagnose); "
          "runs.csv has one row per bag. A *map error* is a gradient section found by runs of "
          f"at least {cfg['min_trains']} trains, more often than spurious detections explain "
          f"(binomial test against {cfg['p_false']:.0%} per run, Bonferroni over every "
          f"section found, alpha = {cfg['alpha']:g}), with values that agree (Cochran's Q, "
          "alpha); its size is the inverse-variance combination of the runs' values. A *train "
          "alert* is a train whose parameter departs from the other trains' median "
          "(leave-one-out, robust spread) or trends in time, beyond the Bonferroni Student-t "
          "quantile above (crit). Method: train_estimation/core/offline/fleet.py."]
    return "\n".join(L) + "\n"


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
    for t in tasks:
        t["key"] = content_key(t)
        f = cache / f"{t['key']}.json"
        if f.is_file():
            row = json.loads(f.read_text())
            row.update({"train": t["train"], "bag": t["bag"], "cached": True})
            if t.get("time") is not None:
                row["time"] = t["time"]
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
        for r in new:
            r["cached"] = False
            if not str(r.get("error") or "").startswith(_NOT_CACHED):
                (cache / f"{r['key']}.json").write_text(json.dumps(r, default=json_default))
        rows += new
    else:
        wall = 0.0
    info["wall_s"] = wall
    by_key = {t["key"]: t for t in tasks}
    for r in rows:
        r["manifest_day"] = by_key[r["key"]].get("day")
    day = args.day or time.strftime("%Y-%m-%d", time.gmtime())
    if args.no_history:
        for r in rows:
            r["day"] = r["manifest_day"] or day
        pool = rows
    else:
        pool = window(merge_history(out / "history.jsonl", rows, day), args.days)
    info["days"] = sorted({str(r.get("day")) for r in pool})
    info["pool"] = len(pool)
    res = consensus(consensus_rows(pool), FleetConfig(alpha=args.alpha))
    write_csv(rows, out / "runs.csv")
    plots = []
    crow = consensus_rows([r for r in pool if not r.get("error")])
    by_name = {}
    for ln in lines.values():
        by_name.setdefault(ln.name, ln)
    for name, d in res.lines.items():
        if name in by_name:
            fn = f"line_{name}.png"
            plot_line(name, by_name[name], dict(d, _runs=[r for r in crow if r["line"] == name]),
                      out / fn)
            plots.append(fn)
    if res.trains["parameters"]:
        plot_trends(res.trains, out / "trends.png")
        plots.append("trends.png")
    n_bad = sum(1 for r in rows if r.get("error"))
    too_many = n_bad > args.max_failed * len(rows)
    info["max_failed"] = args.max_failed
    (out / "report.md").write_text(report_md(res, rows, info, plots))
    (out / "fleet.json").write_text(json.dumps(
        {"map_errors": res.map_errors, "train_alerts": res.train_alerts, "lines": res.lines,
         "trains": res.trains, "config": res.config, "reliability": res.reliability,
         "failures": failure_groups(rows), "run": info}, indent=1, default=json_default))
    print(f"fleet: {len(rows)} bags ({n_bad} failed), {len(todo)} analysed in {wall:.0f} s, "
          f"total {time.perf_counter() - t0:.0f} s; consensus over {len(pool)} runs of "
          f"{len(info['days'])} days")
    for m in res.map_errors:
        print(f"map error: line {m['line']} [{m['start']:.0f}, {m['end']:.0f}) m "
              f"{m['permille']:+.2f} +- {m['se']:.2f} per mille ({len(m['trains_found'])} "
              f"trains, {m['runs_found']}/{m['runs_passed']} runs)")
    for a in sorted(res.train_alerts, key=lambda a: (a["train"], a["parameter"])):
        print(f"train alert: {a['train']} {a['parameter']} {a['kind']} (z = {a['z']:+.1f})")
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
