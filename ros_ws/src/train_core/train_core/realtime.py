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

:class:`CallbackTrace` (off unless ``TRAIN_NODE_TRACE`` names a directory) records where a live
node's time goes: its callbacks and its executor's waits on the steady and the thread CPU clocks
(``benchmarks/bench_latency.py --trace``).
"""

from __future__ import annotations

import gc
import inspect
import os
import sys
import time

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


TRACE_VARIABLE = "TRAIN_NODE_TRACE"  # a directory: an estimator node traces its callbacks there


class CallbackTrace:
    """Where a live node's time goes (``bench_latency --trace``): every callback's start and end
    and marks inside it, each on the steady clock and on the thread's CPU clock (ns), written
    as JSON at shutdown. The CPU clock tells work from waiting: a stage whose wall time
    exceeds its CPU time waited for a core; the CPU time between two callbacks is the
    executor's own (building its wait set, taking the message). Off unless
    ``TRAIN_NODE_TRACE`` names a directory (:meth:`from_env`): a few microseconds per mark."""

    def __init__(self, directory: str):
        self.directory = directory
        self.marks: list = []  # (label, steady ns, thread CPU ns, value)

    @classmethod
    def from_env(cls) -> CallbackTrace | None:
        directory = os.environ.get(TRACE_VARIABLE)
        return cls(directory) if directory else None

    def mark(self, label: str, value=None) -> None:
        self.marks.append((label, time.monotonic_ns(), time.thread_time_ns(), value))

    def _wrapped(self, name: str, fn):
        def traced(*args):
            self.mark("B:" + name)
            try:
                return fn(*args)
            finally:
                self.mark("E:" + name)
        # rclpy reads a subscription callback's arity from its signature
        traced.__signature__ = inspect.signature(fn)
        return traced

    def _wrapped_sub(self, name: str, fn):
        """A subscription's callback taking rclpy's MessageInfo too, whose stamps the start
        mark keeps: (published, received, now), ns on the system clock (the DDS layer's own
        stamps: received -> now is the time the message waited in the node's queue, behind
        the executor and the callbacks before it). ``fn`` gets what it asked for."""
        with_info = _takes_two(fn)

        def traced(msg, info):
            self.mark("B:" + name, (info.get("source_timestamp"),
                                    info.get("received_timestamp"), time.time_ns()))
            try:
                return fn(msg, info) if with_info else fn(msg)
            finally:
                self.mark("E:" + name)
        return traced

    def wrap(self, node) -> None:
        """Every subscription, timer and service callback of ``node`` (rclpy's /clock one
        included) marked at its start ``B:`` and end ``E:`` with the topic, period or service
        (a subscription's start with its message's DDS stamps, :meth:`_wrapped_sub`);
        and the executor's waits (``wait``, ``woken``): rclpy's executor builds a wait set in
        Python for each wait (this process-wide patch of its module marks them)."""
        import rclpy.executors as executors

        if not isinstance(executors._rclpy, _TracedImpl):
            executors._rclpy = _TracedImpl(executors._rclpy, self)
        for sub in node.subscriptions:
            sub.callback = self._wrapped_sub("sub " + sub.topic_name, sub.callback)
        for tmr in node.timers:
            tmr.callback = self._wrapped(f"timer {tmr.timer_period_ns * 1e-9:g} s", tmr.callback)
        for srv in node.services:
            srv.callback = self._wrapped("service " + srv.srv_name, srv.callback)

    def dump(self, name: str) -> str:
        import json

        path = os.path.join(self.directory, f"trace_{name}_{os.getpid()}.json")
        with open(path, "w") as f:
            json.dump(self.marks, f)
        return path


def _takes_two(fn) -> bool:
    """Whether rclpy would hand ``fn`` the MessageInfo too (its own test of the signature)."""
    try:
        inspect.signature(fn).bind(object(), object())
    except TypeError:
        return False
    return True


class _TracedImpl:
    """rclpy's C extension as the executor sees it, with its wait sets' waits marked."""

    def __init__(self, impl, trace: CallbackTrace):
        self._impl, self._trace = impl, trace

    def __getattr__(self, name):
        return getattr(self._impl, name)

    def WaitSet(self, *args):  # noqa: N802 (rclpy's name)
        return _TracedWaitSet(self._impl.WaitSet(*args), self._trace)


class _TracedWaitSet:
    def __init__(self, ws, trace: CallbackTrace):
        self._ws, self._trace = ws, trace

    def __getattr__(self, name):
        return getattr(self._ws, name)

    def wait(self, timeout):
        self._trace.mark("wait")
        try:
            return self._ws.wait(timeout)
        finally:
            self._trace.mark("woken")
