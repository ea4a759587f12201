"""Offline data generation: a scenario straight into a rosbag2/MCAP bag, no ROS running.

    python -m train_sim.generate --scenario metro_demo --seed 3 --out bags/x

    python -m train_sim.generate --scenario metro_demo --model out/diag/model --out bags/y

Uses the same :class:`train_sim.world.World` as the ``simulator`` node, so the same scenario and
seed give the same messages. The bag holds what the train sends after the radio link
(``odometer``, ``balise``), ``control`` and ``ground_truth``; ``--measured`` leaves ground truth
out (a "measured data" bag, docs/interfaces.md). Each message's log time is its arrival time on the
reference clock (the link's latency included), as a recorder on the ground would log it.

``--model DIR`` runs a model written by ``diagnose`` (``DIR/line.yaml``, ``DIR/train.yaml``,
``DIR/effects.yaml``): the scenario's driver, link and seed with that line, train and those
effects, on that line's own stations, start and timetable (:func:`train_sim.scenario.with_model`).
"""

from __future__ import annotations

import argparse
import sys
import time

from train_core.bagio import BagError, BagWriter
from train_core.config import ConfigError


def generate(scenario, out, seed=None, duration=None, namespace="/train", measured=False):
    """Simulate ``scenario`` (a Scenario) and write the bag; returns the SimResult."""
    from train_sim.world import simulate

    res = simulate(scenario, seed=seed, duration=duration)
    with BagWriter(out, namespace=namespace) as writer:
        for t_recv, topic, stamp, fields in res.received_events():
            if measured and topic == "ground_truth":
                continue
            writer.write(topic, stamp, fields, t_ns=int(round(t_recv * 1e9)))
    return res


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="generate", description=__doc__.splitlines()[0])
    p.add_argument("--scenario", required=True, help="scenario name (see scenarios/) or YAML path")
    p.add_argument("--seed", type=int, default=None, help="random seed (default: the scenario's)")
    p.add_argument("--duration", type=float, default=None, help="s of simulated time")
    p.add_argument("--out", required=True, help="bag directory to create (must not exist)")
    p.add_argument("--namespace", default="/train", help="topic namespace (default /train)")
    p.add_argument("--measured", action="store_true", help="leave ground_truth out")
    p.add_argument("--model", default=None, metavar="DIR",
                   help="run the model in DIR (line.yaml, train.yaml, effects.yaml, as written "
                        "by diagnose into OUT/model) instead of the scenario's line/train/effects")
    args = p.parse_args(argv)
    from train_sim.scenario import load_scenario, with_model

    try:
        sc = load_scenario(args.scenario)
        if args.model:
            sc = with_model(sc, args.model)
        t0 = time.perf_counter()
        res = generate(sc, args.out, args.seed, args.duration, args.namespace, args.measured)
    except (ConfigError, BagError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    n = {k: int(len(v["t"])) for k, v in (("odometer", res.odometer), ("balise", res.balise))}
    print(f"wrote {args.out}: scenario {sc.name}, {n} samples before the link, "
          f"{time.perf_counter() - t0:.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
