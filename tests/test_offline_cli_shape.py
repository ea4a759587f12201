"""The offline CLIs sit side by side on the core: none imports another (fleet reads a bag through
the core's MeasuredRun, not through identify's or diagnose's CLI), they share one exit-code ladder
(``tools/common``), and that shared module stays light (identify and check_bag start without
the diagnose package)."""

import ast
import json
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PKG = REPO / "ros_ws" / "src" / "train_estimation"
TOOLS = PKG / "train_estimation" / "tools"
OFFLINE = ("identify", "diagnose", "fleet", "check_bag")  # tools/common's users


def console_tools() -> set[str]:
    """The tools modules that are console scripts (setup.py's entry points)."""
    return set(re.findall(r"train_estimation\.tools\.(\w+):main", (PKG / "setup.py").read_text()))


def test_the_offline_clis_are_console_scripts():
    assert set(OFFLINE) <= console_tools()


def test_no_cli_imports_another():
    clis = console_tools()
    pat = re.compile(r"^\s*(?:from|import)\s+train_estimation\.tools\.(\w+)", re.M)
    bad = [f"{name} imports {used}" for name in sorted(clis)
           for used in pat.findall((TOOLS / f"{name}.py").read_text())
           if used in clis and used != name]
    assert bad == []


def test_offline_clis_return_the_shared_exit_codes():
    """main() returns tools/common's EXIT_* (or fail()), never a bare number."""
    bad = []
    for name in OFFLINE:
        tree = ast.parse((TOOLS / f"{name}.py").read_text())
        main = next(n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "main")
        bad += [f"{name}.py:{r.lineno} returns {r.value.value!r}" for r in ast.walk(main)
                if isinstance(r, ast.Return) and isinstance(r.value, ast.Constant)
                and isinstance(r.value.value, int)]
    assert bad == []


def test_common_does_not_import_the_analyses():
    code = ("import json, sys; import train_estimation.tools.common;"
            " import train_estimation.tools.identify;"
            " print(json.dumps(sorted(m for m in sys.modules"
            " if m.startswith('train_estimation.core.offline.diagnose'))))")
    src = ":".join(str(REPO / "ros_ws" / "src" / p) for p in ("train_core", "train_estimation"))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, env={"PYTHONPATH": src, "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr[-2000:]
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []


def test_a_reader_that_goes_away_stops_a_tool_quietly():
    """``check_bag BAG | head -1``: the tool stops with 141 (SIGPIPE's), no traceback."""
    p = subprocess.Popen([sys.executable, "-m", "train_estimation.tools.check_bag",
                          str(REPO / "bags" / "metro_demo_short"), "--no-plots"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    p.stdout.close()  # the reader is gone before the tool writes
    err = p.stderr.read().decode()
    assert p.wait(timeout=120) == 141, err
    assert "Traceback" not in err
