"""Varied test cases for ``diagnose``: a random line, train, link, clock and driving style with a
hidden effect (or none, or a pair) of a given size.

    case = make_case(np.random.default_rng(7), "gradient", "subtle")
    case.scenario            # a train_sim Scenario: believed line/train + the hidden effects
    case.truth["gradient"]   # {"start", "end", "permille"} in docs/interfaces.md names and units
    case.nominal["gradient"] # what the believed model says ({"permille": 0.0})
    case.write(dir)          # line.yaml, train.yaml, scenario.yaml (for the executables)

Line families (``FAMILIES``): ``metro_demo`` (the shipped line, random train and timetable),
``metro`` (random 4-9 km line, stations 0.7-2 km apart, up to +-25 per mille), ``regional``
(8-15 km, stations 2-4 km apart, 120-160 km/h, up to +-15 per mille) and ``highspeed``
(11-15 km, two legs, 200-250 km/h, up to +-12 per mille). Balises every 300-1500 m; trains drawn
around a metro, a regional and a high-speed EMU (mass, rotary allowance, Davis, tau, T, limits);
Bernoulli link with p, r, latency 0-80 ms and jitter 0-30 ms; train-clock epoch 1e8-2e9 s; ATO
brake margin, speed margin, holding brake, initial dwell and dwells; 2-5 stops; 8-12 min runs.

Effect sizes: ``subtle`` is half the deviation from nominal of ``plain``:

=================  ===================================  =====================================
cause              subtle (k = 1)                        plain (k = 2)
=================  ===================================  =====================================
gradient           +-2 k per mille x U(1, 1.25), 300-500 m, on track run at > 3 m/s
resistance         a, b, c all x (1 +- 0.2 k)
braking_rate       f linear from 1 - 0.1 k U(0.3, 1) to 1 - 0.1 k U(1, 1.7) (30 %: constant)
odometer_scale     1 +- 0.0075 k
wheel_slip         1-3 episodes of 2-3 s, slip fraction +-0.05 k, at > 6 m/s
bursty_link        Gilbert-Elliott, mean burst 4 k samples, loss rate about the configured one
brake_delay        believed T + 0.25 k s
mass               believed mass x (1 +- 0.07 k)
clock_drift        +-0.001 k s/s
power_limit        knee speed of the largest traction command at 0.8 / k U(0.8, 1) of the top
                   speed (p_spec = a_max v_top 0.8 / k U(0.8, 1)); judged on 1 / p_spec
adhesion_section   factor 1 - 0.2 k U(1, 1.25) on a stretch of a braking-to-stop approach
traction_delay     believed T + 0.25 k s
=================  ===================================  =====================================

Each cause is one record (``CaseCause`` in ``REGISTRY``: how it is drawn, what it is judged
on); ``CAUSES`` and ``MAIN`` are derived from them. The trajectory-dependent placements
(gradient section, slip episodes, power limit, adhesion section) come from a pilot run of the
same world without those effects, so every effect is exercised. ``main_error`` gives the
relative error |estimate - true| / |true - nominal| of a cause's main quantity (see there).

Pure module: numpy + train_sim / train_core (no ROS). Same generator state -> same case.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml
from train_core.config import Section, load_yaml
from train_core.effects import parse_effects, true_line, true_link, true_train
from train_core.files import config_file
from train_core.link import LinkParams
from train_core.model import line_from_dict, train_from_dict

from .driver import DriverParams, TimetableStop
from .scenario import Scenario

# CAUSES and MAIN: derived from the causes' records, REGISTRY (below their draws)
SIZES = ("plain", "subtle")
FAMILIES = ("metro_demo", "metro", "regional", "highspeed")
MIN_DURATION, MAX_DURATION = 480.0, 720.0  # s, 8-12 min


@dataclass(frozen=True)
class Case:
    """One generated test case (see the module docstring)."""

    scenario: Scenario  # believed line/train + hidden effects; duration, timetable, link, ...
    causes: tuple[str, ...]  # hidden causes, () for nominal data
    size: str  # "plain" or "subtle"
    family: str  # line family
    truth: dict  # cause -> true parameters (docs/interfaces.md names, units; times: true clock)
    nominal: dict  # cause -> the believed model's values of the same parameters
    v_ref: float  # m/s, mean speed while moving (pilot run): resistance is compared there
    line_dict: dict = field(repr=False, default_factory=dict)
    train_dict: dict = field(repr=False, default_factory=dict)
    scenario_dict: dict = field(repr=False, default_factory=dict)

    @property
    def expected(self) -> str:
        """The cause a diagnosis should name first ("none" for nominal data)."""
        return self.causes[0] if self.causes else "none"

    def write(self, directory: str | Path) -> dict[str, Path]:
        """Write ``line.yaml``, ``train.yaml`` (believed) and ``scenario.yaml`` (with the hidden
        effects, loadable by ``load_scenario`` and ``python -m train_sim.generate``)."""
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        paths = {"line": d / "line.yaml", "train": d / "train.yaml",
                 "scenario": d / "scenario.yaml"}
        for key, data in (("line", self.line_dict), ("train", self.train_dict),
                          ("scenario", self.scenario_dict)):
            paths[key].write_text(yaml.safe_dump(_plain(data), sort_keys=False))
        return paths

    def truth_in_bag(self, first_stamp: float, last_stamp: float | None = None) -> dict:
        """The true parameters as the contract states them for a bag whose first (last)
        received odometer stamps are ``first_stamp`` (``last_stamp``): slip times in s since the
        first stamp on the stamp clock; f_start/f_end = f at the first/last message."""
        out = {k: dict(v) for k, v in self.truth.items()}
        eff = self.scenario.effects
        drift = eff.clock_drift.drift if eff.clock_drift else 0.0
        epoch = self.scenario.stamp_epoch

        def true_time(stamp):
            return (stamp - epoch) / (1.0 + drift)

        if "wheel_slip" in out:
            out["wheel_slip"]["intervals"] = [
                [epoch + t0 * (1 + drift) - first_stamp, epoch + t1 * (1 + drift) - first_stamp]
                for t0, t1 in self.truth["wheel_slip"]["intervals"]]
        if "braking_rate" in out and eff.braking_rate is not None:
            last = last_stamp if last_stamp is not None else epoch + self.scenario.duration * (
                1 + drift)
            out["braking_rate"] = {"f_start": eff.braking_rate.value(true_time(first_stamp)),
                                   "f_end": eff.braking_rate.value(true_time(last))}
        return out


# ------------------------------------------------------------------------------------------------
# Main quantity of each cause and its relative error
# ------------------------------------------------------------------------------------------------

def main_value(cause: str, params: dict, v_ref: float = 10.0) -> float:
    """The scalar a cause is judged on (``MAIN`` names it): the parameter itself, except
    resistance (the force a + b v + c v^2 at ``v_ref``: a, b, c alone are nearly collinear),
    braking_rate (mean of f_start and f_end), wheel_slip (total slip time) and power_limit
    (1 / p_spec: 0 without a limit, so that the deviation from nominal is finite)."""
    c = BY_NAME[cause]
    if c.derived is not None:
        return float(c.derived(params, v_ref))
    return float(params[c.param])


def main_error(cause: str, estimate: dict, truth: dict, nominal: dict,
               v_ref: float = 10.0) -> float:
    """|estimate - true| / |true - nominal| of the cause's main quantity (the benchmark's measure).

    wheel_slip: the duration of the symmetric difference between the estimated and the true
    interval sets over the true slip time (0 = the same episodes, 1 = as bad as finding none).
    gradient, adhesion_section: the value's error, plus the misplaced length of the section
    relative to its length (a right value at the wrong place is not a right answer)."""
    judged = BY_NAME[cause].judged
    if judged == "episodes":
        a, b = _union(estimate.get("intervals", [])), _union(truth["intervals"])
        inter = sum(max(0.0, min(x1, y1) - max(x0, y0)) for x0, x1 in a for y0, y1 in b)
        la, lb = sum(x1 - x0 for x0, x1 in a), sum(y1 - y0 for y0, y1 in b)
        return (la + lb - 2 * inter) / lb
    est, tru = main_value(cause, estimate, v_ref), main_value(cause, truth, v_ref)
    nom = main_value(cause, {**truth, **nominal}, v_ref)
    err = abs(est - tru) / abs(tru - nom)
    if judged == "section":
        s0, s1, e0, e1 = truth["start"], truth["end"], estimate["start"], estimate["end"]
        overlap = max(0.0, min(s1, e1) - max(s0, e0))
        err += ((s1 - s0) + (e1 - e0) - 2 * overlap) / (s1 - s0)
    return float(err)


def _union(intervals) -> list[tuple[float, float]]:
    out: list[list[float]] = []
    for t0, t1 in sorted((float(a), float(b)) for a, b in intervals):
        if out and t0 <= out[-1][1]:
            out[-1][1] = max(out[-1][1], t1)
        else:
            out.append([t0, t1])
    return [(a, b) for a, b in out]


# ------------------------------------------------------------------------------------------------
# The case generator
# ------------------------------------------------------------------------------------------------

def make_case(rng: np.random.Generator, cause: str | None | tuple = None, size: str = "plain",
              family: str | None = None, pilot=None) -> Case:
    """A random case with the hidden ``cause`` (None or "none": nominal data; a tuple: several
    causes at once) at ``size`` ("plain" or "subtle") on a line of ``family`` (default: drawn).

    ``pilot``: the function that runs the pilot simulation (default
    :func:`train_sim.world.simulate`; injectable for tests)."""
    causes = _causes(cause)
    if size not in SIZES:
        raise ValueError(f"size must be one of {SIZES}, got {size!r}")
    if family is None:
        family = FAMILIES[int(rng.integers(len(FAMILIES)))]
    if family not in FAMILIES:
        raise ValueError(f"family must be one of {FAMILIES}, got {family!r}")
    if pilot is None:
        from .world import simulate as pilot
    k = 1.0 if size == "subtle" else 2.0

    line_d = _line(rng, family)
    train_d = _train(rng, family)
    line, train = line_from_dict(line_d, f"case {family} line"), train_from_dict(train_d)
    stations = line.stations
    start_st, stops = stations[0], list(stations[1:])
    if family == "metro_demo":  # a random subset of 2-3 of the stops after A
        n = int(rng.integers(2, len(stops) + 1))
        stops = [stops[i] for i in sorted(rng.choice(len(stops), size=n, replace=False))]
    rate = float(rng.choice([5.0, 10.0]))
    driver_d = {
        "mode": "ato",
        "control_period": float(rng.choice([0.1, 0.2])),
        "brake_margin": round(float(rng.uniform(0.7, 0.95)), 3),
        "speed_margin": round(float(rng.uniform(0.3, 2.0 if family != "highspeed" else 8.0)), 2),
        "hold_brake": round(float(rng.uniform(0.2, 0.5)), 2),
        "initial_dwell": round(float(rng.uniform(3.0, 30.0)), 1),
    }
    dwells = [round(float(rng.uniform(15.0, 45.0)), 1) for _ in stops]
    p, r = float(rng.uniform(0.15, 0.5)), int(rng.choice([2, 3]))
    link_d = {"model": "bernoulli", "p": round(p, 3), "r": r,
              "latency": round(float(rng.uniform(0.0, 0.08)), 4),
              "jitter": round(float(rng.uniform(0.0, 0.03)), 4)}
    epoch = round(float(rng.uniform(1e8, 2e9)), 3)
    seed = int(rng.integers(2**31))
    target_duration = float(rng.uniform(MIN_DURATION, MAX_DURATION))
    eff_rng = np.random.default_rng(rng.integers(2**63))  # effect draws: own stream

    base = {
        "name": f"case-{family}-{'+'.join(causes) or 'none'}-{size}",
        "description": "generated by train_sim.cases",
        "line": "./line.yaml", "train": "./train.yaml", "seed": seed,
        "duration": 900.0,
        "start": {"position": start_st.position, "speed": 0.0},
        "sensors": {"odometer_rate": rate, "stamp_epoch": epoch},
        "integration": {"max_step": 0.01},
        "driver": driver_d,
        "timetable": [{"station": s.name, "dwell": d} for s, d in zip(stops, dwells)],
        "link": link_d,
        "effects": {},
    }
    # Effects that do not need the trajectory are drawn first and are in the pilot run.
    eff_d, truth, nominal = {}, {}, {}
    for c in causes:
        if not BY_NAME[c].on_run:
            eff_d[c], truth[c], nominal[c] = BY_NAME[c].draw(k, eff_rng, train, link_d)
    pilot_sc = _build(base | {"effects": dict(eff_d)}, line, train, line_d, train_d)
    res = pilot(pilot_sc)

    # Timetable and duration: the stops the train completes within about the target duration.
    stop_t = [s["t"] for s in res.stops]
    n_stops = len(stop_t)
    keep = max([i + 1 for i in range(n_stops) if stop_t[i] + 15.0 <= target_duration] or
               [min(n_stops, 1)])
    if keep < 2 and n_stops >= 2 and stop_t[1] + 15.0 <= MAX_DURATION:
        keep = 2  # two braking-to-stop phases whenever the longest run allows them
    if keep >= 1:
        duration = min(max(stop_t[keep - 1] + float(rng.uniform(15.0, 40.0)), MIN_DURATION),
                       MAX_DURATION)
    else:
        duration = MAX_DURATION
    base["timetable"] = base["timetable"][:max(keep, 1)]
    base["duration"] = round(duration, 1)

    tr = res.truth
    # the pilot ran the whole timetable: after the last stop kept, the case's train stands
    # while the pilot's drove on, so only the pilot's run up to that stop is the case's
    t_same = stop_t[keep - 1] if 1 <= keep <= n_stops else duration
    inside = tr["t"] <= min(duration, t_same)
    t, x, v = tr["t"][inside], tr["position"][inside], tr["velocity"][inside]
    moving = v > 1.0
    v_ref = float(np.mean(v[moving])) if moving.any() else 10.0
    # control is logged with every truth sample (world.py), so the two align
    run = _PilotRun(line=line, res=res, t=t, x=x, v=v, t_same=t_same,
                    a_cmd=res.control["target_acceleration"][inside])
    for c in causes:
        if BY_NAME[c].on_run:
            BY_NAME[c].draw(k, eff_rng, run, eff_d, truth, nominal)
    if "braking_rate" in eff_d:
        eff_d["braking_rate"]["t_end"] = base["duration"]
    base["effects"] = eff_d
    sc = _build(base, line, train, line_d, train_d)
    return Case(scenario=sc, causes=causes, size=size, family=family, truth=truth,
                nominal=nominal, v_ref=v_ref, line_dict=line_d, train_dict=train_d,
                scenario_dict=base)


def _causes(cause) -> tuple[str, ...]:
    if cause is None or cause == "none":
        return ()
    causes = (cause,) if isinstance(cause, str) else tuple(cause)
    for c in causes:
        if c not in CAUSES:
            raise ValueError(f"unknown cause {c!r} (allowed: none, {', '.join(CAUSES)})")
    if len(set(causes)) != len(causes):
        raise ValueError(f"a cause appears twice in {causes}")
    return causes


def _sign(rng) -> float:
    return 1.0 if rng.random() < 0.5 else -1.0


def _resistance(k, rng, train, link_d):
    s = 1.0 + _sign(rng) * 0.2 * k * float(rng.uniform(1.0, 1.25))
    d = train.davis
    e = {"a": d.a * s, "b": d.b * s, "c": d.c * s}
    return e, dict(e), {"a": d.a, "b": d.b, "c": d.c}


def _braking_rate(k, rng, train, link_d):
    f0 = 1.0 - 0.1 * k * float(rng.uniform(0.3, 1.0))
    f1 = f0 if rng.random() < 0.3 else 1.0 - 0.1 * k * float(rng.uniform(1.0, 1.7))
    e = {"f_start": round(f0, 4), "f_end": round(f1, 4)}
    f = train.brake.braking_rate
    return e, dict(e), {"f_start": f, "f_end": f}


def _odometer_scale(k, rng, train, link_d):
    e = {"scale": 1.0 + _sign(rng) * 0.0075 * k * float(rng.uniform(1.0, 1.25))}
    return e, dict(e), {"scale": 1.0}


def _bursty_link(k, rng, train, link_d):
    q = link_d["p"] ** link_d["r"]  # configured (Bernoulli) loss probability
    p_bg = 1.0 / (4.0 * k * float(rng.uniform(1.0, 1.25)))
    loss = float(np.clip(q * rng.uniform(1.0, 2.0), 0.05, 0.3))
    p_gb = loss * p_bg / (1.0 - loss)  # stationary loss rate = p_gb / (p_gb + p_bg)
    e = {"p_good_bad": p_gb, "p_bad_good": p_bg}
    # A Bernoulli link with loss q is the two-state chain with p_gb = q, p_bg = 1 - q.
    return e, dict(e), {"p_good_bad": q, "p_bad_good": 1.0 - q}


def _actuator_delay(k, rng, train, link_d):  # brake_delay, traction_delay
    e = {"delay": train.brake.delay + 0.25 * k * float(rng.uniform(1.0, 1.25))}
    return e, dict(e), {"delay": train.brake.delay}


def _mass(k, rng, train, link_d):
    e = {"mass": train.mass * (1.0 + _sign(rng) * 0.07 * k * float(rng.uniform(1, 1.25)))}
    return e, dict(e), {"mass": train.mass}


def _clock_drift(k, rng, train, link_d):
    e = {"drift": _sign(rng) * 0.001 * k * float(rng.uniform(1.0, 1.25))}
    return e, dict(e), {"drift": 0.0}


@dataclass(frozen=True)
class _PilotRun:
    """What the causes drawn on the pilot's trajectory need of it."""

    line: object  # the line (train_core.model.Line)
    res: object  # the pilot's SimResult
    t: np.ndarray  # s, truth times of the part of the run the case repeats
    x: np.ndarray  # m, positions there
    v: np.ndarray  # m/s, speeds there
    t_same: float  # s, end of that part
    a_cmd: np.ndarray  # m/s^2, the commanded acceleration at those times


def _draw_gradient(k, rng, run: _PilotRun, eff, truth, nominal) -> None:
    """A 300-500 m section that the pilot run crosses at > 3 m/s all along, away from stations."""
    line, x, v = run.line, run.x, run.v
    length = float(rng.uniform(300.0, 500.0))
    grid = np.arange(0.0, line.length - length, 10.0)
    ok = np.zeros(grid.shape, bool)
    order = np.argsort(x, kind="stable")
    xs, vs = x[order], v[order]
    for i, s in enumerate(grid):
        sel = (xs >= s - 20.0) & (xs <= s + length + 20.0)
        # crossed (covered by samples over its whole length) and at speed everywhere
        ok[i] = sel.sum() > 5 and xs[sel].min() <= s and xs[sel].max() >= s + length \
            and vs[sel].min() > 3.0
    if not ok.any():
        raise RuntimeError("no stretch of track is run at speed: cannot place a gradient section")
    start = float(rng.choice(grid[ok])) + float(rng.uniform(0.0, 10.0))
    permille = _sign(rng) * 2.0 * k * float(rng.uniform(1.0, 1.25))
    eff["gradient"] = {"start": round(start, 1), "end": round(start + length, 1),
                       "permille": round(permille, 3)}
    truth["gradient"] = dict(eff["gradient"])
    nominal["gradient"] = {"permille": 0.0}


def _draw_slip(k, rng, run: _PilotRun, eff, truth, nominal) -> None:
    """1-3 episodes of 2-3 s at > 6 m/s (with 5 s of margin), well apart."""
    t, v = run.t, run.v
    n = int(rng.integers(1, 4))
    fast = v > 6.0
    # candidate starts: fast over [t0 - 5, t0 + 8]
    dt = float(np.median(np.diff(t)))
    w0, w1 = int(round(5.0 / dt)), int(round(8.0 / dt))
    good = np.array([fast[max(0, i - w0):i + w1].all() and i + w1 < len(t)
                     for i in range(len(t))])
    idx = np.flatnonzero(good)
    if idx.size == 0:
        raise RuntimeError("the train never runs fast enough for a wheel-slip episode")
    chosen: list[float] = []
    for i in rng.permutation(idx):
        t0 = float(t[i])
        if all(abs(t0 - c) > 30.0 for c in chosen):
            chosen.append(t0)
        if len(chosen) == n:
            break
    intervals = sorted([round(t0, 2), round(t0 + float(rng.uniform(2.0, 3.0)), 2)]
                       for t0 in chosen)
    frac = _sign(rng) * 0.05 * k * float(rng.uniform(1.0, 1.25))
    eff["wheel_slip"] = {"intervals": intervals, "slip_fraction": round(frac, 4)}
    truth["wheel_slip"] = {"intervals": [list(iv) for iv in intervals]}
    nominal["wheel_slip"] = {"intervals": []}


def _draw_power_limit(k, rng, run: _PilotRun, eff, truth, nominal) -> None:
    """p_spec such that the largest traction command (95th percentile of the pilot's) meets the
    limit at 0.8 / k U(0.8, 1) of the top speed: a constant-power run above that knee."""
    a_cmd, v = run.a_cmd, run.v
    trac = a_cmd[a_cmd > 0.05]
    if trac.size == 0 or v.max() < 3.0:
        raise RuntimeError("the train never pulls: cannot place a power limit")
    a_max, v_top = float(np.percentile(trac, 95)), float(v.max())
    p_spec = a_max * v_top * 0.8 / k * float(rng.uniform(0.8, 1.0))
    eff["power_limit"] = {"p_spec": round(p_spec, 4)}
    truth["power_limit"] = dict(eff["power_limit"])
    nominal["power_limit"] = {"p_spec": float("inf")}


def _draw_adhesion(k, rng, run: _PilotRun, eff, truth, nominal) -> None:
    """A stretch of the braking-to-stop approach of one of the run's stops (wet rail before a
    station): from 10-30 % to 80-95 % of the braking distance."""
    res, t_end = run.res, run.t_same
    tr, ctrl = res.truth, res.control
    approaches = []
    for stop in res.stops:
        if stop["t"] > t_end:
            continue
        before = (tr["t"] <= stop["t"]) & (ctrl["target_acceleration"] >= 0.0)
        if not before.any():
            continue
        i_b = int(np.flatnonzero(before)[-1])  # the last sample not braking before the stop
        x_b, x_s = float(tr["position"][i_b]), float(stop["stop_position"])
        if x_s - x_b > 60.0 and tr["velocity"][i_b] > 5.0:
            approaches.append((x_b, x_s))
    if not approaches:
        raise RuntimeError("no braking-to-stop approach: cannot place an adhesion section")
    x_b, x_s = approaches[int(rng.integers(len(approaches)))]
    length = x_s - x_b
    start = x_b + length * float(rng.uniform(0.1, 0.3))
    end = x_b + length * float(rng.uniform(0.8, 0.95))
    factor = 1.0 - 0.2 * k * float(rng.uniform(1.0, 1.25))
    eff["adhesion_section"] = {"start": round(start, 1), "end": round(end, 1),
                               "factor": round(factor, 4)}
    truth["adhesion_section"] = dict(eff["adhesion_section"])
    nominal["adhesion_section"] = {"factor": 1.0}


# ------------------------------------------------------------------------------------------------
# The causes: one record each
# ------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class CaseCause:
    """One listed cause as the case generator knows it: how it is drawn and what a fit of it is
    judged on (:func:`main_value`, :func:`main_error`)."""

    name: str  # the cause, as docs/interfaces.md names it
    main: str  # the main quantity it is judged on, as benchmark tables name it (MAIN)
    unit: str  # the main quantity's unit ("1": a ratio or a probability)
    # How it is drawn at size factor k. Before the pilot run (``on_run`` False):
    # (k, rng, believed train, link dict) -> (effect, truth, nominal). On the pilot run's
    # trajectory (``on_run`` True: a place, episodes, a knee speed the run reaches):
    # (k, rng, _PilotRun, effects, truth, nominal), filled in place.
    draw: Callable
    on_run: bool = False
    param: str | None = None  # the parameter that is the main quantity, if one is
    # (parameters, v_ref m/s) -> the main quantity, for a cause judged on a derived one
    derived: Callable | None = None
    # "value": the main quantity's error; "section": plus the section's misplaced length;
    # "episodes": the symmetric difference of the episodes' intervals (main_error)
    judged: str = "value"


REGISTRY = (
    CaseCause("gradient", "permille", "per mille", _draw_gradient, on_run=True, param="permille",
              judged="section"),
    CaseCause("resistance", "force at v_ref (N)", "N", _resistance,
              derived=lambda p, v_ref: p["a"] + p["b"] * v_ref + p["c"] * v_ref**2),
    CaseCause("braking_rate", "mean f", "1", _braking_rate,
              derived=lambda p, v_ref: 0.5 * (float(p["f_start"]) + float(p["f_end"]))),
    CaseCause("odometer_scale", "scale", "1", _odometer_scale, param="scale"),
    CaseCause("wheel_slip", "slip time (symmetric difference, s)", "s", _draw_slip, on_run=True,
              derived=lambda p, v_ref: sum(t1 - t0 for t0, t1 in p.get("intervals", [])),
              judged="episodes"),
    CaseCause("bursty_link", "p_bad_good", "1", _bursty_link, param="p_bad_good"),
    CaseCause("brake_delay", "delay", "s", _actuator_delay, param="delay"),
    CaseCause("mass", "mass", "kg", _mass, param="mass"),
    CaseCause("clock_drift", "drift", "s/s", _clock_drift, param="drift"),
    CaseCause("power_limit", "1 / p_spec (s^3/m^2)", "s^3/m^2", _draw_power_limit, on_run=True,
              derived=lambda p, v_ref: 1.0 / float(p["p_spec"])),
    CaseCause("adhesion_section", "factor", "1", _draw_adhesion, on_run=True, param="factor",
              judged="section"),
    CaseCause("traction_delay", "delay", "s", _actuator_delay, param="delay"),
)
BY_NAME = {c.name: c for c in REGISTRY}
CAUSES = tuple(c.name for c in REGISTRY)
MAIN = {c.name: c.main for c in REGISTRY}


def _build(d: dict, line, train, line_d: dict, train_d: dict) -> Scenario:
    """The Scenario of a scenario dict with in-memory line/train (what scenario_from_dict builds
    from files; Case.write + load_scenario gives the same, tested)."""
    dr = d["driver"]
    driver = DriverParams(mode="ato", control_period=dr["control_period"],
                          brake_margin=dr["brake_margin"], speed_margin=dr["speed_margin"],
                          hold_brake=dr["hold_brake"], initial_dwell=dr["initial_dwell"])
    stations = {s.name: s for s in line.stations}
    timetable = tuple(TimetableStop(e["station"], stations[e["station"]].position, e["dwell"])
                      for e in d["timetable"])
    ln = d["link"]
    link = LinkParams(model="bernoulli", p=ln["p"], r=ln["r"], latency=ln["latency"],
                      jitter=ln["jitter"])
    effects = parse_effects(Section(_plain(d["effects"]), f"{d['name']}.effects"),
                            d["duration"])
    return Scenario(
        name=d["name"], path="", line=line, train=train,
        true_line=true_line(line, effects), true_train=true_train(train, effects),
        seed=d["seed"], duration=float(d["duration"]),
        start_position=float(d["start"]["position"]), start_speed=0.0,
        start_acceleration=0.0, start_target_acceleration=0.0,
        odometer_rate=float(d["sensors"]["odometer_rate"]), max_step=0.01, driver=driver,
        timetable=timetable, link=link, true_link=true_link(link, effects), effects=effects,
        stamp_epoch=float(d["sensors"]["stamp_epoch"]))


def _plain(obj):
    """Python floats/ints/lists (no numpy scalars, no tuples) for safe_dump and the parsers."""
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating):
        return float(obj)
    return obj


# ------------------------------------------------------------------------------------------------
# Lines and trains
# ------------------------------------------------------------------------------------------------

def _line(rng, family: str) -> dict:
    if family == "metro_demo":
        d = load_yaml(config_file("lines", "metro_demo"))
        return d  # the shipped line (make_case draws a subset of its stops)
    if family == "metro":
        length = float(rng.uniform(4000.0, 9000.0))
        spacing, vmax, gmax = (700.0, 2000.0), float(rng.uniform(19.4, 25.0)), 25.0
    elif family == "regional":
        length = float(rng.uniform(8000.0, 15000.0))
        spacing, vmax, gmax = (2000.0, 4000.0), float(rng.uniform(33.3, 44.4)), 15.0
    else:  # highspeed: two legs
        length = float(rng.uniform(11000.0, 15000.0))
        spacing, vmax, gmax = (None, None), float(rng.uniform(55.6, 69.4)), 12.0
    first = float(rng.uniform(100.0, 300.0))
    last = length - float(rng.uniform(200.0, 400.0))
    if spacing[0] is None:
        pos = [first, first + (last - first) * float(rng.uniform(0.45, 0.55)), last]
    else:
        pos = [first]
        while True:
            nxt = pos[-1] + float(rng.uniform(*spacing))
            if nxt > last - spacing[0] * 0.5:
                break
            pos.append(nxt)
        pos.append(last)
        pos = pos[:6]  # at most 5 stops
    pos = [round(p, 1) for p in pos]
    stations = [{"name": f"S{i}", "position": p, "dwell": 30.0} for i, p in enumerate(pos)]
    # gradients: level +-150 m around stations, random sections of 200-1000 m between
    cuts, x = [0.0], 0.0
    while x < length:
        x = min(length, x + float(rng.uniform(200.0, 1000.0)))
        cuts.append(round(x, 1))
    grads = []
    for a, b in zip(cuts, cuts[1:]):
        mid = 0.5 * (a + b)
        level = any(abs(mid - p) < 150.0 + 0.5 * (b - a) for p in pos)
        g = 0.0 if level else round(float(rng.uniform(-gmax, gmax)), 1)
        grads.append({"start": a, "end": b, "permille": g})
    # balises every 300-1500 m
    balises, bx = [], float(rng.uniform(20.0, 300.0))
    while bx < length:
        balises.append({"id": len(balises) + 1, "position": round(bx, 1)})
        bx += float(rng.uniform(300.0, 1500.0))
    limits = [{"start": 0.0, "end": pos[0] + 300.0, "speed": round(min(vmax, 16.7), 2)}]
    return {"name": f"{family}-line", "length": round(length, 1), "max_speed": round(vmax, 2),
            "speed_limits": limits, "gradients": grads, "stations": stations,
            "balises": balises}


def _train(rng, family: str) -> dict:
    u = rng.uniform
    if family in ("metro_demo", "metro"):
        mass = float(u(180e3, 330e3))
        lam, per_t = float(u(0.06, 0.16)), (u(8, 16), u(0.3, 0.6), u(0.02, 0.04))
        tau, delay = float(u(0.3, 0.6)), float(u(0.5, 1.5))
        perf = {"max_traction": u(0.8, 1.1), "service_brake": u(0.7, 1.0),
                "emergency_brake": 1.25, "max_jerk": 0.75}
    elif family == "regional":
        mass = float(u(150e3, 400e3))
        lam, per_t = float(u(0.06, 0.12)), (u(8, 14), u(0.2, 0.4), u(0.015, 0.03))
        tau, delay = float(u(0.3, 0.7)), float(u(0.6, 1.5))
        perf = {"max_traction": u(0.6, 0.9), "service_brake": u(0.6, 0.9),
                "emergency_brake": 1.1, "max_jerk": 0.6}
    else:
        mass = float(u(400e3, 520e3))
        lam, per_t = float(u(0.05, 0.08)), (u(4, 7), u(0.1, 0.18), u(0.01, 0.02))
        tau, delay = float(u(0.4, 0.7)), float(u(0.8, 1.5))
        perf = {"max_traction": u(0.45, 0.7), "service_brake": u(0.5, 0.7),
                "emergency_brake": 1.0, "max_jerk": 0.5}
    tonnes = mass / 1000.0
    return {
        "name": f"{family}-train", "mass": round(mass, 0), "rotary_allowance": round(lam, 3),
        "davis": {"a": round(float(per_t[0]) * tonnes, 2), "b": round(float(per_t[1]) * tonnes, 3),
                  "c": round(float(per_t[2]) * tonnes, 4)},
        "brake": {"time_constant": round(tau, 3), "delay": round(delay, 3), "braking_rate": 1.0},
        "odometer": {"speed_std": round(float(u(0.05, 0.15)), 3),
                     "distance_std": round(float(u(0.1, 0.5)), 3)},
        "balise": {"position_std": round(float(u(0.5, 1.5)), 3)},
        "performance": {k: round(float(v), 3) for k, v in perf.items()},
    }


def describe(case: Case) -> str:
    """One line: family, causes, size and the true values (for logs and benchmark tables)."""
    parts = [f"{case.family}", "+".join(case.causes) or "none", case.size,
             f"{case.scenario.duration:.0f} s", f"{len(case.scenario.timetable)} stops"]
    for c in case.causes:
        parts.append(f"{c}={ {k: _short(v) for k, v in case.truth[c].items()} }")
    return ", ".join(parts)


def _short(v):
    if isinstance(v, float):
        return float(f"{v:.4g}")
    if isinstance(v, list):
        return [_short(u) for u in v]
    return v


__all__ = ["CAUSES", "FAMILIES", "MAIN", "REGISTRY", "SIZES", "Case", "CaseCause", "describe",
           "main_error", "main_value", "make_case"]
