"""Stopping a child process by its PID, politely first (shared by tools and test fixtures)."""

from __future__ import annotations

import os
import signal
import subprocess


def resolve_executable(pkg: str, exe: str) -> str | None:
    """``ros2 run PKG EXE`` resolution: get_package_prefix(PKG)/lib/PKG/EXE, or None."""
    from ament_index_python.packages import PackageNotFoundError, get_package_prefix

    try:
        path = os.path.join(get_package_prefix(pkg), "lib", pkg, exe)
    except PackageNotFoundError:
        return None
    return path if os.access(path, os.X_OK) else None


def stop_process(proc: subprocess.Popen, timeout: float = 10.0) -> int | None:
    """SIGINT (a node closes its bag, logs its counters), then SIGTERM, then SIGKILL.

    Each signal goes to this PID only: never to a process group or a name.
    Returns the exit code (negative: killed by that signal).
    """
    for sig, wait in ((signal.SIGINT, timeout), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
        if proc.poll() is not None:
            break
        try:
            os.kill(proc.pid, sig)
        except ProcessLookupError:
            break
        try:
            proc.wait(wait)
        except subprocess.TimeoutExpired:
            continue
    return proc.poll()
