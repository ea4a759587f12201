"""diagnose's plots (DIR/*.svg): the residual acceleration of the believed and the extended
model against position (with the line profile and the fitted gradient section), against speed
and the commands, and by phase with what is unexplained; the speed trace with slip episodes and
f(t); the loss-run histogram; the recorded commands replayed through both models.

Each plot takes ``Diagnosis.series`` and is drawn only when its series exist, as an SVG file
written by svgplot (numpy and the standard library: no matplotlib is loaded by a diagnose run).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from train_estimation.core.offline.diagnose.series import with_replay
from train_estimation.tools.diagnose_unexplained import at_balise, balise_latency, on_odometer
from train_estimation.tools.svgplot import Figure


def _subplots(rows=1, cols=1, *, figsize, sharex=False, sharey=False, gridspec_kw=None,
              top=0.4, space=0.2):
    """A figure of ``figsize`` inches at DPI and its panels (one Axes, or an array of them in
    reading order), as ``pyplot.subplots`` lays them out, drawn by svgplot."""
    fig = Figure(*figsize, rows=rows, cols=cols, sharex=sharex, sharey=sharey,
                 height_ratios=(gridspec_kw or {}).get("height_ratios"), top=top, dpi=DPI,
                 space=space)
    return fig, (fig.axes[0] if rows * cols == 1 else np.array(fig.axes, dtype=object))


def _get(s: dict, *keys):
    vals = [s.get(k) for k in keys]
    if any(v is None for v in vals):
        return None
    arrs = [np.asarray(v, dtype=float) for v in vals]
    n = min(a.size for a in arrs)
    return [a[:n] for a in arrs] if n > 0 else None


def _binned(x, y, bins):
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if x.size == 0:
        return np.array([]), np.array([]), np.array([])
    edges = np.linspace(x.min(), x.max(), bins + 1)
    idx = np.clip(np.digitize(x, edges) - 1, 0, bins - 1)
    cnt = np.bincount(idx, minlength=bins)
    mean = np.bincount(idx, weights=y, minlength=bins) / np.maximum(cnt, 1)
    sq = np.bincount(idx, weights=y * y, minlength=bins) / np.maximum(cnt, 1)
    sem = np.sqrt(np.maximum(sq - mean**2, 0.0) / np.maximum(cnt, 1))
    c = 0.5 * (edges[1:] + edges[:-1])
    keep = cnt >= 3
    return c[keep], mean[keep], sem[keep]


def plot_position(s: dict, path: Path, dg=None) -> bool:
    """Residual acceleration against track position above the line's gradient profile, with the
    fitted gradient section drawn in."""
    xy = _get(s, "position", "residual_accel")
    if xy is None:
        return False
    x, r = xy
    fig, (a0, a1) = _subplots(2, 1, figsize=(10, 6), sharex=True,
                              gridspec_kw={"height_ratios": [2, 1]})
    a0.dots(x, r, color="0.5", alpha=0.15, label="residual (believed model)")
    span = float(np.nanmax(x) - np.nanmin(x)) if np.isfinite(x).any() else 0.0
    c, m, e = _binned(x, r, max(10, int(span // 100)))
    if c.size:
        a0.band(c, m - 2 * e, m + 2 * e, color="C0", alpha=0.25, step=True)
        a0.step(c, m, lw=1.2, color="C0", label="believed model: mean per 100 m, +-2 SE")
        lim = 1.5 * float(np.percentile(np.abs(m) + 2 * e, 90))  # a few sparse bins may clip
        if lim > 0:
            a0.ylim = (-lim, lim)
    ext = _extended(s, r)
    if ext is not None:
        c, m, e = _binned(x, ext, max(10, int(span // 100)))
        if c.size:
            a0.step(c, m, lw=1.2, color="C3", label="extended model: mean per 100 m")
    a0.hline(0, color="k", lw=0.6)
    a0.ylabel = "residual accel. (m/s^2)"
    prof = s.get("line_gradient") or []
    for st, en, pm in prof:
        a1.line([st, en], [pm, pm], color="C2", lw=1.5)
    sec = s.get("gradient_section")
    if sec is not None:
        st, en, pm = sec
        for ax in (a0, a1):
            ax.vspan(st, en, color="C3", alpha=0.15)
        a1.line([st, en], [pm, pm], color="C3", lw=2.5, label=f"fitted: {pm:+.2f} per mille "
                f"on [{st:.0f}, {en:.0f}) m")
        # the residual a missing section leaves: -g sin(theta) / (1 + lambda), about
        a0.line([st, en], [-9.81e-3 * pm] * 2, color="C3", lw=2, label="fitted section's effect")
        a1.legend(size=8)
    stations = s.get("stations") or []
    if stations:
        a1.vlines([pos for _, pos in stations], color="0.6", lw=0.6, ls=":")
        for name, pos in stations:
            a1.text(pos, None, str(name), size=7)  # below the panel's top
    a1.ylabel = "gradient (per mille)"
    a1.xlabel = "track position (m)"
    a0.legend("upper right", size=8)
    a0.title = _title(dg, "residual acceleration along the line")
    return _save(fig, path)


def plot_speed(s: dict, path: Path, dg=None) -> bool:
    """Residual acceleration against speed (resistance, mass) and against the commanded
    traction and braking (mass, braking rate)."""
    xy = _get(s, "speed", "residual_accel")
    if xy is None:
        return False
    v, r = xy
    ext = _extended(s, r)
    panels = [("speed (m/s)", v)]
    for key, label in (("commanded_traction", "traction command through the actuator (m/s^2)"),
                       ("commanded_braking", "braking command through the actuator (m/s^2)")):
        xs = _get(s, key, "residual_accel")
        if xs is not None:
            panels.append((label, xs[0]))
    fig, axes = _subplots(1, len(panels), figsize=(4.2 * len(panels), 4), sharey=True, top=0.55)
    axes = np.atleast_1d(axes)
    lim = 0.0
    for ax, (label, x) in zip(axes, panels):
        n = min(x.size, r.size)
        ax.dots(x[:n], r[:n], color="0.5", alpha=0.15)
        sel = np.abs(x[:n]) > 1e-3 if "command" in label else np.ones(n, bool)
        c, m, e = _binned(x[:n][sel], r[:n][sel], 20)
        if c.size:
            ax.errorbar(c, m, 2 * e, marker="o", ms=3, color="C0",
                        label="believed model: binned mean +-2 SE")
            lim = max(lim, 1.5 * float(np.percentile(np.abs(m) + 2 * e, 90)))
        if ext is not None:
            c, m, e = _binned(x[:n][sel], ext[:n][sel], 20)
            if c.size:
                ax.errorbar(c, m, 2 * e, marker="s", ms=3, color="C3",
                            label="extended model: binned mean +-2 SE")
        _residual_axis(ax, label)
    return _finish_residuals(fig, axes, lim, "residual accel. (m/s^2)", 8,
                             _title(dg, "residual acceleration against speed and commands"),
                             path)


def _extended(s: dict, r: np.ndarray):
    """The extended model's residual acceleration on the believed one's samples (None when no
    accepted cause changes the motion model)."""
    e = s.get("residual_accel_extended")
    if e is None:
        return None
    e = np.asarray(e, dtype=float)[:r.size]
    return e if e.size == r.size else None


F_MIN_SPAN = 0.2  # -, smallest braking-rate axis span: a 0.1 % change must not fill the panel


def f_axis(values) -> tuple[float, float]:
    """The braking-rate axis: nominal 1 and every value in view, at least F_MIN_SPAN wide."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    lo, hi = min(1.0, float(v.min()) if v.size else 1.0), max(1.0, float(v.max()) if v.size
                                                               else 1.0)
    pad = max(F_MIN_SPAN - (hi - lo), 0.0) / 2 + 0.05 * (hi - lo)
    return lo - pad, hi + pad


def plot_speed_trace(s: dict, path: Path, dg=None) -> bool:
    """The odometer speed against time with the slip episodes and f(t) if fitted."""
    tv = _get(s, "odo_t", "odo_speed")
    if tv is None:
        return False
    t, v = tv
    has_f = s.get("f_t") is not None
    fig, axes = _subplots(2 if has_f else 1, 1, figsize=(10, 6 if has_f else 3.5),
                          sharex=True)
    axes = np.atleast_1d(axes)
    axes[0].line(t, v, lw=0.7, label="odometer speed")
    ref = _get(s, "t", "speed")
    if ref is not None:
        axes[0].line(ref[0], ref[1], lw=0.7, color="C1", alpha=0.8, label="reference speed")
    for i, (t0, t1) in enumerate(s.get("slip_intervals") or []):
        axes[0].vspan(t0, t1, color="C3", alpha=0.3, label="fitted slip episodes" if i == 0
                      else None)
    axes[0].ylabel = "speed (m/s)"
    axes[0].legend(size=8)
    if has_f:
        ft = s["f_t"]
        axes[1].line(np.asarray(ft[0]), np.asarray(ft[1]), color="C3", lw=2, label="fitted f(t)")
        axes[1].hline(1.0, color="k", lw=0.6, ls="--", label="nominal f = 1")
        axes[1].ylim = f_axis(ft[1])
        axes[1].ylabel = "braking rate f"
        axes[1].legend(size=8)
    axes[-1].xlabel = "time since the first odometer stamp (s)"
    axes[0].title = _title(dg, "speed trace")
    return _save(fig, path)


def plot_loss_runs(s: dict, path: Path, dg=None) -> bool:
    """Histogram of the lengths of runs of lost odometer samples against the geometric law of
    independent (Bernoulli) losses and of the fitted two-state chain."""
    runs = s.get("loss_runs")
    if runs is None or len(runs) == 0:
        return False
    runs = np.asarray(runs, dtype=int)
    k = np.arange(1, max(int(runs.max()), 5) + 1)
    fig, ax = _subplots(figsize=(6, 4))
    ax.logy = True  # the decades labelled as plain numbers (0.01, 0.1, 1)
    counts = np.bincount(runs, minlength=k[-1] + 1)[1:]
    ax.bars(k, counts / runs.size, color="0.6", label=f"data ({runs.size} runs)")
    q = s.get("loss_fraction")
    if q is not None and 0 < q < 1:
        ax.line(k, (1 - q) * q ** (k - 1), marker="o", color="C0", ms=3,
                label=f"independent losses (p = {q:.3f})")
    p_bg = s.get("loss_p_bad_good")
    if p_bg:
        ax.line(k, p_bg * (1 - p_bg) ** (k - 1), marker="s", color="C3", ms=3,
                label=f"two-state chain (p_bad_good = {p_bg:.3f})")
    ax.xlabel = "length of a run of lost odometer samples"
    ax.ylabel = "fraction of runs"
    ax.legend(size=8)
    ax.title = _title(dg, "loss runs")
    return _save(fig, path)


def plot_replay(s: dict, path: Path, dg=None) -> bool:
    """Before/after: the recorded commands replayed open loop through the believed and the
    extended model from the measured state at each block's start, against the measured speed,
    and the two models' speed errors."""
    tv = _get(s, "replay_t", "replay_measured", "replay_believed", "replay_extended")
    if tv is None:
        return False
    t, y, vb, va = tv
    fig, (a0, a1) = _subplots(2, 1, figsize=(10, 6), sharex=True,
                              gridspec_kw={"height_ratios": [2, 1]})
    a0.line(t, y, color="k", lw=1.0, label="measured (odometer, 1 s average)")
    a0.line(t, vb, color="C0", lw=0.9, label="believed model")
    a0.line(t, va, color="C3", lw=0.9, label="extended model")
    rms = [float(np.sqrt(np.nanmean((m - y) ** 2))) for m in (vb, va)]
    a1.line(t, vb - y, color="C0", lw=0.8, label=f"believed - measured (RMS {rms[0]:.3f} m/s)")
    a1.line(t, va - y, color="C3", lw=0.8, label=f"extended - measured (RMS {rms[1]:.3f} m/s)")
    a1.hline(0, color="k", lw=0.6)
    block = s.get("replay_block")
    if block:  # the restarts, over each panel's whole height
        starts = np.arange(t[0], t[-1], float(block))
        for ax in (a0, a1):
            ax.vlines(starts, color="0.7", lw=0.5, ls=":")
    a0.ylabel = "speed (m/s)"
    a1.ylabel = "speed error (m/s)"
    a1.xlabel = ("time since the first odometer stamp (s); dotted: restart from the measured "
                 "state")
    for ax in (a0, a1):
        ax.legend("upper right", size=8)
    a0.title = _title(dg, "recorded commands replayed open loop, before/after")
    return _save(fig, path)


PHASE_COLOURS = (("traction", "C0"), ("coasting", "C2"), ("braking", "C3"))


def plot_phases(s: dict, path: Path, dg=None) -> bool:
    """Residual acceleration of the believed model by phase (traction, coasting, braking),
    against position and against speed, binned means +-2 SE per phase; what the report calls
    unexplained shaded (where, or the speed range of its phase)."""
    xy = _get(s, "position", "speed", "residual_accel", "phase")
    if xy is None:
        return False
    x, v, r, ph = xy
    fig, axes = _subplots(1, 2, figsize=(12, 4.2), sharey=True, top=0.55)
    lim = 0.0
    for ax, q, label in ((axes[0], x, "track position (m)"), (axes[1], v, "speed (m/s)")):
        for i, (name, col) in enumerate(PHASE_COLOURS):
            sel = ph == i
            c, m, e = _binned(q[sel], r[sel], 30)
            if c.size:
                ax.errorbar(c, m, 2 * e, marker="o", ms=2.5, lw=0.8, color=col,
                            label=f"{name} (binned mean +-2 SE)")
                lim = max(lim, 1.5 * float(np.percentile(np.abs(m) + 2 * e, 90)))
        for u in s.get("unexplained") or []:
            span = u.get("where") if q is x else u.get("speed")
            if balise_latency(u):
                continue  # the readings' timing: no acceleration to shade
            if span and at_balise(u):
                ax.vlines([span[0]], color="0.4", ls="--", lw=1.0,
                          label=f"unexplained: balise read {u['size']:+.1f} m off")
            elif span and on_odometer(u):
                ax.vspan(span[0], span[1], color="tab:purple", alpha=0.12,
                         label=f"unexplained: the odometer counts differently, "
                               f"{u['size']:+.1f} m")
            elif span:
                ax.vspan(span[0], span[1], color="0.5", alpha=0.2,
                         label=f"unexplained ({u['phase']}, {u['size']:+.3f} m/s^2)")
        _residual_axis(ax, label)
    return _finish_residuals(fig, axes, lim, "residual accel., believed model (m/s^2)", 7,
                             _title(dg, "residual by phase"), path)


PLOTS = (("residual_position.svg", plot_position), ("residual_speed.svg", plot_speed),
         ("residual_phases.svg", plot_phases),
         ("speed_trace.svg", plot_speed_trace), ("loss_runs.svg", plot_loss_runs),
         ("replay.svg", plot_replay))


def _residual_axis(ax, label: str) -> None:
    """One panel of residuals against ``label``: the zero line and the label."""
    ax.hline(0, color="k", lw=0.6)
    ax.xlabel = label


def _finish_residuals(fig, axes, lim: float, ylabel: str, legend_size: int, title: str,
                      path: Path) -> bool:
    """The residual panels' shared y range (+-``lim`` when > 0), label and legend on the
    first, the title, saved to ``path``."""
    if lim > 0:
        axes[0].ylim = (-lim, lim)
    axes[0].ylabel = ylabel
    axes[0].legend(size=legend_size)
    fig.suptitle = title
    return _save(fig, path)


DPI = 90  # the figures' pixels per inch (a 10 x 6 in figure is 900 x 540 px)


def _save(fig, path: Path) -> bool:
    """Write a plot (every plot of this module ends so)."""
    fig.save(path)
    return True


def _title(dg, what: str) -> str:
    return f"{what} -- cause: {dg.cause}" if dg is not None else what


def write_plots(series: dict, out: Path, dg=None) -> list[Path]:
    series = with_replay(series or {})  # the replay's runs are made here, for its plot
    written = []
    for name, fn in PLOTS:
        try:
            if fn(series or {}, out / name, dg):
                written.append(out / name)
        except (ValueError, TypeError, KeyError, IndexError) as exc:  # a plot never kills a run
            print(f"diagnose: plot {name} skipped ({type(exc).__name__}: {exc})",
                  file=sys.stderr)
    return written
