"""Test helpers: simulated runs re-stamped as measured data (train clock at any epoch, phase and
drift; control on the reference clock) and the error of a runner's estimates against truth."""

from __future__ import annotations

import functools

import numpy as np

from train_estimation.core.online.estimators import (
    BrakingAdapter,
    BrakingConfig,
    RobustAdapter,
    RobustConfig,
    StartState,
)
from train_estimation.core.online.replay import replay
from train_sim.scenario import load_scenario
from train_sim.world import simulate


@functools.lru_cache(maxsize=8)
def run(scenario: str = "metro_demo", seed: int = 1, duration: float = 200.0):
    sc = load_scenario(scenario)
    return sc, simulate(sc, seed, duration)


def restamp(events, epoch=0.0, phase=0.0, drift=0.0, control_epoch=0.0):
    """``(topic, stamp, fields, recv)`` in arrival order: odometer/balise stamped by a train clock
    ``epoch + phase + t (1 + drift)``, control on the reference clock ``control_epoch + t``;
    ``recv`` = reference clock at arrival (no latency). ``t`` = the simulator's stamp."""
    out = []
    for topic, t, fields in events:
        if topic in ("odometer", "balise"):
            out.append((topic, epoch + phase + t * (1.0 + drift), fields, control_epoch + t))
        elif topic == "control":
            out.append((topic, control_epoch + t, fields, control_epoch + t))
    return out


def adapter(sc, kind: str = "robust", **cfg):
    st = StartState(sc.start_position)
    if kind == "robust":
        return RobustAdapter(sc.train, sc.line, st, RobustConfig(period=1 / sc.odometer_rate,
                                                                   **cfg))
    return BrakingAdapter(sc.train, sc.line, st, BrakingConfig(algorithm=kind, **cfg))


def errors(outs, res, epoch=0.0, phase=0.0, drift=0.0):
    """Position errors at the output stamps (mapped back to true time)."""
    t = (np.array([o.stamp for o in outs]) - epoch - phase) / (1.0 + drift)
    x = np.array([o.position for o in outs])
    tr = res.truth
    inside = (t >= tr["t"][0]) & (t <= tr["t"][-1])
    return x[inside] - np.interp(t[inside], tr["t"], tr["position"]), t[inside]


def run_replay(sc, res, kind="robust", events=None, **clock):
    ev = events if events is not None else restamp(res.events(), **clock)
    return replay(ev, adapter(sc, kind), 1 / sc.odometer_rate)


def wobbled(sc, res, jitter: float, rng: np.random.Generator) -> list:
    """``res.events()`` of a sampling loop that wobbles: every odometer sample taken up to
    ``jitter`` s off its slot (uniform), stamped at that instant with the truth there (and the
    simulator's own speed noise); ``(topic, t, fields)`` in stamp order."""
    tr = res.truth
    ev = []
    for topic, t, f in res.events():
        if topic == "odometer":
            noise = f["speed"] - float(np.interp(t, tr["t"], tr["velocity"]))
            ts = max(0.0, t + rng.uniform(-jitter, jitter))
            f = {**f, "distance": float(np.interp(ts, tr["t"], tr["position"]))
                 - sc.start_position,
                 "speed": float(np.interp(ts, tr["t"], tr["velocity"])) + noise}
            t = ts
        ev.append((topic, t, f))
    ev.sort(key=lambda e: e[1])
    return ev
