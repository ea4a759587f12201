"""Node processes keep BLAS in the calling thread (train_core.realtime): a fresh process that
imports a node module has one BLAS thread, a user's choice is kept, and a plain numpy process
is left alone (the offline tools keep their threads)."""

import os
import subprocess
import sys

import pytest
from train_core.realtime import BLAS_THREAD_VARIABLES

PROBE = ("import os, sys; {imports}; import numpy, scipy.linalg; "
         "print(os.environ.get('OPENBLAS_NUM_THREADS'), len(os.listdir('/proc/self/task')))")


def run_probe(imports: str, **extra) -> tuple[str, int]:
    env = {k: v for k, v in os.environ.items() if k not in BLAS_THREAD_VARIABLES}
    # the node modules import rclpy but the probe never calls rclpy.init (no DDS participant);
    # were one made, it stays on loopback in the session's domain (conftest.py)
    env.update(ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=os.environ["ROS_DOMAIN_ID"])
    env.update(extra)
    out = subprocess.run([sys.executable, "-c", PROBE.format(imports=imports)], env=env,
                         capture_output=True, text=True, check=True, timeout=60).stdout.split()
    return out[0], int(out[1])


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="thread count from /proc")
@pytest.mark.parametrize("module", ["train_estimation.nodes.robust_filter",
                                    "train_sim.nodes.simulator"])
def test_node_process_has_one_blas_thread(module):
    var, threads = run_probe(f"import {module}")
    assert var == "1"
    assert threads == 1  # the interpreter's own thread only: no OpenBLAS workers


def test_user_choice_kept_and_offline_untouched():
    var, _ = run_probe("import train_estimation.nodes.robust_filter", OPENBLAS_NUM_THREADS="2")
    assert var == "2"
    var, _ = run_probe("import train_estimation.core.robust.robust_filter")
    assert var == "None"


class _Node:
    def __init__(self):
        self.me = self  # a reference cycle: only the cyclic collector frees it


def _cycle():
    import weakref
    return weakref.ref(_Node())


def test_collect_due_runs_the_due_collection_and_only_then():
    import gc

    from train_core.realtime import collect_due
    saved = gc.get_threshold()
    try:
        gc.set_threshold(10_000, 3, 1_000_000)
        gc.collect()
        ref = _cycle()
        assert collect_due() is None and ref() is not None  # not due: left to later
        keep = [[] for _ in range(6_000)]  # the youngest count past half its threshold
        assert collect_due() == 0 and ref() is None
        gens = []
        for _ in range(4):
            keep += [[] for _ in range(6_000)]
            gens.append(collect_due())
        assert gens == [0, 0, 0, 1]  # the middle generation once its count passes 3
        gc.disable()
        keep += [[] for _ in range(6_000)]
        assert collect_due() is None  # a disabled collector stays off
    finally:
        gc.enable()
        gc.set_threshold(*saved)
