"""diagnose's plots as a reader sees them: every panel of residual_speed.png labelled, with a
zero line and a grid; f(t) on an axis holding nominal 1 and at least F_MIN_SPAN wide; the
extended model's residual beside the believed model's when a cause is accepted."""

from __future__ import annotations

import numpy as np
import pytest

from train_estimation.tools import diagnose_plots as plots


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
    return any(np.allclose(ln.get_ydata(), 0.0) and len(ln.get_ydata()) == 2
               for ln in ax.get_lines())


@pytest.mark.parametrize("extended", [False, True])
def test_every_residual_speed_panel_has_its_label_zero_line_and_grid(figures, tmp_path,
                                                                     extended):
    assert plots.plot_speed(series(extended), tmp_path / "r.png")
    (fig,) = figures
    axes = fig.get_axes()
    assert len(axes) == 3
    for ax in axes:
        assert ax.get_xlabel(), "unlabelled panel"
        assert _has_zero_line(ax)
        assert any(g.get_visible() for g in ax.xaxis.get_gridlines())
    colours = {ln.get_color() for ax in axes for ln in ax.get_lines()}
    assert ("C3" in colours) == extended  # the extended model's curve only when there is one


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
    assert plots.plot_speed_trace(s, tmp_path / "s.png")
    lo, hi = figures[0].get_axes()[1].get_ylim()
    assert lo <= 0.9987 and hi >= 1.0 and hi - lo >= plots.F_MIN_SPAN


def test_the_plots_are_the_same_bytes_for_the_same_series(tmp_path):
    """Two runs on the same data write the same files (no date, no run-dependent state), each
    an opaque RGB PNG at the plots' resolution."""
    from PIL import Image

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
        with Image.open(a) as im:
            assert im.mode == "RGB" and round(im.info["dpi"][0]) == plots.DPI, a.name
