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
returned in order of true time.

Clocks (docs/interfaces.md, ``diagnose``): the reference clock is true time t; ``ground_truth`` and
``control`` are stamped with it. ``odometer`` and ``balise`` are stamped by the train's own clock,
``stamp_epoch + t (1 + drift)`` (scenario ``sensors.stamp_epoch``, default 0; clock_drift
effect, default 0). A received message arrives at ``t_recv`` = t + the link's latency (default
0): :meth:`World.deliver` hands messages out in arrival order, as a receiver (and a recorder's
log time) sees them.

Commands come from the ATO (closed loop) or, open loop, from a recorded series
(:func:`open_loop`): the same integration serves both.

Randomness: one ``np.random.SeedSequence(seed)`` spawns six independent streams: odometer
noise, balise detection offsets, odometer link, balise link, odometer latency, balise latency.
Effects that do not touch a stream leave its draws unchanged, so runs with and without an effect
differ only where documented.

Pure module: numpy + the package's pure modules.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass, field, replace

import numpy as np
from train_core.actuator import Actuator
from train_core.effects import (
    Effects,
    braking_rate_at,
    drive_effects,
    true_line,
    true_link,
    true_train,
)
from train_core.link import Link, LinkParams
from train_core.model import Line, TrainParams
from train_core.motion import Motion, warm_actuator

from .driver import Driver, DriverParams
from .scenario import Scenario
from .sensors import BaliseReader, Odometer
from .unlisted import balise_moves, clock_step, odometer_bias, odometer_factor, unlisted_hooks

_EPS = 1e-9  # s
TRUTH_COVARIANCE = (math.nan,) * 16  # docs/interfaces.md: NaN where not estimated (truth is not)


@dataclass
class SimResult:
    """Everything one run produced (arrays per topic, including messages the link dropped)."""

    scenario: str
    seed: int
    duration: float  # s
    truth: dict  # t, position, velocity, acceleration, braking_rate
    odometer: dict  # t, stamp, seq, distance, speed, speed_variance, received, t_recv
    balise: dict  # t, stamp, seq, balise_id, position, position_variance, received, t_recv
    control: dict  # t, stamp, target_acceleration
    stops: list  # dicts: station, position, stop_position, stopping_error (m), t (s)
    emergency_brakes: int  # rising edges of the emergency-brake flag
    dropped: dict  # {'odometer': n, 'balise': n} messages lost on the link
    sent: dict  # {'odometer': n, 'balise': n} messages offered to the link
    _events: list = field(default_factory=list, repr=False)

    def events(self) -> list:
        """(topic, stamp_s, fields) of the messages received, in order of sending (true time)."""
        return [e[1:] for e in self._events]

    def received_events(self) -> list:
        """(t_recv, topic, stamp_s, fields) in order of arrival (reference clock, s): what a
        receiver sees, out of order where the link's jitter reorders messages."""
        return sorted(self._events, key=lambda e: e[0])  # stable: ties keep sending order


class World:
    """The world of one scenario and seed, advanced in true time."""

    def __init__(self, scenario: Scenario, seed: int | None = None,
                 commands: tuple[np.ndarray, np.ndarray] | None = None):
        """``commands = (t, a_Tar)``: replay this recorded series open loop (each a_Tar issued at
        its time t, s, true time of this world) instead of running the ATO."""
        sc = scenario
        self.scenario = sc
        self.seed = int(sc.seed if seed is None else seed)
        s_odo, s_bal, s_lodo, s_lbal, s_dodo, s_dbal = np.random.SeedSequence(self.seed).spawn(6)
        tt, eff = sc.true_train, sc.effects
        self.effects = eff
        act = Actuator(tt.brake.time_constant,
                       eff.traction_delay.delay if eff.traction_delay else tt.brake.delay,
                       a0=sc.start_acceleration, u0=sc.start_target_acceleration,
                       brake_delay=eff.brake_delay.delay if eff.brake_delay else tt.brake.delay)
        self._braking_rate_const = None if eff.braking_rate else tt.brake.braking_rate
        self.motion = Motion(tt, sc.true_line, sc.train, act, sc.start_position,
                             sc.start_speed, sc.max_step,
                             None if self._braking_rate_const is not None else self.braking_rate,
                             **drive_effects(eff), **unlisted_hooks(sc.unlisted, tt))
        if commands is None:
            self.driver = Driver(sc.line, sc.train, sc.driver, sc.timetable, sc.start_position,
                                 sc.start_speed, a0=sc.start_acceleration,
                                 u0=sc.start_target_acceleration)
            self._cmd_t = self._cmd_a = None
        else:
            self.driver = None
            ct, ca = (np.asarray(c, dtype=float) for c in commands)
            order = np.argsort(ct, kind="stable")
            self._cmd_t, self._cmd_a = ct[order].tolist(), ca[order].tolist()
        self.odometer = Odometer(sc.train.odometer_speed_std, sc.train.odometer_distance_std,
                                 np.random.default_rng(s_odo))
        self.balise_reader = BaliseReader(sc.line.balises, sc.train.balise_position_std,
                                          np.random.default_rng(s_bal), sc.start_position,
                                          moved=balise_moves(sc.unlisted))
        slot = 1.0 / sc.odometer_rate  # the radio's cycle: the Markov link's time step
        self.links = {"odometer": Link(sc.true_link, np.random.default_rng(s_lodo),
                                       np.random.default_rng(s_dodo), slot),
                      "balise": Link(sc.true_link, np.random.default_rng(s_lbal),
                                     np.random.default_rng(s_dbal), slot)}
        self.t = 0.0
        self.a_tar = sc.start_target_acceleration
        self.axle_distance = 0.0  # m, distance the axle counted since the start
        self._scale = eff.odometer_scale.scale if eff.odometer_scale else 1.0
        self._drift = eff.clock_drift.drift if eff.clock_drift else 0.0
        self._epoch = sc.stamp_epoch
        self._slip = eff.wheel_slip
        # without a bias the axle's count gains exactly 0.0 per step from it: skipped
        self._biased = sc.unlisted is not None and (sc.unlisted.odometer_bias is not None or
                                                    sc.unlisted.odometer_speed_scale is not None)
        self._slip_times = sorted({t for iv in self._slip.intervals for t in iv}) if self._slip \
            else []
        self._rate = sc.odometer_rate
        self._period = sc.driver.control_period
        self._k_sample = 0
        self._k_ctrl = 0
        self._due_done = False  # events at self.t processed
        self._log = {k: [] for k in ("truth", "odometer", "balise", "control")}
        self._events: list = []  # (t_recv, topic, stamp, fields), in order of sending
        self._pending: list = []  # heap of (t_recv, n, topic, stamp, fields) not yet delivered
        self._n_sent = 0

    # -- inputs ----------------------------------------------------------------------------------
    def set_movement_authority(self, end_of_authority: float, permitted_speed: float,
                               emergency_brake: bool) -> str:
        """Hand the zone controller's authority to the ATO (takes effect at its next cycle);
        "" or why it was refused (``Driver.set_movement_authority``)."""
        if self.driver is None:
            return ""
        return self.driver.set_movement_authority(end_of_authority, permitted_speed,
                                                  emergency_brake)

    def set_braking_rate_belief(self, braking_rate: float) -> None:
        if self.driver is not None:
            self.driver.set_braking_rate_belief(braking_rate)

    def train_stamp(self, t: float) -> float:
        """The train clock's reading at true time ``t`` (s)."""
        return self._epoch + t * (1.0 + self._drift) + clock_step(self.scenario.unlisted, t)

    def braking_rate(self, t: float) -> float:
        """True braking rate f(t)."""
        if self._braking_rate_const is not None:
            return self._braking_rate_const
        return braking_rate_at(self.effects, self.scenario.true_train, t)

    @property
    def act(self) -> Actuator:
        return self.motion.act

    @property
    def state(self):
        return self.motion.state

    @property
    def dyn(self):
        return self.motion.dyn

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
        motion, slips = self.motion, bool(self._slip_times)
        while True:
            if not self._due_done:
                if self.t > t_end + _EPS:
                    break
                self._due(out)
                self._due_done = True
            t_sample, t_ctrl = self._k_sample / self._rate, self._next_command_time()
            t_next = min(t_sample, t_ctrl, motion.act.next_switch(),
                         self._next_slip() if slips else math.inf)
            # Snap to the canonical sample/cycle time when another event coincides with it
            # up to round-off (e.g. 10.0 + 1.2 vs 112 / 10), so times never depend on it.
            for t_canon in (t_sample, t_ctrl):
                if abs(t_next - t_canon) <= _EPS:
                    t_next = t_canon
            if t_next > t_end + _EPS:
                break
            self._integrate(t_next, out)
            self._due_done = False
        for e in out:
            heapq.heappush(self._pending, (e[0], self._n_sent, *e[1:]))
            self._n_sent += 1
        self._events.extend(out)
        return [e[1:] for e in out]

    def deliver(self, t_end: float) -> list:
        """(topic, stamp, fields) of the messages that have arrived by ``t_end`` (reference
        clock) and were not delivered before, in order of arrival. Without link latency this is
        exactly what :meth:`advance` returned."""
        out = []
        pend = self._pending
        while pend and pend[0][0] <= t_end + _EPS:
            e = heapq.heappop(pend)
            out.append(e[2:])
        return out

    def _next_command_time(self) -> float:
        if self.driver is not None:
            return self._k_ctrl * self._period
        return self._cmd_t[self._k_ctrl] if self._k_ctrl < len(self._cmd_t) else math.inf

    def _next_slip(self) -> float:
        for ts in self._slip_times:
            if ts > self.t + _EPS:
                return ts
        return math.inf

    def _integrate(self, t_next: float, out: list) -> None:
        t_start = self.t
        br = self.balise_reader
        mid = 0.5 * (t_start + t_next)
        factor = self._scale * (self._slip.factor(mid) if self._slip else 1.0) * \
            odometer_factor(self.scenario.unlisted, mid)
        unlisted, biased = self.scenario.unlisted, self._biased
        # the axle's count in a local between balises (visit runs at every integration step)
        axle = self.axle_distance
        trigger = br.next_trigger

        def visit(t0, h, x0, x1):
            nonlocal axle, trigger
            axle += factor * (x1 - x0)
            if biased and h > 0.0:
                # an odometer bias (unlisted test effect) counts bias x time moving
                axle += odometer_bias(unlisted, (x1 - x0) / h) * h
            if x1 >= trigger:
                for tb, bal in br.crossings(t0, x0, t0 + h, x1):
                    self._emit_balise(tb, bal, out)
                trigger = br.next_trigger

        self.motion.integrate(t_next, visit)
        self.axle_distance = axle
        self.t = t_next

    def _due(self, out: list) -> None:
        t = self.t
        while self._next_command_time() <= t + _EPS:
            if self.driver is not None:
                self.a_tar = self.driver.update(t, self.state.x, self.state.v, self.state.stopped)
            else:
                self.a_tar = self._cmd_a[self._k_ctrl]
            self.act.command(t, self.a_tar)
            self._k_ctrl += 1
        if self._k_sample / self._rate <= t + _EPS:
            self._emit_sample(t, out)
            self._k_sample += 1

    # -- messages --------------------------------------------------------------------------------
    def _emit_sample(self, t: float, out: list) -> None:
        st = self.state
        acc = self.motion.drive_acceleration
        f = self.braking_rate(t)
        self._log["truth"].append((t, st.x, st.v, acc, f))
        out.append((t, "ground_truth", t, {
            "source": "truth", "position": st.x, "velocity": st.v, "acceleration": acc,
            "braking_rate": f, "covariance": TRUTH_COVARIANCE, "measurement_used": False,
            "integrity": 0, "protection_level_ahead": 0.0, "protection_level_behind": 0.0}))
        # control is on the reference clock (docs/interfaces.md): the ATO's command as issued
        self._log["control"].append((t, t, self.a_tar))
        out.append((t, "control", t, {"target_acceleration": self.a_tar}))
        slip = self._slip.factor(t) if self._slip else 1.0
        seq, dist, speed, var = self.odometer.sample(
            self.axle_distance,
            self._scale * slip * odometer_factor(self.scenario.unlisted, t) * st.v
            + odometer_bias(self.scenario.unlisted, st.v))
        stamp = self.train_stamp(t)
        t_recv = self.links["odometer"].send(t)
        ok = t_recv is not None
        self._log["odometer"].append((t, stamp, seq, dist, speed, var, ok,
                                      t_recv if ok else math.nan))
        if ok:
            out.append((t_recv, "odometer", stamp, {"seq": seq, "distance": dist,
                                                    "speed": speed, "speed_variance": var}))

    def _emit_balise(self, t: float, balise, out: list) -> None:
        seq, bid, pos, var = self.balise_reader.reading(balise)
        stamp = self.train_stamp(t)
        t_recv = self.links["balise"].send(t)
        ok = t_recv is not None
        self._log["balise"].append((t, stamp, seq, bid, pos, var, ok,
                                    t_recv if ok else math.nan))
        if ok:
            out.append((t_recv, "balise", stamp, {"seq": seq, "balise_id": bid, "position": pos,
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
                            "received", "t_recv"), (f8, f8, u4, f8, f8, f8, b, f8)),
            balise=table(self._log["balise"],
                         ("t", "stamp", "seq", "balise_id", "position", "position_variance",
                          "received", "t_recv"), (f8, f8, u4, u4, f8, f8, b, f8)),
            control=table(self._log["control"], ("t", "stamp", "target_acceleration"),
                          (f8,) * 3),
            stops=[dict(s) for s in self.driver.stops] if self.driver else [],
            emergency_brakes=self.driver.emergency_brakes if self.driver else 0,
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


NO_EFFECTS = Effects()
LOSSLESS = LinkParams(p=0.0)  # every message received, no latency


def open_loop(line: Line, train: TrainParams, commands: tuple, *, effects: Effects = NO_EFFECTS,
              believed_train: TrainParams | None = None, t0: float = 0.0,
              duration: float, x0: float, v0: float = 0.0, odometer_rate: float = 10.0,
              link: LinkParams = LOSSLESS, seed: int = 0, max_step: float = 0.01,
              warmup: float = 30.0, unlisted=None) -> SimResult:
    """The simulator open loop: ``line``/``train`` (+ ``effects``) driven by a recorded command
    series instead of the ATO, from true time ``t0`` for ``duration`` s.

    ``commands = (t, a_Tar)`` (s, m/s^2, any times; those before ``t0`` fill the actuator's delay
    line and set its output at t0 by running the actuator alone over ``warmup`` s, which forgets
    the unknown earlier state exactly enough: exp(-warmup / tau)). The world's train is
    ``train`` with ``effects`` applied; ``believed_train`` is the train the controller converts
    commands into force for (default ``train``; the ``mass`` effect makes them differ). The
    result's times are true times (t0 + world time); motion, ground truth and sensor readings
    come from the same :class:`World` as a closed-loop run (``link`` default: lossless).
    ``unlisted``: test effects (:mod:`train_sim.unlisted`), their times in the world's frame
    (true time - t0).
    """
    from .scenario import Scenario

    ct = np.asarray(commands[0], dtype=float) - t0  # the world's frame: t0 -> 0
    ca = np.asarray(commands[1], dtype=float)
    believed = believed_train if believed_train is not None else train
    # Effects with a time axis are given in absolute time: shift them into the world's frame.
    eff = effects
    if eff.braking_rate is not None:
        br = eff.braking_rate
        eff = replace(eff, braking_rate=type(br)(
            br.f_start, br.f_end, br.mode, br.t_start - t0,
            None if br.t_end is None else br.t_end - t0, br.t_step - t0))
    if eff.wheel_slip is not None:
        ws = eff.wheel_slip
        eff = replace(eff, wheel_slip=replace(
            ws, intervals=tuple((a - t0, b - t0) for a, b in ws.intervals)))
    tt = true_train(train, eff)
    # Actuator state at t0: the commands issued before t0 through the true actuator alone.
    brake_delay = eff.brake_delay.delay if eff.brake_delay else None
    f_of = (lambda t: eff.braking_rate.value(t)) if eff.braking_rate else None
    act = warm_actuator(tt, ct, ca, 0.0, warmup, brake_delay, f_of,
                        eff.traction_delay.delay if eff.traction_delay else None)
    before = ct < 0.0
    sc = Scenario(
        name="open_loop", path="", line=line, train=believed,
        true_line=true_line(line, eff), true_train=tt, seed=seed, duration=duration,
        start_position=x0, start_speed=v0, start_acceleration=act.a,
        start_target_acceleration=0.0, odometer_rate=odometer_rate, max_step=max_step,
        driver=DriverParams(), timetable=(), link=link, true_link=true_link(link, eff),
        effects=eff, unlisted=unlisted)
    world = World(sc, seed, commands=(ct[~before], ca[~before]))
    world.motion.act = act
    world.advance(duration)
    res = world.result()
    return _shift(res, t0)


def _shift(res: SimResult, t0: float) -> SimResult:
    if t0 == 0.0:
        return res
    for tab in (res.truth, res.odometer, res.balise, res.control):
        for k in ("t", "t_recv"):
            if k in tab:
                tab[k] = tab[k] + t0
    res.duration = res.duration + t0
    return res
