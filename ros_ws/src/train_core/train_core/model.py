"""The train and the line as the railway describes them: frozen dataclasses with SI units.

One model class serves both the world (the simulator integrates it) and the estimators (they
discretise it), so simulated truth and filter assumptions cannot silently diverge. The simulator's
effects (``train_core.effects``) produce a *modified copy* of these objects with
:func:`dataclasses.replace`; the estimators only ever see what ``train.yaml``/``line.yaml`` say.

Longitudinal dynamics (mass point)::

    (1 + lambda) M dv/dt = F_drive - (a + b v + c v^2) - M g sin(theta(x)),    dx/dt = v

Pure module: numpy + PyYAML only.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path

import numpy as np

from .config import REQUIRED, ConfigError, Section, check_top_level, load_yaml

G = 9.80665  # m/s^2, standard gravity


@dataclass(frozen=True)
class Davis:
    """Davis running resistance R(v) = a + b v + c v^2 in newtons (whole train)."""

    a: float  # N
    b: float  # N/(m/s)
    c: float  # N/(m/s)^2

    def force(self, v):
        """Resistance in N opposing motion; ``v`` in m/s (scalar or array), v >= 0."""
        return self.a + self.b * v + self.c * v * v


@dataclass(frozen=True)
class Brake:
    """Brake/traction actuator after Zheng et al. (2015) eq. (1)-(3)."""

    time_constant: float  # s, first-order lag tau
    delay: float  # s, transport delay T (estimators use Pade with lambda = 2/T)
    braking_rate: float = 1.0  # -, f: achieved braking = f * commanded braking (1 = nominal)


@dataclass(frozen=True)
class Performance:
    """Limits the driver/ATO works with (extra keys of train.yaml, all optional)."""

    max_traction: float = 1.0  # m/s^2, largest traction command
    service_brake: float = 0.8  # m/s^2, service braking the ATO plans with (magnitude)
    emergency_brake: float = 1.2  # m/s^2, emergency braking (magnitude, nominal f)
    max_jerk: float = 0.75  # m/s^3, comfort limit on command changes


@dataclass(frozen=True)
class TrainParams:
    """The train as the railway believes it to be (``train.yaml``)."""

    mass: float  # kg, total (tare + load)
    rotary_allowance: float  # -, lambda: effective mass = (1 + lambda) * mass
    davis: Davis
    brake: Brake
    odometer_speed_std: float = 0.1  # m/s, odometer speed noise (1 sigma)
    odometer_distance_std: float = 0.0  # m, per-sample noise on counted distance (extra key)
    balise_position_std: float = 1.0  # m, balise reading noise (extra key)
    performance: Performance = field(default_factory=Performance)
    name: str = "train"

    @property
    def effective_mass(self) -> float:
        """kg, (1 + lambda) M."""
        return (1.0 + self.rotary_allowance) * self.mass

    @property
    def odometer_speed_variance(self) -> float:
        """(m/s)^2, the odometer speed variance ``train.yaml`` states: what every estimator
        assumes until (or where) a message states its own ``speed_variance``. Floored at 1e-6
        so that a noiseless odometer still gives a proper (invertible) measurement."""
        return max(self.odometer_speed_std ** 2, 1e-6)

    @property
    def balise_position_variance(self) -> float:
        """m^2, the balise reading variance ``train.yaml`` states (``balise.position_std``,
        > 0): what the estimators and ``diagnose`` assume for a stream that states none."""
        return self.balise_position_std ** 2

    @property
    def odometer_distance_variance(self) -> float:
        """m^2, the variance of the counted distance as a position reading (``train.yaml``'s
        ``distance_std``), floored at 1e-4 for the same reason."""
        return max(self.odometer_distance_std ** 2, 1e-4)

    def resistance_accel(self, v):
        """m/s^2, deceleration from Davis resistance: R(v) / ((1 + lambda) M)."""
        return self.davis.force(v) / self.effective_mass

    def with_changes(self, **kw) -> TrainParams:
        return replace(self, **kw)


@dataclass(frozen=True)
class GradientSection:
    start: float  # m
    end: float  # m
    permille: float  # per mille, positive = uphill in the running direction


@dataclass(frozen=True)
class Balise:
    id: int
    position: float  # m, surveyed position of the reference mark


@dataclass(frozen=True)
class Station:
    name: str
    position: float  # m, stopping point (the train's reference end stops here)
    dwell: float = 30.0  # s, planned dwell time (extra key)


@dataclass(frozen=True)
class SpeedLimit:
    start: float  # m
    end: float  # m
    speed: float  # m/s


@dataclass(frozen=True)
class Line:
    """The line map as the railway knows it (``line.yaml``)."""

    name: str
    length: float  # m
    balises: tuple[Balise, ...] = ()
    gradients: tuple[GradientSection, ...] = ()
    stations: tuple[Station, ...] = ()
    speed_limits: tuple[SpeedLimit, ...] = ()
    max_speed: float = 22.23  # m/s, line speed where no section limit applies (extra key)
    alert_limit: float = math.nan  # m, the largest protection level the operation on this
    #   line can use (extra key; NaN: not stated, the estimators' parameter decides)

    @cached_property
    def _gradient_table(self):
        """(starts, ends, permilles) sorted by start, as lists and arrays; None where sections
        overlap (then the last listed wins, as a loop over them decides)."""
        secs = sorted(self.gradients, key=lambda g: g.start)
        if any(b.start < a.end for a, b in zip(secs, secs[1:])):
            return None
        st, en, pm = ([g.start for g in secs], [g.end for g in secs],
                      [float(g.permille) for g in secs])
        return st, en, pm, np.array(st), np.array(en), np.array(pm)

    def gradient_permille(self, x):
        """Gradient in per mille at position(s) ``x`` (m); 0 outside every section.

        A lookup by bisection over the sections' starts: a real line has hundreds of sections
        and the simulator asks four times per integration step."""
        tab = self._gradient_table
        if tab is None:  # overlapping sections (a hand-made Line): the last listed wins
            x = np.asarray(x, dtype=float)
            out = np.zeros_like(x)
            for sec in self.gradients:
                out = np.where((x >= sec.start) & (x < sec.end), sec.permille, out)
            return out if out.ndim else float(out)
        st, en, pm, a_st, a_en, a_pm = tab
        if np.ndim(x) == 0:
            xf = float(x)
            i = bisect.bisect_right(st, xf) - 1
            return pm[i] if i >= 0 and xf < en[i] else 0.0
        x = np.asarray(x, dtype=float)
        if not st:
            return np.zeros_like(x)
        i = np.searchsorted(a_st, x, side="right") - 1
        j = np.clip(i, 0, None)
        return np.where((i >= 0) & (x < a_en[j]), a_pm[j], 0.0)

    def gradient_accel(self, x):
        """m/s^2 per unit mass: g sin(theta(x)), with tan(theta) = permille / 1000.

        The dynamics divide this by (1 + lambda): M g sin(theta) / ((1 + lambda) M).
        """
        if np.ndim(x) == 0:  # one position (the simulator's step): no array overhead
            p = self.gradient_permille(x) / 1000.0
            return G * p / math.sqrt(1.0 + p * p)
        p = np.asarray(self.gradient_permille(x), dtype=float) / 1000.0
        out = G * p / np.sqrt(1.0 + p * p)  # sin(atan(p)) without the trig calls
        return out if out.ndim else float(out)

    def speed_limit(self, x) -> float:
        """m/s, the most restrictive limit at position ``x``."""
        lim = self.max_speed
        for s in self.speed_limits:
            if s.start <= x < s.end:
                lim = min(lim, s.speed)
        return lim

    def balise_by_id(self, balise_id: int) -> Balise | None:
        for b in self.balises:
            if b.id == balise_id:
                return b
        return None

    def with_changes(self, **kw) -> Line:
        return replace(self, **kw)


# ---------------------------------------------------------------------------------------------
# Loading with validation. Extra keys are allowed (docs/interfaces.md: "extra keys"), at the top
# level, in the line's list entries and in the train's sections, and named in a warning with
# their near misses; a typo of an absent key holding that key's kind of value is an error
# (config.check_keys), and a required key stays required (`davis: {A: ...}` lacks `a`).
# ---------------------------------------------------------------------------------------------

TRAIN_KEYS = ("mass", "rotary_allowance", "davis", "brake", "odometer")
# every key the loader reads (identify writes the last) -> the kind of value it holds
TRAIN_ALL_KEYS = {"name": "string", "mass": "number", "rotary_allowance": "number",
                  "davis": "mapping", "brake": "mapping", "odometer": "mapping",
                  "balise": "mapping", "performance": "mapping", "identification": "mapping"}
LINE_KEYS = {"name": "string", "length": "number", "balises": "list", "gradients": "list",
             "stations": "list", "speed_limits": "list", "max_speed": "number",
             "alert_limit": "number", "curves": "list"}
#   curves: signed radii of an imported real line (train_core.ttobench), kept for the reader,
#   not modelled
# the entries of the line's lists: extra keys allowed there too (a station's platform, a
# section's curve radius), by the same rule
BALISE_KEYS = {"id": "integer", "position": "number"}
GRADIENT_KEYS = {"start": "number", "end": "number", "permille": "number"}
STATION_KEYS = {"name": "string", "position": "number", "dwell": "number"}
SPEED_LIMIT_KEYS = {"start": "number", "end": "number", "speed": "number"}


def _numbers(*keys) -> dict:
    return dict.fromkeys(keys, "number")


def train_from_dict(data: dict, where: str = "train.yaml") -> TrainParams:
    s = Section(data, where)
    check_top_level(s.data, TRAIN_ALL_KEYS, where)
    davis = s.section("davis", _numbers("a", "b", "c"), default=REQUIRED)
    brake = s.section("brake", _numbers("time_constant", "delay", "braking_rate"),
                      default=REQUIRED)
    odo = s.section("odometer", _numbers("speed_std", "distance_std"), default={})
    bal = s.section("balise", _numbers("position_std"), default={})
    perf = s.section("performance", _numbers("max_traction", "service_brake",
                                             "emergency_brake", "max_jerk"), default={})
    dflt = Performance()
    return TrainParams(
        name=s.string("name", "train"),
        mass=s.number("mass", REQUIRED, lo=0.0, lo_open=True, unit="kg"),
        rotary_allowance=s.number("rotary_allowance", REQUIRED, lo=0.0, hi=1.0),
        davis=Davis(
            a=davis.number("a", REQUIRED, lo=0.0, unit="N"),
            b=davis.number("b", REQUIRED, lo=0.0, unit="N s/m"),
            c=davis.number("c", REQUIRED, lo=0.0, unit="N s^2/m^2"),
        ),
        brake=Brake(
            time_constant=brake.number("time_constant", REQUIRED, lo=0.0, lo_open=True, unit="s"),
            delay=brake.number("delay", REQUIRED, lo=0.0, unit="s"),
            braking_rate=brake.number("braking_rate", 1.0, lo=0.0, hi=2.0),
        ),
        odometer_speed_std=odo.number("speed_std", 0.1, lo=0.0, unit="m/s"),
        odometer_distance_std=odo.number("distance_std", 0.0, lo=0.0, unit="m"),
        balise_position_std=bal.number("position_std", 1.0, lo=0.0, lo_open=True, unit="m"),
        performance=Performance(
            max_traction=perf.number("max_traction", dflt.max_traction, lo=0.0, lo_open=True),
            service_brake=perf.number("service_brake", dflt.service_brake, lo=0.0, lo_open=True),
            emergency_brake=perf.number(
                "emergency_brake", dflt.emergency_brake, lo=0.0, lo_open=True
            ),
            max_jerk=perf.number("max_jerk", dflt.max_jerk, lo=0.0, lo_open=True),
        ),
    )


def line_from_dict(data: dict, where: str = "line.yaml") -> Line:
    s = Section(data, where)
    check_top_level(s.data, LINE_KEYS, where)
    length = s.number("length", REQUIRED, lo=0.0, lo_open=True, unit="m")
    # positions on the line, as the stations' (a balise or a section beyond the line's end is
    # a unit slip, km for m, or a map of another line)
    balises = tuple(
        Balise(id=b.integer("id", REQUIRED, lo=0),
               position=b.number("position", REQUIRED, lo=0.0, hi=length, unit="m"))
        for b in s.sections("balises", BALISE_KEYS, default=[])
    )
    ids = [b.id for b in balises]
    if len(set(ids)) != len(ids):
        raise ConfigError(f"{where}.balises: balise ids must be unique")
    grads = []
    for g in s.sections("gradients", GRADIENT_KEYS, default=[]):
        start, end = _span(g, 0.0, length)
        grads.append(GradientSection(start, end, g.number("permille", REQUIRED, lo=-60, hi=60)))
    grads.sort(key=lambda g: g.start)
    for a, b in zip(grads, grads[1:]):
        if b.start < a.end:
            raise ConfigError(f"{where}.gradients: sections [{a.start:g}, {a.end:g}) and "
                              f"[{b.start:g}, {b.end:g}) overlap")
    stations = tuple(
        Station(
            name=st.string("name", REQUIRED),
            position=st.number("position", REQUIRED, lo=0.0, hi=length),
            dwell=st.number("dwell", 30.0, lo=0.0, unit="s"),
        )
        for st in s.sections("stations", STATION_KEYS, default=[])
    )
    limits = []
    for sl in s.sections("speed_limits", SPEED_LIMIT_KEYS, default=[]):
        start, end = _span(sl)
        limits.append(SpeedLimit(start, end, sl.number("speed", REQUIRED, lo=0.0, lo_open=True,
                                                        unit="m/s")))
    limits = tuple(limits)
    return Line(
        name=s.string("name", "line"),
        length=length,
        balises=tuple(sorted(balises, key=lambda b: b.position)),
        gradients=tuple(grads),
        stations=tuple(sorted(stations, key=lambda st: st.position)),
        speed_limits=limits,
        max_speed=s.number("max_speed", 22.23, lo=0.0, lo_open=True, unit="m/s"),
        alert_limit=_or_nan(s.number("alert_limit", None, lo=0.0, lo_open=True, unit="m")),
    )


def _span(sec: Section, lo: float | None = None, hi: float | None = None) -> tuple:
    """A section's (start, end) in m, each within [lo, hi] where given, the end after the
    start."""
    start = sec.number("start", REQUIRED, lo=lo, hi=hi, unit="m")
    end = sec.number("end", REQUIRED, lo=lo, hi=hi, unit="m")
    if end <= start:
        raise ConfigError(f"{sec.where}: end ({end:g}) must be greater than start ({start:g})")
    return start, end


def _or_nan(value) -> float:
    return math.nan if value is None else float(value)


def load_train(path: str | Path) -> TrainParams:
    return train_from_dict(load_yaml(path), str(path))


def load_line(path: str | Path) -> Line:
    return line_from_dict(load_yaml(path), str(path))


def braking_distance(v: float, decel: float) -> float:
    """m, distance to stop from ``v`` (m/s) at constant deceleration ``decel`` (m/s^2 > 0)."""
    if decel <= 0:
        return math.inf
    return v * v / (2.0 * decel)
