"""Scenarios: which line, train, timetable, link, sensor rates, effects, seed and duration.

``load_scenario("metro_demo")`` reads ``<share>/scenarios/metro_demo.yaml``; a path (anything with
a ``/`` or ending in ``.yaml``) is read as is. Inside a scenario, ``line:`` and ``train:`` are
either bare names (``config/lines/<name>.yaml``, ``config/trains/<name>.yaml`` of train_core) or
paths relative to the scenario file; ``line: ttobench:ID`` is a real line from TTOBench's track
file ``ID.json``, found at run time in $TRAIN_LINES_DIR or ``../shared/lines/`` beside the
checkout and converted by :mod:`train_core.ttobench` (a clear error says where to put the file
and how to get it when it is absent).

Validation is strict (:mod:`train_core.config`): a missing key, a value out of range, an unknown
effect or an unknown field raises :class:`~train_core.config.ConfigError` with a one-line message
naming the file, the key and what is allowed.

Pure module: PyYAML + the shared model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

from train_core.config import REQUIRED, ConfigError, Section, load_yaml
from train_core.effects import Effects, parse_effects, true_line, true_link, true_train
from train_core.files import config_file, share_dir
from train_core.link import MODELS, LinkParams
from train_core.model import Line, TrainParams, load_line, load_train

from .driver import DRIVER_MODES, DriverParams, TimetableStop

TTOBENCH = "ttobench:"  # line: ttobench:ID, a real line (train_core.ttobench, docs/real_lines.md)
SCENARIO_KEYS = ("name", "description", "line", "train", "seed", "duration", "start", "sensors",
                 "integration", "driver", "timetable", "link", "effects")


def data_root() -> Path:
    """Directory holding train_sim's ``scenarios/`` (source tree or installed share)."""
    return share_dir("train_sim", "scenarios")


@dataclass(frozen=True)
class Scenario:
    """One simulation set-up. ``line``/``train`` are believed; ``true_*`` = believed + effects."""

    name: str
    path: str  # the scenario file
    line: Line  # what line.yaml says (estimators get this)
    train: TrainParams  # what train.yaml says (estimators get this)
    true_line: Line
    true_train: TrainParams
    seed: int
    duration: float  # s
    start_position: float  # m
    start_speed: float  # m/s
    start_acceleration: float  # m/s^2, actuator output a_hat(0)
    start_target_acceleration: float  # m/s^2, command filling the delay line at t = 0
    odometer_rate: float  # Hz
    max_step: float  # s, largest internal integration step (<= 0.01)
    driver: DriverParams
    timetable: tuple[TimetableStop, ...]
    link: LinkParams  # configured link model
    true_link: LinkParams  # the one the world uses (bursty_link effect)
    effects: Effects
    stamp_epoch: float = 0.0  # s, the train clock's reading at true time 0 (odometer, balise)
    line_path: str = ""  # the line.yaml file the estimators are given
    train_path: str = ""  # the train.yaml file the estimators are given
    unlisted: object = None  # train_sim.unlisted.Unlisted: test effects outside the causes list

    def with_effects(self, effects: Effects) -> Scenario:
        """The same scenario with other effects (true models recomputed)."""
        return replace(self, effects=effects, true_line=true_line(self.line, effects),
                       true_train=true_train(self.train, effects),
                       true_link=true_link(self.link, effects))

    def with_changes(self, **kw) -> Scenario:
        """dataclasses.replace, recomputing the true models if believed ones or effects change."""
        sc = replace(self, **kw)
        return sc.with_effects(sc.effects)


def _resolve(ref: str, kind: str, base: Path) -> Path:
    if kind == "lines" and ref.startswith(TTOBENCH):
        # a real line from TTOBench's track file, found at run time (not in the repository)
        from train_core.ttobench import resolve_line

        return resolve_line(ref[len(TTOBENCH):])
    if "/" in ref or ref.endswith(".yaml"):
        p = Path(ref)
        return p if p.is_absolute() else (base / p)
    return config_file(kind, ref)


def scenario_path(name_or_path: str | Path) -> Path:
    s = str(name_or_path)
    if "/" in s or s.endswith(".yaml"):
        return Path(s)
    return data_root() / "scenarios" / f"{s}.yaml"


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load and validate a scenario by name (package ``scenarios/``) or path."""
    path = scenario_path(name_or_path)
    return scenario_from_dict(load_yaml(path), str(path), path.parent)


def scenario_from_dict(data: dict, where: str, base_dir: Path | str = ".") -> Scenario:
    base = Path(base_dir)
    s = Section(data, where, SCENARIO_KEYS)
    line_path = _resolve(s.string("line", REQUIRED), "lines", base)
    train_path = _resolve(s.string("train", REQUIRED), "trains", base)
    line, train = load_line(line_path), load_train(train_path)
    duration = s.number("duration", REQUIRED, lo=0.0, lo_open=True, hi=1e6, unit="s")

    st = s.section("start", ("position", "speed", "acceleration", "target_acceleration"),
                   default=REQUIRED)
    x0 = st.number("position", REQUIRED, lo=0.0, hi=line.length, unit="m")
    v0 = st.number("speed", 0.0, lo=0.0, hi=150.0, unit="m/s")
    a0 = st.number("acceleration", 0.0, lo=-5.0, hi=5.0, unit="m/s^2")
    u0 = st.number("target_acceleration", 0.0, lo=-5.0, hi=5.0, unit="m/s^2")

    sens = s.section("sensors", ("odometer_rate", "stamp_epoch"), default={})
    rate = sens.number("odometer_rate", 10.0, lo=0.0, lo_open=True, hi=1000.0, unit="Hz")
    epoch = sens.number("stamp_epoch", 0.0, lo=0.0, hi=4.0e9, unit="s")
    integ = s.section("integration", ("max_step",), default={})
    max_step = integ.number("max_step", 0.01, lo=0.0, lo_open=True, hi=0.01, unit="s")

    d = s.section("driver", ("mode", "control_period", "braking_rate_belief", "brake_margin",
                             "speed_margin", "speed_gain", "stop_tolerance", "ma_margin",
                             "hold_brake", "initial_dwell", "profile"), default={})
    dflt = DriverParams()
    mode = d.string("mode", "ato", choices=DRIVER_MODES)
    profile = _profile(d, mode)
    driver = DriverParams(
        mode=mode,
        control_period=d.number("control_period", max(1.0 / rate, max_step), lo=max_step,
                                hi=10.0, unit="s"),
        braking_rate_belief=d.number("braking_rate_belief", 1.0, lo=0.0, lo_open=True, hi=2.0),
        brake_margin=d.number("brake_margin", dflt.brake_margin, lo=0.1, hi=1.0),
        speed_margin=d.number("speed_margin", dflt.speed_margin, lo=0.0, hi=10.0, unit="m/s"),
        speed_gain=d.number("speed_gain", dflt.speed_gain, lo=0.0, hi=10.0, unit="1/s"),
        stop_tolerance=d.number("stop_tolerance", dflt.stop_tolerance, lo=0.0, lo_open=True,
                                hi=50.0, unit="m"),
        ma_margin=d.number("ma_margin", dflt.ma_margin, lo=0.0, hi=500.0, unit="m"),
        hold_brake=d.number("hold_brake", dflt.hold_brake, lo=0.0, hi=5.0, unit="m/s^2"),
        initial_dwell=d.number("initial_dwell", 0.0, lo=0.0, unit="s"),
        profile=profile,
    )

    stations = {stn.name: stn for stn in line.stations}
    timetable = []
    for e in s.sections("timetable", ("station", "dwell"), default=[]):
        name = e.string("station", REQUIRED)
        if name not in stations:
            raise ConfigError(f"{e.where}.station: unknown station '{name}' "
                              f"(allowed: {', '.join(stations) or 'none in the line file'})")
        stn = stations[name]
        timetable.append(TimetableStop(name, stn.position,
                                       e.number("dwell", stn.dwell, lo=0.0, unit="s")))
    for a, b in zip(timetable, timetable[1:]):
        if b.position <= a.position:
            raise ConfigError(f"{where}.timetable: stations must be in running direction "
                              f"('{b.station}' is not beyond '{a.station}')")

    ln = s.section("link", ("model", "p", "r", "p_good_bad", "p_bad_good", "loss_good",
                            "loss_bad", "latency", "jitter", "outages"), default={})
    link = LinkParams(
        model=ln.string("model", "bernoulli", choices=MODELS),
        p=ln.number("p", 0.5, lo=0.0, hi=1.0),
        r=ln.integer("r", 3, lo=1, hi=100),
        p_good_bad=ln.number("p_good_bad", 0.0, lo=0.0, hi=1.0),
        p_bad_good=ln.number("p_bad_good", 1.0, lo=0.0, hi=1.0, lo_open=True),
        loss_good=ln.number("loss_good", 0.0, lo=0.0, hi=1.0),
        loss_bad=ln.number("loss_bad", 1.0, lo=0.0, hi=1.0),
        latency=ln.number("latency", 0.0, lo=0.0, hi=10.0, unit="s"),
        jitter=ln.number("jitter", 0.0, lo=0.0, hi=10.0, unit="s"),
        outages=ln.intervals("outages", ()),
    )
    effects = parse_effects(s.section("effects", default={}), duration)
    if effects.gradient is not None and effects.gradient.end > line.length:
        raise ConfigError(f"{where}.effects.gradient.end: {effects.gradient.end:g} is beyond the "
                          f"line, allowed [0, {line.length:g}] m")

    return Scenario(
        name=s.string("name", Path(where).stem),
        path=where,
        line_path=str(line_path),
        train_path=str(train_path),
        line=line,
        train=train,
        true_line=true_line(line, effects),
        true_train=true_train(train, effects),
        seed=s.integer("seed", 0, lo=0, hi=2**63 - 1),
        duration=duration,
        start_position=x0,
        start_speed=v0,
        start_acceleration=a0,
        start_target_acceleration=u0,
        odometer_rate=rate,
        max_step=max_step,
        driver=driver,
        timetable=tuple(timetable),
        link=link,
        true_link=true_link(link, effects),
        effects=effects,
        stamp_epoch=epoch,
    )


def _profile(d: Section, mode: str) -> tuple[tuple[float, float], ...]:
    raw = d.data.get("profile")
    if raw is None:
        if mode == "open_loop":
            raise ConfigError(f"{d.where}: missing key 'profile' (required by mode open_loop)")
        return ()
    ok = isinstance(raw, list) and all(
        isinstance(r, list) and len(r) == 2
        and all(isinstance(u, (int, float)) and not isinstance(u, bool) and math.isfinite(u)
                for u in r)
        and r[0] >= 0 and -5.0 <= r[1] <= 5.0 for r in raw)
    if not ok:
        raise ConfigError(f"{d.where}.profile: expected a list of [t (s, >= 0), a_Tar "
                          f"(m/s^2, in [-5, 5])], got {raw!r}")
    return tuple((float(a), float(b)) for a, b in raw)


def with_model(sc: Scenario, model_dir: str | Path) -> Scenario:
    """``sc`` with the line, train and effects of a model directory (``diagnose``'s
    ``OUT/model``: ``line.yaml``, ``train.yaml`` and optionally ``effects.yaml``, a mapping
    {effect: {parameters}} as in a scenario's ``effects:``). The model is both what the world
    runs and what the estimators are given; its effects are the fitted ones.

    The run is on the model's own line: when that line has the scenario's stations (same names
    at the same positions) the scenario's start and timetable are kept; otherwise the train
    starts at the model line's first station and calls at every other one, in running order,
    with line.yaml's dwells (a scenario's stop positions on another line would put the train's
    stops off every platform). The scenario's driver, link, seed and duration are kept."""
    d = Path(model_dir)
    for name in ("line.yaml", "train.yaml"):
        if not (d / name).is_file():
            raise ConfigError(f"{d}: missing {name} (a model directory holds line.yaml, "
                              "train.yaml and optionally effects.yaml)")
    line = load_line(d / "line.yaml")
    train = load_train(d / "train.yaml")
    eff_path = d / "effects.yaml"
    raw = load_yaml(eff_path) if eff_path.is_file() else {}
    effects = parse_effects(Section(raw or {}, str(eff_path)), sc.duration)
    start, timetable = _own_timetable(sc, line)
    return replace(sc, line=line, train=train, line_path=str(d / "line.yaml"),
                   train_path=str(d / "train.yaml"), start_position=start,
                   timetable=timetable).with_effects(effects)


def _own_timetable(sc: Scenario, line: Line) -> tuple[float, tuple[TimetableStop, ...]]:
    """(start position m, timetable) of scenario ``sc`` run on ``line`` (see with_model)."""
    tol = 1e-6  # m: "the same position" (both are read from YAML)
    here = {s.name: s.position for s in line.stations}
    same = (all(abs(here.get(s.name, math.inf) - s.position) <= tol for s in sc.line.stations)
            and sc.start_position <= line.length)
    if same:
        return sc.start_position, sc.timetable
    if not line.stations:
        return min(sc.start_position, line.length), ()
    stations = sorted(line.stations, key=lambda s: s.position)
    return (stations[0].position,
            tuple(TimetableStop(s.name, s.position, s.dwell) for s in stations[1:]))
