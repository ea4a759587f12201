"""The code base passes `ruff check` (configuration in ruff.toml)."""

import shutil
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_ruff_check_passes():
    ruff = shutil.which("ruff")
    assert ruff, "ruff is not installed (it is pinned in requirements.txt: use ./run test)"
    out = subprocess.run([ruff, "check", "."], cwd=REPO, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr[-2000:]
