"""`fleet`'s Dask runner: one bag's analysis as a Dask task (:func:`analyse_bag`: its topics'
health, identify's fit and diagnose's ranking in one flat row; pure Python, no rclpy) and the
cluster that runs them (an embedded LocalCluster or one at a scheduler's address; every worker
probed first).
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
import time
import traceback
from pathlib import Path

import numpy as np

from train_estimation.tools.fleet_row import BagRow

VERSION = "fleet-3"  # part of the cache key: bump when a task's result changes meaning


# ------------------------------------------------------------------------------------------------
# One bag (a Dask task: pure Python, no rclpy)
# ------------------------------------------------------------------------------------------------

def analyse_bag(task: dict) -> BagRow:
    """check_bag + identify + diagnose of one bag -> its row. Never raises: a failure is a row
    with ``error`` set (the reason in one line)."""
    t0 = time.perf_counter()
    row = {"train": task["train"], "bag": task["bag"], "line_file": task["line"],
           "train_file": task["train_file"], "time": task.get("time"), "key": task.get("key"),
           "error": None}
    read: dict = {}  # the bag once read: why it failed may be that it was never closed
    try:
        row.update(_analyse(task, read))
        out = BagRow(**row)
    except Exception as exc:  # noqa: BLE001 - any failure of one bag is reported, not fatal
        from train_estimation.tools.common import unclosed

        why = f"{type(exc).__name__}: {' '.join(str(exc).split())}"[:300]
        out = BagRow(**{k: row[k] for k in ("train", "bag", "line_file", "train_file", "time",
                                            "key")},
                     error=why + unclosed(read.get("bag")),
                     traceback_at=traceback.extract_tb(exc.__traceback__)[-1].name)
    return dataclasses.replace(out, seconds=round(time.perf_counter() - t0, 2))


def _analyse(task: dict, read: dict | None = None) -> dict:
    """One bag, read once: its topics' health, identify's fit and diagnose's ranking (the
    row's fields they fill). ``read["bag"]`` holds the bag once read."""
    from train_core.bagio import read_bag
    from train_core.model import load_line, load_train

    from train_estimation.core.offline.diagnose import diagnose
    from train_estimation.core.offline.measured import TOPICS, MeasuredRun, topic_health

    line, train = load_line(task["line"]), load_train(task["train_file"])
    out: dict = {"line": line.name}
    bag = read_bag(task["bag"], topics=TOPICS)
    if read is not None:
        read["bag"] = bag
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
    out = {"cause": dg.cause, "accepted": "+".join(accepted),
           "balise": ((dg.evidence.get("_model") or {}).get("balise_readings") or {}).get(
               "innovations")}
    ranked = {r.cause: r for r in dg.ranking if r.cause in BY_NAME}
    for name, fit in ranked.items():
        out.update(BY_NAME[name].fleet_row(fit, dg.evidence.get(name) or {}, name in accepted,
                                           train))
    return jsonable(out)


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
    if not paths:  # no task whose files the client sees: only the imports are checked
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
            from train_estimation.tools import fleet_dask as _runner
        except Exception as exc:  # noqa: BLE001
            return {"version": None, "python": _sys.executable,
                    "problem": f"{type(exc).__name__}: {exc}"}
        return dict(_runner.worker_check(paths), python=_sys.executable)
    return probe


def probe_workers(client, task: dict | None, address: str, wait_s: float = 60.0) -> int:
    """Check before submitting that every worker can run the analysis (and sees ``task``'s
    files, if given); the number of workers. Raises ClusterError with one line: which
    workers, what is missing, how to start them."""
    hint = WORKER_HINT.format(address=address)
    try:
        client.wait_for_workers(1, timeout=wait_s)
    except (TimeoutError, OSError) as exc:
        raise ClusterError(f"no worker connected to the scheduler at {address} within "
                           f"{wait_s:.0f} s; start workers with: {hint}") from exc
    paths = {} if task is None else {k: task[k] for k in ("bag", "line", "train_file")}
    res = client.run(_probe_function(paths), on_error="return")
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
              info: dict | None = None) -> list[BagRow]:
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


def _readable(task: dict) -> bool:
    """Whether the client sees the task's bag and reads its line and train files."""
    from train_core.config import ConfigError
    from train_core.model import load_line, load_train

    if not os.path.exists(task["bag"]):
        return False
    try:
        load_line(task["line"])
        load_train(task["train_file"])
    except (ConfigError, OSError):
        return False
    return True


def _run(client, tasks, progress, address, wait_s, info, show=True) -> list[BagRow]:
    # the workers must see what the client sees: probed with the first task whose bag, line
    # and train files the client finds and reads (a bag missing here is that task's own
    # failure, one row: probed with it, a first bag still being copied stopped the whole run
    # as "workers cannot see it")
    probe = next((t for t in tasks if _readable(t)), None)
    info["workers_n"] = probe_workers(client, probe, address, wait_s)
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


def _collect(client, tasks: list[dict], progress: bool,
             info: dict | None = None) -> list[BagRow]:
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
                row = BagRow(train=t["train"], bag=t["bag"], line_file=t["line"],
                             train_file=t["train_file"], time=t.get("time"),
                             key=t["key"], error=f"task failed: {type(exc).__name__}: "
                             f"{exc}"[:300])
            row = dataclasses.replace(row, worker=(where.get(fut.key) or [None])[0])
            rows.append(row)
            bar.set_postfix_str(Path(row.bag).name[-24:])
            bar.update(1)
    if info is not None:
        per: dict = {}
        for r in rows:
            per[r.worker] = per.get(r.worker, 0) + 1
        info["bags_per_worker"] = per
    return rows
