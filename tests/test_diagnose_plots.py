"""diagnose's plots as a reader sees them: every panel of residual_speed.svg labelled, with a
zero line and a grid; f(t) on an axis holding nominal 1 and at least F_MIN_SPAN wide; the
extended model's residual beside the believed model's when a cause is accepted; the SVG files
well-formed, with every series drawn, the same bytes for the same data; svgplot's ticks and
its polylines' decimation, which keeps every spike."""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from train_estimation.tools import diagnose_plots as plots
from train_estimation.tools import svgplot

SVG = "{http://www.w3.org/2000/svg}"


@pytest.fixture
def figures(monkeypatch):
    """The figures the plot functions draw, kept for inspection."""
    kept = []
    make = plots._subplots

    def keep(*a, **kw):
        fig, ax = make(*a, **kw)
        kept.append(fig)
        return fig, ax

    monkeypatch.setattr(plots, "_subplots", keep)
    return kept


def series(extended: bool) -> dict:
    rng = np.random.default_rng(3)
    n = 2000
    v = rng.uniform(0, 20, n)
    tr = np.where(rng.random(n) < 0.4, rng.uniform(0, 1, n), 0.0)
    br = np.where(tr == 0, -rng.uniform(0, 0.8, n), 0.0)
    r = 0.3 * br + rng.normal(0, 0.05, n)
    s = {"speed": v, "residual_accel": r, "commanded_traction": tr, "commanded_braking": br}
    if extended:
        s["residual_accel_extended"] = r - 0.3 * br
    return s


def _has_zero_line(ax) -> bool:
    return any(it["kind"] == "hline" and it["y"] == 0.0 for it in ax.items)


@pytest.mark.parametrize("extended", [False, True])
def test_every_residual_speed_panel_has_its_label_zero_line_and_grid(figures, tmp_path,
                                                                     extended):
    assert plots.plot_speed(series(extended), tmp_path / "r.svg")
    (fig,) = figures
    axes = fig.axes
    assert len(axes) == 3
    for ax in axes:
        assert ax.xlabel, "unlabelled panel"
        assert _has_zero_line(ax)
    colours = {it["color"] for ax in axes for it in ax.items if it["kind"] == "errorbar"}
    assert ("C3" in colours) == extended  # the extended model's curve only when there is one
    root = ET.parse(tmp_path / "r.svg").getroot()
    # each panel's grid: one path of light lines
    assert sum(p.get("stroke") == "#b0b0b0" for p in root.iter(f"{SVG}path")) == 3


def test_braking_rate_axis_holds_nominal_and_a_minimum_span():
    lo, hi = plots.f_axis([0.9987, 1.0])  # a change of 0.1 % must not fill the panel
    assert lo <= 0.9987 and hi >= 1.0 and hi - lo >= plots.F_MIN_SPAN
    lo, hi = plots.f_axis([0.7, 0.7])  # worn brakes: both the fit and nominal 1 in view
    assert lo < 0.7 and hi > 1.0
    lo, hi = plots.f_axis([])
    assert lo < 1.0 < hi


def test_speed_trace_draws_f_on_that_axis(figures, tmp_path):
    t = np.linspace(0, 300, 600)
    s = {"odo_t": t, "odo_speed": np.full(t.size, 10.0),
         "f_t": (np.array([0.0, 300.0]), np.array([0.9995, 0.9987]))}
    assert plots.plot_speed_trace(s, tmp_path / "s.svg")
    lo, hi = figures[0].axes[1].ylim
    assert lo <= 0.9987 and hi >= 1.0 and hi - lo >= plots.F_MIN_SPAN


def test_the_plots_are_the_same_bytes_for_the_same_series(tmp_path):
    """Two runs on the same data write the same files (no date, no run-dependent state), each
    a well-formed SVG document of the figure's size at DPI with every series drawn."""
    rng = np.random.default_rng(1)
    t = np.arange(0.0, 200.0, 0.5)
    v = 10.0 + np.sin(t / 20.0)
    s = {"t": t, "position": 10.0 * t, "speed": v, "residual_accel": rng.normal(0, 0.05, t.size),
         "residual_accel_extended": rng.normal(0, 0.04, t.size), "odo_t": t, "odo_speed": v,
         "phase": np.arange(t.size) % 3, "line_gradient": [(0.0, 2000.0, 1.0)],
         "loss_runs": np.array([1, 2, 1, 4]), "loss_fraction": 0.05,
         "replay_t": t, "replay_measured": v, "replay_believed": v + 0.1,
         "replay_extended": v + 0.02, "replay_block": 30.0}
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    first = plots.write_plots(s, tmp_path / "a")
    second = plots.write_plots(s, tmp_path / "b")
    assert [p.name for p in first] == [p.name for p in second] and len(first) == 6
    for a, b in zip(first, second):
        assert a.read_bytes() == b.read_bytes(), a.name
        root = ET.parse(a).getroot()
        width = {"residual_speed.svg": 378, "residual_phases.svg": 1080, "loss_runs.svg": 540}
        assert root.tag == f"{SVG}svg" and root.get("width") == str(width.get(a.name, 900))
        coords = [el.get(k) for el in root.iter() for k in ("d", "x", "y", "cx", "cy", "width",
                                                            "height", "r") if el.get(k)]
        assert not any(re.search(r"\d\.\d\d", c) for c in coords), a.name  # 0.1 px
    # the replay: measured, believed, extended and the two errors, as five polylines
    root = ET.parse(tmp_path / "a" / "replay.svg").getroot()
    strokes = [p.get("stroke") for p in root.iter(f"{SVG}path") if p.get("fill") == "none"
               and p.get("stroke") in ("#000000", "#1f77b4", "#d62728")]
    texts = [t.text for t in root.iter(f"{SVG}text")]
    assert "believed model" in texts and "extended model" in texts
    assert any(t.startswith("believed - measured (RMS") for t in texts)
    assert len(strokes) >= 5, strokes


def test_nice_ticks_step_by_1_2_5_and_give_at_least_three():
    assert list(svgplot.nice_ticks(0.0, 10.0, 5)) == [0.0, 2.0, 4.0, 6.0, 8.0, 10.0]
    assert len(svgplot.nice_ticks(-2.3, 4.4, 3)) >= 3
    t = svgplot.nice_ticks(0.9, 1.1, 4)
    assert np.allclose(t, [0.9, 0.95, 1.0, 1.05, 1.1])
    assert svgplot.tick_label(-0.0, 0.5) == "0.0" and svgplot.tick_label(0.05, 0.01) == "0.05"


def test_a_polyline_keeps_each_pixel_column_s_extremes():
    """100,000 samples over 800 px become about two per column, and a one-sample spike is one
    of them."""
    x = np.arange(100_000, dtype=float)
    y = np.sin(x / 5000.0)
    y[54_321] = 40.0
    fig = svgplot.Figure(10, 4)
    fig.axes[0].line(x, y)
    d = next(p.get("d") for p in ET.fromstring(fig.svg()).iter(f"{SVG}path")
             if p.get("stroke") == "#1f77b4")
    pts = d[1:].split()
    assert len(pts) // 2 <= 2 * 800
    ys = np.array(pts[1::2], dtype=float)
    assert ys.min() <= fig.axes[0].box[1] + 0.05 * fig.axes[0].box[3]  # the spike, at the top
