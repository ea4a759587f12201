"""`fleet`'s outputs: runs.csv, the line and trend plots, and report.md (its findings first,
then the map errors, the resistance per line, the train alerts and the failed bags)."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from train_estimation.tools.fleet_row import BagRow


def failure_groups(rows: list[BagRow]) -> list[tuple[int, str]]:
    """The failed bags' reasons grouped (paths and numbers blanked), most frequent first."""
    import re

    groups: dict = {}
    for r in rows:
        if r.error:
            why = re.sub(r"(?:[A-Za-z]:)?(?:/[^\s:'\",()]+)+", "<path>", r.error)
            why = re.sub(r"\b\d+(?:\.\d+)?\b", "#", why)
            groups[why] = groups.get(why, 0) + 1
    return sorted(((n, w) for w, n in groups.items()), key=lambda x: (-x[0], x[1]))


def failure_line(rows: list[BagRow], top: int = 3) -> str:
    """'N of M bags failed: k x reason; ...' (empty when none failed)."""
    g = failure_groups(rows)
    n = sum(c for c, _ in g)
    if not n:
        return ""
    parts = [f"{c} x {w[:120]}" for c, w in g[:top]]
    if len(g) > top:
        parts.append(f"{len(g) - top} other reasons")
    return f"{n} of {len(rows)} bags failed: {'; '.join(parts)}"


def speed_note(section: dict) -> str:
    """What the passes' speeds say of a section found as a gradient (core.offline.fleet's
    place-against-speed test), in words, or ''."""
    sp = section.get("speed_test")
    if not sp or section["verdict"] not in ("map error", "disputed",
                                            "drag growing with speed (a tunnel)"):
        return ""
    kmh = f"{3.6 * sp['v_min']:.0f}-{3.6 * sp['v_max']:.0f} km/h"
    by = "; decided by " + ", ".join(
        f"{d['train']}'s pass" + (f" {d['bag']}" if d.get("bag") else "")
        + (f" on {d['day']}" if d.get("day") else "")
        + f" at {3.6 * d['v_m_s']:.0f} km/h ({d['permille']:.2f} per mille)"
        for d in sp.get("decided_by") or [])
    if sp["decided"] == "place":
        return f" (the same at {kmh}: not a drag growing with speed{by})"
    if sp["decided"] == "speed":
        return (f" ({sp['permille_per_v2'] * 1e3:+.3f} per mille per 1000 m^2/s^2 over "
                f"passes at {kmh}: not the same at every speed, as a map error is{by})")
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


def write_csv(rows: list[BagRow], path: Path) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=COLUMNS, extrasaction="ignore")
        w.writeheader()
        for r in sorted(rows, key=lambda r: (r.train, r.time or 0.0, r.bag)):
            w.writerow({k: _fmt_cell(getattr(r, k)) for k in COLUMNS})


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


def findings(res, rows: list[BagRow], rel: dict) -> list[str]:
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
    for a in res.readers.get("alerts", []):
        L.append(f"- **train {a['train']}'s balise reader** is not the sensor its readings "
                 f"state: {a['signature']} (its {a['runs']} runs pooled, {a['readings']} "
                 "readings)")
    bad = [r for r in rows if r.error]
    if bad:
        L.append(f"- **{len(bad)} of {len(rows)} bags could not be analysed** (listed below)")
    return L


def report_md(res, rows: list[BagRow], info: dict, plots: list[str]) -> str:
    ok = [r for r in rows if not r.error]
    bad = [r for r in rows if r.error]
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
    L += [f"{len(rows)} bags of {len({r.train for r in rows})} trains on "
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
        for r in sorted(bad, key=lambda r: r.bag):
            L.append(f"| {r.train} | {r.bag} | {r.error} |")
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
