"""Effects outside the causes list, for tests: what a diagnosis must not explain by a listed cause.

Every cause that ``diagnose`` knows (the table in docs/interfaces.md) has an effect in
:mod:`train_core.effects`. The effects here are deliberately none of them, nor the power limit,
the traction delay or the adhesion section: each is a physical difference that no listed cause
describes, and each is confined in a different way, so that a check "no listed cause is
confirmed" meets every kind of structure a residual can have:

===================  ======================  ==================================================
effect               where it shows          what the world does
===================  ======================  ==================================================
``tunnel_drag``      in a place              extra aerodynamic resistance c v^2 (N) while the
                                             train's reference point is on [start, end): a
                                             tunnel. Not a gradient (it grows with speed), not
                                             the Davis c (it acts on one stretch only).
``brake_fade``       at some speeds          braking delivered x ``factor`` while v < ``v_fade``
                                             (the electric brake fading at low speed before the
                                             friction brake takes over). Not braking_rate (it
                                             holds at every speed) nor an adhesion section (it
                                             holds at every place).
``traction_gain``    in one phase            traction delivered x ``factor`` (a motor car cut
                                             out), at every speed and place; braking untouched.
                                             Not mass (which scales braking and resistance too),
                                             not a power limit (no knee in speed).
``wind``             in time                 a constant extra force ``force`` (N, > 0 against
                                             the motion) on [t0, t1) of true time (a gust
                                             front). Not a gradient (it is not tied to a place)
                                             nor resistance (it does not depend on speed).
``traction_fade``    at some speeds, in      traction delivered x ``factor`` while v >
                     traction                ``v_fade`` (a motor's field-weakening range
                                             derated). Not a power limit (a step at v_fade, not
                                             p_spec / v), nor mass or resistance (braking and
                                             coasting untouched).
``neutral_section``  in a place, in          traction delivered x ``factor`` while the train is
                     traction                on [start, end) (a stretch fed at a low voltage, a
                                             phase break). Not a gradient (coasting and braking
                                             there are untouched; it scales with the command).
``odometer_rescale``  from a time on          the odometer counts ``factor`` times the distance
                                             and speed from true time ``t0`` on (it moved to an
                                             axle with other wheels). Not an odometer scale (one
                                             scale for the whole run) nor slip (it persists).
``load_change``      from a time on, in          traction delivered x ``factor`` from true time
                     traction                    ``t0`` on (passengers boarded at a stop: the
                                                 same motors move more mass; the brake is
                                                 load-weighed, so braking is untouched). Not mass
                                                 (one mass for the whole run, braking too) nor
                                                 a traction delay or power limit.
``coast_drag``       in coasting                 an extra deceleration ``decel`` (m/s^2) while
                                                 neither traction nor braking is delivered and
                                                 the train moves (the motors' drag, or a light
                                                 electric brake the coasting notch applies). Not
                                                 resistance nor a gradient (traction and braking
                                                 are untouched).
``hunting_drag``     at some speeds, in every      an extra resistance ``force`` (N) while the train
                     phase                         runs faster than ``v_crit`` (a bogie hunting:
                                                   the wheelsets' lateral oscillation above a
                                                   critical speed dissipates energy). Not
                                                   resistance (a step at a speed, not the Davis
                                                   curve), nor a power limit (braking and
                                                   coasting too).
``resistance_warmup`` in time, in every     an extra resistance ``force`` x exp(-(t - t0) /
                     phase                   ``tau``) (N) from true time ``t0`` on (axle
                                             bearings and gearboxes run in cold: their drag
                                             falls as they warm). Not resistance (the Davis
                                             curve holds for the whole run) nor a gradient.
``odometer_bias``    while moving            the odometer reads ``bias`` (m/s) more speed than
                                             the axle turns while the train moves, and counts
                                             it into the distance (a radar's offset). Not an
                                             odometer scale (the same m/s at every speed) nor
                                             slip (it persists).
``odometer_speed_scale`` at some speeds     the odometer reads (1 + ``k`` v / ``v_ref``) times
                                             the train's speed and counts it (a radar whose
                                             error grows with speed). Not an odometer scale
                                             (one factor at every speed) nor slip.
``brake_power_limit`` at some speeds, in     the braking delivered is at most ``p`` / v
                     braking                 (m/s^2; an electric brake limited by the power it
                                             can return, without a friction blend above it).
                                             Not braking_rate (full braking below the knee) nor
                                             an adhesion section (every place).
``traction_trip``    in time, in traction    traction delivered x ``factor`` on [t0, t1) of
                                             true time (a converter tripped, then reset). Not
                                             mass nor a traction delay (it ends).
``clock_step``       from a time on          the train's clock reads ``step`` s more from true
                                             time ``t0`` on (set by hand, or by a time server
                                             after an outage). Not clock drift (a rate, not a
                                             jump) nor a delay of the commands (both
                                             phases, and it does not end).
``clock_slew``       from a time on          the train's clock runs ``rate`` s/s faster from
                                             true time ``t0`` on (a time server slewing it
                                             towards the reference). Not clock drift (one
                                             rate for the run) nor a step.
``misplaced_balise``  at one balise           the balise lies ``offset`` m from the position the
                                             map and its telegram give (a survey error): read
                                             there, it reports the map's position. Not an
                                             odometer scale (one reading, not a drift with
                                             distance) nor slip (the readings after it agree).
===================  ======================  ==================================================

The bench (:mod:`train_sim.unlisted_cases`) uses the first four; the others are kept for
tests, so that a test does not only mirror the bench.

Use: ``scenario.with_changes(unlisted=Unlisted(wind=Wind(120.0, 180.0, 9000.0)))``; the world
(``simulate``, ``generate``) runs them through the hooks of :class:`train_core.dynamics.Dynamics`
(delivered traction/braking parts; extra deceleration), a misplaced balise through the balise
reader's trigger positions (:func:`balise_moves`), an odometer rescale through the world's
odometer factor (:func:`odometer_factor`). They are not parsed from scenario files
(they exist to be hidden from the tools under test). Only the motion, the place where a balise
is read and what the odometer counts change; sensor noise and link draws stay those of the same
seed without them.

Pure module: standard library only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from train_core.model import TrainParams


@dataclass(frozen=True)
class TunnelDrag:
    start: float  # m, track position where the extra drag begins
    end: float  # m, where it ends
    c: float  # N/(m/s)^2, extra resistance c v^2 on [start, end)


@dataclass(frozen=True)
class BrakeFade:
    v_fade: float  # m/s, braking is weaker below this speed
    factor: float  # -, multiplier of the delivered braking below v_fade


@dataclass(frozen=True)
class TractionGain:
    factor: float  # -, multiplier of the delivered traction


@dataclass(frozen=True)
class Wind:
    t0: float  # s, true time the force starts
    t1: float  # s, true time it stops
    force: float  # N, extra force against the motion (negative: tail wind)


@dataclass(frozen=True)
class TractionFade:
    v_fade: float  # m/s, traction is weaker above this speed
    factor: float  # -, multiplier of the delivered traction above v_fade


@dataclass(frozen=True)
class NeutralSection:
    start: float  # m, track position where the traction is weaker
    end: float  # m, where it ends
    factor: float  # -, multiplier of the delivered traction on [start, end)


@dataclass(frozen=True)
class OdometerRescale:
    t0: float  # s, true time from which the odometer counts differently
    factor: float  # -, multiplier of the distance and speed it counts from t0 on


@dataclass(frozen=True)
class LoadChange:
    t0: float  # s, true time from which the traction moves more (or less) load
    factor: float  # -, multiplier of the delivered traction from t0 on


@dataclass(frozen=True)
class CoastDrag:
    decel: float  # m/s^2, extra deceleration while coasting (moving, no traction or braking)


@dataclass(frozen=True)
class HuntingDrag:
    v_crit: float  # m/s, the critical speed above which the bogies hunt
    force: float  # N, extra resistance above v_crit


@dataclass(frozen=True)
class MisplacedBalise:
    balise_id: int  # the balise (its id in line.yaml)
    offset: float  # m, where it lies minus where the map and its telegram say


@dataclass(frozen=True)
class ResistanceWarmup:
    t0: float  # s, true time the warm-up starts (the run's start)
    tau: float  # s, time constant of the decay
    force: float  # N, extra resistance at t0


@dataclass(frozen=True)
class OdometerBias:
    bias: float  # m/s, speed the odometer reads (and counts) beyond the train's while moving


@dataclass(frozen=True)
class OdometerSpeedScale:
    k: float  # -, the odometer's relative error at v_ref (0 at standstill, linear in speed)
    v_ref: float  # m/s


@dataclass(frozen=True)
class BrakePowerLimit:
    p: float  # m^2/s^3, the braking delivered (m/s^2) is at most p / v


@dataclass(frozen=True)
class TractionTrip:
    t0: float  # s, true time the traction drops
    t1: float  # s, true time it is restored
    factor: float  # -, multiplier of the delivered traction on [t0, t1)


@dataclass(frozen=True)
class ClockStep:
    t0: float  # s, true time the train's clock jumps
    step: float  # s, what it reads more from t0 on (negative: it jumps back)


@dataclass(frozen=True)
class ClockSlew:
    t0: float  # s, true time the clock's rate changes
    rate: float  # s/s, what the clock runs faster from t0 on (negative: slower)


@dataclass(frozen=True)
class Unlisted:
    """The test effects of one run; None = off."""

    tunnel_drag: TunnelDrag | None = None
    brake_fade: BrakeFade | None = None
    traction_gain: TractionGain | None = None
    wind: Wind | None = None
    traction_fade: TractionFade | None = None
    neutral_section: NeutralSection | None = None
    misplaced_balise: MisplacedBalise | None = None
    odometer_rescale: OdometerRescale | None = None
    load_change: LoadChange | None = None
    coast_drag: CoastDrag | None = None
    hunting_drag: HuntingDrag | None = None
    resistance_warmup: ResistanceWarmup | None = None
    odometer_bias: OdometerBias | None = None
    odometer_speed_scale: OdometerSpeedScale | None = None
    brake_power_limit: BrakePowerLimit | None = None
    traction_trip: TractionTrip | None = None
    clock_step: ClockStep | None = None
    clock_slew: ClockSlew | None = None


# coast_drag acts while the train moves faster than this (m/s) with less than COAST_DRIVE (m/s^2)
# of traction and of braking delivered
COAST_MIN_SPEED = 0.5
COAST_DRIVE = 0.01


def odometer_factor(unlisted: Unlisted | None, t: float) -> float:
    """The multiplier of what the odometer counts at true time ``t`` (1 without a rescale)."""
    r = unlisted.odometer_rescale if unlisted is not None else None
    return r.factor if r is not None and t >= r.t0 else 1.0


def odometer_bias(unlisted: Unlisted | None, v: float) -> float:
    """m/s the odometer reads beyond the train's speed ``v``: a bias while the train moves
    faster than COAST_MIN_SPEED, and a speed scale's k v^2 / v_ref (0 without either)."""
    if unlisted is None:
        return 0.0
    b, sc = unlisted.odometer_bias, unlisted.odometer_speed_scale
    out = b.bias if b is not None and v > COAST_MIN_SPEED else 0.0
    return out + (sc.k * v * v / sc.v_ref if sc is not None else 0.0)


def clock_step(unlisted: Unlisted | None, t: float) -> float:
    """s the train's clock reads more at true time ``t`` than its epoch and drift say (0
    without a step or a slew)."""
    if unlisted is None:
        return 0.0
    c, w = unlisted.clock_step, unlisted.clock_slew
    out = c.step if c is not None and t >= c.t0 else 0.0
    return out + (w.rate * (t - w.t0) if w is not None and t >= w.t0 else 0.0)


def balise_moves(unlisted: Unlisted | None) -> dict:
    """balise id -> m it lies from its map position (the balise reader's ``moved``)."""
    mb = unlisted.misplaced_balise if unlisted is not None else None
    return {} if mb is None else {int(mb.balise_id): float(mb.offset)}


def unlisted_hooks(unlisted: Unlisted | None, true_train: TrainParams) -> dict:
    """The ``drive_hook``/``resist_hook`` keywords of :class:`train_core.motion.Motion` for
    ``unlisted`` on ``true_train`` (forces in N become decelerations over its effective mass)."""
    if unlisted is None:
        return {}
    out = {}
    fade, gain = unlisted.brake_fade, unlisted.traction_gain
    tfade, neutral = unlisted.traction_fade, unlisted.neutral_section
    load, coast = unlisted.load_change, unlisted.coast_drag
    bpl, trip = unlisted.brake_power_limit, unlisted.traction_trip
    if any(e is not None for e in (fade, gain, tfade, neutral, load, coast, bpl, trip)):
        g = gain.factor if gain is not None else 1.0

        def drive_hook(t, x, v, a_tr, a_br):
            if fade is not None and v < fade.v_fade:
                a_br = fade.factor * a_br
            k = g
            if tfade is not None and v > tfade.v_fade:
                k *= tfade.factor
            if neutral is not None and neutral.start <= x < neutral.end:
                k *= neutral.factor
            if load is not None and t >= load.t0:
                k *= load.factor
            if trip is not None and trip.t0 <= t < trip.t1:
                k *= trip.factor
            if bpl is not None and v > 0.0 and -a_br * v > bpl.p:
                a_br = -bpl.p / v
            if coast is not None and v > COAST_MIN_SPEED and a_tr < COAST_DRIVE \
                    and a_br > -COAST_DRIVE:
                a_br = a_br - coast.decel
            return k * a_tr, a_br

        out["drive_hook"] = drive_hook
    tun, wind, hunt = unlisted.tunnel_drag, unlisted.wind, unlisted.hunting_drag
    warm = unlisted.resistance_warmup
    if tun is not None or wind is not None or hunt is not None or warm is not None:
        m_eff = true_train.effective_mass

        def resist_hook(t, x, v):
            f = 0.0
            if tun is not None and tun.start <= x < tun.end:
                f += tun.c * v * v
            if wind is not None and wind.t0 <= t < wind.t1 and v > 0.0:
                f += wind.force
            if hunt is not None and v > hunt.v_crit:
                f += hunt.force
            if warm is not None and t >= warm.t0 and v > 0.0:
                f += warm.force * math.exp(-(t - warm.t0) / warm.tau)
            return f / m_eff

        out["resist_hook"] = resist_hook
    return out
