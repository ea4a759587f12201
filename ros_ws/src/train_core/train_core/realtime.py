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
"""

from __future__ import annotations

import os
import sys

BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def single_threaded_blas() -> bool:
    """Ask for one BLAS thread unless the user chose; False if numpy was already loaded (then
    the setting comes too late for this process)."""
    for var in BLAS_THREAD_VARIABLES:
        os.environ.setdefault(var, "1")
    return "numpy" not in sys.modules
