"""``train_core.replay_loop`` (``motion.replay``'s loop compiled) against the interpreted replay,
bit for bit: commands through traction, cruise, braking to stops, dwells and starts on a line's
gradients, started at rest and moving, early and late in the run, with the two chains' delays,
a power limit, a low-adhesion section and another believed train; and the cases it leaves to
the interpreted loop."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from train_core import aot, motion, replay_loop
from train_core.model import load_line, load_train

CONFIG = Path(__file__).resolve().parents[1] / "config"


def _commands(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """10 Hz commands over 400 s: traction, coasting, braking to a stop and dwells, with
    jittered stamps (off the 0.1 s lattice) and noise on the levels."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 400.0, 0.1) + rng.uniform(-0.02, 0.02, 4000)
    t.sort()
    phase = (t // 50.0).astype(int) % 4
    level = np.choose(phase, [1.0, 0.0, -0.9, -1.2]) + rng.normal(0.0, 0.05, t.size)
    level[(phase == 3) & (t % 50.0 > 30.0)] = -1.2  # held at rest
    return t, level


def _cases():
    train = load_train(CONFIG / "trains" / "metro_b6.yaml")
    line = load_line(CONFIG / "lines" / "metro_demo.yaml")
    heavy = dataclasses.replace(train, mass=train.mass * 1.2)
    for seed in (1, 2):
        t_cmd, a_cmd = _commands(seed)
        for t0, v0 in ((0.0, 0.0), (12.3, 6.0), (95.0, 0.0), (151.7, 14.0), (333.3, 3.0)):
            t_out = t0 + np.sort(np.random.default_rng(seed).uniform(0.0, 30.0, 60))
            base = dict(line=line, train=train, t_cmd=t_cmd, a_cmd=a_cmd, t0=t0, t_out=t_out,
                        x0=100.0 + 40.0 * t0, v0=v0, max_step=0.05)
            yield base
            yield dict(base, max_step=0.01)
            yield dict(base, brake_delay=1.4, traction_delay=0.9)
            yield dict(base, p_spec=4.0)
            yield dict(base, adhesion=(base["x0"] + 20.0, base["x0"] + 300.0, 0.5))
            yield dict(base, train=heavy, believed=train, p_spec=6.0, brake_delay=0.2,
                       adhesion=(0.0, 1e6, 0.7))


@pytest.mark.skipif(replay_loop.kernel() is None, reason="numba is not installed")
def test_compiled_replay_is_the_interpreted_one_bit_for_bit():
    n = stops = 0
    for case in _cases():
        kw = {k: case.get(k) for k in ("believed", "brake_delay", "traction_delay", "p_spec",
                                       "adhesion")}
        args = [case[k] for k in ("line", "train", "t_cmd", "t_cmd", "t0", "t_out", "x0", "v0")]
        args[3] = case["a_cmd"]
        ref = motion._replay_python(*args, kw["believed"], kw["brake_delay"], None,
                                    case["max_step"], kw["traction_delay"], kw["p_spec"],
                                    kw["adhesion"])
        got = motion._replay_compiled(*args, kw["believed"], kw["brake_delay"],
                                      case["max_step"], kw["traction_delay"], kw["p_spec"],
                                      kw["adhesion"])
        assert got is not None
        assert ref[0].tobytes() == got[0].tobytes() and ref[1].tobytes() == got[1].tobytes()
        stops += int(np.any(ref[1] == 0.0) and np.any(ref[1] > 0.0))
        n += 1
    assert n == 60 and stops >= 10  # replays that stop or start within their 30 s


def test_left_to_the_interpreted_loop():
    """A braking rate that varies in time runs interpreted (the same function either way);
    commands out of time order within the actuator's warm-up raise as before."""
    case = next(_cases())

    def f_of_t(t):
        return 0.9 - 1e-3 * t

    r = motion.replay(case["line"], case["train"], case["t_cmd"], case["a_cmd"], 20.0,
                      20.0 + np.arange(1.0, 30.0), 300.0, 5.0, braking_rate_of_t=f_of_t)
    ref = motion._replay_python(case["line"], case["train"], case["t_cmd"], case["a_cmd"], 20.0,
                                20.0 + np.arange(1.0, 30.0), 300.0, 5.0, None, None, f_of_t,
                                0.01, None, None, None)
    assert r[1].tobytes() == ref[1].tobytes()
    t_cmd = case["t_cmd"].copy()
    t_cmd[300], t_cmd[301] = t_cmd[301] + 0.5, t_cmd[300]
    with pytest.raises(ValueError, match="time order"):
        motion.replay(case["line"], case["train"], t_cmd, case["a_cmd"], 45.0,
                      45.0 + np.arange(1.0, 30.0), 300.0, 5.0)


def test_the_replay_runs_compiled_ahead_of_time_without_numba():
    """./run setup builds the loop ahead of time: a replay imports no numba."""
    if os.environ.get("TRAIN_NO_JIT") or os.environ.get("TRAIN_NO_AOT"):
        pytest.skip("compiled loops turned off in this environment")
    assert aot.load("replay_loop", [replay_loop.__file__]) is not None, \
        "not compiled ahead of time: ./run setup"
    code = textwrap.dedent("""
        import sys
        from train_core import replay_loop
        k = replay_loop.kernel()
        print("numba" in sys.modules, k is not None)
        """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60, check=True).stdout.split()
    assert out == ["False", "True"]
