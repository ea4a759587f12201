"""`diagnose`: find what the simulation of a train gets wrong in measured data and name the cause.

    diagnose --bag BAG --line line.yaml --train train.yaml --out DIR

Reads the bag's ``odometer``, ``balise`` and ``control`` topics (a ``ground_truth`` topic, if
present, is never used), aligns the believed model (line.yaml, train.yaml) with the data, fits
one extended model per cause (docs/interfaces.md ``diagnose``: gradient, resistance, braking_rate,
odometer_scale, wheel_slip, bursty_link, brake_delay, mass, clock_drift, power_limit,
adhesion_section, traction_delay) and ranks them.

Output (DIR is created):
  DIR/report.json   cause, parameters, ranking, unexplained, untestable, evidence, gain
                    (docs/interfaces.md)
  DIR/model/        line.yaml, train.yaml, effects.yaml: the believed model extended by every
                    confirmed cause; run it with
                    python -m train_sim.generate --scenario S --model DIR/model --out BAG
  DIR/*.png         residual acceleration of the believed and the extended model against
                    position (with the line profile and the fitted gradient section), against
                    speed and against the commands; the speed trace with slip episodes; f(t);
                    the loss-run histogram; the recorded commands replayed through both
                    models (replay.png); the residual by phase against position and speed
                    with what is unexplained (residual_phases.png)
  DIR/report.html   the report in one self-contained page (verdict first, plots embedded)
  DIR/inputs.json   the bag, line and train analysed and when (the page's header)

How to read the report:
  cause        the first confirmed cause; "none" when nothing is confirmed and nothing is
               left over, "unexplained" when nothing is confirmed and the residuals still
               hold structure that no listed cause explains
  ranking      every cause tested, best first, "none" among them, each with a status:
               confirmed (accepted by the score, its fit on half of the data predicts the
               other half better beyond that gain's own noise, its size is beyond what the
               data resolve, and it shows in every phase, speed, place and time it predicts,
               with the speed law it predicts: a gradient does not grow as v^2 as drag does),
               "not confirmed" (with why) or "rejected" (score not above none's). Only
               confirmed causes go into DIR/model. The score of a cause is
               the BIC-penalised log-likelihood ratio with the prior odds of "none" against
               the K causes tested, 2 (ll_cause - ll_null) - k ln n - 2 ln K (k: its
               parameter count, n: the number of measurements); > 0 means the data support
               the cause, "none" has score 0. With two effects the greedy refit ranks the
               second cause (scored on top of the first) second.
  unexplained  what the confirmed model leaves in the residuals (a calibrated test by phase,
               speed, position, time and command onsets): phase, where (m), when (s), speed
               (m/s), size (m/s^2) and the closest listed cause with why it does not fit;
               [] when nothing is left
  untestable   causes the data cannot test, with the reason (e.g. no braking, no balises)
  evidence     per cause: its score alone, log-likelihood gain, parameter count, n, the fit
               alone and the standard errors of its parameters
  gain         how much better the extended model predicts data not used for the fit, with
               the metric named (held-out speed RMSE for motion causes, balise position error
               for the odometer scale, stamp residual for the clock, log-likelihood per
               sample for the link)
Times in parameters are seconds since the first odometer stamp, on the train's stamp clock.

Exit status: 0 when a diagnosis was made (including "none"); 2 with one line on stderr saying
what is missing when the input is unusable (unreadable bag, no control, no odometer, no
balises, too short, never moving, missing or malformed YAML).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import yaml
from train_core.bagio import BagError, read_bag
from train_core.config import ConfigError, Section, load_yaml
from train_core.effects import Effects, effect_to_dict, parse_effects, true_line, true_train
from train_core.model import line_from_dict, load_line, load_train, train_from_dict

from train_estimation.core.offline.diagnose.residuals import SENSOR_WHY
from train_estimation.core.offline.diagnose.result import jsonable
from train_estimation.core.offline.diagnose.series import with_replay
from train_estimation.core.offline.diagnose.verdict import (  # noqa: F401 (SCORE_FORMULA: help)
    LATENCY_WHY,
    RATE_WHY,
    SCORE_FORMULA,
)
from train_estimation.core.offline.measured import TOPICS, MeasuredRun
from train_estimation.tools.common import EXIT_OK, Progress, fail, one_line, unclosed
from train_estimation.tools.report_html import write_report_html

# ------------------------------------------------------------------------------------------------
# Bag -> MeasuredRun
# ------------------------------------------------------------------------------------------------

def read_measured(path) -> MeasuredRun:
    """The measured run of a bag path; only the topics diagnose uses are decoded (a
    ground_truth topic is never read)."""
    return MeasuredRun.from_bag(read_bag(path, topics=TOPICS))


# ------------------------------------------------------------------------------------------------
# Report
# ------------------------------------------------------------------------------------------------

# ------------------------------------------------------------------------------------------------
# The extended model (DIR/model)
# ------------------------------------------------------------------------------------------------

def write_model(out: Path, dg, line_path: str, train_path: str, data) -> dict:
    """DIR/model: line.yaml (+ fitted gradient section), train.yaml (+ fitted Davis), and
    effects.yaml (the other confirmed causes, in a scenario's ``effects:`` syntax): each
    confirmed cause's ``train_core.effects`` dataclass (``model_effect`` of the cause), put
    where the cause says (``model_file``).

    ``mass`` goes into effects.yaml, not train.yaml: docs/interfaces.md's mass cause keeps the drive
    force computed for the believed mass, which is what train.yaml's mass is in the simulator;
    the effect makes the world's train heavier or lighter exactly as in the data.

    A fitted value the files cannot hold (e.g. a gradient beyond line.yaml's +-60 per mille) is
    left out of the model with a note (printed in the summary and written into the files'
    header), never clipped silently: the report keeps the fit as it is."""
    from train_estimation.core.offline.diagnose import BY_NAME

    d = out / "model"
    d.mkdir(parents=True, exist_ok=True)
    m = _Model(load_yaml(line_path), load_yaml(train_path), line_path)
    ctx = model_context(dg, data, m.line.length)
    for a in dg.accepted:
        cause = BY_NAME[a.cause]
        eff, note = cause.model_effect(a, ctx)
        if eff is None:
            if note:
                m.skipped.append(note)
            continue
        m.add(a.cause, cause.model_file, cause.effect_field, eff, note, max(ctx.duration, 1.0))
    head = ("# written by diagnose: the believed {what} extended by the confirmed causes\n"
            "# ({causes}); times are seconds from the start of the run\n"
            + "".join(f"# {s}\n" for s in m.skipped))
    causes = ", ".join(a.cause for a in dg.accepted) or "none"
    (d / "line.yaml").write_text(head.format(what="line", causes=causes)
                                 + yaml.safe_dump(jsonable(m.line_d), sort_keys=False))
    (d / "train.yaml").write_text(head.format(what="train", causes=causes)
                                  + yaml.safe_dump(jsonable(m.train_d), sort_keys=False))
    (d / "effects.yaml").write_text(
        head.format(what="model's effects (train_sim scenario `effects:` syntax)",
                    causes=causes)
        + (yaml.safe_dump(jsonable(m.effects), sort_keys=False) if m.effects else "{}\n"))
    # what we wrote must load (the simulator reads these files)
    line_from_dict(load_yaml(d / "line.yaml"), str(d / "line.yaml"))
    train_from_dict(load_yaml(d / "train.yaml"), str(d / "train.yaml"))
    parse_effects(Section(load_yaml(d / "effects.yaml"), str(d / "effects.yaml")),
                  max(ctx.duration, 1.0))
    return {"dir": d, "effects": m.effects, "notes": m.notes + m.effect_notes + m.skipped}


def model_context(dg, data, line_length: float):
    """The diagnosis' times on true time: the run's length and the accepted clock drift."""
    from train_estimation.core.offline.diagnose import BY_NAME, ModelContext

    n = len(data.odo_stamp)
    drift = sum(BY_NAME[a.cause].clock_drift(a) for a in dg.accepted)
    duration = float(np.ptp(data.odo_stamp)) if n else 0.0
    return ModelContext(duration=duration / (1.0 + drift), line_length=line_length,
                        drift=drift, t_first=float(np.min(data.odo_stamp)) if n else 0.0,
                        evidence=dg.evidence or {}, odo_stamp=data.odo_stamp,
                        odo_speed=data.odo_speed)


class _Model:
    """The model directory's contents while effects are added to them."""

    def __init__(self, line_d: dict, train_d: dict, line_path: str):
        self.line_d, self.train_d = line_d, train_d
        self.line = line_from_dict(line_d, line_path)
        self.train = train_from_dict(train_d, "train.yaml")
        self.effects: dict = {}
        self.notes, self.effect_notes, self.skipped = [], [], []

    def add(self, name: str, where: str, field: str, eff, note, duration: float) -> None:
        """Put one effect into line.yaml, train.yaml or effects.yaml; a value the file cannot
        hold (the loaders and the simulator's parser decide) is skipped with a note."""
        effects = Effects(**{field: eff})
        try:
            if where == "line":
                new_line = true_line(self.line, effects)
                grads = [{"start": float(s.start), "end": float(s.end),
                          "permille": round(float(s.permille), 4)} for s in new_line.gradients]
                line_from_dict({**self.line_d, "gradients": grads}, "line.yaml")
                self.line, self.line_d["gradients"] = new_line, grads
            elif where == "train":
                new = true_train(self.train, effects)
                for f in dataclasses.fields(new):
                    v = getattr(new, f.name)
                    if v != getattr(self.train, f.name):
                        self.train_d[f.name] = dataclasses.asdict(v) \
                            if dataclasses.is_dataclass(v) else v
                self.train = new
            else:
                params = effect_to_dict(eff)
                parse_effects(Section({field: params}, "effects.yaml"), duration)
                self.effects[field] = params
        except ConfigError as exc:
            self.skipped.append(f"{name} not in the model ({one_line(exc)})")
            return
        if note:
            (self.notes if where != "effects" else self.effect_notes).append(note)


# ------------------------------------------------------------------------------------------------
# Plots (take Diagnosis.series; each plot only when its series exist)
# ------------------------------------------------------------------------------------------------

def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


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
    plt = _plt()
    x, r = xy
    fig, (a0, a1) = plt.subplots(2, 1, figsize=(10, 6), sharex=True,
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
    a0.set_title(_title(dg, "residual acceleration along the line"))
    for ax in (a0, a1):
        ax.grid(alpha=0.3)
    return _save(fig, path)


def plot_speed(s: dict, path: Path, dg=None) -> bool:
    """Residual acceleration against speed (resistance, mass) and against the commanded
    traction and braking (mass, braking rate)."""
    xy = _get(s, "speed", "residual_accel")
    if xy is None:
        return False
    plt = _plt()
    v, r = xy
    ext = _extended(s, r)
    panels = [("speed (m/s)", v)]
    for key, label in (("commanded_traction", "traction command through the actuator (m/s^2)"),
                       ("commanded_braking", "braking command through the actuator (m/s^2)")):
        xs = _get(s, key, "residual_accel")
        if xs is not None:
            panels.append((label, xs[0]))
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 4), sharey=True)
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
        ax.axhline(0, color="k", lw=0.6)
        ax.set_xlabel(label)
        ax.grid(alpha=0.3)
    if lim > 0:
        axes[0].set_ylim(-lim, lim)
    axes[0].set_ylabel("residual accel. (m/s^2)")
    axes[0].legend(fontsize=8)
    fig.suptitle(_title(dg, "residual acceleration against speed and commands"), fontsize=10)
    return _save(fig, path)


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
    plt = _plt()
    t, v = tv
    has_f = s.get("f_t") is not None
    fig, axes = plt.subplots(2 if has_f else 1, 1, figsize=(10, 6 if has_f else 3.5),
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
    axes[0].set_title(_title(dg, "speed trace"))
    return _save(fig, path)


def plot_loss_runs(s: dict, path: Path, dg=None) -> bool:
    """Histogram of the lengths of runs of lost odometer samples against the geometric law of
    independent (Bernoulli) losses and of the fitted two-state chain."""
    runs = s.get("loss_runs")
    if runs is None or len(runs) == 0:
        return False
    plt = _plt()
    runs = np.asarray(runs, dtype=int)
    k = np.arange(1, max(int(runs.max()), 5) + 1)
    fig, ax = plt.subplots(figsize=(6, 4))
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
    ax.set_xlabel("length of a run of lost odometer samples")
    ax.set_ylabel("fraction of runs")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    ax.set_title(_title(dg, "loss runs"))
    return _save(fig, path)


def plot_replay(s: dict, path: Path, dg=None) -> bool:
    """Before/after: the recorded commands replayed open loop through the believed and the
    extended model from the measured state at each block's start, against the measured speed,
    and the two models' speed errors."""
    tv = _get(s, "replay_t", "replay_measured", "replay_believed", "replay_extended")
    if tv is None:
        return False
    plt = _plt()
    t, y, vb, va = tv
    fig, (a0, a1) = plt.subplots(2, 1, figsize=(10, 6), sharex=True,
                                 gridspec_kw={"height_ratios": [2, 1]})
    a0.plot(t, y, color="k", lw=1.0, label="measured (odometer, 1 s average)")
    a0.plot(t, vb, color="C0", lw=0.9, label="believed model")
    a0.plot(t, va, color="C3", lw=0.9, label="extended model")
    rms = [float(np.sqrt(np.nanmean((m - y) ** 2))) for m in (vb, va)]
    a1.plot(t, vb - y, color="C0", lw=0.8, label=f"believed - measured (RMS {rms[0]:.3f} m/s)")
    a1.plot(t, va - y, color="C3", lw=0.8, label=f"extended - measured (RMS {rms[1]:.3f} m/s)")
    a1.axhline(0, color="k", lw=0.6)
    block = s.get("replay_block")
    if block:
        for tb in np.arange(t[0], t[-1], float(block)):
            for ax in (a0, a1):
                ax.axvline(tb, color="0.7", lw=0.5, ls=":")
    a0.set_ylabel("speed (m/s)")
    a1.set_ylabel("speed error (m/s)")
    a1.set_xlabel("time since the first odometer stamp (s); dotted: restart from the measured "
                  "state")
    for ax in (a0, a1):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper right")
    a0.set_title(_title(dg, "recorded commands replayed open loop, before/after"))
    return _save(fig, path)


PHASE_COLOURS = (("traction", "C0"), ("coasting", "C2"), ("braking", "C3"))


def plot_phases(s: dict, path: Path, dg=None) -> bool:
    """Residual acceleration of the believed model by phase (traction, coasting, braking),
    against position and against speed, binned means +-2 SE per phase; what the report calls
    unexplained shaded (where, or the speed range of its phase)."""
    xy = _get(s, "position", "speed", "residual_accel", "phase")
    if xy is None:
        return False
    plt = _plt()
    x, v, r, ph = xy
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2), sharey=True)
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
        ax.axhline(0, color="k", lw=0.6)
        ax.set_xlabel(label)
        ax.grid(alpha=0.3)
    if lim > 0:
        axes[0].set_ylim(-lim, lim)
    axes[0].set_ylabel("residual accel., believed model (m/s^2)")
    axes[0].legend(fontsize=7)
    fig.suptitle(_title(dg, "residual by phase"), fontsize=10)
    return _save(fig, path)


PLOTS = (("residual_position.png", plot_position), ("residual_speed.png", plot_speed),
         ("residual_phases.png", plot_phases),
         ("speed_trace.png", plot_speed_trace), ("loss_runs.png", plot_loss_runs),
         ("replay.png", plot_replay))


def _save(fig, path: Path) -> bool:
    """Lay out, write and close a plot (every plot of this module ends so)."""
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    _plt().close(fig)
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


# ------------------------------------------------------------------------------------------------
# Summary and CLI
# ------------------------------------------------------------------------------------------------

def _fmt_params(p: dict) -> str:
    parts = []
    for k, v in p.items():
        if isinstance(v, float):
            parts.append(f"{k}={v:.4g}")
        elif isinstance(v, list):
            parts.append(f"{k}=" + ",".join(
                "[" + ",".join(f"{x:.1f}" if isinstance(x, float) else str(x) for x in iv) + "]"
                if isinstance(iv, list) else str(iv) for iv in v[:4]) + ("..." if len(v) > 4
                                                                         else ""))
        else:
            parts.append(f"{k}={v}")
    return " ".join(parts)


def summary(dg, bag_path, data, elapsed: float, model: dict) -> list[str]:
    n_odo, n_bal = len(data.odo_stamp), len(data.balise_stamp)
    dur = float(np.ptp(data.odo_stamp)) if n_odo else 0.0
    out = [f"diagnose {bag_path}: {dur:.0f} s, {n_odo} odometer samples, {n_bal} balise "
           f"readings, {elapsed:.1f} s",
           f"{'rank':<5}{'cause':<16}{'score':>10}  {'status':<14} parameters"]
    checks = (((dg.evidence or {}).get("_model") or {}).get("confirmation") or {}).get(
        "checks") or {}
    for i, r in enumerate(dg.ranking[:6]):
        out.append(f"{i + 1:<5}{r.cause:<16}{r.score:>10.1f}  {r.status or '-':<14} "
                   f"{_fmt_params(r.parameters)}")
        if r.why:
            out.append(f"{'':<33}why: {r.why}")
        caveat = (checks.get(r.cause) or {}).get("caveat")
        if r.status == "confirmed" and caveat:
            # what one run's data cannot tell the confirmed cause from (docs/diagnose.md)
            out.append(f"{'':<33}caveat: {caveat}")
    if len(dg.ranking) > 6:
        out.append(f"     ... {len(dg.ranking) - 6} more in report.json")
    for u in dg.unexplained:
        out.append(unexplained_line(u))
    for u in dg.untestable:
        out.append(f"untestable: {u['cause']} ({u['why']})")
    g = dg.gain or {}
    if g.get("before") is not None and g.get("after") is not None:
        out.append(f"gain: {g.get('metric')}: {g['before']:.4g} -> {g['after']:.4g}")
    notes = list(model.get("notes", []))
    if model.get("effects"):
        notes.append("effects.yaml: " + ", ".join(model["effects"]))
    if notes:
        out.append("model: " + "; ".join(notes))
    out.append(f"cause: {dg.cause}")
    return out


def _span(r, unit: str) -> str | None:
    return None if r is None else f"{r[0]:.0f}-{r[1]:.0f} {unit}"


def at_balise(u: dict) -> bool:
    """An ``unexplained`` entry at one balise reading (``where`` one point): its size is the
    reading's offset in m, not an acceleration (docs/diagnose.md)."""
    w = u.get("where")
    return bool(w) and w[0] == w[1]


def clock_step(u: dict) -> bool:
    """An ``unexplained`` entry of a step of the train's clock (``when`` one point, no
    ``where``: no other entry has that shape): its size is the step in s (docs/diagnose.md)."""
    t = u.get("when")
    return not u.get("where") and bool(t) and t[0] == t[1]


def clock_rate(u: dict) -> bool:
    """An ``unexplained`` entry of a change of the train clock's rate (``when`` a span, no
    ``where``, the closest listed cause ``clock_drift`` with the rate's change as the reason:
    a time entry of the motion has the same shape): its size is what the clock reads more by
    the end, in s."""
    t, best = u.get("when"), u.get("best_listed") or {}
    return (not u.get("where") and bool(t) and t[0] != t[1]
            and best.get("cause") == "clock_drift"
            and str(best.get("why", "")).startswith(RATE_WHY))


def balise_latency(u: dict) -> bool:
    """An ``unexplained`` entry of a balise reader that stamps late (no ``where`` nor ``when``,
    the closest listed cause ``clock_drift`` with the latency as the reason): its size is the
    latency in s."""
    best = u.get("best_listed") or {}
    return (not u.get("where") and not u.get("when")
            and str(best.get("why", "")).startswith(LATENCY_WHY))


def sensor_noise(u: dict) -> bool:
    """An ``unexplained`` entry of odometer speed readings that are not the sensor stated (no
    ``where`` nor ``when``, the reason beginning with ``SENSOR_WHY``): its size is the
    readings' SD over the stated SD (docs/diagnose.md)."""
    best = u.get("best_listed") or {}
    return (not u.get("where") and not u.get("when")
            and str(best.get("why", "")).startswith(SENSOR_WHY))


def heat_fade(u: dict) -> bool:
    """An ``unexplained`` entry of a braking weaker than believed that brakes fading as they
    heat explain better than the closest listed cause (phase braking, no ``where`` nor
    ``when``, the reason saying so): its size is the heat law's largest change of the
    acceleration in m/s^2 (> 0: less braking), not a residual."""
    best = u.get("best_listed") or {}
    return (u.get("phase") == "braking" and not u.get("where") and not u.get("when")
            and "a heat law fits better" in str(best.get("why", "")))


def on_odometer(u: dict) -> bool:
    """An ``unexplained`` entry of the odometer's count (``where`` and ``when`` both spans: no
    acceleration family gives both): its size is the odometer error in m (docs/diagnose.md)."""
    w, t = u.get("where"), u.get("when")
    return bool(w) and bool(t) and w[0] != w[1]


def unexplained_size(u: dict) -> str:
    """An ``unexplained`` entry's size with its unit, which depends on the entry's kind: an
    offset in m at a balise or on the odometer, a time in s for the clocks and the balise
    reader, a ratio to the stated SD for the odometer's readings, a residual acceleration in
    m/s^2 otherwise (docs/diagnose.md)."""
    size = u.get("size")
    if not isinstance(size, (int, float)):
        return "-"
    if on_odometer(u) or at_balise(u):
        return f"{size:+.4g} m"
    if clock_step(u) or clock_rate(u) or balise_latency(u):
        return f"{size:+.4g} s"
    if sensor_noise(u):
        return f"x{size:.4g} of the stated SD"
    return f"{size:+.4g} m/s^2"


def unexplained_line(u: dict) -> str:
    """One line of the summary for an ``unexplained`` entry."""
    best = u.get("best_listed") or {}
    closest = f"; closest listed: {best['cause']} ({best['why']})" if best else ""
    if on_odometer(u):
        return (f"unexplained: the odometer counts differently on {_span(u['where'], 'm')} "
                f"({_span(u['when'], 's')}), {u['size']:+.1f} m from the train's position by "
                f"the end of it: it moved to other wheels or its calibration changed, not one "
                f"scale for the run" + closest)
    if clock_step(u):
        return (f"unexplained: the train's clock jumped by {u['size']:+.3f} s at "
                f"{u['when'][0]:.1f} s (the odometer's sample grid moved at once): the readings "
                f"after it are analysed on the clock before it" + closest)
    if clock_rate(u):
        return (f"unexplained: the train's clock changes its rate at {u['when'][0]:.0f} s and "
                f"reads {u['size']:+.3f} s more by {u['when'][1]:.0f} s than one rate says"
                + closest)
    if sensor_noise(u):
        return f"unexplained: {best['why']} (phase all, the whole run)"
    if heat_fade(u):
        sp = u["speed"]
        return (f"unexplained: the brakes deliver less than believed (up to {u['size']:+.3f} "
                f"m/s^2, braking at {sp[0]:.1f}-{sp[1]:.1f} m/s), as brakes that fade as they "
                f"heat: no listed cause; closest listed: {best['cause']} ({best['why']})")
    if balise_latency(u):
        sp = u["speed"]
        return (f"unexplained: every balise reading lies {u['size']:+.3f} s x speed behind the "
                f"train's position by the odometer (read at {sp[0]:.1f}-{sp[1]:.1f} m/s): the "
                f"balise reader stamps late (or early), no listed cause" + closest)
    if at_balise(u):
        return (f"unexplained: the balise at {u['where'][0]:.0f} m (read at {u['when'][0]:.0f} s, "
                f"{u['speed'][0]:.1f} m/s) is {u['size']:+.1f} m from the train's position by "
                f"the odometer: it lies elsewhere than the map says, or another balise was read"
                + closest)
    where = [x for x in (_span(u.get("where"), "m"), _span(u.get("when"), "s")) if x]
    sp = u.get("speed")
    return (f"unexplained: {u['phase']}" + (f" on {', '.join(where)}" if where else "")
            + (f" at {sp[0]:.1f}-{sp[1]:.1f} m/s" if sp else "")
            + f", residual {u['size']:+.3f} m/s^2" + closest)


def inputs_record(args, line, train, data) -> dict:
    """DIR/inputs.json: what was analysed and when, for the report's header."""
    n_odo = len(data.odo_stamp)
    dur = float(np.ptp(data.odo_stamp)) if n_odo else 0.0
    return {"bag": str(Path(args.bag).resolve()), "line": str(Path(args.line).resolve()),
            "line_name": line.name, "train": str(Path(args.train).resolve()),
            "train_name": train.name,
            "data": f"{dur:.0f} s, {n_odo} odometer samples, {len(data.balise_stamp)} balise "
                    f"readings, {len(data.ctrl_stamp)}"
                    " commands",
            "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="diagnose", description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="\n".join(__doc__.splitlines()[2:]))
    p.add_argument("--bag", required=True,
                   help="measured data: rosbag2 (MCAP) with odometer, balise and control")
    p.add_argument("--line", required=True, help="line.yaml as the railway believes it")
    p.add_argument("--train", required=True, help="train.yaml as the railway believes it")
    p.add_argument("--out", required=True,
                   help="output directory: report.json, plots and model/ (created)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--no-plots", action="store_true",
                   help="no PNG plots (report.json, model/ and report.html without figures; "
                        "the plots take longer than the analysis on a short bag)")
    args = p.parse_args(argv)
    from train_estimation.core.offline.diagnose import DiagnoseError, diagnose

    t0 = time.perf_counter()
    bag = None
    try:
        line, train = load_line(args.line), load_train(args.train)
        bag = read_bag(args.bag, topics=TOPICS)
        data = MeasuredRun.from_bag(bag)
        if unclosed(bag) and not args.quiet:
            print(f"diagnose: note: {args.bag}{unclosed(bag)}", file=sys.stderr)
        bar = None if args.quiet else Progress("diagnose", what_width=36)
        dg = diagnose(data, line, train, progress=bar)
    except (ConfigError, BagError) as exc:
        return fail("diagnose", str(exc))
    except DiagnoseError as exc:  # a truncated bag is the usual reason: named with its repair
        return fail("diagnose", f"cannot diagnose {args.bag}: {exc}{unclosed(bag)}")
    elapsed = time.perf_counter() - t0
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "report.json").write_text(json.dumps(dg.to_json(), indent=1) + "\n")
    (out / "inputs.json").write_text(json.dumps(inputs_record(args, line, train, data)) + "\n")
    model = write_model(out, dg, args.line, args.train, data)
    if not args.no_plots:
        write_plots(dg.series, out, dg)
    lines = summary(dg, args.bag, data, elapsed, model)
    lines.insert(-1, f"report: {write_report_html(out, 'diagnose')}")  # "cause: ..." stays last
    print("\n".join(lines))
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
