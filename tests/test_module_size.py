"""diagnose's and fleet's modules stay readable: none over MAX_LINES lines (the analysis in
core/offline/diagnose/ with its causes, and the tools around it: the command lines, plots,
report page and fleet's task, row and report)."""

from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "ros_ws/src/train_estimation/train_estimation"
MAX_LINES = 600
GLOBS = ("core/offline/diagnose/**/*.py", "tools/diagnose*.py", "tools/fleet*.py",
         "tools/report_*.py")


def test_no_diagnose_or_fleet_module_is_over_max_lines():
    files = sorted({p for g in GLOBS for p in PKG.glob(g)})
    assert len(files) > 20, files  # the globs still find the package
    sizes = {str(p.relative_to(PKG)): len(p.read_text().splitlines()) for p in files}
    over = {k: n for k, n in sizes.items() if n > MAX_LINES}
    assert not over, f"over {MAX_LINES} lines: {over} (split by role)"


def test_the_svg_plot_writer_stays_small():
    """tools/svgplot.py, diagnose's plot writer, is under 400 lines: a writer for the few
    kinds of mark the plots use, not a plotting library."""
    assert len((PKG / "tools" / "svgplot.py").read_text().splitlines()) < 400
