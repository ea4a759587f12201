"""Scenarios on real lines (TTOBench's track files, docs/real_lines.md) and the hidden map
errors the benchmarks and tests put on them.

The track files are not in the repository: :func:`available` says which real-line scenarios
can run here and, for the others, why not (the message of
:func:`train_core.ttobench.find_track`: where to put the file and how to get it). Benchmarks
skip the absent ones with that note; tests skip with it.

Pure module (the scenario loader and numpy).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from train_core.config import ConfigError
from train_core.effects import Effects, GradientEffect

from .scenario import Scenario, load_scenario

# the scenarios whose line is a real one, in the order the tables list them
REAL_SCENARIOS = ("yizhuang_metro", "zurich_stadelhofen")


def available(names=REAL_SCENARIOS) -> tuple[dict, dict]:
    """({name: Scenario} that load here, {name: why not} for the others)."""
    ok, missing = {}, {}
    for n in names:
        try:
            ok[n] = load_scenario(n)
        except ConfigError as exc:
            missing[n] = str(exc)
    return ok, missing


@dataclass(frozen=True)
class HiddenGradient:
    """A map error put on a real line: the world's gradient on [start, end) is the map's plus
    ``permille``."""

    scenario: Scenario  # the scenario with the effect (its line is still the map)
    start: float  # m
    end: float  # m
    permille: float  # per mille, true minus mapped


def hidden_gradient(sc: Scenario, rng: np.random.Generator, *, length=(300.0, 700.0),
                    size=(4.0, 8.0), margin: float = 150.0) -> HiddenGradient:
    """A section of ``length`` m (uniform) with ``+-size`` per mille (uniform magnitude, random
    sign) placed uniformly between two stops of the timetable, at least ``margin`` m from
    either (where the train runs, not where it stands), on a stretch the run covers."""
    stops = [sc.start_position] + [s.position for s in sc.timetable]
    gaps = [(a + margin, b - margin) for a, b in zip(stops, stops[1:])]
    lo_len = length[0]
    gaps = [(a, b) for a, b in gaps if b - a >= lo_len]
    if not gaps:
        raise ValueError(f"{sc.name}: no stretch between stops is long enough for a section "
                         f"of {lo_len:g} m")
    w = np.array([b - a for a, b in gaps])
    a, b = gaps[int(rng.choice(len(gaps), p=w / w.sum()))]
    ln = float(min(rng.uniform(*length), b - a))
    start = float(rng.uniform(a, b - ln))
    permille = float(rng.choice([-1.0, 1.0]) * rng.uniform(*size))
    start, end = round(start, 1), round(start + ln, 1)
    eff = Effects(gradient=GradientEffect(start, end, round(permille, 2)))
    return HiddenGradient(sc.with_effects(eff), start, end, round(permille, 2))
