"""Compiled scalar loops (numba when installed): :mod:`train_core.jit`, the one decorator shared
with the model's own loops."""

from train_core.jit import COMPILED, jit

__all__ = ["COMPILED", "jit"]
