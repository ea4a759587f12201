"""`check_bag`: offline checks of a recorded bag (no running ROS needed).

    check_bag BAG [--line line.yaml --train train.yaml] [--out DIR]
              [--threshold KEY<=VALUE ...] [--thresholds FILE.yaml] [--expected-received P]

Reports per estimator in the bag (grouped by TrainState ``source`` on the ``estimate/*`` topics):
position, velocity and braking-rate error against ``ground_truth`` (RMSE, 95th percentile, max),
consistency (NEES of position/velocity against truth, with its 95% acceptance fraction), the
estimate latency (receive time minus stamp), and per topic the received fraction from sequence
gaps, gaps and out-of-order or duplicate stamps. Thresholds name a key of ``summary.json`` with
dots, e.g. ``estimators.robust_filter.position.rmse<=5`` or
``topics.odometer.received_fraction>=0.8``.

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

from train_estimation.core import reasons as R
from train_sim.bagio import Bag, BagError, read_bag

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


def topic_health(bag: Bag, topic: str) -> dict:
    msgs = bag.topics.get(topic, [])
    stamps = bag.stamps(topic)
    out: dict = {"count": len(msgs), "type": bag.types.get(topic, "")}
    if len(msgs) == 0:
        return out
    d = np.diff(stamps)
    # the estimators' rejection names (core/reasons.py) for what the stamps alone show
    out[R.OUT_OF_ORDER] = int(np.sum(d < 0))
    out["duplicate_stamps"] = int(np.sum(d == 0))
    out[R.NON_FINITE] = int(sum(1 for _, s, f in msgs if not math.isfinite(s) or any(
        isinstance(v, float) and not math.isfinite(v) for v in f.values())))
    out["max_gap_s"] = float(d.max()) if d.size else 0.0
    if "seq" in msgs[0][2]:
        seq = bag.series(topic, "seq")
        span = int(seq.max() - seq.min() + 1)
        out["seq_span"] = span
        out["received_fraction"] = len(np.unique(seq)) / span
        out["seq_gaps"] = int(np.sum(np.diff(np.sort(seq)) > 1))
    return out


def estimator_report(bag: Bag, topic: str, source: str, truth: dict | None) -> dict:
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
    rep["latency_s"] = {"median": float(np.median(lat)), "p99": float(np.percentile(lat, 99))}
    series = {"stamp": stamp, "x": x, "v": v, "f": f_hat, "cov": cov}
    if truth is not None and len(rows):
        inside = (stamp >= truth["t"][0]) & (stamp <= truth["t"][-1])
        xt = np.interp(stamp, truth["t"], truth["x"])
        vt = np.interp(stamp, truth["t"], truth["v"])
        ft = np.interp(stamp, truth["t"], truth["f"])
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
    return {"t": t[order], "x": get("position"), "v": get("velocity"), "f": get("braking_rate")}


def check(bag_path: str, out_dir: Path | None = None, expected_received: float | None = None,
          plots: bool = True) -> dict:
    bag = read_bag(bag_path)
    if not bag.topics:
        raise CheckError(f"{bag_path}: no CONTRACT.md topics in the bag ({bag.skipped or 'empty'})")
    truth = truth_series(bag)
    summary: dict = {"bag": str(bag_path), "namespace": bag.namespace,
                     "has_ground_truth": truth is not None,
                     "topics": {t: topic_health(bag, t) for t in sorted(bag.topics)},
                     "estimators": {}, "skipped": bag.skipped}
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
            rep = estimator_report(bag, topic, source, truth)
            series[source] = rep.pop("_series")
            summary["estimators"][source] = rep
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "summary.json").write_text(json.dumps(summary, indent=1, default=float))
        if plots and series:
            summary["plots"] = make_plots(out_dir, series, truth)
            (out_dir / "summary.json").write_text(json.dumps(summary, indent=1, default=float))
    return summary


def make_plots(out_dir: Path, series: dict, truth: dict | None) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    fig, axes = plt.subplots(3, 1, figsize=(10, 10), sharex=True)
    for name, s in series.items():
        t = s["stamp"]
        sx = np.sqrt(np.maximum(s["cov"][:, 0, 0], 0))
        sv = np.sqrt(np.maximum(s["cov"][:, 1, 1], 0))
        if "xt" in s:
            (ln,) = axes[0].plot(t, s["x"] - s["xt"], lw=0.8, label=f"{name} error")
            axes[0].fill_between(t, -3 * sx, 3 * sx, color=ln.get_color(), alpha=0.15)
            (ln,) = axes[1].plot(t, s["v"] - s["vt"], lw=0.8, label=f"{name} error")
            axes[1].fill_between(t, -3 * sv, 3 * sv, color=ln.get_color(), alpha=0.15)
        if np.any(np.isfinite(s["f"])):
            sf = np.sqrt(np.maximum(s["cov"][:, 3, 3], 0))
            (ln,) = axes[2].plot(t, s["f"], lw=0.8, label=name)
            axes[2].fill_between(t, s["f"] - 3 * sf, s["f"] + 3 * sf, color=ln.get_color(),
                                 alpha=0.15)
    if truth is not None:
        axes[2].plot(truth["t"], truth["f"], "k--", lw=1, label="truth")
    axes[0].set_ylabel("position error (m)\nband: +-3 sigma")
    axes[1].set_ylabel("velocity error (m/s)\nband: +-3 sigma")
    axes[2].set_ylabel("braking rate f")
    axes[2].set_xlabel("time (s)")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    path = out_dir / "estimates_vs_truth.png"
    fig.savefig(path, dpi=90)
    plt.close(fig)
    files.append(str(path))
    if truth is not None:
        fig, ax = plt.subplots(figsize=(10, 4))
        for name, s in series.items():
            if "xt" in s:
                ax.plot(s["xt"], np.abs(s["x"] - s["xt"]), ".", ms=2, label=name)
        ax.set_xlabel("position along the line (m)")
        ax.set_ylabel("|position error| (m)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        path = out_dir / "error_over_position.png"
        fig.savefig(path, dpi=90)
        plt.close(fig)
        files.append(str(path))
    return files


_THRESH = re.compile(r"^\s*([\w./-]+)\s*(<=|>=)\s*([-+0-9.eE]+|nan|inf)\s*$")


def parse_threshold(text: str) -> tuple[str, str, float]:
    m = _THRESH.match(text)
    if not m:
        raise CheckError(f"threshold '{text}': write KEY<=VALUE or KEY>=VALUE")
    return m.group(1), m.group(2), float(m.group(3))


def load_thresholds(path: str) -> list[tuple[str, str, float]]:
    import yaml

    data = yaml.safe_load(Path(path).read_text()) or {}
    out = []
    for key, spec in data.items():
        if not isinstance(spec, dict) or not set(spec) <= {"max", "min"}:
            raise CheckError(f"{path}: {key}: expected {{max: V}} and/or {{min: V}}")
        if "max" in spec:
            out.append((key, "<=", float(spec["max"])))
        if "min" in spec:
            out.append((key, ">=", float(spec["min"])))
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
        lines.append("estimator       pos RMSE  pos p95  pos max  vel RMSE  f RMSE  NEES  "
                     "in 3sig  latency p50/p99 (ms, bag time)")
        for name, r in summary["estimators"].items():
            p, v, f = r.get("position", {}), r.get("velocity", {}), r.get("braking_rate", {})
            g = lambda d, k: f"{d[k]:.3f}" if k in d else "-"  # noqa: E731
            nees = r.get("nees", {}).get("mean")
            lines.append(
                f"{name:<14} {g(p, 'rmse'):>9} {g(p, 'p95'):>8} {g(p, 'max'):>8} "
                f"{g(v, 'rmse'):>9} {g(f, 'rmse'):>7} {'-' if nees is None else f'{nees:.2f}':>5}"
                f"  {r.get('position_within_3sigma', float('nan')):7.3f}  "
                f"{1e3 * r['latency_s']['median']:.1f}/{1e3 * r['latency_s']['p99']:.1f}")
        for name, r in summary["estimators"].items():
            fb = r.get("braking_rate_final")
            if fb:
                lines.append(f"{name}: braking rate at {fb['t']:.0f} s: {fb['estimate']:.3f} "
                             f"+- {fb['std']:.3f} (truth {fb['truth']:.3f})")
    for k, why in summary.get("skipped", {}).items():
        lines.append(f"not used: {k}: {why}")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="check_bag", description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="\n".join(__doc__.splitlines()[2:]))
    p.add_argument("bag", help="rosbag2 directory (MCAP) or .mcap file")
    p.add_argument("--line", help="line.yaml (checked for validity; positions are reported "
                                  "against it)")
    p.add_argument("--train", help="train.yaml (checked for validity)")
    p.add_argument("--out", help="folder for summary.json and plots")
    p.add_argument("--threshold", action="append", default=[], metavar="KEY<=VALUE",
                   help="a pass/fail threshold on a summary key (repeatable)")
    p.add_argument("--thresholds", help="YAML file {KEY: {max: V, min: V}}")
    p.add_argument("--expected-received", type=float, default=None,
                   help="received fraction the link is configured for (e.g. 0.875)")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    args = p.parse_args(argv)
    try:
        from train_sim.config import ConfigError
        from train_sim.model import load_line, load_train

        if args.line:
            load_line(args.line)
        if args.train:
            load_train(args.train)
        thresholds = [parse_threshold(t) for t in args.threshold]
        if args.thresholds:
            thresholds += load_thresholds(args.thresholds)
        summary = check(args.bag, Path(args.out) if args.out else None, args.expected_received,
                        plots=not args.no_plots)
        results = evaluate(summary, thresholds)
    except (BagError, CheckError, ConfigError, OSError) as exc:
        print(f"check_bag: {exc}", file=sys.stderr)
        return 2
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
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
