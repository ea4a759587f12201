"""Process settings for the nodes' real-time callbacks (imported before numpy; no numpy here).

The nodes multiply small matrices in callbacks that must answer within milliseconds. numpy's
and scipy's OpenBLAS start worker threads at import (one per core) and hand work to them; on a
machine whose other core is busy, the callback then loses a scheduler tick (4 ms here) every so
often. Measured on the robust filter's odometer callback, in-process, with the other core
loaded: p99 5.2-5.4 ms with the default threads, 2.0-2.4 ms with one
(``benchmarks/bench_latency.py``; docs/benchmarks.md, Latency). Limiting the threads later, through
OpenBLAS's own call, did not help: only the start-up setting did. So the node packages call
:func:`single_threaded_blas` in their ``__init__``, before anything imports numpy; a variable the
user set is kept.

Python's cyclic garbage collector runs when a callback happens to cross its allocation
threshold, inside the callback: on the estimators' in-process callbacks (metro_demo 120 s) a
youngest-generation collection took 0.2-0.5 ms in 1-2 % of them (the 99th percentile is there),
a middle one 0.5-1.2 ms, and the first full collection 50-67 ms, most of it the modules and
compiled kernels loaded at start-up. :func:`settle_heap` (once the node is built) freezes what
start-up left, so no later collection walks it, and :func:`collect_due` (after a callback has
published) runs the collection that the allocations have made due, so that the next callback
does not: the same generations, collected after the estimate leaves instead of before.
"""

from __future__ import annotations

import gc
import os
import sys

BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def single_threaded_blas() -> bool:
    """Ask for one BLAS thread unless the user chose; False if numpy was already loaded (then
    the setting comes too late for this process)."""
    for var in BLAS_THREAD_VARIABLES:
        os.environ.setdefault(var, "1")
    return "numpy" not in sys.modules


def settle_heap() -> None:
    """Collect once and move every object left into the permanent generation (``gc.freeze``):
    the start-up's modules, kernels and models, which later collections then skip."""
    gc.collect()
    gc.freeze()


def collect_due(fraction: float = 0.5) -> int | None:
    """Run, now, the collection the allocation counts are heading for: when the youngest
    generation's count is past ``fraction`` of its threshold, collect the oldest generation
    whose count is past its threshold (CPython's own choice; a full collection without its
    extra rule on the long-lived objects, which :func:`settle_heap` made few). Returns the
    generation collected, or None (not due, or the collector disabled)."""
    if not gc.isenabled():
        return None
    t0, t1, t2 = gc.get_threshold()
    c0, c1, c2 = gc.get_count()
    if t0 <= 0 or c0 < fraction * t0:
        return None
    gen = 2 if c1 > t1 and c2 > t2 else 1 if c1 > t1 else 0
    gc.collect(gen)
    return gen
