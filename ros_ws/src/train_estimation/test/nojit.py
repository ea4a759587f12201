"""Test helper: a test module's function run in a fresh process without numba, so that
compiled kernels can be compared with their interpreted form bit for bit."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np


def interpreted(test_module: str, name: str, core_module: str, timeout: float = 600.0
                ) -> np.ndarray:
    """``test_module.name()`` (no arguments, an array back) run in a fresh process with
    ``TRAIN_NO_JIT=1`` (the kernels' decorator a no-op), ``core_module`` (dotted) checked to
    run interpreted there (its ``COMPILED`` False)."""
    here = str(Path(__file__).parent)
    code = textwrap.dedent(f"""
        import importlib
        import sys
        import numpy as np
        sys.path.insert(0, {here!r})
        from {test_module} import {name}
        assert not importlib.import_module({core_module!r}).COMPILED
        np.save(sys.argv[1], {name}())
        """)
    out = Path(os.environ.get("TMPDIR", "/tmp")) / f"nojit_{name}_{os.getpid()}.npy"
    run = subprocess.run([sys.executable, "-c", code, str(out)], capture_output=True,
                         text=True, env={**os.environ, "TRAIN_NO_JIT": "1"}, timeout=timeout)
    assert run.returncode == 0, run.stderr
    values = np.load(out)
    out.unlink()
    return values
