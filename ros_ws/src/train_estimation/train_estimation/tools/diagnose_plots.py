"""diagnose's plots (DIR/*.png): the residual acceleration of the believed and the extended
model against position (with the line profile and the fitted gradient section), against speed
and the commands, and by phase with what is unexplained; the speed trace with slip episodes and
f(t); the loss-run histogram; the recorded commands replayed through both models.

Each plot takes ``Diagnosis.series`` and is drawn only when its series exist; matplotlib (its
Figure on the Agg canvas, not pyplot) is imported on the first plot, so ``diagnose --no-plots``
never loads it.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from train_estimation.core.offline.diagnose.series import with_replay
from train_estimation.tools.diagnose_unexplained import at_balise, balise_latency, on_odometer


def _subplots(*grid, figsize, **kw):
    """A figure of ``figsize`` inches at DPI on matplotlib's Agg canvas and its axes, as
    ``pyplot.subplots(*grid, figsize=figsize, **kw)`` makes them, without pyplot: no figure
    manager, no registry of open figures to close, no backend to select."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, dpi=DPI)
    FigureCanvasAgg(fig)
    return fig, fig.subplots(*grid, **kw)


def _decimal_log_formatter():
    """A log axis' tick labels as plain numbers (0.001, 0.01, 1; 1e-05 below), labelled where
    matplotlib's own log formatter labels them, without its mathtext."""
    from matplotlib.ticker import LogFormatter

    class Decimal(LogFormatter):
        def _num_to_string(self, x, vmin, vmax):
            return f"{x:g}"

    return Decimal()


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
    a0.plot(x, r, ".", ms=1, alpha=0.15, color="0.5", label="residual (believed model)")
    span = float(np.nanmax(x) - np.nanmin(x)) if np.isfinite(x).any() else 0.0
    c, m, e = _binned(x, r, max(10, int(span // 100)))
    if c.size:
        a0.fill_between(c, m - 2 * e, m + 2 * e, color="C0", alpha=0.25, step="mid")
        a0.step(c, m, where="mid", lw=1.2, color="C0",
                label="believed model: mean per 100 m, +-2 SE")
        lim = 1.5 * float(np.percentile(np.abs(m) + 2 * e, 90))  # a few sparse bins may clip
        if lim > 0:
            a0.set_ylim(-lim, lim)
    ext = _extended(s, r)
    if ext is not None:
        c, m, e = _binned(x, ext, max(10, int(span // 100)))
        if c.size:
            a0.step(c, m, where="mid", lw=1.2, color="C3",
                    label="extended model: mean per 100 m")
    a0.axhline(0, color="k", lw=0.6)
    a0.set_ylabel("residual accel. (m/s^2)")
    prof = s.get("line_gradient") or []
    for st, en, pm in prof:
        a1.plot([st, en], [pm, pm], color="C2", lw=1.5)
    sec = s.get("gradient_section")
    if sec is not None:
        st, en, pm = sec
        for ax in (a0, a1):
            ax.axvspan(st, en, color="C3", alpha=0.15)
        a1.plot([st, en], [pm, pm], color="C3", lw=2.5, label=f"fitted: {pm:+.2f} per mille "
                f"on [{st:.0f}, {en:.0f}) m")
        # the residual a missing section leaves: -g sin(theta) / (1 + lambda), about
        a0.plot([st, en], [-9.81e-3 * pm] * 2, color="C3", lw=2, label="fitted section's effect")
        a1.legend(fontsize=8)
    for name, pos in s.get("stations") or []:
        a1.axvline(pos, color="0.6", lw=0.6, ls=":")
        a1.text(pos, a1.get_ylim()[1] if prof else 0, str(name), fontsize=7, va="top")
    a1.set_ylabel("gradient (per mille)")
    a1.set_xlabel("track position (m)")
    a0.legend(fontsize=8, loc="upper right")
    _set_title(a0, dg, "residual acceleration along the line")
    for ax in (a0, a1):
        ax.grid(alpha=0.3)
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
    fig, axes = _subplots(1, len(panels), figsize=(4.2 * len(panels), 4), sharey=True)
    axes = np.atleast_1d(axes)
    lim = 0.0
    for ax, (label, x) in zip(axes, panels):
        n = min(x.size, r.size)
        ax.plot(x[:n], r[:n], ".", ms=1, alpha=0.15, color="0.5")
        sel = np.abs(x[:n]) > 1e-3 if "command" in label else np.ones(n, bool)
        c, m, e = _binned(x[:n][sel], r[:n][sel], 20)
        if c.size:
            ax.errorbar(c, m, yerr=2 * e, fmt="o-", ms=3, color="C0",
                        label="believed model: binned mean +-2 SE")
            lim = max(lim, 1.5 * float(np.percentile(np.abs(m) + 2 * e, 90)))
        if ext is not None:
            c, m, e = _binned(x[:n][sel], ext[:n][sel], 20)
            if c.size:
                ax.errorbar(c, m, yerr=2 * e, fmt="s-", ms=3, color="C3",
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
    axes[0].plot(t, v, lw=0.7, label="odometer speed")
    ref = _get(s, "t", "speed")
    if ref is not None:
        axes[0].plot(ref[0], ref[1], lw=0.7, color="C1", alpha=0.8, label="reference speed")
    for i, (t0, t1) in enumerate(s.get("slip_intervals") or []):
        axes[0].axvspan(t0, t1, color="C3", alpha=0.3, label="fitted slip episodes" if i == 0
                        else None)
    axes[0].set_ylabel("speed (m/s)")
    axes[0].legend(fontsize=8)
    if has_f:
        ft = s["f_t"]
        axes[1].plot(np.asarray(ft[0]), np.asarray(ft[1]), color="C3", lw=2, label="fitted f(t)")
        axes[1].axhline(1.0, color="k", lw=0.6, ls="--", label="nominal f = 1")
        axes[1].set_ylim(*f_axis(ft[1]))
        axes[1].set_ylabel("braking rate f")
        axes[1].legend(fontsize=8)
    axes[-1].set_xlabel("time since the first odometer stamp (s)")
    for ax in axes:
        ax.grid(alpha=0.3)
    _set_title(axes[0], dg, "speed trace")
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
    counts = np.bincount(runs, minlength=k[-1] + 1)[1:]
    ax.bar(k, counts / runs.size, color="0.6", label=f"data ({runs.size} runs)")
    q = s.get("loss_fraction")
    if q is not None and 0 < q < 1:
        ax.plot(k, (1 - q) * q ** (k - 1), "o-", color="C0", ms=3,
                label=f"independent losses (p = {q:.3f})")
    p_bg = s.get("loss_p_bad_good")
    if p_bg:
        ax.plot(k, p_bg * (1 - p_bg) ** (k - 1), "s-", color="C3", ms=3,
                label=f"two-state chain (p_bad_good = {p_bg:.3f})")
    ax.set_yscale("log")
    # the decades as 0.01, 0.1, 1 rather than 10^-2 typeset as mathtext (its parser's first
    # use costs a tenth of a second of CPU)
    ax.yaxis.set_major_formatter(_decimal_log_formatter())
    ax.yaxis.set_minor_formatter(_decimal_log_formatter())
    ax.set_xlabel("length of a run of lost odometer samples")
    ax.set_ylabel("fraction of runs")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    _set_title(ax, dg, "loss runs")
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
    a0.plot(t, y, color="k", lw=1.0, label="measured (odometer, 1 s average)")
    a0.plot(t, vb, color="C0", lw=0.9, label="believed model")
    a0.plot(t, va, color="C3", lw=0.9, label="extended model")
    rms = [float(np.sqrt(np.nanmean((m - y) ** 2))) for m in (vb, va)]
    a1.plot(t, vb - y, color="C0", lw=0.8, label=f"believed - measured (RMS {rms[0]:.3f} m/s)")
    a1.plot(t, va - y, color="C3", lw=0.8, label=f"extended - measured (RMS {rms[1]:.3f} m/s)")
    a1.axhline(0, color="k", lw=0.6)
    block = s.get("replay_block")
    if block:  # the restarts as one collection a panel (one artist, not one per line)
        starts = np.arange(t[0], t[-1], float(block))
        for ax in (a0, a1):
            ax.vlines(starts, 0, 1, transform=ax.get_xaxis_transform(), color="0.7", lw=0.5,
                      ls=":")
    a0.set_ylabel("speed (m/s)")
    a1.set_ylabel("speed error (m/s)")
    a1.set_xlabel("time since the first odometer stamp (s); dotted: restart from the measured "
                  "state")
    for ax in (a0, a1):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper right")
    _set_title(a0, dg, "recorded commands replayed open loop, before/after")
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
    fig, axes = _subplots(1, 2, figsize=(12, 4.2), sharey=True)
    lim = 0.0
    for ax, q, label in ((axes[0], x, "track position (m)"), (axes[1], v, "speed (m/s)")):
        for i, (name, col) in enumerate(PHASE_COLOURS):
            sel = ph == i
            c, m, e = _binned(q[sel], r[sel], 30)
            if c.size:
                ax.errorbar(c, m, yerr=2 * e, fmt="o-", ms=2.5, lw=0.8, color=col,
                            label=f"{name} (binned mean +-2 SE)")
                lim = max(lim, 1.5 * float(np.percentile(np.abs(m) + 2 * e, 90)))
        for u in s.get("unexplained") or []:
            span = u.get("where") if q is x else u.get("speed")
            if balise_latency(u):
                continue  # the readings' timing: no acceleration to shade
            if span and at_balise(u):
                ax.axvline(span[0], color="0.4", ls="--", lw=1.0,
                           label=f"unexplained: balise read {u['size']:+.1f} m off")
            elif span and on_odometer(u):
                ax.axvspan(span[0], span[1], color="tab:purple", alpha=0.12,
                           label=f"unexplained: the odometer counts differently, "
                                 f"{u['size']:+.1f} m")
            elif span:
                ax.axvspan(span[0], span[1], color="0.5", alpha=0.2,
                           label=f"unexplained ({u['phase']}, {u['size']:+.3f} m/s^2)")
        _residual_axis(ax, label)
    return _finish_residuals(fig, axes, lim, "residual accel., believed model (m/s^2)", 7,
                             _title(dg, "residual by phase"), path)


PLOTS = (("residual_position.png", plot_position), ("residual_speed.png", plot_speed),
         ("residual_phases.png", plot_phases),
         ("speed_trace.png", plot_speed_trace), ("loss_runs.png", plot_loss_runs),
         ("replay.png", plot_replay))


def _residual_axis(ax, label: str) -> None:
    """One panel of residuals against ``label``: the zero line, the label, the grid."""
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xlabel(label)
    ax.grid(alpha=0.3)


def _finish_residuals(fig, axes, lim: float, ylabel: str, legend_size: int, title: str,
                      path: Path) -> bool:
    """The residual panels' shared y range (+-``lim`` when > 0), label and legend on the
    first, the title, saved to ``path``."""
    if lim > 0:
        axes[0].set_ylim(-lim, lim)
    axes[0].set_ylabel(ylabel)
    axes[0].legend(fontsize=legend_size)
    fig.suptitle(title, fontsize=10)
    return _save(fig, path, top=0.55)


DPI = 90  # the PNGs' pixels per inch


def _save(fig, path: Path, top: float = 0.4, space: float = 0.2) -> bool:
    """Lay out, write and close a plot (every plot of this module ends so).

    The margins are fixed, in inches (``top``: the title's, 0.5 with a suptitle; ``space``
    between panels, 0.1 where they share the axis between them): they hold the tick labels,
    axis labels and titles these plots have with some room to spare (tight_layout gave
    0.63-0.88 in left, 0.59 bottom, 0.36-0.48 top, 0.15 right), without tight_layout's extra
    pass over every text and tick (a third of a plot's CPU)."""
    w, h = fig.get_size_inches()
    rows, cols = fig.axes[0].get_subplotspec().get_gridspec().get_geometry()
    left, right, bottom = 0.95, 0.2, 0.6
    aw = (w - left - right - space * (cols - 1)) / cols  # a panel's mean width and height
    ah = (h - bottom - top - space * (rows - 1)) / rows
    fig.subplots_adjust(left=left / w, right=1 - right / w, bottom=bottom / h, top=1 - top / h,
                        wspace=space / aw, hspace=space / ah)
    _write_png(fig, path)
    return True


PNG_COMPRESSION = 2  # zlib's level: half the CPU of PIL's default 6, the files ~10 % larger


def _write_png(fig, path: Path) -> None:
    """Draw the figure once and write it as an RGB PNG (the page is opaque: its alpha channel,
    255 everywhere, is left out, as matplotlib's savefig keeps it), with savefig's metadata
    (the resolution, the software: no date, so that a plot's bytes depend on its data only)."""
    import matplotlib
    from PIL import Image, PngImagePlugin

    fig.canvas.draw()
    rgba = np.asarray(fig.canvas.buffer_rgba())
    opaque = bool((rgba[:, :, 3] == 255).all())
    img = Image.fromarray(np.ascontiguousarray(rgba[:, :, :3]) if opaque else rgba,
                          "RGB" if opaque else "RGBA")
    info = PngImagePlugin.PngInfo()
    info.add_text("Software", f"Matplotlib version{matplotlib.__version__}, "
                              "https://matplotlib.org/")
    img.save(path, format="png", compress_level=PNG_COMPRESSION, dpi=(DPI, DPI), pnginfo=info)


def _set_title(ax, dg, what: str) -> None:
    """The panel's title at its top (y = 1): matplotlib's automatic placement, which measures
    every tick label to clear a top axis these plots do not have, is left out."""
    ax.set_title(_title(dg, what), y=1.0)


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
