"""Core modules are pure: importing them must not pull in rclpy or any message package.

Everything under ``train_sim`` and ``train_estimation`` except the ``nodes`` sub-packages is core
(the offline tools included: they read bags with rosbags, not with ROS).
"""

import json
import pkgutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SRC = [REPO / "ros_ws" / "src" / "train_sim", REPO / "ros_ws" / "src" / "train_estimation"]


def core_modules() -> list[str]:
    mods = []
    for root in SRC:
        pkg = root.name
        for info in pkgutil.walk_packages([str(root / pkg)], prefix=f"{pkg}."):
            if ".nodes" in info.name or info.name.endswith("__main__"):
                continue
            mods.append(info.name)
    return sorted(mods)


def test_there_are_core_modules():
    mods = core_modules()
    assert "train_sim.model" in mods and "train_sim.config" in mods


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
