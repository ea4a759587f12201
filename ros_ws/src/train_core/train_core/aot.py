"""Kernels compiled ahead of time, for short-lived processes (numba's ``pycc``, when installed).

A process that calls a numba-compiled loop pays numba's import (about 0.3 s) and, at the first
call, the set-up of numba's type system (another 0.3 s), even when the machine code itself comes
from numba's on-disk cache: a third of what ``diagnose`` takes on a 10-minute bag. The loops such
a process calls (:mod:`train_core.lag`, ``numerics.augmented_kf``) are therefore also compiled,
once per change of their source, into one small extension module per source module: it loads in
a millisecond and needs neither numba nor its cache at run time. The module is compiled by
numba from the same Python functions with the same IEEE arithmetic (no fast-math), so it gives
what the just-in-time kernels give, bit for bit (tested).

The extension lives in the source module's ``__pycache__`` as ``aot_<name>_<digest>``, the digest
being of the Python version, numpy's version and the bytes of the source files the kernels come
from: an edited source has another digest, so a stale module is never loaded and the caller
falls back to numba's just-in-time kernels until :func:`build` runs again (``./run setup``
does, through each module's ``build_aot``). ``TRAIN_NO_JIT=1`` (interpreted loops) and
``TRAIN_NO_AOT=1`` (numba's just-in-time kernels) make :func:`load` return None.

Pure: the standard library only (numba's ``pycc`` imported inside :func:`build`).
"""

from __future__ import annotations

import hashlib
import importlib.machinery
import importlib.util
import os
import shutil
import sys
import tempfile
from pathlib import Path


def _digest(sources) -> str:
    h = hashlib.blake2b(digest_size=8)
    h.update(sys.version.encode())
    np = sys.modules.get("numpy")
    if np is None:  # the kernels take numpy arrays: every caller has imported it
        import numpy as np
    h.update(np.__version__.encode())
    for s in sources:
        h.update(b"|")
        h.update(Path(s).read_bytes())
    return h.hexdigest()


def module_name(name: str, sources) -> str:
    """The extension module's name for ``sources`` as they are now."""
    return f"aot_{name}_{_digest(sources)}"


def _dir(sources) -> Path:
    return Path(sources[0]).resolve().parent / "__pycache__"


def _suffix() -> str:
    return importlib.machinery.EXTENSION_SUFFIXES[0]


def load(name: str, sources):
    """The compiled module of kernels ``name`` built from ``sources`` (paths of Python files,
    the first one's directory holding it), or None: not built for these sources, turned off
    (``TRAIN_NO_JIT``, ``TRAIN_NO_AOT``), or not loadable."""
    if os.environ.get("TRAIN_NO_JIT") or os.environ.get("TRAIN_NO_AOT"):
        return None
    try:
        mod = module_name(name, sources)
        path = _dir(sources) / (mod + _suffix())
        if not path.is_file():
            return None
        spec = importlib.util.spec_from_file_location(mod, path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module
    except (OSError, ImportError):  # unreadable, or built against another ABI: numba's jit
        return None


def build(name: str, sources, exports: dict) -> Path:
    """Compile ``exports`` ({exported name: (Python function, numba signature)}) into the
    extension :func:`load` finds for ``sources`` (nothing to do when it is there); older
    builds of ``name`` are removed. The functions' globals must be what numba compiles (its
    just-in-time dispatchers for the kernels they call). Takes 10-30 s."""
    import warnings

    out = _dir(sources)
    mod = module_name(name, sources)
    path = out / (mod + _suffix())
    if path.is_file():
        return path
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pycc's pending deprecation: numba's jit is the fallback
        from numba.pycc import CC
    out.mkdir(exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out) as tmp:
        cc = CC(mod)
        cc.output_dir = tmp
        cc.verbose = False
        for export, (fn, sig) in exports.items():
            cc.export(export, sig)(fn)
        cc.compile()
        built = next(Path(tmp).glob(mod + "*"))
        os.replace(built, path)  # atomic: a concurrent load sees the whole file or none
    for old in out.glob(f"aot_{name}_*"):
        if old != path:
            if old.is_dir():
                shutil.rmtree(old, ignore_errors=True)
            else:
                old.unlink(missing_ok=True)
    return path
