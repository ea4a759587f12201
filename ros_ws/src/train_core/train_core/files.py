"""Where the project's data files are: the package's source tree or its installed share dir.

One lookup for every package (``train_core`` keeps the line and train files that both the
simulator and the estimators read; ``train_sim`` keeps its scenarios). Pure: no ROS import unless
the source tree is absent (then the ament index of an installed workspace is asked).
"""

from __future__ import annotations

import os
from pathlib import Path

_SRC = Path(__file__).resolve().parents[2]  # ros_ws/src when run from the source tree


def share_dir(pkg: str, marker: str) -> Path:
    """Directory of package ``pkg`` that holds ``marker`` (a sub-folder): the source tree if it
    has it, else ``<prefix>/share/<pkg>`` found through the ament index.

    ``TRAIN_<PKG>_SHARE`` (e.g. ``TRAIN_SIM_SHARE`` for ``train_sim``) overrides both.
    """
    env = os.environ.get(f"TRAIN_{pkg.upper().removeprefix('TRAIN_')}_SHARE")
    if env:
        return Path(env)
    src = _SRC / pkg
    if (src / marker).is_dir():
        return src
    try:  # installed with colcon: <prefix>/share/<pkg>
        from ament_index_python.packages import get_package_share_directory

        return Path(get_package_share_directory(pkg))
    except Exception:  # pragma: no cover - no ROS environment and no source tree
        return src


def config_file(kind: str, name: str) -> Path:
    """``config/<kind>/<name>.yaml`` of train_core: kind ``lines`` or ``trains``."""
    return share_dir("train_core", "config") / "config" / kind / f"{name}.yaml"
