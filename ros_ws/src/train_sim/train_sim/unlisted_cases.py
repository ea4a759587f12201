"""Test cases with an effect outside the causes list: a nominal :func:`train_sim.cases.make_case`
(varied line, train, link, clock and driver) with one :mod:`train_sim.unlisted` effect placed
where the run exercises it (from a pilot run of the nominal case).

    case = unlisted_case(np.random.default_rng(7), "brake_fade")
    case.scenario        # the scenario with the effect (Scenario.unlisted)
    case.kind, case.phase, case.truth

Sizes are those of a plain listed effect (an extra deceleration of 0.04-0.08 m/s^2 where the
effect acts; 20-30 % of the traction or of the low-speed braking):

===================  =================================================  ==============
kind                 placement and size                                  phase
===================  =================================================  ==============
``tunnel_drag``      a 500-900 m stretch run at > 60 % of the top       all
                     speed; c v^2 = 0.04-0.08 m/s^2 x M_eff at the
                     stretch's mean speed
``brake_fade``       v_fade at 35-50 % of the top speed, factor         braking
                     0.6-0.75
``traction_gain``    factor 0.7-0.8 or 1.2-1.3                          traction
``wind``             60-120 s while moving, +-0.04-0.08 m/s^2 x M_eff   all
===================  =================================================  ==============

Two further kinds (:data:`TEST_KINDS`) are for tests only, so that a test does not only mirror
the bench:

===================  =================================================  ==============
``traction_fade``    above 40-60 % of the top speed, factor 0.6-0.75    traction
``neutral_section``  a 300-600 m stretch where the train accelerates    traction
                     (> 0.15 m/s^2 at > 3 m/s), factor 0.4-0.6
``odometer_rescale`` from the time the train has run 30-60 % of the      all
                     run's distance on, factor 1 +- 0.01-0.02
``load_change``      from the departure of a stop the run makes         traction
                     between 30 and 70 % of its time, factor 0.8-0.88
                     or 1.12-1.2
``coast_drag``       0.04-0.08 m/s^2 while coasting (a case whose run   coasting
                     coasts for at least 20 s is drawn)
``hunting_drag``     above 60-80 % of the top speed, 0.04-0.08 m/s^2     all
                     x M_eff
``resistance_warmup`` from the run's start, tau 20-35 % of the run's    all
                     time, 0.06-0.12 m/s^2 x M_eff at the start
``odometer_bias``    +-0.04-0.1 m/s while moving                          all
``odometer_speed_scale`` k +-1-2 % at the top speed                        all
``brake_power_limit`` the knee at 45-65 % of the top speed for the run's   braking
                     median braking command
``traction_trip``    60-120 s from a traction onset between 20 and 70 %  traction
                     of the run's time, factor 0.4-0.6
``clock_step``       +-0.5-3 s at a time between 30 and 70 % of the run   all
``clock_slew``       +-0.5-2 ms/s from a time between 20 and 50 % of      all
                     the run
``misplaced_balise`` a balise the run passes at > 3 m/s with balises    all
                     passed before and after it, +-8-20 m from its
                     map position
===================  =================================================  ==============

``phase`` is the phase ``diagnose``'s ``unexplained`` signature should name.

Pure module: numpy + train_sim / train_core (no ROS). Same generator state -> same case.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .cases import Case, make_case
from .unlisted import (
    BrakeFade,
    BrakePowerLimit,
    ClockSlew,
    ClockStep,
    CoastDrag,
    HuntingDrag,
    LoadChange,
    MisplacedBalise,
    NeutralSection,
    OdometerBias,
    OdometerRescale,
    OdometerSpeedScale,
    ResistanceWarmup,
    TractionFade,
    TractionGain,
    TractionTrip,
    TunnelDrag,
    Unlisted,
    Wind,
)

KINDS = ("tunnel_drag", "brake_fade", "traction_gain", "wind")
TEST_KINDS = ("traction_fade", "neutral_section", "misplaced_balise", "odometer_rescale",
              "load_change", "coast_drag", "hunting_drag", "resistance_warmup",
              "odometer_bias", "brake_power_limit", "traction_trip", "clock_step",
              "clock_slew", "odometer_speed_scale")
PHASE = {"tunnel_drag": "all", "brake_fade": "braking", "traction_gain": "traction",
         "wind": "all", "traction_fade": "traction", "neutral_section": "traction",
         "misplaced_balise": "all", "odometer_rescale": "all", "load_change": "traction",
         "coast_drag": "coasting", "hunting_drag": "all", "resistance_warmup": "all",
         "odometer_bias": "all", "brake_power_limit": "braking", "traction_trip": "traction",
         "clock_step": "all", "clock_slew": "all", "odometer_speed_scale": "all"}


@dataclass(frozen=True)
class UnlistedCase:
    case: Case  # the nominal case (line, train, scenario files; no listed effect)
    scenario: object  # the case's scenario with the unlisted effect
    kind: str
    phase: str  # the phase the effect acts in (traction, braking or all)
    truth: dict  # the effect's parameters

    def write(self, directory):
        """line.yaml and train.yaml (the believed model) as Case.write."""
        return self.case.write(directory)


def unlisted_case(rng: np.random.Generator, kind: str, pilot=None) -> UnlistedCase:
    """A random nominal case with the unlisted effect ``kind`` (one of :data:`KINDS` or
    :data:`TEST_KINDS`)."""
    if kind not in KINDS + TEST_KINDS:
        raise ValueError(f"kind must be one of {KINDS + TEST_KINDS}, got {kind!r}")
    if pilot is None:
        from .world import simulate as pilot
    while True:
        case = make_case(rng, None, "plain")
        sc = case.scenario
        sim = pilot(sc)
        # a coasting drag needs a run that coasts (moving, neither traction nor braking
        # commanded) long enough to show it; another case is drawn from the same generator
        if kind != "coast_drag" or _coasting_time(sim) >= 20.0:
            break
    tr = sim.truth
    t, x, v = tr["t"], tr["position"], tr["velocity"]
    v_top = float(np.max(v))
    m_eff = sc.true_train.effective_mass
    eff_rng = np.random.default_rng(rng.integers(2**63))
    a = float(eff_rng.uniform(0.04, 0.08))  # m/s^2
    if kind == "tunnel_drag":
        fast = np.flatnonzero(v > 0.6 * v_top)
        i = int(fast[eff_rng.integers(fast.size)])
        length = float(eff_rng.uniform(500.0, 900.0))
        start = float(np.clip(x[i] - 0.5 * length, x.min(), x.max() - length))
        inside = (x >= start) & (x < start + length)
        v_in = float(np.mean(v[inside])) if inside.any() else v_top
        eff = TunnelDrag(round(start, 1), round(start + length, 1),
                         round(a * m_eff / max(v_in, 1.0) ** 2, 3))
        u = Unlisted(tunnel_drag=eff)
    elif kind == "brake_fade":
        eff = BrakeFade(round(float(eff_rng.uniform(0.35, 0.5)) * v_top, 2),
                        round(float(eff_rng.uniform(0.6, 0.75)), 3))
        u = Unlisted(brake_fade=eff)
    elif kind == "traction_gain":
        f = float(eff_rng.uniform(0.2, 0.3))
        eff = TractionGain(round(1.0 + f if eff_rng.random() < 0.5 else 1.0 - f, 3))
        u = Unlisted(traction_gain=eff)
    elif kind == "traction_fade":
        eff = TractionFade(round(float(eff_rng.uniform(0.4, 0.6)) * v_top, 2),
                           round(float(eff_rng.uniform(0.6, 0.75)), 3))
        u = Unlisted(traction_fade=eff)
    elif kind == "neutral_section":
        acc = np.gradient(v, t)
        ok = np.flatnonzero((acc > 0.15) & (v > 3.0))
        i = int(ok[eff_rng.integers(ok.size)])
        length = float(eff_rng.uniform(300.0, 600.0))
        start = float(x[i]) - 0.3 * length
        eff = NeutralSection(round(start, 1), round(start + length, 1),
                             round(float(eff_rng.uniform(0.4, 0.6)), 3))
        u = Unlisted(neutral_section=eff)
    elif kind == "odometer_rescale":
        # from the time the train has run 30-60 % of the run's distance: the rest of the run
        # (at least 40 % of it, with its balises) is counted differently
        frac = float(eff_rng.uniform(0.3, 0.6))
        t0 = float(t[np.searchsorted(x, x[0] + frac * (x[-1] - x[0]))])
        sign = 1.0 if eff_rng.random() < 0.5 else -1.0
        eff = OdometerRescale(round(t0, 1),
                              round(1.0 + sign * float(eff_rng.uniform(0.01, 0.02)), 4))
        u = Unlisted(odometer_rescale=eff)
    elif kind == "load_change":
        # the departure from a stop in the middle of the run: the first time after a
        # standstill of 10 s or more, between 30 and 70 % of the run's time
        still = v < 0.05
        dep = np.flatnonzero(still[:-1] & ~still[1:]) + 1
        span = t[-1] - t[0]
        mid = [i for i in dep if 0.3 * span <= t[i] - t[0] <= 0.7 * span]
        if not mid:
            raise RuntimeError("no stop in the middle of the run")
        i = int(mid[eff_rng.integers(len(mid))])
        f = float(eff_rng.uniform(0.12, 0.2))
        eff = LoadChange(round(float(t[i]) - 1.0, 1),
                         round(1.0 - f if eff_rng.random() < 0.5 else 1.0 + f, 3))
        u = Unlisted(load_change=eff)
    elif kind == "coast_drag":
        eff = CoastDrag(round(a, 4))
        u = Unlisted(coast_drag=eff)
    elif kind == "hunting_drag":
        eff = HuntingDrag(round(float(eff_rng.uniform(0.6, 0.8)) * v_top, 2), round(a * m_eff, 1))
        u = Unlisted(hunting_drag=eff)
    elif kind == "resistance_warmup":
        span = float(t[-1] - t[0])
        eff = ResistanceWarmup(round(float(t[0]), 1),
                               round(float(eff_rng.uniform(0.2, 0.35)) * span, 1),
                               round(1.5 * a * m_eff, 1))
        u = Unlisted(resistance_warmup=eff)
    elif kind == "odometer_bias":
        sign = 1.0 if eff_rng.random() < 0.5 else -1.0
        eff = OdometerBias(round(sign * float(eff_rng.uniform(0.04, 0.1)), 3))
        u = Unlisted(odometer_bias=eff)
    elif kind == "odometer_speed_scale":
        sign = 1.0 if eff_rng.random() < 0.5 else -1.0
        eff = OdometerSpeedScale(round(sign * float(eff_rng.uniform(0.01, 0.02)), 4),
                                 round(v_top, 2))
        u = Unlisted(odometer_speed_scale=eff)
    elif kind == "brake_power_limit":
        ct, ca = np.asarray(sim.control["t"]), np.asarray(sim.control["target_acceleration"])
        brake = ca[ca < -0.05]
        a_ref = float(np.median(-brake)) if brake.size else 0.5
        eff = BrakePowerLimit(round(float(eff_rng.uniform(0.45, 0.65)) * v_top * a_ref, 3))
        u = Unlisted(brake_power_limit=eff)
    elif kind == "traction_trip":
        ct, ca = np.asarray(sim.control["t"]), np.asarray(sim.control["target_acceleration"])
        on = ct[1:][(ca[1:] > 0.05) & (ca[:-1] <= 0.05)]
        span = float(t[-1] - t[0])
        mid = on[(on - t[0] >= 0.2 * span) & (on - t[0] <= 0.7 * span)]
        if not mid.size:
            raise RuntimeError("no traction onset in the middle of the run")
        t0 = float(mid[eff_rng.integers(mid.size)])
        eff = TractionTrip(round(t0, 1), round(t0 + float(eff_rng.uniform(60.0, 120.0)), 1),
                           round(float(eff_rng.uniform(0.4, 0.6)), 3))
        u = Unlisted(traction_trip=eff)
    elif kind == "clock_step":
        span = float(t[-1] - t[0])
        sign = 1.0 if eff_rng.random() < 0.5 else -1.0
        eff = ClockStep(round(float(t[0]) + float(eff_rng.uniform(0.3, 0.7)) * span, 1),
                        round(sign * float(eff_rng.uniform(0.5, 3.0)), 2))
        u = Unlisted(clock_step=eff)
    elif kind == "clock_slew":
        span = float(t[-1] - t[0])
        sign = 1.0 if eff_rng.random() < 0.5 else -1.0
        eff = ClockSlew(round(float(t[0]) + float(eff_rng.uniform(0.2, 0.5)) * span, 1),
                        round(sign * float(eff_rng.uniform(5e-4, 2e-3)), 5))
        u = Unlisted(clock_slew=eff)
    elif kind == "misplaced_balise":
        # a balise passed at speed, with balises passed before and after it (so that the
        # odometer carries the position to it and on from it)
        passed = sorted(b.position for b in sc.line.balises if x.min() < b.position < x.max())
        inner = [p for p in passed[1:-1] if np.interp(p, x, v) > 3.0]
        if not inner:
            raise RuntimeError("no balise passed at speed between two others")
        pos = inner[int(eff_rng.integers(len(inner)))]
        bid = next(b.id for b in sc.line.balises if b.position == pos)
        sign = 1.0 if eff_rng.random() < 0.5 else -1.0
        eff = MisplacedBalise(int(bid), round(sign * float(eff_rng.uniform(8.0, 20.0)), 2))
        u = Unlisted(misplaced_balise=eff)
    else:
        moving = np.flatnonzero(v > 2.0)
        dur = float(eff_rng.uniform(60.0, 120.0))
        t_mov = t[moving]
        ok = t_mov[(t_mov > t_mov[0] + 10.0) & (t_mov < t_mov[-1] - dur)]
        t0 = float(ok[eff_rng.integers(ok.size)]) if ok.size else float(t_mov[0])
        sign = 1.0 if eff_rng.random() < 0.5 else -1.0
        eff = Wind(round(t0, 1), round(t0 + dur, 1), round(sign * a * m_eff, 1))
        u = Unlisted(wind=eff)
    truth = {k: getattr(eff, k) for k in eff.__dataclass_fields__}
    return UnlistedCase(case, sc.with_changes(unlisted=u), kind, PHASE[kind], truth)


def _coasting_time(sim) -> float:
    """s the pilot run moves (> 0.5 m/s) with neither traction nor braking commanded."""
    tr = sim.truth
    t, v = np.asarray(tr["t"]), np.asarray(tr["velocity"])
    ct, u = np.asarray(sim.control["t"]), np.asarray(sim.control["target_acceleration"])
    k = np.clip(np.searchsorted(ct, t, side="right") - 1, 0, max(ct.size - 1, 0))
    coast = (v > 0.5) & (np.abs(u[k]) < 0.01) if ct.size else np.zeros(t.size, bool)
    return float(np.sum(np.diff(t)[coast[:-1]]))
