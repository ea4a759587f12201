"""Pytest fixtures shared by every test of the project (unit, integration, bag tests).

ROS isolation is done here, at import time, before any test or fixture can start rclpy or a
node process, so that no test depends on the developer's shell:

- ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` (DDS discovery and traffic stay on loopback);
- ``ROS_DOMAIN_ID``: one random id per test session in [1, 90] (``TRAIN_ROS_DOMAIN_ID``
  overrides it), so two test runs on one machine do not see each other's nodes; pytest-xdist's
  worker gwN uses that id + N, so two workers never share a ROS graph;
- ``ROS_LOG_DIR`` inside the repo's ignored ``.cache/`` folder.

Fixtures:
- ``ros_env``: the environment (a dict) every node process gets;
- ``launch``: start node processes; every process is stopped by its PID at teardown
  (SIGINT, then SIGTERM, then SIGKILL), also when the test fails;
- ``ros_node``: an rclpy node inside the test process, for probing topics and waiting for
  discovery (matched publishers/subscribers) instead of sleeping blindly.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import random
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent

# pytest rewrites the asserts of every test module it imports (about 7 s of CPU for the suite's
# 200 modules) and keeps the result in __pycache__ only where the process may write bytecode:
# scripts/env.sh forbids it for every process (PYTHONDONTWRITEBYTECODE, so that no node writes
# beside the sources; `./run setup` compiles the workspace), which made each pytest worker of
# both phases rewrite them all again. The test processes themselves may write it (the node
# processes they start keep the environment's rule).
sys.dont_write_bytecode = False

# The session's domain is drawn once, in pytest's main process, and handed to pytest-xdist's
# workers through the environment; worker gwN takes that domain + N, so that workers running
# node tests side by side never share a graph (two draws of their own would collide 1 time in 100)
_base = os.environ.get("TRAIN_ROS_DOMAIN_ID") or os.environ.get("_TRAIN_TEST_DOMAIN_BASE")
if not _base:
    _base = str(random.SystemRandom().randint(1, 90))
os.environ["_TRAIN_TEST_DOMAIN_BASE"] = _base
_worker = os.environ.get("PYTEST_XDIST_WORKER", "")
_domain = str(int(_base) + (int(_worker[2:]) if _worker[2:].isdigit() else 0))
os.environ["ROS_DOMAIN_ID"] = _domain
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.pop("ROS_STATIC_PEERS", None)
os.environ.setdefault("ROS_LOG_DIR", str(REPO / ".cache" / "ros_log"))
Path(os.environ["ROS_LOG_DIR"]).mkdir(parents=True, exist_ok=True)


def pytest_report_header(config):
    return (f"ROS_DOMAIN_ID={os.environ['ROS_DOMAIN_ID']} "
            f"ROS_AUTOMATIC_DISCOVERY_RANGE={os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE']}")


def _have_ros() -> bool:
    try:
        import ament_index_python  # noqa: F401
        import rclpy  # noqa: F401
    except Exception:
        return False
    return True


@pytest.fixture(scope="session")
def ros_env() -> dict:
    """The environment for node processes: the test session's isolated ROS settings."""
    if not _have_ros():
        pytest.fail("rclpy is not importable: run the tests with ./run test (it sets up ROS 2)")
    env = dict(os.environ)
    env["PYTHONUNBUFFERED"] = "1"
    return env


def executable(pkg: str, exe: str) -> str:
    """Resolve PKG EXE exactly the way `ros2 run` does: get_package_prefix(pkg)/lib/pkg/exe."""
    from train_core.procs import resolve_executable

    path = resolve_executable(pkg, exe)
    if path is None:
        raise FileNotFoundError(f"{pkg}/{exe} is not an installed executable (is ros_ws built?)")
    return path


_SIMULATED: dict[bytes, bytes] = {}


@contextlib.contextmanager
def simulations_shared():
    """Inside it, ``train_sim.world.simulate`` runs once per (scenario, seed, duration) in this
    test process: a later call with the same arguments (the same pickled bytes) gets a fresh
    copy of the first run's result, unpickled, bit for bit what a run gives (simulate is pure
    and deterministic given the seed). For the pilot runs of the drawn cases
    (``train_sim.cases.make_case``, ``train_sim.unlisted_cases.unlisted_case``), which draw
    the same nominal case again for every kind at one seed; outside it simulate is as it is."""
    from train_sim import world

    simulate = world.simulate

    def shared(scenario, seed=None, duration=None):
        key = pickle.dumps((scenario, seed, duration))
        if key not in _SIMULATED:
            _SIMULATED[key] = pickle.dumps(simulate(scenario, seed, duration))
        return pickle.loads(_SIMULATED[key])

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(world, "simulate", shared)
        yield


class Launcher:
    """Starts processes and remembers their PIDs; ``stop_all`` ends exactly those."""

    def __init__(self, env: dict, logdir: Path):
        self.env = env
        self.logdir = logdir
        self.procs: list[tuple[str, subprocess.Popen]] = []

    def start(self, cmd: list[str], name: str | None = None, env: dict | None = None
              ) -> subprocess.Popen:
        name = name or Path(cmd[0]).name
        out = open(self.logdir / f"{name}.{len(self.procs)}.log", "wb")
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT,
                                env={**self.env, **(env or {})}, cwd=str(REPO))
        out.close()
        proc.log_path = Path(out.name)  # type: ignore[attr-defined]
        self.procs.append((name, proc))
        return proc

    def node(self, pkg: str, exe: str, *args: str, name: str | None = None,
             env: dict | None = None) -> subprocess.Popen:
        return self.start([executable(pkg, exe), *args], name=name or exe, env=env)

    @staticmethod
    def stop(proc: subprocess.Popen, timeout: float = 10.0) -> int | None:
        """SIGINT, then SIGTERM, then SIGKILL, each to this PID only."""
        from train_core.procs import stop_process

        return stop_process(proc, timeout)

    def stop_all(self) -> None:
        for _, proc in reversed(self.procs):
            self.stop(proc)

    def logs(self) -> str:
        parts = []
        for name, proc in self.procs:
            text = Path(proc.log_path).read_text(errors="replace")  # type: ignore[attr-defined]
            parts.append(f"----- {name} (pid {proc.pid}, rc {proc.poll()}) -----\n{text[-4000:]}")
        return "\n".join(parts)


@pytest.fixture
def launch(ros_env, tmp_path, request):
    launcher = Launcher(ros_env, tmp_path)
    yield launcher
    launcher.stop_all()
    rep = getattr(request.node, "rep_call", None)
    if rep is not None and rep.failed:
        sys.stderr.write(launcher.logs())


_ROS_FIXTURES = {"launch", "ros_node"}  # node processes, rclpy in the test


def pytest_collection_modifyitems(config, items):
    """Every test that starts processes in the ROS environment is marked ``ros``, whether or not
    its module says so: ``./run test`` runs those three at a time, each worker on its own ROS
    domain, after the CPU-bound rest has run in parallel (their timing is real time: a node test
    keeps about half a core busy)."""
    for item in items:
        if _ROS_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.ros)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    rep = outcome.get_result()
    setattr(item, f"rep_{rep.when}", rep)


class RosProbe:
    """An rclpy node in the test process with helpers that wait on the ROS graph."""

    def __init__(self):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(f"test_probe_{os.getpid()}", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def spin_for(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=min(0.05, max(0.0, end - time.monotonic())))

    def wait_until(self, predicate, timeout: float = 20.0, what: str = "condition") -> None:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if predicate():
                return
            self.executor.spin_once(timeout_sec=0.05)
        raise TimeoutError(f"timed out after {timeout:.0f} s waiting for {what}")

    def call(self, client, request, timeout: float = 20.0, what: str = "a service answer",
             resend: float = 5.0):
        """The service's response to ``request``, the request sent again every ``resend`` s
        until one comes (the requests here are idempotent: a get, or a set of the same value).
        A service may drop its response while the client's response reader is not yet matched
        ("failed to send response (timeout): client will not receive response", on a loaded
        machine), and a request sent once then waits for ever."""
        end = time.monotonic() + timeout
        futures = []
        while time.monotonic() < end:
            futures.append(client.call_async(request))
            until = min(end, time.monotonic() + resend)
            while time.monotonic() < until:
                for future in futures:
                    if future.done():
                        return future.result()
                self.executor.spin_once(timeout_sec=0.05)
        raise TimeoutError(f"timed out after {timeout:.0f} s waiting for {what} "
                           f"({len(futures)} requests sent)")

    def wait_for_publishers(self, topic: str, count: int = 1, timeout: float = 20.0) -> None:
        self.wait_until(lambda: self.node.count_publishers(topic) >= count, timeout,
                        f"{count} publisher(s) on {topic}")

    def wait_for_subscribers(self, topic: str, count: int = 1, timeout: float = 20.0) -> None:
        self.wait_until(lambda: self.node.count_subscribers(topic) >= count, timeout,
                        f"{count} subscriber(s) on {topic}")

    def collect(self, msg_type, topic: str, qos: int = 1000) -> list:
        """Subscribe now; the returned list fills while the probe spins."""
        box: list = []
        self.node.create_subscription(msg_type, topic, box.append, qos)
        return box

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.shutdown(context=self.context)


@pytest.fixture
def ros_node(ros_env):
    probe = RosProbe()
    yield probe
    probe.close()


@pytest.fixture(scope="session")
def repo() -> Path:
    return REPO


@pytest.fixture(scope="session")
def ruff_bin() -> str | None:
    return shutil.which("ruff")
