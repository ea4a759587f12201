"""Every installed executable resolves the way `ros2 run` does and answers --help."""

import os
import subprocess
from pathlib import Path

import pytest
from ament_index_python.packages import get_package_prefix

PACKAGES = ("train_sim", "train_estimation")
CONTRACT = {
    "train_sim": {"simulator", "zone_controller"},
    "train_estimation": {"robust_filter", "gsma_estimator", "recorder", "check_bag", "identify",
                         "diagnose", "fleet", "csv2bag"},
}


def installed(pkg: str) -> list[Path]:
    libdir = Path(get_package_prefix(pkg)) / "lib" / pkg
    return sorted(p for p in libdir.iterdir() if os.access(p, os.X_OK)) if libdir.is_dir() else []


def all_executables():
    return [(pkg, p.name) for pkg in PACKAGES for p in installed(pkg)]


def test_packages_are_indexed():
    for pkg in (*PACKAGES, "train_interfaces"):
        assert Path(get_package_prefix(pkg)).is_dir()


def test_installed_executables_are_contract_names():
    found = all_executables()
    assert found, "no executables installed"
    for pkg, name in found:
        assert name in CONTRACT[pkg], f"{pkg}/{name} is not a docs/interfaces.md executable"


def test_every_contract_executable_is_installed():
    found = set(all_executables())
    for pkg in PACKAGES:
        for name in sorted(CONTRACT[pkg]):
            assert (pkg, name) in found, f"{pkg}/{name} (docs/interfaces.md) is not installed"


@pytest.mark.parametrize("pkg,exe", all_executables())
def test_executable_answers_help(pkg, exe, ros_env):
    path = Path(get_package_prefix(pkg)) / "lib" / pkg / exe
    out = subprocess.run([str(path), "--help"], capture_output=True, text=True, timeout=60,
                         env=ros_env)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "usage" in out.stdout.lower(), out.stdout[:500]
