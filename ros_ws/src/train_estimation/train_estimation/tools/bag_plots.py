"""Plots of `check_bag`: estimates against ground truth, over time and along the line.

Pure plotting (matplotlib, Agg): the series come from ``check_bag.check``. What a reader should
see at a glance:

- one panel per estimator and quantity, so one filter's band never hides another's;
- the start-up (initial uncertainty converging) in its own narrow column, the rest scaled to the
  steady state, so a transient of metres does not flatten errors of centimetres;
- 3-sigma bands clipped to the quantity's physical range (a braking rate is in [0, 2]);
- station stops shaded and named, balise passages as dotted lines (from the line file when
  given, else from the balise readings in the bag), braking phases (when the braking rate is
  observable at all) shaded on the braking-rate panels.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

F_RANGE = (0.0, 2.0)  # -, physical range of the braking rate (0 = no brake, 1 = nominal)
STARTUP_MIN = 5.0  # s, shortest start-up column
STARTUP_MAX_FRACTION = 0.25  # of the run: longest start-up column
BRAKING = -0.1  # m/s^2: commands below this inform the braking rate (gsma_estimator min_brake)


def _sigma(cov: np.ndarray, i: int) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return np.sqrt(np.maximum(cov[:, i, i], 0.0))


def startup_end(series: dict, t0: float, t1: float) -> float:
    """End of the start-up: after it every position sigma stays within twice its run median."""
    t_ss = t0 + STARTUP_MIN
    limit = t0 + STARTUP_MAX_FRACTION * (t1 - t0)
    for s in series.values():
        sx = _sigma(s["cov"], 0)
        ok = np.isfinite(sx)
        if not ok.any():
            continue
        high = ok & (sx > 2.0 * np.median(sx[ok])) & (s["stamp"] <= limit)
        if high.any():
            t_ss = max(t_ss, float(s["stamp"][np.flatnonzero(high)[-1]]) + 1.0)
    return min(t_ss, max(limit, t0 + STARTUP_MIN))


def markers(truth: dict | None, line, balise_msgs: list, control: dict | None) -> dict:
    """Times of station stops (spans), balise passages and braking phases (spans)."""
    out = {"stops": [], "balises": [], "braking": []}
    if truth is not None and len(truth["t"]):
        t, x, v = truth["t"], truth["x"], truth["v"]
        rest = v <= 1e-6
        for a, b in _runs(rest):
            if t[b] - t[a] < 2.0:
                continue
            name = "at rest"
            if line is not None and line.stations:
                st = min(line.stations, key=lambda s: abs(s.position - x[a]))
                name = st.name if abs(st.position - x[a]) < 10.0 else "at rest"
            out["stops"].append((float(t[a]), float(t[b]), name))
        if line is not None:
            xm = np.maximum.accumulate(x)  # the train never rolls back: x is monotone
            for bal in line.balises:
                i = int(np.searchsorted(xm, bal.position))
                if 0 < i < len(t):
                    out["balises"].append((float(t[i]), bal.id, True))
        if control is not None and len(control["t"]):
            braking = np.interp(t, control["t"], control["a"]) < BRAKING
            moving = v > 0.3
            for a, b in _runs(braking & moving):
                out["braking"].append((float(t[a]), float(t[b])))
    if not out["balises"]:
        out["balises"] = [(float(s), int(i), False) for s, i in balise_msgs]
    return out


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) index of each run of True."""
    d = np.diff(np.concatenate([[0], mask.astype(int), [0]]))
    starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1) - 1
    return list(zip(starts.tolist(), ends.tolist()))


def _decorate(ax, mk: dict, names: bool, braking: bool) -> None:
    lo, hi = ax.get_xlim()
    for a, b, name in mk["stops"]:
        if b < lo or a > hi:
            continue
        ax.axvspan(a, b, color="0.85", lw=0, zorder=0)
        if names:
            ax.text(0.5 * (max(a, lo) + min(b, hi)), 1.0, name, transform=ax.get_xaxis_transform(),
                    ha="center", va="bottom", fontsize=8)
    for t, _bid, _ in mk["balises"]:
        if lo <= t <= hi:
            ax.axvline(t, color="tab:purple", ls=":", lw=0.8, zorder=1)
    if braking:
        for a, b in mk["braking"]:
            if b >= lo and a <= hi:
                ax.axvspan(a, b, color="tab:green", alpha=0.12, lw=0, zorder=0)


def _scaled(values: list[np.ndarray], margin: float = 1.1) -> float:
    vals = np.concatenate([np.abs(v[np.isfinite(v)]) for v in values] + [np.zeros(1)])
    return margin * float(vals.max()) or 1.0


def band(s: dict, kind: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(curve, band low, band high) of one panel: kind "x"/"v" = error and +-3 sigma about 0,
    "braking_rate" = the estimate and its 3-sigma interval clipped to the physical range."""
    if kind == "braking_rate":
        sf = _sigma(s["cov"], 3)
        y = s["braking_rate"]
        return y, np.clip(y - 3 * sf, *F_RANGE), np.clip(y + 3 * sf, *F_RANGE)
    i, key = (0, "x") if kind == "x" else (1, "v")
    sd = _sigma(s["cov"], i)
    return s[key] - s[key + "t"], -3 * sd, 3 * sd


def plot_time(path: Path, series: dict, truth: dict | None, mk: dict, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    names = list(series)
    rows = []  # (kind, estimator)
    if truth is not None:
        rows += [("x", n) for n in names if "xt" in series[n]]
        rows += [("v", n) for n in names if "xt" in series[n]]
    rows += [("braking_rate", n) for n in names if np.any(np.isfinite(series[n]["braking_rate"]))]
    if not rows:
        return
    t0 = min(float(s["stamp"][0]) for s in series.values())
    t1 = max(float(s["stamp"][-1]) for s in series.values())
    t_ss = startup_end(series, t0, t1)
    colors = {n: f"C{i}" for i, n in enumerate(names)}
    fig, axes = plt.subplots(len(rows), 2, figsize=(13, 2.1 * len(rows) + 1.2), sharex="col",
                             gridspec_kw={"width_ratios": [1, 4]}, squeeze=False)
    units = {"x": "position error (m)", "v": "velocity error (m/s)",
             "braking_rate": "braking rate f"}
    for r, (kind, name) in enumerate(rows):
        s = series[name]
        t = s["stamp"]
        c = colors[name]
        y, lo, hi = band(s, kind)
        steady = t >= t_ss
        for col, (a, b) in enumerate(((t0, t_ss), (t_ss, t1))):
            ax = axes[r, col]
            ax.fill_between(t, lo, hi, color=c, alpha=0.2, lw=0, step="post")
            ax.plot(t, y, color=c, lw=0.7)
            if kind == "braking_rate" and truth is not None:
                ax.plot(truth["t"], truth["braking_rate"], "k--", lw=1)
            ax.set_xlim(a, b)
            ax.grid(alpha=0.3)
            if kind == "braking_rate":
                top = np.nanmax(np.concatenate([hi, y, [1.05]]))
                if truth is not None:
                    top = max(top, float(np.nanmax(truth["braking_rate"])))
                ax.set_ylim(F_RANGE[0], min(F_RANGE[1], top + 0.05))
            elif col == 1 and steady.any():
                m = _scaled([y[steady], hi[steady]])
                ax.set_ylim(-m, m)
            _decorate(ax, mk, names=(r == 0 and col == 1), braking=(kind == "braking_rate"))
        axes[r, 0].set_ylabel(f"{name}\n{units[kind]}", fontsize=9)
    axes[0, 0].set_title("start-up", fontsize=10, pad=14)
    axes[0, 1].set_title("after start-up (scaled to it)", fontsize=10, pad=14)
    axes[-1, 0].set_xlabel("time (s)")
    axes[-1, 1].set_xlabel("time (s)")
    handles = [Line2D([], [], color="0.3", lw=0.7, label="estimate - truth (f: estimate)"),
               Patch(color="0.3", alpha=0.2, label="+-3 sigma (stated)"),
               Line2D([], [], color="k", ls="--", label="true braking rate"),
               Patch(color="0.85", label="at rest (station named)"),
               Line2D([], [], color="tab:purple", ls=":", label="balise passage"),
               Patch(color="tab:green", alpha=0.12, label="braking (f observable)")]
    fig.legend(handles=handles, loc="lower center", ncol=6, fontsize=8, frameon=False)
    fig.suptitle(f"{title}: estimates against ground truth", fontsize=12)
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    fig.savefig(path, dpi=80)
    plt.close(fig)


def plot_position(path: Path, series: dict, line, bal_positions: list, title: str) -> None:
    """Position error against true position, after the start-up (its metres would set the
    scale), one panel per estimator."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [n for n in series if "xt" in series[n]]
    if not names:
        return
    t0 = min(float(s["stamp"][0]) for s in series.values())
    t1 = max(float(s["stamp"][-1]) for s in series.values())
    t_ss = startup_end(series, t0, t1)
    fig, axes = plt.subplots(len(names), 1, figsize=(13, 2.4 * len(names) + 1.2), sharex=True,
                             squeeze=False)
    for r, name in enumerate(names):
        s = series[name]
        ax = axes[r, 0]
        ok = s["inside"] & (s["stamp"] >= t_ss)
        xt, err = s["xt"][ok], (s["x"] - s["xt"])[ok]
        sd = _sigma(s["cov"], 0)[ok]
        order = np.argsort(xt, kind="stable")
        ax.fill_between(xt[order], -3 * sd[order], 3 * sd[order], color=f"C{r}", alpha=0.2, lw=0)
        ax.plot(xt, err, ".", ms=2, color=f"C{r}")
        ax.set_ylabel(f"{name}\nposition error (m)", fontsize=9)
        ax.grid(alpha=0.3)
        if line is not None:
            for st in line.stations:
                ax.axvline(st.position, color="k", lw=1)
                if r == 0:
                    ax.text(st.position, 1.0, st.name, transform=ax.get_xaxis_transform(),
                            ha="center", va="bottom", fontsize=9)
        for xb in bal_positions:
            ax.axvline(xb, color="tab:purple", ls=":", lw=0.8)
    axes[-1, 0].set_xlabel("true position along the line (m); solid: stations, dotted: balises"
                           + ("" if line is not None else " (received)"))
    fig.suptitle(f"{title}: position error along the line after the start-up (t > {t_ss:.0f} s; "
                 "band +-3 sigma)", fontsize=12)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
