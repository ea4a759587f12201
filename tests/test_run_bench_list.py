"""`./run bench` without a name lists the benchmarks (no set-up needed to read the list)."""

import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_run_bench_alone_lists_every_benchmark_with_its_first_line():
    res = subprocess.run([str(REPO / "run"), "bench"], capture_output=True, text=True,
                         timeout=60, cwd=REPO)
    assert res.returncode == 0, res.stderr
    names = sorted(p.stem[len("bench_"):] for p in (REPO / "benchmarks").glob("bench_*.py"))
    listed = [ln.split()[0] for ln in res.stdout.splitlines() if ln.startswith("  ")]
    assert listed == names
    assert "diagnose         Benchmark of `diagnose`" in res.stdout
    res = subprocess.run([str(REPO / "run"), "bench", "no_such"], capture_output=True,
                         text=True, timeout=60, cwd=REPO)
    assert res.returncode == 2 and "no benchmark 'no_such'" in res.stderr
