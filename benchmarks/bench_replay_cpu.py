"""Thread CPU per estimate of the estimators' offline replay, on one clock and on a drifting one.

The node's work per estimate without ROS: a simulated run's messages pushed through the same
runner and adapters as the nodes (``core.online.replay``), timed on the thread's CPU clock
(``time.thread_time``: what a core spends, not what the machine's load adds to the wall).
Each estimator's run is replayed once to warm it (numba's cache, the model's maps) and then
``--repeats`` times; the least is kept. Two clocks:

* ``one``: the simulator's stamps as they are (every stream on one clock);
* ``drift``: the odometer and the balise reader on a train clock at epoch 1,000 s, phase 3 ms
  and drift 1e-5, the commands on another clock at epoch 50 s (measured data's clocks: nearly
  every step's dt is new there).

Quick mode (``--quick``): 300 s of metro_demo, one repeat, GSMA and the KF (about a minute).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

# the tests' helpers (``test/clocks.py``): a simulated run restamped as measured data's clocks,
# and the estimators' adapters with the nodes' defaults -- the same as the clock tests replay
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "ros_ws/src/train_estimation/test"))
from clocks import adapter, restamp  # noqa: E402

from train_estimation.core.online.replay import replay  # noqa: E402
from train_sim.scenario import load_scenario  # noqa: E402
from train_sim.world import simulate  # noqa: E402

KINDS = ("robust", "kf", "gsma", "sma", "rbpf", "qgrbpf")


def cpu_per_estimate(sc, kind: str, events: list, repeats: int) -> float:
    """us of thread CPU per estimate, the least of ``repeats`` replays after a warm one."""
    replay(events, adapter(sc, kind), 1.0 / sc.odometer_rate)
    best = float("inf")
    for _ in range(repeats):
        t0 = time.thread_time()
        outs, _ = replay(events, adapter(sc, kind), 1.0 / sc.odometer_rate)
        best = min(best, (time.thread_time() - t0) / max(len(outs), 1))
    return 1e6 * best


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="300 s, one repeat, gsma and kf")
    ap.add_argument("--scenario", default="metro_demo")
    ap.add_argument("--duration", type=float, default=600.0, help="s of simulated run")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=3, help="timed replays per estimator")
    ap.add_argument("--estimators", nargs="+", choices=KINDS, default=list(KINDS))
    a = ap.parse_args(argv)
    if a.quick:
        a.duration, a.repeats, a.estimators = 300.0, 1, ["gsma", "kf"]
    sc = load_scenario(a.scenario)
    raw = simulate(sc, a.seed, a.duration).events()
    clocks = {"one": restamp(raw),
              "drift": restamp(raw, epoch=1000.0, phase=0.003, drift=1e-5, control_epoch=50.0)}
    print(f"thread CPU per estimate (us), {a.scenario} {a.duration:g} s seed {a.seed}, "
          f"least of {a.repeats}")
    print("| estimator | one clock | drifting clock | ratio |")
    print("|---|---|---|---|")
    ratios = []
    for kind in a.estimators:
        one = cpu_per_estimate(sc, kind, clocks["one"], a.repeats)
        drift = cpu_per_estimate(sc, kind, clocks["drift"], a.repeats)
        ratios.append(drift / one)
        print(f"| {kind} | {one:.0f} | {drift:.0f} | {drift / one:.2f} |", flush=True)
    print(f"median ratio drifting / one clock: {statistics.median(ratios):.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
