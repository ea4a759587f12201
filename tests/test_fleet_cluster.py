"""`fleet` on a Dask cluster started as a user starts one: `./run scheduler` and `./run worker`
as separate processes on 127.0.0.1 (free ports), not a LocalCluster.

First one worker started from the project's virtual environment WITHOUT the ROS workspace on
its path (the plain `dask worker` of the venv): `fleet` must stop before submitting, exit 2 and
say in one line what is missing and how to start workers, and write no report. Then two
workers started with `./run worker`: the fleet's bags are analysed by both and the report is
written. Every process is stopped by its PID (the `launch` fixture), also on failure.
"""

import json
import os
import socket
import subprocess
import sys
import time

import pytest

from train_sim.fleet import FleetSpec, write_fleet

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def small_fleet(tmp_path_factory):
    d = tmp_path_factory.mktemp("cluster_fleet")
    write_fleet(d, FleetSpec(trains=2, runs=1, degraded=0, seed=5, stops=1))
    return d


def _fleet(manifest, out, address) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "train_estimation.tools.fleet", "--manifest", str(manifest),
         "--out", str(out), "--scheduler", address, "--quiet", "--wait", "30"],
        capture_output=True, text=True, timeout=180)


def _wait_workers(client, n: int, timeout: float = 60.0) -> None:
    end = time.monotonic() + timeout
    while len(client.scheduler_info(n_workers=-1)["workers"]) != n:
        assert time.monotonic() < end, f"the scheduler did not get {n} workers"
        time.sleep(0.2)


def test_fleet_on_scheduler_and_worker_processes(launch, small_fleet, tmp_path):
    from dask.distributed import Client

    port, dash = free_port(), free_port()
    address = f"tcp://127.0.0.1:{port}"
    launch.start([os.path.join(REPO, "run"), "scheduler", "--host", "127.0.0.1", "--port",
                  str(port), "--dashboard-address", f"127.0.0.1:{dash}"], name="scheduler")
    # the venv's own dask worker, without the workspace: what a user gets without ./run
    plain = {k: v for k, v in launch.env.items()}
    bad = subprocess.Popen(
        [os.path.join(REPO, ".venv", "bin", "dask"), "worker", address, "--nthreads", "1",
         "--no-nanny", "--no-dashboard"],
        env={k: v for k, v in plain.items() if k not in ("PYTHONPATH", "AMENT_PREFIX_PATH")},
        cwd=str(tmp_path), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    launch.procs.append(("plain-worker", bad))  # stopped by PID at teardown too
    bad.log_path = os.devnull
    end = time.monotonic() + 60
    while True:
        try:
            client = Client(address, timeout=5)
            break
        except OSError:
            assert time.monotonic() < end, "the scheduler did not start"
            time.sleep(0.5)
    with client:
        _wait_workers(client, 1)
        out = tmp_path / "out_bad"
        r = _fleet(small_fleet / "manifest.csv", out, address)
        lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
        assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
        assert len(lines) == 2, r.stderr  # "N bags to analyse on ..." and the one line why
        assert "No module named 'train_estimation'" in lines[1], lines[1]
        assert f"./run worker {address}" in lines[1], lines[1]
        assert not (out / "report.md").exists() and "map error" not in r.stdout

        launch.stop(bad)
        _wait_workers(client, 0)
        for i in range(2):
            launch.start([os.path.join(REPO, "run"), "worker", address, "--nworkers", "1",
                          "--no-nanny", "--no-dashboard"], name=f"worker{i}")
        _wait_workers(client, 2)
        out = tmp_path / "out"
        r = _fleet(small_fleet / "manifest.csv", out, address)
        assert r.returncode == 0, (r.stdout, r.stderr)
        assert f"dashboard at http://127.0.0.1:{dash}/status" in r.stderr
        res = json.loads((out / "fleet.json").read_text())
        assert res["failures"] == []
        assert len(res["run"]["bags_per_worker"]) == 2, res["run"]  # both workers worked
        report = (out / "report.md").read_text()
        first = report.splitlines()[0]
        assert first.startswith("# Fleet report") and "failed" not in first
        assert "2 bags of 2 trains on 2 lines: 2 analysed, 0 failed" in report
        # one run per line cannot exclude a map error: the report says so
        assert "**The consensus is unreliable**" in report
        assert "Too few analysed runs on north, south" in report


def test_embedded_cluster_dashboard():
    """The embedded cluster's dashboard, on a free port: its status page is served."""
    import urllib.request

    from train_estimation.tools import fleet_dask as runner

    port = free_port()
    with runner.local_cluster(1, f"127.0.0.1:{port}") as cluster:
        assert cluster.dashboard_link == f"http://127.0.0.1:{port}/status"
        with urllib.request.urlopen(cluster.dashboard_link, timeout=30) as page:
            assert page.status == 200 and b"bokeh" in page.read().lower()
