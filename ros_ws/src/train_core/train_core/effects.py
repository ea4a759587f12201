"""Effects: the ways the real world differs from ``line.yaml``/``train.yaml``.

One effect per cause of docs/interfaces.md's ``diagnose`` table; each is off unless the scenario
switches it on. The world runs with ``true_line``/``true_train``/``true_link`` built here with
:func:`dataclasses.replace` on the believed objects; estimators only ever get the believed ones.
Each effect changes the data in exactly one documented way:

=================  ================================================================================
effect             what changes (and nothing else, for the same seed)
=================  ================================================================================
gradient           true gradient on [start, end) = mapped gradient + ``permille`` (an unmapped
                   section when the map says 0 there). Changes the motion only.
resistance         true Davis coefficients a, b, c (N). Changes the motion only.
braking_rate       true braking rate f(t): ``linear`` from f_start at t_start to f_end at t_end
                   (Zheng eq. (23), f_k = f_0 - 0.005 k, is f_start = 1, f_end = 1 - 0.005 t_end),
                   held outside; or ``step`` from f_start to f_end at t_step. Motion only.
odometer_scale     odometer distance and speed are ``scale`` x the axle-free truth (wheel wear:
                   scale = nominal / true wheel diameter). Odometer values only.
wheel_slip         during each interval [t0, t1] the axle speed is (1 + slip_fraction) v (slip if
                   > 0, slide if < 0); the counted distance integrates the axle speed, so it keeps
                   the excess afterwards. ``fractions`` (optional): one slip fraction per
                   interval instead. ``shape`` (optional): ``step`` (default) or ``sine``, the
                   fraction rising and falling as a half sine over the interval, peaking at
                   slip_fraction mid-episode. Odometer values only.
bursty_link        both topics' links become Gilbert-Elliott with p_good_bad, p_bad_good
                   (loss_good, loss_bad default 0 and 1). Which messages are received only.
brake_delay        true transport delay (s) of *braking* commands; traction keeps train.yaml's
                   delay (the brake is its own chain, actuator.py). Motion only.
mass               true mass M (kg). The drive force is computed for the believed mass
                   (dynamics.py), so traction, braking and resistance accelerations all change.
clock_drift        the train's clock runs at rate (1 + drift): odometer and balise stamps are
                   epoch + t (1 + drift); control and ground truth stay on the reference clock
                   (true time). Stamps only.
power_limit        traction delivered at most ``p_spec`` / v (m^2/s^3, traction power per kg of
                   believed effective mass): a command a is met below the knee speed p_spec / a.
                   Braking untouched. Motion only (dynamics.py).
adhesion_section   braking delivered x ``factor`` while the train's reference point is on
                   [start, end) (m). Traction untouched. Motion only (dynamics.py).
traction_delay     true transport delay (s) of *traction* commands; braking keeps train.yaml's
                   delay (or brake_delay's). Motion only (World's actuator).
=================  ================================================================================

Pure module: PyYAML-free (validation uses :mod:`train_core.config` sections).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

from .config import REQUIRED, ConfigError, Section
from .link import LinkParams
from .model import Brake, Davis, GradientSection, Line, TrainParams


@dataclass(frozen=True)
class GradientEffect:
    start: float  # m
    end: float  # m
    permille: float  # per mille, added to the mapped gradient on [start, end)


@dataclass(frozen=True)
class ResistanceEffect:
    a: float  # N
    b: float  # N s/m
    c: float  # N s^2/m^2


@dataclass(frozen=True)
class BrakingRateEffect:
    f_start: float  # -, braking rate at t_start (linear) / before t_step (step)
    f_end: float  # -, braking rate at t_end (linear) / from t_step on (step)
    mode: str = "linear"  # "linear" or "step"
    t_start: float = 0.0  # s, start of the linear drift
    t_end: float | None = None  # s, end of the linear drift (default: scenario duration)
    t_step: float = 0.0  # s, time of the step (mode "step")

    def value(self, t: float) -> float:
        """f(t)."""
        if self.mode == "step":
            return self.f_end if t >= self.t_step else self.f_start
        t1 = self.t_end if self.t_end is not None else self.t_start
        if t <= self.t_start or t1 <= self.t_start:
            return self.f_start if t <= self.t_start else self.f_end
        if t >= t1:
            return self.f_end
        return self.f_start + (self.f_end - self.f_start) * (t - self.t_start) / (t1 - self.t_start)


@dataclass(frozen=True)
class OdometerScaleEffect:
    scale: float  # -, odometer reading / truth


@dataclass(frozen=True)
class WheelSlipEffect:
    intervals: tuple[tuple[float, float], ...]  # s, [(t0, t1), ...] episodes
    slip_fraction: float = 0.1  # -, axle speed = (1 + slip_fraction) v during an episode
    # -, one slip fraction per episode (same order as ``intervals``); empty: ``slip_fraction``
    # in every episode
    fractions: tuple[float, ...] = ()
    # "step": the fraction holds over the whole episode, from its first instant to its last;
    # "sine": it builds up and dies away as a half sine, the fraction its peak (mid-episode), as
    # adhesion is lost and regained over the episode rather than at once
    shape: str = "step"

    def __post_init__(self):
        if self.shape not in ("step", "sine"):
            raise ValueError(f"wheel_slip shape: unknown {self.shape!r} (step or sine)")

    def fraction(self, i: int) -> float:
        """-, the slip fraction of episode ``i`` (its peak with ``shape`` "sine")."""
        return self.fractions[i] if self.fractions else self.slip_fraction

    def factor(self, t: float) -> float:
        for i, (t0, t1) in enumerate(self.intervals):
            if t0 <= t < t1:
                g = 1.0 if self.shape == "step" else math.sin(math.pi * (t - t0) / (t1 - t0))
                return 1.0 + self.fraction(i) * g
        return 1.0


@dataclass(frozen=True)
class BurstyLinkEffect:
    p_good_bad: float  # -, per message
    p_bad_good: float  # -, per message
    loss_good: float = 0.0  # -
    loss_bad: float = 1.0  # -


@dataclass(frozen=True)
class BrakeDelayEffect:
    delay: float  # s, true transport delay T


@dataclass(frozen=True)
class MassEffect:
    mass: float  # kg, true total mass


@dataclass(frozen=True)
class ClockDriftEffect:
    drift: float  # s per s: train stamp = t (1 + drift)


@dataclass(frozen=True)
class Effects:
    """All effects of a scenario; None = off."""

    gradient: GradientEffect | None = None
    resistance: ResistanceEffect | None = None
    braking_rate: BrakingRateEffect | None = None
    odometer_scale: OdometerScaleEffect | None = None
    wheel_slip: WheelSlipEffect | None = None
    bursty_link: BurstyLinkEffect | None = None
    brake_delay: BrakeDelayEffect | None = None
    mass: MassEffect | None = None
    clock_drift: ClockDriftEffect | None = None
    power_limit: PowerLimitEffect | None = None
    adhesion_section: AdhesionSectionEffect | None = None
    traction_delay: TractionDelayEffect | None = None

    def active(self) -> list[str]:
        return [f.name for f in fields(self) if getattr(self, f.name) is not None]


EFFECT_NAMES = tuple(f.name for f in fields(Effects))


# ------------------------------------------------------------------------------------------------
# The true world from the believed one
# ------------------------------------------------------------------------------------------------

def true_line(line: Line, eff: Effects) -> Line:
    """The line with the unmapped gradient section added (piecewise constant, re-split)."""
    g = eff.gradient
    if g is None:
        return line
    cuts = sorted({g.start, g.end, *(s.start for s in line.gradients),
                   *(s.end for s in line.gradients)})
    sections = []
    for a, b in zip(cuts, cuts[1:]):
        mid = 0.5 * (a + b)
        value = float(line.gradient_permille(mid)) + (g.permille if g.start <= mid < g.end else 0)
        if value != 0.0 or any(s.start <= mid < s.end for s in line.gradients):
            sections.append(GradientSection(a, b, value))
    return replace(line, gradients=tuple(sections))


def true_train(train: TrainParams, eff: Effects) -> TrainParams:
    t = train
    if eff.resistance is not None:
        r = eff.resistance
        t = replace(t, davis=Davis(r.a, r.b, r.c))
    brake = t.brake  # brake_delay is not here: it delays braking only (World's actuator)
    if eff.braking_rate is not None:
        brake = replace(brake, braking_rate=eff.braking_rate.f_start)
    if brake is not t.brake:
        t = replace(t, brake=Brake(brake.time_constant, brake.delay, brake.braking_rate))
    if eff.mass is not None:
        t = replace(t, mass=eff.mass.mass)
    return t


def true_link(link: LinkParams, eff: Effects) -> LinkParams:
    b = eff.bursty_link
    if b is None:
        return link
    return replace(link, model="gilbert_elliott", p_good_bad=b.p_good_bad,
                   p_bad_good=b.p_bad_good, loss_good=b.loss_good, loss_bad=b.loss_bad)


def drive_effects(eff: Effects) -> dict:
    """The :class:`~train_core.motion.Motion` keywords of the effects on the delivered drive
    (power limit, adhesion section)."""
    return {"p_spec": eff.power_limit.p_spec if eff.power_limit else None,
            "adhesion": eff.adhesion_section.as_tuple() if eff.adhesion_section else None}


def replay_effects(eff: Effects) -> dict:
    """The :func:`~train_core.motion.replay` keywords of the effects on the actuators (brake
    and traction delays, the braking-rate schedule) and on the delivered drive: what the world
    runs beyond the true train and line, so that a replay of recorded commands (diagnose's
    held-out gain) moves as the simulator would."""
    return {"brake_delay": eff.brake_delay.delay if eff.brake_delay else None,
            "braking_rate_of_t": eff.braking_rate.value if eff.braking_rate else None,
            "traction_delay": eff.traction_delay.delay if eff.traction_delay else None,
            **drive_effects(eff)}


def braking_rate_at(eff: Effects, train: TrainParams, t: float) -> float:
    """True braking rate f(t): the effect's schedule, else the (true) train's braking_rate."""
    if eff.braking_rate is not None:
        return eff.braking_rate.value(t)
    return train.brake.braking_rate


# ------------------------------------------------------------------------------------------------
# Parsing (strict: unknown effect, unknown field, missing key, out-of-range value)
# ------------------------------------------------------------------------------------------------

def parse_effects(sec: Section, duration: float) -> Effects:
    """Effects from the scenario's ``effects:`` mapping ({name: {parameters}})."""
    for name in sec.data:
        if name not in EFFECT_NAMES:
            raise ConfigError(f"{sec.where}: unknown effect '{name}' "
                              f"(allowed: {', '.join(EFFECT_NAMES)})")
    kw = {}
    if sec.has("gradient"):
        s = sec.section("gradient", ("start", "end", "permille"))
        start, end = s.number("start", REQUIRED, lo=0.0, unit="m"), s.number("end", REQUIRED)
        if end <= start:
            raise ConfigError(f"{s.where}.end: {end:g} must be greater than start ({start:g})")
        kw["gradient"] = GradientEffect(start, end,
                                        s.number("permille", REQUIRED, lo=-60.0, hi=60.0))
    if sec.has("resistance"):
        s = sec.section("resistance", ("a", "b", "c"))
        kw["resistance"] = ResistanceEffect(s.number("a", REQUIRED, lo=0.0, unit="N"),
                                            s.number("b", REQUIRED, lo=0.0, unit="N s/m"),
                                            s.number("c", REQUIRED, lo=0.0, unit="N s^2/m^2"))
    if sec.has("braking_rate"):
        s = sec.section("braking_rate",
                        ("f_start", "f_end", "mode", "t_start", "t_end", "t_step"))
        mode = s.string("mode", "linear", choices=("linear", "step"))
        t_start = s.number("t_start", 0.0, lo=0.0, unit="s")
        t_end = s.number("t_end", duration, lo=t_start, unit="s")
        kw["braking_rate"] = BrakingRateEffect(
            f_start=s.number("f_start", REQUIRED, lo=0.0, hi=2.0),
            f_end=s.number("f_end", REQUIRED, lo=0.0, hi=2.0),
            mode=mode, t_start=t_start, t_end=t_end,
            t_step=s.number("t_step", REQUIRED if mode == "step" else 0.0, lo=0.0, unit="s"))
    if sec.has("odometer_scale"):
        s = sec.section("odometer_scale", ("scale",))
        kw["odometer_scale"] = OdometerScaleEffect(
            s.number("scale", REQUIRED, lo=0.5, hi=1.5))
    if sec.has("wheel_slip"):
        s = sec.section("wheel_slip", ("intervals", "slip_fraction", "fractions", "shape"))
        ivs = s.intervals("intervals", REQUIRED)
        kw["wheel_slip"] = WheelSlipEffect(
            intervals=ivs, slip_fraction=s.number("slip_fraction", 0.1, lo=-0.9, hi=1.0),
            fractions=_slip_fractions(s, ivs),
            shape=s.string("shape", "step", choices=("step", "sine")))
    if sec.has("bursty_link"):
        s = sec.section("bursty_link", ("p_good_bad", "p_bad_good", "loss_good", "loss_bad"))
        kw["bursty_link"] = BurstyLinkEffect(
            p_good_bad=s.number("p_good_bad", REQUIRED, lo=0.0, hi=1.0),
            p_bad_good=s.number("p_bad_good", REQUIRED, lo=0.0, hi=1.0, lo_open=True),
            loss_good=s.number("loss_good", 0.0, lo=0.0, hi=1.0),
            loss_bad=s.number("loss_bad", 1.0, lo=0.0, hi=1.0))
    if sec.has("brake_delay"):
        s = sec.section("brake_delay", ("delay",))
        kw["brake_delay"] = BrakeDelayEffect(s.number("delay", REQUIRED, lo=0.0, hi=10.0,
                                                      unit="s"))
    if sec.has("mass"):
        s = sec.section("mass", ("mass",))
        kw["mass"] = MassEffect(s.number("mass", REQUIRED, lo=0.0, lo_open=True, unit="kg"))
    if sec.has("clock_drift"):
        s = sec.section("clock_drift", ("drift",))
        kw["clock_drift"] = ClockDriftEffect(s.number("drift", REQUIRED, lo=-0.1, hi=0.1,
                                                      unit="s/s"))
    _parse_drive_effects(sec, kw)
    return Effects(**kw)


# ------------------------------------------------------------------------------------------------
# Effects on the delivered drive and the traction chain
# ------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class PowerLimitEffect:
    """Traction limited by power: the traction acceleration delivered is at most p_spec / v, so a
    command a is met below the knee speed p_spec / a (dynamics.py)."""

    p_spec: float  # m^2/s^3, traction power per kg of believed effective mass


@dataclass(frozen=True)
class AdhesionSectionEffect:
    """Braking weaker on a stretch of track: the braking acceleration delivered is x ``factor``
    while the train's reference point is on [start, end) (dynamics.py)."""

    start: float  # m, track position
    end: float  # m, track position
    factor: float  # -, braking-rate multiplier on [start, end)

    def as_tuple(self) -> tuple[float, float, float]:
        return (self.start, self.end, self.factor)


@dataclass(frozen=True)
class TractionDelayEffect:
    """Traction commands take effect ``delay`` after they are issued (braking keeps its own)."""

    delay: float  # s, true transport delay of traction commands


def _parse_drive_effects(sec: Section, kw: dict) -> None:
    if sec.has("power_limit"):
        s = sec.section("power_limit", ("p_spec",))
        kw["power_limit"] = PowerLimitEffect(s.number("p_spec", REQUIRED, lo=0.0, lo_open=True,
                                                      unit="m^2/s^3"))
    if sec.has("adhesion_section"):
        s = sec.section("adhesion_section", ("start", "end", "factor"))
        start, end = s.number("start", REQUIRED, lo=0.0, unit="m"), s.number("end", REQUIRED)
        if end <= start:
            raise ConfigError(f"{s.where}.end: {end:g} must be greater than start ({start:g})")
        kw["adhesion_section"] = AdhesionSectionEffect(
            start, end, s.number("factor", REQUIRED, lo=0.0, hi=2.0))
    if sec.has("traction_delay"):
        s = sec.section("traction_delay", ("delay",))
        kw["traction_delay"] = TractionDelayEffect(s.number("delay", REQUIRED, lo=0.0, hi=10.0,
                                                            unit="s"))
# Writing (the inverse of parse_effects: what is written parses back to the same effects)
# ------------------------------------------------------------------------------------------------

def _slip_fractions(s, ivs) -> tuple[float, ...]:
    """wheel_slip's optional ``fractions``: one number in [-0.9, 1] per interval, in the order
    the intervals are written (they are sorted by start, and the fractions with them)."""
    raw = s.data.get("fractions")
    if raw is None:
        return ()
    ivs_raw = s.data.get("intervals")
    ok = isinstance(raw, list) and len(raw) == len(ivs) and all(
        isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
        and -0.9 <= x <= 1.0 for x in raw)
    if not ok:
        raise ConfigError(f"{s.where}.fractions: expected one number in [-0.9, 1] per interval "
                          f"({len(ivs)}), got {raw!r}")
    order = sorted(range(len(raw)), key=lambda i: (float(ivs_raw[i][0]), float(ivs_raw[i][1])))
    return tuple(float(raw[i]) for i in order)


def effect_to_dict(effect) -> dict:
    """One effect's parameters in the scenario's ``effects:`` syntax (plain YAML types); a
    field at its dataclass default is left out, as :func:`parse_effects` fills it in."""
    from dataclasses import MISSING

    out = {}
    for f in fields(effect):
        v = getattr(effect, f.name)
        if f.default is not MISSING and v == f.default:
            continue
        out[f.name] = _plain(v)
    return out


def effects_to_dict(eff: Effects) -> dict:
    """A scenario's ``effects:`` mapping ({name: {parameters}}) of every active effect."""
    return {name: effect_to_dict(getattr(eff, name)) for name in eff.active()}


def _plain(v):
    if v is None or isinstance(v, str | bool):
        return v
    if isinstance(v, tuple | list):
        return [_plain(x) for x in v]
    return float(v)
