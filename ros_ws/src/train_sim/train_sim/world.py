"""The simulated world: true train on the true line, ATO, sensors and radio links.

:class:`World` is stepped by the ROS simulator node (``advance(t_end)``) and by the offline
generator through :func:`simulate`, which is nothing but ``World(sc, seed).advance(duration)``:
both paths produce identical messages for the same seed.

Time line (true time t, s, from 0):

* ATO cycle at j * control_period: the driver reads (x, v) and issues a_Tar into the actuator's
  delay line (actuator.py, Zheng eq. (1)).
* Sample k at k / odometer_rate: ground truth (true time stamp), the ATO's current a_Tar on
  ``control`` (not through the lossy link), and one odometer sample through its link.
* Balise passages inside the integration steps, at interpolated times, through their link.
* Between events the motion is integrated with RK4 at steps <= max_step (dynamics.py), with
  steps cut at every actuator input change and wheel-slip boundary so each step sees a constant
  delayed command.

At equal times the order is: ATO cycle, then ground_truth, control, odometer. Messages are
returned in order of true time. The train's messages are stamped with its clock, t (1 + drift)
(clock_drift effect; drift 0 otherwise); ground truth is stamped with true time.

Randomness: one ``np.random.SeedSequence(seed)`` spawns four independent streams: odometer
noise, balise detection offsets, odometer link, balise link. Effects that do not touch a stream
leave its draws unchanged, so runs with and without an effect differ only where documented.

Pure module: numpy + the package's pure modules.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .actuator import Actuator
from .driver import Driver
from .dynamics import Dynamics, MotionState
from .effects import braking_rate_at
from .link import Link
from .scenario import Scenario
from .sensors import BaliseReader, Odometer

_EPS = 1e-9  # s
TRUTH_COVARIANCE = (math.nan,) * 16  # CONTRACT.md: NaN where not estimated (truth is not)


@dataclass
class SimResult:
    """Everything one run produced (arrays per topic, including messages the link dropped)."""

    scenario: str
    seed: int
    duration: float  # s
    truth: dict  # t, position, velocity, acceleration, braking_rate
    odometer: dict  # t, stamp, seq, distance, speed, speed_variance, received
    balise: dict  # t, stamp, seq, balise_id, position, position_variance, received
    control: dict  # t, stamp, target_acceleration
    stops: list  # dicts: station, position, stop_position, stopping_error (m), t (s)
    emergency_brakes: int  # rising edges of the emergency-brake flag
    dropped: dict  # {'odometer': n, 'balise': n} messages lost on the link
    sent: dict  # {'odometer': n, 'balise': n} messages offered to the link
    _events: list = field(default_factory=list, repr=False)

    def events(self) -> list:
        """Time-ordered (topic, stamp_s, fields) of the messages received, as the node sends."""
        return list(self._events)


class World:
    """The world of one scenario and seed, advanced in true time."""

    def __init__(self, scenario: Scenario, seed: int | None = None):
        sc = scenario
        self.scenario = sc
        self.seed = int(sc.seed if seed is None else seed)
        s_odo, s_bal, s_lodo, s_lbal = np.random.SeedSequence(self.seed).spawn(4)
        tt, eff = sc.true_train, sc.effects
        self.effects = eff
        self.act = Actuator(tt.brake.time_constant, tt.brake.delay,
                            a0=sc.start_acceleration, u0=sc.start_target_acceleration)
        self.dyn = Dynamics(tt, sc.true_line, sc.train)
        self.state = MotionState(sc.start_position, sc.start_speed, sc.start_speed == 0.0)
        self.driver = Driver(sc.line, sc.train, sc.driver, sc.timetable, sc.start_position,
                             sc.start_speed, a0=sc.start_acceleration,
                             u0=sc.start_target_acceleration)
        self.odometer = Odometer(sc.train.odometer_speed_std, sc.train.odometer_distance_std,
                                 np.random.default_rng(s_odo))
        self.balise_reader = BaliseReader(sc.line.balises, sc.train.balise_position_std,
                                          np.random.default_rng(s_bal), sc.start_position)
        self.links = {"odometer": Link(sc.true_link, np.random.default_rng(s_lodo)),
                      "balise": Link(sc.true_link, np.random.default_rng(s_lbal))}
        self.t = 0.0
        self.a_tar = sc.start_target_acceleration
        self.axle_distance = 0.0  # m, distance the axle counted since the start
        self._scale = eff.odometer_scale.scale if eff.odometer_scale else 1.0
        self._drift = eff.clock_drift.drift if eff.clock_drift else 0.0
        self._slip = eff.wheel_slip
        self._slip_times = sorted({t for iv in self._slip.intervals for t in iv}) if self._slip \
            else []
        self._f_const = None if eff.braking_rate else tt.brake.braking_rate
        self._rate = sc.odometer_rate
        self._period = sc.driver.control_period
        self._k_sample = 0
        self._k_ctrl = 0
        self._due_done = False  # events at self.t processed
        self._log = {k: [] for k in ("truth", "odometer", "balise", "control")}
        self._events: list = []

    # -- inputs ----------------------------------------------------------------------------------
    def set_movement_authority(self, end_of_authority: float, permitted_speed: float,
                               emergency_brake: bool) -> None:
        """Hand the zone controller's authority to the ATO (takes effect at its next cycle)."""
        self.driver.set_movement_authority(end_of_authority, permitted_speed, emergency_brake)

    def set_braking_rate_belief(self, f: float) -> None:
        self.driver.set_braking_rate_belief(f)

    def braking_rate(self, t: float) -> float:
        """True braking rate f(t)."""
        if self._f_const is not None:
            return self._f_const
        return braking_rate_at(self.effects, self.scenario.true_train, t)

    # -- stepping --------------------------------------------------------------------------------
    def advance(self, t_end: float) -> list:
        """Run up to true time ``t_end``; the received messages produced, in time order.

        The integration grid never depends on ``t_end``: the world only moves from one of its
        own event times (ATO cycle, sample, actuator input change, slip boundary) to the next
        one that is <= t_end. So calling ``advance`` in any chunks gives bit-for-bit the same
        messages as one call (the node and ``simulate`` agree). A balise passed after the last
        event time <= t_end is released by the next call, with its exact stamp.
        """
        out: list = []
        while True:
            if not self._due_done:
                if self.t > t_end + _EPS:
                    break
                self._due(out)
                self._due_done = True
            t_sample, t_ctrl = self._k_sample / self._rate, self._k_ctrl * self._period
            t_next = min(t_sample, t_ctrl, self.act.next_switch(), self._next_slip())
            # Snap to the canonical sample/cycle time when another event coincides with it
            # up to round-off (e.g. 10.0 + 1.2 vs 112 / 10), so times never depend on it.
            for t_canon in (t_sample, t_ctrl):
                if abs(t_next - t_canon) <= _EPS:
                    t_next = t_canon
            if t_next > t_end + _EPS:
                break
            self._integrate(t_next, out)
            self._due_done = False
        self._events.extend(out)
        return out

    def _next_slip(self) -> float:
        for ts in self._slip_times:
            if ts > self.t + _EPS:
                return ts
        return math.inf

    def _integrate(self, t_next: float, out: list) -> None:
        t_start = self.t
        span = t_next - t_start
        n = max(1, math.ceil(span / self.scenario.max_step - 1e-9))
        h = span / n
        act, dyn, st, br = self.act, self.dyn, self.state, self.balise_reader
        tau = act.tau
        factor = self._scale * (self._slip.factor(t_start + 0.5 * span) if self._slip else 1.0)
        f_const = self._f_const
        u = act.u  # constant over the whole span (it ends at the next input change)
        for i in range(n):
            t0 = t_start + i * h
            f = f_const if f_const is not None else self.braking_rate(t0 + 0.5 * h)
            ue = u if u >= 0.0 else f * u
            a0, a_mid, a_end = act.segment(h, f)
            x0 = st.x
            dyn.step(st, h, a0, a_mid, a_end, ue, tau)
            if st.x > x0:
                self.axle_distance += factor * (st.x - x0)
                if st.x >= br.next_trigger:
                    for tb, bal in br.crossings(t0, x0, t0 + h, st.x):
                        self._emit_balise(tb, bal, out)
        self.t = t_next
        act.t = t_next  # no round-off drift between the actuator and the world clock
        act._activate()

    def _due(self, out: list) -> None:
        t = self.t
        if self._k_ctrl * self._period <= t + _EPS:
            self.a_tar = self.driver.update(t, self.state.x, self.state.v, self.state.stopped)
            self.act.command(t, self.a_tar)
            self._k_ctrl += 1
        if self._k_sample / self._rate <= t + _EPS:
            self._emit_sample(t, out)
            self._k_sample += 1

    # -- messages --------------------------------------------------------------------------------
    def _emit_sample(self, t: float, out: list) -> None:
        st = self.state
        acc = self.dyn.kappa * self.act.a
        f = self.braking_rate(t)
        self._log["truth"].append((t, st.x, st.v, acc, f))
        out.append(("ground_truth", t, {
            "source": "truth", "position": st.x, "velocity": st.v, "acceleration": acc,
            "braking_rate": f, "covariance": TRUTH_COVARIANCE, "measurement_used": False}))
        stamp = t * (1.0 + self._drift)
        self._log["control"].append((t, stamp, self.a_tar))
        out.append(("control", stamp, {"target_acceleration": self.a_tar}))
        slip = self._slip.factor(t) if self._slip else 1.0
        seq, dist, speed, var = self.odometer.sample(self.axle_distance,
                                                     self._scale * slip * st.v)
        ok = self.links["odometer"].transmit()
        self._log["odometer"].append((t, stamp, seq, dist, speed, var, ok))
        if ok:
            out.append(("odometer", stamp, {"seq": seq, "distance": dist, "speed": speed,
                                            "speed_variance": var}))

    def _emit_balise(self, t: float, balise, out: list) -> None:
        seq, bid, pos, var = self.balise_reader.reading(balise)
        stamp = t * (1.0 + self._drift)
        ok = self.links["balise"].transmit()
        self._log["balise"].append((t, stamp, seq, bid, pos, var, ok))
        if ok:
            out.append(("balise", stamp, {"seq": seq, "balise_id": bid, "position": pos,
                                          "position_variance": var}))

    # -- results ---------------------------------------------------------------------------------
    def result(self) -> SimResult:
        def table(rows, names, dtypes):
            cols = list(zip(*rows)) if rows else [()] * len(names)
            return {n: np.asarray(c, dtype=d) for n, c, d in zip(names, cols, dtypes)}

        f8, u4, b = np.float64, np.uint32, bool
        return SimResult(
            scenario=self.scenario.name, seed=self.seed, duration=self.t,
            truth=table(self._log["truth"],
                        ("t", "position", "velocity", "acceleration", "braking_rate"), (f8,) * 5),
            odometer=table(self._log["odometer"],
                           ("t", "stamp", "seq", "distance", "speed", "speed_variance",
                            "received"), (f8, f8, u4, f8, f8, f8, b)),
            balise=table(self._log["balise"],
                         ("t", "stamp", "seq", "balise_id", "position", "position_variance",
                          "received"), (f8, f8, u4, u4, f8, f8, b)),
            control=table(self._log["control"], ("t", "stamp", "target_acceleration"),
                          (f8,) * 3),
            stops=[dict(s) for s in self.driver.stops],
            emergency_brakes=self.driver.emergency_brakes,
            dropped={k: ln.dropped for k, ln in self.links.items()},
            sent={k: ln.sent for k, ln in self.links.items()},
            _events=list(self._events),
        )


def simulate(scenario: Scenario, seed: int | None = None, duration: float | None = None
             ) -> SimResult:
    """Offline run of ``scenario`` (pure, deterministic given ``seed``; default scenario.seed)."""
    world = World(scenario, seed)
    world.advance(scenario.duration if duration is None else float(duration))
    return world.result()
