"""Core modules are pure: importing them must not pull in rclpy or any message package.

Everything under ``train_core``, ``train_sim`` and ``train_estimation`` except the ``nodes``
sub-packages and ``train_core.ros`` (the nodes' message helpers) is core (the offline tools
included: they read bags with rosbags, not with ROS).

The packages depend in one direction only (docs/nodes.md's package tree): train_core <- train_sim,
train_estimation <- train_bringup. Checked on the import statements of the package code.
"""

import json
import pkgutil
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SRC = [REPO / "ros_ws" / "src" / p for p in ("train_core", "train_sim", "train_estimation")]
ROS_LAYER = ("train_core.ros",)


def core_modules() -> list[str]:
    mods = []
    for root in SRC:
        pkg = root.name
        for info in pkgutil.walk_packages([str(root / pkg)], prefix=f"{pkg}."):
            if (".nodes" in info.name or info.name.endswith("__main__")
                    or info.name in ROS_LAYER):
                continue
            mods.append(info.name)
    return sorted(mods)


def test_there_are_core_modules():
    mods = core_modules()
    assert "train_core.model" in mods and "train_core.config" in mods
    assert "train_sim.world" in mods and "train_estimation.core.offline.identify" in mods
    # the diagnose package and every cause module are core too
    assert {"train_estimation.core.offline.diagnose.search",
            "train_estimation.core.offline.diagnose.causes.base",
            "train_estimation.core.offline.measured"} <= set(mods)


def test_core_does_not_import_the_tools():
    """The offline CLIs sit on the core, never the other way round."""
    pat = re.compile(r"^\s*(?:from|import)\s+(train_estimation\.tools|\.+tools)\b", re.M)
    core = REPO / "ros_ws" / "src" / "train_estimation" / "train_estimation" / "core"
    bad = [str(f.relative_to(core)) for f in sorted(core.rglob("*.py"))
           if pat.search(f.read_text())]
    assert bad == []


def test_core_modules_do_not_import_ros():
    code = r"""
import importlib, json, sys
bad = {}
for name in json.loads(sys.argv[1]):
    importlib.import_module(name)
    leaked = sorted(m for m in sys.modules
                    if m.split('.')[0] == 'rclpy' or m.split('.')[0].endswith('_msgs')
                    or m.split('.')[0] == 'train_interfaces')
    if leaked:
        bad[name] = leaked[:5]
        break
print(json.dumps(bad))
"""
    env_path = ":".join(str(p) for p in SRC)
    out = subprocess.run(
        [sys.executable, "-c", code, json.dumps(core_modules())],
        capture_output=True, text=True, timeout=120,
        env={"PYTHONPATH": env_path, "PATH": "/usr/bin:/bin", "MPLBACKEND": "Agg"},
    )
    assert out.returncode == 0, out.stderr[-3000:]
    bad = json.loads(out.stdout.strip().splitlines()[-1])
    assert bad == {}, f"core module imports ROS: {bad}"


# package -> the project packages it may import (train_interfaces only through train_core.ros)
ALLOWED = {
    "train_core": {"train_core", "train_interfaces"},
    "train_sim": {"train_core", "train_sim", "train_interfaces"},
    "train_estimation": {"train_core", "train_estimation", "train_interfaces"},
    "train_bringup": {"train_core", "train_sim", "train_estimation", "train_bringup"},
}


def test_dependency_direction():
    """shared -> sim / estimation -> bringup, no arrow back and none between sim and estimation."""
    pat = re.compile(r"^\s*(?:from|import)\s+(train_[a-z_]+)", re.M)
    bad = []
    for pkg, allowed in ALLOWED.items():
        for f in sorted((REPO / "ros_ws" / "src" / pkg / pkg).rglob("*.py")):
            for used in set(pat.findall(f.read_text())):
                if used not in allowed:
                    bad.append(f"{f.relative_to(REPO)} imports {used}")
    assert bad == []


# the core's families (docs/nodes.md): the maths at the bottom, the filters of each paper on it,
# the online wing (runner, adapters, integrity) on those, the offline wing (identify, diagnose,
# fleet) beside the online one; ``core/reasons.py`` is the one vocabulary every family uses
FAMILY_DEPS = {
    "numerics": {"numerics"},
    "robust": {"numerics", "robust"},
    "braking": {"numerics", "braking"},
    "online": {"numerics", "robust", "braking", "online"},
    "offline": {"numerics", "offline"},
}


def _core_imports(path: Path, core: Path) -> set[str]:
    """Families of the core that a module imports (relative imports resolved)."""
    rel_pkg = path.relative_to(core).parent.parts  # e.g. ("offline", "diagnose")
    found = set()
    for dots, name in re.findall(r"^\s*from\s+(\.+)([\w.]*)\s+import", path.read_text(), re.M):
        up = len(dots) - 1
        parts = list(rel_pkg[:len(rel_pkg) - up] if up else rel_pkg) + name.split(".")
        parts = [p for p in parts if p]
        if parts:
            found.add(parts[0])
    for name in re.findall(r"^\s*(?:from|import)\s+train_estimation\.core\.(\w+)",
                           path.read_text(), re.M):
        found.add(name)
    return found


def test_core_families_depend_downwards():
    """numerics <- robust, braking <- online; offline on numerics only: no family reaches up
    or sideways (a filter never imports the runner, the offline wing never the online one)."""
    core = REPO / "ros_ws" / "src" / "train_estimation" / "train_estimation" / "core"
    assert sorted(p.name for p in core.iterdir() if p.is_dir() and p.name in FAMILY_DEPS) \
        == sorted(FAMILY_DEPS)
    flat = sorted(p.name for p in core.glob("*.py") if p.name not in ("__init__.py",))
    assert flat == ["reasons.py"], f"core modules outside a family folder: {flat}"
    bad = []
    for fam, allowed in FAMILY_DEPS.items():
        for f in sorted((core / fam).rglob("*.py")):
            for used in _core_imports(f, core) - allowed - {"reasons"}:
                bad.append(f"{f.relative_to(core)} imports core.{used}")
    assert bad == []
