"""`check_bag`: offline checks of a recorded bag (no running ROS needed).

    check_bag BAG | --bag BAG [--line line.yaml] [--train train.yaml] [--out DIR]
              [--title TEXT] [--threshold KEY<=VALUE ...] [--thresholds FILE.yaml]
              [--expected-received P] [--rate-factor R] [--allow-missing TOPIC,...]

Reports per estimator in the bag (grouped by TrainState ``source`` on the ``estimate/*`` topics):
position, velocity and braking-rate error against ``ground_truth`` (RMSE, 95th percentile, max),
consistency (NEES of position/velocity against truth, with its 95% acceptance fraction), the
estimate latency (the recorder's receive time minus the sample stamp, in bag time: simulated
time when the run was recorded with use_sim_time; ``--rate-factor`` converts it to wall time),
and per topic the received fraction from sequence gaps, gaps and out-of-order or duplicate
stamps. With ``--line``: errors by position too (position RMSE on each section between
stations, the error at rest at each station, |error| just before and 1 s after each balise
passage), and the plots mark stations and balises (without it, balises from the bag's readings).
Thresholds name a key of ``summary.json`` with dots, e.g.
``estimators.robust_filter.position.rmse<=5`` or ``topics.odometer.received_fraction>=0.8``.

A bag lacking one of the measured data's topics (odometer, balise, control) is refused, naming
the missing ones (and, for a bag its recorder never closed, the repair command); where that is
intended (a bag of estimates only, a speed-only log) ``--allow-missing`` names the topics it may
lack.

Exit code: 0 every threshold passed, 1 a threshold failed, 2 the bag is unreadable or lacks what
was asked (one-line reason). Writes ``DIR/summary.json`` and PNG plots beside it.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path

import numpy as np
from train_core.bagio import Bag, BagError, read_bag

from train_estimation.core.offline.measured import topic_health
from train_estimation.tools.common import (
    EXIT_CHECK_FAILED,
    EXIT_OK,
    INPUT_TOPICS,
    fail,
    pipe_safe,
    unclosed,
)

ESTIMATE_PREFIX = "estimate/"
CHI2_95 = {1: 3.841, 2: 5.991}  # 95% quantiles of chi-square with 1 and 2 degrees of freedom


class CheckError(RuntimeError):
    """The bag lacks what was asked: exit code 2."""


def _stats(err: np.ndarray) -> dict:
    err = err[np.isfinite(err)]
    if err.size == 0:
        return {"n": 0}
    a = np.abs(err)
    return {"n": int(err.size), "rmse": float(np.sqrt(np.mean(err**2))),
            "p95": float(np.percentile(a, 95)), "max": float(a.max()),
            "mean": float(err.mean())}


ALERT_LIMIT = 10.0  # m: the estimators' alert limit where neither they nor --line state one
#   (docs/integrity.md)


def stanford_regions(rows: list, inside: np.ndarray, err: np.ndarray,
                     alert_limit: float = ALERT_LIMIT) -> dict | None:
    """The Stanford-diagram regions of the estimates with ground truth (``err``: position
    error of the rows ``inside`` the truth's span), by their protection levels: ``nominal``
    (error within the protection level, the level within the alert limit), ``unavailable``
    (error within the level, the level beyond the limit), ``misleading`` (error beyond the
    level on its side, not ALARM), ``hazardous`` (also beyond the alert limit), ``alarm``;
    None for a bag recorded before estimates carried protection levels."""
    sel = [f for (_, _, f), i in zip(rows, inside) if i]
    if not sel or "protection_level_ahead" not in sel[0]:
        return None
    ahead = np.array([f["protection_level_ahead"] for f in sel], float)
    behind = np.array([f["protection_level_behind"] for f in sel], float)
    alarm = np.array([f.get("integrity", 0) == 2 for f in sel])
    with np.errstate(invalid="ignore"):
        within = (err >= -ahead) & (err <= behind)
        pl = np.maximum(ahead, behind)
        mis = ~alarm & ~within
        return {"alert_limit": alert_limit, "estimates": int(len(sel)),
                "nominal": int(np.sum(~alarm & within & (pl <= alert_limit))),
                "unavailable": int(np.sum(~alarm & within & (pl > alert_limit))),
                "misleading": int(np.sum(mis & ~(np.abs(err) > alert_limit))),
                "hazardous": int(np.sum(mis & (np.abs(err) > alert_limit))),
                "alarm": int(np.sum(alarm)),
                "pl_median": float(np.median(pl[~alarm])) if np.any(~alarm) else math.inf}


def estimator_report(bag: Bag, topic: str, source: str, truth: dict | None,
                     rate_factor: float | None = None, alert_limit: float = ALERT_LIMIT) -> dict:
    rows = [(t, s, f) for t, s, f in bag.topics[topic] if f["source"] == source]
    stamp = np.array([s for _, s, _ in rows])
    recv = np.array([t for t, _, _ in rows]) * 1e-9
    x = np.array([f["position"] for _, _, f in rows])
    v = np.array([f["velocity"] for _, _, f in rows])
    f_hat = np.array([f["braking_rate"] for _, _, f in rows])
    cov = np.array([np.asarray(f["covariance"], dtype=float).reshape(4, 4) for _, _, f in rows])
    used = np.array([f["measurement_used"] for _, _, f in rows], dtype=bool)
    rep: dict = {"topic": topic, "count": len(rows),
                 "measurement_used_fraction": float(used.mean()) if len(rows) else 0.0}
    lat = recv - stamp  # in the recorder's clock: bag (sim) time, not wall time
    rep["latency_s"] = {"median": float(np.median(lat)), "p99": float(np.percentile(lat, 99)),
                        "clock": "bag"}
    if rate_factor:
        # at rate factor r one wall second is r bag seconds (the recorder's clock is /clock,
        # which advances in steps of the simulator's wall_step * r: that is the resolution)
        rep["latency_wall_s"] = {"median": float(np.median(lat)) / rate_factor,
                                 "p99": float(np.percentile(lat, 99)) / rate_factor,
                                 "rate_factor": rate_factor}
    series = {"stamp": stamp, "x": x, "v": v, "braking_rate": f_hat, "cov": cov}
    if truth is not None and len(rows):
        inside = (stamp >= truth["t"][0]) & (stamp <= truth["t"][-1])
        xt = np.interp(stamp, truth["t"], truth["x"])
        vt = np.interp(stamp, truth["t"], truth["v"])
        ft = np.interp(stamp, truth["t"], truth["braking_rate"])
        ex, ev, ef = (x - xt)[inside], (v - vt)[inside], (f_hat - ft)[inside]
        rep["position"] = _stats(ex)
        rep["velocity"] = _stats(ev)
        if np.any(np.isfinite(f_hat)):
            rep["braking_rate"] = _stats(ef)
            last = np.flatnonzero(inside)[-1]
            rep["braking_rate_final"] = {"t": float(stamp[last]), "estimate": float(f_hat[last]),
                                         "std": float(np.sqrt(max(cov[last, 3, 3], 0.0))),
                                         "truth": float(ft[last])}
        c = cov[inside][:, :2, :2]
        ok = np.all(np.isfinite(c.reshape(len(c), -1)), axis=1)
        if ok.any():
            e = np.stack([ex, ev], axis=1)[ok]
            nees = np.einsum("ni,nij,nj->n", e, np.linalg.pinv(c[ok]), e)
            rep["nees"] = {"dof": 2, "mean": float(nees.mean()),
                           "fraction_within_95": float(np.mean(nees <= CHI2_95[2]))}
            sx = np.sqrt(np.maximum(c[ok][:, 0, 0], 0))
            rep["position_within_3sigma"] = float(np.mean(np.abs(ex[ok]) <= 3 * sx))
        regions = stanford_regions(rows, inside, ex, alert_limit)
        if regions is not None:
            rep["integrity"] = regions
        series.update(xt=xt, vt=vt, ft=ft, inside=inside)
    rep["_series"] = series
    return rep


def truth_series(bag: Bag) -> dict | None:
    rows = bag.topics.get("ground_truth", [])
    if not rows:
        return None
    t = np.array([s for _, s, _ in rows])
    order = np.argsort(t, kind="stable")
    get = lambda k: np.array([f[k] for _, _, f in rows])[order]  # noqa: E731
    return {"t": t[order], "x": get("position"), "v": get("velocity"),
            "braking_rate": get("braking_rate")}


def by_position(series: dict, truth: dict, line) -> dict:
    """Errors located on the line: sections between stations, stops, balise passages."""
    stations = sorted(line.stations, key=lambda st: st.position)
    xm = np.maximum.accumulate(truth["x"])  # the train never rolls back
    passages = []
    for bal in sorted(line.balises, key=lambda b: b.position):
        i = int(np.searchsorted(xm, bal.position))
        if 0 < i < len(truth["t"]):
            passages.append((bal, float(truth["t"][i])))
    out = {}
    for name, s in series.items():
        if "xt" not in s:
            continue
        ok = s["inside"]
        t, xt, vt = s["stamp"][ok], s["xt"][ok], s["vt"][ok]
        ex, ev = (s["x"] - s["xt"])[ok], (s["v"] - s["vt"])[ok]
        sections = []
        for a, b in zip(stations, stations[1:]):
            m = (xt >= a.position) & (xt < b.position) & (vt > 0.0)
            st = {"from": a.name, "to": b.name, "n": int(m.sum())}
            if m.any():
                st.update(position_rmse=float(np.sqrt(np.mean(ex[m] ** 2))),
                          position_max=float(np.abs(ex[m]).max()),
                          velocity_rmse=float(np.sqrt(np.mean(ev[m] ** 2))))
            sections.append(st)
        stops = []
        for st in stations:
            m = (np.abs(xt - st.position) < 10.0) & (vt <= 1e-6)
            if m.any():
                stops.append({"station": st.name, "n": int(m.sum()),
                              "position_error": float(np.median(ex[m]))})
        bal = []
        for b, tb in passages:
            before = np.flatnonzero(t < tb)
            after = np.flatnonzero(t >= tb + 1.0)
            if before.size and after.size:
                bal.append({"id": b.id, "position": b.position, "t": tb,
                            "error_before": float(abs(ex[before[-1]])),
                            "error_after": float(abs(ex[after[0]]))})
        out[name] = {"sections": sections, "stops": stops, "balises": bal}
    return out


def _markers(bag: Bag, truth: dict | None, line) -> dict:
    from train_estimation.tools.bag_plots import markers

    control = None
    if bag.topics.get("control"):
        control = {"t": bag.stamps("control"), "a": bag.series("control", "target_acceleration")}
    bal = [(s, f["balise_id"]) for _, s, f in bag.topics.get("balise", [])]
    return markers(truth, line, bal, control)


def check(bag_path: str, out_dir: Path | None = None, expected_received: float | None = None,
          plots: bool = True, line=None, rate_factor: float | None = None,
          title: str | None = None) -> dict:
    """Check one bag; ``line`` is a :class:`train_core.model.Line` (errors by position)."""
    bag = read_bag(bag_path)
    if not bag.topics:
        raise CheckError(f"{bag_path}: no docs/interfaces.md topics in the bag "
                         f"({bag.skipped or 'empty'})")
    truth = truth_series(bag)
    summary: dict = {"bag": str(bag_path), "namespace": bag.namespace,
                     "has_ground_truth": truth is not None,
                     "topics": {t: topic_health(bag, t) for t in sorted(bag.topics)},
                     "estimators": {}, "skipped": bag.skipped,
                     "missing_topics": [t for t in INPUT_TOPICS if not bag.topics.get(t)]}
    if expected_received is not None:
        for t in ("odometer", "balise"):
            h = summary["topics"].get(t)
            if h and "received_fraction" in h:
                n = h["seq_span"]
                sd = math.sqrt(expected_received * (1 - expected_received) / max(n, 1))
                h["expected_received_fraction"] = expected_received
                h["received_fraction_z"] = (h["received_fraction"] - expected_received) / sd \
                    if sd > 0 else 0.0
    series = {}
    for topic in sorted(bag.topics):
        if not topic.startswith(ESTIMATE_PREFIX):
            continue
        for source in sorted({f["source"] for _, _, f in bag.topics[topic]}):
            stated = getattr(line, "alert_limit", math.nan)  # the line's, where it states one
            rep = estimator_report(bag, topic, source, truth, rate_factor,
                                   stated if math.isfinite(stated) else ALERT_LIMIT)
            series[source] = rep.pop("_series")
            summary["estimators"][source] = rep
    if line is not None and truth is not None:
        summary["line"] = line.name
        summary["by_position"] = by_position(series, truth, line)
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "summary.json").write_text(json.dumps(summary, indent=1, default=float))
        if plots and series:
            title = title or f"{Path(bag_path).name} ({bag.namespace or '/'})"
            mk = _markers(bag, truth, line)
            mk["line"] = line
            bal = ([b.position for b in line.balises] if line is not None else
                   sorted({float(f["position"]) for _, _, f in bag.topics.get("balise", [])}))
            summary["plots"] = make_plots(out_dir, series, truth, mk, bal, title)
            (out_dir / "summary.json").write_text(json.dumps(summary, indent=1, default=float))
    return summary


def make_plots(out_dir: Path, series: dict, truth: dict | None, mk: dict,
               balise_positions: list, title: str) -> list[str]:
    from train_estimation.tools.bag_plots import plot_position, plot_time

    files = []
    path = out_dir / "estimates_vs_truth.png"
    plot_time(path, series, truth, mk, title)
    if path.exists():
        files.append(str(path))
    if truth is not None:
        path = out_dir / "error_over_position.png"
        plot_position(path, series, mk.get("line"), balise_positions, title)
        if path.exists():
            files.append(str(path))
    return files


_THRESH = re.compile(r"^\s*([\w./-]+)\s*(<=|>=)\s*([-+0-9.eE]+|nan|inf)\s*$")


def parse_threshold(text: str) -> tuple[str, str, float]:
    m = _THRESH.match(text)
    if not m:
        raise CheckError(f"threshold '{text}': write KEY<=VALUE or KEY>=VALUE")
    return m.group(1), m.group(2), float(m.group(3))


def load_thresholds(path: str) -> list[tuple[str, str, float]]:
    """``{summary key: {max: V, min: V}}`` from a YAML file (read as every YAML the project
    reads: :func:`train_core.config.load_yaml`); an empty file holds none."""
    from train_core.config import load_yaml

    if not Path(path).read_text(errors="replace").strip():
        return []
    data = load_yaml(path)  # ConfigError: one line, exit 2
    out = []
    for key, spec in data.items():
        if not isinstance(spec, dict) or not spec or not set(spec) <= {"max", "min"}:
            raise CheckError(f"{path}: {key}: expected {{max: V}} and/or {{min: V}}")
        for bound, op in (("max", "<="), ("min", ">=")):
            if bound in spec:
                v = spec[bound]
                if isinstance(v, bool) or not isinstance(v, int | float) or math.isnan(v):
                    raise CheckError(f"{path}: {key}: {bound} must be a number, got {v!r}")
                out.append((key, op, float(v)))
    return out


def lookup(summary: dict, key: str):
    node = summary
    for part in key.split("."):  # topic and estimator names hold no dots
        if not isinstance(node, dict) or part not in node:
            raise CheckError(f"threshold key '{key}' is not in the summary (missing '{part}')")
        node = node[part]
    return node


def evaluate(summary: dict, thresholds) -> list[dict]:
    results = []
    for key, op, limit in thresholds:
        value = float(lookup(summary, key))
        ok = value <= limit if op == "<=" else value >= limit
        results.append({"key": key, "op": op, "limit": limit, "value": value, "pass": bool(ok)})
    return results


def format_report(summary: dict) -> str:
    lines = [f"bag {summary['bag']} (namespace {summary['namespace'] or '/'})"]
    lines.append("topic                 count  received  out-of-order  max gap (s)")
    for t, h in summary["topics"].items():
        rf = h.get("received_fraction")
        lines.append(f"{t:<20} {h['count']:>6}  {'' if rf is None else f'{rf:8.3f}':>8}  "
                     f"{h.get('out_of_order', 0):>12}  {h.get('max_gap_s', 0):>11.2f}")
    if summary["estimators"]:
        wall = all("latency_wall_s" in r for r in summary["estimators"].values())
        lines.append("estimator       pos RMSE  pos p95  pos max  vel RMSE  f RMSE  NEES  "
                     "in 3sig  latency p50/p99 (ms" + (", wall)" if wall else ", bag time)"))
        for name, r in summary["estimators"].items():
            lat = r["latency_wall_s"] if wall else r["latency_s"]
            p, v, f = r.get("position", {}), r.get("velocity", {}), r.get("braking_rate", {})
            g = lambda d, k: f"{d[k]:.3f}" if k in d else "-"  # noqa: E731
            nees = r.get("nees", {}).get("mean")
            lines.append(
                f"{name:<14} {g(p, 'rmse'):>9} {g(p, 'p95'):>8} {g(p, 'max'):>8} "
                f"{g(v, 'rmse'):>9} {g(f, 'rmse'):>7} {'-' if nees is None else f'{nees:.2f}':>5}"
                f"  {r.get('position_within_3sigma', float('nan')):7.3f}  "
                f"{1e3 * lat['median']:.1f}/{1e3 * lat['p99']:.1f}")
        for name, r in summary["estimators"].items():
            g = r.get("integrity")
            if g:
                lines.append(f"{name}: protection levels (alert limit {g['alert_limit']:g} m): "
                             f"nominal {g['nominal']}, unavailable {g['unavailable']}, "
                             f"misleading {g['misleading']}, hazardous {g['hazardous']}, "
                             f"alarm {g['alarm']} of {g['estimates']}; median level "
                             f"{g['pl_median']:.2f} m")
        for name, r in summary["estimators"].items():
            fb = r.get("braking_rate_final")
            if fb:
                lines.append(f"{name}: braking rate at {fb['t']:.0f} s: {fb['estimate']:.3f} "
                             f"+- {fb['std']:.3f} (truth {fb['truth']:.3f})")
        if wall:
            rf = next(iter(summary["estimators"].values()))["latency_wall_s"]["rate_factor"]
            lines.append(f"(units: m, m/s; latency = sample stamp to the recorder's log time, "
                         f"link, estimator and queues included; bag time / {rf:g} = wall time)")
        else:
            lines.append("(units: m, m/s; latency = sample stamp to the recorder, in the bag's "
                         "clock: simulated time if recorded with use_sim_time)")
    if summary.get("by_position"):
        lines += format_by_position(summary)
    other = []  # topics of other packages' types (Odometry, /diagnostics): one line
    for k, why in summary.get("skipped", {}).items():
        if why.endswith("is not a docs/interfaces.md type"):
            other.append(f"{k} ({why.split()[1].replace('/msg/', '/')})")
        else:
            lines.append(f"not used: {k}: {why}")
    if other:
        lines.append("also in the bag, not checked: " + ", ".join(sorted(other)))
    return "\n".join(lines)


def format_by_position(summary: dict) -> list[str]:
    bp = summary["by_position"]
    names = list(bp)
    w = max(14, *(len(n) + 1 for n in names))
    lines = [f"errors by position on line {summary.get('line')} (m; sections: RMSE while "
             "running, stations: error at rest)",
             f"{'':<12}" + "".join(f"{n:>{w}}" for n in names)]
    first = bp[names[0]]
    for k, sec in enumerate(first["sections"]):
        row = f"{sec['from'] + ' -> ' + sec['to']:<12}"
        for n in names:
            v = bp[n]["sections"][k].get("position_rmse")
            row += f"{'-' if v is None else f'{v:.3f}':>{w}}"
        lines.append(row)
    for st in first["stops"]:
        row = f"{'at ' + st['station']:<12}"
        for n in names:
            stops = {x["station"]: x for x in bp[n]["stops"]}
            v = stops.get(st["station"], {}).get("position_error")
            row += f"{'-' if v is None else f'{v:+.3f}':>{w}}"
        lines.append(row)
    parts = []
    for n in names:
        b = bp[n]["balises"]
        if b:
            before = np.mean([x["error_before"] for x in b])
            after = np.mean([x["error_after"] for x in b])
            parts.append(f"{n} {before:.3f} -> {after:.3f}")
    if parts:
        lines.append(f"balise passages ({len(first['balises'])}): mean |position error| just "
                     "before -> 1 s after: " + "; ".join(parts))
    return lines


@pipe_safe
def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="check_bag", description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="\n".join(__doc__.splitlines()[2:]))
    p.add_argument("bag", nargs="?", help="rosbag2 directory (MCAP) or .mcap file")
    p.add_argument("--bag", dest="bag_option", metavar="BAG",
                   help="the bag, as an option (as identify and diagnose take it)")
    p.add_argument("--allow-missing", action="append", default=[], metavar="TOPIC[,TOPIC]",
                   help=f"a topic of {', '.join(INPUT_TOPICS)} the bag may lack (repeatable; "
                        "default: each is required)")
    p.add_argument("--line", help="line.yaml: adds errors by position (sections between "
                                  "stations, each station stop, balise passages) to the report "
                                  "and marks stations and balises on the plots")
    p.add_argument("--train", help="train.yaml (checked for validity)")
    p.add_argument("--out", help="folder for summary.json and plots")
    p.add_argument("--threshold", action="append", default=[], metavar="KEY<=VALUE",
                   help="a pass/fail threshold on a summary key (repeatable)")
    p.add_argument("--thresholds", help="YAML file {KEY: {max: V, min: V}}")
    p.add_argument("--expected-received", type=float, default=None,
                   help="received fraction the link is configured for (e.g. 0.875)")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.add_argument("--rate-factor", type=float, default=None,
                   help="simulated s per wall s of the recorded run: latency in wall time")
    p.add_argument("--title", default=None, help="title of the plots (default: the bag name)")
    args = p.parse_args(argv)
    if (args.bag is None) == (args.bag_option is None):
        p.error("give the bag once: check_bag BAG or check_bag --bag BAG")
    args.bag = args.bag or args.bag_option
    allowed = {t.strip() for a in args.allow_missing for t in a.split(",") if t.strip()}
    if allowed - set(INPUT_TOPICS):
        return fail("check_bag", f"--allow-missing {', '.join(sorted(allowed - set(INPUT_TOPICS)))}"
                                 f": name topics of {', '.join(INPUT_TOPICS)}")
    try:
        from train_core.config import ConfigError
        from train_core.model import load_line, load_train

        line = load_line(args.line) if args.line else None
        if args.train:
            load_train(args.train)
        thresholds = [parse_threshold(t) for t in args.threshold]
        if args.thresholds:
            thresholds += load_thresholds(args.thresholds)
        if args.rate_factor is not None and not (math.isfinite(args.rate_factor)
                                                  and args.rate_factor > 0):
            raise CheckError(f"--rate-factor {args.rate_factor}: must be > 0")
        summary = check(args.bag, Path(args.out) if args.out else None, args.expected_received,
                        plots=not args.no_plots, line=line, rate_factor=args.rate_factor,
                        title=args.title)
        missing = [t for t in summary["missing_topics"] if t not in allowed]
        if missing:
            raise CheckError(
                f"{args.bag}: no {' and no '.join(missing)} messages: measured data has "
                f"{', '.join(INPUT_TOPICS)} (docs/interfaces.md); record "
                f"{'them' if len(missing) > 1 else 'it'}, or --allow-missing "
                f"{','.join(missing)} if the bag is meant without"
                f"{unclosed(summary['skipped'])}")
        results = evaluate(summary, thresholds)
    except (BagError, CheckError, ConfigError, OSError) as exc:
        return fail("check_bag", str(exc))
    summary["thresholds"] = results
    if args.out:
        (Path(args.out) / "summary.json").write_text(json.dumps(summary, indent=1, default=float))
    print(format_report(summary))
    for r in results:
        print(f"{'PASS' if r['pass'] else 'FAIL'} {r['key']} = {r['value']:.4g} "
              f"{r['op']} {r['limit']:g}")
    if args.out:
        print(f"summary: {Path(args.out) / 'summary.json'}")
        for f in summary.get("plots", []):
            print(f"plot: {f}")
    failed = [r for r in results if not r["pass"]]
    if failed:
        print(f"check_bag: {len(failed)} threshold(s) failed", file=sys.stderr)
        return EXIT_CHECK_FAILED
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
