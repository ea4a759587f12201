"""train_core.aot: kernels compiled ahead of time are loaded for their source only, give what
numba's jit gives, and spare a process numba's import."""

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from train_core import aot, lag

KERNEL = textwrap.dedent("""
    import numpy as np


    def decay(x, a):
        y = np.empty_like(x)
        acc = 0.0
        for k in range(x.shape[0]):
            acc = a * acc + x[k] / 3.0
            y[k] = acc
        return y
    """)


def _module(tmp_path, text):
    src = tmp_path / "kern.py"
    src.write_text(text)
    sys.path.insert(0, str(tmp_path))
    try:
        sys.modules.pop("kern", None)
        import kern
    finally:
        sys.path.remove(str(tmp_path))
    return src, kern


@pytest.mark.slow
def test_built_for_its_source_only(tmp_path, monkeypatch):
    pytest.importorskip("numba")
    monkeypatch.delenv("TRAIN_NO_JIT", raising=False)
    monkeypatch.delenv("TRAIN_NO_AOT", raising=False)
    src, kern = _module(tmp_path, KERNEL)
    assert aot.load("kern", [src]) is None  # never built
    path = aot.build("kern", [src], {"decay": (kern.decay, "f8[::1](f8[::1], f8)")})
    assert path.parent == tmp_path / "__pycache__" and path.is_file()
    mod = aot.load("kern", [src])
    assert mod is not None and "numba" not in repr(type(mod.decay))
    x = np.random.default_rng(1).normal(size=1000)
    from numba import njit
    assert np.array_equal(mod.decay(x, 0.9), njit(kern.decay)(x, 0.9))  # numba's jit's bits
    assert np.array_equal(mod.decay(x, 0.9), kern.decay(x, 0.9))  # and the Python's
    # turned off: numba's jit or the interpreter instead
    for var in ("TRAIN_NO_AOT", "TRAIN_NO_JIT"):
        monkeypatch.setenv(var, "1")
        assert aot.load("kern", [src]) is None
        monkeypatch.delenv(var)
    # an edited source has another digest: the old build is never loaded
    src.write_text(KERNEL.replace("/ 3.0", "/ 4.0"))
    assert aot.load("kern", [src]) is None
    new = aot.build("kern", [src], {"decay": (kern.decay, "f8[::1](f8[::1], f8)")})
    assert new.name != path.name and not path.exists()  # the old build removed


def test_the_lag_runs_compiled_ahead_of_time_without_numba():
    """./run setup builds lag's loop ahead of time: a process that uses it imports no numba,
    and it is scipy's lfilter bit for bit like the jit (test_lag)."""
    if os.environ.get("TRAIN_NO_JIT") or os.environ.get("TRAIN_NO_AOT"):
        pytest.skip("compiled loops turned off in this environment")
    assert aot.load("lag", [lag.__file__]) is not None, "not compiled ahead of time: ./run setup"
    code = textwrap.dedent("""
        import sys
        import numpy as np
        from train_core import lag
        y = lag.first_order(np.arange(5.0), 0.5, 0.5)
        print("numba" in sys.modules, type(lag._COMPILED).__name__, y.tolist())
        """)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split()[:2] == ["False", "builtin_function_or_method"]
